"""Bilateral normal integration (BiNI; Cao, Santo, Shi, Okura, Matsushita, ECCV 2022).

The least squares of :mod:`reconstruct.surface.masked` ask every pair of 4-neighbours to agree
with the mean of their two gradients, so a step (a depth discontinuity, visible as a
non-integrable gradient field) is smeared over its surroundings. BiNI gives every pixel i two
*one-sided* equations per axis,

    forward   a_i·(z_{i+1} − z_i − g_i) = 0   with weight w⁺_i,
    backward  a_i·(z_i − z_{i−1} − g_i) = 0   with weight w⁻_i = 1 − w⁺_i,

and lets each pixel trust the side on which the surface is continuous:

    w⁺_i = σ(k·a_i²·((z_i − z_{i−1})² − (z_{i+1} − z_i)²)),

the weights being recomputed from the previous solution (iteratively reweighted least squares,
starting from w⁺ = w⁻ = ½). The factor a_i is the denominator of the gradient: BiNI writes
the equations as nz·∂z + nx = 0 rather than ∂z = −nx/nz, so a_i = nz (orthographic) or the
cosine between the normal and the line of sight (perspective, where z is the log-depth). It
weights each pixel by a_i², which trusts the gradient of a steep normal less: a normal error δ
moves the gradient by about δ/a_i².

Both one-sided equations that involve an edge (i, i+1) share its difference operator, so each
pass is one weighted least-squares solve over edges, with weight c_i·w⁺_i + c_{i+1}·w⁻_{i+1}
and target the weighted mean of g_i and g_{i+1} (c = a²): the solver of
:mod:`reconstruct.surface.masked`, with the aggregation multigrid of
:mod:`reconstruct.surface.multigrid` as preconditioner (it coarsens with the actual weights,
so nearly cut edges stay nearly cut on the coarse levels).

The IRLS stops, as BiNI's, when the weighted energy changes by less than `tol` (relative)
between two passes. Large masks are first solved on 2×2 blocks (:func:`_multiscale`).

The steps it kept are counted (``info["cut_edges"]``): edges both of whose one-sided
equations keep less than :data:`CUT_WEIGHT` of their weight, each pixel trusting its other
side. Where the surface is continuous no edge is cut, even where the weights stray from ½
(:func:`reconstruct.surface.choose.integrate_auto` uses the count as the evidence of depth
steps).

Limits. The weights compare differences in pixel footprints, so the same scene behaves
differently at different resolutions; and the IRLS starts from least squares, which smears a
step over its surroundings, so where the surface is continuous only along a thin band (a
step whose height grows quickly from zero) the weights can cut that band too and the two
sides drift apart by a free constant. Measured on a rendered "scissor" step: kept at 160×120
(0.45 mm against 6.33 mm for least squares), lost at 640×480 (6.32 mm against 6.33 mm,
52 s). A part cut off all around keeps an arbitrary offset, as with any integrator.

Against least squares (numbers from ``benchmarks/real_integration.py`` and
``benchmarks/integration.py``, 2 cores). Real data with depth discontinuities and occluding
contours (DiLiGenT, perspective, mean absolute depth error after the median-ratio scale):
cat 2.24 → 0.08 mm, harvest 8.15 → 2.70 mm against masked least squares, in 0.65 s and 6 s
instead of 0.05 s. Continuous surfaces: worse (a clay tablet's true normals 0.034 → 0.054 px,
a sphere to its outline 0.004 → 0.015 px, a coin relief from photometric stereo 0.17 →
0.27 px), for two reasons measured on the tablet: the nz² weights alone (k = 0) take it to
0.043 px, and the sigmoid weights stray from ½ wherever the slope changes (the two one-sided
differences differ by about twice slope × curvature), leaning the solution towards the
flatter side: 0.054 px. Better on some steep walls under noise (wedges cut at 75°, a
sphere cap to 80° with 2 % noise), where its nz² weighting trusts the noisiest gradients
less. Cost at 24 Mpixel (tablet
relief, 14 Mpixel in the mask): 52 s and 5.1 GB peak against 10 s and 2.4 GB. So ``auto``
(:func:`reconstruct.surface.choose.integrate_auto`) runs it on masks of at most a megapixel
and keeps its result only when it cut edges (``info["cut_edges"]``); else it integrates by
masked least squares with the same nz² weights.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from reconstruct.surface.masked import (
    _component_means_removed,
    _edge_masks,
    _embed,
    _masked_inputs,
    _solve_edges,
    _warm_start,
)

__all__ = ["CUT_WEIGHT", "discontinuity_preserving"]

WeightRule = Literal["differences", "residuals"]

#: An edge is cut when the mean weight of its two one-sided equations (w⁺ of the pixel
#: before it, w⁻ of the pixel after) is below this: both pixels trust their other side. On
#: the smooth scenes of ``benchmarks/integration.py`` no edge's mean was below it (at 2 %
#: noise a few were below 0.2); steps and occluding contours cut tens to thousands.
CUT_WEIGHT = 0.1


def _sigmoid(t: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * t))  # overflow-free logistic


def _slices(axis: int) -> tuple[tuple[slice, ...], tuple[slice, ...]]:
    lo = [slice(None)] * 2
    hi = [slice(None)] * 2
    lo[axis] = slice(None, -1)
    hi[axis] = slice(1, None)
    return tuple(lo), tuple(hi)


def _forward_weights(
    z: np.ndarray, g: np.ndarray, c: np.ndarray, edges: np.ndarray, k: float, axis: int,
    rule: WeightRule,
) -> np.ndarray:
    """w⁺ of every pixel along one axis from the one-sided differences of z.

    ``rule="differences"`` is BiNI's: the side with the smaller jump c·Δ² wins.
    ``rule="residuals"`` compares c·(Δ − g)² instead: the side that agrees with the
    pixel's own gradient wins (this module's former orthographic rule).
    A side without a neighbour in the mask makes the other one certain.
    """
    diff = np.diff(z, axis=axis)  # z_{i+1} − z_i on each edge
    lo, hi = _slices(axis)
    s_fwd = np.full(g.shape, np.inf)
    s_bwd = np.full(g.shape, np.inf)
    if rule == "differences":
        d2 = diff * diff
        s_fwd[lo] = np.where(edges, d2, np.inf)
        s_bwd[hi] = np.where(edges, d2, np.inf)
    else:
        s_fwd[lo] = np.where(edges, (diff - g[lo]) ** 2, np.inf)
        s_bwd[hi] = np.where(edges, (diff - g[hi]) ** 2, np.inf)
    with np.errstate(invalid="ignore"):
        t = (k * c) * (s_bwd - s_fwd)
    # inf − finite = ±inf: the missing side loses; both missing (NaN): no equation anyway.
    t = np.nan_to_num(t, nan=0.0, posinf=50.0, neginf=-50.0)
    return _sigmoid(t)


def _edge_system(
    g: np.ndarray, c: np.ndarray, w_fwd: np.ndarray, edges: np.ndarray, floor: float, axis: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Edge weights and targets along one axis: both one-sided equations on each edge."""
    lo, hi = _slices(axis)
    a = c[lo] * w_fwd[lo]  # pixel i's forward equation on edge (i, i+1)
    b = c[hi] * (1.0 - w_fwd[hi])  # pixel i+1's backward equation on the same edge
    weight = a + b
    target = (a * g[lo] + b * g[hi]) / np.maximum(weight, 1e-300)
    weight = np.where(edges, np.maximum(weight, floor), 0.0)
    return weight, target


