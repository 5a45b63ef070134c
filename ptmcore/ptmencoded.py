"""Fitting PTMs to photographs in their own encoding, as HP's PTMfitter does.

PTMfitter's LRGB fit (worked out from ``shared/fixtures/ptmfitter_8x5``, whose 12 photographs
and PTMfitter output are reproduced **byte for byte** by :func:`fit_ptm_encoded` followed by
:func:`ptmcore.ptmfile.write_ptm`): it fits the photographs' own 8-bit values, not linear light.

* The luminance of a photograph is the luma ``0.2125 R + 0.7154 G + 0.0721 B`` of its bytes (the
  Rec. 709 weights as they were quoted around 2000; the current 0.2126/0.7152/0.0722 misses one
  of the 240 coefficient bytes, by 0.005 of a step; Rec. 601 weights or the mean of R, G, B miss
  most of them). In a grid search (steps of 0.0005) only weights next to these reproduce every
  byte, but that rests on a handful of bytes close to a rounding boundary in one small fixture.
* Per pixel, that luminance is normalised so that the pixel's brightest photograph has L = 255:
  ``L_n = 255 · Y_n / max_n Y_n``; the polynomial is the least-squares (pseudoinverse) fit of L_n.
* The pixel's colour in the RGB block is the least-squares solution of ``C_n ≈ rgb · L_n / 255``
  over the photographs, ``rgb = max_n Y_n · Σ C_n Y_n / Σ Y_n²``, truncated (not rounded) to an
  integer. (Fitting against the polynomial's values instead of the observed L_n gives the same
  bytes on the fixture; the mean colour times the peak luminance, or the colour of the brightest
  photograph, do not.)
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .bands import run_bands
from .errors import InputError
from .fit import fit_matrix
from .lp import as_directions

if TYPE_CHECKING:  # reduce imports this module
    from .corrections import Corrections
    from .reduce import Reduced

__all__ = ["ENCODINGS", "HP_LUMA_WEIGHTS", "EncodedFit", "EncodedFits", "finish_lrgb", "fit_ptm_encoded", "fit_ptm_rgb_encoded"]

#: Luma weights HP's PTMfitter applies to the photographs' R, G, B bytes (see the module notes).
HP_LUMA_WEIGHTS = np.array([0.2125, 0.7154, 0.0721])
#: What the encoded fits may be fitted to (:class:`EncodedFit`).
ENCODINGS = ("stored", "srgb", "linear")


@dataclass(frozen=True, eq=False)  # eq=False: arrays have no single truth value
class EncodedFit:
    """The fits to make to the photographs as encoded, for the files viewers open.

    Passed to :func:`ptmcore.images.load_stack_and_fits`, they are added up in the pass that
    decodes the photographs for the stack, so the files are made without reading them again.

    Attributes
    ----------
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    ptm_format : {"lrgb", "rgb"} or None
        The PTM to fit (:func:`fit_ptm_encoded`, :func:`fit_ptm_rgb_encoded`), or none.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the PTM light matrix (:func:`ptmcore.fit.fit_matrix`).
    hsh_order : {2, 3} or None
        Also fit an HSH of this order (:func:`ptmcore.rtifile.fit_rti_hsh`).
    encoding : {"stored", "srgb", "linear"}
        The values fitted: the samples as stored (HP's PTMfitter and RTIBuilder: 8-bit bytes,
        16-bit values / 257), or every photograph display-encoded as sRGB (8-bit sRGB
        photographs as stored; linear ones — 16-bit, float, 8-bit read as linear — encoded),
        or in linear light (8-bit sRGB bytes decoded). Always in 0..255 units.
    """

    directions: np.ndarray
    ptm_format: str | None = "lrgb"
    solver: str = "pinv"
    hsh_order: int | None = None
    encoding: str = "stored"

    def __post_init__(self) -> None:
        if self.ptm_format not in ("lrgb", "rgb", None):
            raise ValueError(f"PTM format must be 'lrgb', 'rgb' or None, not {self.ptm_format!r}")
        if self.encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {ENCODINGS}, not {self.encoding!r}")
        # A copy: the fits are matched against the directions a later stage uses.
        object.__setattr__(self, "directions", np.array(self.directions, dtype=np.float64))

    def matrices(self, n: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The PTM's (6, N) and the HSH's (K, N) float32 matrices for ``n`` photographs.

        The PTM's is empty (0, 0) without a PTM; the HSH's is None without an HSH. Photographs
        enter the fits in 0..255 units, so the HSH's (fitted in 0..1) is divided by 255 here.
        """
        directions = as_directions(self.directions, n)
        ptm = (fit_matrix(directions, self.solver).astype(np.float32) if self.ptm_format is not None
               else np.zeros((0, 0), np.float32))
        if self.hsh_order is None:
            return ptm, None
        from .hsh import ORDERS, hsh_fit_matrix

        if self.hsh_order not in ORDERS:
            raise ValueError(f"HSH order must be one of {ORDERS}, got {self.hsh_order!r}")
        return ptm, (hsh_fit_matrix(directions, self.hsh_order) / 255.0).astype(np.float32)


