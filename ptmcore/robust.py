"""Robust per-pixel fits: photometric stereo and PTMs that leave out shadows and highlights.

The plain fits (:func:`ptmcore.fit.fit_ptm`, :func:`ptmcore.normals.photometric_stereo`) weight
every photograph equally, or drop samples by fixed thresholds. A sample in cast or attached
shadow, or on a specular highlight, fits neither the Lambertian model nor the biquadratic PTM
well, and it pulls the fit (and so the normal) towards itself. Here every pixel gets its own
weights, built from its own earlier estimates:

1. a first Lambertian estimate without the dark samples (shadows) and the clipped ones;
2. a second one that also drops the samples in attached shadow (``n·l < min_shading``) and
   those whose half vector is within ``specular_cone`` of the first normal, which is where a
   highlight would be. A highlight covers several neighbouring lights on one side of the normal
   and pulls a least-squares fit so far towards them that their residuals no longer stand out.
   The cone is needed to break that;
3. ``iterations`` robust passes: iteratively reweighted least squares with Tukey's biweight
   (``method="irls"``), or trimming with weights of 0 or 1 (``method="trimmed"``). Residuals are
   measured in a per-pixel scale: on the first pass, the RMS residual of step 2 over its own
   samples; after that, the RMS under the previous weights divided by its Gaussian consistency
   factor. A sample gets no weight once it is ``reject_below`` scales under the model or
   ``reject_above`` scales over it. The upper bound is the tighter one. Positive outliers
   (highlights) are common and come in groups. Negative ones are mostly shadows, and those are
   also dropped outright: at ``n·l < min_shading``, or when darker than
   ``cast_shadow_ratio`` × the prediction.

Each pass is a per-pixel weighted least-squares problem (:mod:`ptmcore.pixelfit`). The PTM fitted
with these weights, and normals read from it without the PTM's bias, are in
:mod:`ptmcore.robustptm`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from .bands import band_rows, run_bands
from .diskstack import release_rows
from .images import ImageStack
from .lobe import DEGREE, Lobe, estimate_lobe, lobe_factors
from .lp import as_directions
from .normals import PhotometricStereo, empty_result, store_normals
from .pixelfit import Basis, blocked_matmul, orthonormal_basis, weighted_fit

if TYPE_CHECKING:  # robustptm imports this module
    from .robustptm import KernelPTM

__all__ = ["METHODS", "robust_photometric_stereo", "robust_rows"]

#: Robust methods: Tukey-biweight IRLS, or trimming (weights 0 or 1) at the same bounds.
METHODS = ("irls", "trimmed")

_MAD_TO_SIGMA = 1.4826
#: Memory for one band of the stack as float32. Each band's float64 work arrays take about as
#: much again, and smaller bands spread across more threads.
_BAND_BYTES = 4 << 20
#: Pixels per band of the compiled photometric stereo.
_KERNEL_PIXELS = 1 << 16
#: The kernel's coefficients when there is no lobe (it does not read them).
_NO_LOBE = np.zeros(DEGREE + 1)
#: The stricter test of the specular cone's fit (see :func:`_lambertian_start`).
_CONE_SINGULAR = 1e-3


def band_height(n: int, width: int) -> int:
    """Rows per band of the robust fits, for ``n`` photographs ``width`` pixels wide."""
    return band_rows(n, width, 4, _BAND_BYTES)


# --------------------------------------------------------------------------------------------
# Robust weights


def _tukey(t: np.ndarray) -> np.ndarray:
    """Tukey's biweight ``max(0, 1 − t²)²`` of ``t`` (residual / bound), in place."""
    t *= t
    np.subtract(1.0, t, out=t)
    np.maximum(t, 0.0, out=t)
    t *= t
    return t


@lru_cache(maxsize=16)
def _consistency(method: str, below: float, above: float) -> float:
    """RMS of standard-normal residuals under the weights with bounds (below, above).

    Dividing a weighted RMS by this factor gives σ when the inliers are Gaussian. Without it
    the scale would shrink at every pass.
    """
    r = np.linspace(-below, above, 20001)
    density = np.exp(-0.5 * r * r)
    w = _tukey(r / np.where(r > 0, above, below)) if method == "irls" else np.ones_like(r)
    return float(np.sqrt(np.sum(w * r * r * density) / np.sum(w * density)))


