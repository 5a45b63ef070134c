"""Normals from plain and robust fits on synthetic scenes, and where PTM normals break down.

1. Scenes. The clay tablet (512×384, a dome of 48 lights at 15°–75° elevation, sensor noise
   0.5 %) is rendered five ways: Lambertian without cast shadows; with specular highlights
   (Blinn–Phong, specular 0.6, shininess 40) and cast shadows; Lambertian with cast shadows;
   the same as 8-bit sRGB JPEG; and lit by a single ring of 48 lights at 40° elevation
   (``data_synthetic.lights.ring_lights``), which leaves the PTM basis rank-deficient. For each
   scene the table gives the mean and median angular error inside the tablet's mask of:

   * PTM maximum: :func:`ptmcore.normals.normals_from_ptm` of the plain fit
     (:func:`ptmcore.fit.fit_ptm`) and of the robust fit (:func:`ptmcore.robustptm.robust_ptm`);
   * PTM debiased: :func:`ptmcore.robustptm.debiased_normals` of the plain fit (with the lights'
     hemisphere PTM) and of the robust fit (with its per-pixel hemisphere);
   * photometric stereo: plain (:func:`ptmcore.normals.photometric_stereo`) and robust
     (:func:`ptmcore.robust.robust_photometric_stereo`);

   and the time of each fit (median of ``--repeat``) relative to the plain PTM fit. A second
   table compares the robust methods (IRLS and trimming) and the robust PTM fit when it is given
   the robust photometric-stereo normals.
2. Breakdown. A Lambertian spherical cap with slants up to 80° (256×256, 48 lights, noise
   0.5 %) is lit by domes that cover different ranges of elevation. For each range, the table
   gives the mean error per 10° band of slant, and the slant from which each method is off by
   more than 5° and 10° on average.

Run: ``.venv/bin/python benchmarks/normals_table.py [--size 512x384] [--lights 48] [--repeat 3]``
Prints Markdown and writes ``benchmarks/results/normals_table.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import ptmcore  # noqa: E402
from procinfo import cpu_model  # noqa: E402
from data_synthetic import write_capture  # noqa: E402
from data_synthetic.lights import dome_lights, ring_lights  # noqa: E402
from data_synthetic.render import render  # noqa: E402
from data_synthetic.sphere import sphere_cap  # noqa: E402
from ptmcore.images import LUMA_WEIGHTS, SATURATED, ImageStack  # noqa: E402
from ptmcore.robust import robust_photometric_stereo  # noqa: E402
from ptmcore.robustptm import debiased_normals, hemisphere_coefficients, robust_ptm  # noqa: E402
from reconstruct.surface.accuracy import load_ground_truth, normal_accuracy  # noqa: E402

#: The scenes: write_capture options (lights= is filled in for the ring).
SCENES = {
    "Lambertian, no cast shadows": {"cast_shadows": False},
    "specular + cast shadows": {"specular": 0.6, "shininess": 40.0},
    "Lambertian + cast shadows": {},
    "8-bit JPEG (+ cast shadows)": {"encoding": "jpeg8"},
    "ring of lights at 40°": {"ring": 40.0},
}
#: Columns of the main table: (key, label).
MAIN = [
    ("ptm_max_plain", "PTM max plain"),
    ("ptm_max_robust", "PTM max robust"),
    ("ptm_debiased_plain", "PTM debiased plain"),
    ("ptm_debiased_robust", "PTM debiased robust"),
    ("ps_plain", "PS plain"),
    ("ps_robust", "PS robust"),
]
#: Fits whose time is measured: (key, label).
FITS = [
    ("fit_ptm", "PTM plain"),
    ("robust_ptm", "PTM robust"),
    ("robust_ptm_given_ps", "PTM robust given PS normals"),
    ("photometric_stereo", "PS plain"),
    ("robust_ps", "PS robust"),
]
#: Dome elevation ranges of the breakdown study, degrees.
ELEVATIONS = [(5.0, 85.0), (15.0, 75.0), (30.0, 75.0), (45.0, 75.0), (15.0, 45.0), (30.0, 60.0)]
SLANT_BINS = np.arange(0.0, 81.0, 10.0)
#: Mean errors (°) that count as broken down.
BREAKDOWN_DEG = (5.0, 10.0)


def timed(fn: Callable[[], object], repeat: int) -> tuple[object, float]:
    """Result of ``fn`` and the median of ``repeat`` timings after one untimed call."""
    result = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return result, statistics.median(times)


def measure_scene(name: str, options: dict, shape: tuple[int, int], n_lights: int, seed: int,
                  repeat: int) -> dict:
    options = dict(options)
    ring = options.pop("ring", None)
    if ring is not None:
        options["lights"] = ring_lights(n_lights, ring)
    with tempfile.TemporaryDirectory() as tmp:
        info = write_capture(Path(tmp) / "cap", scene="tablet", shape=shape, n_lights=n_lights,
                             seed=seed, scan_points=0, **options)
        lights = ptmcore.read_lp(info.lp_path)
        stack = ptmcore.load_stack(lights.paths)
        truth = load_ground_truth(info.ground_truth_dir)
    d = lights.directions
    fits = {
        "fit_ptm": lambda: ptmcore.fit_ptm(stack, d),
        "robust_ptm": lambda: robust_ptm(stack, d),
        "robust_ptm_trimmed": lambda: robust_ptm(stack, d, method="trimmed"),
        "photometric_stereo": lambda: ptmcore.photometric_stereo(stack, d),
        "robust_ps": lambda: robust_photometric_stereo(stack, d),
        "robust_ps_trimmed": lambda: robust_photometric_stereo(stack, d, method="trimmed"),
    }
    results, seconds = {}, {}
    for key, fn in fits.items():
        results[key], seconds[key] = timed(fn, repeat)
    ps_normals = results["robust_ps"].normals
    results["robust_ptm_given_ps"], seconds["robust_ptm_given_ps"] = timed(
        lambda: robust_ptm(stack, d, normals=ps_normals), repeat)

    plain, rob, rob_t = results["fit_ptm"], results["robust_ptm"], results["robust_ptm_trimmed"]
    normals = {
        "ptm_max_plain": ptmcore.normals_from_ptm(plain.coefficients),
        "ptm_max_robust": ptmcore.normals_from_ptm(rob.ptm.coefficients),
        "ptm_debiased_plain": debiased_normals(plain.coefficients, hemisphere_coefficients(d)),
        "ptm_debiased_robust": rob.normals,
        "ps_plain": results["photometric_stereo"].normals,
        "ps_robust": ps_normals,
        "ptm_max_robust_trimmed": ptmcore.normals_from_ptm(rob_t.ptm.coefficients),
        "ptm_debiased_robust_trimmed": rob_t.normals,
        "ps_robust_trimmed": results["robust_ps_trimmed"].normals,
        "ptm_max_robust_given_ps": ptmcore.normals_from_ptm(results["robust_ptm_given_ps"].ptm.coefficients),
        "ptm_debiased_robust_given_ps": results["robust_ptm_given_ps"].normals,
    }
    errors = {}
    for key, n in normals.items():
        acc = normal_accuracy(n, truth)
        errors[key] = {k: acc[k] for k in ("mean_deg", "median_deg", "p95_deg")}
    base = seconds["fit_ptm"]
    return {
        "scene": name,
        "errors": errors,
        "seconds": seconds,
        "time_vs_plain_ptm": {k: s / base for k, s in seconds.items()},
    }


def _stack_in_memory(luminance: np.ndarray, clipped: np.ndarray) -> ImageStack:
    """An ImageStack of linear luminance (N, H, W), stored as load_stack stores it."""
    lum = np.round(np.clip(luminance, 0.0, 1.0) * 65534.0).astype(np.uint16)
    lum[clipped] = SATURATED
    n, h, w = lum.shape
    return ImageStack(lum, np.ones((h, w, 3), np.float32), [], 16, False, clipped.sum(axis=(1, 2)))


def breakdown(n_lights: int, seed: int, size: int = 256) -> list[dict]:
    """Mean error per slant band of a Lambertian cap under domes of several elevation ranges."""
    surface = sphere_cap((size, size), seed=seed, max_slope_deg=80.0)
    slant = np.degrees(np.arccos(np.clip(surface.normals[..., 2], -1.0, 1.0)))
    rows = []
    for low, high in ELEVATIONS:
        dirs = dome_lights(n_lights, low, high)
        radiance = render(surface, dirs, noise=0.005, seed=seed)
        stack = _stack_in_memory(radiance @ LUMA_WEIGHTS, (radiance >= 1.0).any(axis=-1))
        del radiance
        plain = ptmcore.fit_ptm(stack, dirs)
        rob = robust_ptm(stack, dirs)
        methods = {
            "ptm_max_plain": ptmcore.normals_from_ptm(plain.coefficients),
            "ptm_max_robust": ptmcore.normals_from_ptm(rob.ptm.coefficients),
            "ptm_debiased_plain": debiased_normals(plain.coefficients, hemisphere_coefficients(dirs)),
            "ptm_debiased_robust": rob.normals,
            "ps_plain": ptmcore.photometric_stereo(stack, dirs).normals,
            "ps_robust": robust_photometric_stereo(stack, dirs).normals,
        }
        for key, n in methods.items():
            err = ptmcore.angular_error(n, surface.normals)
            per_bin = []
            for a, b in zip(SLANT_BINS[:-1], SLANT_BINS[1:]):
                sel = surface.mask & (slant >= a) & (slant < b)
                per_bin.append(float(err[sel].mean()) if sel.any() else None)
            row = {"elevations_deg": [low, high], "method": key, "mean_deg_per_slant_bin": per_bin}
            for limit in BREAKDOWN_DEG:
                over = [a for a, e in zip(SLANT_BINS[:-1], per_bin) if e is not None and e > limit]
                row[f"over_{limit:.0f}_deg_from_slant_deg"] = float(over[0]) if over else None
            rows.append(row)
    return rows


def _machine() -> str:
    model = cpu_model()
    return (f"{platform.machine()}, {model}, {os.cpu_count()} cores, "
            f"Python {platform.python_version()}, NumPy {np.__version__}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="512x384")
    ap.add_argument("--lights", type=int, default=48)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    load_before = os.getloadavg()

    scenes = [measure_scene(name, opts, (h, w), args.lights, args.seed, args.repeat)
              for name, opts in SCENES.items()]
    print("## Normals on the synthetic tablet: mean / median angular error (°)\n")
    print("| scene | " + " | ".join(label for _, label in MAIN) + " |")
    print("| --- |" + " --- |" * len(MAIN))
    for s in scenes:
        cells = [f"{s['errors'][k]['mean_deg']:.2f} / {s['errors'][k]['median_deg']:.2f}" for k, _ in MAIN]
        print(f"| {s['scene']} | " + " | ".join(cells) + " |")
    print(f"\n## Time of each fit relative to the plain PTM fit (median of {args.repeat})\n")
    print("| scene | plain PTM fit s | " + " | ".join(label for _, label in FITS) + " |")
    print("| --- | --- |" + " --- |" * len(FITS))
    for s in scenes:
        cells = [f"{s['time_vs_plain_ptm'][k]:.1f}×" for k, _ in FITS]
        print(f"| {s['scene']} | {s['seconds']['fit_ptm']:.3f} | " + " | ".join(cells) + " |")
    print("\n## Robust methods: mean angular error (°) and time relative to the plain PTM fit\n")
    print("| scene | PS IRLS | PS trimmed | PTM debiased IRLS | PTM debiased trimmed "
          "| PTM max IRLS | PTM max trimmed | PTM debiased, given PS normals |")
    print("| --- |" + " --- |" * 7)
    for s in scenes:
        e, t = s["errors"], s["time_vs_plain_ptm"]
        print(f"| {s['scene']} | {e['ps_robust']['mean_deg']:.2f} ({t['robust_ps']:.1f}×) "
              f"| {e['ps_robust_trimmed']['mean_deg']:.2f} ({t['robust_ps_trimmed']:.1f}×) "
              f"| {e['ptm_debiased_robust']['mean_deg']:.2f} ({t['robust_ptm']:.1f}×) "
              f"| {e['ptm_debiased_robust_trimmed']['mean_deg']:.2f} ({t['robust_ptm_trimmed']:.1f}×) "
              f"| {e['ptm_max_robust']['mean_deg']:.2f} | {e['ptm_max_robust_trimmed']['mean_deg']:.2f} "
              f"| {e['ptm_debiased_robust_given_ps']['mean_deg']:.2f} ({t['robust_ptm_given_ps']:.1f}×) |")

    rows = breakdown(args.lights, args.seed)
    labels = [f"{a:.0f}–{b:.0f}" for a, b in zip(SLANT_BINS[:-1], SLANT_BINS[1:])]
    print("\n## Breakdown: Lambertian cap, mean error (°) per slant band, by dome elevation range\n")
    print("Last columns: the slant band from which the mean error exceeds 5° and 10°.\n")
    print("| elevations | method | " + " | ".join(labels) + " | > 5° from | > 10° from |")
    print("| --- | --- |" + " --- |" * (len(labels) + 2))
    for r in rows:
        low, high = r["elevations_deg"]
        cells = ["–" if e is None else f"{e:.1f}" for e in r["mean_deg_per_slant_bin"]]
        cells += ["—" if r[f"over_{x:.0f}_deg_from_slant_deg"] is None
                  else f"{r[f'over_{x:.0f}_deg_from_slant_deg']:.0f}°" for x in BREAKDOWN_DEG]
        print(f"| {low:.0f}–{high:.0f}° | {r['method']} | " + " | ".join(cells) + " |")

    meta = {"date": time.strftime("%Y-%m-%d"), "machine": _machine(), "size": args.size,
            "lights": args.lights, "repeat": args.repeat, "seed": args.seed,
            "load_average_before": [round(x, 2) for x in load_before],
            "load_average_after": [round(x, 2) for x in os.getloadavg()]}
    out = Path(__file__).resolve().parent / "results" / "normals_table.json"
    out.parent.mkdir(exist_ok=True)
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"meta": meta, "scenes": scenes, "breakdown": rows}, indent=2) + "\n")
    os.replace(tmp, out)
    print(f"\n{meta['date']}, {meta['machine']}; load average {meta['load_average_before']} before, "
          f"{meta['load_average_after']} after; written {out}")


if __name__ == "__main__":
    main()