def _energy(
    z: np.ndarray, g: np.ndarray, c: np.ndarray, w_fwd: np.ndarray, edges: np.ndarray,
    axis: int,
) -> float:
    """Σ over the one-sided equations of weight·c·residual² along one axis."""
    lo, hi = _slices(axis)
    diff = np.diff(z, axis=axis)
    e = c[lo] * w_fwd[lo] * (diff - g[lo]) ** 2 + c[hi] * (1.0 - w_fwd[hi]) * (diff - g[hi]) ** 2
    return float(e[edges].sum())


def _irls(
    g_row: np.ndarray,
    g_col: np.ndarray,
    c_row: np.ndarray,
    c_col: np.ndarray,
    mask: np.ndarray,
    start: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    *,
    k: float,
    iterations: int,
    tol: float,
    cg_tol: float,
    maxiter: int,
    min_weight: float,
    rule: WeightRule,
    workers: int | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """BiNI on the bounding box from `start` = (z, w⁺ along rows, w⁺ along columns), or from
    least squares when None; returns float64 heights (unfixed constants), the last weights
    and an info dict."""
    ex, ey = _edge_masks(mask)
    if start is None:
        half = np.full(mask.shape, 0.5)
        wf_row = wf_col = half
        z = _warm_start(g_row, g_col, mask)
    else:
        z, wf_row, wf_col = start
    energy = math.inf
    done = 0
    cg_iterations = 0
    converged = False
    for done in range(1, iterations + 1):
        wx, tx = _edge_system(g_col, c_col, wf_col, ex, min_weight, axis=1)
        wy, ty = _edge_system(g_row, c_row, wf_row, ey, min_weight, axis=0)
        z, info = _solve_edges(
            wx, tx, wy, ty, mask, z, tol=cg_tol, maxiter=maxiter,
            preconditioner="multigrid", workers=workers,
        )
        del wx, tx, wy, ty
        cg_iterations += info["iterations"]
        wf_col = _forward_weights(z, g_col, c_col, ex, k, axis=1, rule=rule)
        wf_row = _forward_weights(z, g_row, c_row, ey, k, axis=0, rule=rule)
        previous = energy
        energy = _energy(z, g_col, c_col, wf_col, ex, 1) + _energy(z, g_row, c_row, wf_row, ey, 0)
        if abs(previous - energy) <= tol * energy:
            converged = True
            break
    info = {"iterations": [done], "cg_iterations": cg_iterations, "energy": energy,
            "converged": converged}
    return z, wf_row, wf_col, info


def _cut_edges(wf_row: np.ndarray, wf_col: np.ndarray, mask: np.ndarray) -> int:
    """Edges of the mask whose two one-sided equations keep, on average, less than
    :data:`CUT_WEIGHT` of their weight (w⁺ the forward weights along each axis)."""
    ex, ey = _edge_masks(mask)
    cut = 0
    for w, edges, axis in ((wf_col, ex, 1), (wf_row, ey, 0)):
        lo, hi = _slices(axis)
        kept = 0.5 * (w[lo] + (1.0 - w[hi]))
        cut += int(np.count_nonzero(edges & (kept < CUT_WEIGHT)))
    return cut


def _block_means(a: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted means over 2×2 blocks (zero-padded to even size); 0 where a block weighs 0."""
    h, w = a.shape
    hc, wc = (h + 1) // 2, (w + 1) // 2
    num = np.zeros((2 * hc, 2 * wc))
    den = np.zeros((2 * hc, 2 * wc))
    num[:h, :w] = a * weights
    den[:h, :w] = weights
    num = num.reshape(hc, 2, wc, 2).sum(axis=(1, 3))
    den = den.reshape(hc, 2, wc, 2).sum(axis=(1, 3))
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def _blocks_up(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Each value copied to its 2×2 block, cropped to `shape`."""
    return np.repeat(np.repeat(a, 2, axis=0), 2, axis=1)[: shape[0], : shape[1]]


def _multiscale(
    g_row: np.ndarray,
    g_col: np.ndarray,
    c_row: np.ndarray,
    c_col: np.ndarray,
    mask: np.ndarray,
    *,
    coarse_pixels: int,
    refine_iterations: int,
    iterations: int,
    **options,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """:func:`_irls`, started from the solution of the 2×2-coarsened problem when the mask
    has more than `coarse_pixels` pixels.

    Gradients (height per pixel) are the same at both scales and heights halve, so the
    coarse heights, doubled, and the coarse weights, copied to each block, start the fine
    IRLS: an edge inside a block starts with full weight, an edge between two blocks with the
    coarse edge's. The fine passes then mostly move the discontinuities by a pixel or so
    (the 24 Mpixel tablet relief of ``benchmarks/real_integration.py``: 4 passes at the
    coarsest level, then 3 at each finer one).
    """
    if int(mask.sum()) <= coarse_pixels or min(mask.shape) < 16:
        return _irls(g_row, g_col, c_row, c_col, mask, None, iterations=iterations, **options)
    inside = mask.astype(np.float64)
    coarse = [_block_means(a, inside) for a in (g_row, g_col, c_row, c_col)]
    z, wf_row, wf_col, info = _multiscale(
        *coarse, _block_means(inside, inside) > 0, coarse_pixels=coarse_pixels,
        refine_iterations=refine_iterations, iterations=iterations, **options,
    )
    del coarse
    start = (2.0 * _blocks_up(z, mask.shape), _blocks_up(wf_row, mask.shape),
             _blocks_up(wf_col, mask.shape))
    del z, wf_row, wf_col
    z, wf_row, wf_col, fine = _irls(
        g_row, g_col, c_row, c_col, mask, start, iterations=refine_iterations, **options
    )
    fine["iterations"] = info["iterations"] + fine["iterations"]
    fine["cg_iterations"] += info["cg_iterations"]
    return z, wf_row, wf_col, fine


def discontinuity_preserving(
    p: np.ndarray,
    q: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    cosines: np.ndarray | tuple[np.ndarray, np.ndarray] | None = None,
    pixel_size: float = 1.0,
    k: float = 2.0,
    iterations: int = 100,
    tol: float = 1e-4,
    cg_tol: float = 1e-4,
    maxiter: int = 200,
    min_weight: float = 1e-6,
    rule: WeightRule = "differences",
    coarse_pixels: int = 1 << 20,
    refine_iterations: int = 10,
    workers: int | None = -1,
    return_info: bool = False,
) -> np.ndarray | tuple[np.ndarray, dict]:
    """Bilateral normal integration (BiNI) of a gradient field on a masked domain.

    The formulation and the IRLS are in the module docstring. Orthographic by default (the
    factor a of each pixel is the nz of its gradient); :func:`integrate_perspective` calls it
    on scaled log-depth gradients with the cosines of the viewing angles. Each 4-connected
    component of the mask keeps one free constant (mean 0).

    Parameters
    ----------
    p, q : numpy.ndarray
        ``(H, W)`` gradients ∂z/∂x and ∂z/∂y (y up) in height per horizontal unit.
        Pixels with a non-finite gradient are left out of the domain.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool domain; the whole image when omitted.
    cosines : numpy.ndarray or (numpy.ndarray, numpy.ndarray), optional
        The factor a of each pixel's equations (``(H, W)``, or one array for the equations
        along x and one along y): nz for an orthographic camera, the cosine between normal
        and line of sight for a perspective one. Default: ``1/sqrt(1 + p² + q²)``, the nz
        of the normals the gradients came from.
    pixel_size : float
        Size of a pixel; heights come out in its unit.
    k : float
        Sharpness of the sigmoid, in 1/pixel² (the differences are in pixel units whatever
        `pixel_size` is). Small k (→ 0) gives least squares weighted by a²; large k a hard
        choice of side, sensitive to noise. The default 2 is Cao et al.'s for all their
        experiments.
    iterations : int
        Most reweighted solves (BiNI's evaluation on DiLiGenT uses 100).
    tol : float
        Stop when the weighted energy changes by less than this fraction between two
        passes (BiNI: 1e-4).
    cg_tol, maxiter : float, int
        Conjugate-gradient stopping rule of each solve (relative residual of the normal
        equations), warm-started from the previous solve. BiNI stops its Jacobi-preconditioned
        CG at 1e-3; with this multigrid preconditioner 1e-3 is about twice as fast, but the
        IRLS then follows the rounding of the solves: DiLiGenT's harvest came out between
        2.12 and 2.32 mm with different BLAS thread counts, against 2.70 mm to three
        decimals with 1e-4 and 2.79 mm with 1e-6.
    min_weight : float
        Floor of the edge weights (relative to a flat pixel's ½ + ½): keeps each component
        of the mask connected, so that its constant stays fixed.
    rule : {"differences", "residuals"}
        What the weights compare: BiNI's one-sided depth differences (default), or the
        one-sided residuals against the pixel's gradient (this project's former rule, kept
        for comparisons: with ``cosines=1``, ``min_weight=1e-3``, ``iterations=51``,
        ``tol=0`` and ``cg_tol=1e-6`` this function is what it was before BiNI's form).
    coarse_pixels, refine_iterations : int
        Above `coarse_pixels` pixels in the mask the problem is first solved on 2×2 blocks
        (recursively), and the full-size IRLS starts from that solution and its weights with
        at most `refine_iterations` passes (:func:`_multiscale`). With the default 2²⁰ a
        mask of 24 Mpixel is solved at 1.5, 6 and 24 Mpixel; the DiLiGenT objects
        (0.06 Mpixel) are solved directly.
    workers : int or None
        Threads for scipy.fft (the warm start).
    return_info : bool
        Also return a dict with ``iterations`` (the reweighted solves of each level, coarsest
        first), ``cg_iterations`` (all levels), ``energy``, ``converged`` and ``cut_edges``
        (the edges the full-size level cut: :data:`CUT_WEIGHT`).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 heights, mean 0 on each 4-connected component of the mask, NaN
        outside it. With `return_info`, a ``(height, info)`` tuple.
    """
    if not (math.isfinite(k) and k >= 0):
        raise ValueError(f"k must be a non-negative number, not {k}")
    if rule not in ("differences", "residuals"):
        raise ValueError(f"rule must be 'differences' or 'residuals', not {rule!r}")
    if not (isinstance(iterations, int) and iterations >= 1):
        raise ValueError(f"iterations must be a whole number of at least 1, not {iterations}")
    shape = np.shape(p)
    g_row, g_col, m, box = _masked_inputs(p, q, mask, pixel_size)
    gr = g_row.astype(np.float64)
    gc = g_col.astype(np.float64)
    del g_row, g_col
    if cosines is None:
        a = 1.0 / np.sqrt(1.0 + gr * gr + gc * gc)
        a_col = a_row = a
    else:
        pair = cosines if isinstance(cosines, tuple) else (cosines, cosines)
        a_col, a_row = (np.asarray(c, dtype=np.float64) for c in pair)
        if a_col.shape != shape or a_row.shape != shape:
            raise ValueError(f"cosines must have the gradients' shape {shape}")
        a_col, a_row = a_col[box], a_row[box]
        m = m & np.isfinite(a_col) & np.isfinite(a_row)
        if (a_col[m] <= 0).any() or (a_row[m] <= 0).any():
            raise ValueError("cosines must be positive inside the mask")
    if not m.any():
        empty = np.full(shape, np.nan, dtype=np.float32)
        return (empty, {"iterations": [0], "cg_iterations": 0, "energy": 0.0,
                        "converged": True, "cut_edges": 0}) if return_info else empty
    c_col = np.where(m, a_col * a_col, 0.0)
    c_row = np.where(m, a_row * a_row, 0.0)
    z, wf_row, wf_col, info = _multiscale(
        gr, gc, c_row, c_col, m, coarse_pixels=coarse_pixels,
        refine_iterations=refine_iterations, k=k, iterations=iterations, tol=tol,
        cg_tol=cg_tol, maxiter=maxiter, min_weight=min_weight, rule=rule, workers=workers,
    )
    info["cut_edges"] = _cut_edges(wf_row, wf_col, m)
    del wf_row, wf_col
    z, _, _ = _component_means_removed(z, m)
    height = _embed(z, m, box, shape, pixel_size)
    return (height, info) if return_info else height
