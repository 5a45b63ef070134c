"""Near lights in highlight RTI: distant directions versus triangulated light positions.

Renders a capture lit by a hand-held flash one to two image widths from the object, with two
black glossy spheres beside it (``data_synthetic.nearlight``), then

1. calibrates from the auto-detected spheres (``reconstruct.calibration.calibrate.calibrate_stack``,
   with the disagreement tolerance opened so every photograph keeps its combined direction)
   and triangulates each photograph's light (``reconstruct.calibration.triangulate``);
2. computes normals three ways: (a) ``ptmcore.photometric_stereo`` with one distant direction
   per photograph (the spheres' combined direction); (b) ``near_photometric_stereo`` with the
   triangulated positions; (c) the same with the true positions, as a reference;
3. reports the light-position error (pixels and % of the distance), the mean and median
   normal error on the object (spheres masked out) and the ratio (b)/(a).

Run: ``.venv/bin/python benchmarks/nearlight.py [--size 1024x768] [--lights 32]``
Writes ``benchmarks/results/nearlight.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_synthetic.nearlight import render_nearlight_capture
from ptmcore import load_stack, photometric_stereo
from ptmcore.atomic import atomic_write
from ptmcore.nearlight import near_photometric_stereo
from reconstruct.surface.accuracy import load_ground_truth, normal_accuracy
from reconstruct.calibration.calibrate import calibrate_stack
from reconstruct.calibration.triangulate import lights_are_near, triangulate


def run(shape: tuple[int, int], n_lights: int, distance: tuple[float, float], seed: int,
        encoding: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        info = render_nearlight_capture(Path(tmp) / "cap", shape=shape, n_lights=n_lights,
                                        distance=distance, seed=seed, encoding=encoding)
        render_s = time.perf_counter() - t0
        stack = load_stack(info.image_paths)
        truth = load_ground_truth(info.ground_truth_dir)

        t0 = time.perf_counter()
        cal = calibrate_stack(stack, disagreement_tol_deg=180.0)
        tri = triangulate(cal)
        calib_s = time.perf_counter() - t0

        h, w = shape
        centre = np.array([(w - 1) / 2.0, -(h - 1) / 2.0, 0.0])
        true_dist = np.linalg.norm(info.positions - centre, axis=1)
        ok = tri.usable
        pos_err = np.linalg.norm(tri.positions[ok] - info.positions[ok], axis=1)
        rel_err = 100.0 * pos_err / true_dist[ok]
        sphere_err = [float(np.hypot(a[0] - b[0], a[1] - b[1])) for a, b in zip(cal.spheres, info.spheres)]

        results = {}
        t0 = time.perf_counter()
        dist_ok = cal.usable
        distant = photometric_stereo(stack.select(dist_ok), cal.directions[dist_ok])
        results["distant"] = (distant.normals, time.perf_counter() - t0, int(dist_ok.sum()))
        t0 = time.perf_counter()
        near = near_photometric_stereo(stack.select(ok), tri.positions[ok])
        results["near_triangulated"] = (near.normals, time.perf_counter() - t0, int(ok.sum()))
        t0 = time.perf_counter()
        ref = near_photometric_stereo(stack, info.positions)
        results["near_true_positions"] = (ref.normals, time.perf_counter() - t0, n_lights)

        methods = {}
        for name, (normals, seconds, used) in results.items():
            acc = normal_accuracy(normals, truth)
            methods[name] = {"mean_deg": acc["mean_deg"], "median_deg": acc["median_deg"],
                             "p95_deg": acc["p95_deg"], "photographs": used, "seconds": seconds}
    return {
        "shape": [h, w], "lights": n_lights, "distance_widths": list(distance), "seed": seed,
        "encoding": encoding, "spheres_detected": len(cal.spheres),
        "sphere_radius_px": [float(s[2]) for s in info.spheres],
        "sphere_centre_error_px": sphere_err,
        "triangulated": int(ok.sum()), "status": tri.status,
        "lights_are_near": bool(lights_are_near(tri, shape)),
        "light_distance_px": {"min": float(true_dist.min()), "max": float(true_dist.max())},
        "position_error_px": {"mean": float(pos_err.mean()), "median": float(np.median(pos_err)),
                              "max": float(pos_err.max())},
        "position_error_pct": {"mean": float(rel_err.mean()), "median": float(np.median(rel_err)),
                               "max": float(rel_err.max())},
        "ray_residual_px_median": float(np.median(tri.residual[ok])),
        "normals": methods,
        "ratio_mean_near_over_distant": methods["near_triangulated"]["mean_deg"] / methods["distant"]["mean_deg"],
        "seconds": {"render": render_s, "calibrate_and_triangulate": calib_s},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="1024x768", help="W x H")
    ap.add_argument("--lights", type=int, default=32)
    ap.add_argument("--distance", default="1.0,2.0", help="lo,hi in image widths")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--encoding", default="png", choices=["png", "tiff16"])
    ap.add_argument("--output", default="nearlight.json", help="file name in benchmarks/results/")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.lower().split("x"))
    lo, hi = (float(v) for v in args.distance.split(","))
    res = run((h, w), args.lights, (lo, hi), args.seed, args.encoding)
    res["machine"] = f"{platform.machine()} {platform.processor() or ''}".strip()
    res["python"] = platform.python_version()

    print(f"{w}×{h}, {args.lights} lights at {lo}–{hi} image widths, {args.encoding}, "
          f"{res['spheres_detected']} spheres detected, {res['triangulated']} triangulated")
    pe, pp = res["position_error_px"], res["position_error_pct"]
    print(f"light position error: mean {pe['mean']:.1f} px ({pp['mean']:.2f} % of distance), "
          f"median {pe['median']:.1f} px, max {pe['max']:.1f} px ({pp['max']:.2f} %)")
    print("| normals | mean ° | median ° | p95 ° | s |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name, m in res["normals"].items():
        print(f"| {name} | {m['mean_deg']:.2f} | {m['median_deg']:.2f} | {m['p95_deg']:.2f} | {m['seconds']:.1f} |")
    print(f"ratio near/distant (mean): {res['ratio_mean_near_over_distant']:.3f}")
    out = Path(__file__).resolve().parent / "results" / args.output
    out.parent.mkdir(exist_ok=True)
    with atomic_write(out, "w") as f:
        json.dump(res, f, indent=2)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
