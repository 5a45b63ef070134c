"""Room light and uneven lamps (issue 37): what they do to the normals, and what
:mod:`ptmcore.illumination` gives back.

1. Normals: a synthetic tablet (:func:`data_synthetic.clay_tablet`, 640×480, 48 dome lights
   from 15° to 75°, noise 0.5 %, 16-bit linear) by per-pixel Lambertian photometric stereo
   (least squares on each pixel's samples between 10 % of its 90th percentile and the clip:
   the usual shadow threshold; the pipeline's robust fit is measured elsewhere); mean angular
   error inside the tablet's mask and over the frame, for: the clean capture; 10 % room light
   (:mod:`data_synthetic.illumination`, brighter towards one side) without and with the ambient
   frame subtracted (:func:`~ptmcore.illumination.subtract_ambient`, the frame a 16-bit TIFF with
   its own noise); cos⁴ vignetting (corners 0.75) × each lamp's cone × inverse-square fall-off
   of lamps at 2.5 half-diagonals × lamps 0.8–1.2 strong, without and with the flat field
   (:func:`~ptmcore.illumination.load_flat_field` on a board capture written as TIFF, with a dark
   label and dust on it).
2. The flat field's polynomial degree: the largest and 99th-percentile relative gain error
   over the frame against the true gains (16-bit and 8-bit JPEG boards).
3. Stray light (:func:`~ptmcore.illumination.estimate_stray_light`) on grid samples (every 4th
   pixel) of synthetic captures — tablet and sphere, matte and glossy (Blinn–Phong 0.6,
   exponent 40), 16-bit and JPEG, 0 / 5 / 10 / 20 % room light, domes from 15° and 30° — and of
   the real captures in ``../shared/real`` (DiLiGenT's cat, neuralrti_icon; skipped when absent).
4. The ambient check's thumbnails: a JPEG photograph's mean linear luminance read at 1/8 scale
   against the full decode.

Run: ``.venv/bin/python benchmarks/illumination.py``. Prints Markdown tables.
"""

from __future__ import annotations

import datetime
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from procinfo import cpu_model  # noqa: E402
from data_synthetic import clay_tablet, dome_lights, render, sphere_cap  # noqa: E402
from data_synthetic import illumination as synth  # noqa: E402
from data_synthetic.encoding import to_uint16_linear, write_jpeg8, write_tiff16  # noqa: E402
from ptmcore.illumination import (  # noqa: E402
    estimate_stray_light,
    load_flat_field,
    read_ambient,
    subtract_ambient,
)
from ptmcore.images import LUMA_WEIGHTS, read_image, srgb_to_linear  # noqa: E402

REAL = ROOT.parent / "shared" / "real"
SHAPE = (480, 640)


def lambertian_normals(lum: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """Per-pixel least-squares normals of ``(N, H, W)`` luminance, samples between 10 % of each
    pixel's 90th percentile and the clip."""
    n, h, w = lum.shape
    s = lum.reshape(n, -1)
    bright = np.quantile(s, 0.9, axis=0)
    wts = ((s >= 0.1 * bright) & (s < 0.999)).astype(np.float32)
    out = np.empty((h * w, 3), np.float32)
    chunk = 65536
    for p0 in range(0, h * w, chunk):
        ws, ss = wts[:, p0:p0 + chunk], s[:, p0:p0 + chunk]
        m = np.einsum("np,ni,nj->pij", ws, lights, lights, optimize=True) + 1e-9 * np.eye(3)
        rhs = np.einsum("np,ni,np->pi", ws, lights, ss, optimize=True)
        b = np.linalg.solve(m, rhs[..., None])[..., 0]
        out[p0:p0 + chunk] = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    return out.reshape(h, w, 3)


def angular_error(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=-1), -1, 1)))


def luminance(images: np.ndarray) -> np.ndarray:
    return (images @ LUMA_WEIGHTS).astype(np.float32)


def quantised(radiance: np.ndarray) -> np.ndarray:
    """16-bit linear, as a TIFF photograph reads back."""
    return (to_uint16_linear(radiance) / np.float32(65535)).astype(np.float32)


