"""Accuracy on real captures with laser-scanned ground truth (``../shared/real/``, when present).

Normals: DiLiGenT's objects (folders with ``light_directions.txt``, ``Normal_gt.*``: the ceramic
cat in the shared data), read as ``reconstruct run`` reads them (the given light intensities
divided out). For each normal method, the mean and median angular error inside the object's
mask, beside the figures published for that object (DiLiGenT's benchmark table: least squares,
Woodham 1980; ST14, Shi et al., TPAMI 2014, the best classical method there).

Depth: BiNI's DiLiGenT objects (``bini_depth/``: perspective normal maps, masks, intrinsics and
laser depth), masked least squares against bilateral integration, by
``benchmarks/real_integration.py``'s table (mean absolute depth error after BiNI's median-ratio
scale; BiNI's paper reports about 1.5 mm averaged over nine DiLiGenT objects).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/real.py [--real ../shared/real]``
(one BLAS thread: scipy's conjugate gradients slow down badly with threaded dot products on a
busy machine); prints Markdown and writes
``benchmarks/results/real.json``. Skips (exit 0, a message) when the folder is absent.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ptmcore.intensity import apply_intensities, estimate_intensities  # noqa: E402
from ptmcore.normals import angular_error, photometric_stereo  # noqa: E402
from ptmcore.psdataset import is_ps_dataset, read_ps_dataset  # noqa: E402
from ptmcore.robust import robust_photometric_stereo  # noqa: E402

#: Published mean angular errors (°) on DiLiGenT (Shi et al., TPAMI 2019, table of calibrated
#: methods): least squares and ST14.
PUBLISHED = {"cat": {"least squares (published)": 8.41, "ST14 (published)": 6.12}}

#: The normal methods: label → function of (stack, directions).
METHODS = {
    "least squares, dark samples left out (`--fit plain`)": lambda s, d: photometric_stereo(s, d),
    "robust, trimmed (`--fit trimmed`)": lambda s, d: robust_photometric_stereo(s, d, method="trimmed"),
    "robust IRLS (`--fit irls`)": lambda s, d: robust_photometric_stereo(s, d),
    "IRLS + reflectance lobe (`--fit lobe`, default)": lambda s, d: robust_photometric_stereo(s, d, lobe=True),
}


def normals_table(folders: list[Path]) -> list[dict]:
    rows = []
    for folder in folders:
        ds = read_ps_dataset(folder)
        dirs = ds.lights.directions
        name = folder.name.removeprefix("diligent_")
        if not rows:  # compile the kernels outside the timings
            robust_photometric_stereo(ds.stack, dirs, lobe=True)
        for label, method in METHODS.items():
            t0 = time.perf_counter()
            ps = method(ds.stack, dirs)
            seconds = time.perf_counter() - t0
            err = angular_error(ps.normals, ds.ground_truth_normals, ds.mask)
            rows.append({"object": name, "method": label, "mean_deg": float(err.mean()),
                         "median_deg": float(np.median(err)), "seconds": seconds})
        # As `reconstruct run FOLDER --intensities estimate` does it: estimated on the
        # photographs as stored, applied scaled to a minimum of 1.
        raw = read_ps_dataset(folder, divide_intensities=False)
        t0 = time.perf_counter()
        factors = estimate_intensities(raw.stack, dirs, mask=raw.mask)
        ps = robust_photometric_stereo(apply_intensities(raw.stack, factors, relative=True), dirs, lobe=True)
        seconds = time.perf_counter() - t0
        err = angular_error(ps.normals, ds.ground_truth_normals, ds.mask)
        rows.append({"object": name, "method": "`--fit lobe` with `--intensities estimate` (given ones ignored)",
                     "mean_deg": float(err.mean()), "median_deg": float(np.median(err)), "seconds": seconds})
        for label, value in PUBLISHED.get(name, {}).items():
            rows.append({"object": name, "method": label, "mean_deg": value, "median_deg": None, "seconds": None})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", type=Path, default=ROOT.parent / "shared" / "real")
    args = ap.parse_args()
    if not args.real.is_dir():
        print(f"{args.real} not found: nothing to measure")
        return
    folders = sorted(p for p in args.real.iterdir() if p.is_dir() and is_ps_dataset(p))
    rows = normals_table(folders)
    print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, Python {platform.python_version()}\n")
    print("| object | normals | mean ° | median ° | seconds |")
    print("| --- | --- | ---: | ---: | ---: |")
    for r in rows:
        med = "" if r["median_deg"] is None else f"{r['median_deg']:.2f}"
        sec = "" if r["seconds"] is None else f"{r['seconds']:.2f}"
        print(f"| {r['object']} | {r['method']} | {r['mean_deg']:.2f} | {med} | {sec} |")
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from real_integration import real_table

    print("\nPerspective integration of BiNI's ground-truth normals (depth error in mm):\n")
    print(real_table())
    out = ROOT / "benchmarks" / "results" / "real.json"
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "normals": rows}, indent=1))


if __name__ == "__main__":
    main()
