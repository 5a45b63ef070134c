"""Per-image light intensity factors, read from a file or estimated from the photographs.

RTI and photometric stereo take every photograph to be lit by a light of the same strength.
Flash units do not quite keep to that (a few per cent from shot to shot, more when a flash
has not fully recharged), and a dataset may list each light's measured brightness. Dividing
each photograph by its factor before the fit removes that error: Lambertian normals are
otherwise pulled towards the brighter lights.

* :func:`read_intensities` reads the factors from a text file (one value or ``r g b`` per
  photograph, in the order of the ``.lp`` file);
* :func:`estimate_intensities` estimates relative factors from the stack itself;
* :func:`apply_intensities` divides them out of an :class:`~ptmcore.images.ImageStack`.
"""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path

import numpy as np

from .errors import InputError, read_input_text
from .images import _LUM_SCALE, LUMA_WEIGHTS, SATURATED, ImageStack, linear_to_srgb
from .lp import as_directions

#: Samples with ``n·l`` below this are left out: dim, and the most sensitive to the normal's
#: error and to ambient light.
_MIN_SHADING = 0.1
#: Samples whose normal is within this angle of the half-way vector between light and camera
#: are left out: that is where specular highlights are, and their excess brightness would
#: otherwise be read as a brighter light.
_HIGHLIGHT_HALF_ANGLE_DEG = 30.0
#: First-pass shadow threshold: fraction of the pixel's brightest unsaturated sample.
_DARK_FRACTION = 0.05
#: Later passes keep samples whose relative residual is within this many robust standard
#: deviations (1.4826 × median absolute residual) of their photograph's median, and never
#: reject below the floor (noise of a clean capture).
_TRIM_SIGMAS = 3.0
_TRIM_FLOOR = 0.02
#: A photograph needs this many samples to measure its factor on.
_MIN_SAMPLES = 20


def read_numeric_rows(
    path: str | os.PathLike, what: str, widths: tuple[int, ...]
) -> tuple[np.ndarray, list[int]]:
    """Read a text file of whitespace-separated numbers, the same count on every line.

    Blank lines and ``#`` comments (whole-line or trailing) are skipped.

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
    text = read_input_text(path, what)
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
            vals = [float(f) for f in fields]
        except ValueError:
            raise InputError(f"line {no}: not a number: {raw.strip()[:60]!r}", path) from None
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


def _sample_pixels(
    stack: ImageStack, mask: np.ndarray | None, max_pixels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Luminance ``(N, P)`` float64 and usability ``(N, P)`` of evenly spread pixels.

    A regular subsample is enough: the factors are one number per photograph, measured over
    thousands of pixels, and a grid keeps the result deterministic.
    """
    h, w = stack.shape
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (h, w):
            raise ValueError(f"mask is {mask.shape} but the stack is {(h, w)}")
        candidates = np.flatnonzero(mask)
    else:
        candidates = np.arange(h * w)
    if candidates.size > max_pixels:
        candidates = candidates[np.linspace(0, candidates.size - 1, max_pixels).astype(np.int64)]
    rows, cols = np.divmod(candidates, w)
    raw = stack.luminance[:, rows, cols]  # (N, P) codes
    usable = raw != stack.saturated_code
    values = stack.table[raw].astype(np.float64)
    # Background (dark in every usable photograph) says nothing about the lights.
    lit = np.where(usable, values, 0.0).max(axis=0) > 2e-3
    return values[:, lit], usable[:, lit]


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
    ok = det > 1e-6 * np.maximum(count / 3.0, 1e-12) ** 3
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


