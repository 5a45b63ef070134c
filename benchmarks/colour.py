"""Captures as they really come (colour): photographs with an embedded ICC profile, and camera
RAW files, through ``reconstruct run`` as a user runs it, against a synthetic truth.

The source is one synthetic capture (:func:`data_synthetic.write_capture`: tablet, 512 × 384,
48 dome lights, seed 1, 16-bit linear TIFF, with ``ground_truth/``). Its photographs are
re-encoded and each capture is run with
``.venv/bin/python -m reconstruct run CAPTURE -o OUT --ground-truth CAPTURE/ground_truth``.

1. Embedded colour profiles: 8-bit JPEGs (Pillow, quality 95, 4:4:4) of the same linear light
   (a) sRGB-encoded, no profile (the reference); (b) Adobe RGB (1998) (D65, gamma 563/256),
   converted from linear sRGB by littlecms (``imagecodecs.cms_transform`` from
   ``ptmcore.decoders._linear_profile("rgb")``), its ICC profile embedded; (c) the same bytes
   without the profile (as the tool read them before it read profiles: as sRGB); (d) a
   ProPhoto-like wide gamut (D50 white, gamma 1.8), tagged, and (e) untagged.
2. Camera RAW: DNGs (:func:`data_synthetic.raw.write_dng`, neutral (0.55, 1, 0.7), an RGGB
   Bayer mosaic that LibRaw demosaics) with AsShotNeutral equal to the neutral, and with it
   varying from photograph to photograph as an automatic white balance would: R × (1, 1.03,
   0.97) and B × (1.03, 0.97, 1) cycling (the first photograph, whose balance the run uses for
   the whole capture, has B 3 % high). The 16-bit TIFF capture's run is the reference.

Reported per capture: the mean normal error (report.json ``accuracy.normals.mean_deg``); the
albedo's colour error inside the truth's mask: ``albedo.png`` (8-bit sRGB) decoded to linear,
scaled so that its mean luminance (Rec. 709 weights) inside the mask is the truth's
(``ground_truth/albedo.npy``, linear sRGB; the run's albedo has an arbitrary global scale),
then the mean over the mask of the chromaticity difference ½(|Δr| + |Δg|) with
r = R/(R+G+B), g = G/(R+G+B), and the median CIEDE2000 ΔE (``skimage.color.rgb2lab`` of the
sRGB-encoded values, ``deltaE_ciede2000``); part 2 also the median ΔE against the TIFF run's
albedo; and ``capture_checks.colour`` of report.json. Last, a sanity check of the decoders: the
first photograph as :func:`ptmcore.images.read_image` returns it, made linear (8-bit sRGB
decoded, 16-bit / 65535, float as is), against the linear TIFF it was made from (mean and 99th
percentile absolute difference, and ΣR/ΣG over the mask, read over source).

Machine and date first. Run: ``.venv/bin/python benchmarks/colour.py`` (about 1 minute on 2 cores).
Prints Markdown tables.
"""

from __future__ import annotations

import datetime
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import imagecodecs
import numpy as np
from PIL import Image
from skimage.color import deltaE_ciede2000, rgb2lab

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from procinfo import cpu_model  # noqa: E402
from data_synthetic import write_capture  # noqa: E402
from data_synthetic.raw import write_dng  # noqa: E402
from ptmcore.decoders import _linear_profile  # noqa: E402
from ptmcore.images import LUMA_WEIGHTS, linear_to_srgb, read_image, srgb_to_linear  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NEUTRAL = (0.55, 1.0, 0.7)

ADOBE = imagecodecs.cms_profile("rgb", whitepoint=[0.3127, 0.3290, 1.0],
                                primaries=[0.64, 0.33, 1, 0.21, 0.71, 1, 0.15, 0.06, 1], gamma=563 / 256)
PROPHOTO = imagecodecs.cms_profile("rgb", whitepoint=[0.3457, 0.3585, 1.0],
                                   primaries=[0.7347, 0.2653, 1, 0.1596, 0.8404, 1, 0.0366, 0.0001, 1], gamma=1.8)


