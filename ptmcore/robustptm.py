"""Robust PTMs, and PTM normals without the bias towards the view direction.

:func:`robust_ptm` fits a PTM at each pixel with the weights of robust Lambertian photometric
stereo (:mod:`ptmcore.robust`), which leave out the pixel's shadowed, clipped and specular
samples.

PTM normals. Fit a PTM to a Lambertian surface and its maximum is biased towards the view
direction, whichever samples are used: ``n·l = nx·lu + ny·lv + nz·√(1 − lu² − lv²)``, and the
square root is not biquadratic. The fitted polynomial is exactly ``ρ (nx·lu + ny·lv + nz·q)``,
where ``q`` is the same fit (same weights) of ``lz = √(1 − lu² − lv²)`` alone: the
"hemisphere" PTM. The gradient is zero at the maximum ``(lu0, lv0)``, so
``(nx, ny) = −nz ∇q(lu0, lv0)``. :func:`debiased_normals` uses this to read the normal from the
maximum through ``q``. On a Lambertian surface the result is exact; the plain maximum
(:func:`ptmcore.normals.normals_from_ptm`) is not. See ``benchmarks/normals_table.py``.

Degenerate pixels. Where a pixel's samples are all within :data:`ptmcore.normals.FLAT` of
its brightest (all clipped, all black, or one value under every light), or its PTM is flat, no
normal is read: the direction of its fit's rounding noise would differ between CPUs and between
the kernel and the NumPy steps. Its normal is (0, 0, 1) and ``RobustPTM.valid`` is False there,
in both; the PTM is kept for relighting.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from .bands import run_bands
from .fit import PTM, evaluate_at, fit_matrix, light_matrix
from .images import ImageStack
from .lp import as_directions
from .normals import FLAT
from .pixelfit import blocked_matmul, orthonormal_basis, weighted_fit
from .robust import Lights, RobustOptions, band_height, reweight, robust_lambertian, robust_rows, unit_columns

__all__ = ["KernelPTM", "RobustPTM", "debiased_normals", "hemisphere_coefficients", "robust_fit_ptm", "robust_ptm"]

#: The test of a PTM's weighted fit; below it the plain fit stands in (here and in the kernel).
_PTM_SINGULAR = 1e-4
_UP = np.array([[0.0], [0.0], [1.0]])


def hemisphere_coefficients(directions: np.ndarray) -> np.ndarray:
    """The plain least-squares PTM of ``lz`` over the lights, shape (6,), float64.

    Pass it as ``hemisphere`` to :func:`debiased_normals` for a PTM fitted with these lights by
    :func:`ptmcore.fit.fit_ptm` (or read from a file).
    """
    d = np.asarray(directions, dtype=np.float64)
    return fit_matrix(d) @ d[:, 2]


def _debiased(a: np.ndarray, q: np.ndarray, same: np.ndarray | bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Normals (3, P) float32 from PTM coefficients ``a`` and hemisphere PTMs ``q`` (6, P),
    and where they were read (P,): not where the samples are all the ``same`` (P,), the PTM is
    flat (:data:`ptmcore.normals.FLAT`) or it gives no normal facing the camera, where they
    are (0, 0, 1)."""
    a0, a1, a2, a3, a4, a5 = a[:6]
    q0, q1, q2, q3, q4 = q[:5]
    det = 4 * a0 * a1 - a2 * a2
    concave = (a0 < 0) & (det > 0)
    det = np.where(concave, det, 1.0)
    # The stationary point of the polynomial. On a steep slope it lies outside the unit disk,
    # and the map below still brings it back.
    lu = (a2 * a4 - 2 * a1 * a3) / det
    lv = (a2 * a3 - 2 * a0 * a4) / det
    # Where the polynomial has no maximum: ρ·nz is the least-squares factor between its
    # quadratic part and the hemisphere's, and ρ·(nx, ny) is what is left of its linear part.
    qq = q0 * q0 + q1 * q1 + 0.5 * q2 * q2
    rho_z = (a0 * q0 + a1 * q1 + 0.5 * a2 * q2) / np.where(qq > 0, qq, 1.0)
    g = np.stack([
        np.where(concave, -(2 * q0 * lu + q2 * lv + q3), a3 - rho_z * q3),
        np.where(concave, -(2 * q1 * lv + q2 * lu + q4), a4 - rho_z * q4),
        np.where(concave, 1.0, rho_z),
    ])
    unit, length = unit_columns(g)
    shape = np.abs(a0) + np.abs(a1) + np.abs(a2) + np.abs(a3) + np.abs(a4)
    good = ~same & (shape > FLAT * np.abs(a5)) & (length > 0) & np.isfinite(length) & (unit[2] > 0)
    return np.where(good, unit, _UP).astype(np.float32), good


