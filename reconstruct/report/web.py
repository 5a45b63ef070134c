"""Export of an LRGB PTM for the OpenLIME web viewer (its ``rti`` layer, "relight" format).

The layout is the one written by Relight (``relight-cli``/RelightLab, cnr-isti-vclab/relight)
for a PTM with the ``lrgb`` colour space and read by OpenLIME (cnr-isti-vclab/openlime)
``LayerRTI`` + ``ShaderRTI``; it was taken from their sources, not guessed:

* ``info.json`` — ``width``, ``height``, ``format: "jpg"`` (the planes' file suffix),
  ``type: "ptm"``, ``colorspace: "lrgb"``, ``nplanes: 9``, ``quality``, ``pixelSizeInMM``
  (only when known) and ``materials: [{"scale": [9 numbers], "bias": [9 numbers]}]``.
  ``nplanes`` counts the colour planes too: the viewer loads ``ceil(nplanes / 3)`` images
  named ``plane_0.jpg``, ``plane_1.jpg``, … (Relight ``convert_rti.cpp`` sets 9 for an
  LRGB ``.ptm``; its builder accepts only 6 or 9 for LRGB PTMs). ``quality`` is not read by
  OpenLIME but Relight's converter back to ``.ptm`` takes its JPEG quality from it.
* ``plane_0.jpg`` — the base colour, scale 1 and bias 0.
* ``plane_1.jpg`` — the constant and linear terms in the channels (R, G, B) = (1, x, y), i.e.
  (a5, a3, a4) of ``L = a0·lu² + a1·lv² + a2·lu·lv + a3·lu + a4·lv + a5``.
* ``plane_2.jpg`` — the quadratic terms (R, G, B) = (x², xy, y²), i.e. (a0, a2, a1). (Relight
  ``legacy_rti.cpp``: "lrgb ptm order is x^2, y^2, xy, x, y, 1, r, g, b while we use r, g, b,
  1, x, y, x2 xy y2".)

``scale`` and ``bias`` hold one entry per channel in plane order (plane_0 R, G, B, plane_1
R, G, B, plane_2 R, G, B): the shader's uniforms ``vec3 scale[]``/``bias[]`` indexed by plane.
The viewer samples a channel as ``c = byte / 255`` and dequantises it as
``value = (c − bias) · scale``. For the LRGB PTM it computes per pixel (``ShaderRTI`` class
``LRGB.render`` with ``PTM.lightWeights``)::

    l     = Σ_k w_k · value_k,  w = (1, x, y, x², x·y, y²) over plane_1 then plane_2
    color = l · basecolor,      basecolor = (plane_0 − bias) · scale = rgb / 255

with (x, y) the first two components of the unit light vector (``ShaderRTI.setLight`` maps
a point of the square to the disk and sets z = √(1 − x² − y²)); the light pad's y grows
upwards (``Controller2D.project``), the frame used here. ``color`` is written to the 8-bit
framebuffer, which clips it to 0–1. For this to equal RTIViewer's ``rgb · L / 255`` (L in
0–255 luminance units, see :mod:`ptmcore.relight`), each value is the coefficient in 0–1
luminance units, ``a / 255`` — the units Relight's builder uses, whose scales are the
coefficient range divided by 255 (``RtiBuilder::finalizeMaterial``).

Quantisation: each coefficient channel is mapped linearly onto 0–255 over its full range
[m, M] of a/255: ``scale = M − m``, ``bias = −m / scale`` and
``byte = round((value − m) / scale · 255)``, so ``value = (byte/255 − bias) · scale`` is within
half a step, ``scale / 510``, before JPEG compression. (Relight takes a quantile of the
range instead, clipping outliers; the full range never clips.)

The JPEGs are written in the RGB colour space without chroma subsampling (Pillow's
``keep_rgb``, ``subsampling=0``), as Relight writes LRGB planes (``JCS_RGB``): a YCbCr
transform would spread each coefficient's compression error over the other two channels of
its plane. Rows are in image order (row 0 at the top), as the viewer displays them. The planes
and the layers below are data, so they carry no colour tag (no ICC profile, no PNG ``sRGB``
chunk, unlike the images for people, :mod:`ptmcore.colourtags`); the page uploads them with
``UNPACK_COLORSPACE_CONVERSION_WEBGL`` off.

Beside these, the folder gets its own viewer, so that it can be published as it is:

* ``index.html`` — a relighting page in plain WebGL, no library (the package's
  ``webviewer.html``, copied): it renders the planes as OpenLIME's shader does, the mouse (or a
  hemisphere widget, or the arrow keys) moving the light; wheel zoom and pan; the light and layer
  in the address (``#light=x,y&layer=relit|normals|height``), so a link shows what its sender saw.
* ``viewer.json`` — what the page needs beyond ``info.json``: ``encoding`` (``"srgb"``, or
  ``"linear"`` for a PTM of linear light, which the page encodes to sRGB for display) and
  ``layers``, the optional normal-map and height-map images :func:`export_web_layers` adds.
"""