def _sources(src: Path) -> list[tuple[str, np.ndarray]]:
    """The source capture's photographs: (stem, linear float32 (H, W, 3)) in lights.lp's order."""
    names = [line.split()[0] for line in (src / "lights.lp").read_text().splitlines()[1:] if line.strip()]
    return [(Path(n).stem, read_image(src / n).astype(np.float32) / np.float32(65535)) for n in names]


def _folder(src: Path, dst: Path, suffix: str) -> None:
    """``dst`` with lights.lp renamed to ``suffix`` (same order and directions) and ground_truth."""
    dst.mkdir()
    lines = (src / "lights.lp").read_text().splitlines()
    out = [lines[0]] + [line.replace(".tif", suffix, 1) for line in lines[1:] if line.strip()]
    (dst / "lights.lp").write_text("\n".join(out) + "\n")
    shutil.copytree(src / "ground_truth", dst / "ground_truth")


def _jpeg_capture(src: Path, dst: Path, photos, profile: bytes | None, embed: bool) -> None:
    """8-bit JPEGs, sRGB-encoded (``profile`` None) or converted to ``profile`` by littlecms."""
    _folder(src, dst, ".jpg")
    linear = _linear_profile("rgb")
    for stem, img in photos:
        img = np.clip(img, 0, 1)
        if profile is None:
            codes = np.round(linear_to_srgb(img) * 255).astype(np.uint8)
        else:
            codes = imagecodecs.cms_transform(np.ascontiguousarray(img), linear, profile, colorspace="rgb",
                                              outcolorspace="rgb", outdtype=np.uint8)
        extra = {"icc_profile": profile} if embed and profile is not None else {}
        Image.fromarray(codes).save(dst / f"{stem}.jpg", format="JPEG", quality=95, subsampling=0, **extra)


def _dng_capture(src: Path, dst: Path, photos, cycling: bool) -> None:
    _folder(src, dst, ".dng")
    r_cycle, b_cycle = (1.0, 1.03, 0.97), (1.03, 0.97, 1.0)
    for k, (stem, img) in enumerate(photos):
        shot = None
        if cycling:
            shot = (NEUTRAL[0] * r_cycle[k % 3], NEUTRAL[1], NEUTRAL[2] * b_cycle[k % 3])
        write_dng(dst / f"{stem}.dng", img, neutral=NEUTRAL, as_shot=shot)


def _run(folder: Path, out: Path) -> tuple[dict, np.ndarray, float]:
    """report.json, the linear albedo (float64) and the run's time."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "reconstruct", "run", str(folder), "-o", str(out),
                    "--ground-truth", str(folder / "ground_truth")], check=True, capture_output=True, cwd=ROOT)
    took = time.perf_counter() - start
    report = json.loads((out / "report.json").read_text())
    albedo = srgb_to_linear(np.asarray(Image.open(out / "albedo.png").convert("RGB"), np.float64) / 255.0)
    shutil.rmtree(out)
    return report, albedo, took


def _scaled(albedo: np.ndarray, like: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``albedo`` scaled so that its mean luminance inside ``mask`` is ``like``'s."""
    return albedo * ((like[mask] @ LUMA_WEIGHTS).mean() / (albedo[mask] @ LUMA_WEIGHTS).mean())