def _same_samples(v: np.ndarray) -> np.ndarray:
    """Where a pixel's samples (N, P) are all within :data:`ptmcore.normals.FLAT` of the
    brightest: all clipped, all black or one value, with no direction in them (P,).

    The samples decide it, not the fit: a weighted fit of one value with few samples (a
    condition number of 10⁴) has a shape of rounding well above FLAT. The plain fit stands in
    there.
    """
    top = v.max(axis=0).astype(np.float64)
    return top - v.min(axis=0) <= FLAT * top


def debiased_normals(coefficients: np.ndarray, hemisphere: np.ndarray, *,
                     valid: np.ndarray | None = None) -> np.ndarray:
    """Normals from each PTM's maximum, read through the fit's own model of the hemisphere.

    For a Lambertian pixel the fitted PTM is ``ρ (nx·lu + ny·lv + nz·q)``, where ``q`` is the
    ``hemisphere`` PTM (the same fit of ``lz``). At the maximum ``(lu0, lv0)`` this gives
    ``(nx, ny) = −nz ∇q(lu0, lv0)``. Where the polynomial has no maximum (it is not concave),
    ``ρ·nz`` is read from its quadratic part and ``ρ·(nx, ny)`` from what remains of its
    linear part.

    No normal is read from a flat PTM, where |a0| + … + |a4| ≤ :data:`ptmcore.normals.FLAT` ×
    |a5| (an all-zero PTM too): its samples carry no direction, and the direction of what shape
    it has is rounding, which differs between CPUs. Nor where the reading gives no finite
    normal facing the camera. Those pixels' normals are (0, 0, 1).

    Parameters
    ----------
    coefficients : ndarray, shape (..., 6)
        PTM coefficients.
    hemisphere : ndarray, shape (..., 6) or (6,)
        The fit's PTM of ``lz``. For :func:`robust_ptm` there is one per pixel; for a plain fit,
        :func:`hemisphere_coefficients` gives one for all pixels.
    valid : ndarray, shape (...), bool, optional
        Out: where a normal was read (False where it is the (0, 0, 1) of a flat PTM or of no
        reading).

    Returns
    -------
    ndarray, shape (..., 3), float32
        Unit normals, or (0, 0, 1) where none can be read.
    """
    coefficients = np.asarray(coefficients)
    shape = coefficients.shape[:-1]
    a = coefficients.reshape(-1, 6)
    q = np.broadcast_to(np.asarray(hemisphere), coefficients.shape).reshape(-1, 6)
    out = np.empty((a.shape[0], 3), dtype=np.float32)
    good = np.empty(a.shape[0], dtype=bool)
    step = 1 << 16  # keeps the float64 temporaries of a large map bounded
    for p0 in range(0, a.shape[0], step):
        part = slice(p0, p0 + step)
        unit, good[part] = _debiased(a[part].T.astype(np.float64), q[part].T.astype(np.float64))
        out[part] = unit.T
    if valid is not None:
        valid[...] = good.reshape(shape)
    return out.reshape(*shape, 3)


