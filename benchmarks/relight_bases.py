"""How faithfully each relighting basis relights a capture under lights it was not fitted to,
and whether ``--basis auto`` picks the best one.

Rendered captures (320 × 320, 49 dome lights fitted, 20 more lights held out at random
directions between 15° and 75° elevation, seed 0; 16-bit linear TIFF): matte, matte with cast
shadows, glossy, sharply glossy, dark glossy, coloured pigments with a white gloss, and a
glossy sphere. Real captures from ``../shared/real`` (skipped when absent): the NeuralRTI
icon (72 JPEGs) and the DiLiGenT cat (96 16-bit PNGs), every sixth photograph held out.

For each basis of :data:`ptmcore.bases.NAMES` in each encoding, :func:`ptmcore.bases.fit_published`
fits it to the fitting photographs, :meth:`PublishedBasis.display` renders it under each held-out
light as a viewer shows it (8-bit sRGB), and PSNR (dB, over R, G, B) and SSIM
(``skimage.metrics.structural_similarity``, channels averaged) compare it with the held-out
photograph, encoded the same way; for rendered captures also against the held-out lights
rendered without sensor noise (the object itself: SSIM rewards a prediction that carries noise
like the photograph's). ``auto`` is the basis and encoding
:func:`ptmcore.bases.choose_basis` picks from the fitting photographs alone (leave-one-out) among
the default candidates (:data:`ptmcore.bases.AUTO`), ``auto (all)`` among all of them with the
learned basis (``--basis-candidates all``: ``neural`` scored on lights held out of one training);
the seconds of each fit and choice are recorded in the JSON; "best of relight's" is the best on
held-out lights of the bases relight builds by default (PTM, HSH 3, RBF and bilinear with 9
planes, ``rbf9`` and ``bilinear9``; fitted to sRGB, as relight does), in PSNR and, separately,
in SSIM. The planes are not quantised here (the JPEG planes
of ``web/`` add their own error, alike for all bases).

Then the fit's time per basis at 24 MP (6000 × 4000, 48 photographs: a rendered 600 × 400
capture tiled), median of three runs, choice included for ``auto``.

Run: ``.venv/bin/python benchmarks/relight_bases.py [--quick] [--no-24mp] [--only-24mp BASES]``.
Prints Markdown tables and writes ``benchmarks/results/relight_bases.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_synthetic import clay_tablet, dome_lights, render, sphere_cap  # noqa: E402
from ptmcore.bases import AUTO, CANDIDATES, ENCODINGS, NAMES, choose_basis, fit_published  # noqa: E402
from ptmcore.interpolation import DEFAULT_PLANES  # noqa: E402
from ptmcore.images import ImageStack, linear_to_srgb, load_stack, read_image  # noqa: E402
from ptmcore.lp import read_lp, write_lp  # noqa: E402

REAL = ROOT.parent / "shared" / "real"
SHAPE = (320, 320)
FIT_LIGHTS = 49
HELD_OUT = 20
#: The bases relight builds, as it fits them by default (to the photographs as displayed; RBF
#: and bilinear with relight's 9 planes, "rbf9" and "bilinear9" here, where this project's
#: have :data:`ptmcore.bases.PCA_PLANES`).
RELIGHT = (("ptm", "srgb"), ("hsh3", "srgb"), ("rbf9", "srgb"), ("bilinear9", "srgb"))
#: Every (basis, encoding) measured: the learned basis is fitted to sRGB only.
KEYS = [(n, e) for n in NAMES for e in ENCODINGS if n != "neural" or e == "srgb"] + [("rbf9", "srgb"), ("bilinear9", "srgb")]


def fit(stack: ImageStack, directions: np.ndarray, key: str, encoding: str):
    """:func:`fit_published`, with "rbf9"/"bilinear9" the basis with relight's 9 planes."""
    if key in ("rbf9", "bilinear9"):
        return fit_published(stack, directions, key[:-1], encoding, planes=DEFAULT_PLANES)
    return fit_published(stack, directions, key, encoding)


