"""Camera drift (ptmcore.align): what a steady capture reads, how well a displacement is found,
and what `reconstruct run` makes of a capture that moved, with `--align auto` (the default) and off.

1. The measurement alone. Synthetic: a tablet and a sphere (640 × 480, 48 dome lights, linear
   float), steady and with photographs displaced (shifted by a 5th-order spline, not by the warp
   under test): every other one by (4, −3) px, the second half (the dome's upper rings, a bump
   half-way) by (4, −3) px, every other one by half a pixel, every one by a random jitter of up to
   ±2 px. Real: the photographs of ../shared/real (DiLiGenT's cat and the RTI icon), steady.
   Prints the largest displacement read (px), the worst error against the truth (px, once the
   common frame's offset is taken out) and the measurement's time.
2. Whole runs. A synthetic tablet capture (`data_synthetic.write_capture`, 640 × 480, 48 lights,
   16-bit TIFF, noise) written clean and with the same defects, and one of 1024 × 800 with the
   second half of the photographs rotated by 0.5° about the centre, and a steady glossy one of
   1024 × 768 (specular 0.5, shininess 40: highlights that move with the light); each run with `--align off`
   and `--align auto`; the mean normal error against the ground truth (and against the steady
   capture's), the largest displacement the run read, and whether it resampled. The jitter's
   offsets have a median of zero, so that the common frame (their median) is the ground truth's.

Machine and date first. Run: .venv/bin/python benchmarks/drift.py [--quick] (--quick: part 1 only)
"""

from __future__ import annotations

import datetime
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import affine_transform
from scipy.ndimage import shift as ndshift

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from procinfo import cpu_model  # noqa: E402
from data_synthetic import write_capture  # noqa: E402
from data_synthetic.encoding import write_tiff16  # noqa: E402
from data_synthetic.lights import dome_lights  # noqa: E402
from data_synthetic.render import render  # noqa: E402
from data_synthetic.surfaces import SCENES  # noqa: E402
from ptmcore.align import ALIGN_THRESHOLD_PX, DriftProbe, measure_drift  # noqa: E402
from ptmcore.images import read_image  # noqa: E402
from ptmcore.lp import read_lp  # noqa: E402

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "real"
N = 48