class KernelPTM(NamedTuple):
    """The robust PTM's basis and result arrays as the compiled kernel takes them
    (``ptm`` of :func:`ptmcore.robustkernel.robust_ps_rows`; a named tuple, which numba
    compiles field by field).

    The basis is the PTM's terms orthonormalised with ``lz`` as an extra column
    (:func:`ptmcore.pixelfit.orthonormal_basis`), r columns at the N lights.
    """

    outer_t: np.ndarray  #: (K, N) float32, ``Basis.outer.T``
    u_t: np.ndarray  #: (r, N) float32, ``Basis.u.T``
    back: np.ndarray  #: (6, r) float64, solution in ``u`` → PTM coefficients
    plain_z: np.ndarray  #: (r,) float64, the plain fit of ``lz``
    gram_rows: np.ndarray  #: (r(r+1)/2,) int64, the rows of the sums that make the normal matrix
    extra_rows: np.ndarray  #: (r,) int64, the rows of Σ w φ lz
    singular: float  #: below it (det G / mean eigenvalue^r) the plain fit stands in
    flat: float  #: :data:`ptmcore.normals.FLAT`
    coefficients: np.ndarray  #: out: (H, W, 6) float32
    hemisphere: np.ndarray  #: out: (H, W, 6) float32
    normals: np.ndarray  #: out: (H, W, 3) float32, debiased
    valid: np.ndarray  #: out: (H, W) bool, where a normal was read
    used: np.ndarray  #: out: (H, W) float32, the weights' sums


@dataclass
class RobustPTM:
    """Result of :func:`robust_ptm`.

    Attributes
    ----------
    ptm : PTM
        The robustly fitted PTM (coefficients in linear luminance, as from ``fit_ptm``).
    hemisphere : ndarray, shape (H, W, 6), float32
        The same weighted fit of ``lz`` at each pixel; :func:`debiased_normals` needs it.
    normals : ndarray, shape (H, W, 3), float32
        ``debiased_normals(ptm.coefficients, hemisphere)``.
    samples : ndarray, shape (H, W), float32
        Sum of the final weights (how many photographs count).
    valid : ndarray, shape (H, W), bool
        Where a normal was read: False where the samples are all within
        :data:`ptmcore.normals.FLAT` of the brightest (all clipped or black, or one value under
        every light), the PTM is flat or it gives no normal facing the camera, and the normal
        is (0, 0, 1).
    """

    ptm: PTM
    hemisphere: np.ndarray
    normals: np.ndarray
    samples: np.ndarray
    valid: np.ndarray


