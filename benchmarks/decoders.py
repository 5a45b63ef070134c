"""Which decoders are fastest: simplejpeg, Pillow and OpenCV on one large JPEG; imagecodecs
and OpenCV on the same photograph as a 16-bit RGB PNG.

The project decodes JPEGs with simplejpeg and PNGs with imagecodecs (see ptmcore/decoders.py);
this script is the measurement behind those choices. It renders one synthetic 6000×4000
photograph (or takes ``--image FILE``) and reports the median of ``--repeat`` decodes per
decoder, each to an (H, W, 3) array, and the ratio to the project's decoder. (Pillow reads a
16-bit RGB PNG as 8 bits, so it is not in the PNG table.)

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
    _table(f"{len(data) / 1e6:.1f} MB JPEG", decoders, args.repeat)

    import imagecodecs

    rgb16 = (simplejpeg.decode_jpeg(data, colorspace="RGB").astype(np.uint16) * 257)
    png = cv2.imencode(".png", rgb16[..., ::-1])[1].tobytes()
    _table(f"{len(png) / 1e6:.1f} MB 16-bit RGB PNG of the same photograph", {
        "imagecodecs": lambda: imagecodecs.png_decode(png),
        "OpenCV": lambda: cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED),
    }, args.repeat)


def _table(what: str, decoders: dict, repeat: int) -> None:
    times = {}
    for name, decode in decoders.items():
        decode()
        runs = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            decode()
            runs.append(time.perf_counter() - t0)
        times[name] = statistics.median(runs)
    first = next(iter(times))
    print(f"{what}, median of {repeat} decodes "
          f"({time.strftime('%Y-%m-%d %H:%M')}, {platform.machine()}, {os.cpu_count()} cores):")
    print(f"| decoder | seconds | × {first} |\n| --- | --- | --- |")
    for name, t in times.items():
        print(f"| {name} | {t:.3f} | {t / times[first]:.2f} |")


if __name__ == "__main__":
    main()
