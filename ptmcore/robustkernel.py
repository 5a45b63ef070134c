"""The compiled per-pixel kernel of robust photometric stereo.

:func:`ptmcore.robust.robust_photometric_stereo` runs the steps of :mod:`ptmcore.robust` (first
Lambertian estimate, specular cone, robust passes) one pixel at a time here, with numba. In NumPy
those steps are some forty element-wise passes over a band of the stack per pixel fit; here each
chunk of a row's pixels is read once from the stack (through the stack's code → linear table)
into buffers that stay in the cache, and every pass works on those, with the pixels in the
innermost loops so that the compiler vectorises them as BLAS vectorises the NumPy products. The kernel releases the GIL,
so bands of rows run in the caller's threads: ``threads`` is respected and numba's own threading
layer is not involved (several of its layers may not be entered from several threads at once).

The arithmetic follows the NumPy steps: float32 where they use float32 (residuals, weights,
thresholds), float64 for the normal equations, which NumPy sums in float32 before converting;
results agree within float32 rounding (``tests/test_robust_kernel.py``). The NumPy steps stay in
:mod:`ptmcore.robust`: the robust PTM fit (:mod:`ptmcore.robustptm`) uses them.

Compiled code is cached on disk (numba's ``cache=True``, beside this module or in
``NUMBA_CACHE_DIR``), so only the first run after installation pays for compilation.
"""

from __future__ import annotations

import math

import numba
import numpy as np

__all__ = ["robust_ps_rows"]

# Indices into the float64 parameter vector (numba compiles one function for every option
# set instead of one per keyword combination).
_DARK, _MIN_SHADING, _CAST, _COS_CONE, _BELOW, _ABOVE, _NOISE, _RELATIVE, _CONSISTENCY = range(9)
_RIDGE = 1e-6
_MAD_TO_SIGMA = 1.4826
#: Fused multiply-adds and reciprocals allowed (not reassociation, so sums keep their order):
#: like the different summation order, they change results by float32 rounding only.
_FAST = {"contract", "arcp", "nsz"}


@numba.njit(nogil=True, cache=True, fastmath=_FAST)
def _solve(w, wv, m, outer_t, u_t, r, prior, singular, out, ok, gram, rhs, low):  # pragma: no cover - compiled
    """Each pixel's weighted least squares ``min Σ_k w (v − u c)²`` with a ridge towards
    ``prior``, as :func:`ptmcore.pixelfit.weighted_fit`: the sums in float32 (as its matrix
    products), the Cholesky solve in float64. ``w`` and ``wv`` = w·v (N, m) are filled by the
    caller in the pass that makes the weights (one pass fewer over the samples); writes c into
    ``out`` (3, m) and well-posedness into ``ok`` (m,). ``outer_t`` (r(r + 1)/2, N) and ``u_t``
    (r, N) are the basis's products and columns; ``gram``, ``rhs`` (float32) and ``low``
    (11, m) float64 are work arrays. Every loop runs over the pixels innermost, so the compiler
    vectorises it."""
    # The sums are two small matrix products, as in the NumPy steps; BLAS does them several
    # times faster than a compiled loop that keeps nine running sums per pixel in memory.
    np.dot(outer_t, w, gram)
    np.dot(u_t, wv, rhs)
    # low[0:6]: the Cholesky factor, packed as gram; low[6]: ridge λ; low[7]: det; low[8:11]:
    # the forward solution.
    lam = low[6]
    det = low[7]
    for j in range(m):
        mean_eig = 0.0
        for a in range(r):
            mean_eig += gram[_packed(a, a, r), j]
        lam[j] = _RIDGE * max(mean_eig / r, 1e-30)
        det[j] = 1.0
    for jj in range(r):
        djj = _packed(jj, jj, r)
        for j in range(m):
            d = np.float64(gram[djj, j]) + lam[j]
            for k in range(jj):
                d -= low[_packed(k, jj, r), j] ** 2
            d = max(d, lam[j])
            det[j] *= d
            low[djj, j] = math.sqrt(d)
        for i in range(jj + 1, r):
            e = _packed(jj, i, r)
            for j in range(m):
                s = np.float64(gram[e, j])
                for k in range(jj):
                    s -= low[_packed(k, i, r), j] * low[_packed(k, jj, r), j]
                low[e, j] = s / low[djj, j]
    y = low[8:11]
    for i in range(r):
        for j in range(m):
            s = np.float64(rhs[i, j]) + lam[j] * prior[i, j]
            for k in range(i):
                s -= low[_packed(k, i, r), j] * y[k, j]
            y[i, j] = s / low[_packed(i, i, r), j]
    for i in range(r - 1, -1, -1):
        for j in range(m):
            s = y[i, j]
            for k in range(i + 1, r):
                s -= low[_packed(i, k, r), j] * out[k, j]
            out[i, j] = s / low[_packed(i, i, r), j]
    for j in range(m):
        mean_eig = lam[j] / _RIDGE
        # det G > singular · (mean eigenvalue)^r, without logarithms: each pivot ≥ λ keeps the
        # product far from underflow.
        ok[j] = det[j] > singular * mean_eig ** r


