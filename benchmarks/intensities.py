"""Light intensities estimated from the photographs (``--intensities estimate``) against known ones.

1. Real: DiLiGenT's cat (``../shared/real/diligent_cat``; skipped when absent), 96 photographs
   under calibrated LEDs whose RGB intensities (``light_intensities.txt``) vary sixfold. The
   photographs are read as they are (:func:`ptmcore.psdataset.read_ps_dataset` with
   ``divide_intensities=False``), and the factors estimated by
   :func:`ptmcore.intensity.fit_intensities`: for luminance from the stack (what
   ``reconstruct run --intensities estimate`` gives a capture with an ``.lp``), and per channel
   from the RGB photographs.
2. Synthetic: captures rendered by :func:`data_synthetic.render` (cast shadows, Blinn–Phong
   gloss, noise 0.5 %, clipped at 1) under random RGB intensities: a common strength 0.5–1.5
   times a per-channel tint 0.95–1.05.

Error: estimate ``e`` and reference ``r`` are each defined up to one scale (per channel), so the
scale ``s`` minimising ``Σ_k (s e_k / r_k − 1)²`` is applied and the table gives the mean and
the maximum over the photographs of ``|s e_k / r_k − 1|``. The luminance reference is the RGB
intensities weighted by :data:`ptmcore.images.LUMA_WEIGHTS` (what
:func:`ptmcore.intensity.apply_intensities` reduces them to). ``spread`` is
:attr:`ptmcore.intensity.IntensityFit.spread` (mean / max), the estimator's own idea of its error.

   For scale, the factors that best explain the cat's photographs by Lambert's law under its
   laser-scanned normals (per-photograph and per-pixel medians of ``I / (ρ n·l)``, alternated,
   over the samples with ``n·l ≥ 0.1`` outside the 30° specular cone): what a Lambertian
   estimate could reach if the normals were known.

3. Normals on the cat: mean angular error inside the mask of the default photometric stereo
   (:func:`reconstruct.pipeline.estimate_normals` with the default options, as
   ``reconstruct run``) when the photographs are divided by: the given intensities per channel
   (what the dataset reader does, the default of ``reconstruct run`` on the folder); the
   estimated RGB factors, per channel in the same way; the given intensities reduced to
   luminance, and the estimated luminance factors, both divided out of the luminance stack by
   :func:`~ptmcore.intensity.apply_intensities` (after scaling them to a minimum of 1, so that
   nothing clips); and nothing.

4. ``--large``: the time of the luminance estimate on a 24-megapixel stack (6000×4000, 24
   photographs of a Lambertian sphere filling the frame's height, 16-bit, no noise; 1.2 GB),
   to show that it does not grow with the image size: only the sampled pixels are read.

``--compare-to REV`` also runs ``estimate_intensities`` of ``ptmcore/intensity.py`` as it was at
git revision REV (e.g. the commit before a change), on the luminance.

Run: ``.venv/bin/python benchmarks/intensities.py [--compare-to REV] [--no-normals] [--large]``
Prints Markdown tables and writes ``benchmarks/results/intensities.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
import types
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_synthetic import clay_tablet, dome_lights, render, sphere_cap  # noqa: E402
from ptmcore.images import LUMA_WEIGHTS, SATURATED, ImageStack, load_stack, read_image  # noqa: E402
from ptmcore.intensity import apply_intensities, fit_intensities  # noqa: E402
from ptmcore.normals import angular_error  # noqa: E402

CAT = ROOT.parent / "shared" / "real" / "diligent_cat"
LUMA = LUMA_WEIGHTS.astype(np.float64)

#: Synthetic scenes: (label, surface, lights, render options).
SCENES = [
    ("sphere, glossy (0.6, n=40), 48 lights 15–75°", "sphere", (48, 15.0, 75.0), {"specular": 0.6, "shininess": 40.0}),
    ("sphere, broad gloss (0.3, n=5), 48 lights", "sphere", (48, 15.0, 75.0), {"specular": 0.3, "shininess": 5.0}),
    ("sphere, gloss (0.5, n=10), 96 lights 45–85°", "sphere", (96, 45.0, 85.0), {"specular": 0.5, "shininess": 10.0}),
    ("tablet, glossy (0.6, n=40), 48 lights", "tablet", (48, 15.0, 75.0), {"specular": 0.6, "shininess": 40.0}),
    ("tablet, Lambertian, 96 lights", "tablet", (96, 15.0, 75.0), {}),
    ("tablet, broad gloss (0.3, n=5), 48 lights", "tablet", (48, 15.0, 75.0), {"specular": 0.3, "shininess": 5.0}),
]


def relative_errors(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``|s e / r − 1|`` per photograph with the least-squares scale ``s``."""
    q = np.asarray(estimate, np.float64) / np.asarray(reference, np.float64)
    s = q.sum() / (q * q).sum()
    return np.abs(s * q - 1.0)


