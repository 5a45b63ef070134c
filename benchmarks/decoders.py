"""Which JPEG decoder is fastest: simplejpeg, Pillow and OpenCV on one large JPEG.

The project decodes JPEGs with simplejpeg (see ptmcore/images.py); this script is the
measurement behind that choice. It renders one synthetic 6000×4000 photograph (or takes
``--image FILE``) and reports the median of ``--repeat`` decodes per decoder, each to an
(H, W, 3) uint8 array, and the ratio to simplejpeg.

Run: ``.venv/bin/python benchmarks/decoders.py [--image FILE] [--repeat 7]``
"""

from __future__ import annotations

import argparse
import io
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _sample_jpeg(path: Path) -> None:
    from data_synthetic.encoding import write_jpeg8
    from data_synthetic.lights import dome_lights
    from data_synthetic.render import render
    from data_synthetic.surfaces import SCENES

    surface = SCENES["tablet"]((4000, 6000), pixel_size=0.02, seed=0)
    write_jpeg8(path, render(surface, dome_lights(48)[:1], cast_shadows=False, noise=0.01)[0], quality=95)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--image", type=Path)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    import cv2
    import simplejpeg
    from PIL import Image

    with tempfile.TemporaryDirectory() as tmp:
        path = args.image or Path(tmp) / "sample.jpg"
        if args.image is None:
            _sample_jpeg(path)
        data = path.read_bytes()
    decoders = {
        "simplejpeg": lambda: simplejpeg.decode_jpeg(data, colorspace="RGB"),
        "Pillow": lambda: np.asarray(Image.open(io.BytesIO(data)).convert("RGB")),
        "OpenCV": lambda: cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR),
    }
    times = {}
    for name, decode in decoders.items():
        decode()
        runs = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            decode()
            runs.append(time.perf_counter() - t0)
        times[name] = statistics.median(runs)
    print(f"{len(data) / 1e6:.1f} MB JPEG, median of {args.repeat} decodes "
          f"({time.strftime('%Y-%m-%d')}, {platform.machine()}, {os.cpu_count()} cores):")
    print("| decoder | seconds | × simplejpeg |\n| --- | --- | --- |")
    for name, t in times.items():
        print(f"| {name} | {t:.3f} | {t / times['simplejpeg']:.2f} |")


if __name__ == "__main__":
    main()