def normals_table(tmp: Path) -> None:
    surface = clay_tablet(SHAPE, seed=0)
    lights = dome_lights(48, 15, 75)
    t0 = time.perf_counter()
    clean = render(surface, lights, seed=1)
    print(f"rendered {len(lights)} photographs {SHAPE[1]}×{SHAPE[0]} in {time.perf_counter() - t0:.1f} s\n")
    rows = []

    def score(name: str, lum: np.ndarray, seconds: float = 0.0) -> None:
        err = angular_error(lambertian_normals(lum, lights), surface.normals)
        rows.append((name, float(err[surface.mask].mean()), float(err.mean()), seconds))

    score("clean", luminance(quantised(clean)))

    ambient = synth.ambient_frame(surface.albedo, 0.10, gradient=0.3)
    rng = np.random.default_rng(9)
    write_tiff16(tmp / "ambient.tif", ambient + 0.005 * rng.standard_normal(ambient.shape, dtype=np.float32))
    with_room = quantised(synth.add_ambient(clean.copy(), ambient))
    score("10 % room light", luminance(with_room))
    t0 = time.perf_counter()
    frame = read_ambient(tmp / "ambient.tif", SHAPE)
    for image in with_room:
        for r0 in range(0, SHAPE[0], 128):  # band by band, as the decoding pass
            rows_ = slice(r0, min(SHAPE[0], r0 + 128))
            subtract_ambient(image[rows_], frame, rows_)
    score("10 % room light, ambient frame subtracted", luminance(with_room), time.perf_counter() - t0)
    del with_room

    strength = np.random.default_rng(5).uniform(0.8, 1.2, len(lights)).astype(np.float32)
    gains = (synth.vignetting(SHAPE, 0.75)[None] * synth.lamp_cone(SHAPE, lights, seed=2)
             * synth.inverse_square(SHAPE, lights, 2.5) * strength[:, None, None])
    uneven = quantised(synth.apply_gains(clean.copy(), gains))
    score("vignetting + lamp cone + fall-off", luminance(uneven))
    names = [f"img_{k:03d}.tif" for k in range(len(lights))]
    board = synth.render_board(SHAPE, lights, gains, labels=[(420, 60, 120, 80)], dust=40, noise=0.005, seed=3)
    synth.write_board_capture(tmp / "flat", board, names)
    del board
    t0 = time.perf_counter()
    flat = load_flat_field(tmp / "flat", names, lights, SHAPE)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    for k, image in enumerate(uneven):
        for r0 in range(0, SHAPE[0], 128):
            image[r0:r0 + 128] /= flat.gain_rows(k, r0, min(SHAPE[0], r0 + 128))[..., None]
    t_apply = time.perf_counter() - t0
    score("vignetting + lamp cone + fall-off, flat field", luminance(uneven), t_load + t_apply)
    est = np.stack([flat.gain_rows(k, 0, SHAPE[0]) for k in range(len(lights))])
    q = est / gains
    q /= np.median(q)
    info = flat.describe()

    print("| capture | mean error in mask (°) | mean error, frame (°) | correction (s) |")
    print("| --- | ---: | ---: | ---: |")
    for name, masked, whole, seconds in rows:
        print(f"| {name} | {masked:.2f} | {whole:.2f} | {seconds:.2f} |" if seconds else
              f"| {name} | {masked:.2f} | {whole:.2f} | |")
    print(f"\nflat field: loaded in {t_load:.2f} s (48 TIFFs), divided out in {t_apply:.2f} s; gain error over the "
          f"frame max {100 * np.abs(q - 1).max():.2f} %, p99 {100 * np.quantile(np.abs(q - 1), 0.99):.2f} %; "
          f"label and dust rejected: {100 * info['rejected']:.1f} % of blocks")
    print(f"describe(): {info['summary']}\n")


