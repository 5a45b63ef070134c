"""Light that is not the lamps' own, and lamps that do not light the frame evenly (issue 37).

Photometric stereo and RTI take every photograph to hold the light of one distant lamp of the
same strength everywhere in the frame. Two common departures bend the normals and the height map
without any error to show for it:

* **Room light** (a window, a monitor, the ceiling lights left on) is added to every photograph.
  It fills the shadows and flattens the normals: 10 % of ambient light raised a synthetic
  tablet's mean normal error from 0.35° to 1.94°. An **ambient frame** (a photograph with the
  lamps off, as RTI guides ask for) is subtracted in linear light (:func:`read_ambient`,
  :func:`check_ambient`, :func:`subtract_ambient`); without one, :func:`estimate_stray_light`
  measures the raised floor in the object's attached shadows and says so.
* **Uneven lamps** (a lamp's cone, the lens's vignetting, the inverse-square fall-off of a
  hand-held flash the ``.lp`` takes as distant) multiply each photograph by a smooth gain that
  differs from light to light. A **flat-field capture** (a flat white or grey board under the same
  lights) measures it (:func:`load_flat_field`, :class:`FlatField`); a **grey card** seen in every
  photograph measures at least each lamp's strength (:func:`reference_intensities`).

All of it works in linear light: 8-bit photographs are sRGB-decoded, 16-bit ones divided by
65535, float ones (:func:`ptmcore.images.read_image` after an ICC conversion) taken as they are.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.polynomial import legendre

from .decoders import image_size
from .errors import InputError, first_few
from .images import LUMA_WEIGHTS, ImageStack, read_image
from .raw import RAW_SUFFIXES, RawDevelopment

__all__ = [
    "FlatField",
    "StrayLight",
    "check_ambient",
    "estimate_stray_light",
    "load_flat_field",
    "measure_region",
    "parse_region",
    "read_ambient",
    "reference_intensities",
    "subtract_ambient",
]

# --- ambient frame -------------------------------------------------------------------------

#: Photographs compared with the ambient frame (evenly spread over the capture; read reduced).
_COMPARED = 8
#: Thumbnails are read with their shorter side at least this long (JPEG: libjpeg's DCT scaling,
#: a fraction of a full decode); a frame's mean brightness needs no more.
_THUMB_SIDE = 64
#: An ambient frame is refused when its mean linear luminance exceeds the dimmest compared
#: photograph's by more than this share plus :data:`_AMBIENT_SLACK`. Every photograph is the
#: room's light plus a lamp's, so the ambient frame can be at most as bright as the dimmest one;
#: the share allows for exposure flicker between frames and for the thumbnails' means, which
#: for 8-bit photographs are averaged in sRGB before decoding and so read a little low
#: (Jensen's inequality: up to 2.4 % on a synthetic tablet's JPEG at 1/4 scale).
_AMBIENT_MARGIN = 0.10
#: … and this much linear luminance: the noise floor of a dark 8-bit frame (sRGB code 5).
_AMBIENT_SLACK = 0.0015
#: Rows converted to float at a time: a 24-megapixel TIFF read whole is not also held as
#: float32 RGB.
_BAND_ROWS = 256


def to_linear_rgb(img: np.ndarray) -> np.ndarray:
    """A photograph as :func:`~ptmcore.images.read_image` returns it (uint8 sRGB, uint16 linear,
    float linear; grey or RGB) as a new float32 ``(H, W, 3)`` array of linear light
    (:func:`ptmcore.corrections.to_linear_rgb`, which the decoding pass uses too)."""
    # Imported here: corrections applies this module's ambient frame.
    from .corrections import to_linear_rgb as convert

    return convert(img)


def _luminance(img: np.ndarray) -> np.ndarray:
    """Linear luminance ``(H, W)`` float32 of a photograph as read, converted band by band."""
    out = np.empty(img.shape[:2], np.float32)
    for r0 in range(0, img.shape[0], _BAND_ROWS):
        band = to_linear_rgb(img[r0:r0 + _BAND_ROWS])
        out[r0:r0 + _BAND_ROWS] = band[:, :, 0] if img.ndim == 2 else band @ LUMA_WEIGHTS
    return out


def _size_text(shape: Sequence[int]) -> str:
    return f"{shape[1]}×{shape[0]}"


def _check_size(path: Path, shape: tuple[int, int], what: str, theirs: str = "the photographs") -> None:
    """Refuse a file whose header gives another size than ``shape`` (H, W), before decoding it."""
    size = image_size(path)
    if size is not None and (int(size[1]), int(size[0])) != tuple(shape):
        raise InputError(f"{what} is {size[0]}×{size[1]} pixels but {theirs} are {_size_text(shape)}", path)


def read_ambient(path: str | os.PathLike, shape: tuple[int, int], *, raw: RawDevelopment | None = None) -> np.ndarray:
    """The ambient frame (the room's light alone) as linear light.

    Parameters
    ----------
    path : str or PathLike
        A photograph of the object with the lamps off: same camera, exposure and framing.
    shape : tuple of int
        ``(H, W)`` of the capture's photographs.

    Returns
    -------
    ndarray, shape (H, W, 3), float32
        Linear light: 8-bit sRGB decoded, 16-bit ÷ 65535, float as it is, grey repeated into
        three channels.

    Raises
    ------
    InputError
        If it cannot be read, or is not of the photographs' size (naming both sizes).
    """
    path = Path(path)
    _check_size(path, shape, "the ambient frame")
    img = read_image(path, raw=raw)
    if img.shape[:2] != tuple(shape):
        raise InputError(f"the ambient frame is {_size_text(img.shape)} pixels but the photographs are "
                         f"{_size_text(shape)}", path)
    return to_linear_rgb(img)


def _resize(img: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``img`` averaged down (or up) to ``shape`` (H, W)."""
    import cv2

    return cv2.resize(img, (shape[1], shape[0]), interpolation=cv2.INTER_AREA)


def check_ambient(ambient: np.ndarray, photographs: Sequence[str | os.PathLike], path: str | os.PathLike, *,
                  raw: RawDevelopment | None = None) -> None:
    """Refuse an ambient frame brighter than the photographs.

    Every photograph holds the room's light plus its lamp's, so the ambient frame is at most as
    bright as the dimmest photograph, pixel by pixel and so on average. The mean linear
    luminance of the frame is compared with that of up to :data:`_COMPARED` photographs spread
    evenly over the capture, read as thumbnails (cheap); it may exceed the dimmest of them by
    :data:`_AMBIENT_MARGIN` (10 %) plus :data:`_AMBIENT_SLACK` (exposure flicker, the
    thumbnails' averaging, noise). A frame brighter than that is a photograph with a lamp on
    (or a longer exposure), and subtracting it would blacken most of the capture.

    Parameters
    ----------
    ambient : ndarray, shape (H, W, 3), float32
        From :func:`read_ambient`.
    photographs : sequence of path
        The capture's photographs, in order.
    path : str or PathLike
        The ambient frame's file, for the message.

    Raises
    ------
    InputError
        Naming the ambient frame, its level and the dimmest photograph's.
    """
    if not len(photographs):
        return
    picks = np.unique(np.linspace(0, len(photographs) - 1, min(_COMPARED, len(photographs))).round().astype(int))
    side = max(1, min(_THUMB_SIDE, min(ambient.shape[:2])))
    own_map = ambient @ LUMA_WEIGHTS
    levels = []
    for k in picks:
        lum = _luminance(read_image(photographs[k], min_side=side, raw=raw))
        levels.append(float(lum.mean()))
        # Pixel by pixel too: a photograph with a lamp on, given by mistake, is no brighter on
        # average than the dimmest photograph when it is that photograph or its neighbour, but it
        # is brighter than the photographs lit from the other side over much of the frame, or
        # as bright as its own photograph nearly everywhere. Noise and JPEG rounding allowed for.
        small = own_map if lum.shape == own_map.shape else _resize(own_map, lum.shape)
        brighter = float(np.mean(small > lum * 1.05 + 0.01))
        same = float(np.mean(small >= lum * 0.95 - 0.005))
        if brighter > 0.25 or same > 0.9:
            raise InputError(f"the ambient frame is brighter than the photographs ({'as bright as' if same > 0.9 else 'brighter than'} "
                             f"{Path(photographs[k]).name} over {max(brighter, same):.0%} of the frame): is it a "
                             "photograph with a lamp on? It must be the room's light alone (lamps off, same "
                             "exposure)", path)
    dimmest = int(np.argmin(levels))
    own = float(own_map.mean())
    if own > (1 + _AMBIENT_MARGIN) * levels[dimmest] + _AMBIENT_SLACK:
        raise InputError(f"the ambient frame (mean linear luminance {own:.4g}) is brighter than the photographs "
                         f"(the dimmest of {len(picks)} compared, {Path(photographs[picks[dimmest]]).name}: "
                         f"{levels[dimmest]:.4g}): is it a photograph with the lamps on?", path)


def subtract_ambient(img: np.ndarray, ambient: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
    """Subtract the ambient frame from a photograph in linear light, in place, clipped at 0.

    Parameters
    ----------
    img : ndarray, shape (R, W, 3), float32
        A decoded photograph (or a band of its rows) converted to linear light.
    ambient : ndarray, shape (H, W, 3), float32
        From :func:`read_ambient`.
    rows : slice
        The rows of the frame ``img`` holds (default: all of them).

    Returns
    -------
    ndarray
        ``img`` itself.
    """
    part = ambient[rows]
    if img.shape != part.shape:
        raise ValueError(f"a photograph band of shape {img.shape} against ambient rows of shape {part.shape}")
    np.subtract(img, part, out=img)
    # Noise makes some shadow samples darker than the ambient frame; negative light is none.
    np.maximum(img, 0, out=img)
    return img


# --- flat field ----------------------------------------------------------------------------

#: Image files a board capture may hold (when it has no ``.lp``).
_IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", *sorted(RAW_SUFFIXES))
#: The board's photographs are reduced to block means on a grid at most this long: a smooth
#: gain needs no more, and ~12,000 blocks keep the robust fit to a few milliseconds a light.
_GRID_SIDE = 128
#: Total degree of the polynomial in log-gain. A Gaussian lamp spot is exactly quadratic in
#: log, cos⁴ vignetting and inverse-square fall-off nearly so. Measured (benchmarks/illumination.py:
#: 640×480 board under 48 lamps, cos⁴ vignetting × a spot on a floor × inverse-square fall-off,
#: a label and dust; largest gain error over the frame, 16-bit / 8-bit JPEG board): degree 2:
#: 11.7 / 11.9 %, 3: 4.7 / 4.6 %, 4: 0.63 / 1.7 %, 5: 1.0 / 2.9 %, 6: 1.1 / 3.0 % (higher degrees
#: bend at the corners, where the grid has the fewest blocks to hold them).
FLAT_DEGREE = 4
#: Blocks darker than this (linear) are left out: no log, and the board's surround or a hole.
_BLOCK_DARK = 1e-4
#: Robust fit: Huber's then Tukey's weights on residuals of log brightness, scale 1.4826 ×
#: median |residual| but not below the floor (a clean board's residuals are noise of a
#: fraction of a per cent; a smaller scale would trim its noise).
_HUBER_K = 1.345
_TUKEY_C = 4.685
_MIN_LOG_SCALE = 0.003
_HUBER_ROUNDS = 6
_TUKEY_ROUNDS = 12
#: Points across the frame where :meth:`FlatField.describe` evaluates the gains.
_DESCRIBE_POINTS = 33


def _legendre_rows(t: np.ndarray, degree: int) -> np.ndarray:
    """Legendre polynomials P_0…P_degree at ``t`` in [-1, 1]: better conditioned than powers."""
    return legendre.legvander(np.asarray(t, dtype=np.float64), degree)


def _terms(degree: int) -> list[tuple[int, int]]:
    """(i, j) of the terms P_i(u) P_j(v) of total degree ≤ ``degree``."""
    return [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]


def _design(u: np.ndarray, v: np.ndarray, degree: int) -> np.ndarray:
    pu, pv = _legendre_rows(u, degree), _legendre_rows(v, degree)
    return np.stack([pu[:, i] * pv[:, j] for i, j in _terms(degree)], axis=1)


def _robust_fit(a: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Coefficients of ``y ≈ a @ c`` by IRLS: least squares, then Huber, then Tukey weights.

    Huber's weights first, since from the plain least-squares start a large label can pull the
    fit far enough that Tukey's (which give up on anything far) would keep the wrong side;
    Huber's loss is convex, so its fit does not depend on the start. Tukey's then give dust,
    labels and clipped highlights no weight at all.

    Returns
    -------
    coefficients : ndarray
    scale : float
        The residuals' robust scale (log units: relative).
    rejected : float
        Share of the points given no weight by the last round.
    """
    w = np.ones(len(y))
    c = np.zeros(a.shape[1])
    scale = _MIN_LOG_SCALE
    for rnd in range(_HUBER_ROUNDS + _TUKEY_ROUNDS):
        aw = a * w[:, None]
        new = np.linalg.solve(aw.T @ a + 1e-12 * np.eye(a.shape[1]), aw.T @ y)
        done = rnd > _HUBER_ROUNDS and np.max(np.abs(new - c)) < 1e-7
        c = new
        r = y - a @ c
        scale = max(1.4826 * float(np.median(np.abs(r))), _MIN_LOG_SCALE)
        x = np.abs(r) / scale
        if rnd < _HUBER_ROUNDS:
            w = np.minimum(1.0, _HUBER_K / np.maximum(x, 1e-12))
        else:
            w = np.clip(1 - (x / _TUKEY_C) ** 2, 0, None) ** 2
        if done:
            break
    return c, scale, float(np.mean(w == 0))


@dataclass
class FlatField:
    """Each light's gain over the frame, measured on a flat board (:func:`load_flat_field`).

    The board, flat, facing the camera and of one reflectance ρ, photographed under light k
    reads ``B_k(x) = ρ · l_k,z · g_k(x)``: its gain ``g_k`` is everything that makes the lamp's
    light at ``x`` differ from a distant lamp of unit strength — the lamp's cone, the lens's
    vignetting, the inverse-square fall-off of a near lamp, and the lamp's strength relative
    to the others. ``log g_k`` is a polynomial of total degree :attr:`degree` in Legendre
    polynomials of ``u = 2 (col + ½) / W − 1`` and ``v = 2 (row + ½) / H − 1``, scaled by one
    constant so that the median over the lights of ``g_k`` at the frame's centre is 1. Dividing
    photograph k by ``g_k`` corrects both the pattern over the frame and the lamps' strengths.

    What it cannot correct: the board shows the lamps' light in the board's plane, not at the
    object's depth (a near lamp's fall-off differs over a tall object's height); a near lamp also
    changes direction across the frame, which a gain cannot undo (use the near-light model,
    :mod:`ptmcore.nearlight`); the object's cast shadows and inter-reflections are its own. A
    board tilted by ``t`` from the camera's axis scales light k by ``n_b · l_k / l_k,z``, an
    error in the lamps' relative strengths of up to ``tan t · |l_k,xy| / l_k,z``. The gain is
    one for the three channels: a lamp whose colour changes over its cone is corrected in
    luminance only.

    Attributes
    ----------
    shape : tuple of int
        ``(H, W)`` of the photographs.
    degree : int
        Total degree of the polynomial in log-gain.
    coefficients : ndarray, shape (N, T), float64
        Per light, the coefficients of the terms ``P_i(u) P_j(v)`` in the order of
        :attr:`terms`.
    names : list of str
        The board photograph matched with each of the capture's photographs.
    matched_by : {"name", "order"}
        How the board's photographs were matched with the capture's.
    residual : ndarray, shape (N,), float64
        Robust scale of each fit's residuals, relative (log units): the board's noise and
        texture the smooth gain leaves.
    rejected : ndarray, shape (N,), float64
        Share of each board photograph's blocks the robust fit gave no weight (dust, a label,
        the board's edge, clipped highlights).
    """

    shape: tuple[int, int]
    degree: int
    coefficients: np.ndarray
    names: list[str] = field(default_factory=list)
    matched_by: str = "order"
    residual: np.ndarray | None = None
    rejected: np.ndarray | None = None

    @property
    def terms(self) -> list[tuple[int, int]]:
        """(i, j) of each coefficient's term ``P_i(u) P_j(v)``."""
        return _terms(self.degree)

    def __len__(self) -> int:
        return len(self.coefficients)

    def _matrix(self, k: int) -> np.ndarray:
        m = np.zeros((self.degree + 1, self.degree + 1))
        for (i, j), c in zip(self.terms, self.coefficients[k]):
            m[j, i] = c
        return m

    def _log_gain(self, k: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """log g_k on the grid ``rows × cols`` (pixel coordinates, may be fractional)."""
        h, w = self.shape
        pv = _legendre_rows(2 * (rows + 0.5) / h - 1, self.degree)
        pu = _legendre_rows(2 * (cols + 0.5) / w - 1, self.degree)
        # Separable: (rows, d+1) @ (d+1, d+1) @ (d+1, cols), O(rows · cols · d), no per-pixel terms.
        return pv @ self._matrix(k) @ pu.T

    def gain_rows(self, k: int, r0: int, r1: int) -> np.ndarray:
        """The gain of light ``k`` on rows ``r0:r1`` of the frame, at full resolution.

        Returns
        -------
        ndarray, shape (r1 - r0, W), float32
            Divide photograph ``k``'s linear light (each channel) by it.
        """
        h, w = self.shape
        if not 0 <= r0 <= r1 <= h:
            raise ValueError(f"rows {r0}:{r1} outside a frame of {h} rows")
        return np.exp(self._log_gain(k, np.arange(r0, r1, dtype=np.float64),
                                     np.arange(w, dtype=np.float64))).astype(np.float32)

    def gains_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Every light's gain on the grid ``rows × cols``: ``(N, len(rows), len(cols))`` float64."""
        rows = np.asarray(rows, dtype=np.float64)
        cols = np.asarray(cols, dtype=np.float64)
        return np.exp(np.stack([self._log_gain(k, rows, cols) for k in range(len(self))]))

    def describe(self) -> dict:
        """What the flat field found, for the report.

        Returns
        -------
        dict
            ``lights``, ``degree``, ``matched_by``; per light ``min_gain``, ``max_gain``,
            ``centre_gain`` (its strength relative to the median lamp) and ``corner_darkening``
            (1 − the mean gain at the four corners / the gain at the centre); ``spread`` (the
            median over lights of max/min gain over the frame), ``worst_corner_darkening``,
            ``intensity_range`` (the strongest lamp's centre gain / the weakest's), the
            robust fits' ``residual`` and ``rejected`` (medians) and ``summary``, a sentence.
        """
        h, w = self.shape
        rows = np.linspace(-0.5, h - 0.5, _DESCRIBE_POINTS)
        cols = np.linspace(-0.5, w - 0.5, _DESCRIBE_POINTS)
        g = self.gains_at(rows, cols)
        centre = np.exp(np.stack([self._log_gain(k, np.array([(h - 1) / 2]), np.array([(w - 1) / 2]))[0, 0]
                                  for k in range(len(self))]))
        corners = g[:, [0, 0, -1, -1], [0, -1, 0, -1]].mean(axis=1)
        darkening = 1 - corners / centre
        lo, hi = g.min(axis=(1, 2)), g.max(axis=(1, 2))
        worst = float(darkening.max())
        spread = float(np.median(hi / lo))
        if worst >= 0.02:
            summary = (f"lamps light the frame unevenly: up to {100 * worst:.0f} % darker at the corners than at "
                       f"the centre (median max/min over the frame {spread:.2f})")
        else:
            summary = f"lamps light the frame evenly (median max/min over the frame {spread:.2f})"
        summary += f"; lamp strengths differ {float(centre.max() / centre.min()):.2f}-fold"
        return {
            "lights": len(self),
            "degree": self.degree,
            "matched_by": self.matched_by,
            "min_gain": [round(float(v), 4) for v in lo],
            "max_gain": [round(float(v), 4) for v in hi],
            "centre_gain": [round(float(v), 4) for v in centre],
            "corner_darkening": [round(float(v), 4) for v in darkening],
            "spread": round(spread, 4),
            "worst_corner_darkening": round(worst, 4),
            "intensity_range": round(float(centre.max() / centre.min()), 4),
            "residual": None if self.residual is None else round(float(np.median(self.residual)), 5),
            "rejected": None if self.rejected is None else round(float(np.median(self.rejected)), 4),
            "summary": summary,
        }


def _board_files(folder: Path) -> tuple[list[Path], Path | None]:
    """The board capture's photographs: its ``.lp``'s, else its image files, sorted by name."""
    from .lp import read_lp

    if not folder.is_dir():
        raise InputError("flat-field folder not found" if not folder.exists() else "is not a folder", folder)
    lps = sorted(p for p in folder.iterdir() if p.suffix.lower() == ".lp" and p.is_file())
    if len(lps) > 1:
        raise InputError(f"the flat-field folder holds several light files ({first_few([p.name for p in lps])}); "
                         "keep one", folder)
    if lps:
        return list(read_lp(lps[0]).paths), lps[0]
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES and p.is_file()),
                   key=lambda p: p.name)
    return files, None


def _match(files: list[Path], capture_names: Sequence[str]) -> tuple[list[Path], str]:
    """The board photograph of each capture photograph: by name (the stem, ignoring case and
    extension: the board may be TIFF where the capture is JPEG) when every capture name has
    exactly one board photograph of its name, else by order."""
    by_stem: dict[str, list[Path]] = {}
    for p in files:
        by_stem.setdefault(p.stem.lower(), []).append(p)
    stems = [Path(n).stem.lower() for n in capture_names]
    if all(len(by_stem.get(s, ())) == 1 for s in stems) and len(set(stems)) == len(stems):
        return [by_stem[s][0] for s in stems], "name"
    return list(files), "order"


def _board_grid(path: Path, shape: tuple[int, int],
                raw: RawDevelopment | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A board photograph as block means of linear luminance on a grid ≤ :data:`_GRID_SIDE`.

    Returns the block means, and each block's centre as ``u``, ``v`` in [-1, 1] (flattened);
    blocks holding a clipped pixel or darker than :data:`_BLOCK_DARK` are left out.
    """
    _check_size(path, shape, "the board photograph", "the capture's photographs")
    side = max(1, min(shape) * _GRID_SIDE // max(shape))
    img = read_image(path, min_side=side, raw=raw)
    h, w = img.shape[:2]
    if image_size(path) is None and (h, w) != tuple(shape):  # no header to check: decoded whole
        raise InputError(f"the board photograph is {_size_text(img.shape)} pixels but the capture's photographs "
                         f"are {_size_text(shape)}", path)
    top = np.iinfo(img.dtype).max if img.dtype.kind == "u" else 1.0
    clipped = (img >= top) if img.ndim == 2 else (img >= top).any(axis=2)
    lum = _luminance(img)
    f = max(1, math.ceil(max(h, w) / _GRID_SIDE))
    gh, gw = h // f, w // f
    if gh < 2 or gw < 2:
        raise InputError(f"the board photograph is too small ({_size_text(img.shape)} pixels) for a flat field", path)
    blocks = lum[:gh * f, :gw * f].reshape(gh, f, gw, f).mean(axis=(1, 3), dtype=np.float64)
    bad = clipped[:gh * f, :gw * f].reshape(gh, f, gw, f).any(axis=(1, 3)) | ~(blocks > _BLOCK_DARK)
    # Block centres in the full frame, in the same u, v as FlatField (the thumbnail spans it).
    v = 2 * (np.arange(gh) + 0.5) * f / h - 1
    u = 2 * (np.arange(gw) + 0.5) * f / w - 1
    uu, vv = np.meshgrid(u, v)
    keep = ~bad.ravel()
    return blocks.ravel()[keep], uu.ravel()[keep], vv.ravel()[keep]


def load_flat_field(
    folder: str | os.PathLike,
    capture_names: Sequence[str],
    lights: np.ndarray,
    shape: tuple[int, int],
    *,
    degree: int = FLAT_DEGREE,
    raw: RawDevelopment | None = None,
) -> FlatField:
    """Measure each light's gain over the frame from a capture of a flat board.

    Parameters
    ----------
    folder : str or PathLike
        A capture of a flat white or grey board (matte, filling the frame, facing the camera)
        under the same lights, camera and exposure. Its photographs are those its ``.lp`` lists
        when it has one (read with :func:`ptmcore.lp.read_lp`; its directions are not used),
        else its ``.jpg``, ``.jpeg``, ``.png``, ``.tif``, ``.tiff`` and camera RAW files sorted by
        name.
    capture_names : sequence of str
        The capture's photographs' file names, in the order of its lights. A board photograph
        of the same name (ignoring the extension and case) is matched with each when every one
        has one; otherwise the board's photographs are taken in their order.
    lights : ndarray, shape (N, 3)
        The capture's light directions (x right, y up, z towards the camera).
    shape : tuple of int
        ``(H, W)`` of the capture's photographs.
    degree : int
        Total degree of the polynomial in log-gain (:data:`FLAT_DEGREE`).
    raw : RawDevelopment, optional
        The capture's development of camera RAW photographs (:mod:`ptmcore.raw`), so that the
        board is developed as the capture is.

    Returns
    -------
    FlatField

    Raises
    ------
    InputError
        If the folder is missing, holds another number of photographs than the capture (naming
        both counts), a board photograph of another size (naming the file and both sizes), or one
        black or clipped over most of the frame.
    """
    folder = Path(folder)
    lights = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    if len(lights) != len(capture_names):
        raise ValueError(f"{len(capture_names)} photographs but {len(lights)} light directions")
    files, lp = _board_files(folder)
    if len(files) != len(capture_names):
        source = f"its light file {lp.name} lists" if lp is not None else "it holds"
        raise InputError(f"the flat-field capture does not match the capture: {source} {len(files)} photograph(s), "
                         f"the capture has {len(capture_names)}", folder)
    files, how = _match(files, capture_names)
    terms = len(_terms(degree))
    coefficients = np.empty((len(files), terms))
    residual = np.empty(len(files))
    rejected = np.empty(len(files))
    for k, path in enumerate(files):
        b, u, v = _board_grid(path, shape, raw)
        if len(b) < 4 * terms:
            raise InputError("the board photograph is black or clipped over most of the frame", path)
        a = _design(u, v, degree)
        coefficients[k], residual[k], rejected[k] = _robust_fit(a, np.log(b))
    # g_k = B_k / (ρ l_k,z): divide out the lamp's elevation, then one constant c (ρ and the
    # exposure) so that the median lamp has gain 1 at the frame's centre.
    coefficients[:, 0] -= np.log(lights[:, 2])
    centre = _design(np.zeros(1), np.zeros(1), degree)[0] @ coefficients.T
    coefficients[:, 0] -= float(np.median(centre))
    return FlatField(shape=(int(shape[0]), int(shape[1])), degree=degree, coefficients=coefficients,
                     names=[p.name for p in files], matched_by=how, residual=residual, rejected=rejected)


# --- grey card -----------------------------------------------------------------------------

#: A reference region whose mean linear luminance is below this in some photograph is black
#: there (in shadow, outside the lamp's cone): a grey card of 18 % under a lamp at 15° reads
#: about 0.05, and at 0.002 an 8-bit photograph's quantisation alone errs by several per cent.
_CARD_BLACK = 0.002
#: … and a region with more than this share of clipped samples is clipped there (a clipped
#: sample reads 1 whatever its light: 0.5 % of them err the mean by at most 0.5 % of the excess).
_CARD_CLIPPED = 0.005


def parse_region(text: str, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """Read ``--reference-region``: ``x,y,w,h`` in pixels.

    ``x`` is the column and ``y`` the row of the region's top-left corner (image coordinates,
    row 0 at the top), ``w`` and ``h`` its width and height.

    Parameters
    ----------
    text : str
        Four non-negative integers separated by commas (spaces allowed).
    shape : tuple of int
        ``(H, W)`` of the photographs.

    Returns
    -------
    tuple of int
        ``(x, y, w, h)``.

    Raises
    ------
    InputError
        If the text is not four integers, the region is empty, or it leaves the frame.
    """
    h_img, w_img = int(shape[0]), int(shape[1])
    fields = [f.strip() for f in str(text).split(",")]
    if len(fields) != 4 or not all(re.fullmatch(r"[0-9]{1,9}", f) for f in fields):
        raise InputError(f"--reference-region {str(text)[:40]!r}: expected x,y,w,h (four non-negative whole numbers "
                         "of pixels, as 120,80,40,40)")
    x, y, w, h = (int(f) for f in fields)
    if w < 1 or h < 1:
        raise InputError(f"--reference-region {text!r}: the region is empty (width and height must be at least 1)")
    if x + w > w_img or y + h > h_img:
        raise InputError(f"--reference-region {text!r}: columns {x}–{x + w - 1}, rows {y}–{y + h - 1} leave the "
                         f"photographs' frame of {w_img}×{h_img} pixels")
    return x, y, w, h


def measure_region(stack: ImageStack, region: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Mean linear luminance and share of clipped samples of ``region`` in each photograph.

    Parameters
    ----------
    stack : ImageStack
    region : tuple of int
        ``(x, y, w, h)`` from :func:`parse_region`.

    Returns
    -------
    means : ndarray, shape (N,), float64
    clipped : ndarray, shape (N,), float64
        For :func:`reference_intensities`.
    """
    x, y, w, h = region
    values, saturated = stack.band(y, y + h, x, x + w)
    return (values.mean(axis=(1, 2), dtype=np.float64), saturated.mean(axis=(1, 2), dtype=np.float64))


def reference_intensities(region_means: np.ndarray, lights: np.ndarray, *,
                          clipped: np.ndarray | None = None,
                          names: Sequence[str | os.PathLike] | None = None) -> np.ndarray:
    """Each photograph's light intensity, relative, from a grey card seen in every photograph.

    A matte card facing the camera reads ``ρ · E_k · l_k,z`` under light k, so its mean linear
    luminance over ``l_k,z`` is the lamp's strength ``E_k`` at the card, up to one constant:
    the factors are normalised to a median of 1. Divide the stack by them
    (:func:`ptmcore.intensity.apply_intensities`). A card tilted by ``t`` errs by up to
    ``tan t · |l_k,xy| / l_k,z``; a card where the lamps' cones differ from the object's middle
    measures the lamps there (a flat field, :func:`load_flat_field`, measures them everywhere).

    Parameters
    ----------
    region_means : ndarray, shape (N,)
        The region's mean linear luminance in each photograph (:func:`measure_region`).
    lights : ndarray, shape (N, 3)
        Light directions.
    clipped : ndarray, shape (N,), optional
        The region's share of clipped samples in each photograph.
    names : sequence of str or path, optional
        The photographs, to name the one where the region is black or clipped.

    Returns
    -------
    ndarray, shape (N,), float64
        Positive factors, median 1.

    Raises
    ------
    InputError
        If the region is black (mean below :data:`_CARD_BLACK`) or clipped in some photograph,
        naming the first such photograph.
    """
    m = np.asarray(region_means, dtype=np.float64).reshape(-1)
    d = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
    if len(d) != len(m):
        raise ValueError(f"{len(m)} region means but {len(d)} light directions")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    clip = np.zeros(len(m)) if clipped is None else np.asarray(clipped, dtype=np.float64).reshape(-1)
    # A mean of 1 is a region clipped throughout even when no clip share was given.
    bad_clip = (clip > _CARD_CLIPPED) | (m >= 1.0)
    bad_black = ~(m >= _CARD_BLACK)
    bad = bad_clip | bad_black
    if bad.any():
        k = int(np.argmax(bad))
        what = "clipped" if bad_clip[k] else f"black (mean linear luminance {m[k]:.2g})"
        others = int(bad.sum()) - 1
        more = f"; so are {others} other photograph(s)" if others else ""
        problem = (f"the reference region is {what} in this photograph{more}: choose a grey card "
                   "lit and unclipped in every photograph")
        if names is not None:
            raise InputError(problem, names[k])
        raise InputError(f"photograph {k + 1}: {problem}")
    f = m / d[:, 2]
    return f / float(np.median(f))


# --- stray light without an ambient frame -------------------------------------------------

#: A sample is in attached shadow when the fitted n·l is below this: clearly turned away from
#: the lamp, so a small error of the normal (a few degrees: sin 5° ≈ 0.09) does not put a lit
#: sample there.
SHADOW_COSINE = -0.15
#: Samples fitted as lit: n·l above this after the first round (brightly lit; dim ones are the
#: most sensitive to the normal's error and to the very floor being measured).
_LIT_COSINE = 0.25
#: First round, before any normal is known: per pixel, samples between this share of its 90th
#: percentile (above shadows, and above a floor of 10 % or 20 % room light) and the 90th
#: percentile itself (below highlights).
_FIRST_DARK = 0.3
_FIRST_BRIGHT_QUANTILE = 0.9
#: Later rounds keep lit samples within this many robust standard deviations of the fit, but
#: never cut below this share of the albedo (the noise of a clean capture); what lies above is
#: a highlight, below a cast shadow.
_TRIM_SIGMAS = 3.0
_TRIM_FLOOR = 0.03
_ROUNDS = 3
#: A pixel needs this many lit samples for a normal, and this many in attached shadow.
_MIN_LIT = 8
_MIN_SHADOW = 2
#: Pixels darker than this share of the brightest pixels (the 95th percentile of the pixels'
#: albedos) are left out: a black background's ratios are noise over noise.
_MIN_ALBEDO_SHARE = 0.1
#: Fewer pixels with attached-shadow samples than this, and the level is not measured.
MIN_SHADOW_PIXELS = 25
#: … nor when they are fewer than this share of the pixels fitted: a shadowed side is a part
#: of the object, not a scatter of pixels whose fit went wrong. Measured: 7.8–18 % on the
#: synthetic tablet and sphere under domes from 15° or 30°, 8.7 % on DiLiGenT's cat; 0.3 % on
#: the flat painted icon of neuralrti_icon, whose few such pixels read 5.7 %.
MIN_SHADOW_SHARE = 0.01
#: Clipped samples (linear value ≥ this) are never used.
_CLIP = 0.999
#: The level above which a capture is said to hold room light; see :class:`StrayLight`.
STRAY_LIGHT_WARN = 0.025
#: Lit samples whose normal lies within 30° of the half-way vector between lamp and camera are
#: left out of the fit: that is where a glossy surface's highlight is (as
#: :mod:`ptmcore.intensity` does). 20° let the highlights of a glossy tablet pull its normals
#: (5 % room light read 4.3 %) and made neuralrti_icon read 3.8 % at a grid step of 4; a flat
#: pixel so loses its lamps above 30°, but it has no attached shadow to measure anyway.
_HIGHLIGHT_COSINE = math.cos(math.radians(30.0))


@dataclass(frozen=True)
class StrayLight:
    """Room light in the photographs, measured from the object's attached shadows.

    Attributes
    ----------
    level : float or None
        The light in attached shadows relative to the pixel's albedo (the ambient light as a
        share of a lamp facing the surface), median over the pixels of the median of each
        pixel's attached-shadow samples / its albedo; None when too few pixels have samples in
        attached shadow to say (a dome without low lights, a flat object).
    pixels : int
        The pixels it was measured on.
    warn : bool
        Whether ``level`` exceeds :attr:`threshold`.
    threshold : float
        :data:`STRAY_LIGHT_WARN`: 2.5 %. Measured (``benchmarks/illumination.py``, every 4th
        pixel): dark-room captures read 0.26–0.52 % (synthetic tablet and sphere, matte or
        glossy, 16-bit or 8-bit JPEG, cast shadows, domes from 15° or 30°: the sensor's noise
        clipped at black) and 1.1–1.2 % on DiLiGenT's cat (a glossy ceramic whose concave parts
        light each other); 5 % of room light reads 4.98–5.04 %, 10 % 9.97–10.02 %. 2.5 % is
        twice the worst dark room and half the least room light the warning must catch.
    fitted : int
        The pixels whose Lambertian fit was usable (lit enough, well posed, not background).
    lit_offset : float or None
        The constant term of the lit samples' fit ``I = b · l + c``, as ``c / |b|`` (median over
        pixels): room light shows there too, but so does any departure from Lambert's law, so it
        is reported, not used.
    """

    level: float | None
    pixels: int
    warn: bool
    threshold: float = STRAY_LIGHT_WARN
    fitted: int = 0
    lit_offset: float | None = None

    @property
    def message(self) -> str:
        """The finding in words for the report."""
        if self.level is None:
            return (f"room light not measured: only {self.pixels} of the {self.fitted} pixels fitted have samples in "
                    "attached shadow (the lights are too high, or the object too flat, to see its shadowed sides)")
        if self.warn:
            return (f"room light in the photographs: the object's shadowed sides hold {100 * self.level:.1f} % of "
                    "a lamp's light, which flattens the normals; photograph an ambient frame with the lamps off "
                    "(--ambient) or darken the room")
        return f"no room light found (shadowed sides hold {100 * self.level:.1f} % of a lamp's light)"


def _fit(values: np.ndarray, design: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weighted least squares ``values[:, p] ≈ design @ x_p``, all pixels at once.

    Returns the solutions (P, K) and which pixels' systems were well posed.
    """
    k = design.shape[1]
    m = np.einsum("np,ni,nj->pij", weights, design, design, optimize=True)
    rhs = np.einsum("np,ni,np->pi", weights, design, values, optimize=True)
    # Ill-posed pixels (lights in one plane, too few samples) get the identity and are flagged.
    ok = np.linalg.cond(m) < 1e6
    m[~ok] = np.eye(k)
    rhs[~ok] = 0
    return np.linalg.solve(m, rhs[..., None])[..., 0], ok


def estimate_stray_light(samples: np.ndarray, lights: np.ndarray) -> StrayLight:
    """Detect room light in a capture without an ambient frame.

    Each sampled pixel's normal and albedo are fitted robustly on its brightly lit samples
    (``I = b · l + c``, the constant ``c`` taking the room's light so that it does not tilt the
    normal), cast shadows and highlights trimmed; then its samples in attached shadow
    (``n · l <`` :data:`SHADOW_COSINE`) should be black in a dark room, apart from light
    reflected off the object's other parts. Room light raises them all by the same share of the
    albedo.

    Parameters
    ----------
    samples : ndarray, shape (N, P)
        Linear luminance of P pixels in each of the N photographs (e.g. ``stack.table`` of
        :meth:`ptmcore.images.ImageStack.grid`, or thumbnails' pixels); the background may be in it.
    lights : ndarray, shape (N, 3)
        Light directions.

    Returns
    -------
    StrayLight
    """
    s = np.asarray(samples, dtype=np.float64)
    d = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
    if s.ndim != 2 or s.shape[0] != len(d):
        raise ValueError(f"samples of shape {s.shape} for {len(d)} lights")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    usable = np.isfinite(s) & (s < _CLIP)
    s = np.where(np.isfinite(s), s, 0.0)
    x, ok_offset, lit_offset = _robust_lambert(s, usable, d, offset=True)
    plain, ok_plain, lit_plain = _robust_lambert(s, usable, d, offset=False)
    albedo = np.linalg.norm(x[:, :3], axis=1)
    good = ok_offset & ok_plain & (lit_offset.sum(axis=0) >= _MIN_LIT) & (lit_plain.sum(axis=0) >= _MIN_LIT)
    good &= albedo > 0
    if good.any():
        good &= albedo >= _MIN_ALBEDO_SHARE * np.quantile(albedo[good], 0.95)
    # In attached shadow under both fits. The constant term keeps room light from tilting the
    # normal, but it also lets a dark pixel that is not Lambertian (a camera's tone curve, a
    # varnish's sheen) be read as a steep facet with a floor: on a flat painted icon
    # (neuralrti_icon) such pixels were fitted 37° steep and read as 15–19 % room light. The
    # fit without the constant takes that floor as shading, turning such a normal towards the
    # camera, and room light moves a truly steep facet's normal by only a few degrees.
    shadow = usable & good & (d @ _unit_rows(x[:, :3]).T < SHADOW_COSINE) & (d @ _unit_rows(plain).T < SHADOW_COSINE)
    counted = shadow.sum(axis=0) >= _MIN_SHADOW
    pixels = int(counted.sum())
    offset = float(np.median(x[good, 3] / albedo[good])) if good.any() else None
    if pixels < max(MIN_SHADOW_PIXELS, MIN_SHADOW_SHARE * int(good.sum())):
        return StrayLight(level=None, pixels=pixels, warn=False, fitted=int(good.sum()), lit_offset=offset)
    ratios = np.nanmedian(np.where(shadow[:, counted], s[:, counted], np.nan), axis=0) / albedo[counted]
    level = float(np.median(ratios))
    return StrayLight(level=level, pixels=pixels, warn=level > STRAY_LIGHT_WARN, fitted=int(good.sum()),
                      lit_offset=offset)


def _unit_rows(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def _robust_lambert(s: np.ndarray, usable: np.ndarray, d: np.ndarray, *, offset: bool
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each pixel's Lambertian fit ``I = b · l (+ c)`` on its brightly lit samples, robustly.

    Returns ``(P, 4)`` solutions ``(b, c)`` (``c`` = 0 without ``offset``, and then only ``b``
    as ``(P, 3)``), which pixels were well posed, and the samples of the last fit ``(N, P)``.
    """
    design = np.concatenate([d, np.ones((len(d), 1))], axis=1) if offset else d
    halfway = _unit_rows(d + np.array([0.0, 0.0, 1.0]))
    bright = np.quantile(s, _FIRST_BRIGHT_QUANTILE, axis=0)
    w = (usable & (s > _FIRST_DARK * bright) & (s <= bright)).astype(np.float64)
    for _ in range(_ROUNDS):
        x, ok = _fit(s, design, w)
        albedo = np.linalg.norm(x[:, :3], axis=1)
        normal = _unit_rows(x[:, :3])
        r = s - design @ x.T
        lit = usable & (d @ normal.T > _LIT_COSINE) & (halfway @ normal.T < _HIGHLIGHT_COSINE)
        kept = lit & (w > 0)
        spread = np.where(kept, np.abs(r), np.nan)
        spread[:, ~kept.any(axis=0)] = 0  # no sample left: no NaN-only column (and no warning)
        sigma = np.maximum(1.4826 * np.nanmedian(spread, axis=0), _TRIM_FLOOR * albedo / _TRIM_SIGMAS)
        w = (lit & (np.abs(r) <= _TRIM_SIGMAS * sigma)).astype(np.float64)
    return x, ok, w > 0
