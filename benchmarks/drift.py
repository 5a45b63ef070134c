"""Camera drift (ptmcore.align): what a steady capture reads, and how well a displacement is found.

Synthetic: a tablet and a sphere (640 × 480, 48 dome lights, 16-bit linear), steady and with
every other photograph displaced by (4, −3) px or by (0.6, 0.4) px (shifted by a 5th-order spline,
not by the warp under test). Real: the photographs of ../shared/real (the DiLiGenT cat and the
RTI icon), which are steady. Prints the largest displacement read (px), the error against the
truth and the measurement's time; machine and date first. Run: .venv/bin/python benchmarks/drift.py
"""

from __future__ import annotations

import datetime
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import shift as ndshift

from data_synthetic.lights import dome_lights
from data_synthetic.render import render
from data_synthetic.surfaces import SCENES
from ptmcore.align import ALIGN_THRESHOLD_PX, DriftProbe, measure_drift
from ptmcore.images import read_image
from ptmcore.lp import read_lp

REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "real"


def _cpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def _measure(images, lights, srgb8=False):
    probe = DriftProbe(images[0].shape[:2], len(images))
    for k, img in enumerate(images):
        if img.ndim == 2:
            img = np.broadcast_to(img[..., None], img.shape + (3,))
        probe.take(k, img, srgb8 and img.dtype == np.uint8)
    start = time.perf_counter()
    drift = measure_drift(probe, lights)
    return drift, time.perf_counter() - start


def main() -> None:
    print(f"# {datetime.date.today()}, {_cpu()}; threshold {ALIGN_THRESHOLD_PX} px")
    lights = dome_lights(48, 15, 75)
    for scene in ("tablet", "sphere"):
        images = np.clip(render(SCENES[scene]((480, 640), pixel_size=None, seed=1), lights, seed=1), 0, 1)
        images = images.astype(np.float32)
        for name, offset in (("steady", None), ("every other (4, -3) px", (3.0, 4.0)),
                             ("every other (0.6, 0.4) px", (-0.4, 0.6))):
            data, truth = images, np.zeros((48, 2))
            if offset is not None:
                data = images.copy()
                for k in range(1, 48, 2):
                    data[k] = ndshift(images[k], (*offset, 0), order=5, mode="nearest")
                    truth[k] = (offset[1], -offset[0])  # x right, y up
            drift, took = _measure(data, lights)
            error = np.abs(drift.offsets - truth).max()
            print(f"{scene:7s} {name:26s} largest read {drift.largest()[1]:5.2f} px, worst error {error:5.2f} px, "
                  f"median confidence {np.median(drift.confidence):.2f}, {took:4.2f} s")
    cat = REAL / "diligent_cat"
    if cat.is_dir():
        names = (cat / "filenames.txt").read_text().split()
        drift, took = _measure([read_image(cat / n) for n in names], np.loadtxt(cat / "light_directions.txt"))
        print(f"real    DiLiGenT cat (steady)      largest read {drift.largest()[1]:5.2f} px, {took:4.2f} s")
    for lp in sorted(REAL.glob("*/*.lp")):
        lights_ = read_lp(lp)
        drift, took = _measure([read_image(p) for p in lights_.paths], lights_.directions, srgb8=True)
        print(f"real    {lp.parent.name} (steady)  largest read {drift.largest()[1]:5.2f} px, {took:4.2f} s")


if __name__ == "__main__":
    main()
