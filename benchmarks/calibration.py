"""Highlight-RTI calibration on generated sphere captures, by kind of sphere and of lighting.

Every variant renders ``--captures`` captures (:func:`data_synthetic.spheres.render_sphere_capture`)
of the same random scenes: the image size, 1 or 2 spheres of radius 75–120 px at non-overlapping
positions, 14–24 lights, PNG or JPEG, the background's brightness, tint and texture, 0–2
photographs with hidden highlights, and for every fourth capture a pinhole camera (focal length
0.7–1.3 × the image width, a wide to normal lens) instead of the orthographic view. The variants
differ in the spheres' reflectance and the lights' elevations:

- ``sharp``: the renderer's default, a Phong lobe of exponent 500 (a polished sphere) with a
  clipped core, lights at 15°–75°;
- ``broad``: Blinn–Phong exponents 10–50 (log-uniform; the half-maximum spans 19°–43° of light
  direction), peak 0.5–0.9, black spheres of albedo 0.01–0.05, lights at 15°–75°;
- ``low``: Blinn–Phong exponents 50–200, peak 0.5–0.9, lights at 20°–35° only;
- ``saturated``: Blinn–Phong exponents 30–300 with a peak of 2–5 (clipped over much of the
  highlight), lights at 15°–75°;
- ``held-out-like``: what the issue describes of the held-out capture: two black glossy spheres
  (albedo 0.01–0.05), Blinn–Phong exponents 15–60, peak 0.6–1.6, lights at 20°–90°;
- ``broad+saturated``: a stress case beyond it: exponents 10–30 with a peak of 2–4, lights at
  20°–90°;
- ``broad+nl``, ``low+nl``, ``saturated+nl``, ``held-out-like+nl``: the same scenes and lobes
  as ``broad``, ``low``, ``saturated`` and ``held-out-like``, with the lobe multiplied by n·l
  (``n_dot_l=True``: a BRDF lit by a light, as physically based renderers shade it, rather
  than the lobe alone as :func:`data_synthetic.render.render` and classic Phong shading do).

Measured, with no hints (spheres detected by :func:`reconstruct.calibration.spheres.detect_spheres`;
when detection fails, the true outlines are given so the light accuracy is still measured):

- detection: a capture is detected when every sphere is found (centre within 2 px of the true
  outline's centre, radius within 2 % of its mean radius) and nothing else is;
- light directions: angular error of every usable photograph against the truth, with the true
  intrinsics for the perspective captures (and, for contrast on ``sharp``, with the orthographic
  model), combined over the spheres and for each sphere alone;
- the factor (n·l)^q the calibration estimated (``Calibration.lobe_cosine``; 0 for the lobe
  alone, 1 for the lobe × n·l);
- for comparison, the same mean of normals with q fixed at 0 (the estimator before q was
  estimated, which takes the lobe alone to be the radiance), and the estimator before that: the
  intensity-weighted centroid of the half-maximum blob grown by two pixels, in the image (its
  code is kept below as :func:`old_highlight`), on the same spheres and photographs, combined
  with the same weights. The centroid's limit of 2 % of the disc on the blob's area is lifted
  so that broad lobes are measured at all; how many highlights it would have refused is
  counted;
- the time per highlight of the three, on the spheres' crops (decoding excluded);
- hidden highlights: how many photographs with hidden highlights are flagged, and how many
  photographs are mis-estimated silently (not flagged, error above 2°).

A last table renders one orthographic sphere (radius 100 px, no noise, 8-bit) under 14
lights at elevations 20°–85° with a Blinn–Phong lobe, alone or times n·l (and times n·l written
to 8 bits without the sRGB curve but read back with it), and gives the error at a few
elevations with q estimated from the 14 highlights, with q fixed at 0, and of the centroid.

Run: ``.venv/bin/python benchmarks/calibration.py [--captures 12] [--seed 0] [--variants …]``
Prints a summary and writes ``benchmarks/results/calibration.json``.
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
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_synthetic.spheres import render_sphere_capture
from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from ptmcore.images import load_stack, srgb_to_linear
from reconstruct.calibration.calibrate import _crops_per_sphere, _sphere_crops, calibrate_stack
from reconstruct.calibration.highlights import find_highlights, sphere_highlights
from reconstruct.calibration.reflection import ellipse_mean_radius, light_from_highlight, sphere_normal_at

SHAPES = ((300, 400), (360, 480), (400, 560), (480, 640))
SILENT_DEG = 2.0


def _loguniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _sharp(rng: np.random.Generator) -> dict:
    return {}


def _blinn_phong(shininess: tuple[float, float], specular: tuple[float, float],
                 elevations_deg: tuple[float, float] | None = None):
    """A draw of black spheres (albedo 0.01–0.05) with a Blinn–Phong lobe: exponent
    log-uniform and peak uniform in the given ranges, lights at the given elevations (the
    renderer's 15°–75° when None)."""
    def draw(rng: np.random.Generator) -> dict:
        out = {"lobe": "blinn-phong", "shininess": _loguniform(rng, *shininess),
               "specular": float(rng.uniform(*specular)),
               "sphere_albedo": float(rng.uniform(0.01, 0.05))}
        if elevations_deg is not None:
            out |= {"min_elevation_deg": elevations_deg[0], "max_elevation_deg": elevations_deg[1]}
        return out
    return draw


_broad = _blinn_phong((10, 50), (0.5, 0.9))
_low = _blinn_phong((50, 200), (0.5, 0.9), (20.0, 35.0))
_saturated = _blinn_phong((30, 300), (2.0, 5.0))
_held_out_like = _blinn_phong((15, 60), (0.6, 1.6), (20.0, 90.0))
_broad_saturated = _blinn_phong((10, 30), (2.0, 4.0), (20.0, 90.0))


def _times_n_dot_l(draw):
    return lambda rng: draw(rng) | {"n_dot_l": True}


#: name → (draw of the reflectance and lighting, number of spheres or None for 1–2 at random)
VARIANTS = {
    "sharp": (_sharp, None),
    "broad": (_broad, None),
    "low": (_low, None),
    "saturated": (_saturated, None),
    "held-out-like": (_held_out_like, 2),
    "broad+saturated": (_broad_saturated, None),
    "broad+nl": (_times_n_dot_l(_broad), None),
    "low+nl": (_times_n_dot_l(_low), None),
    "saturated+nl": (_times_n_dot_l(_saturated), None),
    "held-out-like+nl": (_times_n_dot_l(_held_out_like), 2),
}


def _lobe_stream(name: str) -> int:
    """Index of a variant's stream of reflectances: a "+nl" variant draws its base's."""
    return list(VARIANTS).index(name.removesuffix("+nl"))


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _place_spheres(rng: np.random.Generator, shape: tuple[int, int], count: int,
                   margin: float) -> list[tuple[float, float, float]] | None:
    """Random non-overlapping spheres inside the image, or None if they do not fit."""
    h, w = shape
    spheres: list[tuple[float, float, float]] = []
    for _ in range(200):
        r = float(rng.uniform(75.0, 120.0))
        lo = r + margin
        if 2 * lo >= min(h, w):
            continue
        cx, cy = float(rng.uniform(lo, w - lo)), float(rng.uniform(lo, h - lo))
        if all(np.hypot(cx - x, cy - y) > r + q + 10 for x, y, q in spheres):
            spheres.append((cx, cy, r))
            if len(spheres) == count:
                return spheres
    return None


def _draw_capture(rng: np.random.Generator, index: int, folder: Path, reflectance: dict,
                  count: int | None):
    """Render one random capture; perspective for every fourth. Retries until it fits."""
    perspective = index % 4 == 3
    while True:
        shape = SHAPES[rng.integers(len(SHAPES))]
        drawn = int(rng.integers(1, 3))
        # Perspective outlines grow towards the borders: keep a wider margin there.
        spheres = _place_spheres(rng, shape, count or drawn, 14.0 if perspective else 3.0)
        if spheres is None:
            continue
        n_lights = int(rng.integers(14, 25))
        n_hidden = int(rng.choice([0, 0, 1, 2]))
        hidden = tuple(int(k) for k in rng.choice(n_lights, n_hidden, replace=False))
        brightness = float(rng.uniform(0.25, 1.1))
        tint = brightness * rng.uniform(0.7, 1.0, 3) * np.array([0.6, 0.55, 0.5])
        params = {
            "shape": shape, "n_lights": n_lights, "spheres": spheres, "seed": int(rng.integers(1 << 30)),
            "hidden": hidden, "encoding": str(rng.choice(["png", "jpeg"])),
            "background_tint": tuple(float(v) for v in tint),
            "background_texture": float(rng.uniform(0.0, 0.4)),
            "focal_px": float(rng.uniform(0.7, 1.3) * shape[1]) if perspective else None,
        } | reflectance
        try:
            return render_sphere_capture(folder, **params), params
        except InputError:
            continue  # a perspective outline left the image: draw again


def _match(found, info) -> tuple[bool, list[dict]]:
    """Whether the detected spheres are exactly the true ones, and per-sphere offsets."""
    rows = []
    used = set()
    for x0, y0, a, b, _ in info.outlines:
        r_true = ellipse_mean_radius(a, b)
        best = None
        for j, (cx, cy, r) in enumerate(found):
            d = float(np.hypot(cx - x0, cy - y0))
            if best is None or d < best[0]:
                best = (d, j, r)
        if best is None:
            rows.append({"found": False})
            continue
        d, j, r = best
        ok = d <= 2.0 and abs(r - r_true) <= 0.02 * r_true
        if ok:
            used.add(j)
        rows.append({"found": ok, "centre_px": d, "radius_rel": float((r - r_true) / r_true)})
    return all(row["found"] for row in rows) and len(used) == len(found), rows


def old_highlight(crop: np.ndarray, sphere) -> tuple[tuple[float, float] | None, bool]:
    """The highlight estimator before the mean of normals, position only: the intensity-weighted
    centroid, in the image, of the half-maximum blob around the brightest pixel grown by two
    pixels (weights: excess over the disc's median). Returns the position (None without a
    candidate) and whether its limit on the blob's area (2 % of the disc) would have refused
    the highlight."""
    cx, cy, r = sphere
    yy, xx = np.ogrid[:crop.shape[0], :crop.shape[1]]
    disc = np.hypot(xx - cx, yy - cy) < r - 1.5
    vals = crop[disc]
    peak, body = float(vals.max()), float(np.median(vals))
    if peak < 0.15 or peak < 3.0 * body:
        return None, False
    blobs, _ = ndimage.label((crop > body + 0.5 * (peak - body)) & disc)
    iy, ix = np.unravel_index(np.argmax(np.where(disc, crop, -np.inf)), crop.shape)
    blob = blobs == blobs[iy, ix]
    refused = int(blob.sum()) > 0.02 * int(disc.sum())
    grown = ndimage.binary_dilation(blob, iterations=2) & disc
    wgt = np.clip(crop - body, 0, None) * grown
    total = float(wgt.sum())
    if total <= 0:
        return None, refused
    return (float((wgt * xx).sum() / total), float((wgt * yy).sum() / total)), refused


def _old_directions(stack, cal) -> tuple[np.ndarray, int, float]:
    """(S, N, 3) directions of :func:`old_highlight` on the calibration's spheres (NaN where it
    finds no candidate), how many highlights its area limit would have refused, and the
    seconds it took."""
    n = len(stack)
    positions = np.full((len(cal.spheres), n, 2), np.nan)
    refused = 0
    seconds = 0.0
    for i, sph in enumerate(cal.spheres):
        crops, x0, y0 = _sphere_crops(stack, sph)
        local = (sph[0] - x0, sph[1] - y0, sph[2])
        for k in range(n):
            t0 = time.perf_counter()
            pos, no = old_highlight(crops[k], local)
            seconds += time.perf_counter() - t0
            refused += int(no and np.isfinite(cal.highlights[i, k, 0]))
            if pos is not None:
                positions[i, k] = pos[0] + x0, pos[1] + y0
    return _lights(positions, cal), refused, seconds


def _lights(positions: np.ndarray, cal) -> np.ndarray:
    """(S, N, 3) light directions of (S, N, 2) highlight positions in the photographs on the
    calibration's spheres (NaN where NaN), one call per sphere."""
    return np.stack([light_from_highlight(p[:, 0], p[:, 1], sph, cal.intrinsics)
                     for p, sph in zip(positions, cal.spheres)])


def _highlight_directions(stack, cal, lobe_cosine: float | None
                          ) -> tuple[np.ndarray, np.ndarray, float]:
    """(S, N, 3) directions and (S, N) confidences of the mean of normals with the given q
    (None: estimated) on the calibration's spheres, and the seconds it took."""
    crops, corners, local, cameras = _crops_per_sphere(stack, cal.spheres, cal.intrinsics)
    t0 = time.perf_counter()
    found, _ = sphere_highlights(crops, local, intrinsics=cameras, lobe_cosine=lobe_cosine)
    seconds = time.perf_counter() - t0
    positions = np.full((len(cal.spheres), len(stack), 2), np.nan)
    conf = np.zeros(positions.shape[:2])
    for i, (x0, y0) in enumerate(corners):
        for k, one in enumerate(found[i]):
            if one is not None:
                positions[i, k] = one[0] + x0, one[1] + y0
                conf[i, k] = one[2]
    return _lights(positions, cal), conf, seconds


def _combine(sdirs: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean direction over the spheres, normalised (NaN where no weight)."""
    w = np.where(np.isfinite(sdirs).all(-1), weights, 0.0)
    summed = np.einsum("mn,mnc->nc", w, np.nan_to_num(sdirs))
    norm = np.linalg.norm(summed, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 0, summed / norm, np.nan)


def measure(index: int, rng: np.random.Generator, reflectance: dict, count: int | None) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        info, params = _draw_capture(rng, index, Path(tmp) / "cap", reflectance, count)
        row = {"index": index, "perspective": info.camera is not None,
               "shape": list(params["shape"]), "spheres": len(info.spheres),
               "radii_px": [s[2] for s in info.spheres], "lights": params["n_lights"],
               "hidden": list(info.hidden), "encoding": params["encoding"],
               "background_tint": params["background_tint"],
               "background_texture": params["background_texture"],
               "focal_px": params["focal_px"], "reflectance": reflectance}
        stack = load_stack(info.image_paths)
        t0 = time.perf_counter()
        try:
            cal = calibrate_stack(stack, intrinsics=info.camera)
            detected, per_sphere = _match(cal.spheres, info)
            row["detection_error"] = None
        except InputError as exc:
            cal, detected, per_sphere = None, False, []
            row["detection_error"] = exc.problem
        row["seconds"] = time.perf_counter() - t0
        row["detected"] = detected
        row["detected_spheres"] = per_sphere
        if not detected:
            # Light accuracy is still measured, from the true outlines given as hints.
            hints = [(x0, y0, ellipse_mean_radius(a, b)) for x0, y0, a, b, _ in info.outlines]
            cal = calibrate_stack(stack, spheres=hints, intrinsics=info.camera)
        row["model_used"] = cal.view_model
        row.update(_light_stats(cal.directions, cal.sphere_directions, cal.usable, info, "lights"))
        row["lobe_cosine"] = cal.lobe_cosine
        old_sdirs, refused, old_s = _old_directions(stack, cal)
        old = _combine(old_sdirs, cal.sphere_confidence)
        row.update(_light_stats(old, old_sdirs, cal.usable & np.isfinite(old).all(1), info,
                                "old_lights"))
        row["old_lights"]["refused_by_area_limit"] = refused
        q0_sdirs, q0_conf, q0_s = _highlight_directions(stack, cal, 0.0)
        q0 = _combine(q0_sdirs, q0_conf)
        row.update(_light_stats(q0, q0_sdirs, cal.usable & np.isfinite(q0).all(1), info,
                                "q0_lights"))
        _, _, new_s = _highlight_directions(stack, cal, None)
        count = max(int(np.isfinite(cal.highlights[..., 0]).sum()), 1)
        row["ms_per_highlight"] = {"estimated_q": 1e3 * new_s / count, "q_0": 1e3 * q0_s / count,
                                   "old_centroid": 1e3 * old_s / count}
        if info.camera is not None and not reflectance:
            ortho = calibrate_stack(stack, spheres=cal.spheres)
            row.update(_light_stats(ortho.directions, ortho.sphere_directions, ortho.usable,
                                    info, "ortho_lights"))
    return row


def _light_stats(directions, sphere_directions, ok, info, key: str) -> dict:
    hidden = np.zeros(len(info.directions), bool)
    hidden[list(info.hidden)] = True
    err = _angles_deg(directions, info.directions)
    ok = ok & np.isfinite(err)
    sphere_err = [_angles_deg(d, info.directions)[ok] for d in sphere_directions]
    sphere_err = np.concatenate([e[np.isfinite(e)] for e in sphere_err])
    elevation = np.degrees(np.arcsin(np.clip(info.directions[:, 2], -1, 1)))
    return {key: {
        "errors_deg": [float(e) for e in err[ok]],
        "elevations_deg": [float(e) for e in elevation[ok]],
        "sphere_errors_deg": [float(e) for e in sphere_err],
        "hidden_flagged": int((hidden & ~ok).sum()),
        "hidden_total": int(hidden.sum()),
        "visible_flagged": int((~hidden & ~ok).sum()),
        "silent_misestimates": int((ok & (err > SILENT_DEG)).sum()),
    }}


def _summary(rows: list[dict], which: str, key: str) -> dict:
    sel = [r for r in rows if key in r and (which == "all" or r["perspective"] == (which == "perspective"))]
    err = np.concatenate([r[key]["errors_deg"] for r in sel]) if sel else np.zeros(0)
    elev = np.concatenate([r[key]["elevations_deg"] for r in sel]) if sel else np.zeros(0)
    serr = np.concatenate([r[key]["sphere_errors_deg"] for r in sel]) if sel else np.zeros(0)
    low = err[elev < 35.0]
    out = {
        "captures": len(sel),
        "photographs_usable": int(err.size),
        "mean_deg": float(err.mean()) if err.size else None,
        "max_deg": float(err.max()) if err.size else None,
        "low_lights_mean_deg": float(low.mean()) if low.size else None,
        "sphere_mean_deg": float(serr.mean()) if serr.size else None,
        "sphere_max_deg": float(serr.max()) if serr.size else None,
        "hidden_flagged": sum(r[key]["hidden_flagged"] for r in sel),
        "hidden_total": sum(r[key]["hidden_total"] for r in sel),
        "visible_flagged": sum(r[key]["visible_flagged"] for r in sel),
        "silent_misestimates": sum(r[key]["silent_misestimates"] for r in sel),
    }
    if key == "old_lights":
        out["refused_by_area_limit"] = sum(r[key]["refused_by_area_limit"] for r in sel)
    return out


def _sphere_image(light: np.ndarray, shininess: float, cosine: bool, radius: float = 100.0,
                  supersample: int = 3) -> tuple[np.ndarray, tuple[float, float, float]]:
    """One orthographic black sphere (albedo 0.02) under a Blinn–Phong lobe of peak 0.9,
    optionally times n·l, supersampled, clipped to [0, 1] and quantised to 8 bits."""
    size = int(2 * radius + 9)
    sphere = (size / 2 - 0.3, size / 2 + 0.2, radius)
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    coords = (np.arange(size)[:, None] + sub[None, :]).ravel()
    xx, yy = np.meshgrid(coords, coords)
    normals = sphere_normal_at(xx, yy, sphere)
    on = np.hypot(xx - sphere[0], yy - sphere[1]) < radius
    half = light + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half)
    ndotl = normals @ light
    lobe = np.clip(normals @ half, 0, None) ** shininess * (ndotl > 0)
    if cosine:
        lobe = lobe * np.clip(ndotl, 0, None)
    fine = np.where(on, 0.02 * np.clip(ndotl, 0, None) + 0.9 * lobe, 0.3)
    img = fine.reshape(size, supersample, size, supersample).mean(axis=(1, 3))
    return np.round(np.clip(img, 0.0, 1.0) * 255).astype(np.float32) / 255, sphere


#: Elevations of the convention table's lights (two azimuths each), and those reported.
_TABLE_ELEVATIONS = (20.0, 25.0, 30.0, 45.0, 60.0, 70.0, 85.0)
_TABLE_REPORTED = (20.0, 45.0, 70.0)


#: The convention table's shadings: (name, lobe times n·l, 8-bit values linear rather than sRGB).
_TABLE_SHADINGS = (("lobe alone", False, False), ("lobe × n·l", True, False),
                   ("lobe × n·l, no sRGB", True, True))


def convention_table() -> list[dict]:
    """Errors on one sphere under 14 lights, lobe alone or times n·l: the mean of normals with
    q estimated from the 14 highlights and with q = 0, and the image centroid.

    The last shading writes linear values to 8 bits without the sRGB curve, as a careless
    generator may; they are read back as sRGB, as :func:`ptmcore.images.load_stack` does.
    """
    rows = []
    lights = np.array([[np.cos(np.radians(e)) * np.cos(a), np.cos(np.radians(e)) * np.sin(a),
                        np.sin(np.radians(e))]
                       for e in _TABLE_ELEVATIONS for a in (0.6, 2.9)])
    for shininess in (15.0, 50.0, 200.0, 2000.0):
        for shading, cosine, raw in _TABLE_SHADINGS:
            imgs = []
            for light in lights:
                img, sphere = _sphere_image(light, shininess, cosine)
                imgs.append(srgb_to_linear(img) if raw else img)
            imgs = np.stack(imgs).astype(np.float32)
            found, q = sphere_highlights([imgs], [sphere])
            fixed = find_highlights(imgs, sphere, lobe_cosine=0.0)
            for elevation in _TABLE_REPORTED:
                k = _TABLE_ELEVATIONS.index(elevation) * 2
                light = lights[k]
                new = float(_angles_deg(light_from_highlight(*found[0][k][:2], sphere), light))
                q0 = float(_angles_deg(light_from_highlight(*fixed[k][:2], sphere), light))
                (ox, oy), _ = old_highlight(imgs[k], sphere)
                old = float(_angles_deg(light_from_highlight(ox, oy, sphere), light))
                rows.append({"shininess": shininess, "elevation_deg": elevation,
                             "shading": shading, "lobe_cosine": q, "new_deg": new,
                             "q0_deg": q0, "old_deg": old})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--captures", type=int, default=12, help="captures per variant")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=list(VARIANTS))
    ap.add_argument("--no-table", action="store_true", help="skip the lobe-convention table")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "calibration.json")
    args = ap.parse_args()
    variants = {}
    for name in args.variants:
        draw, count = VARIANTS[name]
        # The same scenes in every variant; their reflectance from a stream of its own.
        rng = np.random.default_rng(args.seed)
        lobe_rng = np.random.default_rng([args.seed, _lobe_stream(name) + 1])
        rows = []
        for i in range(args.captures):
            row = measure(i, rng, draw(lobe_rng), count)
            rows.append(row)
            errs, old = row["lights"]["errors_deg"], row["old_lights"]["errors_deg"]
            q0 = row["q0_lights"]["errors_deg"]
            print(f"{name} #{i:02d} {'persp' if row['perspective'] else 'ortho'} {row['spheres']} "
                  f"sphere(s) {row['encoding']:4s} detected={row['detected']} "
                  f"mean={np.mean(errs) if errs else float('nan'):.3f}° "
                  f"max={np.max(errs) if errs else float('nan'):.3f}° "
                  f"q={row['lobe_cosine']:.2f} "
                  f"q=0 mean={np.mean(q0) if q0 else float('nan'):.3f}° "
                  f"old mean={np.mean(old) if old else float('nan'):.3f}° "
                  f"({row['seconds']:.1f} s)", flush=True)
        summary = {
            "captures": len(rows),
            "detected": sum(r["detected"] for r in rows),
            "spheres_detected": sum(s["found"] for r in rows for s in r["detected_spheres"]),
            "spheres_total": sum(r["spheres"] for r in rows),
            "all": _summary(rows, "all", "lights"),
            "orthographic": _summary(rows, "orthographic", "lights"),
            "perspective_with_intrinsics": _summary(rows, "perspective", "lights"),
            "q_0": _summary(rows, "all", "q0_lights"),
            "old_estimator": _summary(rows, "all", "old_lights"),
            "lobe_cosine": [r["lobe_cosine"] for r in rows],
            "ms_per_highlight": {key: float(np.mean([r["ms_per_highlight"][key] for r in rows]))
                                 for key in ("estimated_q", "q_0", "old_centroid")},
        }
        if name == "sharp":
            summary["perspective_orthographic_model"] = _summary(rows, "perspective", "ortho_lights")
        variants[name] = {"summary": summary, "captures": rows}
    conventions = [] if args.no_table else convention_table()

    print(f"\n{'variant':17s} {'detected':>9s} {'usable':>6s} {'q':>9s} {'new mean':>9s} "
          f"{'new max':>8s} {'low mean':>9s} {'q=0 mean':>9s} {'q=0 max':>8s} {'old mean':>9s} "
          f"{'old max':>8s} {'old refused':>11s} {'hidden':>7s} {'silent':>6s} "
          f"{'ms/highlight new, q=0, old':>27s}")
    for name, res in variants.items():
        s = res["summary"]
        a, z, o = s["all"], s["q_0"], s["old_estimator"]
        low = a["low_lights_mean_deg"]
        q = f"{min(s['lobe_cosine']):.2f}–{max(s['lobe_cosine']):.2f}"
        ms = s["ms_per_highlight"]
        print(f"{name:17s} {s['detected']:>4d}/{s['captures']:<4d} {a['photographs_usable']:>6d} "
              f"{q:>9s} {a['mean_deg']:>8.3f}° {a['max_deg']:>7.3f}° "
              f"{'—' if low is None else f'{low:.3f}°':>9s} {z['mean_deg']:>8.3f}° "
              f"{z['max_deg']:>7.3f}° {o['mean_deg']:>8.3f}° {o['max_deg']:>7.3f}° "
              f"{o['refused_by_area_limit']:>11d} {a['hidden_flagged']:>3d}/{a['hidden_total']:<3d} "
              f"{a['silent_misestimates']:>6d} {ms['estimated_q']:>9.1f} {ms['q_0']:>6.1f} "
              f"{ms['old_centroid']:>6.1f}")
    print("\nlobe convention (one orthographic sphere, r = 100 px, no noise, 14 lights at 20°–85°)")
    for c in conventions:
        print(f"  exponent {c['shininess']:5.0f}  {c['shading']:19s}  q = {c['lobe_cosine']:.2f}  "
              f"elevation {c['elevation_deg']:4.0f}°  new {c['new_deg']:.3f}°  "
              f"q=0 {c['q0_deg']:.3f}°  old {c['old_deg']:.3f}°")
    result = {"benchmark": "calibration", "date": time.strftime("%Y-%m-%d"),
              "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
              "python": platform.python_version(), "seed": args.seed,
              "captures_per_variant": args.captures,
              "summary": {name: res["summary"] for name, res in variants.items()},
              "lobe_convention": conventions,
              "variants": variants}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