def _chroma_error(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    ca = a[mask] / np.maximum(a[mask].sum(axis=1, keepdims=True), 1e-12)
    cb = b[mask] / np.maximum(b[mask].sum(axis=1, keepdims=True), 1e-12)
    return float(np.abs(ca[:, :2] - cb[:, :2]).mean())


def _delta_e(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    la = rgb2lab(linear_to_srgb(a[mask].reshape(1, -1, 3)))
    lb = rgb2lab(linear_to_srgb(b[mask].reshape(1, -1, 3)))
    return float(np.median(deltaE_ciede2000(la, lb)))


def _decoded(path: Path, source: np.ndarray, mask: np.ndarray) -> str:
    """The first photograph as read_image returns it, made linear, against its source."""
    img = read_image(path)
    dtype = img.dtype
    if img.dtype == np.uint8:
        img = srgb_to_linear(img.astype(np.float32) / np.float32(255))
    elif img.dtype == np.uint16:
        img = img.astype(np.float32) / np.float32(65535)
    d = np.abs(img.astype(np.float64) - source)
    bright = mask & (source[..., 1] > 0.02)
    ratio = (img[bright][:, 0].sum() / img[bright][:, 1].sum()) / (source[bright][:, 0].sum() / source[bright][:, 1].sum())
    return f"{dtype} | {d.mean():.4f} | {np.quantile(d, 0.99):.4f} | {ratio:.3f}"


def main() -> None:
    print(f"# {datetime.date.today()}, {cpu_model()}")
    begin = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        src = tmp / "tiff"
        write_capture(src, shape=(384, 512), n_lights=48, seed=1, scan_points=0)
        photos = _sources(src)
        truth = np.load(src / "ground_truth" / "albedo.npy").astype(np.float64)
        mask = np.asarray(Image.open(src / "ground_truth" / "mask.png")) > 127
        print(f"\nSynthetic tablet 512 × 384, 48 lights, {int(mask.sum())} pixels in the mask; "
              "errors against the truth's albedo inside it.")

        def row(name: str, folder: Path, reference: np.ndarray | None = None) -> tuple[str, np.ndarray]:
            report, albedo, took = _run(folder, tmp / "out")
            albedo = _scaled(albedo, truth, mask)
            normals = report["accuracy"]["normals"]["mean_deg"]
            colour = report.get("capture_checks", {}).get("colour", "–")
            cells = [name, f"{normals:.3f}°", f"{_chroma_error(albedo, truth, mask):.4f}",
                     f"{_delta_e(albedo, truth, mask):.2f}"]
            if reference is not None:
                cells.append(f"{_delta_e(albedo, reference, mask):.2f}")
            cells += [colour, f"{took:.1f}"]
            return cells, albedo

        def line(cells: list[str]) -> str:
            return "| " + " | ".join(cells) + " |"

        checks = []
        tiff_cells, tiff_albedo = row("16-bit linear TIFF (source)", src, reference=None)
        checks.append(("16-bit linear TIFF", src / f"{photos[0][0]}.tif"))

        print("\n## 1. Embedded colour profiles (8-bit JPEG, quality 95, 4:4:4)\n")
        print("| capture | normals, mean | albedo chromaticity error | ΔE2000 (median) | colour (report) | run, s |")
        print("| --- | --- | --- | --- | --- | --- |")
        print(line(tiff_cells))
        cases = (("sRGB, untagged (reference)", None, False), ("Adobe RGB, profile embedded", ADOBE, True),
                 ("Adobe RGB, no profile (read as sRGB)", ADOBE, False),
                 ("ProPhoto-like, profile embedded", PROPHOTO, True),
                 ("ProPhoto-like, no profile (read as sRGB)", PROPHOTO, False))
        for number, (name, profile, embed) in enumerate(cases):
            folder = tmp / f"jpeg{number}"
            _jpeg_capture(src, folder, photos, profile, embed)
            print(line(row(name, folder)[0]))
            checks.append((name, folder / f"{photos[0][0]}.jpg"))

        print("\n## 2. Camera RAW (DNG, neutral (0.55, 1, 0.7); reference: the TIFF capture's run)\n")
        print("| capture | normals, mean | albedo chromaticity error | ΔE2000 (median) | ΔE2000 against TIFF run "
              "(median) | colour (report) | run, s |")
        print("| --- | --- | --- | --- | --- | --- | --- |")
        print(line(tiff_cells[:4] + ["0 (itself)"] + tiff_cells[4:]))
        for name, cycling in (("DNG, as-shot = neutral", False), ("DNG, as-shot cycling ±3 % (first: B +3 %)", True)):
            folder = tmp / ("dng_cycling" if cycling else "dng")
            _dng_capture(src, folder, photos, cycling)
            print(line(row(name, folder, reference=tiff_albedo)[0]))
            checks.append((name, folder / f"{photos[0][0]}.dng"))

        print("\n## Decoders: the first photograph (read_image, made linear) against its linear source\n")
        print("| capture | read as | mean abs. difference | 99th pct | ΣR/ΣG, read / source |")
        print("| --- | --- | --- | --- | --- |")
        for name, path in checks:
            print(f"| {name} | {_decoded(path, photos[0][1].astype(np.float64), mask)} |")
    print(f"\nTotal {time.perf_counter() - begin:.0f} s.")


if __name__ == "__main__":
    main()