def held_out_lights(count: int, seed: int) -> np.ndarray:
    """Random directions, azimuth uniform, elevation uniform in 15°–75°."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, count)
    el = np.radians(rng.uniform(15.0, 75.0, count))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def pigments(surface, seed: int):
    """The tablet painted in four saturated pigments (red, blue, ochre, green) in patches."""
    rng = np.random.default_rng(seed)
    h, w = surface.shape
    colours = np.array([[0.60, 0.08, 0.05], [0.06, 0.12, 0.55], [0.55, 0.38, 0.08], [0.08, 0.40, 0.12]], np.float32)
    patch = rng.integers(0, 4, size=(4, 4))
    rows = np.minimum(np.arange(h) * 4 // h, 3)
    cols = np.minimum(np.arange(w) * 4 // w, 3)
    albedo = colours[patch[rows[:, None], cols[None, :]]]
    return dataclasses.replace(surface, albedo=np.where(surface.mask[..., None], albedo, surface.albedo))


def darkened(surface, factor: float = 0.15):
    return dataclasses.replace(surface, albedo=surface.albedo * np.float32(factor))


SCENES = {
    "matte": dict(scene="tablet", specular=0.0, cast_shadows=False),
    "shadows": dict(scene="tablet", specular=0.0, cast_shadows=True),
    "glossy": dict(scene="tablet", specular=0.6, shininess=40.0, cast_shadows=True),
    "sharp gloss": dict(scene="tablet", specular=1.0, shininess=200.0, cast_shadows=True),
    "dark glossy": dict(scene="tablet", specular=0.5, shininess=60.0, cast_shadows=True, albedo=darkened),
    "pigments": dict(scene="tablet", specular=0.3, shininess=40.0, cast_shadows=True, albedo=pigments),
    "sphere glossy": dict(scene="sphere", specular=0.6, shininess=60.0, cast_shadows=False),
}


def write_tiffs(folder: Path, radiance: np.ndarray, lights: np.ndarray) -> list[Path]:
    import tifffile

    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, image in enumerate(radiance):
        name = f"img_{i:03d}.tif"
        tifffile.imwrite(folder / name, np.rint(np.clip(image, 0, 1) * 65535).astype(np.uint16))
        names.append(name)
    write_lp(folder / "lights.lp", names, lights)
    return [folder / n for n in names]


def display(linear: np.ndarray) -> np.ndarray:
    return np.rint(255.0 * linear_to_srgb(np.clip(linear, 0, 1))).astype(np.uint8)


def scores(published, truths: np.ndarray, lights: np.ndarray) -> tuple[float, float]:
    from skimage.metrics import structural_similarity

    psnr, ssim = [], []
    for truth, light in zip(truths, lights):
        shown = published.display(light)
        mse = np.mean((shown.astype(np.float64) - truth) ** 2)
        psnr.append(10 * np.log10(255.0 ** 2 / max(mse, 1e-12)))
        ssim.append(structural_similarity(truth, shown, channel_axis=2, data_range=255))
    return float(np.mean(psnr)), float(np.mean(ssim))


def measure(stack: ImageStack, fit_dirs: np.ndarray, truths: np.ndarray, held_dirs: np.ndarray,
            clean: np.ndarray | None = None) -> dict:
    """Every basis against the held-out photographs ``truths`` and, for a rendered capture,
    against the same lights rendered without sensor noise (``clean``): the object itself."""
    result = {"bases": {}, "fit_seconds": {}}
    for name, encoding in KEYS:
        t0 = time.perf_counter()
        published = fit(stack, fit_dirs, name, encoding)
        result["fit_seconds"][f"{name}/{encoding}"] = round(time.perf_counter() - t0, 2)
        psnr, ssim = scores(published, truths, held_dirs)
        result["bases"][f"{name}/{encoding}"] = {"psnr": round(psnr, 2), "ssim": round(ssim, 4)}
        if clean is not None:
            psnr, ssim = scores(published, clean, held_dirs)
            result["bases"][f"{name}/{encoding}"].update(clean_psnr=round(psnr, 2), clean_ssim=round(ssim, 4))
    for label, candidates in (("auto", AUTO), ("auto_all", CANDIDATES["all"])):
        t0 = time.perf_counter()
        choice = choose_basis(stack, fit_dirs, candidates=candidates)
        seconds = round(time.perf_counter() - t0, 2)
        key = f"{choice.name}/{choice.encoding}"
        result[label] = {"choice": key, **result["bases"][key], "choose_seconds": seconds,
                         "score_psnr": round(choice.best.psnr, 2) if choice.best else None,
                         "scores": {f"{c.name}/{c.encoding}": round(c.psnr, 2) for c in choice.scores}}
    relight = {f"{n}/{e}": result["bases"][f"{n}/{e}"] for n, e in RELIGHT}
    best = max(relight, key=lambda k: relight[k]["psnr"])
    result["best_relight"] = {"basis": best, **relight[best]}
    best_ssim = max(relight, key=lambda k: relight[k]["ssim"])
    result["best_relight_ssim"] = {"basis": best_ssim, **relight[best_ssim]}
    if clean is not None:
        result["best_relight_clean"] = {
            "psnr": max(r["clean_psnr"] for r in relight.values()),
            "ssim": max(r["clean_ssim"] for r in relight.values())}
    return result


def rendered(name: str, spec: dict, seed: int, tmp: Path) -> dict:
    spec = dict(spec)
    make = clay_tablet if spec.pop("scene") == "tablet" else sphere_cap
    paint = spec.pop("albedo", None)
    surface = make(SHAPE, seed=seed)
    if paint is not None:
        surface = paint(surface, seed) if paint is pigments else paint(surface)
    fit_dirs = dome_lights(FIT_LIGHTS)
    held_dirs = held_out_lights(HELD_OUT, seed + 1)
    radiance = render(surface, np.vstack([fit_dirs, held_dirs]), seed=seed, **spec)
    clean = render(surface, held_dirs, seed=seed, **{**spec, "noise": 0.0})
    if radiance.ndim == 3:
        radiance = radiance[..., None].repeat(3, axis=-1)
        clean = clean[..., None].repeat(3, axis=-1)
    paths = write_tiffs(tmp / name.replace(" ", "_"), radiance[:FIT_LIGHTS], fit_dirs)
    stack = load_stack(paths)
    truths = np.stack([display(r) for r in radiance[FIT_LIGHTS:]])
    return measure(stack, fit_dirs, truths, held_dirs, np.stack([display(r) for r in clean]))


def real_capture(paths: list[Path], directions: np.ndarray, *, linearize: bool) -> dict:
    held = np.arange(len(paths)) % 6 == 3
    fit_paths = [p for p, h in zip(paths, held) if not h]
    stack = load_stack(fit_paths, linearize=linearize)
    truths = []
    for p in (p for p, h in zip(paths, held) if h):
        image = read_image(p)
        if image.ndim == 2:
            image = image[..., None].repeat(3, axis=-1)
        # The photograph as a screen shows it: 8-bit sRGB ones as stored, 16-bit linear ones encoded.
        truths.append(image[..., :3] if image.dtype == np.uint8 else display(image[..., :3].astype(np.float32) / 65535.0))
    return measure(stack, directions[~held], np.stack(truths), directions[held])


def real(which: str = "all") -> dict:
    out = {}
    icon = REAL / "neuralrti_icon" / "dirs.lp"
    if icon.is_file():
        lights = read_lp(icon)
        out["icon (real, 72 JPEG)"] = real_capture(lights.paths, lights.directions, linearize=True)
    cat = REAL / "diligent_cat"
    if which == "all" and (cat / "light_directions.txt").is_file():
        names = (cat / "filenames.txt").read_text().split()
        dirs = np.loadtxt(cat / "light_directions.txt")
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        out["cat (real, 96 PNG16)"] = real_capture([cat / n for n in names], dirs, linearize=False)
    return out


def timing_24mp(repeats: int = 3, keys=NAMES) -> dict:
    """Seconds of choose_basis and of fit_published per basis (``keys``, as :func:`fit` names
    them) on a 6000 × 4000 × 48 stack."""
    small_shape, tiles = (400, 600), (10, 10)
    surface = clay_tablet(small_shape, seed=0)
    dirs = dome_lights(48)
    radiance = render(surface, dirs, specular=0.4, shininess=40.0, seed=0)
    luminance = np.clip(radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32), 0, 1)
    codes = np.rint(255.0 * linear_to_srgb(luminance)).astype(np.uint8)
    codes = np.minimum(codes, 254)
    big = np.tile(codes, (1, *tiles))
    chroma = np.tile(surface.albedo / np.maximum(surface.albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32),
                                                 1e-6)[..., None], (*tiles, 1)).astype(np.float32)
    stack = ImageStack(big, chroma, [Path(f"img_{i}") for i in range(48)], 8, True, np.zeros(48, np.int64))
    out = {"shape": list(stack.shape), "photographs": 48}
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        choose_basis(stack, dirs)
        t.append(time.perf_counter() - t0)
    out["choose (auto)"] = round(float(np.median(t)), 2)
    for name in keys:
        t = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fit(stack, dirs, name, "srgb")
            t.append(time.perf_counter() - t0)
        out[name] = round(float(np.median(t)), 2)
    return out


def machine() -> str:
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        model = next(line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("Model name"))
    except (OSError, StopIteration):
        model = platform.processor() or platform.machine()
    import os

    return f"{model}, {os.cpu_count()} CPUs"


def table(results: dict) -> str:
    lines = ["| capture | auto's choice | auto PSNR / SSIM | auto − best of relight's (PSNR / SSIM) | "
             "auto (all)'s choice | auto (all) PSNR / SSIM | auto (all) − best | best of relight's PSNR / SSIM | "
             "best SSIM of relight's |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in results.items():
        a, x, b, s = r["auto"], r["auto_all"], r["best_relight"], r["best_relight_ssim"]
        lines.append(f"| {name} | {a['choice']} | {a['psnr']:.2f} dB / {a['ssim']:.3f} | "
                     f"{a['psnr'] - b['psnr']:+.2f} dB / {a['ssim'] - s['ssim']:+.3f} | "
                     f"{x['choice']} | {x['psnr']:.2f} dB / {x['ssim']:.3f} | "
                     f"{x['psnr'] - b['psnr']:+.2f} dB / {x['ssim'] - s['ssim']:+.3f} | "
                     f"{b['basis']} {b['psnr']:.2f} dB / {b['ssim']:.3f} | {s['basis']} {s['ssim']:.3f} |")
    return "\n".join(lines)


def clean_table(results: dict) -> str:
    """The rendered captures' choices against the held-out lights rendered without noise."""
    lines = ["| capture | auto's choice | PSNR / SSIM against the noise-free rendering | "
             "auto − best of relight's (PSNR / SSIM) | best of relight's PSNR / best SSIM |",
             "| --- | --- | --- | --- | --- |"]
    for name, r in results.items():
        if "best_relight_clean" not in r:
            continue
        a, b = r["bases"][r["auto"]["choice"]], r["best_relight_clean"]
        lines.append(f"| {name} | {r['auto']['choice']} | {a['clean_psnr']:.2f} dB / {a['clean_ssim']:.3f} | "
                     f"{a['clean_psnr'] - b['psnr']:+.2f} dB / {a['clean_ssim'] - b['ssim']:+.3f} | "
                     f"{b['psnr']:.2f} dB / {b['ssim']:.3f} |")
    return "\n".join(lines)


