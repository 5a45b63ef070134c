"""Per-image light intensity factors, read from a file or estimated from the photographs.

RTI and photometric stereo take every photograph to be lit by a light of the same strength.
Flash units do not quite keep to that (a few per cent from shot to shot, more when a flash
has not fully recharged), and a dataset may list each light's measured brightness. Dividing
each photograph by its factor before the fit removes that error: Lambertian normals are
otherwise pulled towards the brighter lights.

* :func:`read_intensities` reads the factors from a text file (one value or ``r g b`` per
  photograph, in the order of the ``.lp`` file);
* :func:`fit_intensities` estimates relative factors from the photographs themselves (per
  channel for colour photographs), with a measure of their uncertainty;
  :func:`estimate_intensities` returns just the factors;
* :func:`apply_intensities` divides them out of an :class:`~ptmcore.images.ImageStack`.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .diskstack import release_rows
from .errors import InputError, read_input_text
from .images import _LUM_SCALE, LUMA_WEIGHTS, SATURATED, ImageStack, linear_to_srgb
from .lp import MAX_TEXT_BYTES, as_directions, decimal_number
from .pixelfit import SINGULAR

#: Samples with ``n·l`` below this are left out: dim, and the most sensitive to the normal's
#: error and to ambient light. (0.25 was tried: better under a broad gloss and 48 lights down
#: to 15°, worse under DiLiGenT's 96 lights at 45–85° elevation, the same on its cat.)
_MIN_SHADING = 0.1
#: Samples whose normal is within this angle of the half-way vector between light and camera
#: are left out: that is where specular highlights are, and their excess brightness would
#: otherwise be read as a brighter light.
_HIGHLIGHT_HALF_ANGLE_DEG = 30.0
#: First selection, before any factor is known: each pixel's brightest fifth of samples is
#: left out (its highlights), and those below this fraction of its brightest (shadows).
_BRIGHTEST_FRACTION = 0.2
_DARK_FRACTION = 0.05
#: Later rounds keep samples whose residual is within this many robust standard deviations
#: (1.4826 × median absolute residual) of their photograph's median, and never reject below
#: the floor (noise of a clean capture), in units of the pixel's albedo.
_TRIM_SIGMAS = 3.0
_TRIM_FLOOR = 0.02
_MAD_TO_SIGMA = 1.4826
#: A photograph needs this many samples to measure its factor on.
_MIN_SAMPLES = 20
#: The rounds stop when no factor moves by more than this (relative).
_CONVERGED = 1e-3
#: Light directions within this angle of a plane through the object (or of a line) count as
#: in it when the lights are checked for an ambiguity.
_COPLANAR_DEG = 0.5
#: IntensityFit.spread compares the object's halves in a checkerboard of blocks this many to
#: the object's extent.
_SPREAD_BLOCKS = 4
#: The first normals must depart from their main direction by at least this (RMS, degrees).
_MIN_NORMAL_SPREAD_DEG = 2.0


def read_numeric_rows(
    path: str | os.PathLike, what: str, widths: tuple[int, ...]
) -> tuple[np.ndarray, list[int]]:
    """Read a text file of whitespace-separated numbers, the same count on every line.

    Blank lines and ``#`` comments (whole-line or trailing) are skipped. Numbers are plain
    decimals (:func:`ptmcore.lp.decimal_number`: not ``1_0``, ``nan`` or ``0x10``).

    Parameters
    ----------
    path : str or PathLike
    what : str
        What the file holds, for messages ("light intensity file").
    widths : tuple of int
        Numbers per line that are accepted (every line must have the same count).

    Returns
    -------
    values : ndarray, shape (K, width), float64
        Finite values.
    lines : list of int
        The 1-based line number of each row.

    Raises
    ------
    InputError
        If the file is missing, unreadable or empty, a line has another count of fields or a
        field that is not a finite number, or the lines disagree on the count.
    """
    path = Path(path)
    text = read_input_text(path, what, max_bytes=MAX_TEXT_BYTES)
    rows: list[list[float]] = []
    numbers: list[int] = []
    expected = " or ".join(str(w) for w in widths)
    for no, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        # Some tools write comma-separated values; a comma is never part of a number here.
        fields = line.replace(",", " ").split()
        if len(fields) not in widths:
            raise InputError(f"line {no}: expected {expected} number(s), got {raw.strip()[:60]!r}", path)
        try:
            vals = [decimal_number(f) for f in fields]
        except ValueError:
            raise InputError(f"line {no}: not a number (plain decimals, as 0.5 or 1.2e-3): {raw.strip()[:60]!r}",
                             path) from None
        if not all(np.isfinite(vals)):
            raise InputError(f"line {no}: value is not finite: {raw.strip()[:60]!r}", path)
        if rows and len(vals) != len(rows[0]):
            raise InputError(
                f"line {no}: has {len(vals)} number(s) but line {numbers[0]} has {len(rows[0])}", path
            )
        rows.append(vals)
        numbers.append(no)
    if not rows:
        raise InputError(f"{what} is empty", path)
    return np.asarray(rows, dtype=np.float64), numbers


def check_positive(values: np.ndarray, lines: list[int], path: str | os.PathLike, what: str) -> None:
    """Raise :class:`InputError` at the first row holding a value that is not > 0."""
    bad = np.flatnonzero((values <= 0).any(axis=1))
    if bad.size:
        k = int(bad[0])
        shown = " ".join(f"{v:g}" for v in values[k])
        raise InputError(
            f"line {lines[k]}: {what} must be positive, got {shown} (photograph {k + 1})", path
        )


def read_intensities(path: str | os.PathLike, n: int) -> np.ndarray:
    """Read per-photograph light intensity factors.

    The file has one line per photograph, in the order of the ``.lp`` file: either one value
    (the light's strength) or three (``r g b``, its strength per channel). Blank lines and
    ``#`` comments are ignored. Only ratios matter: a common scale of all factors changes
    nothing but the albedo's scale.

    Parameters
    ----------
    path : str or PathLike
        The text file.
    n : int
        Number of photographs.

    Returns
    -------
    ndarray, shape (n,) or (n, 3), float64
        The factors, all positive.

    Raises
    ------
    InputError
        If the file is missing or malformed, lists another number of photographs, or holds a
        factor that is zero, negative or not finite.
    """
    values, lines = read_numeric_rows(path, "light intensity file", (1, 3))
    if len(values) != n:
        raise InputError(f"lists {len(values)} intensities but there are {n} photographs", path)
    check_positive(values, lines, path, "intensity")
    return values[:, 0].copy() if values.shape[1] == 1 else values


@dataclass
class IntensityFit:
    """Light intensity factors estimated from the photographs (:func:`fit_intensities`).

    Attributes
    ----------
    factors : ndarray, shape (N,) or (N, C), float64
        One factor per photograph (per channel for colour images), mean 1 over the measured
        photographs (each channel on its own): divide photograph ``k`` by ``factors[k]`` to
        equalise the lights. A photograph that could not be measured (fewer than 20 samples
        outside shadow and highlight: too dark, or a light near the camera over a nearly flat
        object) gets 1, the right value for lights of equal strength.
    spread : ndarray, same shape as ``factors``, float64
        Half the relative difference between the factors estimated from two halves of the
        object (the pixels of a checkerboard of blocks, four across the object, and the
        others): how much the answer depends on which part of the surface it rests on. It is
        large when the surface determines the factors weakly (a nearly flat object) or the
        reflectance departs from Lambert's law differently in different regions; it does not
        show a departure the whole surface shares. ``inf`` for a photograph that was not
        measured, and everywhere if a half alone did not determine the factors.
    samples : ndarray, shape (N,), int64
        Samples (pixels) each photograph's factor rests on; 0 for one that was not measured.
    rounds : int
        Rounds of selection and solution that were run.
    """

    factors: np.ndarray
    spread: np.ndarray
    samples: np.ndarray
    rounds: int


def _channel_weights(channels: int) -> np.ndarray:
    """Weights reducing ``channels`` values to the signal the samples are selected on."""
    if channels == 3:
        return LUMA_WEIGHTS.astype(np.float64)
    return np.full(channels, 1.0 / channels)


def _sample_pixels(
    images: ImageStack | np.ndarray, mask: np.ndarray | None, max_pixels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Linear values ``(N, P, C)`` float64, the signal they are selected on ``(N, P)``
    (:func:`_channel_weights`), usability ``(N, P)`` and the half each pixel is in ``(P,)``
    bool, of evenly spread pixels.

    A regular subsample is enough: the factors are one number per photograph, measured over
    thousands of pixels, and a grid keeps the result deterministic. Only the sampled pixels are
    read, so a memory-mapped stack of a large capture is not read whole.
    """
    stack = isinstance(images, ImageStack)
    if not stack and images.ndim not in (3, 4):
        raise ValueError(f"expected photographs (N, H, W) or (N, H, W, C), got shape {images.shape}")
    h, w = images.shape if stack else images.shape[1:3]
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (h, w):
            raise ValueError(f"mask is {mask.shape} but the photographs are {(h, w)}")
        candidates = np.flatnonzero(mask)
        if candidates.size > max_pixels:
            candidates = candidates[np.linspace(0, candidates.size - 1, max_pixels).astype(np.int64)]
    else:  # without listing every pixel of a large image
        candidates = np.unique(np.linspace(0, h * w - 1, min(max_pixels, h * w)).astype(np.int64))
    rows, cols = np.divmod(candidates, w)
    if stack:
        raw = images.luminance[:, rows, cols]  # (N, P) codes
        release_rows(images.luminance, 0, h)  # a stack on disk: the pages the reading mapped
        usable = raw != images.saturated_code
        values = images.table[raw].astype(np.float64)[..., None]
    else:
        raw = np.asarray(images[:, rows, cols])
        raw = raw[..., None] if raw.ndim == 2 else raw
        if np.issubdtype(raw.dtype, np.integer):
            top = np.iinfo(raw.dtype).max
            usable = np.all(raw < top, axis=2)
            values = raw / float(top)
        else:
            values = raw.astype(np.float64)
            usable = np.all(np.isfinite(values), axis=2)
            values[~usable] = 0.0
    signal = values @ _channel_weights(values.shape[2])
    # Background (dark in every usable photograph) says nothing about the lights.
    lit = np.where(usable, signal, 0.0).max(axis=0) > 2e-3
    # Two halves of the object, a checkerboard of blocks a quarter of its extent across, for
    # IntensityFit.spread: each half sees every kind of region, but none of the other's pixels.
    rows, cols = rows[lit], cols[lit]
    if rows.size:
        block = max(np.ptp(rows), np.ptp(cols), 1) / _SPREAD_BLOCKS
        halves = ((rows - rows.min()) // block + (cols - cols.min()) // block) % 2 == 1
    else:
        halves = np.zeros(0, dtype=bool)
    return values[:, lit], signal[:, lit], usable[:, lit], halves


def _undetermining_lights(dirs: np.ndarray) -> str | None:
    """Why these light directions leave the factors undetermined, or None if they do not.

    Other factors ``f'`` fit as well as the true ones exactly when some 3×3 matrix ``A``, not a
    multiple of the identity, has every light direction as an eigenvector (``b → Aᵀb`` then
    absorbs the change into the normals). The eigenvectors of such a matrix lie in a plane
    through the origin and one line, or on three lines; so the lights are degenerate when, for
    some light (or none), all lights off its line lie in one plane through the origin.
    """
    unit = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    n = len(unit)
    tol = np.sin(np.radians(_COPLANAR_DEG)) ** 2
    outer = (unit[:, :, None] * unit[:, None, :]).reshape(n, 9)
    # For each light, the second moment of the lights not on its line.
    same_line = np.abs(unit @ unit.T) > np.cos(np.radians(_COPLANAR_DEG))
    rest = (outer.sum(axis=0) - same_line.astype(np.float64) @ outer).reshape(n, 3, 3)
    count = n - same_line.sum(axis=1)
    flat = np.linalg.eigvalsh(rest)[:, 0] <= tol * np.maximum(count, 1)
    if np.linalg.eigvalsh(outer.sum(axis=0).reshape(3, 3))[0] <= tol * n:
        return "the lights do not determine the intensities: they all lie in one plane through the object"
    if flat.any():
        k = int(np.argmax(flat))
        return (
            "the lights do not determine the intensities: apart from the light of photograph "
            f"{k + 1}, they all lie in one plane through the object"
        )
    return None


def _check_normals_vary(b: np.ndarray) -> None:
    """Raise :class:`InputError` if the normals of ``b`` (P, 3) are all nearly parallel.

    On a flat surface every pixel has the same normal ``n``, and any factors of the form
    ``f_k (n·l_k) / (c·l_k)`` explain the photographs as well as the true ones (with each
    ``b_i`` turned towards ``c``): a three-parameter family that only a spread of normals
    rules out. A single other direction of normals is enough for generic lights.
    """
    unit = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    moment = unit.T @ unit / max(len(unit), 1)
    # The second eigenvalue is the mean squared sine of the normals' angle to their main
    # direction, in the direction they spread the most.
    spread = np.sqrt(max(np.linalg.eigvalsh(moment)[1], 0.0))
    if len(unit) == 0 or spread < np.sin(np.radians(_MIN_NORMAL_SPREAD_DEG)):
        raise InputError(
            "the surface is too flat to estimate light intensities: its normals depart from one "
            f"direction by {np.degrees(np.arcsin(min(spread, 1.0))):.1f}° (RMS), and at least "
            f"{_MIN_NORMAL_SPREAD_DEG:g}° are needed to tell a light's strength from its angle"
        )


def _light_outer(dirs: np.ndarray) -> np.ndarray:
    """Products ``xx, yy, zz, xy, xz, yz`` of each light direction, shape (N, 6)."""
    x, y, z = dirs.T
    return np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=1)


def _normal_matrices(outer: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ``Σ w l lᵀ`` (P, 3, 3) from weights (N, P), and where it is well posed (P,)."""
    m6 = weights.T @ outer  # (P, 6): a matrix product, far faster than a 3-operand einsum
    m = m6[:, [0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(-1, 3, 3)
    det = np.linalg.det(m)
    count = m6[:, 0] + m6[:, 1] + m6[:, 2]
    # Coplanar lit lights leave the normal along their plane's normal undetermined.
    ok = det > SINGULAR * np.maximum(count / 3.0, 1e-12) ** 3
    m[~ok] = np.eye(3)
    return m, ok


def _fit_scaled_normals(
    dirs: np.ndarray, outer: np.ndarray, values: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares ``b = ρ n`` per pixel from ``values`` (N, P).

    Returns ``b`` (P, 3) and where the used lights determined it (P,).
    """
    m, ok = _normal_matrices(outer, weights)
    rhs = (weights * values).T @ dirs  # (P, 3)
    b = np.linalg.solve(m, rhs[..., None])[..., 0]
    b[~ok] = 0.0
    return b, ok


def _quadratic_forms(
    dirs: np.ndarray, outer: np.ndarray, values: np.ndarray, weights: np.ndarray,
    halves: np.ndarray, chunk: int = 8192,
) -> np.ndarray:
    """The forms ``Q`` of :func:`_factors_from_form` over the two halves of the pixels, (2, N, N).

    With ``u_k = 1 / f_k`` the model ``u_k v_ki = l_k·b_i`` is linear in ``(u, b)``; the weighted
    squared residual with each pixel's ``b_i`` eliminated (variable projection) is ``uᵀ Q u``,
    ``Q = Σ_i diag(w_i v_i²) − A_iᵀ M_i⁻¹ A_i``, ``A_i = Lᵀ diag(w_i v_i)``, ``M_i = Lᵀ W_i L``.
    With ``M_i⁻¹ = C_i C_iᵀ`` the second term is ``Y_iᵀ Y_i``, ``Y_i = C_iᵀ A_i``: one matrix
    product over all pixels instead of a solve per pixel. ``halves`` (P,) bool says which
    pixels are in the second half.
    """
    n = len(values)
    forms = np.zeros((2, n, n))
    diagonal = np.diag_indices(n)
    for half in (0, 1):
        part = np.flatnonzero(halves == bool(half))
        for s in range(0, part.size, chunk):
            cols = part[s : s + chunk]
            w = weights[:, cols]
            v = values[:, cols]
            wv = w * v
            m, ok = _normal_matrices(outer, w)
            c = np.linalg.cholesky(np.linalg.inv(m[ok]))  # (Pok, 3, 3)
            y = np.matmul(c.transpose(0, 2, 1), dirs.T) * wv.T[ok][:, None, :]  # (Pok, 3, N)
            y = y.reshape(-1, n)
            forms[half][diagonal] += (wv * v)[:, ok].sum(axis=1)
            forms[half] -= y.T @ y
    return forms


def _factors_from_form(form: np.ndarray, measured: np.ndarray) -> np.ndarray | None:
    """Factors minimising ``uᵀ Q u`` (``u = 1 / f``) over the measured photographs.

    The least-squares ``u`` is the eigenvector of the smallest eigenvalue (up to scale).
    Photographs not measured are left out (a zero row would let the eigenproblem pick one of
    them alone) and get 1. Returns None if the answer is degenerate (not all positive).
    """
    keep = np.flatnonzero(measured)
    _, vecs = np.linalg.eigh(form[np.ix_(keep, keep)])
    u = vecs[:, 0] * np.sign(vecs[:, 0].sum())
    if not np.all(u > 1e-6 * np.abs(u).max()):
        return None
    f = np.ones(len(form))
    f[keep] = 1.0 / u
    f[keep] /= f[keep].mean()
    return f


def _first_selection(signal: np.ndarray, usable: np.ndarray) -> np.ndarray:
    """Weights (N, P) of the first normals: without any pixel's brightest fifth (its highlights)
    and its samples below 5 % of its brightest (shadows). Neither test depends on the factors,
    which are unknown yet."""
    n = len(signal)
    ranked = np.sort(np.where(usable, signal, np.inf), axis=0)
    first_dropped = np.floor((1.0 - _BRIGHTEST_FRACTION) * usable.sum(axis=0)).astype(np.int64)
    threshold = np.take_along_axis(ranked, np.minimum(first_dropped, n - 1)[None], axis=0)
    brightest = np.where(usable, signal, 0.0).max(axis=0)
    return (usable & (signal < threshold) & (signal > _DARK_FRACTION * brightest)).astype(np.float64)


def _selection(
    dirs: np.ndarray, half: np.ndarray, signal: np.ndarray, usable: np.ndarray,
    factors: np.ndarray, b: np.ndarray, ok: np.ndarray,
) -> np.ndarray:
    """Weights (N, P), 0 or 1, of the samples that the Lambertian model describes.

    Given the current factors and each pixel's ``b = ρ n``, a sample is kept if it is
    unsaturated, lit (``n·l ≥ _MIN_SHADING``), away from the specular direction (normal more
    than ``_HIGHLIGHT_HALF_ANGLE_DEG`` from the half-way vector of light and camera), and its
    residual (in units of the pixel's albedo) is within a few robust standard deviations of its
    photograph's median residual (cast shadows, interreflections and the rest of a highlight
    are trimmed). The centre is per photograph so that a factor still wrong does not trim its
    own photograph's samples.
    """
    rho = np.linalg.norm(b, axis=1)
    inv_rho = 1.0 / np.where(rho > 0, rho, 1.0)
    predicted = dirs @ b.T  # (N, P), in the units of signal / factors
    candidate = (
        usable
        & ok[None, :]
        & (predicted * inv_rho >= _MIN_SHADING)
        & ((half @ b.T) * inv_rho < np.cos(np.radians(_HIGHLIGHT_HALF_ANGLE_DEG)))
    )
    residual = np.where(candidate, (signal / factors[:, None] - predicted) * inv_rho, np.nan)
    with warnings.catch_warnings():  # a photograph without candidates has no median
        warnings.simplefilter("ignore", RuntimeWarning)
        dev = np.abs(residual - np.nanmedian(residual, axis=1, keepdims=True))
        spread = _MAD_TO_SIGMA * np.nanmedian(dev)
    tol = max(_TRIM_FLOOR, _TRIM_SIGMAS * float(spread)) if np.isfinite(spread) else np.inf
    return (candidate & (dev <= tol)).astype(np.float64)


def _spread(forms: np.ndarray, measured: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """Half the relative difference of the factors from the two halves of the sample."""
    halves = [_factors_from_form(form, measured) for form in forms]
    if any(h is None for h in halves):
        return np.full(len(factors), np.inf)
    return np.where(measured, np.abs(halves[0] - halves[1]) / (2.0 * factors), np.inf)


def fit_intensities(
    images: ImageStack | np.ndarray,
    directions: np.ndarray,
    *,
    iterations: int = 10,
    mask: np.ndarray | None = None,
    max_pixels: int = 20_000,
) -> IntensityFit:
    """Estimate relative per-photograph light intensity factors from the photographs.

    Model: sample ``i`` of photograph ``k`` is ``f_k ρ_i n_i·l_k`` (Lambertian, light ``k`` of
    strength ``f_k``, known direction ``l_k``). With ``u_k = 1 / f_k`` and ``b_i = ρ_i n_i`` this
    reads ``u_k I_ki = l_k·b_i``, linear in all unknowns, so the factors minimising the squared
    residual over a selection of samples are found directly: each pixel's ``b_i`` is eliminated
    in closed form, leaving the smallest eigenvector of an N×N matrix (the linear solution of
    semi-calibrated photometric stereo: Cho, Matsushita, Tai, Kweon, "Semi-calibrated
    photometric stereo", IEEE TPAMI 42(1), 2020). Alternating photometric stereo with
    per-photograph ratio updates converges to the same answer, but slowly.

    Robustness comes from the selection, which alternates with that solution: the first normals
    are fitted without each pixel's brightest fifth of samples and its darkest (tests that need
    no factors); then each round selects the samples that the Lambertian model describes, given
    the current normals and factors (:func:`_selection`: lit, away from the specular direction,
    residual not an outlier), solves for the factors and refits the normals, until no factor
    moves by more than 0.1 % or after ``iterations`` rounds. Pixels are a regular subsample of
    at most ``max_pixels``, so the time does not grow with the image size beyond reading them.

    Colour photographs (an array ``(N, H, W, C)``) get one factor per channel: the samples are
    selected once, on the luminance, and each channel's factors are then solved on those
    samples in the same way (each channel with its own albedo).

    Ambiguity: a global scale is unobservable (``f → s f`` with ``ρ → ρ / s`` explains the
    photographs as well), hence the normalisation to mean 1 (per channel). Beyond that the
    factors are determined when the lights do not all lie in one plane through the object
    apart from one line, and the normals are not all parallel. Both are checked
    (:func:`_undetermining_lights`, :func:`_check_normals_vary`); a surface whose normals vary
    little shows as a large :attr:`IntensityFit.spread`, and a photograph whose samples all fall
    in shadow or in the highlight cone is not measured. A gloss that Lambert's law does not
    describe, on a surface whose normals vary little, is read in part as a trend of the factors
    with the light's direction (on a glossy tablet under a broad lobe, errors of 5–10 %,
    ``benchmarks/intensities.py``).

    Parameters
    ----------
    images : ImageStack or ndarray, shape (N, H, W) or (N, H, W, C)
        The photographs, linear. An array of integers is taken as a fraction of its type's
        maximum, which marks a clipped sample; in a float array, NaN marks one. A sample with
        a clipped channel is not used.
    directions : ndarray, shape (N, 3)
        Unit light directions.
    iterations : int
        Most rounds of sample selection and solution (at least 1).
    mask : ndarray, shape (H, W), bool, optional
        Pixels to use (the object); default: every pixel lit in some photograph.
    max_pixels : int
        Size of the pixel subsample.

    Returns
    -------
    IntensityFit
        Factors ``(N,)`` for a stack or an ``(N, H, W)`` array, ``(N, C)`` for ``(N, H, W, C)``.

    Raises
    ------
    InputError
        If fewer than four photographs are given or can be measured, too few pixels are lit,
        the surface is flat, or the lights (or the lights and the lit surface) leave the factors
        undetermined.
    """
    n = len(images)
    if n < 4:
        raise InputError(
            f"{n} photographs: at least 4 are needed to estimate light intensities "
            "(with 3, any intensities fit equally well)"
        )
    dirs = as_directions(directions, n, np.float64)
    problem = _undetermining_lights(dirs)
    if problem is not None:
        raise InputError(problem)
    values, signal, usable, halves = _sample_pixels(images, mask, max(int(max_pixels), 1))
    if values.shape[1] < _MIN_SAMPLES:
        raise InputError(f"only {values.shape[1]} lit pixels: too few to estimate light intensities")
    outer = _light_outer(dirs)
    half = dirs + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)

    weights = _first_selection(signal, usable)
    factors = np.ones(n)
    rounds = max(1, int(iterations))
    for round_ in range(rounds):
        b, ok = _fit_scaled_normals(dirs, outer, signal / factors[:, None], weights)
        if round_ == 0:
            _check_normals_vary(b[ok])
        chosen = _selection(dirs, half, signal, usable, factors, b, ok)
        measured = chosen.sum(axis=1) >= _MIN_SAMPLES
        chosen[~measured] = 0.0
        solved = None
        if measured.sum() >= 4:
            forms = _quadratic_forms(dirs, outer, signal, chosen, halves)
            solved = _factors_from_form(forms.sum(axis=0), measured)
        if solved is None:
            if round_ == 0:
                raise InputError(
                    "the lights and the lit surface do not determine the light intensities "
                    f"({int(measured.sum())} photographs with enough usable pixels; too little "
                    "of the surface lit, or its normals too alike)"
                )
            rounds = round_
            break  # a degenerate re-selection: keep the previous round's answer
        change = np.abs(solved / factors - 1.0).max()
        factors, weights, kept = solved, chosen, (forms, measured)
        if change < _CONVERGED:
            rounds = round_ + 1
            break
    forms, measured = kept
    samples = np.count_nonzero(weights, axis=1)  # rows of unmeasured photographs are zero
    if isinstance(images, ImageStack) or images.ndim == 3:
        return IntensityFit(factors, _spread(forms, measured, factors), samples, rounds)
    per_channel = np.ones((n, values.shape[2]))
    spread = np.zeros_like(per_channel)
    for c in range(values.shape[2]):
        forms = _quadratic_forms(dirs, outer, values[..., c], weights, halves)
        solved = _factors_from_form(forms.sum(axis=0), measured)
        if solved is None:
            raise InputError(f"the samples do not determine the light intensities of channel {c + 1}")
        per_channel[:, c] = solved
        spread[:, c] = _spread(forms, measured, solved)
    return IntensityFit(per_channel, spread, samples, rounds)


def estimate_intensities(
    images: ImageStack | np.ndarray,
    directions: np.ndarray,
    *,
    iterations: int = 10,
    mask: np.ndarray | None = None,
    max_pixels: int = 20_000,
) -> np.ndarray:
    """The factors of :func:`fit_intensities`: ``(N,)`` float64 (``(N, C)`` for colour
    photographs), mean 1 over the photographs that could be measured; divide photograph ``k``
    by ``factors[k]`` to equalise the lights (:func:`apply_intensities`)."""
    return fit_intensities(
        images, directions, iterations=iterations, mask=mask, max_pixels=max_pixels
    ).factors


def apply_intensities(stack: ImageStack, factors: np.ndarray, *, relative: bool = False,
                      in_place: bool = False) -> ImageStack:
    """Divide each photograph's luminance by its light intensity factor.

    Parameters
    ----------
    stack : ImageStack
    factors : ndarray, shape (N,) or (N, 3)
        Positive factors, e.g. from :func:`read_intensities` or :func:`estimate_intensities`.
        Per-channel factors are reduced to their luminance-weighted value, since the stack holds
        luminance only.
    relative : bool
        Divide by the factors scaled to a minimum of 1 instead: only their ratios matter to the
        normals, and no sample is pushed past the stored range (the albedo's scale changes).
    in_place : bool
        Write the divided codes over the input's (a run's pipeline: no second stack in memory,
        and a stack on disk stays on disk, its pages released band by band).

    Returns
    -------
    ImageStack
        A new stack (the input is unchanged unless ``in_place``) with the same chroma and paths. Clipped samples
        stay clipped; a sample whose divided value exceeds the representable range (a factor
        below 1 on a bright sample) is marked clipped too, since its value cannot be stored.
        To avoid that, pass ``relative=True``.

    Raises
    ------
    ValueError
        If ``factors`` does not hold one positive, finite value (or triple) per photograph.
    """
    n = len(stack)
    f = np.asarray(factors, dtype=np.float64)
    if f.ndim == 2 and f.shape == (n, 3):
        f = f @ LUMA_WEIGHTS.astype(np.float64)
    if f.shape != (n,):
        raise ValueError(f"expected {n} intensity factors, got array of shape {np.shape(factors)}")
    if not np.all(np.isfinite(f) & (f > 0)):
        raise ValueError("intensity factors must be positive and finite")
    if relative:
        f = f / f.min()
    h, w = stack.shape
    out = stack.luminance if in_place else np.empty_like(stack.luminance)
    saturated = np.zeros(n, dtype=np.int64)
    rows = max(1, (1 << 20) // max(w, 1))
    for k in range(n):
        inv = np.float32(1.0 / f[k])
        for r0 in range(0, h, rows):
            # Both helpers read all of src before they write dst, so src may be dst.
            src = stack.luminance[k, r0 : r0 + rows]
            dst = out[k, r0 : r0 + rows]
            if src.dtype == np.uint16:
                clipped = _divide_uint16(src, inv, dst)
            else:
                clipped = _divide_codes(src, stack.table, inv, dst)
            saturated[k] += int(np.count_nonzero(clipped))
            release_rows(out, r0, r0 + rows, range(k, k + 1))
    return replace(stack, luminance=out, saturated=saturated)


def _divide_uint16(src: np.ndarray, inv: np.float32, dst: np.ndarray) -> np.ndarray:
    """uint16 codes × ``inv`` into ``dst``; returns where they are clipped."""
    clipped = src == SATURATED
    scaled = src.astype(np.float32) * inv
    clipped |= scaled > _LUM_SCALE + 0.5
    np.rint(np.minimum(scaled, _LUM_SCALE), out=scaled)
    dst[...] = scaled.astype(np.uint16)
    dst[clipped] = SATURATED
    return clipped


def _divide_codes(src: np.ndarray, table: np.ndarray, inv: np.float32, dst: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes (``load_stack(storage="auto")``): decoded through ``table``, scaled by
    ``inv`` and encoded again, 255 kept for clipped samples and for values beyond 1."""
    mark = np.iinfo(src.dtype).max
    scaled = table[src] * inv
    clipped = (src == mark) | (scaled > 1.0)
    code = np.rint(np.float32(255.0) * linear_to_srgb(scaled))
    dst[...] = np.minimum(code, mark - 1).astype(src.dtype)
    dst[clipped] = mark
    return clipped
