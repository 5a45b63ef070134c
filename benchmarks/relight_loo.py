"""Leave-one-out relighting error of PTM, HSH order 2 and HSH order 3 on synthetic captures.

Which basis reproduces an object best under a light it was not fitted to? For each capture,
every light is left out in turn, the basis is fitted to the others and the photograph of the
left-out light is predicted (:mod:`ptmcore.loo`, exact PRESS shortcut, no refits). Reported
inside the tablet's mask: the RMSE in linear luminance (full scale 1), the same in 8-bit sRGB
levels (observed and predicted luminance both encoded as sRGB × 255, for intuition), and the
95th percentile of the per-pixel RMS map (where a basis fails: highlights, shadow edges).

Captures: the clay tablet, 512×384, sensor noise σ = 0.5 % of full scale, seed 0:

* lambertian — 48-light dome (15°–75°), no cast shadows, 16-bit linear TIFF;
* specular   — as lambertian plus a Blinn–Phong highlight (specular 0.6, shininess 40);
* shadows    — as lambertian with cast shadows;
* jpeg8      — as lambertian, stored as 8-bit sRGB JPEG (quality 95);
* ring       — as lambertian, but 48 lights on one ring at 45° elevation.

Run: ``.venv/bin/python benchmarks/relight_loo.py [--size 512x384] [--lights 48]``
Prints a Markdown table and writes ``benchmarks/results/relight_loo.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import ptmcore  # noqa: E402
from data_synthetic import ring_lights, write_capture  # noqa: E402
from ptmcore.fit import light_matrix  # noqa: E402
from ptmcore.hsh import hsh_basis  # noqa: E402
from ptmcore.loo import UndeterminedLightWarning, hat_diagonal, loo_error, undetermined_lights  # noqa: E402
from reconstruct.surface.accuracy import load_ground_truth  # noqa: E402

BASES = {
    "PTM": light_matrix,
    "HSH 2": lambda d: hsh_basis(d, 2),
    "HSH 3": lambda d: hsh_basis(d, 3),
}

RING_ELEVATION_DEG = 45.0


def scenes(n_lights: int) -> dict[str, dict]:
    """write_capture options of each capture."""
    lambertian = {"specular": 0.0, "cast_shadows": False, "encoding": "tiff16"}
    return {
        "lambertian": lambertian,
        "specular": {**lambertian, "specular": 0.6, "shininess": 40.0},
        "shadows": {**lambertian, "cast_shadows": True},
        "jpeg8": {**lambertian, "encoding": "jpeg8"},
        "ring": {**lambertian, "lights": ring_lights(n_lights, RING_ELEVATION_DEG)},
    }


def srgb_levels(v: np.ndarray) -> np.ndarray:
    """Linear luminance as an 8-bit sRGB level (clipped to 0..255 like a display, not rounded)."""
    return 255.0 * ptmcore.linear_to_srgb(v)


def measure(name: str, options: dict, shape: tuple[int, int], n_lights: int, seed: int) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        info = write_capture(Path(tmp) / "cap", scene="tablet", shape=shape, n_lights=n_lights,
                             seed=seed, scan_points=0, **options)
        lights = ptmcore.read_lp(info.lp_path)
        stack = ptmcore.load_stack(lights.paths)
        mask = load_ground_truth(info.ground_truth_dir).mask
        mean_luminance = float(stack.band(0, stack.shape[0])[0][:, mask].mean())
        for basis_name, make in BASES.items():
            basis = make(lights.directions)
            excluded = undetermined_lights(basis)
            with warnings.catch_warnings():
                # Counted in the table instead.
                warnings.simplefilter("ignore", UndeterminedLightWarning)
                t0 = time.perf_counter()
                rms_map, rmse = loo_error(stack, basis, mask=mask)
                seconds = time.perf_counter() - t0
                _, rmse_levels = loo_error(stack, basis, mask=mask, transform=srgb_levels)
            rows.append({
                "scene": name, "basis": basis_name, "terms": basis.shape[1],
                # The rank the fit and the leave-one-out error use (trace of the hat matrix).
                "rank": int(round(hat_diagonal(basis).sum())),
                "lights": len(lights), "excluded_lights": excluded.tolist(),
                "loo_rmse_linear": rmse, "loo_rmse_srgb_levels": rmse_levels,
                "loo_p95_pixel_rms_linear": float(np.percentile(rms_map[mask], 95)),
                "mean_luminance": mean_luminance,
                "seconds": seconds,
            })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="512x384")
    ap.add_argument("--lights", type=int, default=48)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    rows = []
    for name, options in scenes(args.lights).items():
        rows += measure(name, options, (h, w), args.lights, args.seed)
    print("| scene | basis | terms (rank) | LOO RMSE linear | LOO RMSE 8-bit sRGB levels "
          "| p95 pixel RMS linear | LOO s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        excluded = f", {len(r['excluded_lights'])} lights excluded" if r["excluded_lights"] else ""
        print(f"| {r['scene']} | {r['basis']} | {r['terms']} ({r['rank']}{excluded}) "
              f"| {r['loo_rmse_linear']:.5f} | {r['loo_rmse_srgb_levels']:.2f} "
              f"| {r['loo_p95_pixel_rms_linear']:.5f} | {r['seconds']:.3f} |")
    out = Path(__file__).resolve().parent / "results" / "relight_loo.json"
    out.parent.mkdir(exist_ok=True)
    meta = {"date": time.strftime("%Y-%m-%d"),
            "machine": f"{platform.machine()}, {platform.processor() or 'cpu'}, {os.cpu_count()} cores",
            "python": platform.python_version(), "numpy": np.__version__,
            "size": args.size, "lights": args.lights, "seed": args.seed, "scene": "tablet",
            "ring_elevation_deg": RING_ELEVATION_DEG, "noise": 0.005,
            "region": "tablet mask (ground_truth/mask.png)"}
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2) + "\n")
    os.replace(tmp, out)
    print(f"\n{meta['date']}, {meta['machine']}; written {out}")


if __name__ == "__main__":
    main()