def full_table(results: dict) -> str:
    keys = [f"{n}/{e}" for n, e in KEYS]
    lines = ["| capture | " + " | ".join(keys) + " |", "| --- |" + " --- |" * len(keys)]
    for name, r in results.items():
        lines.append(f"| {name} | " + " | ".join(f"{r['bases'][k]['psnr']:.1f} / {r['bases'][k]['ssim']:.3f}"
                                                 for k in keys) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="three rendered scenes, no real captures")
    parser.add_argument("--no-24mp", action="store_true", help="skip the 24 MP timing")
    parser.add_argument("--real", choices=("all", "icon", "none"), default="all",
                        help="which real captures of ../shared/real to measure (default all)")
    parser.add_argument("--only-24mp", metavar="BASES",
                        help="only the 24 MP timing, of these comma-separated bases (e.g. ptm,rbf,rbf9)")
    args = parser.parse_args()
    if args.only_24mp:
        seconds = timing_24mp(keys=args.only_24mp.split(","))
        print(f"Machine: {machine()}; {time.strftime('%Y-%m-%d')}\nSeconds at 24 MP (48 photographs), median of 3: "
              + json.dumps(seconds))
        return
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, spec in list(SCENES.items())[:3 if args.quick else None]:
            t0 = time.perf_counter()
            results[name] = rendered(name, spec, 0, Path(tmp))
            print(f"{name}: {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    if not args.quick and args.real != "none":
        results.update(real(args.real))
    report = {"machine": machine(), "date": time.strftime("%Y-%m-%d"), "auto_candidates": list(AUTO),
              "captures": results}
    if not args.no_24mp:
        report["seconds_24mp"] = timing_24mp()
    print(f"Machine: {report['machine']}; {report['date']}\n")
    print(table(results) + "\n")
    print("Rendered captures against their held-out lights rendered without sensor noise:\n")
    print(clean_table(results) + "\n")
    print("Every basis (PSNR dB / SSIM on held-out lights):\n")
    print(full_table(results) + "\n")
    if "seconds_24mp" in report:
        print("Seconds at 24 MP (48 photographs), median of 3: " + json.dumps(report["seconds_24mp"]))
    out = ROOT / "benchmarks" / "results" / "relight_bases.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
