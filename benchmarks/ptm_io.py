"""PTM files: quantisation error of the 8-bit file, and read/write speed at 24 megapixels.

1. Quantisation: the synthetic tablet (512×384, 48 lights, 8-bit sRGB JPEG) is fitted as HP's
   PTMfitter fits it (LRGB and RGB formats); each light of the capture is rendered from the
   float coefficients and from the written-and-read ``.ptm``; the RMSE between the two (8-bit
   levels) is the error the file format adds. The RMSE of the float fit against the photographs
   is given for scale.
2. Speed: an LRGB PTM of 6000×4000 pixels (the tablet's coefficients tiled) is written and read
   ``--repeat`` times; medians.

Run: ``.venv/bin/python benchmarks/ptm_io.py [--repeat 3]``
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_synthetic import write_capture  # noqa: E402
from ptmcore.fit import light_matrix  # noqa: E402
from ptmcore.images import read_image  # noqa: E402
from ptmcore.lp import read_lp  # noqa: E402
from ptmcore.ptmencoded import fit_ptm_encoded, fit_ptm_rgb_encoded  # noqa: E402
from ptmcore.ptmfile import read_ptm, write_ptm  # noqa: E402


def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a.astype(np.float64) - b) ** 2)))


def quantisation(tmp: Path) -> None:
    info = write_capture(tmp / "cap", "tablet", shape=(384, 512), n_lights=48, encoding="jpeg8", seed=0)
    lights = read_lp(info.lp_path)
    photos = [read_image(p) for p in lights.paths]
    rows = lights.directions
    coef, rgb = fit_ptm_encoded(lights.paths, rows)
    write_ptm(tmp / "lrgb.ptm", coef, rgb)
    lrgb = read_ptm(tmp / "lrgb.ptm")
    coef3 = fit_ptm_rgb_encoded(lights.paths, rows)
    write_ptm(tmp / "rgb.ptm", coef3)
    rgbf = read_ptm(tmp / "rgb.ptm")
    q_l, q_r, f_l, f_r = [], [], [], []
    for d, photo in zip(rows, photos):
        basis = light_matrix(d[None])[0].astype(np.float32)
        float_l = np.clip(rgb * (coef @ basis)[..., None] / 255, 0, 255)
        float_r = np.clip(coef3 @ basis, 0, 255)
        q_l.append(_rmse(lrgb.render(d), float_l))
        q_r.append(_rmse(rgbf.render(d), float_r))
        f_l.append(_rmse(float_l, photo))
        f_r.append(_rmse(float_r, photo))
    print("| format | RMSE file vs float fit (levels) | RMSE float fit vs photographs (levels) |")
    print("| --- | --- | --- |")
    print(f"| LRGB | {np.mean(q_l):.3f} | {np.mean(f_l):.2f} |")
    print(f"| RGB | {np.mean(q_r):.3f} | {np.mean(f_r):.2f} |")
    return coef, rgb


def speed(tmp: Path, coef: np.ndarray, rgb: np.ndarray, repeat: int) -> None:
    reps = (int(np.ceil(4000 / coef.shape[0])), int(np.ceil(6000 / coef.shape[1])))
    big = np.tile(coef, reps + (1,))[:4000, :6000]
    big_rgb = np.tile(rgb, reps + (1,))[:4000, :6000]
    path = tmp / "big.ptm"
    writes, reads = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        write_ptm(path, big, big_rgb)
        writes.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        read_ptm(path)
        reads.append(time.perf_counter() - t0)
    size = path.stat().st_size / 1e6
    print(f"\n24-megapixel LRGB PTM ({size:.0f} MB), medians of {repeat}:")
    print("| operation | seconds |\n| --- | --- |")
    print(f"| write_ptm | {statistics.median(writes):.2f} |")
    print(f"| read_ptm | {statistics.median(reads):.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores\n")
    with tempfile.TemporaryDirectory() as tmp:
        coef, rgb = quantisation(Path(tmp))
        speed(Path(tmp), coef, rgb, args.repeat)


if __name__ == "__main__":
    main()