from __future__ import annotations

import io
import json
import math
import os
from concurrent.futures import ThreadPoolExecutor
from importlib.resources import files
from pathlib import Path
from typing import Literal

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from ptmcore.png import write_png
from reconstruct.report.figures import normal_colors, thin

__all__ = ["LAYER_SIDE", "PLANE_TERMS", "export_openlime", "export_web_layers", "lrgb_planes"]

#: Coefficient index (a0..a5) in each channel of plane_1 and plane_2: (1, x, y) and (x², xy, y²).
PLANE_TERMS = ((5, 3, 4), (0, 2, 1))

# Number of planes, counting the colour planes, as OpenLIME and Relight count them.
_NPLANES = 9

#: Longest side of the normal-map and height-map layers, pixels: sharp on a screen at the
#: whole object's view, and 12 MB of decoded textures at most (the relit planes stay full size).
LAYER_SIDE = 2048

# The page, in the package: see the module docstring.
_VIEWER_PAGE = "webviewer.html"


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


def export_openlime(
    folder: str | os.PathLike,
    coefficients: np.ndarray,
    rgb: np.ndarray,
    *,
    pixel_size_mm: float | None = None,
    quality: int = 95,
    encoding: Literal["srgb", "linear"] = "srgb",
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

    Returns
    -------
    list of Path
        The files written, in the order written: the three planes, ``info.json``,
        ``viewer.json``, ``index.html``.

    Raises
    ------
    InputError
        If the folder cannot be created or written to.
    ValueError
        If the arrays do not match, a coefficient is not finite, the quality is not 1–100,
        the pixel size is not a positive number or the encoding is neither sRGB nor linear.
    """
    if encoding not in ("srgb", "linear"):
        raise ValueError(f"encoding must be 'srgb' or 'linear', not {encoding!r}")
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 1 <= quality <= 100:
        raise ValueError(f"JPEG quality must be an integer from 1 to 100, not {quality!r}")
    if pixel_size_mm is not None and not (math.isfinite(float(pixel_size_mm)) and float(pixel_size_mm) > 0):
        raise ValueError(f"pixel size must be a positive number of millimetres, not {pixel_size_mm!r}")
    coef, col = _checked(coefficients, rgb)
    h, w = col.shape[:2]
    folder = Path(folder)
    written = []
    with ThreadPoolExecutor(max_workers=-(-_NPLANES // 3)) as pool:
        # The colour plane needs no quantising: its JPEG is encoded while the coefficient planes
        # are computed, and each plane is written while the ones after it are still encoding.
        jobs = [pool.submit(_encode_jpeg, np.ascontiguousarray(col), int(quality))]
        try:
            planes, scale, bias = lrgb_planes(coef, col)
            jobs += [pool.submit(_encode_jpeg, plane, int(quality)) for plane in planes[1:]]
            _make_folder(folder)
            for i, job in enumerate(jobs):
                data = job.result()
                path = folder / f"plane_{i}.jpg"
                with atomic_write(path, "wb") as f:
                    f.write(data)
                written.append(path)
        finally:
            for job in jobs:  # after an error: nothing more is written, so nothing more is encoded
                job.cancel()

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
    path = folder / "info.json"
    with atomic_write(path, "w") as f:
        f.write(json.dumps(info, indent=1) + "\n")
    written.append(path)
    written.append(_write_viewer_json(folder, {"encoding": encoding, "layers": {}}))
    path = folder / "index.html"
    with atomic_write(path, "wb") as f:
        f.write(files(__package__).joinpath(_VIEWER_PAGE).read_bytes())
    written.append(path)
    return written


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