def robust_ptm(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    method: str = "irls",
    normals: np.ndarray | None = None,
    iterations: int = 3,
    refine: int = 0,
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
) -> RobustPTM:
    """Fit a PTM at each pixel, leaving out its shadowed, clipped and specular samples.

    The weights are those of robust Lambertian photometric stereo (steps 1–3 of
    :mod:`ptmcore.robust`): a sample gets the weight that the Lambertian model gives it, and the PTM is
    then fitted once with those weights. Judged by the polynomial's own residuals instead,
    highlights keep part of their weight, because six coefficients can absorb part of a highlight.
    On the synthetic tablet with highlights, the debiased normals were off by 0.81° with the
    Lambertian weights, by 1.17° after one polynomial pass (``refine=1``) and by 1.25° after two.

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    method : {"irls", "trimmed"}
    normals : ndarray, shape (H, W, 3), optional
        Fixed normals for the Lambertian weights (for example from
        :func:`ptmcore.robust.robust_photometric_stereo`). Only ρ is fitted then, by the NumPy
        steps: slower than the default, which the kernel does.
    iterations : int
        Number of robust Lambertian passes.
    refine : int
        Additional passes that reweight by the polynomial's residuals, with the normals from
        :func:`debiased_normals` (or ``normals``) deciding the attached shadows.
    dark_fraction, min_shading, cast_shadow_ratio, specular_cone, reject_below, reject_above,
    noise_floor, relative_floor
        As in :func:`ptmcore.robust.robust_photometric_stereo`.
    threads : int, optional
        Threads that work on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.
    compiled : bool
        Run the compiled kernel (:func:`ptmcore.robustkernel.robust_ps_rows` with its PTM fit)
        where it applies (no ``normals``, ``refine`` 0: the defaults); False runs the NumPy
        steps of this module, the kernel's reference in its tests.

    Returns
    -------
    RobustPTM
    """
    opt = RobustOptions(method, iterations, dark_fraction, min_shading, cast_shadow_ratio,
                        specular_cone, reject_below, reject_above, noise_floor, relative_floor)
    n = len(stack)
    h, w = stack.shape
    dirs = as_directions(directions, n)
    if refine < 0:
        raise ValueError(f"refine must be ≥ 0, got {refine}")
    if normals is not None and np.shape(normals) != (h, w, 3):
        raise ValueError(f"normals must have shape {(h, w, 3)}, got {np.shape(normals)}")
    # lz joins the sums as an extra column, so the same factorisation also fits the
    # hemisphere PTM that the debiased normals need.
    basis = orthonormal_basis(light_matrix(dirs), dirs[:, 2:3])
    plain_z = (basis.u.T.astype(np.float64) @ dirs[:, 2])[:, None]
    coef = np.empty((h, w, 6), dtype=np.float32)
    hemi = np.empty((h, w, 6), dtype=np.float32)
    nout = np.empty((h, w, 3), dtype=np.float32)
    valid = np.empty((h, w), dtype=bool)
    used = np.empty((h, w), dtype=np.float32)
    if compiled and normals is None and refine == 0:
        ptm = KernelPTM(np.ascontiguousarray(basis.outer.T), np.ascontiguousarray(basis.u.T),
                        np.ascontiguousarray(basis.back), np.ascontiguousarray(plain_z[:, 0]),
                        basis.gram_rows.astype(np.int64), basis.extra_rows[0].astype(np.int64), _PTM_SINGULAR,
                        FLAT, coef, hemi, nout, valid, used)
        robust_rows(stack, dirs, opt, threads, progress, ptm=ptm)
        return RobustPTM(PTM(coef, stack.chroma), hemi, nout, used, valid)
    lights = Lights.of(dirs)

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        v = values.reshape(n, -1)
        usable = ~saturated.reshape(n, -1)
        given = None if normals is None else np.ascontiguousarray(
            normals[r0:r1].reshape(-1, 3).T, dtype=np.float32)
        unit, _, _, weights = robust_lambertian(lights, opt, v, usable, given)
        # The plain fit (a matrix product) stands in where the weights leave too few samples,
        # or samples too close together, to fit six coefficients.
        plain = [blocked_matmul(basis.u.T, v).astype(np.float64),
                 np.broadcast_to(plain_z, (basis.rank, v.shape[1]))]
        (c, cz), ok = weighted_fit(basis, v, weights, plain, _PTM_SINGULAR)
        # And where the samples are all the same, whose weighted fit would have a shape of
        # rounding only (the plain fit's is the sums' rounding, flat).
        same = _same_samples(v)
        ok &= ~same
        c = np.where(ok, c, plain[0])
        cz = np.where(ok, cz, plain[1])
        shading = blocked_matmul(lights.dirs, unit)
        for _ in range(refine):
            a = blocked_matmul(basis.back, c)
            if normals is None:
                unit, _ = _debiased(a, blocked_matmul(basis.back, cz))
                shading = blocked_matmul(lights.dirs, unit)
            candidates = (shading > min_shading) & usable
            pred = blocked_matmul(basis.u, c.astype(np.float32))
            candidates &= v >= cast_shadow_ratio * pred
            res = np.subtract(v, pred, out=pred)
            # The polynomial's value at the normal stands in for ρ in the scale's floor.
            lu, lv = unit[0].astype(np.float64), unit[1].astype(np.float64)
            rho = np.abs(evaluate_at(a.T, lu, lv))
            weights = reweight(opt, res, candidates, weights, False, basis.rank, rho)
            (c, cz), _ = weighted_fit(basis, v, weights, [c, cz])
        a = blocked_matmul(basis.back, c)
        q = blocked_matmul(basis.back, cz)
        coef[r0:r1] = a.T.reshape(r1 - r0, w, 6)
        hemi[r0:r1] = q.T.reshape(r1 - r0, w, 6)
        unit, good = _debiased(a, q, same)
        nout[r0:r1] = unit.T.reshape(r1 - r0, w, 3)
        valid[r0:r1] = good.reshape(r1 - r0, w)
        used[r0:r1] = weights.sum(axis=0).reshape(r1 - r0, w)

    run_bands(h, band_height(n, w), work, threads=threads, progress=progress)
    return RobustPTM(PTM(coef, stack.chroma), hemi, nout, used, valid)


def robust_fit_ptm(stack: ImageStack, directions: np.ndarray, **options: Any) -> PTM:
    """Only the PTM of :func:`robust_ptm`, for use with :func:`ptmcore.normals.normals_from_ptm`.

    ``options`` are the keywords of :func:`robust_ptm`, with its defaults.
    """
    return robust_ptm(stack, directions, **options).ptm