def degree_table(tmp: Path) -> None:
    lights = dome_lights(48, 15, 75)
    strength = np.random.default_rng(5).uniform(0.8, 1.2, len(lights)).astype(np.float32)
    gains = (synth.vignetting(SHAPE, 0.75)[None] * synth.lamp_cone(SHAPE, lights, seed=2)
             * synth.inverse_square(SHAPE, lights, 2.5) * strength[:, None, None])
    print("| board | degree | max gain error (%) | p99 (%) | fit time (s) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for enc, ext in (("tiff16", ".tif"), ("jpeg8", ".jpg")):
        names = [f"b{k:03d}{ext}" for k in range(len(lights))]
        board = synth.render_board(SHAPE, lights, gains, labels=[(420, 60, 120, 80)], dust=40, noise=0.005, seed=3)
        synth.write_board_capture(tmp / enc, board, names, encoding=enc)
        for degree in (2, 3, 4, 5, 6):
            t0 = time.perf_counter()
            flat = load_flat_field(tmp / enc, names, lights, SHAPE, degree=degree)
            seconds = time.perf_counter() - t0
            q = np.stack([flat.gain_rows(k, 0, SHAPE[0]) for k in range(len(lights))]) / gains
            q = np.abs(q / np.median(q) - 1)
            print(f"| {enc} | {degree} | {100 * q.max():.2f} | {100 * np.quantile(q, 0.99):.2f} | {seconds:.2f} |")
    print()


def _jpeg_roundtrip(radiance: np.ndarray, tmp: Path) -> np.ndarray:
    out = []
    for k, image in enumerate(radiance):
        write_jpeg8(tmp / f"s{k}.jpg", image)
        out.append(srgb_to_linear(read_image(tmp / f"s{k}.jpg") / np.float32(255)))
    return np.stack(out)


def stray_table(tmp: Path) -> None:
    shape = (240, 320)
    print("| scene | dome from | surface | file | room light | level (%) | pixels | warn |")
    print("| --- | ---: | --- | --- | ---: | ---: | ---: | --- |")
    worst_dark, least_lit = 0.0, 1.0
    for scene, build in (("tablet", clay_tablet), ("sphere", sphere_cap)):
        surface = build(shape, seed=0)
        for low in (15, 30):
            lights = dome_lights(48, low, 75)
            for gloss in (0.0, 0.6):
                for enc in ("16-bit", "JPEG"):
                    for ambient in (0.0, 0.05, 0.10, 0.20):
                        if enc == "JPEG" and ambient not in (0.0, 0.05):
                            continue
                        radiance = render(surface, lights, specular=gloss, shininess=40, ambient=ambient, seed=1)
                        images = _jpeg_roundtrip(radiance, tmp) if enc == "JPEG" else quantised(radiance)
                        lum = luminance(images)[:, 2::4, 2::4].reshape(len(lights), -1)
                        found = estimate_stray_light(lum, lights)
                        level = "—" if found.level is None else f"{100 * found.level:.2f}"
                        if found.level is not None:
                            if ambient == 0:
                                worst_dark = max(worst_dark, found.level)
                            elif ambient == 0.05:
                                least_lit = min(least_lit, found.level)
                        kind = "glossy" if gloss else "matte"
                        print(f"| {scene} | {low}° | {kind} | {enc} | {100 * ambient:.0f} % | {level} | "
                              f"{found.pixels} | {'yes' if found.warn else 'no'} |")
    print(f"\nsynthetic: dark room reads at most {100 * worst_dark:.2f} %, 5 % room light at least "
          f"{100 * least_lit:.2f} %\n")
    if (REAL / "diligent_cat").exists():
        from ptmcore.psdataset import read_ps_dataset

        data = read_ps_dataset(REAL / "diligent_cat")
        for step in (2, 4, 8):
            samples = data.stack.table[data.stack.grid(step)].reshape(len(data.stack), -1)
            found = estimate_stray_light(samples, data.lights.directions)
            print(f"- DiLiGenT cat, grid step {step}: {found.message} ({found.pixels} pixels)")
    if (REAL / "neuralrti_icon").exists():
        from ptmcore.images import load_stack
        from ptmcore.lp import read_lp

        lp = read_lp(REAL / "neuralrti_icon" / "dirs.lp")
        stack = load_stack(lp.paths)
        for step in (2, 4, 8):
            samples = stack.table[stack.grid(step)].reshape(len(stack), -1)
            found = estimate_stray_light(samples, lp.directions)
            print(f"- neuralrti_icon, grid step {step}: {found.message} ({found.pixels} pixels)")
    print()


def thumbnail_bias(tmp: Path) -> None:
    surface = clay_tablet(SHAPE, seed=0)
    lights = dome_lights(8, 15, 75)
    radiance = render(surface, lights, seed=1)
    ratios = []
    for k, image in enumerate(radiance):
        write_jpeg8(tmp / f"t{k}.jpg", image)
        full = read_image(tmp / f"t{k}.jpg")
        thumb = read_image(tmp / f"t{k}.jpg", min_side=64)
        mean = [float((srgb_to_linear(x / np.float32(255)) @ LUMA_WEIGHTS).mean()) for x in (full, thumb)]
        ratios.append(mean[1] / mean[0])
    print(f"JPEG thumbnail (min_side 64: {thumb.shape[1]}×{thumb.shape[0]}) mean linear luminance / full decode: "
          f"{min(ratios):.3f}–{max(ratios):.3f}\n")


def main() -> None:
    print(f"# Room light and uneven lamps\n\n{cpu_model()}, {datetime.date.today().isoformat()}\n")
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        normals_table(tmp)
        degree_table(tmp)
        stray_table(tmp)
        thumbnail_bias(tmp)


if __name__ == "__main__":
    main()