@numba.njit(nogil=True, cache=True, inline="always", fastmath=_FAST)
def _packed(a, b, r):  # pragma: no cover - compiled
    """Row of entry (a, b), a ≤ b, of an r×r symmetric matrix stored as its upper triangle."""
    return a * r - a * (a - 1) // 2 + (b - a)


@numba.njit(nogil=True, cache=True, fastmath=_FAST)
def _to_normal(c, m, back, r, g32, unit, rho):  # pragma: no cover - compiled
    """ρ = |g| (float64) into ``rho``, g = back · c as float32 into ``g32`` (the predictions are
    made from it, as the NumPy steps make them) and the unit normal (float32) into ``unit``."""
    for j in range(m):
        g0 = g1 = g2 = 0.0
        for a in range(r):
            g0 += back[0, a] * c[a, j]
            g1 += back[1, a] * c[a, j]
            g2 += back[2, a] * c[a, j]
        length = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        div = length if length > 0 else 1.0
        rho[j] = length
        g32[0, j], g32[1, j], g32[2, j] = np.float32(g0), np.float32(g1), np.float32(g2)
        unit[0, j], unit[1, j], unit[2, j] = np.float32(g0 / div), np.float32(g1 / div), np.float32(g2 / div)


@numba.njit(nogil=True, cache=True, fastmath=_FAST)
def _median_scale(res, cand, m, out):  # pragma: no cover - compiled
    """1.4826 × the lower median of ``|res|`` over each pixel's candidates, into ``out``."""
    n = res.shape[0]
    buf = np.empty(n, np.float32)
    for j in range(m):
        count = 0
        for k in range(n):
            if cand[k, j]:
                buf[count] = abs(res[k, j])
                count += 1
        out[j] = 0.0 if count == 0 else _MAD_TO_SIGMA * np.sort(buf[:count])[(count - 1) // 2]


@numba.njit(nogil=True, cache=True, fastmath=_FAST)
def robust_ps_rows(codes, table, r0, r1, outer_t, u_t, back, dirs, halves, par, irls, cone, iterations,
                   normals, albedo, samples, valid, chunk=256):  # pragma: no cover - compiled
    """Robust photometric stereo of rows ``r0:r1``, written into the result arrays.

    Parameters
    ----------
    codes : ndarray, shape (N, H, W), uint8 or uint16
        The stack as stored; the last code of ``table`` marks a clipped sample.
    table : ndarray, float32
        Linear luminance of every code.
    r0, r1 : int
        The rows to do.
    outer_t, u_t : ndarray, shape (r(r + 1)/2, N) and (r, N), float32
        Products of the pairs of columns, and the columns, of the orthonormal basis of the light
        directions (``Basis.outer.T`` and ``Basis.u.T`` of :func:`ptmcore.pixelfit.orthonormal_basis`).
    back : ndarray, shape (3, r), float64
        Maps a solution in ``u`` to g = ρn.
    dirs, halves : ndarray, shape (N, 3), float32
        Light directions and half vectors.
    par : ndarray, float64
        dark fraction, min shading, cast-shadow ratio, cos(specular cone), reject below,
        reject above, noise floor, relative floor, consistency factor.
    irls : bool
        Tukey weights (else trimming).
    cone : bool
        Whether the specular-cone estimate is made.
    iterations : int
        Robust passes.
    normals, albedo, samples, valid : ndarray
        The result arrays (H, W, 3) float32, (H, W) float32, (H, W) uint16, (H, W) bool.
    chunk : int
        Pixels done together: their samples stay in the cache through every pass.
    """
    n, _, width = codes.shape
    r = u_t.shape[0]
    # Every chunk has the same width, so the work arrays stay contiguous for BLAS; the columns
    # past the image's edge have no usable sample and are not stored.
    chunk = -(-width // -(-width // chunk))
    sat = table.shape[0] - 1
    dark = np.float32(par[_DARK])
    min_shading = par[_MIN_SHADING]
    min_shading32 = np.float32(min_shading)
    cast = np.float32(par[_CAST])
    cos_cone = np.float32(par[_COS_CONE])
    below, above = par[_BELOW], par[_ABOVE]
    noise, relative, consistency = par[_NOISE], par[_RELATIVE], par[_CONSISTENCY]
    v = np.empty((n, chunk), np.float32)
    usable = np.empty((n, chunk), np.bool_)
    w = np.empty((n, chunk), np.float32)
    w2 = np.empty((n, chunk), np.float32)
    res = np.empty((n, chunk), np.float32)
    cand = np.empty((n, chunk), np.bool_)
    c = np.empty((3, chunk))
    c2 = np.empty((3, chunk))
    zero = np.zeros((3, chunk))
    g32 = np.empty((3, chunk), np.float32)
    g32b = np.empty((3, chunk), np.float32)
    unit = np.empty((3, chunk), np.float32)
    unit2 = np.empty((3, chunk), np.float32)
    rho = np.empty(chunk)
    rho2 = np.empty(chunk)
    ok = np.empty(chunk, np.bool_)
    ok2 = np.empty(chunk, np.bool_)
    vmax = np.empty(chunk, np.float32)
    scale = np.empty(chunk)
    hi = np.empty(chunk, np.float32)
    floor = np.empty(chunk, np.float32)
    lo = np.empty(chunk, np.float32)
    rhs = np.empty((r, chunk), np.float32)
    gram = np.empty((outer_t.shape[0], chunk), np.float32)
    wv = np.empty((n, chunk), np.float32)
    wv2 = np.empty((n, chunk), np.float32)
    num = np.empty(chunk, np.float32)
    den = np.empty(chunk, np.float32)
    low = np.empty((11, chunk))
    for row in range(r0, r1):
        for c0 in range(0, width, chunk):
            inside = min(chunk, width - c0)
            m = chunk
            vv, uu, ww, ww2, rr, cc = v, usable, w, w2, res, cand
            for j in range(m):
                vmax[j] = 0.0
            for k in range(n):
                for j in range(inside):
                    code = codes[k, row, c0 + j]
                    vv[k, j] = table[code]
                    uu[k, j] = code != sat
                    vmax[j] = max(vmax[j], vv[k, j])
                for j in range(inside, m):
                    vv[k, j] = 0.0
                    uu[k, j] = False
            # Step 1: without dark (shadowed) and clipped samples.
            for j in range(m):
                vmax[j] = max(dark * vmax[j], np.float32(1e-4))
            for k in range(n):
                for j in range(m):
                    ww[k, j] = np.float32(1.0) if (vv[k, j] > vmax[j]) & uu[k, j] else np.float32(0.0)
                    wv[k, j] = ww[k, j] * vv[k, j]
            _solve(ww, wv, m, outer_t, u_t, r, zero, 1e-6, c, ok, gram, rhs, low)
            _to_normal(c, m, back, r, g32, unit, rho)
            if cone:
                # Step 2: without the lights whose half vector is near the first normal.
                for k in range(n):
                    # Loop invariants read into locals: the compiler cannot tell that the
                    # stores below do not change them.
                    d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
                    h0, h1, h2 = halves[k, 0], halves[k, 1], halves[k, 2]
                    for j in range(m):
                        lit = d0 * unit[0, j] + d1 * unit[1, j] + d2 * unit[2, j]
                        half = h0 * unit[0, j] + h1 * unit[1, j] + h2 * unit[2, j]
                        in_cone = (lit > min_shading32) & (half < cos_cone) & uu[k, j]
                        ww2[k, j] = np.float32(1.0) if in_cone else np.float32(0.0)
                        wv2[k, j] = ww2[k, j] * vv[k, j]
                _solve(ww2, wv2, m, outer_t, u_t, r, c, 1e-3, c2, ok2, gram, rhs, low)
                _to_normal(c2, m, back, r, g32b, unit2, rho2)
                for j in range(m):
                    # Where the cone's fit is ill posed or its normal left the cone, the first
                    # estimate stays: the cone's fit is only meant to undo a highlight's pull.
                    agree = unit2[0, j] * unit[0, j] + unit2[1, j] * unit[1, j] + unit2[2, j] * unit[2, j]
                    if ok2[j] and agree > cos_cone:
                        for a in range(r):
                            c[a, j] = c2[a, j]
                        for k in range(n):
                            ww[k, j] = ww2[k, j]
                _to_normal(c, m, back, r, g32, unit, rho)
            # Step 3: robust passes.
            for t in range(iterations):
                for j in range(m):
                    floor[j] = np.float32(min_shading * rho[j])
                    num[j] = 0.0
                    den[j] = 0.0
                # Predictions, candidates and residuals, and in the same pass the residuals'
                # RMS under the previous weights (the scale; see ptmcore.robust.reweight).
                for k in range(n):
                    d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
                    for j in range(m):
                        p = d0 * g32[0, j] + d1 * g32[1, j] + d2 * g32[2, j]
                        cc[k, j] = (p > floor[j]) & uu[k, j] & (vv[k, j] >= cast * p)
                        res_kj = vv[k, j] - p
                        rr[k, j] = res_kj
                        num[j] += ww[k, j] * res_kj * res_kj
                        den[j] += ww[k, j]
                if t > 0 or cone:
                    # The cone's fit's residuals over its own samples first (r parameters
                    # fitted to them), then the previous pass's, divided by the consistency.
                    dof = np.float32(0.0) if t > 0 else np.float32(r)
                    for j in range(m):
                        scale[j] = math.sqrt(num[j] / max(den[j] - dof, np.float32(1.0)))
                        if t > 0:
                            scale[j] = np.float32(scale[j]) / consistency
                else:
                    _median_scale(rr, cc, m, scale)
                for j in range(m):
                    s = max(scale[j], noise + relative * rho[j])
                    hi[j] = np.float32(s * above)
                    lo[j] = np.float32(s * -below)
                if irls:
                    # Tukey's biweight of |res| / the bound of its sign: of res/hi and res/lo,
                    # the larger is the one with the right sign. Multiplying by reciprocals
                    # instead of dividing changes the weights by float32 rounding only.
                    for j in range(m):
                        hi[j] = np.float32(1.0) / hi[j]
                        lo[j] = np.float32(1.0) / lo[j]
                    for k in range(n):
                        for j in range(m):
                            q = max(rr[k, j] * hi[j], rr[k, j] * lo[j])
                            q = max(np.float32(1.0) - q * q, np.float32(0.0))
                            ww[k, j] = q * q if cc[k, j] else np.float32(0.0)
                            wv[k, j] = ww[k, j] * vv[k, j]
                else:
                    for k in range(n):
                        for j in range(m):
                            keep = (rr[k, j] <= hi[j]) & (rr[k, j] >= lo[j]) & cc[k, j]
                            ww[k, j] = np.float32(1.0) if keep else np.float32(0.0)
                            wv[k, j] = ww[k, j] * vv[k, j]
                _solve(ww, wv, m, outer_t, u_t, r, c, 1e-6, c2, ok2, gram, rhs, low)
                for j in range(m):
                    if ok2[j]:
                        for a in range(r):
                            c[a, j] = c2[a, j]
                    ok[j] = ok[j] | ok2[j]
                _to_normal(c, m, back, r, g32, unit, rho)
            for j in range(inside):
                col = c0 + j
                # As ptmcore.normals.store_normals: (0, 0, 1) where undetermined; lights in one
                # plane (r < 3) leave every normal undetermined.
                gx = np.float64(unit[0, j]) * rho[j]
                gy = np.float64(unit[1, j]) * rho[j]
                gz = np.float64(unit[2, j]) * rho[j]
                length = math.sqrt(gx * gx + gy * gy + gz * gz)
                good = ok[j] and r == 3 and length > 0 and math.isfinite(length)
                if good:
                    normals[row, col, 0] = gx / length
                    normals[row, col, 1] = gy / length
                    normals[row, col, 2] = gz / length
                    albedo[row, col] = length
                else:
                    normals[row, col, 0] = 0.0
                    normals[row, col, 1] = 0.0
                    normals[row, col, 2] = 1.0
                    albedo[row, col] = 0.0
                valid[row, col] = good
            total = np.zeros(m, np.float32)
            for k in range(n):
                for j in range(m):
                    total[j] += ww[k, j]
            for j in range(inside):
                samples[row, c0 + j] = np.uint16(round(total[j]))