def error_summary(estimate: np.ndarray, reference: np.ndarray) -> dict:
    e = relative_errors(estimate, reference)
    return {"mean_pct": 100 * float(e.mean()), "max_pct": 100 * float(e.max())}


def luminance_stack(lum: np.ndarray, clipped: np.ndarray) -> ImageStack:
    """An ImageStack of linear luminance ``(N, H, W)`` in [0, 1] with clip marks."""
    codes = np.round(np.clip(lum, 0.0, 1.0) * 65534).astype(np.uint16)
    codes[clipped] = SATURATED
    h, w = lum.shape[1:]
    return ImageStack(codes, np.ones((h, w, 3), np.float32), [], 16, False, clipped.sum(axis=(1, 2)))


def baseline_estimator(rev: str):
    """``estimate_intensities`` of ``ptmcore/intensity.py`` at git revision ``rev``."""
    source = subprocess.run(["git", "show", f"{rev}:ptmcore/intensity.py"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    module = types.ModuleType(f"ptmcore._intensity_{rev}")
    module.__package__ = "ptmcore"
    exec(compile(source, f"{rev}:ptmcore/intensity.py", "exec"), module.__dict__)
    return module.estimate_intensities


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def estimate_row(name: str, rgb: np.ndarray, stack: ImageStack, dirs: np.ndarray, reference: np.ndarray,
                 mask: np.ndarray | None, baseline) -> dict:
    """Estimates on luminance (stack) and per channel (rgb) against ``reference`` (N, 3)."""
    lum, seconds = timed(lambda: fit_intensities(stack, dirs, mask=mask))
    colour = fit_intensities(rgb, dirs, mask=mask)
    row = {"capture": name, "photographs": len(dirs), "seconds_luminance": seconds, "rounds": lum.rounds,
           "luminance": error_summary(lum.factors, reference @ LUMA),
           "spread_pct": [100 * float(lum.spread.mean()), 100 * float(lum.spread.max())],
           "channels": [error_summary(colour.factors[:, c], reference[:, c]) for c in range(3)]}
    if baseline is not None:
        row["baseline_luminance"] = error_summary(baseline(stack, dirs, mask=mask), reference @ LUMA)
    return row, lum.factors, colour.factors


def synthetic_rows(baseline, seed: int, shape: tuple[int, int]) -> list[dict]:
    rows = []
    for i, (label, kind, (n, lo, hi), options) in enumerate(SCENES):
        rng = np.random.default_rng(seed + i)
        surface = sphere_cap(shape) if kind == "sphere" else clay_tablet(shape, seed=seed + i)
        dirs = dome_lights(n, lo, hi, seed=seed + i)
        intensities = rng.uniform(0.5, 1.5, n)[:, None] * rng.uniform(0.95, 1.05, (n, 3))
        radiance = render(surface, dirs, noise=0.005, seed=seed + i, **options)
        radiance *= (0.6 * intensities[:, None, None, :]).astype(np.float32)
        clipped = (radiance >= 1.0).any(axis=3)
        rgb = np.where(clipped[..., None], np.nan, radiance)
        stack = luminance_stack(radiance @ LUMA_WEIGHTS, clipped)
        row, _, _ = estimate_row(label, rgb, stack, dirs, intensities, surface.mask, baseline)
        rows.append(row)
    return rows


def large_row(n: int = 24, shape: tuple[int, int] = (4000, 6000), seed: int = 0) -> dict:
    """Time and error of the luminance estimate on a large stack, built a band of rows at a time."""
    rng = np.random.default_rng(seed)
    dirs = dome_lights(n, 15.0, 75.0, seed=seed)
    factors = rng.uniform(0.5, 1.5, n)
    h, w = shape
    codes = np.empty((n, h, w), np.uint16)
    radius = 0.48 * h
    x = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / radius
    for r0 in range(0, h, 500):
        y = -(np.arange(r0, min(r0 + 500, h), dtype=np.float32) - (h - 1) / 2)[:, None] / radius
        z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
        inside = z > 0
        for k, (lx, ly, lz) in enumerate(dirs.astype(np.float32)):
            shade = np.maximum(lx * x + ly * y + lz * z, 0.0) * inside
            codes[k, r0 : r0 + 500] = np.round(shade * np.float32(0.6 * factors[k] * 65534))
    stack = ImageStack(codes, np.ones((h, w, 3), np.float32), [], 16, False, np.zeros(n, np.int64))
    fit, seconds = timed(lambda: fit_intensities(stack, dirs))
    return {"capture": f"{w}×{h} sphere", "photographs": n, "seconds": seconds, "rounds": fit.rounds,
            "luminance": error_summary(fit.factors, factors)}


def lambertian_reference(rgb: np.ndarray, dirs: np.ndarray, normals: np.ndarray, mask: np.ndarray,
                         rounds: int = 30) -> np.ndarray:
    """Luminance factors explaining the photographs best by Lambert's law under known normals."""
    usable = mask & (np.linalg.norm(normals, axis=2) > 0.5)
    v = np.stack([image[usable].astype(np.float64) @ LUMA for image in rgb])  # (N, P)
    n = normals[usable].astype(np.float64)
    half = dirs + [0.0, 0.0, 1.0]
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    shading = dirs @ n.T
    use = (shading >= 0.1) & (half @ n.T < np.cos(np.radians(30.0)))
    v, shading, use = v[:, use.any(axis=0)], shading[:, use.any(axis=0)], use[:, use.any(axis=0)]
    factors = np.ones(len(dirs))
    with np.errstate(divide="ignore", invalid="ignore"):  # both branches of where are computed
        for _ in range(rounds):
            rho = np.nanmedian(np.where(use, v / (factors[:, None] * shading), np.nan), axis=0)
            factors = np.nanmedian(np.where(use, v / (rho * shading), np.nan), axis=1)
    return factors


def read_cat() -> dict:
    from ptmcore.psdataset import read_ps_dataset

    ds = read_ps_dataset(CAT, threads=2, divide_intensities=False)
    with ThreadPoolExecutor(2) as pool:
        rgb = np.stack(list(pool.map(read_image, ds.lights.paths)))  # (N, H, W, 3) uint16, as stored
    return {"dataset": ds, "rgb": rgb, "raw": ds.stack}


def cat_normals(cat: dict, lum_factors: np.ndarray, rgb_factors: np.ndarray) -> list[dict]:
    """Mean angular error of the default photometric stereo under each division."""
    from reconstruct.pipeline import estimate_normals, load_capture

    ds = cat["dataset"]
    capture = load_capture(CAT)  # the dataset reader divides by the given intensities per channel
    given_lum = ds.intensities @ LUMA
    stacks = {
        "given intensities, per channel (default)": capture.stack,
        "estimated, per channel": load_stack(ds.lights.paths, linearize=False, threads=2,
                                             channel_gains=rgb_factors.min() / rgb_factors),
        "given intensities, luminance": apply_intensities(cat["raw"], given_lum, relative=True),
        "estimated, luminance (--intensities estimate)": apply_intensities(cat["raw"], lum_factors, relative=True),
        "none": cat["raw"],
    }
    rows = []
    for label, stack in stacks.items():
        capture.stack = stack
        result, seconds = timed(lambda: estimate_normals(capture))
        err = angular_error(result.normals, ds.ground_truth_normals, ds.mask)
        rows.append({"division": label, "mean_deg": float(err.mean()), "median_deg": float(np.median(err)),
                     "seconds": seconds})
    return rows


def pct(d: dict) -> str:
    return f"{d['mean_pct']:.2f} / {d['max_pct']:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--compare-to", metavar="REV", help="also run the estimator of this git revision")
    ap.add_argument("--no-normals", action="store_true", help="skip the normals on the cat (the slow part)")
    ap.add_argument("--large", action="store_true", help="also time a 24-megapixel stack")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", default="256x192", help="synthetic captures, WxH")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    baseline = baseline_estimator(args.compare_to) if args.compare_to else None

    rows, normals = [], []
    if CAT.is_dir():
        cat = read_cat()
        ds = cat["dataset"]
        row, lum_factors, rgb_factors = estimate_row("DiLiGenT cat (real)", cat["rgb"], cat["raw"],
                                                     ds.lights.directions, ds.intensities, ds.mask, baseline)
        rows.append(row)
        reference = lambertian_reference(cat["rgb"], ds.lights.directions, ds.ground_truth_normals, ds.mask)
        laser = error_summary(reference, ds.intensities @ LUMA)
        if not args.no_normals:
            normals = cat_normals(cat, lum_factors, rgb_factors)
        del cat
    else:
        laser = None
        print(f"{CAT} not found: the real capture is skipped\n")
    rows += synthetic_rows(baseline, args.seed, (h, w))
    large = large_row(seed=args.seed) if args.large else None

    head = "| capture | N | luminance mean / max % |"
    rule = "| --- | --- | --- |"
    if baseline is not None:
        head += f" before ({args.compare_to}) mean / max % |"
        rule += " --- |"
    print(head + " R | G | B mean / max % | spread mean / max % | rounds | s |")
    print(rule + " --- | --- | --- | --- | --- | --- |")
    for r in rows:
        line = f"| {r['capture']} | {r['photographs']} | {pct(r['luminance'])} |"
        if baseline is not None:
            line += f" {pct(r['baseline_luminance'])} |"
        line += " " + " | ".join(pct(c) for c in r["channels"])
        line += f" | {r['spread_pct'][0]:.2f} / {r['spread_pct'][1]:.2f} | {r['rounds']} | {r['seconds_luminance']:.1f} |"
        print(line)
    if normals:
        print("\nDiLiGenT cat, default photometric stereo, photographs divided by:\n")
        print("| division | mean ° | median ° |")
        print("| --- | --- | --- |")
        for r in normals:
            print(f"| {r['division']} | {r['mean_deg']:.2f} | {r['median_deg']:.2f} |")

    if laser is not None:
        print(f"\nDiLiGenT cat, Lambert's law under the laser-scanned normals (for scale): luminance {pct(laser)} %")
    if large is not None:
        print(f"\n{large['capture']}, {large['photographs']} photographs: luminance {pct(large['luminance'])} %, "
              f"{large['rounds']} rounds, {large['seconds']:.1f} s")

    out = ROOT / "benchmarks" / "results" / "intensities.json"
    out.parent.mkdir(exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
            "seed": args.seed, "size": args.size, "compare_to": args.compare_to}
    out.write_text(json.dumps({"meta": meta, "estimates": rows, "cat_normals": normals,
                               "cat_laser_normals_lambertian": laser, "large": large}, indent=2) + "\n")
    print(f"\n{meta['date']}, {meta['machine']}; written {out.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
