"""Robust photometric stereo with and without the object's reflectance lobe, on synthetic scenes.

The default normals (``--fit lobe``, :mod:`ptmcore.lobe`) must be at least as accurate as the
Lambertian robust fit (``--fit irls``) on every scene the project renders: Lambertian ones (the
lobe must then be rejected and nothing change), sharp highlights with cast shadows, JPEG input, a
single ring of lights, and glossy surfaces with broad lobes (Blinn–Phong of low shininess),
which is what the lobe is for. For each scene: mean and median angular error inside the mask,
the lobe's residual reduction (``-`` when it was rejected), and the fit's time.

Run: ``.venv/bin/python benchmarks/lobe.py [--size 384x512] [--lights 48]``; prints Markdown
and writes ``benchmarks/results/lobe.json``.
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
from data_synthetic.lights import ring_lights  # noqa: E402
from ptmcore.robust import robust_photometric_stereo  # noqa: E402
from reconstruct.surface.accuracy import load_ground_truth, normal_accuracy  # noqa: E402

#: write_capture options; "ring" becomes a ring of lights at that elevation.
SCENES = {
    "tablet, Lambertian, no cast shadows": {"cast_shadows": False},
    "tablet, Lambertian + cast shadows": {},
    "tablet, 8-bit JPEG": {"encoding": "jpeg8"},
    "tablet, ring of lights at 40°": {"ring": 40.0},
    "tablet, sharp highlights (specular 0.6, shininess 40) + cast shadows": {"specular": 0.6, "shininess": 40.0},
    "tablet, broad lobe (specular 0.3, shininess 8)": {"specular": 0.3, "shininess": 8.0},
    "tablet, broad lobe (specular 0.5, shininess 15)": {"specular": 0.5, "shininess": 15.0},
    "tablet, broad lobe, 8-bit JPEG (specular 0.4, shininess 10)": {"encoding": "jpeg8", "specular": 0.4, "shininess": 10.0},
    "sphere, sharp highlights (specular 0.6, shininess 40)": {"scene": "sphere", "specular": 0.6, "shininess": 40.0},
    "sphere, broad lobe (specular 0.4, shininess 10)": {"scene": "sphere", "specular": 0.4, "shininess": 10.0},
}


def measure(name: str, options: dict, shape: tuple[int, int], n_lights: int) -> dict:
    options = dict(options)
    scene = options.pop("scene", "tablet")
    ring = options.pop("ring", None)
    if ring is not None:
        options["lights"] = ring_lights(n_lights, ring)
    with tempfile.TemporaryDirectory() as tmp:
        info = write_capture(Path(tmp) / "cap", scene=scene, shape=shape, n_lights=n_lights, seed=0,
                             scan_points=0, **options)
        lights = ptmcore.read_lp(info.lp_path)
        stack = ptmcore.load_stack(lights.paths)
        truth = load_ground_truth(info.ground_truth_dir)
    row = {"scene": name}
    for key, lobe in (("irls", False), ("lobe", True)):
        t0 = time.perf_counter()
        ps = robust_photometric_stereo(stack, lights.directions, lobe=lobe)
        seconds = time.perf_counter() - t0
        acc = normal_accuracy(ps.normals, truth)
        row[key] = {"mean_deg": acc["mean_deg"], "median_deg": acc["median_deg"], "seconds": seconds,
                    "lobe": ps.lobe.summary() if ps.lobe else None}
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="384x512", help="HxW (default 384x512)")
    ap.add_argument("--lights", type=int, default=48)
    args = ap.parse_args()
    shape = tuple(int(v) for v in args.size.split("x"))
    # Compile the kernel once, outside the timings.
    measure("warm-up", {"cast_shadows": False}, (32, 32), args.lights)
    rows = [measure(name, opt, shape, args.lights) for name, opt in SCENES.items()]
    print(f"{shape[0]}×{shape[1]} pixels, {args.lights} lights (15°–75° elevation unless a ring), noise 0.5 %; "
          f"{time.strftime('%Y-%m-%d')}, {platform.machine()}, {platform.python_version()}\n")
    print("| scene | irls mean ° | irls median ° | lobe mean ° | lobe median ° | lobe: residual reduction | irls s | lobe s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        a, b = r["irls"], r["lobe"]
        gain = f"{b['lobe']['residual_reduction']:.2f}" if b["lobe"] else "– (Lambertian)"
        print(f"| {r['scene']} | {a['mean_deg']:.3f} | {a['median_deg']:.3f} | {b['mean_deg']:.3f} | "
              f"{b['median_deg']:.3f} | {gain} | {a['seconds']:.2f} | {b['seconds']:.2f} |")
    out = Path(__file__).resolve().parent / "results" / "lobe.json"
    out.write_text(json.dumps({"date": time.strftime("%Y-%m-%d"), "shape": shape, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
