"""Relightable images for the web: Relight's format (what OpenLIME reads), tiled when large.

A relighting basis (:class:`ptmcore.published.PublishedBasis`: PTM, HSH, RBF or bilinear) is
written in the layout Relight (``relight-cli``/RelightLab, cnr-isti-vclab/relight) writes and
OpenLIME (cnr-isti-vclab/openlime) reads with ``LayerRTI`` + ``ShaderRTI``; the layout was taken
from their sources (Relight ``RtiBuilder::saveJSON``/``save``, ``Rti::load``; OpenLIME
``ShaderRTI.init``/``loadBasis``, ``LayoutTiles.initDeepzoom``), not guessed. A NeuralRTI basis
(``"neural"``) is written as OpenLIME's ``LayerNeuralRTI`` + ``ShaderNeural`` read it (their
sources and OpenLIME's example ``dist/assets/rti/neural/info.json``): see `NeuralRTI`_ below.

``info.json``
-------------
Keys, in Relight's order: ``width``, ``height``, ``format: "jpg"`` (the planes' suffix),
``pixelSizeInMM`` (only when known: OpenLIME's scale bar), ``type`` — ``"ptm"``, ``"hsh"``,
``"rbf"`` or ``"bilinear"`` (Relight's name of ``bln``: OpenLIME sets the basis' dimension
``resolution²`` only for that name) —, ``resolution`` (bilinear), ``colorspace`` (``"lrgb"`` or
``"mrgb"``), ``sigma`` and ``lights`` (RBF: the Gaussians' width and the D unit directions,
flattened ``x0, y0, z0, x1, …``), ``nplanes``, ``quality`` (not read by OpenLIME; Relight's
converter back to ``.ptm`` takes its JPEG quality from it), ``basis`` (MRGB, below) and
``materials: [{"range": […] (MRGB), "scale": […], "bias": […]}]``, one entry per plane channel.

The planes are JPEGs ``plane_0.jpg``, ``plane_1.jpg``, … three channels each; a viewer loads
``ceil(nplanes / 3)`` of them. A channel's byte ``b`` holds ``value = (b/255 − bias) · scale``
(OpenLIME's shader). Each coefficient channel is quantised linearly over its full range
[m, M]: ``scale = M − m``, ``bias = −m / scale``, ``b = rint((value − m) / scale · 255)``, within
half a step, ``scale / 510``, before JPEG compression (Relight takes a quantile of the range,
clipping outliers; the full range never clips). A constant channel has scale 1 and bytes 0.

* ``"lrgb"`` (PTM, HSH): ``plane_0`` is the colour (scale 1, bias 0), then the K coefficients
  of the luminance, three per JPEG in the order of the basis terms (PTM ``1, x, y, x², x·y,
  y²``; HSH H0 … H(K−1)); ``nplanes = 3 + 3·ceil(K/3)`` counts the colour channels too.
  OpenLIME computes ``l = Σ_k w_k(light) · value_k`` over every coefficient channel and shows
  ``l · colour/255``. Channels past K (HSH of order 2: 4 terms in 6 channels) have scale 0 and
  bias 0, so they are exactly 0 whatever OpenLIME weighs them with; OpenLIME needs ``nplanes``
  a multiple of 3 (its uniforms ``vec3 scale[]``/``bias[]``). OpenLIME's HSH knows 9 terms at
  most: an HSH of order 4 (16 terms) is rendered only by this folder's own page.
* ``"mrgb"`` (RBF, bilinear): the K coefficient planes, three per JPEG
  (``nplanes = 3·ceil(K/3)``; missing ones are zero, scale 0), and ``basis``, the RGB basis
  shared by all pixels as bytes in OpenLIME's order ``[plane p][direction d][channel]``,
  ``(nplanes + 1)·D·3`` of them: row 0 the mean, ``byte = rint(255 · mean)`` (clamped to
  0–1, as Relight clamps it), read as ``byte/255``; row p ≥ 1 component p,
  ``byte = rint(127 + range_p · B)`` with ``range_p = 127 / max|B_p|`` (Relight's choice: the
  bytes span 0–254), read as ``(byte − 127) / range_p``; ``materials[0].range`` holds the
  ``range_p``. OpenLIME interpolates the basis rows at the light — RBF: normalised Gaussians
  ``exp(−|l_d − light|²/σ²)``, weights ≤ 0.001 dropped and the rest renormalised; bilinear: the
  four nodes around the light's point on the rotated octahedral grid, node ``x + y·R`` — and
  shows ``B₀ + Σ_k value_k · B_k`` (:mod:`ptmcore.published`).

The values are the basis' own: 0–1 units of its ``encoding``. The JPEGs of whole planes are
written in the RGB colour space without chroma subsampling (Pillow's ``keep_rgb``,
``subsampling=0``), as Relight writes LRGB planes (``JCS_RGB``): a YCbCr transform would spread
each coefficient's compression error over the other two channels of its plane. Rows are in
image order (row 0 at the top). The planes are data, so they carry no colour tag (no ICC
profile), unlike the images for people (:mod:`ptmcore.colourtags`).

For the LRGB PTM (:func:`export_openlime`), the coefficient channels hold ``a / 255`` of
``L = a0·lu² + a1·lv² + a2·lu·lv + a3·lu + a4·lv + a5`` (0–255 luminance units, RTIViewer's):
``plane_1`` = (1, x, y) = (a5, a3, a4) and ``plane_2`` = (x², xy, y²) = (a0, a2, a1), so that
OpenLIME shows RTIViewer's ``rgb · L / 255`` (Relight ``legacy_rti.cpp``: "lrgb ptm order is x^2,
y^2, xy, x, y, 1, r, g, b while we use r, g, b, 1, x, y, x2 xy y2").

NeuralRTI
---------
``info.json`` keys: ``width``, ``height``, ``format: "jpg"``, ``pixelSizeInMM`` (when known),
``type: "neural"``, ``colorspace: "rgb"`` (OpenLIME applies it as a GLSL swizzle to the planes'
texels and to the network's output: ``"rgb"`` leaves both as they are), ``planes`` (9, the
code's size: OpenLIME reads no other), ``samples`` (n, the decoder's hidden width), ``quality``,
``min`` and ``max`` (9 numbers each), ``weights`` and ``biases``.

The codes are three RGB JPEGs named from 1 (OpenLIME's names): ``plane_1`` holds code numbers
0–2 in its R, G, B, ``plane_2`` 3–5, ``plane_3`` 6–8 (written as the planes above: RGB, 4:4:4,
no colour tag). Each code number c is quantised over its range [min_c, max_c]:
``b = rint((code − min_c) / (max_c − min_c) · 255)``, read by OpenLIME as
``code = b/255 · (max_c − min_c) + min_c`` (within half a step before JPEG compression; bytes
0 where the number is constant).

The decoder, evaluated per pixel (:mod:`ptmcore.published`): ``h1 = elu(W1·x + b1)`` with
``x = (code_0 … code_8, lu, lv, 0)``, ``h2 = elu(W2·h1 + b2)``, ``rgb = W3·h2 + b3``, (lu, lv)
the x and y of the unit light. ``weights`` holds W1, W2 and W3 as flat arrays, each matrix
row-major, outputs × inputs, as ShaderNeural reads them (``layer1_weights[3·i + j]``, the vec4
j of output i): with n4 the hidden width n padded up to a multiple of 4, W1 is n4 × 12, W2
n4 × n4, W3 3 × n4; ``biases`` holds b1 and b2 (n4 each) and b3 (3). The padding is zeros: a
padded unit is elu(0) = 0 and weighs nothing. Every number is written as the shortest decimal
that reads back as the same float32. OpenLIME keeps these in fragment-shader uniforms,
``n4²/4 + 4.25·n4`` vec4s and a few more, which must fit the GPU's
``MAX_FRAGMENT_UNIFORM_VECTORS`` (1024 on desktops): n ≤ 52 (:mod:`ptmcore.neural`).

Tiles
-----
Above :data:`TILE_THRESHOLD` pixels on the longer side (or when asked), each plane is written
as a DeepZoom pyramid instead of one JPEG (libvips ``dzsave``, as Relight's ``deepzoom``):
``plane_i.dzi`` (``TileSize`` 254, ``Overlap`` 1, ``Format`` jpg) and
``plane_i_files/<level>/<column>_<row>.jpg``. Level 0 is the first level that fits in one tile
(OpenLIME's ``"deepzoom"`` layout, Relight's numbering, libvips' ``depth="onetile"``); each level
above doubles the size, the last one is the image; a level's size is the next one's halved,
rounded up. Tile (c, r) of a level holds its pixels
``[254·c − 1 (if c > 0), min(254·(c + 1) + 1, width))`` across, the same down: one pixel of
overlap with its neighbours, so linear filtering shows no seams. ``info.json`` is the same; in
OpenLIME, open it with ``new OpenLIME.Layer({type: 'rti', layout: 'deepzoom', url: '…/info.json'})``
(``layout: 'image'`` for whole planes; ``type: 'neural'`` for NeuralRTI). Tiles are JPEGs in
libvips' YCbCr, 4:4:4, at the same quality (libvips cannot write RGB JPEGs). The levels below
the image average the planes' bytes: right for the linear bases, whose rendering is linear in
them; for NeuralRTI's codes an approximation, as in OpenLIME.

The folder's own page
---------------------
Beside these, the folder gets its own viewer, so that it can be published as it is:

* ``index.html`` — a relighting page in plain WebGL, no library (the package's
  ``webviewer.html``, copied). It renders every basis above with the formulas of
  :mod:`ptmcore.published` (HSH with this project's angles, :mod:`ptmcore.hsh`, up to order 4;
  NeuralRTI's decoder in a fragment shader, as OpenLIME's), streams the tiles of a pyramid
  (the level that matches the zoom, only the visible tiles), the mouse (or a hemisphere
  widget, or the arrow keys) moving the light; wheel zoom and pan; the light and layer in the
  address (``#light=x,y&layer=relit|normals|height``), so a link shows what its sender saw.
* ``viewer.json`` — what the page needs beyond ``info.json``: ``encoding`` (``"srgb"``, or
  ``"linear"`` for values of linear light, which the page encodes to sRGB for display),
  ``layers`` (the optional normal-map and height-map images :func:`export_web_layers` adds) and,
  from :func:`export_relightable`: ``basis`` (the basis' name), ``terms`` (K, the coefficient
  planes before padding; 9 for NeuralRTI), ``order`` (HSH), ``layout`` (``"image"`` or
  ``"deepzoom"``) and, for a pyramid, ``tiles``: ``format``, ``size``, ``overlap`` and
  ``levels``, the ``[width, height]`` of each level, level 0 first.
"""