def _robust_weights(method: str, res: np.ndarray, scale: np.ndarray, below: float, above: float,
                    candidates: np.ndarray) -> np.ndarray:
    """Weights in [0, 1] of residuals ``res`` (N, P), given each pixel's scale (P,)."""
    hi = (scale * above).astype(np.float32)
    lo = (scale * -below).astype(np.float32)
    if method == "trimmed":
        keep = res <= hi
        keep &= res >= lo
        keep &= candidates
        return keep.astype(np.float32)
    # |res| / bound with the bound of its sign, in three passes: of res/hi and res/lo,
    # the larger is the one with the right sign.
    t = res / hi
    np.maximum(t, res / lo, out=t)
    t = _tukey(t)
    t *= candidates
    return t


def _median_abs(res: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per-pixel median of ``|res|`` over the samples in ``mask`` (0 where there are none)."""
    a = np.abs(res)
    a[~mask] = np.inf
    # Sorting along the contiguous axis is several times faster than sorting across the
    # photographs, even with the copy.
    a = np.ascontiguousarray(a.T)
    a.sort(axis=1)
    count = np.count_nonzero(mask, axis=0)
    med = a[np.arange(a.shape[0]), np.maximum(count - 1, 0) // 2]
    return np.where(count > 0, med, 0.0)


def _weighted_rms(res: np.ndarray, weights: np.ndarray, dof: float) -> np.ndarray:
    """Per-pixel RMS of the residuals under ``weights``, with ``dof`` parameters fitted to them."""
    num = np.einsum("np,np->p", weights * res, res)
    den = np.maximum(weights.sum(axis=0) - dof, 1.0)
    return np.sqrt(num / den)


@dataclass(frozen=True)
class RobustOptions:
    """The thresholds shared by the robust fits (see :func:`robust_photometric_stereo`)."""

    method: str
    iterations: int
    dark_fraction: float
    min_shading: float
    cast_shadow_ratio: float
    specular_cone: float | None
    reject_below: float
    reject_above: float
    noise_floor: float
    relative_floor: float

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.iterations < 0:
            raise ValueError(f"iterations must be ≥ 0, got {self.iterations}")
        if not (self.reject_below > 0 and self.reject_above > 0):
            raise ValueError("reject_below and reject_above must be positive")
        if self.specular_cone is not None and not 0 < self.specular_cone < 90:
            raise ValueError(f"specular_cone must be in (0, 90) degrees, got {self.specular_cone}")

    @property
    def cos_cone(self) -> np.float32 | None:
        return None if self.specular_cone is None else np.float32(np.cos(np.radians(self.specular_cone)))

    @property
    def consistency(self) -> float:
        return _consistency(self.method, self.reject_below, self.reject_above)


def reweight(opt: RobustOptions, res: np.ndarray, candidates: np.ndarray, weights: np.ndarray,
             first: bool, dof: int, rho: np.ndarray) -> np.ndarray:
    """One robust pass's weights from the residuals and the previous weights."""
    if not first:
        scale = _weighted_rms(res, weights, 0.0) / opt.consistency
    elif opt.specular_cone is not None:
        # The residuals of the cone fit, over its own samples.
        scale = _weighted_rms(res, weights, dof)
    else:
        # Without the cone, those samples can still hold highlights, so use their median.
        scale = _MAD_TO_SIGMA * _median_abs(res, candidates)
    # A floor, so clean data are not trimmed down to their rounding errors.
    scale = np.maximum(scale, opt.noise_floor + opt.relative_floor * rho)
    return _robust_weights(opt.method, res, scale, opt.reject_below, opt.reject_above, candidates)


def unit_columns(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors (3, P) float32 and lengths (P,) of the columns of ``g``."""
    rho = np.sqrt(np.einsum("ip,ip->p", g, g))
    return (g / np.where(rho > 0, rho, 1.0)).astype(np.float32), rho


def _half_vectors(dirs: np.ndarray) -> np.ndarray:
    """Unit half vectors between each light and the view direction (0, 0, 1), float32."""
    h = dirs + np.array([0.0, 0.0, 1.0])
    return (h / np.linalg.norm(h, axis=1, keepdims=True)).astype(np.float32)


@dataclass(frozen=True)
class Lights:
    """Light directions in the forms the band workers use."""

    dirs: np.ndarray  # (N, 3) float32
    halves: np.ndarray  # (N, 3) float32
    lambertian: Basis  # of the directions themselves

    @classmethod
    def of(cls, dirs: np.ndarray) -> Lights:
        return cls(dirs.astype(np.float32), _half_vectors(dirs), orthonormal_basis(dirs))


def _lambertian_start(lights: Lights, opt: RobustOptions, v: np.ndarray, usable: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1 and 2 for one band.

    Returns ``g = ρn`` in the orthonormal basis (3, P), where the first fit was well posed
    (P,), and the weights (0 or 1) of the last fit, float32 (N, P).
    """
    basis = lights.lambertian
    weights = ((v > np.maximum(opt.dark_fraction * v.max(axis=0), 1e-4)) & usable).astype(np.float32)
    (c,), ok = weighted_fit(basis, v, weights, None)
    if opt.cos_cone is not None:
        unit, _ = unit_columns(blocked_matmul(basis.back, c))
        cone = blocked_matmul(lights.dirs, unit) > opt.min_shading
        cone &= blocked_matmul(lights.halves, unit) < opt.cos_cone
        cone &= usable
        (c_cone,), ok_cone = weighted_fit(basis, v, cone.astype(np.float32), [c], _CONE_SINGULAR)
        # Where the samples outside the cone are too few or too close together (lights on
        # one ring leave an arc), or the normal moved out of the cone, the first estimate
        # stays: the cone's fit is only meant to undo a highlight's pull.
        unit_cone, _ = unit_columns(blocked_matmul(basis.back, c_cone))
        ok_cone &= np.einsum("ip,ip->p", unit_cone, unit) > opt.cos_cone
        c = np.where(ok_cone, c_cone, c)
        weights = np.where(ok_cone, cone, weights)
    return c, ok, weights


def _albedo(shading: np.ndarray, v: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Per-pixel weighted least squares of ``v = ρ·shading`` for ρ alone, float64."""
    ws = weights * shading
    num = np.einsum("np,np->p", ws, v)
    den = np.einsum("np,np->p", ws, shading)
    return (num / np.maximum(den, 1e-12)).astype(np.float64)


def robust_lambertian(lights: Lights, opt: RobustOptions, v: np.ndarray, usable: np.ndarray,
                      unit: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1–3 with the Lambertian model for one band.

    With ``unit`` (3, P) given, the normals stay fixed and only ρ is fitted.

    Returns
    -------
    unit : ndarray, shape (3, P), float32
    rho : ndarray, shape (P,), float64
    ok : ndarray, shape (P,), bool
        Where some fit was well posed.
    weights : ndarray, shape (N, P), float32
        The final weights.
    """
    basis = lights.lambertian
    c = None
    if unit is None:
        c, ok, weights = _lambertian_start(lights, opt, v, usable)
        unit, rho = unit_columns(blocked_matmul(basis.back, c))
    else:
        shading = blocked_matmul(lights.dirs, unit)
        weights = ((shading > opt.min_shading) & usable).astype(np.float32)
        if opt.cos_cone is not None:
            cone = weights * (blocked_matmul(lights.halves, unit) < opt.cos_cone)
            # The same test as for the cone's fit in _lambertian_start (here only ρ is fitted,
            # but the robust passes after it need samples spread enough to be judged).
            _, ok_cone = weighted_fit(basis, v, cone, None, _CONE_SINGULAR)
            weights = np.where(ok_cone, cone, weights)
        rho = _albedo(shading, v, weights)
        ok = np.ones(v.shape[1], dtype=bool)
    if c is None:
        lit = (shading > opt.min_shading) & usable
    for t in range(opt.iterations):
        if c is None:
            pred = shading * rho.astype(np.float32)
            candidates = lit.copy()
        else:
            # ρ n·l in one product with g = ρn.
            pred = blocked_matmul(lights.dirs, blocked_matmul(basis.back, c).astype(np.float32))
            candidates = pred > (opt.min_shading * rho).astype(np.float32)
            candidates &= usable
        candidates &= v >= opt.cast_shadow_ratio * pred
        res = np.subtract(v, pred, out=pred)
        weights = reweight(opt, res, candidates, weights, t == 0, 1 if c is None else basis.rank, rho)
        if c is None:
            rho = _albedo(shading, v, weights)
            continue
        (c_new,), ok_new = weighted_fit(basis, v, weights, [c])
        c = np.where(ok_new, c_new, c)
        ok |= ok_new
        unit, rho = unit_columns(blocked_matmul(basis.back, c))
    if basis.rank < 3:
        ok = np.zeros_like(ok)  # lights in one plane leave the normals undetermined
    return unit, rho, ok, weights


# --------------------------------------------------------------------------------------------
# Photometric stereo


def _numpy_pass(stack: ImageStack, lights: Lights, opt: RobustOptions, out: PhotometricStereo,
                prior: np.ndarray | None, coefficients: np.ndarray, threads: int | None,
                progress: Callable[[int], None] | None) -> None:
    """One pass of :func:`robust_photometric_stereo` by the NumPy steps above, into ``out``."""
    n, (h, w) = len(stack), stack.shape

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        values = values.reshape(n, -1)
        if prior is not None:
            values = values / lobe_factors(coefficients, lights.halves, prior[r0:r1].reshape(-1, 3).T)
        unit, rho, ok, weights = robust_lambertian(lights, opt, values, ~saturated.reshape(n, -1))
        store_normals(out, slice(r0, r1), unit * rho, ok, weights.sum(axis=0))

    run_bands(h, band_height(n, w), work, threads=threads, progress=progress)


def _mean_directions(a: np.ndarray, b: np.ndarray, threads: int | None) -> None:
    """``a`` ← the unit vector halfway between ``a`` and ``b`` (H, W, 3), in bands of rows."""
    h, w = a.shape[:2]

    def work(r0: int, r1: int) -> None:
        mean = a[r0:r1] + b[r0:r1]
        mean /= np.maximum(np.linalg.norm(mean, axis=2, keepdims=True), np.float32(1e-12))
        a[r0:r1] = mean

    run_bands(h, max(1, _KERNEL_PIXELS // w), work, threads=threads)


def _in_thirds(progress: Callable[[int], None]) -> Callable[[int], None]:
    """A progress callback for three passes over the rows that reports whole rows of one."""
    done = [0, 0]  # rows done in all passes, rows reported

    def report(rows: int) -> None:
        done[0] += rows
        step = done[0] // 3 - done[1]
        if step:
            done[1] += step
            progress(step)

    return report


def robust_rows(stack: ImageStack, dirs: np.ndarray, opt: RobustOptions, threads: int | None,
                progress: Callable[[int], None] | None, *, out: PhotometricStereo | None = None,
                prior: np.ndarray | None = None, lobe: np.ndarray = _NO_LOBE,
                ptm: KernelPTM | None = None) -> None:
    """One pass of the compiled kernel (:func:`ptmcore.robustkernel.robust_ps_rows`) over the
    stack, in bands of rows in ``threads``: the normals into ``out``, and with ``ptm``
    (:class:`ptmcore.robustptm.KernelPTM`) the robust PTM's results.

    ``prior`` and ``lobe``: the normals at which the lobe's coefficients ``lobe`` are evaluated
    (:mod:`ptmcore.lobe`); None and :data:`_NO_LOBE` without a lobe. Not with ``ptm``: the PTM
    is fitted to the photographs themselves.
    """
    if ptm is not None and prior is not None:
        raise ValueError("the robust PTM is not fitted with a reflectance lobe")
    from .robustkernel import robust_ps_rows  # numba's import costs a second; the CLI's start does not need it

    h, w = stack.shape
    basis = orthonormal_basis(dirs)
    cos_cone = 1.0 if opt.cos_cone is None else float(opt.cos_cone)
    par = np.array([opt.dark_fraction, opt.min_shading, opt.cast_shadow_ratio, cos_cone, opt.reject_below,
                    opt.reject_above, opt.noise_floor, opt.relative_floor, opt.consistency], dtype=np.float64)
    codes, table = stack.luminance, stack.table
    outer_t, u_t = np.ascontiguousarray(basis.outer.T), np.ascontiguousarray(basis.u.T)
    back, dirs32, halves = np.ascontiguousarray(basis.back), dirs.astype(np.float32), _half_vectors(dirs)
    results = (None, None, None, None) if out is None else (out.normals, out.albedo, out.samples, out.valid)

    def work(r0: int, r1: int) -> None:
        robust_ps_rows(codes, table, r0, r1, outer_t, u_t, back, dirs32, halves, par, opt.method == "irls",
                       opt.cos_cone is not None, opt.iterations, *results, prior, lobe, ptm)
        release_rows(codes, r0, r1)  # a stack on disk: done with these rows

    # Bands only spread the rows over the threads: the kernel makes its work arrays itself.
    run_bands(h, max(1, _KERNEL_PIXELS // w), work, threads=threads, progress=progress)


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
    compiled: bool = True,
    lobe: bool | Lobe = False,
) -> PhotometricStereo:
    """Lambertian photometric stereo with per-pixel robust weights.

    Each pixel solves ``I_i = ρ n·l_i`` by weighted least squares, with the weights built in
    the steps described in the module docstring: shadows and clipped samples dropped, a first
    estimate, the specular cone dropped, then ``iterations`` robust passes.

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    method : {"irls", "trimmed"}
        Tukey-biweight weights, or weights of 0 or 1 at the same bounds.
    iterations : int
        Number of robust passes after the two first estimates.
    dark_fraction : float
        The first estimate drops samples darker than this × the pixel's brightest.
    min_shading : float
        Samples with ``n·l`` below this (attached shadow, grazing light) are dropped.
    cast_shadow_ratio : float
        Samples darker than this × the prediction (cast shadow) are dropped.
    specular_cone : float or None
        Half-angle in degrees. The second estimate drops the lights whose half vector is within
        this angle of the first normal. None skips the second estimate.
    reject_below, reject_above : float
        Residuals, in robust scales, under and over the prediction, beyond which a sample
        gets no weight.
    noise_floor, relative_floor : float
        The scale is at least ``noise_floor + relative_floor · ρ`` (luminance units).
    threads : int, optional
        Threads that work on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.
    compiled : bool
        Run the compiled kernel (:mod:`ptmcore.robustkernel`); False runs the NumPy steps of
        this module instead, several times slower (6.7–8.7× in BENCHMARKS.md): the kernel's
        reference in its tests and benchmark.
    lobe : bool or Lobe
        Fit the normals with a reflectance lobe shared by the object (:mod:`ptmcore.lobe`):
        True estimates it (and uses it only where it explains the data), a :class:`Lobe` is
        used as given. The fit then takes three passes instead of one.

    Returns
    -------
    PhotometricStereo
        Its ``samples`` field holds the sum of the final weights, rounded; ``lobe`` the lobe
        used, or None.
    """
    opt = RobustOptions(method, iterations, dark_fraction, min_shading, cast_shadow_ratio,
                        specular_cone, reject_below, reject_above, noise_floor, relative_floor)
    n = len(stack)
    h, w = stack.shape
    dirs = as_directions(directions, n)
    if compiled:
        def run(out: PhotometricStereo, prior: np.ndarray | None, coefficients: np.ndarray,
                report: Callable[[int], None] | None) -> None:
            robust_rows(stack, dirs, opt, threads, report, out=out, prior=prior, lobe=coefficients)
    else:
        lights = Lights.of(dirs)

        def run(out: PhotometricStereo, prior: np.ndarray | None, coefficients: np.ndarray,
                report: Callable[[int], None] | None) -> None:
            _numpy_pass(stack, lights, opt, out, prior, coefficients, threads, report)

    result = empty_result((h, w))
    if lobe is True:
        lobe = estimate_lobe(stack, dirs, opt)
    if not lobe:
        run(result, None, _NO_LOBE, progress)
        return result
    # Three passes (module docstring): Lambertian; the lobe at those normals; the lobe at the
    # mean of the two, which damps the overshoot of the second. Undamped, the error on
    # DiLiGenT's cat went 6.45° → 5.96° → 5.49° → 5.76° over the passes; damped it settles.
    thirds = None if progress is None else _in_thirds(progress)
    run(result, None, _NO_LOBE, thirds)
    second = empty_result((h, w))
    run(second, result.normals, lobe.coefficients, thirds)

    _mean_directions(result.normals, second.normals, threads)
    del second
    # The prior is read a chunk at a time before the chunk's normals are written over it.
    run(result, result.normals, lobe.coefficients, thirds)
    result.lobe = lobe
    return result
