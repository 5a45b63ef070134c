"""Held-out relighting error of the NumPy NeuralRTI (ptmcore.neural) against PTM and HSH 3.

Which basis reproduces an object best under a light it was not fitted to? Every 4th light is
held out; the network is trained on the rest (its encoder reads only those photographs), every
pixel is encoded from them and decoded at the held-out lights. PTM and HSH order 3 are fitted
per colour channel by linear least squares at the same fitting lights (coefficients = pinv of
the basis matrix × samples) and evaluated at the held-out ones. All three model the display
(sRGB-encoded) RGB values, 0–1, as NeuralRTI does.

Reported, averaged over the held-out lights, on the whole image: PSNR of the RGB in 8-bit
levels (predictions clipped to 0–1 as a display shows them; 20·log10(255 / RMSE)), and SSIM of
the same images (``skimage.metrics.structural_similarity``, data_range 255, over the three
channels). For the network also the PSNR after its codes are quantised to 8 bits per code
number over its range (how they are published), the training time (54 or 36 fitting lights,
``NeuralParameters()`` defaults) and the time to encode every pixel; for the icon also the
time to train on all 72 photographs.

For reference, the icon's result published with NeuralRTI (``encoded.npy``, ``header.npy`` and
the TensorFlow.js decoder ``model.json`` + ``group1-shard1of1.bin``: RGB, three ELU layers of
216, trained on all 72 photographs) is decoded at the same lights and scored the same way. It
saw those lights in training, so its figures are a fit, not a held-out error.

Captures:

* icon — NeuralRTI's painted icon, 72 JPEG photographs 402×395 (``../shared/real/neuralrti_icon``);
* matte, glossy, shadows — the synthetic clay tablet, 400×400, 48 lights (15°–75°), 16-bit
  linear TIFF (sRGB-encoded here), seed 0: Lambertian without cast shadows; plus a
  Blinn–Phong highlight (specular 0.6, shininess 40); Lambertian with cast shadows.

Run: ``.venv/bin/python benchmarks/neural.py [--only icon,matte] [--output FILE]``
Prints a Markdown table and writes ``benchmarks/results/neural.json`` (or ``FILE``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from skimage.metrics import structural_similarity

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import ptmcore  # noqa: E402
from procinfo import cpu_model  # noqa: E402
from data_synthetic import write_capture  # noqa: E402
from ptmcore.hsh import hsh_basis  # noqa: E402
from ptmcore.images import read_image  # noqa: E402
from ptmcore.neural import (  # noqa: E402
    NeuralParameters,
    decode,
    dequantize_codes,
    encode,
    quantize_codes,
    train_neural,
)
from ptmcore.published import ptm_weights  # noqa: E402
from ptmcore.resources import cpu_count  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ICON = ROOT.parent / "shared" / "real" / "neuralrti_icon"
SYNTHETIC = {
    "matte": {"specular": 0.0, "cast_shadows": False},
    "glossy": {"specular": 0.6, "shininess": 40.0, "cast_shadows": False},
    "shadows": {"specular": 0.0, "cast_shadows": True},
}
HOLD_OUT_STEP = 4


def display_rgb(paths: list[Path]) -> np.ndarray:
    """The photographs as display RGB in 0–1, (N, H, W, 3) float32: 8-bit files are sRGB
    already (the icon's JPEGs), 16-bit ones linear (data_synthetic's TIFFs) and encoded here."""
    images = []
    for path in paths:
        image = read_image(path)
        if image.dtype == np.uint8:
            images.append(image.astype(np.float32) / 255)
        else:
            images.append(ptmcore.linear_to_srgb(image.astype(np.float32) / 65535))
    return np.stack(images)


def scores(predicted: np.ndarray, observed: np.ndarray) -> tuple[float, float]:
    """Mean PSNR (dB) and SSIM over held-out lights of (L, H, W, 3) display RGB images."""
    psnr, ssim = [], []
    for p, o in zip(predicted, observed):
        p8, o8 = 255.0 * np.clip(p, 0, 1).astype(np.float64), 255.0 * o.astype(np.float64)
        rmse = np.sqrt(np.mean((p8 - o8) ** 2))
        psnr.append(20 * np.log10(255.0 / max(rmse, 1e-9)))
        ssim.append(structural_similarity(o8, p8, data_range=255.0, channel_axis=-1))
    return float(np.mean(psnr)), float(np.mean(ssim))


def linear_fit(basis: np.ndarray, values: np.ndarray, keep: np.ndarray, held: np.ndarray) -> np.ndarray:
    """A linear basis fitted per channel at ``keep`` and evaluated at ``held``: (len(held), H, W, 3)."""
    shape = values.shape[1:]
    coefficients = np.linalg.pinv(basis[keep]) @ values[keep].reshape(len(keep), -1)
    return (basis[held] @ coefficients).reshape(len(held), *shape)


def published_icon(held: np.ndarray, directions: np.ndarray, observed: np.ndarray) -> tuple[float, float]:
    """PSNR and SSIM of NeuralRTI's own icon result at the lights ``held``.

    Codes: 8-bit planes with one range (header: min, max, height, width). Decoder: the
    TensorFlow.js layers model, whose weights are the manifest's float32 arrays in order; its
    input is the code followed by (lu, lv), its output display values in [0, 1] in OpenCV's
    BGR order (what OpenLIME's NeuralRTI example declares with ``colorspace: "bgr"``; read as
    RGB, its PSNR here drops from 35 to 18 dB).
    """
    topology = json.loads((ICON / "model.json").read_text())
    flat = np.fromfile(ICON / topology["weightsManifest"][0]["paths"][0], dtype="<f4")
    weights, at = {}, 0
    for spec in topology["weightsManifest"][0]["weights"]:
        size = int(np.prod(spec["shape"]))
        weights[spec["name"]] = flat[at:at + size].reshape(spec["shape"])
        at += size
    names = sorted({name.split("/")[0] for name in weights}, key=lambda s: int(s.removeprefix("dense")))
    low, high, h, w = np.load(ICON / "header.npy")[0]
    codes = low + np.load(ICON / "encoded.npy").astype(np.float32) * np.float32((high - low) / 255)
    predicted = []
    for i in held:
        x = np.hstack([codes, np.broadcast_to(directions[i, :2].astype(np.float32), (len(codes), 2))])
        for name in names[:-1]:
            z = x @ weights[f"{name}/kernel"] + weights[f"{name}/bias"]
            x = np.where(z > 0, z, np.expm1(np.minimum(z, 0)))
        bgr = x @ weights[f"{names[-1]}/kernel"] + weights[f"{names[-1]}/bias"]
        predicted.append(bgr[:, ::-1].reshape(int(h), int(w), 3))
    return scores(np.stack(predicted), observed)


def evaluate(name: str, lp_path: Path, params: NeuralParameters, train_all: bool) -> dict:
    lights = ptmcore.read_lp(lp_path)
    values = display_rgb(lights.paths)
    directions = np.asarray(lights.directions, np.float64)
    n, h, w, _ = values.shape
    held = np.arange(0, n, HOLD_OUT_STEP)
    keep = np.setdiff1d(np.arange(n), held)
    observed = values[held]
    row = {"capture": name, "size": f"{w}x{h}", "lights": n, "fitting_lights": len(keep)}

    samples = values.reshape(n, -1, 3).transpose(1, 0, 2)  # (P, N, 3)
    t0 = time.perf_counter()
    model = train_neural(samples[:, keep], directions[keep], params)
    row["train_s"] = time.perf_counter() - t0
    row["final_training_rmse_levels"] = float(255 * np.sqrt(model.loss[-1]))
    t0 = time.perf_counter()
    codes = encode(model, samples[:, keep])
    row["encode_s"] = time.perf_counter() - t0

    def relit(c: np.ndarray) -> np.ndarray:
        return np.stack([decode(model, c, directions[i]).reshape(h, w, 3) for i in held])

    row["neural_psnr"], row["neural_ssim"] = scores(relit(codes), observed)
    row["neural_8bit_psnr"] = scores(relit(dequantize_codes(*quantize_codes(codes))), observed)[0]
    for label, basis in (("ptm", ptm_weights(directions)), ("hsh3", hsh_basis(directions, 3))):
        row[f"{label}_psnr"], row[f"{label}_ssim"] = scores(linear_fit(basis, values, keep, held), observed)
    if train_all:
        row["published_psnr"], row["published_ssim"] = published_icon(held, directions, observed)
        t0 = time.perf_counter()
        train_neural(samples, directions, params)
        row["train_all_lights_s"] = time.perf_counter() - t0
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", default="icon," + ",".join(SYNTHETIC), help="comma-separated captures")
    parser.add_argument("--output", type=Path, default=ROOT / "benchmarks" / "results" / "neural.json",
                        help="the JSON results (default: %(default)s)")
    args = parser.parse_args()
    wanted = args.only.split(",")
    params = NeuralParameters()
    rows = []
    if "icon" in wanted:
        if ICON.exists():
            rows.append(evaluate("icon", ICON / "dirs.lp", params, train_all=True))
        else:
            print(f"skipping icon: {ICON} not found", file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        for name, options in SYNTHETIC.items():
            if name in wanted:
                info = write_capture(Path(tmp) / name, "tablet", shape=(400, 400), n_lights=48, seed=0,
                                     encoding="tiff16", scan_points=0, **options)
                rows.append(evaluate(name, Path(info.lp_path), params, train_all=False))

    print("| capture | lights (fit) | neural PSNR / SSIM | neural, 8-bit codes: PSNR | PTM PSNR / SSIM "
          "| HSH 3 PSNR / SSIM | train s | encode s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['capture']} {r['size']} | {r['lights']} ({r['fitting_lights']}) "
              f"| {r['neural_psnr']:.2f} / {r['neural_ssim']:.3f} | {r['neural_8bit_psnr']:.2f} "
              f"| {r['ptm_psnr']:.2f} / {r['ptm_ssim']:.3f} | {r['hsh3_psnr']:.2f} / {r['hsh3_ssim']:.3f} "
              f"| {r['train_s']:.1f} | {r['encode_s']:.2f} |")
    for r in rows:
        if "train_all_lights_s" in r:
            print(f"\nTraining on all {r['lights']} photographs of {r['capture']}: {r['train_all_lights_s']:.1f} s. "
                  f"NeuralRTI's published {r['capture']} model (trained on all of them, so not held out) at "
                  f"the same lights: PSNR {r['published_psnr']:.2f} / SSIM {r['published_ssim']:.3f}")

    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps({
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": cpu_model(),
        "cpus": cpu_count(),
        "numpy": np.__version__,
        "held_out": f"every {HOLD_OUT_STEP}th light from the first",
        "params": dataclasses.asdict(params),
        "rows": rows,
    }, indent=2) + "\n")
    print(f"\nwrote {args.output}")


if __name__ == "__main__":
    main()