from __future__ import annotations

import io
import json
import math
import os
import secrets
import shutil
from concurrent.futures import ThreadPoolExecutor
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from ptmcore.png import write_png
from ptmcore.published import OPENLIME_PTM_ORDER
from reconstruct.report.figures import normal_colors, thin

if TYPE_CHECKING:
    from ptmcore.published import PublishedBasis

__all__ = [
    "DZ_OVERLAP",
    "DZ_TILE_SIZE",
    "LAYER_SIDE",
    "NEURAL_PLANES",
    "PLANE_TERMS",
    "TILE_THRESHOLD",
    "export_openlime",
    "export_relightable",
    "export_web_layers",
    "lrgb_planes",
    "pyramid_levels",
]

#: Coefficient index (a0..a5) in each channel of plane_1 and plane_2: (1, x, y) and (x², xy, y²),
#: OpenLIME's order of the PTM's terms.
PLANE_TERMS = (tuple(OPENLIME_PTM_ORDER[:3]), tuple(OPENLIME_PTM_ORDER[3:]))

# Number of planes, counting the colour planes, as OpenLIME and Relight count them.
_NPLANES = 9

#: Longest side of the normal-map and height-map layers, pixels: sharp on a screen at the
#: whole object's view, and 12 MB of decoded textures at most (the relit planes stay full size).
LAYER_SIDE = 2048

