"""Robust per-pixel fits: photometric stereo and PTMs that leave out shadows and highlights.

The plain fits (:func:`ptmcore.fit.fit_ptm`, :func:`ptmcore.normals.photometric_stereo`) give
every photograph the same weight, or leave samples out by fixed thresholds. A sample in cast or
attached shadow, or on a specular highlight, is not explained by the Lambertian model, nor well
by the biquadratic PTM, and pulls the fit, and with it the normal, towards itself. Here each
pixel gets its own weights, from its own first estimate:

1. a first least-squares estimate without the dark samples (shadows) and the clipped ones;
2. a second one that also leaves out the samples in attached shadow (``n·l`` below
   ``min_shading``) and those whose mirror direction lies within ``specular_cone`` of the
   normal, where a highlight would be: a highlight covers several photographs on the same side
   of the normal, which pull a plain fit so far that they no longer stand out by their residual;
3. ``iterations`` passes of iteratively reweighted least squares (``method="irls"``: Tukey's
   biweight) or of trimming (``method="trimmed"``: weights 0 or 1). The residuals are measured
   in units of a per-pixel robust scale (the median absolute residual first, then the
   weighted RMS with its Gaussian consistency factor); a sample loses all weight beyond
   ``reject_below`` scales under the model or ``reject_above`` scales over it. The bound above
   is the tighter one: positive outliers (highlights) are common and come in groups of
   neighbouring lights, negative ones are mostly shadows, which are also left out outright (at
   ``n·l < min_shading``, or darker than ``cast_shadow_ratio`` × the prediction).

Each pass is a per-pixel weighted least-squares problem. It is solved through its normal
equations: the sums ``Σ w φ φᵀ`` (the unique entries of the outer products of the basis
functions, for all pixels of a band in one matrix product) and ``Σ w φ L`` (another), then a
batched Cholesky factorisation in float64, vectorised over the pixels. The basis is first
orthonormalised over the photographs (SVD of the light matrix), which keeps the float32 sums
well conditioned and makes light sets of lower rank (lights on one ring) solvable: the
coefficients are then the minimum-norm ones, as :func:`ptmcore.fit.fit_ptm` gives. A small
ridge towards the previous estimate keeps pixels with too few usable samples where they were.

PTM normals. The maximum of a PTM fitted to a Lambertian surface is biased towards the view
direction, whatever samples are used: ``n·l = nx·lu + ny·lv + nz·√(1 − lu² − lv²)`` and the
square root is not biquadratic. The fitted polynomial is exactly ``ρ (nx·lu + ny·lv + nz·q)``,
where ``q`` is the same fit (same weights) of ``lz = √(1 − lu² − lv²)`` alone, the
"hemisphere" PTM. At the maximum ``(lu0, lv0)`` the gradient vanishes, so
``(nx, ny) = −nz ∇q(lu0, lv0)``: :func:`debiased_normals` reads the normal from the maximum
through ``q``. On a Lambertian surface this is exact; the plain maximum
(:func:`ptmcore.normals.normals_from_ptm`) is not (see ``benchmarks/normals_table.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from .bands import band_rows, run_bands
from .fit import PTM, fit_matrix, light_matrix
from .images import ImageStack
from .lp import as_directions
from .normals import PhotometricStereo

#: Robust methods: Tukey-biweight IRLS, or trimming (0/1 weights) at the same bounds.
METHODS = ("irls", "trimmed")

_MAD_TO_SIGMA = 1.4826
#: Memory for one band of the stack as float32; a band's per-pixel float64 work arrays are
#: about as large again, and smaller bands also spread over more threads.
_BAND_BYTES = 4 << 20
#: Relative ridge of the per-pixel solves (× the mean eigenvalue of the normal matrix).
_RIDGE = 1e-6
#: A normal matrix whose determinant is below this × (mean eigenvalue)^rank is singular.
_SINGULAR = 1e-6
_UP = np.array([[0.0], [0.0], [1.0]])


# --------------------------------------------------------------------------------------------
# Per-pixel weighted least squares


@dataclass(frozen=True)
class _Basis:
    """An orthonormalised model basis over the photographs.

    Attributes
    ----------
    u : ndarray, shape (N, r), float32
        Orthonormal columns spanning the model's basis functions at the N lights.
    back : ndarray, shape (m, r), float64
        Maps solutions in ``u`` to the model's own m coefficients.
    outer : ndarray, shape (N, K), float32
        Products of the pairs of columns of ``[u, extra]`` (upper triangle, row by row), so
        ``outer.T @ w`` gives every pixel's weighted sums at once.
    """

    u: np.ndarray
    back: np.ndarray
    outer: np.ndarray

    @property
    def rank(self) -> int:
        return self.u.shape[1]


def _basis(phi: np.ndarray, extra: np.ndarray | None = None) -> _Basis:
    """Orthonormalise the N×m basis ``phi``; ``extra`` (N×e) columns join the sums only."""
    u, s, vt = np.linalg.svd(phi, full_matrices=False)
    rank = int(np.count_nonzero(s > s[0] * 1e-6))
    u, s, vt = u[:, :rank], s[:rank], vt[:rank]
    cols = u if extra is None else np.column_stack([u, extra])
    i, j = np.triu_indices(cols.shape[1])
    return _Basis(u.astype(np.float32), vt.T / s, (cols[:, i] * cols[:, j]).astype(np.float32))


def _packed(k: int) -> np.ndarray:
    """Index of entry (i, j) of a symmetric k×k matrix stored as its upper triangle."""
    index = np.zeros((k, k), dtype=np.intp)
    i, j = np.triu_indices(k)
    index[i, j] = index[j, i] = np.arange(len(i))
    return index


def _cholesky_solve(
    gram: np.ndarray, rhs: list[np.ndarray], prior: list[np.ndarray] | None
) -> tuple[list[np.ndarray], np.ndarray]:
    """Solve ``(G + λI) x = b + λ x_prior`` for every pixel.

    Parameters
    ----------
    gram : ndarray, shape (K, P), float64
        Each pixel's r×r normal matrix G as its upper triangle (packed by :func:`_packed`).
    rhs : list of ndarray, shape (r, P), float64
        Right-hand sides b.
    prior : list of ndarray, shape (r, P), or None
        Where a pixel's system is (nearly) singular, its solution tends to these (or to 0).

    Returns
    -------
    solutions : list of ndarray, shape (r, P)
    well_posed : ndarray, shape (P,), bool
        Where G alone is far from singular.

    The factorisation runs over the r(r + 1)/2 entries, each a vector over the pixels: about
    r³/6 vector operations instead of P calls of a LAPACK routine, or a (P, r, r) copy for a
    batched one (3–7× slower here).
    """
    r = rhs[0].shape[0]
    index = _packed(r)
    mean_eig = sum(gram[index[i, i]] for i in range(r)) / r
    lam = _RIDGE * np.maximum(mean_eig, 1e-30)
    low: list[list[np.ndarray]] = [[] for _ in range(r)]
    log_det = np.zeros_like(mean_eig)
    for j in range(r):
        d = gram[index[j, j]] + lam
        for k in range(j):
            d = d - low[j][k] * low[j][k]
        d = np.sqrt(np.maximum(d, lam))
        log_det += 2.0 * np.log(d)
        inv = 1.0 / d
        for i in range(j + 1, r):
            s = gram[index[i, j]]
            for k in range(j):
                s = s - low[i][k] * low[j][k]
            low[i].append(s * inv)
        low[j].append(d)
    solutions = []
    for q, b in enumerate(rhs):
        y: list[np.ndarray] = []
        for i in range(r):
            s = b[i] if prior is None else b[i] + lam * prior[q][i]
            for k in range(i):
                s = s - low[i][k] * y[k]
            y.append(s / low[i][i])
        x: list[np.ndarray] = [y[0]] * r
        for i in reversed(range(r)):
            s = y[i]
            for k in range(i + 1, r):
                s = s - low[k][i] * x[k]
            x[i] = s / low[i][i]
        solutions.append(np.stack(x))
    well_posed = log_det > r * np.log(np.maximum(mean_eig, 1e-30)) + np.log(_SINGULAR)
    return solutions, well_posed


# --------------------------------------------------------------------------------------------
# Robust weights


@lru_cache(maxsize=16)
def _consistency(method: str, below: float, above: float) -> float:
    """RMS of standard-normal residuals under the weights at bounds (below, above).

    Dividing a weighted RMS by it makes the scale estimate σ when the inliers are Gaussian;
    otherwise the scale would shrink at every pass.
    """
    r = np.linspace(-below, above, 20001)
    density = np.exp(-0.5 * r * r)
    w = _tukey(r, np.where(r > 0, above, below)) if method == "irls" else np.ones_like(r)
    return float(np.sqrt(np.sum(w * r * r * density) / np.sum(w * density)))


def _tukey(u: np.ndarray, c: np.ndarray | float) -> np.ndarray:
    t = u / c
    t *= t
    np.subtract(1.0, t, out=t)
    np.maximum(t, 0.0, out=t)
    t *= t
    return t


def _robust_weights(method: str, res: np.ndarray, scale: np.ndarray, below: float, above: float
                    ) -> np.ndarray:
    """Weights in [0, 1] of residuals ``res`` (N, P) given each pixel's scale (P,)."""
    bound = np.where(res > 0, np.float32(above), np.float32(below)) * scale
    if method == "trimmed":
        return (np.abs(res) <= bound).astype(np.float32)
    return _tukey(res, bound)