@dataclass
class EncodedFits:
    """The fits of :class:`EncodedFit`, made in the decoding pass.

    Attributes
    ----------
    paths : list of Path
        The photographs they were fitted to, in order.
    fit : EncodedFit
        What was fitted, and to which light directions.
    coefficients : ndarray or None
        The PTM: LRGB ``(H, W, 6)`` float32 with its colour ``rgb`` ``(H, W, 3)`` uint8, or
        RGB format ``(H, W, 3, 6)`` float32 (0..255 units); as :func:`fit_ptm_encoded` and
        :func:`fit_ptm_rgb_encoded` return them.
    rgb : ndarray or None
    hsh : ndarray or None
        ``(H, W, 3, order²)`` float32, as :func:`ptmcore.rtifile.fit_rti_hsh` returns it.
    """

    paths: list[Path]
    fit: EncodedFit
    coefficients: np.ndarray | None = None
    rgb: np.ndarray | None = None
    hsh: np.ndarray | None = None

    def matches(self, paths: Sequence[str | os.PathLike], directions: np.ndarray, solver: str,
                encoding: str = "stored") -> bool:
        """Whether these fits are of ``paths`` (in order) lit from ``directions``, by ``solver``,
        in ``encoding``.

        False when photographs were dropped or lights changed after decoding (e.g. a sphere
        calibration): the caller then fits again from the files.
        """
        d = np.asarray(directions, dtype=np.float64)
        return (
            [Path(p) for p in paths] == self.paths
            and d.shape == self.fit.directions.shape
            and bool(np.array_equal(d, self.fit.directions))
            and solver == self.fit.solver
            and encoding == self.fit.encoding
        )

    def take_ptm(self, ptm_format: str) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The PTM's coefficients and colour (None for RGB format), handed over and forgotten
        here so that their memory goes with the caller's last reference; None if this PTM
        (format) was not fitted."""
        if self.fit.ptm_format != ptm_format or self.coefficients is None:
            return None
        out = (self.coefficients, self.rgb)
        self.coefficients = self.rgb = None
        return out

    def take_hsh(self, order: int) -> np.ndarray | None:
        """The HSH coefficients, handed over as :meth:`take_ptm` does; None if not fitted."""
        if self.fit.hsh_order != order or self.hsh is None:
            return None
        out, self.hsh = self.hsh, None
        return out


def finish_lrgb(sums: np.ndarray, aux: np.ndarray, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """HP's LRGB coefficients and colour from the per-pixel sums of the encoded fit.

    Parameters
    ----------
    sums : ndarray, shape (H, W, 6), float32
        Σ_n pinv[j, n] · Y_n; turned into the coefficients in place (their memory is reused).
    aux : ndarray, shape (H, W, 5), float32
        The peak ``max_n Y_n``, Σ C·Y for R, G, B, and Σ Y².
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).

    Returns
    -------
    coefficients : ndarray, shape (H, W, 6), float32
        ``sums`` itself: L in 0..255 units (``255 · Y / peak``).
    rgb : ndarray, shape (H, W, 3), uint8
        ``peak · Σ C·Y / Σ Y²``, truncated.
    """
    h, w = sums.shape[:2]
    rgb = np.empty((h, w, 3), dtype=np.uint8)

    def work(r0: int, r1: int) -> None:
        band = slice(r0, r1)
        with np.errstate(divide="ignore", invalid="ignore"):
            p = aux[band, :, 0]
            # A pixel black in every photograph keeps L = 0 and colour 0.
            norm = np.where(p > 0, np.float32(255) / p, np.float32(0))[..., None]
            sums[band] *= norm
            colour = np.floor(p[..., None] * aux[band, :, 1:4] / aux[band, :, 4:5])
            rgb[band] = np.clip(np.nan_to_num(colour, nan=0.0, posinf=255.0), 0, 255).astype(np.uint8)

    run_bands(h, max(1, (1 << 18) // w), work, threads=threads)
    return sums, rgb


def _reduce_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    ptm_format: str,
    *,
    solver: str,
    encoding: str,
    linearize: bool,
    threads: int | None,
    progress: Callable[[int], None] | None,
    corrections: Corrections | None = None,
) -> Reduced:
    """Stream the photographs into the sums of one encoded PTM fit, with no stack.

    Parameters
    ----------
    images, directions, solver, encoding, linearize, threads, progress, corrections
        As :func:`fit_ptm_encoded`.
    ptm_format : {"lrgb", "rgb"}
        The PTM whose sums are made (:class:`EncodedFit`).

    Returns
    -------
    Reduced
        The reduction, holding that PTM's sums.

    Raises
    ------
    InputError
        If no photograph is given, one cannot be read, or sizes differ.
    """
    from .reduce import reduce_photographs  # numba's import costs a second; `import ptmcore` does not need it

    # Fewer than six photographs leave the six coefficients underdetermined; the
    # pseudoinverse then gives the minimum-norm fit, and the caller warns about it.
    if len(images) < 1:
        raise InputError("no photographs given")
    fit = EncodedFit(directions, ptm_format, solver, encoding=encoding)
    fit.matrices(len(images))  # bad directions fail before any photograph is decoded
    return reduce_photographs(images, stack=False, linearize=linearize, fit=fit, threads=threads, progress=progress,
                              corrections=corrections)


def fit_ptm_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    encoding: str = "stored",
    linearize: bool = True,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    corrections: Corrections | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Fit an LRGB PTM to photographs as HP's PTMfitter does, in their own encoding.

    The photographs' bytes are used as they are (sRGB-encoded, not linearised). Per photograph
    and pixel the luma ``Y = 0.2125 R + 0.7154 G + 0.0721 B`` is normalised to
    ``L = 255 · Y / max_n Y`` (the pixel's brightest photograph has L = 255), the polynomial is
    the pseudoinverse fit of L, and the colour is the least-squares ``rgb`` of
    ``C ≈ rgb · L / 255``, truncated to bytes. Written with :func:`ptmcore.ptmfile.write_ptm` this reproduces
    PTMfitter's file byte for byte on the shared fixture (see the module notes).

    The photographs are streamed: a few are decoded at a time (in threads) and added to running
    per-pixel sums (:func:`ptmcore.reduce.reduce_photographs`, with no stack), so memory is 11
    float32 per pixel (the six coefficient sums, the peak luma, Σ C·Y and Σ Y²) plus a few
    photographs, however many there are. :func:`ptmcore.images.load_stack_and_fits` makes the
    same fit in the pass that decodes the stack.

    Parameters
    ----------
    images : sequence of path or ndarray, or ndarray (N, H, W[, 3])
        The photographs, 8-bit (16-bit values are divided by 257, floats multiplied by 255).
    directions : ndarray, shape (N, 3)
        Unit light directions, one per photograph.
    solver : {"pinv", "lstsq", "rohde"}
        The {1}-inverse of the light matrix (:func:`ptmcore.fit.fit_matrix`).
    encoding : {"stored", "srgb", "linear"}
        The values fitted (:class:`EncodedFit`); "stored" is PTMfitter's.
    linearize : bool
        8-bit photographs are sRGB (else linear), for ``encoding`` other than "stored".
    threads : int, optional
        Decoding threads (default: all CPUs).
    progress : callable, optional
        Called with 1 after each photograph.
    corrections : Corrections, optional
        Done to each photograph before the fit (:mod:`ptmcore.corrections`).

    Returns
    -------
    coefficients : ndarray, shape (H, W, 6), float32
        Luminance coefficients, L in 0..255 units, row 0 at the top.
    rgb : ndarray, shape (H, W, 3), uint8
        The colour block.

    Raises
    ------
    InputError
        If no photograph is given, one cannot be read, or sizes differ.
    """
    done = _reduce_encoded(images, directions, "lrgb", solver=solver, encoding=encoding, linearize=linearize,
                           threads=threads, progress=progress, corrections=corrections)
    return finish_lrgb(done.ptm_sums, done.ptm_aux, threads=threads)


def fit_ptm_rgb_encoded(
    images: Sequence[str | os.PathLike | np.ndarray] | np.ndarray,
    directions: np.ndarray,
    *,
    solver: str = "pinv",
    encoding: str = "stored",
    linearize: bool = True,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    corrections: Corrections | None = None,
) -> np.ndarray:
    """Fit an RGB-format PTM (one polynomial per channel) to photographs in their own encoding.

    Each channel's byte values (0..255, not linearised) are fitted by the pseudoinverse, so
    ``PTMFile.render`` of the written file approximates the photographs directly. Streams the
    photographs like :func:`fit_ptm_encoded` (18 float32 per pixel).

    Parameters
    ----------
    images, directions, solver, encoding, linearize, threads, progress, corrections
        As :func:`fit_ptm_encoded`.

    Returns
    -------
    ndarray, shape (H, W, 3, 6), float32
        Per-channel coefficients in 0..255 units, row 0 at the top.

    Raises
    ------
    InputError
        As :func:`fit_ptm_encoded`.
    """
    return _reduce_encoded(images, directions, "rgb", solver=solver, encoding=encoding, linearize=linearize,
                           threads=threads, progress=progress, corrections=corrections).channel_sums