#: Longest side, pixels, above which ``tiles="auto"`` writes pyramids. 4096 is the texture side
#: every WebGL device of the last decade takes (larger planes must be shrunk on the GPU, losing
#: the detail they were published for), and a whole 4096² plane is already a 3–6 MB JPEG and
#: 64 MB of decoded RGBA texture, times 3 to 7 planes, all downloaded before the first picture;
#: tiles show the first picture after a few 254² tiles, whatever the size.
TILE_THRESHOLD = 4096

#: DeepZoom tile side and overlap, pixels: Relight's and libvips' defaults, what OpenLIME's
#: documentation calls the typical tile (254 + 2 · 1 = 256, a power of two with its overlap).
DZ_TILE_SIZE = 254
DZ_OVERLAP = 1

# The page, in the package: see the module docstring.
_VIEWER_PAGE = "webviewer.html"

# PublishedBasis.type → Relight's (OpenLIME's) name in info.json and the colour space it goes with.
_RELIGHT_TYPES = {"ptm": ("ptm", "lrgb"), "hsh": ("hsh", "lrgb"), "rbf": ("rbf", "mrgb"), "bln": ("bilinear", "mrgb"),
                  "neural": ("neural", "rgb")}

#: Code size of a NeuralRTI basis: OpenLIME's ShaderNeural reads three RGB planes.
NEURAL_PLANES = 9


def _checked(coefficients: np.ndarray, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An LRGB PTM's arrays, checked: ``(H, W, 6)`` coefficients and a uint8 ``(H, W, 3)`` colour."""
    coef = np.asarray(coefficients)
    col = np.asarray(rgb)
    if coef.ndim != 3 or coef.shape[2] != 6:
        raise ValueError(f"coefficients must be (H, W, 6), not {coef.shape}")
    if col.shape != coef.shape[:2] + (3,) or col.dtype != np.uint8:
        raise ValueError(
            f"rgb must be uint8 {coef.shape[:2] + (3,)} to match the coefficients, not {col.dtype} {col.shape}"
        )
    return coef, col


def lrgb_planes(
    coefficients: np.ndarray, rgb: np.ndarray
) -> tuple[list[np.ndarray], list[float], list[float]]:
    """Quantise an LRGB PTM into OpenLIME's three 8-bit planes.

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6)
        a0..a5 in 0–255 luminance units (RTIViewer's convention).
    rgb : ndarray, shape (H, W, 3), uint8
        The colour.

    Returns
    -------
    planes : list of ndarray
        Three ``(H, W, 3)`` uint8 images: the colour, (1, x, y) and (x², xy, y²).
    scale, bias : list of float
        Nine entries each, one per channel in plane order, such that the value of a channel
        is ``(byte / 255 − bias) · scale`` (the colour planes have scale 1 and bias 0). The
        coefficient channels hold ``a / 255``.

    Raises
    ------
    ValueError
        If the shapes or types do not match, or a coefficient is not finite.
    """
    from ptmcore.quantize import coefficient_range, lrgb_plane_codes  # numba: imported only when needed

    coef, col = _checked(coefficients, rgb)
    # Compiled passes, each coefficient read once per pass: the ranges, then both planes.
    lows, highs = coefficient_range(coef)
    scale = [1.0, 1.0, 1.0]
    bias = [0.0, 0.0, 0.0]
    offsets = np.zeros((len(PLANE_TERMS), 3), dtype=np.float32)
    steps = np.zeros((len(PLANE_TERMS), 3), dtype=np.float32)
    for p, terms in enumerate(PLANE_TERMS):
        for c, k in enumerate(terms):
            lo, hi = float(lows[k]), float(highs[k])
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"coefficient a{k} is not finite everywhere")
            span = hi - lo
            # A constant channel quantises to all zeros, which decodes to lo whatever the
            # scale; 1 keeps the bias finite.
            s = span / 255.0 if span > 0 else 1.0
            m = lo / 255.0
            scale.append(s)
            bias.append(-m / s)
            # The byte is rint((float32(a) − float32(lo)) · step) clipped to 0..255, in float32.
            offsets[p, c] = np.float32(lo)
            steps[p, c] = np.float32(255.0 / span) if span > 0 else np.float32(0.0)
    planes = [np.ascontiguousarray(col)]
    planes += lrgb_plane_codes(coef, PLANE_TERMS, offsets, steps)
    return planes, scale, bias