def _least_squares_factors(
    dirs: np.ndarray, outer: np.ndarray, values: np.ndarray, weights: np.ndarray, chunk: int = 8192
) -> np.ndarray | None:
    """Factors minimising ``Σ w (v / f_k − l_k·b_i)²`` over both the factors and every ``b_i``.

    With ``u_k = 1 / f_k`` the model ``u_k v_ki = l_k·b_i`` is linear in ``(u, b)``;
    eliminating each pixel's ``b_i`` (variable projection) leaves a quadratic form ``uᵀ Q u``
    with ``Q = Σ_i D_i W_i D_i − A_iᵀ M_i⁻¹ A_i``, ``A_i = Lᵀ W_i D_i``, ``M_i = Lᵀ W_i L``.
    Its eigenvector of the smallest eigenvalue is the least-squares ``u`` (up to scale).
    Photographs without any weight are left out and get 1. Returns None if the answer is
    degenerate (not all positive).
    """
    n, p = values.shape
    q = np.zeros((n, n))
    for s in range(0, p, chunk):
        w = weights[:, s : s + chunk]
        wv = w * values[:, s : s + chunk]  # (N, Pc); weights are 0/1, so W D D W = W D²
        m, ok = _normal_matrices(outer, w)
        q[np.diag_indices(n)] += (wv * values[:, s : s + chunk])[:, ok].sum(axis=1)
        a = wv.T[ok][:, None, :] * dirs.T[None]  # (Pok, 3, N)
        mia = np.linalg.solve(m[ok], a)
        q -= a.reshape(-1, n).T @ mia.reshape(-1, n)
    keep = np.flatnonzero(weights.any(axis=1))
    q = q[np.ix_(keep, keep)]
    _, evecs = np.linalg.eigh(q)
    u = evecs[:, 0] * np.sign(evecs[:, 0].sum())
    if not np.all(u > 1e-6 * np.abs(u).max()):
        return None
    f = np.ones(n)
    f[keep] = 1.0 / u
    return f / f[keep].mean()


def estimate_intensities(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    iterations: int = 3,
    mask: np.ndarray | None = None,
    max_pixels: int = 20_000,
) -> np.ndarray:
    """Estimate relative per-photograph light intensity factors from the stack.

    Model: the luminance of pixel ``i`` in photograph ``k`` is ``f_k ρ_i n_i·l_k`` (Lambertian,
    light ``k`` of strength ``f_k``). With ``u_k = 1 / f_k`` and ``b_i = ρ_i n_i`` this reads
    ``u_k I_ki = l_k·b_i``, which is linear in all unknowns, so the factors minimising the
    squared residual over a selection of samples are found directly (each pixel's ``b_i``
    eliminated in closed form, leaving the smallest eigenvector of an N×N matrix) rather than
    by alternating photometric stereo and ratio updates, which converges slowly (the error
    shrinks by only about a fifth per sweep with 24 lights) and, with per-image medians,
    drifted to 1–2.5 % errors in tests where this reaches 0.1–0.5 %.

    Robustness comes from the selection, re-made in each of ``iterations`` rounds from the
    previous round's normals, albedo and factors: a sample is used if it is unsaturated, lit
    (``n·l ≥ 0.1``, so out of attached shadow), away from the specular direction (normal more
    than 30° from the half-way vector of light and camera), and its observed / predicted
    ratio is within a few robust standard deviations of its photograph's median ratio (so
    cast shadows, interreflections and the rest of a highlight are trimmed). The first round
    only drops clipped samples and those below 5 % of their pixel's brightest (shadows).
    Pixels are a regular subsample of at most ``max_pixels``; the factors are normalised to
    mean 1.

    Ambiguity: a global scale is unobservable (``f → s f`` with ``ρ → ρ / s`` explains the
    photographs as well), hence the normalisation. Beyond that the factors are determined when
    there are at least four lights not all lying in one plane through the origin plus one
    other line (in particular any four or more in general position) and the normals in the
    sample span three dimensions: other factors ``f'`` would need a 3×3 matrix ``A`` with
    ``(f'_k / f_k) l_k = A l_k`` for every light, i.e. every light direction an eigenvector
    of ``A``, which for such lights forces ``A`` to be a multiple of the identity. With three
    lights any factors are absorbed into the normals, so at least four photographs are needed.

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    iterations : int
        Rounds of sample selection and solution (at least 1).
    mask : ndarray, shape (H, W), bool, optional
        Pixels to use (the object); default: every pixel lit in some photograph.
    max_pixels : int
        Size of the pixel subsample.

    Returns
    -------
    ndarray, shape (N,), float64
        Factors with mean 1 over the photographs that could be measured; divide photograph
        ``k`` by ``factors[k]`` to equalise the lights (:func:`apply_intensities`). A
        photograph with fewer than 20 usable samples gets 1.

    Raises
    ------
    InputError
        If fewer than four photographs are given or can be measured, too few pixels are lit,
        or the lights and lit normals leave the factors undetermined.
    """
    n = len(stack)
    if n < 4:
        raise InputError(
            f"{n} photographs: at least 4 are needed to estimate light intensities "
            "(with 3, any intensities fit equally well)"
        )
    dirs = as_directions(directions, n, np.float64)
    values, usable = _sample_pixels(stack, mask, max(int(max_pixels), 1))
    if values.shape[1] < _MIN_SAMPLES:
        raise InputError(f"only {values.shape[1]} lit pixels: too few to estimate light intensities")
    outer = _light_outer(dirs)
    half = dirs + np.array([0.0, 0.0, 1.0])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    cos_highlight = np.cos(np.radians(_HIGHLIGHT_HALF_ANGLE_DEG))

    brightest = np.where(usable, values, 0.0).max(axis=0)
    selected = usable & (values > _DARK_FRACTION * brightest)
    factors = np.ones(n)
    for round_ in range(max(1, int(iterations))):
        # A photograph with too few samples cannot be measured; leaving it out of the solve
        # (rather than with a zero row) keeps the eigenproblem from picking it alone.
        measured = selected.sum(axis=1) >= _MIN_SAMPLES
        if measured.sum() < 4:
            raise InputError(
                f"only {int(measured.sum())} photographs have enough usable pixels: "
                "too few to estimate light intensities"
            )
        w = (selected & measured[:, None]).astype(np.float64)
        solved = _least_squares_factors(dirs, outer, values, w)
        if solved is None:
            if round_ == 0:
                raise InputError(
                    "the lights and the lit surface do not determine the light intensities "
                    "(lights nearly coplanar, or too little of the surface lit)"
                )
            break  # a degenerate re-selection: keep the previous round's answer
        factors = np.ones(n)
        factors[measured] = solved[measured] / solved[measured].mean()
        if round_ == max(1, int(iterations)) - 1:
            break
        b, ok = _fit_scaled_normals(dirs, outer, values / factors[:, None], w)
        rho = np.linalg.norm(b, axis=1)
        inv_rho = 1.0 / np.where(rho > 0, rho, 1.0)
        predicted = (dirs @ b.T) * factors[:, None]  # (N, P) observed brightness expected
        candidate = (
            usable
            & ok[None, :]
            & (predicted * inv_rho >= _MIN_SHADING * factors[:, None])
            & ((half @ b.T) * inv_rho < cos_highlight)
        )
        ratio = np.where(candidate, values / np.where(candidate, predicted, 1.0), np.nan)
        with np.errstate(all="ignore"):
            centre = np.nanmedian(ratio, axis=1, keepdims=True)
            dev = np.abs(ratio - centre)
            spread = 1.4826 * np.nanmedian(dev)
        tol = max(_TRIM_FLOOR, _TRIM_SIGMAS * float(spread)) if np.isfinite(spread) else np.inf
        selected = candidate & (dev <= tol)
    return factors


