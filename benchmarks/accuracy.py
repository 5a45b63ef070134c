"""Accuracy of the normal methods and integrators on synthetic scenes with ground truth.

For each scene (clay tablet, sphere cap) and encoding (16-bit linear TIFF, 8-bit sRGB JPEG), a
capture is rendered with a dome of 48 lights, cast shadows and sensor noise; then both normal
methods (photometric stereo, PTM maximum) and both integrators (DCT, Frankot–Chellappa) are
run, and the mean and median angular error inside the object's mask and the height RMSE in mm
(after removing the mean offset) are reported.

Run: ``.venv/bin/python benchmarks/accuracy.py [--size 512x384] [--lights 48]``
Prints a Markdown table and writes ``benchmarks/results/accuracy.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import ptmcore  # noqa: E402
from data_synthetic import write_capture  # noqa: E402
from reconstruct.surface.accuracy import height_rmse, load_ground_truth, normal_accuracy  # noqa: E402
from reconstruct.surface.integrate import integrate  # noqa: E402


def measure(scene: str, encoding: str, shape: tuple[int, int], n_lights: int, seed: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        info = write_capture(Path(tmp) / "cap", scene=scene, shape=shape, n_lights=n_lights,
                             encoding=encoding, seed=seed)
        lights = ptmcore.read_lp(info.lp_path)
        stack = ptmcore.load_stack(lights.paths)
        truth = load_ground_truth(info.ground_truth_dir)
        methods = {
            "ps": lambda: ptmcore.photometric_stereo(stack, lights.directions).normals,
            "ptm": lambda: ptmcore.normals_from_ptm(ptmcore.fit_ptm(stack, lights.directions).coefficients),
        }
        for name, estimate in methods.items():
            t0 = time.perf_counter()
            normals = estimate()
            seconds = time.perf_counter() - t0
            acc = normal_accuracy(normals, truth)
            row = {"scene": scene, "encoding": encoding, "normals": name, "lights": n_lights,
                   "mean_deg": acc["mean_deg"], "median_deg": acc["median_deg"], "seconds": seconds}
            for integrator in ("dct", "fc"):
                h = integrate(normals, integrator, pixel_size=info.pixel_size)
                row[f"height_rmse_mm_{integrator}"] = height_rmse(h, truth)
            rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="512x384")
    ap.add_argument("--lights", type=int, default=48)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    rows = []
    for scene in ("tablet", "sphere"):
        for encoding in ("tiff16", "jpeg8"):
            rows += measure(scene, encoding, (h, w), args.lights, args.seed)
    print("| scene | encoding | normals | mean ° | median ° | height RMSE mm (dct) | height RMSE mm (fc) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['scene']} | {r['encoding']} | {r['normals']} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} "
              f"| {r['height_rmse_mm_dct']:.4f} | {r['height_rmse_mm_fc']:.4f} |")
    out = Path(__file__).resolve().parent / "results" / "accuracy.json"
    out.parent.mkdir(exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, "
            f"{__import__('os').cpu_count()} cores", "size": args.size, "lights": args.lights, "seed": args.seed}
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    print(f"\n{meta['date']}, {meta['machine']}; written {out}")


if __name__ == "__main__":
    main()