def _median_abs(res: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-pixel median of ``|res|`` over the samples in ``mask`` (0 where there are none)."""
    a = np.abs(res)
    a[~mask] = np.inf
    # Sorting along the contiguous axis is several times faster than along the photographs.
    a = np.ascontiguousarray(a.T)
    a.sort(axis=1)
    count = np.count_nonzero(mask, axis=0)
    med = a[np.arange(a.shape[0]), np.maximum(count - 1, 0) // 2]
    return np.where(count > 0, med, 0.0)


def _scale(method: str, res: np.ndarray, candidates: np.ndarray, weights: np.ndarray | None,
           below: float, above: float) -> np.ndarray:
    """Robust per-pixel scale of the residuals of the candidate samples.

    The first pass (``weights`` None) takes the median absolute residual, which resists up to
    half the samples being outliers but needs a sort; later passes take the RMS under the
    previous weights, which no longer include the outliers.
    """
    if weights is None:
        return _MAD_TO_SIGMA * _median_abs(res, candidates)
    w = weights * candidates
    num = np.einsum("np,np,np->p", w, res, res)
    den = w.sum(axis=0)
    rms = np.sqrt(num / np.maximum(den, 1e-12))
    return rms / _consistency(method, below, above)


def _check_method(method: str, iterations: int, below: float, above: float) -> None:
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if iterations < 0:
        raise ValueError(f"iterations must be ≥ 0, got {iterations}")
    if not (below > 0 and above > 0):
        raise ValueError("reject_below and reject_above must be positive")


def _half_vectors(dirs: np.ndarray) -> np.ndarray:
    """Unit half vectors between each light and the view direction (0, 0, 1), float32."""
    h = dirs + np.array([0.0, 0.0, 1.0])
    return (h / np.linalg.norm(h, axis=1, keepdims=True)).astype(np.float32)


def _unit(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (3, P) float32 and lengths (P,) of the columns of ``g``."""
    rho = np.sqrt(np.einsum("ip,ip->p", g, g))
    return (g / np.where(rho > 0, rho, 1.0)).astype(np.float32), rho


# --------------------------------------------------------------------------------------------
# Photometric stereo


def robust_photometric_stereo(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    method: str = "irls",
    iterations: int = 3,
    dark_fraction: float = 0.05,
    min_shading: float = 0.05,
    cast_shadow_ratio: float = 0.4,
    specular_cone: float | None = 30.0,
    reject_below: float = 3.0,
    reject_above: float = 2.0,
    noise_floor: float = 0.002,
    relative_floor: float = 0.01,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> PhotometricStereo:
    """Lambertian photometric stereo with per-pixel robust weights.

    Each pixel solves ``I_i = ρ n·l_i`` by weighted least squares, with weights from the steps
    in the module description: shadows and clipped samples out, a first estimate, the
    specular cone out, then ``iterations`` robust passes.

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    method : {"irls", "trimmed"}
        Tukey-biweight weights, or 0/1 weights at the same bounds.
    iterations : int
        Robust passes after the two first estimates.
    dark_fraction : float
        The first estimate leaves out samples darker than this × the pixel's brightest.
    min_shading : float
        Samples with ``n·l`` below this (attached shadow, grazing light) are left out.
    cast_shadow_ratio : float
        Samples darker than this × the prediction (cast shadow) are left out.
    specular_cone : float or None
        Half-angle in degrees: the second estimate leaves out lights whose half vector lies
        within it of the first normal. None skips that estimate.
    reject_below, reject_above : float
        Residuals, in robust scales, under and over the prediction beyond which a sample has
        no weight.
    noise_floor, relative_floor : float
        The scale is at least ``noise_floor + relative_floor · ρ`` (luminance units), so clean
        data are not trimmed to their rounding errors.
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    PhotometricStereo
        ``samples`` is the sum of the final weights, rounded.
    """
    _check_method(method, iterations, reject_below, reject_above)
    n = len(stack)
    h, w = stack.shape
    dirs = as_directions(directions, n)
    basis = _basis(dirs)
    dirs32 = dirs.astype(np.float32)
    halves = _half_vectors(dirs)
    cos_cone = None if specular_cone is None else np.float32(np.cos(np.radians(specular_cone)))
    normals = np.empty((h, w, 3), dtype=np.float32)
    albedo = np.empty((h, w), dtype=np.float32)
    samples = np.empty((h, w), dtype=np.uint16)
    valid = np.empty((h, w), dtype=bool)

    def solve(v: np.ndarray, wts: np.ndarray, prior: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        gram = (basis.outer.T @ wts).astype(np.float64)
        b = (basis.u.T @ (wts * v)).astype(np.float64)
        (c,), ok = _cholesky_solve(gram, [b], None if prior is None else [prior])
        return c, ok

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        v = values.reshape(n, -1)
        usable = ~saturated.reshape(n, -1)
        wts = (v > np.maximum(dark_fraction * v.max(axis=0), 1e-4)) & usable
        c, ok = solve(v, wts.astype(np.float32), None)
        if cos_cone is not None:
            unit, _ = _unit(basis.back @ c)
            wts = (dirs32 @ unit > min_shading) & (halves @ unit < cos_cone) & usable
            c_new, ok_new = solve(v, wts.astype(np.float32), c)
            # Too few samples outside the cone: keep the first estimate.
            c = np.where(ok_new, c_new, c)
        weights = None
        for _ in range(iterations):
            unit, rho = _unit(basis.back @ c)
            shading = dirs32 @ unit
            candidates = (shading > min_shading) & usable
            shading *= rho.astype(np.float32)  # now the prediction
            candidates &= v >= cast_shadow_ratio * shading
            res = np.subtract(v, shading, out=shading)
            scale = _scale(method, res, candidates, weights, reject_below, reject_above)
            scale = np.maximum(scale, noise_floor + relative_floor * rho).astype(np.float32)
            weights = _robust_weights(method, res, scale, reject_below, reject_above)
            weights *= candidates
            c_new, ok_new = solve(v, weights, c)
            c = np.where(ok_new, c_new, c)
            ok |= ok_new
        g = basis.back @ c
        unit, rho = _unit(g)
        good = ok & (rho > 0) & np.isfinite(rho)
        used = wts.sum(axis=0) if weights is None else weights.sum(axis=0)
        normals[r0:r1] = np.where(good, unit, _UP).T.reshape(r1 - r0, w, 3)
        albedo[r0:r1] = np.where(good, rho, 0.0).reshape(r1 - r0, w)
        samples[r0:r1] = np.round(used).reshape(r1 - r0, w)
        valid[r0:r1] = good.reshape(r1 - r0, w)

    run_bands(h, band_rows(n, w, 4, _BAND_BYTES), work, threads=threads, progress=progress)
    return PhotometricStereo(normals, albedo, samples, valid)


# --------------------------------------------------------------------------------------------
# PTM


def hemisphere_coefficients(directions: np.ndarray) -> np.ndarray:
    """The plain least-squares PTM of ``lz`` over the lights: (6,) float64.

    It is the ``hemisphere`` to pass to :func:`debiased_normals` for a PTM fitted by
    :func:`ptmcore.fit.fit_ptm` (or read from a file) with these lights.
    """
    d = np.asarray(directions, dtype=np.float64)
    return fit_matrix(d) @ d[:, 2]


def _debiased(a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Normals (3, P) from PTM coefficients ``a`` and hemisphere PTMs ``q`` (6, P), float64."""
    a0, a1, a2, a3, a4 = a[:5]
    q0, q1, q2, q3, q4 = q[:5]
    det = 4 * a0 * a1 - a2 * a2
    concave = (a0 < 0) & (det > 0)
    det = np.where(concave, det, 1.0)
    # The stationary point of the polynomial (inside the unit disk or not: on a steep slope
    # it is outside, and the map below still brings it back).
    lu = (a2 * a4 - 2 * a1 * a3) / det
    lv = (a2 * a3 - 2 * a0 * a4) / det
    # Where the polynomial has no maximum, read ρ·nz as the factor between its quadratic part
    # and the hemisphere's (least squares), and ρ·(nx, ny) as what is left of its linear part.
    qq = q0 * q0 + q1 * q1 + 0.5 * q2 * q2
    rho_z = (a0 * q0 + a1 * q1 + 0.5 * a2 * q2) / np.where(qq > 0, qq, 1.0)
    g = np.stack([
        np.where(concave, -(2 * q0 * lu + q2 * lv + q3), a3 - rho_z * q3),
        np.where(concave, -(2 * q1 * lv + q2 * lu + q4), a4 - rho_z * q4),
        np.where(concave, 1.0, rho_z),
    ])
    unit, length = _unit(g)
    bad = ~(length > 0) | ~np.isfinite(length) | (unit[2] <= 0)
    return np.where(bad, _UP, unit)


def debiased_normals(coefficients: np.ndarray, hemisphere: np.ndarray) -> np.ndarray:
    """Normals from each PTM's maximum, read through the fit's model of the hemisphere.

    For a Lambertian pixel the fitted PTM is ``ρ (nx·lu + ny·lv + nz·q)`` with ``q`` the
    ``hemisphere`` PTM (the same fit of ``lz``), so at its maximum ``(lu0, lv0)``
    ``(nx, ny) = −nz ∇q(lu0, lv0)``. Where the polynomial has no maximum (not concave),
    ``ρ·nz`` is read from its quadratic part and ``ρ·(nx, ny)`` from the rest of its linear
    part.

    Parameters
    ----------
    coefficients : ndarray, shape (..., 6)
        PTM coefficients.
    hemisphere : ndarray, shape (..., 6) or (6,)
        The fit's PTM of ``lz``: per pixel from :func:`robust_ptm`, or one for all pixels from
        :func:`hemisphere_coefficients` for a plain fit.

    Returns
    -------
    ndarray, shape (..., 3), float32
        Unit normals; (0, 0, 1) where none can be read.
    """
    coefficients = np.asarray(coefficients)
    shape = coefficients.shape[:-1]
    a = coefficients.reshape(-1, 6).T.astype(np.float64)
    q = np.broadcast_to(np.asarray(hemisphere, dtype=np.float64), coefficients.shape).reshape(-1, 6).T
    out = np.empty((a.shape[1], 3), dtype=np.float32)
    step = 1 << 16  # bounded float64 temporaries for large maps
    for p0 in range(0, a.shape[1], step):
        out[p0 : p0 + step] = _debiased(a[:, p0 : p0 + step], q[:, p0 : p0 + step]).T
    return out.reshape(*shape, 3)


@dataclass
class RobustPTM:
    """Result of :func:`robust_ptm`.

    Attributes
    ----------
    ptm : PTM
        The robustly fitted PTM (coefficients in linear luminance, as ``fit_ptm``).
    hemisphere : ndarray, shape (H, W, 6), float32
        Per pixel, the same weighted fit of ``lz``: what :func:`debiased_normals` needs.
    normals : ndarray, shape (H, W, 3), float32
        ``debiased_normals(ptm.coefficients, hemisphere)``.
    samples : ndarray, shape (H, W), float32
        Sum of the final weights (the number of photographs that count).
    """

    ptm: PTM
    hemisphere: np.ndarray
    normals: np.ndarray
    samples: np.ndarray


def robust_ptm(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    method: str = "irls",
    normals: np.ndarray | None = None,
    iterations: int = 2,
    dark_fraction: float = 0.05,
    min_shading: float = 0.05,
    cast_shadow_ratio: float = 0.4,
    specular_cone: float | None = 30.0,
    reject_below: float = 3.0,
    reject_above: float = 2.0,
    noise_floor: float = 0.002,
    relative_floor: float = 0.01,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> RobustPTM:
    """Fit a PTM per pixel without its shadowed, clipped and specular samples.

    Same steps as :func:`robust_photometric_stereo`, with the PTM polynomial as the model of
    the samples. Which samples are in attached shadow or in the specular cone is decided by a
    normal: ``normals`` if given (e.g. from robust photometric stereo), else the fit's own
    :func:`debiased_normals`, updated at every pass.

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    method : {"irls", "trimmed"}
    normals : ndarray, shape (H, W, 3), optional
        Normals deciding the attached shadows and the specular cone.
    iterations : int
        Robust passes after the two first estimates.
    dark_fraction, min_shading, cast_shadow_ratio, specular_cone, reject_below, reject_above,
    noise_floor, relative_floor
        As in :func:`robust_photometric_stereo` (the prediction is the polynomial's, ρ its
        value at the normal).
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    RobustPTM
    """
    _check_method(method, iterations, reject_below, reject_above)
    n = len(stack)
    h, w = stack.shape
    dirs = as_directions(directions, n)
    if normals is not None and normals.shape != (h, w, 3):
        raise ValueError(f"normals must have shape {(h, w, 3)}, got {normals.shape}")
    phi = light_matrix(dirs)
    # lz joins the sums as an extra column: the same factorisation then also fits the
    # hemisphere PTM, for the debiased normals.
    basis = _basis(phi, dirs[:, 2:3])
    r = basis.rank
    index = _packed(r + 1)
    gram_rows = np.array([index[i, j] for i in range(r) for j in range(i, r)])
    z_rows = index[:r, r]
    dirs32 = dirs.astype(np.float32)
    halves = _half_vectors(dirs)
    cos_cone = None if specular_cone is None else np.float32(np.cos(np.radians(specular_cone)))
    phi32 = phi.astype(np.float32)
    coef = np.empty((h, w, 6), dtype=np.float32)
    hemi = np.empty((h, w, 6), dtype=np.float32)
    nout = np.empty((h, w, 3), dtype=np.float32)
    used = np.empty((h, w), dtype=np.float32)

    def solve(v: np.ndarray, wts: np.ndarray, prior: list[np.ndarray] | None
              ) -> tuple[np.ndarray, np.ndarray]:
        sums = (basis.outer.T @ wts).astype(np.float64)
        b = (basis.u.T @ (wts * v)).astype(np.float64)
        (c, cz), _ = _cholesky_solve(sums[gram_rows], [b, sums[z_rows]], prior)
        return c, cz

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        v = values.reshape(n, -1)
        usable = ~saturated.reshape(n, -1)
        if normals is None:
            wts = (v > np.maximum(dark_fraction * v.max(axis=0), 1e-4)) & usable
            c, cz = solve(v, wts.astype(np.float32), None)
            unit = _debiased(basis.back @ c, basis.back @ cz).astype(np.float32)
            prior = [c, cz]
        else:
            unit = normals[r0:r1].reshape(-1, 3).T.astype(np.float32)
            prior = None
        shading = dirs32 @ unit
        wts = (shading > min_shading) & usable
        if cos_cone is not None:
            wts &= halves @ unit < cos_cone
        c, cz = solve(v, wts.astype(np.float32), prior)
        weights = None
        for _ in range(iterations):
            a = basis.back @ c
            if normals is None:
                unit = _debiased(a, basis.back @ cz).astype(np.float32)
                shading = dirs32 @ unit
            candidates = (shading > min_shading) & usable
            pred = basis.u @ c.astype(np.float32)
            candidates &= v >= cast_shadow_ratio * pred
            # The polynomial's value at the normal stands for the albedo in the floor.
            rho = np.abs(np.einsum("ip,ip->p", light_matrix(unit.T).T, a))
            res = np.subtract(v, pred, out=pred)
            scale = _scale(method, res, candidates, weights, reject_below, reject_above)
            scale = np.maximum(scale, noise_floor + relative_floor * rho).astype(np.float32)
            weights = _robust_weights(method, res, scale, reject_below, reject_above)
            weights *= candidates
            c, cz = solve(v, weights, [c, cz])
        a = basis.back @ c
        q = basis.back @ cz
        coef[r0:r1] = a.T.reshape(r1 - r0, w, 6)
        hemi[r0:r1] = q.T.reshape(r1 - r0, w, 6)
        nout[r0:r1] = _debiased(a, q).T.reshape(r1 - r0, w, 3)
        final = wts.astype(np.float32) if weights is None else weights
        used[r0:r1] = final.sum(axis=0).reshape(r1 - r0, w)

    del phi32
    run_bands(h, band_rows(n, w, 4, _BAND_BYTES), work, threads=threads, progress=progress)
    return RobustPTM(PTM(coef, stack.chroma), hemi, nout, used)


def robust_fit_ptm(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    method: str = "irls",
    normals: np.ndarray | None = None,
    iterations: int = 2,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
    **options: float | None,
) -> PTM:
    """:func:`robust_ptm`'s PTM alone (usable with :func:`ptmcore.normals.normals_from_ptm`).

    ``options`` are the thresholds of :func:`robust_ptm`.
    """
    return robust_ptm(stack, directions, method=method, normals=normals, iterations=iterations,
                      threads=threads, progress=progress, **options).ptm