def _quantised_planes(planes: np.ndarray, channels: int) -> tuple[list[np.ndarray], list[float], list[float]]:
    """Coefficient planes ``(H, W, K)`` as ``channels / 3`` RGB images of bytes, each channel
    over its own range (see the module docstring), with the scales and biases; channels past K
    are zero with scale 0, so that they decode to exactly 0."""
    h, w, k = planes.shape
    codes = np.zeros((h, w, channels), np.uint8)
    scale = [0.0] * channels
    bias = [0.0] * channels
    for c in range(k):
        v = np.asarray(planes[..., c], dtype=np.float32)
        lo, hi = float(v.min()), float(v.max())
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"coefficient plane {c} is not finite everywhere")
        span = hi - lo
        # A constant channel is all zeros, which decodes to lo; scale 1 keeps the bias finite.
        scale[c] = span if span > 0 else 1.0
        bias[c] = -lo / scale[c]
        if span > 0:
            codes[..., c] = np.clip(np.rint((v - np.float32(lo)) * np.float32(255.0 / span)), 0, 255)
    images = [np.ascontiguousarray(codes[..., j : j + 3]) for j in range(0, channels, 3)]
    return images, scale, bias


def _basis_bytes(basis: np.ndarray, rows: int) -> tuple[list[int], list[float]]:
    """An MRGB basis ``(K + 1, D, 3)`` as OpenLIME's bytes, ``rows`` rows after the mean (rows
    past K are zero), and each component row's range (see the module docstring)."""
    k, d = basis.shape[0] - 1, basis.shape[1]
    out = np.full((rows + 1, d, 3), 127, np.int64)
    out[0] = np.rint(np.clip(basis[0], 0.0, 1.0) * 255.0)
    ranges = [1.0] * rows  # a zero row is 127 whatever its range; 1 keeps it finite
    for p in range(1, k + 1):
        largest = float(np.abs(basis[p]).max())
        if largest > 0:
            ranges[p - 1] = 127.0 / largest
            out[p] = np.clip(np.rint(127.0 + ranges[p - 1] * basis[p]), 0, 254)
    return out.ravel().tolist(), ranges


def _encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """RGB JPEG without the YCbCr transform and without chroma subsampling."""
    from PIL import Image

    buf = io.BytesIO()
    # Pillow releases the GIL while encoding, so the planes encode in parallel threads.
    Image.fromarray(image, "RGB").save(buf, "JPEG", quality=quality, subsampling=0, keep_rgb=True)
    return buf.getvalue()