def _displacements(kind: str) -> np.ndarray:
    """``(N, 2)`` (rows, columns) each photograph's content is moved by."""
    d = np.zeros((N, 2))
    if kind == "every other (4, -3) px":
        d[1::2] = (3.0, 4.0)
    elif kind == "second half (4, -3) px":
        d[N // 2:] = (3.0, 4.0)
    elif kind == "every other 0.5 px":
        d[1::2] = (0.3, 0.4)
    elif kind == "jitter up to 2 px":
        d = np.random.default_rng(0).uniform(-2, 2, (N, 2))
        d -= np.median(d, axis=0)
    return d


KINDS = ("steady", "every other (4, -3) px", "second half (4, -3) px", "every other 0.5 px", "jitter up to 2 px")


def _measure(images, lights, srgb8=False):
    probe = DriftProbe(images[0].shape[:2], len(images))
    for k, img in enumerate(images):
        if img.ndim == 2:
            img = np.broadcast_to(img[..., None], img.shape + (3,))
        probe.take(k, img, srgb8 and img.dtype == np.uint8)
    start = time.perf_counter()
    drift = measure_drift(probe, lights)
    return drift, time.perf_counter() - start


def _largest(drift) -> float:
    """The largest offset measured for one photograph (before a group's photographs share
    their median: what the measurement's noise reaches on a steady capture)."""
    return float(np.hypot(drift.offsets[:, 0], drift.offsets[:, 1]).max())


def measurement_table() -> None:
    print(f"\n## The measurement (threshold {ALIGN_THRESHOLD_PX} px)\n")
    print("| capture | defect | largest offset read, px | worst error, px | time, s |")
    print("| --- | --- | --- | --- | --- |")
    lights = dome_lights(N, 15, 75)
    for scene in ("tablet", "sphere"):
        images = np.clip(render(SCENES[scene]((480, 640), pixel_size=None, seed=1), lights, seed=1), 0, 1)
        images = images.astype(np.float32)
        for kind in KINDS:
            truth = _displacements(kind)
            data = np.stack([ndshift(img, (*t, 0), order=5, mode="nearest") if t.any() else img
                             for img, t in zip(images, truth)])
            drift, took = _measure(data, lights)
            found = np.stack([-drift.offsets[:, 1], drift.offsets[:, 0]], axis=1)  # rows, columns
            measured = drift.confidence > 0
            if measured.any():
                error = found[measured] - truth[measured]
                error = f"{np.abs(error - np.median(error, axis=0)).max():.2f}"
            else:
                error = "not measured (featureless)"
            print(f"| synthetic {scene} | {kind} | {_largest(drift):.2f} | {error} | {took:.2f} |")
    cat = REAL / "diligent_cat"
    if cat.is_dir():
        names = (cat / "filenames.txt").read_text().split()
        drift, took = _measure([read_image(cat / n) for n in names], np.loadtxt(cat / "light_directions.txt"))
        print(f"| real DiLiGenT cat | steady | {_largest(drift):.2f} | – | {took:.2f} |")
    for lp in sorted(REAL.glob("*/*.lp")):
        lights_ = read_lp(lp)
        drift, took = _measure([read_image(p) for p in lights_.paths], lights_.directions, srgb8=True)
        print(f"| real {lp.parent.name} | steady | {_largest(drift):.2f} | – | {took:.2f} |")


def _rotated(img: np.ndarray, degrees: float) -> np.ndarray:
    h, w = img.shape[:2]
    t = np.radians(degrees)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    centre = np.array([(h - 1) / 2, (w - 1) / 2])
    offset = centre - rot @ centre
    return np.stack([affine_transform(img[..., c], rot, offset, order=5, mode="nearest")
                     for c in range(img.shape[2])], axis=-1)


def _run(folder: Path, out: Path, align: str) -> dict:
    subprocess.run([sys.executable, "-m", "reconstruct", "run", str(folder), "-o", str(out), "--align", align],
                   check=True, capture_output=True)
    report = json.loads((out / "report.json").read_text())
    shutil.rmtree(out)
    return report


def _row(kind: str, align: str, report: dict, baseline: float) -> str:
    normals = report["accuracy"]["normals"]["mean_deg"]
    drift = report.get("capture_checks", {}).get("drift")
    largest = f"{drift['largest_px']:.2f}" if drift else "–"
    resampled = "yes" if drift and drift["aligned"] else "no"
    return f"| {kind} | {align} | {normals:.3f}° ({normals / baseline:.2f}×) | {largest} | {resampled} |"


def run_table(tmp: Path) -> None:
    print("\n## Whole runs: synthetic tablet, 48 lights, 16-bit TIFF\n")
    print("| defect | --align | normals, mean (against steady) | largest displacement, px (report) | resampled |")
    print("| --- | --- | --- | --- | --- |")
    clean = tmp / "clean"
    write_capture(clean, shape=(480, 640), n_lights=N, seed=1, scan_points=0)
    photos = sorted(clean.glob("img_*.tif"))
    baseline = None
    for number, kind in enumerate(KINDS):
        folder = clean
        if kind != "steady":
            folder = tmp / f"case{number}"
            shutil.copytree(clean, folder)
            truth = _displacements(kind)
            for k, path in enumerate(photos):
                if truth[k].any():
                    img = read_image(path).astype(np.float32) / np.float32(65535)
                    write_tiff16(folder / path.name, np.clip(ndshift(img, (*truth[k], 0), order=5, mode="nearest"), 0, 1))
        for align in ("off", "auto"):
            report = _run(folder, tmp / "out", align)
            baseline = report["accuracy"]["normals"]["mean_deg"] if baseline is None else baseline
            print(_row(f"640 × 480, {kind}", align, report, baseline))
    # A rotation is measured from five tiles, so from frames of 768 px on their shorter side.
    large = tmp / "large"
    write_capture(large, shape=(800, 1024), n_lights=N, seed=1, scan_points=0)
    turned = tmp / "turned"
    shutil.copytree(large, turned)
    for path in sorted(large.glob("img_*.tif"))[N // 2:]:
        img = read_image(path).astype(np.float32) / np.float32(65535)
        write_tiff16(turned / path.name, np.clip(_rotated(img, 0.5), 0, 1))
    baseline = None
    for kind, folder in (("steady", large), ("second half rotated 0.5°", turned)):
        for align in ("off", "auto"):
            report = _run(folder, tmp / "out", align)
            baseline = report["accuracy"]["normals"]["mean_deg"] if baseline is None else baseline
            print(_row(f"1024 × 800, {kind}", align, report, baseline))
    # A glossy object's highlights move with the light and drag its tiles' details with them.
    glossy = tmp / "glossy"
    write_capture(glossy, shape=(768, 1024), n_lights=N, seed=0, specular=0.5, shininess=40.0, scan_points=0)
    baseline = None
    for align in ("off", "auto"):
        report = _run(glossy, tmp / "out", align)
        baseline = report["accuracy"]["normals"]["mean_deg"] if baseline is None else baseline
        print(_row("1024 × 768 glossy (specular 0.5), steady", align, report, baseline))


def main() -> None:
    print(f"# {datetime.date.today()}, {cpu_model()}")
    measurement_table()
    if "--quick" not in sys.argv:
        with tempfile.TemporaryDirectory() as tmp:
            run_table(Path(tmp))


if __name__ == "__main__":
    main()