def apply_intensities(stack: ImageStack, factors: np.ndarray) -> ImageStack:
    """Divide each photograph's luminance by its light intensity factor.

    Parameters
    ----------
    stack : ImageStack
    factors : ndarray, shape (N,) or (N, 3)
        Positive factors, e.g. from :func:`read_intensities` or :func:`estimate_intensities`.
        Per-channel factors are reduced to their luminance-weighted value, since the stack holds
        luminance only.

    Returns
    -------
    ImageStack
        A new stack (the input is unchanged) with the same chroma and paths. Clipped samples
        stay clipped; a sample whose divided value exceeds the representable range (a factor
        below 1 on a bright sample) is marked clipped too, since its value cannot be stored.
        To avoid that, scale the factors so that their minimum is 1: only their ratios matter
        to the normals.

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
    h, w = stack.shape
    out = np.empty_like(stack.luminance)
    saturated = np.zeros(n, dtype=np.int64)
    rows = max(1, (1 << 20) // max(w, 1))
    for k in range(n):
        inv = np.float32(1.0 / f[k])
        for r0 in range(0, h, rows):
            src = stack.luminance[k, r0 : r0 + rows]
            dst = out[k, r0 : r0 + rows]
            if src.dtype == np.uint16:
                clipped = _divide_uint16(src, inv, dst)
            else:
                clipped = _divide_codes(src, stack.table, inv, dst)
            saturated[k] += int(np.count_nonzero(clipped))
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