def _make_folder(folder: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as exc:
        raise InputError("is not a folder; cannot write the web viewer files there", folder) from exc
    except PermissionError as exc:
        raise InputError("cannot be created (permission denied)", folder) from exc
    except OSError as exc:
        raise InputError(f"cannot be created ({exc.strerror or exc})", folder) from exc


def _check_options(quality: object, pixel_size_mm: object, encoding: object) -> None:
    if encoding not in ("srgb", "linear"):
        raise ValueError(f"encoding must be 'srgb' or 'linear', not {encoding!r}")
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 1 <= quality <= 100:
        raise ValueError(f"JPEG quality must be an integer from 1 to 100, not {quality!r}")
    if pixel_size_mm is not None and not (
        isinstance(pixel_size_mm, (int, float, np.number))
        and math.isfinite(float(pixel_size_mm))
        and float(pixel_size_mm) > 0
    ):
        raise ValueError(f"pixel size must be a positive number of millimetres, not {pixel_size_mm!r}")


def _tiled(tiles: bool | str, shape: tuple[int, int], threshold: int) -> bool:
    if isinstance(threshold, bool) or not isinstance(threshold, (int, np.integer)) or threshold < 1:
        raise ValueError(f"tile_threshold must be a positive number of pixels, not {threshold!r}")
    if tiles == "auto":
        return max(shape) > threshold
    if isinstance(tiles, bool):
        return tiles
    raise ValueError(f"tiles must be True, False or 'auto', not {tiles!r}")


def pyramid_levels(width: int, height: int, tile_size: int = DZ_TILE_SIZE) -> list[tuple[int, int]]:
    """The ``(width, height)`` of a DeepZoom pyramid's levels, level 0 (the first that fits in
    one tile) first and the image last: each level is the next one halved, rounded up (libvips).
    """
    levels = [(int(width), int(height))]
    while max(levels[-1]) > tile_size:
        w, h = levels[-1]
        levels.append((-(-w // 2), -(-h // 2)))
    return levels[::-1]


def _write_pyramid(folder: Path, name: str, image: np.ndarray, quality: int) -> list[Path]:
    """One plane as a DeepZoom pyramid, ``name.dzi`` and ``name_files/``, built in a hidden
    folder and moved into place only when complete, so that an error leaves no partial pyramid
    (and an existing one intact until the new one replaces it)."""
    import pyvips  # a large library: imported only when a plane is tiled

    staging = folder / f".{name}.{secrets.token_hex(4)}.tmp"
    try:
        staging.mkdir()
        vips = pyvips.Image.new_from_array(np.ascontiguousarray(image))
        # 4:4:4 as the whole planes: subsampled chroma would blur the coefficients of 2 channels.
        vips.dzsave(str(staging / name), suffix=f".jpg[Q={int(quality)},subsample_mode=off]",
                    tile_size=DZ_TILE_SIZE, overlap=DZ_OVERLAP, depth="onetile", layout="dz")
        tiles = staging / f"{name}_files"
        (tiles / "vips-properties.xml").unlink(missing_ok=True)  # libvips' metadata: no viewer reads it
        target = folder / f"{name}_files"
        if target.exists():
            # A directory cannot be replaced in one rename: the old one is moved aside first.
            target.rename(staging / "old")
        os.replace(tiles, target)
        dzi = folder / f"{name}.dzi"
        with atomic_write(dzi, "wb") as f:
            f.write((staging / f"{name}.dzi").read_bytes())
    except pyvips.Error as exc:  # libvips could not write a tile: the disk, most likely
        raise InputError(f"cannot write the tiles of {name} ({exc.message.strip()})", folder) from exc
    except OSError as exc:
        raise InputError(f"cannot write the tiles of {name} ({exc.strerror or exc})", folder) from exc
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return [dzi, target]


def _write_planes(folder: Path, images: list[np.ndarray], quality: int, tiled: bool, first: int = 0) -> list[Path]:
    """The planes, ``plane_<first>`` first (0 in Relight's format, 1 in OpenLIME's NeuralRTI):
    whole JPEGs encoded in parallel threads, each written while the ones after it are still
    encoding; or pyramids, one after the other (libvips spreads each over the cores)."""
    written: list[Path] = []
    if tiled:
        for i, image in enumerate(images, first):
            written += _write_pyramid(folder, f"plane_{i}", image, quality)
        return written
    with ThreadPoolExecutor(max_workers=max(1, len(images))) as pool:
        jobs = [pool.submit(_encode_jpeg, image, int(quality)) for image in images]
        try:
            for i, job in enumerate(jobs, first):
                data = job.result()
                path = folder / f"plane_{i}.jpg"
                with atomic_write(path, "wb") as f:
                    f.write(data)
                written.append(path)
        finally:
            for job in jobs:  # after an error: nothing more is written, so nothing more is encoded
                job.cancel()
    return written


def _finish(folder: Path, info: dict, extras: dict) -> list[Path]:
    """``info.json`` (after the planes: a viewer never finds one whose planes are missing),
    ``viewer.json`` and ``index.html``."""
    path = folder / "info.json"
    with atomic_write(path, "w") as f:
        f.write(json.dumps(info, indent=1) + "\n")
    written = [path, _write_viewer_json(folder, extras)]
    path = folder / "index.html"
    with atomic_write(path, "wb") as f:
        f.write(files(__package__).joinpath(_VIEWER_PAGE).read_bytes())
    written.append(path)
    return written


def _layout(extras: dict, tiled: bool, shape: tuple[int, int]) -> dict:
    extras["layout"] = "deepzoom" if tiled else "image"
    if tiled:
        levels = pyramid_levels(shape[1], shape[0])
        extras["tiles"] = {"format": "jpg", "size": DZ_TILE_SIZE, "overlap": DZ_OVERLAP,
                           "levels": [list(level) for level in levels]}
    return extras


def export_openlime(
    folder: str | os.PathLike,
    coefficients: np.ndarray,
    rgb: np.ndarray,
    *,
    pixel_size_mm: float | None = None,
    quality: int = 95,
    encoding: Literal["srgb", "linear"] = "srgb",
    tiles: bool | Literal["auto"] = False,
    tile_threshold: int = TILE_THRESHOLD,
) -> list[Path]:
    """Write an LRGB PTM in the layout of OpenLIME's RTI layer (Relight's web format), with
    a relighting page of its own.

    Writes ``plane_0.jpg``, ``plane_1.jpg``, ``plane_2.jpg``, then ``info.json`` (so that a
    viewer never finds an ``info.json`` whose planes are missing), ``viewer.json`` and
    ``index.html``, each through :func:`ptmcore.atomic.atomic_write`. See the module docstring
    for the format. Open it in OpenLIME with ``new OpenLIME.Layer({type: 'rti', layout:
    'image', url: '…/info.json'})``, or serve the folder and open ``index.html``.

    Parameters
    ----------
    folder : str or os.PathLike
        Output folder; created with its parents if missing.
    coefficients : ndarray, shape (H, W, 6)
        a0..a5 of ``L = a0·lu² + a1·lv² + a2·lu·lv + a3·lu + a4·lv + a5`` in 0–255
        luminance units, (lu, lv) the x (right) and y (up) components of the unit light.
    rgb : ndarray, shape (H, W, 3), uint8
        The colour; the viewer renders ``rgb · L / 255``.
    pixel_size_mm : float, optional
        Size of a pixel on the object, written as ``pixelSizeInMM`` (OpenLIME's scale bar).
    quality : int
        JPEG quality, 1–100.
    encoding : {"srgb", "linear"}
        What the coefficients and colour hold (``RunOptions.ptm_encoding``): display
        (sRGB-encoded) values, or linear light,
        which ``index.html`` encodes to sRGB for display (OpenLIME itself shows them as they
        are).
    tiles : bool or "auto"
        Write DeepZoom pyramids instead of whole planes (as :func:`export_relightable`); off by
        default, which keeps this function's output as it always was.
    tile_threshold : int
        With ``tiles="auto"``, the longest side above which the planes are tiled.

    Returns
    -------
    list of Path
        The files written, in the order written: the three planes (for pyramids, each
        ``.dzi`` and its ``_files`` folder), ``info.json``, ``viewer.json``, ``index.html``.

    Raises
    ------
    InputError
        If the folder cannot be created or written to.
    ValueError
        If the arrays do not match, a coefficient is not finite, the quality is not 1–100,
        the pixel size is not a positive number or the encoding is neither sRGB nor linear.
    """
    _check_options(quality, pixel_size_mm, encoding)
    coef, col = _checked(coefficients, rgb)
    h, w = col.shape[:2]
    tiled = _tiled(tiles, (h, w), tile_threshold)
    folder = Path(folder)
    planes, scale, bias = lrgb_planes(coef, col)
    _make_folder(folder)
    written = _write_planes(folder, planes, quality, tiled)
    info: dict = {"width": int(w), "height": int(h), "format": "jpg"}
    if pixel_size_mm is not None:
        info["pixelSizeInMM"] = float(pixel_size_mm)
    info.update(
        {
            "type": "ptm",
            "colorspace": "lrgb",
            "nplanes": _NPLANES,
            "quality": int(quality),
            "materials": [{"scale": scale, "bias": bias}],
        }
    )
    extras: dict = {"encoding": encoding, "layers": {}}
    if tiled:
        _layout(extras, tiled, (h, w))
    return written + _finish(folder, info, extras)


def _checked_network(network: object, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """A neural basis' decoder as float32 layers, checked: ``(k + 2, n)``, ``(n, n)``, ``(n, 3)``
    weights and their biases, finite."""
    try:
        layers = [(np.asarray(w, np.float32), np.asarray(b, np.float32)) for w, b in network]
    except (TypeError, ValueError) as exc:
        raise ValueError(f"a neural basis needs a network of (weights, bias) layers ({exc})") from exc
    n = layers[0][0].shape[-1] if layers and layers[0][0].ndim == 2 else 0
    shapes = [(k + 2, n), (n, n), (n, 3)]
    if n < 1 or [(w.shape, b.shape) for w, b in layers] != [(s, s[1:]) for s in shapes]:
        got = [(w.shape, b.shape) for w, b in layers]
        raise ValueError(f"a neural basis needs three layers of weights {shapes} (and biases) for {k} "
                         f"planes, not {got}")
    if not all(np.isfinite(w).all() and np.isfinite(b).all() for w, b in layers):
        raise ValueError("the network is not finite everywhere")
    return layers


def _checked_basis(basis: PublishedBasis) -> tuple[np.ndarray, int]:
    """The basis' planes as an array, checked against its type, and the number of basis
    directions D (0 for LRGB and neural)."""
    if basis.type not in _RELIGHT_TYPES:
        raise ValueError(f"basis type must be one of {sorted(_RELIGHT_TYPES)}, not {basis.type!r}")
    colorspace = _RELIGHT_TYPES[basis.type][1]
    if basis.colorspace != colorspace:
        raise ValueError(f"a {basis.type} basis is in the {colorspace!r} colour space, not {basis.colorspace!r}")
    planes = np.asarray(basis.planes)
    if planes.ndim != 3 or planes.shape[2] < 1 or min(planes.shape[:2]) < 1:
        raise ValueError(f"planes must be (H, W, K) with K ≥ 1, not {planes.shape}")
    h, w, k = planes.shape
    if colorspace == "rgb":
        if k != NEURAL_PLANES:
            raise ValueError(f"a neural basis has {NEURAL_PLANES} code planes (OpenLIME's three RGB planes), not {k}")
        if not np.isfinite(planes).all():
            raise ValueError("the codes are not finite everywhere")
        _checked_network(basis.network, k)
        return planes, 0
    if colorspace == "lrgb":
        colour = None if basis.colour is None else np.asarray(basis.colour)
        if colour is None or colour.shape != (h, w, 3) or colour.dtype != np.uint8:
            got = "none" if colour is None else f"{colour.dtype} {colour.shape}"
            raise ValueError(f"an lrgb basis needs a uint8 colour of shape {(h, w, 3)}, not {got}")
        if basis.type == "ptm" and k != 6:
            raise ValueError(f"a PTM has 6 coefficient planes, not {k}")
        if basis.type == "hsh" and (basis.order not in (2, 3, 4) or k != basis.order ** 2):
            raise ValueError(f"an HSH needs an order of 2, 3 or 4 and order² planes, not order "
                             f"{basis.order!r} with {k} planes")
        return planes, 0
    vectors = None if basis.basis is None else np.asarray(basis.basis, dtype=np.float64)
    if vectors is None or vectors.ndim != 3 or vectors.shape[0] != k + 1 or vectors.shape[2] != 3:
        got = "none" if vectors is None else vectors.shape
        raise ValueError(f"an mrgb basis needs a basis of shape ({k + 1}, D, 3) for {k} planes, not {got}")
    if not np.isfinite(vectors).all():
        raise ValueError("the basis is not finite everywhere")
    d = vectors.shape[1]
    if basis.type == "rbf":
        lights = None if basis.lights is None else np.asarray(basis.lights, dtype=np.float64)
        if lights is None or lights.shape != (d, 3) or not np.isfinite(lights).all():
            raise ValueError(f"an rbf basis needs {d} finite light directions (D, 3) to match its basis")
        sigma = basis.sigma
        if sigma is None or not (math.isfinite(float(sigma)) and float(sigma) > 0):
            raise ValueError(f"an rbf basis needs a positive sigma, not {sigma!r}")
    else:
        r = basis.resolution
        if isinstance(r, bool) or not isinstance(r, (int, np.integer)) or r < 2 or r * r != d:
            raise ValueError(f"a bln basis needs a resolution R ≥ 2 with R² = D = {d} directions, not {r!r}")
    return planes, d


def export_relightable(
    folder: str | os.PathLike,
    basis: PublishedBasis,
    *,
    pixel_size_mm: float | None = None,
    quality: int = 95,
    tiles: bool | Literal["auto"] = "auto",
    tile_threshold: int = TILE_THRESHOLD,
) -> list[Path]:
    """Write a relighting basis in Relight's web format (what OpenLIME reads), with a
    relighting page of its own.

    Writes the planes (whole JPEGs, or DeepZoom pyramids for large images), then
    ``info.json``, ``viewer.json`` and ``index.html``, each file through
    :func:`ptmcore.atomic.atomic_write` and each pyramid moved into place complete. See the
    module docstring for the format: PTM and HSH of order 2 or 3, RBF, bilinear and NeuralRTI
    bases are shown by OpenLIME as by the folder's page; an HSH of order 4 (16 planes) only by
    the page, OpenLIME's HSH having 9 terms.

    Parameters
    ----------
    folder : str or os.PathLike
        Output folder; created with its parents if missing.
    basis : PublishedBasis
        The basis (its ``encoding`` goes to ``viewer.json``).
    pixel_size_mm : float, optional
        Size of a pixel on the object, written as ``pixelSizeInMM`` (OpenLIME's scale bar).
    quality : int
        JPEG quality, 1–100.
    tiles : bool or "auto"
        Write each plane as a DeepZoom pyramid; ``"auto"``: when the longer side of the image
        exceeds ``tile_threshold``.
    tile_threshold : int
        Pixels; :data:`TILE_THRESHOLD` by default.

    Returns
    -------
    list of Path
        What was written, in order: the planes (``plane_i.jpg``, or ``plane_i.dzi`` and the
        folder ``plane_i_files``; i from 0, from 1 for NeuralRTI), ``info.json``,
        ``viewer.json``, ``index.html``.

    Raises
    ------
    InputError
        If the folder cannot be created or written to.
    ValueError
        If the basis is not consistent (shapes, type and colour space, missing attributes of
        its type), a value is not finite, or an option is out of range.
    """
    _check_options(quality, pixel_size_mm, basis.encoding)
    planes, _ = _checked_basis(basis)
    h, w, k = planes.shape
    tiled = _tiled(tiles, (h, w), tile_threshold)
    info: dict = {"width": int(w), "height": int(h), "format": "jpg"}
    if pixel_size_mm is not None:
        info["pixelSizeInMM"] = float(pixel_size_mm)
    if basis.type == "neural":
        images, more = _neural_planes(planes, basis.network, quality)
    else:
        images, more = _relight_planes(basis, planes, quality)
    info.update(more)
    extras: dict = {"encoding": basis.encoding, "layers": {}, "basis": basis.name or basis.type, "terms": int(k)}
    if basis.type == "hsh":
        extras["order"] = int(basis.order)
    _layout(extras, tiled, (h, w))
    folder = Path(folder)
    _make_folder(folder)
    first = 1 if basis.type == "neural" else 0  # OpenLIME names NeuralRTI's planes from 1
    return _write_planes(folder, images, quality, tiled, first) + _finish(folder, info, extras)


def _relight_planes(basis: PublishedBasis, planes: np.ndarray, quality: int) -> tuple[list[np.ndarray], dict]:
    """A linear basis' JPEG images and its ``info.json`` keys after the image's, in Relight's
    format (module docstring)."""
    k = planes.shape[2]
    relight_type, colorspace = _RELIGHT_TYPES[basis.type]
    channels = 3 * -(-k // 3)  # OpenLIME's uniforms hold whole vec3s: K rounded up to planes of 3
    images, scale, bias = _quantised_planes(planes, channels)
    info: dict = {"type": relight_type}
    if basis.type == "bln":
        info["resolution"] = int(basis.resolution)
    info["colorspace"] = colorspace
    if basis.type == "rbf":
        info["sigma"] = float(basis.sigma)
        info["lights"] = np.asarray(basis.lights, dtype=np.float64).ravel().tolist()
    material: dict = {}
    if colorspace == "lrgb":
        images.insert(0, np.ascontiguousarray(basis.colour))
        scale, bias = [1.0, 1.0, 1.0] + scale, [0.0, 0.0, 0.0] + bias
        info["nplanes"] = 3 + channels
        info["quality"] = int(quality)
    else:
        info["nplanes"] = channels
        info["quality"] = int(quality)
        info["basis"], material["range"] = _basis_bytes(np.asarray(basis.basis, dtype=np.float64), channels)
    material.update({"scale": scale, "bias": bias})
    info["materials"] = [material]
    return images, info


def _float32_list(values: np.ndarray) -> list[float]:
    """Numbers for JSON, each the shortest decimal that reads back as the same float32 (NumPy's
    ``str`` of a float32): a third of the digits of the float64 it widens to, and exact."""
    return [float(str(v)) for v in np.asarray(values, np.float32).ravel()]


def _neural_network(layers: list[tuple[np.ndarray, np.ndarray]]) -> tuple[list[list[float]], list[list[float]]]:
    """The decoder's ``weights`` and ``biases`` as ShaderNeural reads them (module docstring):
    each matrix outputs × inputs, row-major, the hidden width and the inputs padded with zeros
    to multiples of 4."""
    n4 = 4 * -(-layers[1][0].shape[0] // 4)
    inputs = [4 * -(-layers[0][0].shape[0] // 4), n4, n4]
    outputs = [n4, n4, 3]
    weights, biases = [], []
    for (w, b), rows, cols in zip(layers, outputs, inputs):
        matrix = np.zeros((rows, cols), np.float32)
        matrix[: w.shape[1], : w.shape[0]] = w.T  # ours are (inputs, outputs)
        vector = np.zeros(rows, np.float32)
        vector[: b.size] = b
        weights.append(_float32_list(matrix))
        biases.append(_float32_list(vector))
    return weights, biases


def _neural_planes(codes: np.ndarray, network: object, quality: int) -> tuple[list[np.ndarray], dict]:
    """A NeuralRTI basis' three JPEG images of codes and its ``info.json`` keys after the
    image's, in OpenLIME's format (module docstring)."""
    from ptmcore.neural import quantize_codes

    layers = _checked_network(network, codes.shape[2])
    quantised, low, high = quantize_codes(codes)
    images = [np.ascontiguousarray(quantised[..., j : j + 3]) for j in range(0, NEURAL_PLANES, 3)]
    weights, biases = _neural_network(layers)
    info = {"type": "neural", "colorspace": "rgb", "planes": NEURAL_PLANES, "samples": int(layers[1][0].shape[0]),
            "quality": int(quality), "min": _float32_list(low), "max": _float32_list(high),
            "weights": weights, "biases": biases}
    return images, info


def _write_viewer_json(folder: Path, extras: dict) -> Path:
    path = folder / "viewer.json"
    with atomic_write(path, "w") as f:
        f.write(json.dumps(extras, indent=1) + "\n")
    return path


def export_web_layers(
    folder: str | os.PathLike,
    *,
    normals: np.ndarray | None = None,
    height: np.ndarray | None = None,
    unit: str = "pixel",
    max_side: int = LAYER_SIDE,
) -> list[Path]:
    """Add the normal map and the height map as layers of the page :func:`export_openlime` wrote.

    Each map is subsampled (every s-th row and column, s the smallest step bringing the longer
    side to ``max_side``: only those rows are read, nothing full-size is computed) and written
    as an 8-bit PNG; ``viewer.json`` is rewritten last to list them, so the page never asks for
    a missing file.

    * ``normals.png`` — OpenGL-style: ``round((n + 1) · 127.5)`` for (R, G, B) = (x, y up, z);
      a NaN normal is black.
    * ``height.png`` — the height quantised to 16 bits over the subsample's range, high byte in
      R and low byte in G, B = 255 on the object and 0 where the height is NaN (outside the
      mask); ``viewer.json`` gives the range (``min``, ``max``) and ``unit``. PNG, not JPEG:
      the bytes are data.

    Parameters
    ----------
    folder : str or os.PathLike
        The folder of :func:`export_openlime` (its ``viewer.json`` is updated).
    normals : ndarray, shape (H, W, 3), optional
        Unit normals, x right, y up, z towards the camera.
    height : ndarray, shape (H, W), optional
        Heights, NaN outside the object.
    unit : str
        The heights' unit, shown by the page (``mm`` or ``pixel``).
    max_side : int
        Longest side of the layers, pixels.

    Returns
    -------
    list of Path
        The files written: the layers' images, then ``viewer.json``.

    Raises
    ------
    ValueError
        If a map's shape is wrong or ``max_side`` is not positive.
    FileNotFoundError
        If the folder has no ``viewer.json`` (:func:`export_openlime` not called first).
    """
    if max_side < 1:
        raise ValueError(f"max_side must be positive, not {max_side}")
    folder = Path(folder)
    extras = json.loads((folder / "viewer.json").read_text())
    written = []
    if normals is not None:
        if np.ndim(normals) != 3 or np.shape(normals)[2] != 3:
            raise ValueError(f"normals must be (H, W, 3), not {np.shape(normals)}")
        image = normal_colors(thin(normals, max_side)[0])
        write_png(folder / "normals.png", image)
        written.append(folder / "normals.png")
        extras["layers"]["normals"] = {"src": "normals.png", "width": image.shape[1], "height": image.shape[0]}
    if height is not None:
        if np.ndim(height) != 2:
            raise ValueError(f"height must be (H, W), not {np.shape(height)}")
        small = np.ascontiguousarray(thin(height, max_side)[0], dtype=np.float32)
        inside = np.isfinite(small)
        lo, hi = (float(np.nanmin(small)), float(np.nanmax(small))) if inside.any() else (0.0, 0.0)
        step = np.float32(65535.0 / (hi - lo)) if hi > lo else np.float32(0.0)
        code = np.rint((small - np.float32(lo)) * step)
        code[~inside] = 0
        image = np.empty(small.shape + (3,), np.uint8)
        # Little-endian uint16 viewed as bytes: (low, high); high byte to R, low to G.
        pairs = code.astype("<u2").view(np.uint8).reshape(small.shape + (2,))
        image[..., 0], image[..., 1] = pairs[..., 1], pairs[..., 0]
        image[..., 2] = inside * np.uint8(255)
        write_png(folder / "height.png", image)
        written.append(folder / "height.png")
        extras["layers"]["height"] = {"src": "height.png", "width": image.shape[1], "height": image.shape[0],
                                      "min": lo, "max": hi, "unit": unit}
    written.append(_write_viewer_json(folder, extras))
    return written
