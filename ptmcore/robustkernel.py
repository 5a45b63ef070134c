"""The compiled per-pixel kernel of robust photometric stereo.

:func:`ptmcore.robust.robust_photometric_stereo` runs the steps of :mod:`ptmcore.robust` (first
Lambertian estimate, specular cone, robust passes) one pixel at a time here, with numba. In NumPy
those steps are some forty element-wise passes over a band of the stack per pixel fit; here each
chunk of a row's pixels is read once from the stack (through the stack's code → linear table)
into buffers that stay in the cache, and every pass works on those, with the pixels in the
innermost loops so that the compiler vectorises them. The compiler only vectorises a loop whose
arrays it can tell apart, so the work arrays have a width fixed at compilation (:data:`_CHUNK`)
and the loops that use several photographs at a time are inlined where those arrays are made.
The weighted least-squares sums take a few photographs at a time, with every pixel's sums in
registers (:func:`_sums`), and the solves are for three unknowns only, the basis padded to three
columns where the lights lie in a plane, so that each pixel's solve is straight-line code
(:func:`_solve`). The kernel releases the GIL, so bands of rows run in the caller's threads:
``threads`` is respected and numba's own threading layer is not involved (several of its layers
may not be entered from several threads at once).

The same kernel makes the robust PTM (:func:`ptmcore.robustptm.robust_ptm`): with ``ptm``
given, each chunk's final weights fit a PTM and its hemisphere PTM (:func:`_ptm_fit`) and give
the debiased normals, instead of the Lambertian normals. The PTM's sums are 28 per pixel, too
many to keep in registers, so they are added one sum at a time over the photographs (each a
vectorised loop over the chunk's pixels, in the cache), and the 6×6 solves are the Cholesky
factorisation of :func:`ptmcore.pixelfit.cholesky_solve`, vectorised over the pixels as it is.

The arithmetic follows the NumPy steps: float32 where they use float32 (residuals, weights,
thresholds, the least-squares sums), float64 for the normal equations; results agree within
float32 rounding, magnified by each pixel's condition number (``tests/test_robust_kernel.py``,
``tests/test_robust_ptm_kernel.py`` bound it so on any CPU and BLAS library), but
where a sample's weight is on a threshold's edge and rounding tips it across; a flat PTM
(:data:`ptmcore.normals.FLAT`) gives no normal in both. The NumPy steps stay in
:mod:`ptmcore.robust` and :mod:`ptmcore.robustptm` as the kernel's reference (``compiled=False``),
and for what the kernel does not do (a robust PTM with fixed normals or refining passes).

Compiled code is cached on disk (numba's ``cache=True``, beside this module or in
``NUMBA_CACHE_DIR``), so only the first run after installation pays for compilation.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .lobe import FACTOR_RANGE
from .pixelfit import SINGULAR

__all__ = ["robust_ps_rows"]

# Indices into the float64 parameter vector (numba compiles one function for every option
# set instead of one per keyword combination).
_DARK, _MIN_SHADING, _CAST, _COS_CONE, _BELOW, _ABOVE, _NOISE, _RELATIVE, _CONSISTENCY = range(9)
_RIDGE = 1e-6
_MAD_TO_SIGMA = 1.4826
#: Photographs per step of the passes that add up over the photographs. Within a step each
#: pixel's running sums stay in registers; without steps they go to memory and back at every
#: photograph. Two were a few per cent slower on 48 photographs, eight five times slower.
_BLOCK = 4
#: Pixels done together: their samples stay in the cache through every pass. A width known at
#: compilation puts the rows of the work arrays a known distance apart, which is what lets the
#: compiler vectorise the loops that write several rows at once.
_CHUNK = 256
#: Pixels per vector or two: the last chunk of a row is done to a multiple of this.
_LANES = 16
#: Fused multiply-adds and reciprocals allowed (not reassociation, so sums keep their order):
#: they change results by float32 rounding only.
_FAST = {"contract", "arcp", "nsz"}
#: Division by zero gives inf or NaN instead of raising: the check for it on every division
#: keeps a loop from vectorising (the kernel never divides by zero).
_JIT = {"nogil": True, "cache": True, "fastmath": _FAST, "error_model": "numpy"}


@numba.njit(inline="always", **_JIT)
def _packed(a, b, r):  # pragma: no cover - compiled
    """Row of entry (a, b), a ≤ b, of an r×r symmetric matrix stored as its upper triangle."""
    return a * r - a * (a - 1) // 2 + (b - a)


@numba.njit(**_JIT)
def _padded(outer_t, u_t, back, dirs, halves):  # pragma: no cover - compiled
    """The basis and the lights padded with zeros to three columns and a whole number of blocks.

    Returns ``basis`` (9, N'), float32: rows 0–5 are the products of the pairs of columns
    (packed as :func:`_packed` for r = 3), rows 6–8 the columns; ``back`` (3, 3); ``dirs`` and
    ``halves`` (N', 3). N' is N rounded up to a multiple of :data:`_BLOCK`. A padded column
    leaves every sum of its own as 0, and a padded photograph, never usable, adds nothing.
    """
    r, n = u_t.shape
    n_padded = -(-n // _BLOCK) * _BLOCK
    basis = np.zeros((9, n_padded), np.float32)
    back3 = np.zeros((3, 3))
    for a in range(r):
        basis[6 + a, :n] = u_t[a]
        back3[:, a] = back[:, a]
        for b in range(a, r):
            basis[_packed(a, b, 3), :n] = outer_t[_packed(a, b, r)]
    dirs_padded = np.zeros((n_padded, 3), np.float32)
    halves_padded = np.zeros((n_padded, 3), np.float32)
    dirs_padded[:n] = dirs
    halves_padded[:n] = halves
    return basis, back3, dirs_padded, halves_padded


@numba.njit(inline="always", **_JIT)
def _sums_of(sums, j):  # pragma: no cover - compiled
    """Pixel ``j``'s nine sums, as a tuple the compiler keeps in registers."""
    return (sums[0, j], sums[1, j], sums[2, j], sums[3, j], sums[4, j], sums[5, j],
            sums[6, j], sums[7, j], sums[8, j])


@numba.njit(inline="always", **_JIT)
def _add(acc, basis, k, w, wv):  # pragma: no cover - compiled
    """``acc`` plus photograph ``k``'s terms of ``Σ w φ φᵀ`` and ``Σ w φ v`` (``wv`` = w·v)."""
    s0, s1, s2, s3, s4, s5, s6, s7, s8 = acc
    return (s0 + basis[0, k] * w, s1 + basis[1, k] * w, s2 + basis[2, k] * w,
            s3 + basis[3, k] * w, s4 + basis[4, k] * w, s5 + basis[5, k] * w,
            s6 + basis[6, k] * wv, s7 + basis[7, k] * wv, s8 + basis[8, k] * wv)


@numba.njit(inline="always", **_JIT)
def _store(sums, j, acc):  # pragma: no cover - compiled
    """Writes pixel ``j``'s nine sums back."""
    sums[0, j], sums[1, j], sums[2, j], sums[3, j], sums[4, j], sums[5, j] = acc[:6]
    sums[6, j], sums[7, j], sums[8, j] = acc[6:]


@numba.njit(inline="always", **_JIT)
def _sums(w, v, basis, m, sums):  # pragma: no cover - compiled
    """Each pixel's ``Σ w φ φᵀ`` and ``Σ w φ v`` over the photographs, float32, into ``sums``
    (9, m): what the NumPy steps get from two matrix products, added photograph by photograph.

    Inlined: only where the work arrays are made does the compiler know their width, which it
    needs to vectorise the loop (called as a function, the kernel was three times slower).
    """
    for e in range(9):
        for j in range(m):
            sums[e, j] = 0.0
    for k0 in range(0, basis.shape[1], _BLOCK):
        for j in range(m):
            acc = _sums_of(sums, j)
            for k in range(k0, k0 + _BLOCK):
                acc = _add(acc, basis, k, w[k, j], w[k, j] * v[k, j])
            _store(sums, j, acc)


@numba.njit(**_JIT)
def _solve(sums, prior, r, singular, m, out, ok):  # pragma: no cover - compiled
    """Each pixel's weighted least squares with a ridge towards ``prior``, as
    :func:`ptmcore.pixelfit.cholesky_solve` solves it: in float64, from the float32 sums
    (9, m) of :func:`_sums`. Writes the solution into ``out`` (3, m) and
    well-posedness into ``ok`` (m,).

    The basis has three columns, the last ``3 − r`` of them zero (:func:`_padded`): their
    pivots are λ and their unknowns stay 0, so only the determinant, over the first ``r``
    pivots, and the mean eigenvalue, over r, need ``r``. With the size fixed, each pixel's
    factorisation is straight-line code and the loop over the pixels vectorises.
    """
    for j in range(m):
        g00, g01, g02 = np.float64(sums[0, j]), np.float64(sums[1, j]), np.float64(sums[2, j])
        g11, g12, g22 = np.float64(sums[3, j]), np.float64(sums[4, j]), np.float64(sums[5, j])
        mean_eig = max((g00 + g11 + g22) / r, 1e-30)
        lam = _RIDGE * mean_eig
        # G + λI = L D Lᵀ with a unit triangular L: the pivots d are those of the Cholesky
        # factorisation in cholesky_solve (the squares of its diagonal), without its square
        # roots and with three divisions instead of nine; a difference of float64 rounding.
        d0 = max(g00 + lam, lam)
        i0 = 1.0 / d0
        l01 = g01 * i0
        l02 = g02 * i0
        d1 = max(g11 + lam - l01 * g01, lam)
        i1 = 1.0 / d1
        e12 = g12 - l01 * g02
        l12 = e12 * i1
        d2 = max(g22 + lam - l02 * g02 - l12 * e12, lam)
        i2 = 1.0 / d2
        y0 = sums[6, j] + lam * prior[0, j]
        y1 = sums[7, j] + lam * prior[1, j] - l01 * y0
        y2 = sums[8, j] + lam * prior[2, j] - l02 * y0 - l12 * y1
        x2 = y2 * i2
        x1 = y1 * i1 - l12 * x2
        out[0, j] = y0 * i0 - l01 * x1 - l02 * x2
        out[1, j] = x1
        out[2, j] = x2
        # det G > singular · (mean eigenvalue)^r, without logarithms: each pivot ≥ λ keeps the
        # product far from underflow.
        det = d0
        bound = singular * mean_eig
        if r > 1:
            det *= d1
            bound *= mean_eig
        if r > 2:
            det *= d2
            bound *= mean_eig
        ok[j] = det > bound


@numba.njit(**_JIT)
def _to_normal(c, m, back, g32, unit, rho):  # pragma: no cover - compiled
    """ρ = |g| (float64) into ``rho``, g = back · c as float32 into ``g32`` (the predictions are
    made from it, as the NumPy steps make them) and the unit normal (float32) into ``unit``."""
    b00, b01, b02 = back[0, 0], back[0, 1], back[0, 2]
    b10, b11, b12 = back[1, 0], back[1, 1], back[1, 2]
    b20, b21, b22 = back[2, 0], back[2, 1], back[2, 2]
    for j in range(m):
        c0, c1, c2 = c[0, j], c[1, j], c[2, j]
        g0 = b00 * c0 + b01 * c1 + b02 * c2
        g1 = b10 * c0 + b11 * c1 + b12 * c2
        g2 = b20 * c0 + b21 * c1 + b22 * c2
        length = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        inv = 1.0 / length if length > 0 else 1.0
        rho[j] = length
        g32[0, j], g32[1, j], g32[2, j] = np.float32(g0), np.float32(g1), np.float32(g2)
        unit[0, j], unit[1, j], unit[2, j] = np.float32(g0 * inv), np.float32(g1 * inv), np.float32(g2 * inv)


@numba.njit(**_JIT)
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


@numba.njit(inline="always", **_JIT)
def _debiased_normal(a0, a1, a2, a3, a4, a5, q0, q1, q2, q3, q4, flat, same):  # pragma: no cover - compiled
    """The debiased normal (float32 x, y, z) of a PTM ``a`` and its hemisphere PTM ``q``
    (float64; ``q``'s constant term plays no part), and whether it was read:
    :func:`ptmcore.robustptm._debiased` for one pixel. (0, 0, 1), not read, where the samples
    are all the ``same``, the PTM is flat (|a0| + … + |a4| ≤ ``flat`` × |a5|) or it gives no
    normal facing the camera."""
    det = 4 * a0 * a1 - a2 * a2
    concave = (a0 < 0) and (det > 0)
    if not concave:
        det = 1.0
    lu = (a2 * a4 - 2 * a1 * a3) / det
    lv = (a2 * a3 - 2 * a0 * a4) / det
    qq = q0 * q0 + q1 * q1 + 0.5 * q2 * q2
    rho_z = (a0 * q0 + a1 * q1 + 0.5 * a2 * q2) / (qq if qq > 0 else 1.0)
    if concave:
        g0, g1, g2 = -(2 * q0 * lu + q2 * lv + q3), -(2 * q1 * lv + q2 * lu + q4), 1.0
    else:
        g0, g1, g2 = a3 - rho_z * q3, a4 - rho_z * q4, rho_z
    length = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    norm = length if length > 0 else 1.0
    x, y, z = np.float32(g0 / norm), np.float32(g1 / norm), np.float32(g2 / norm)
    shape = abs(a0) + abs(a1) + abs(a2) + abs(a3) + abs(a4)
    if same or not (shape > flat * abs(a5) and length > 0 and math.isfinite(length) and z > 0):
        return np.float32(0.0), np.float32(0.0), np.float32(1.0), False
    return x, y, z, True


@numba.njit(inline="always", **_JIT)
def _less_products(acc, a, ra, b, rb, m):  # pragma: no cover - compiled
    """``acc -= a[ra] · b[rb]`` over the chunk's ``m`` pixels: the step of the Cholesky
    factorisation and of both substitutions of :func:`_ptm_fit`."""
    for j in range(m):
        acc[j] = acc[j] - a[ra, j] * b[rb, j]


@numba.njit(inline="always", **_JIT)
def _divided(out, row, acc, low, e, m):  # pragma: no cover - compiled
    """``out[row] = acc / low[e]`` over the chunk's ``m`` pixels (a substitution's last step)."""
    for j in range(m):
        out[row, j] = acc[j] / low[e, j]


@numba.njit(**_JIT)
def _ptm_fit(ptm, v, w, m, inside, row, c0, sums, rhs, gram, low, sol, work, total, same):  # pragma: no cover - compiled
    """The PTM and hemisphere PTM of the chunk's pixels with weights ``w``, as
    :func:`ptmcore.robustptm.robust_ptm` fits them (:func:`ptmcore.pixelfit.weighted_fit` with
    the plain fits as prior and fallback), written with the debiased normals (none where the
    samples are all the ``same``, (chunk,) bool) and the weights' sums ``total`` (chunk,) into ``ptm``'s result arrays (:class:`ptmcore.robustptm.KernelPTM`)
    at ``row``, columns ``c0:c0 + inside``.

    Work arrays: ``sums`` (K, chunk) and ``rhs`` (2r, chunk) float32;
    ``gram`` and ``low`` (r(r+1)/2, chunk), ``sol`` (4r, chunk) and ``work`` (5, chunk) float64. Every loop over the
    pixels is innermost, so that it vectorises, as :func:`ptmcore.pixelfit.cholesky_solve`'s
    operations are vectors over the pixels.
    """
    outer_t, u_t, back, plain_z = ptm.outer_t, ptm.u_t, ptm.back, ptm.plain_z
    gram_rows, extra_rows, singular, flat = ptm.gram_rows, ptm.extra_rows, ptm.singular, ptm.flat
    coef, hemi, nout, valid, used = ptm.coefficients, ptm.hemisphere, ptm.normals, ptm.valid, ptm.used
    n = u_t.shape[1]  # the photographs (v and w have padded rows past them)
    r = u_t.shape[0]
    k_sums = outer_t.shape[0]
    lam, det, bound, acc, inv = work[0], work[1], work[2], work[3], work[4]
    # Σ w φφᵀ (and Σ w φ lz), as weighted_fit's product outer.T @ weights; Σ w φ v, and the
    # plain fit's Σ φ v: float32, photograph by photograph.
    for e in range(k_sums):
        for j in range(m):
            sums[e, j] = 0.0
    for e in range(2 * r):
        for j in range(m):
            rhs[e, j] = 0.0
    for k in range(n):
        for e in range(k_sums):
            f = outer_t[e, k]
            for j in range(m):
                sums[e, j] += f * w[k, j]
        for a in range(r):
            f = u_t[a, k]
            for j in range(m):
                rhs[a, j] += f * (w[k, j] * v[k, j])
                rhs[r + a, j] += f * v[k, j]
    # cholesky_solve: G + λI = L Lᵀ, λ = 10⁻⁶ × the mean eigenvalue; L's column i is kept in
    # the packed rows of (i, i..r-1) (packed as ptmcore.pixelfit.packed_index packs G).
    for e in range(r * (r + 1) // 2):
        for j in range(m):
            gram[e, j] = np.float64(sums[gram_rows[e], j])
    for j in range(m):
        acc[j] = 0.0
    for i in range(r):
        e = _packed(i, i, r)
        for j in range(m):
            acc[j] += gram[e, j]
    for j in range(m):
        mean = max(acc[j] / r, 1e-30)
        lam[j] = 1e-6 * mean
        det[j] = 1.0
        # det G > singular · mean^r, the NumPy steps' test on logarithms, without them: with
        # orthonormal columns and weights ≤ 1 the pivots keep det within [λ^r, 1].
        bound[j] = singular * mean ** r
    for col in range(r):
        dc = _packed(col, col, r)
        for j in range(m):
            acc[j] = gram[dc, j] + lam[j]
        for kk in range(col):
            e = _packed(kk, col, r)
            _less_products(acc, low, e, low, e, m)
        for j in range(m):
            d = math.sqrt(max(acc[j], lam[j]))
            low[dc, j] = d
            det[j] *= d * d
            inv[j] = 1.0 / d
        for i in range(col + 1, r):
            e = _packed(col, i, r)
            for j in range(m):
                acc[j] = gram[e, j]
            for kk in range(col):
                _less_products(acc, low, _packed(kk, i, r), low, _packed(kk, col, r), m)
            for j in range(m):
                low[e, j] = acc[j] * inv[j]
    # Two right-hand sides, Σ w φ v and Σ w φ lz, each with its plain fit as the prior: the
    # solutions into sol[0:r] and sol[r:2r], the priors into sol[2r:3r] and sol[3r:4r].
    for q in range(2):
        x, prior = q * r, 2 * r + q * r
        for i in range(r):
            if q == 0:
                for j in range(m):
                    sol[prior + i, j] = np.float64(rhs[r + i, j])
                    acc[j] = np.float64(rhs[i, j]) + lam[j] * sol[prior + i, j]
            else:
                z = plain_z[i]
                ez = extra_rows[i]
                for j in range(m):
                    sol[prior + i, j] = z
                    acc[j] = np.float64(sums[ez, j]) + lam[j] * z
            for kk in range(i):
                _less_products(acc, low, _packed(kk, i, r), sol, x + kk, m)
            _divided(sol, x + i, acc, low, _packed(i, i, r), m)
        for i in range(r - 1, -1, -1):
            for j in range(m):
                acc[j] = sol[x + i, j]
            for kk in range(i + 1, r):
                _less_products(acc, low, _packed(i, kk, r), sol, x + kk, m)
            _divided(sol, x + i, acc, low, _packed(i, i, r), m)
    for j in range(inside):
        # Where the weights leave too few samples, or samples too close together, the plain
        # fit (a matrix product in the NumPy steps) stands in; and where the samples are all
        # the same, whose weighted fit would have a shape of rounding only.
        off = 0 if det[j] > bound[j] and not same[j] else 2 * r
        # Back to the PTM's coefficients (sol[off:off + r]) and the hemisphere PTM's (the r rows
        # after), written out: twelve accumulators in registers. A loop over the six through a
        # work array gave the same bits 4–6 % slower (robust_ptm, 400×600 pixels, one thread).
        a0 = a1 = a2 = a3 = a4 = a5 = 0.0
        q0 = q1 = q2 = q3 = q4 = q5 = 0.0
        for b in range(r):
            c, cz = sol[off + b, j], sol[off + r + b, j]
            a0 += back[0, b] * c
            a1 += back[1, b] * c
            a2 += back[2, b] * c
            a3 += back[3, b] * c
            a4 += back[4, b] * c
            a5 += back[5, b] * c
            q0 += back[0, b] * cz
            q1 += back[1, b] * cz
            q2 += back[2, b] * cz
            q3 += back[3, b] * cz
            q4 += back[4, b] * cz
            q5 += back[5, b] * cz
        col = c0 + j
        coef[row, col, 0], coef[row, col, 1], coef[row, col, 2] = a0, a1, a2
        coef[row, col, 3], coef[row, col, 4], coef[row, col, 5] = a3, a4, a5
        hemi[row, col, 0], hemi[row, col, 1], hemi[row, col, 2] = q0, q1, q2
        hemi[row, col, 3], hemi[row, col, 4], hemi[row, col, 5] = q3, q4, q5
        x, y, z, read = _debiased_normal(a0, a1, a2, a3, a4, a5, q0, q1, q2, q3, q4, flat, same[j])
        nout[row, col, 0], nout[row, col, 1], nout[row, col, 2] = x, y, z
        valid[row, col] = read
        used[row, col] = total[j]


@numba.njit(**_JIT)
def robust_ps_rows(codes, table, r0, r1, outer_t, u_t, back, dirs, halves, par, irls, cone, iterations,
                   normals, albedo, samples, valid, prior, lobe, ptm=None):  # pragma: no cover - compiled
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
    normals, albedo, samples, valid : ndarray or None
        The result arrays (H, W, 3) float32, (H, W) float32, (H, W) uint16, (H, W) bool; None
        (all four) when only the PTM is wanted.
    prior : ndarray, shape (H, W, 3), float32, or None
        Unit normals at which the lobe is evaluated (:mod:`ptmcore.lobe`): each sample is
        divided by ``f(n·h, n·l)`` before the fit. May be ``normals`` itself: a chunk's prior
        is read before its normals are written. None: no lobe (the branch is compiled out).
    lobe : ndarray, float64
        The lobe's coefficients, of the powers of (1 − n·h) from the 0th.
    ptm : ptmcore.robustptm.KernelPTM or None
        The robust PTM's basis and result arrays, to fit a PTM with each pixel's final weights
        (:func:`_ptm_fit`). None: no PTM (compiled out).
    """
    n_photos, _, width = codes.shape
    r = u_t.shape[0]
    basis, back3, dirs, halves = _padded(outer_t, u_t, back, dirs, halves)
    n = basis.shape[1]
    chunk = _CHUNK  # a global: numba compiles it in as a constant
    sat = table.shape[0] - 1
    dark = np.float32(par[_DARK])
    min_shading = par[_MIN_SHADING]
    min_shading32 = np.float32(min_shading)
    cast = np.float32(par[_CAST])
    cos_cone = np.float32(par[_COS_CONE])
    below, above = par[_BELOW], par[_ABOVE]
    noise, relative, consistency = par[_NOISE], par[_RELATIVE], par[_CONSISTENCY]
    # The padded photographs' rows stay 0 and unusable.
    v = np.zeros((n, chunk), np.float32)
    usable = np.zeros((n, chunk), np.bool_)
    w = np.empty((n, chunk), np.float32)
    w2 = np.empty((n, chunk), np.float32)
    res = np.empty((n, chunk), np.float32)
    cand = np.empty((n, chunk), np.bool_)
    sums = np.empty((9, chunk), np.float32)
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
    take = np.empty(chunk, np.bool_)
    vmax = np.empty(chunk, np.float32)
    vmin = np.empty(chunk, np.float32)
    same = np.empty(chunk, np.bool_)
    scale = np.empty(chunk)
    hi = np.empty(chunk, np.float32)
    floor = np.empty(chunk, np.float32)
    lo = np.empty(chunk, np.float32)
    num = np.empty(chunk, np.float32)
    den = np.empty(chunk, np.float32)
    total = np.empty(chunk, np.float32)
    pn = np.empty((3, chunk), np.float32)
    lo_f, hi_f = np.float32(FACTOR_RANGE[0]), np.float32(FACTOR_RANGE[1])
    # The PTM's work arrays (empty without it).
    rp = 0 if ptm is None else ptm.u_t.shape[0]
    kp = 0 if ptm is None else ptm.outer_t.shape[0]
    p_sums = np.empty((kp, chunk), np.float32)
    p_rhs = np.empty((2 * rp, chunk), np.float32)
    p_gram = np.empty((rp * (rp + 1) // 2, chunk))
    p_low = np.empty((rp * (rp + 1) // 2, chunk))
    p_sol = np.empty((4 * rp, chunk))
    p_work = np.empty((5, chunk))
    for row in range(r0, r1):
        for c0 in range(0, width, chunk):
            inside = min(chunk, width - c0)
            # The columns from inside to m have no usable sample and are not stored.
            m = min(chunk, -(-inside // _LANES) * _LANES)
            for j in range(m):
                vmax[j] = 0.0
                vmin[j] = np.float32(math.inf)
            if prior is not None:
                for j in range(inside):
                    pn[0, j], pn[1, j], pn[2, j] = prior[row, c0 + j, 0], prior[row, c0 + j, 1], prior[row, c0 + j, 2]
            for k in range(n_photos):
                line = codes[k, row, c0:c0 + inside]
                # The look-up is a gather, which the compiler leaves scalar: on its own the rest
                # of the pass vectorises.
                for j in range(inside):
                    v[k, j] = table[line[j]]
                if prior is not None:
                    h0, h1, h2 = halves[k, 0], halves[k, 1], halves[k, 2]
                    for j in range(inside):
                        x = np.float32(1.0) - (h0 * pn[0, j] + h1 * pn[1, j] + h2 * pn[2, j])
                        f = np.float32(0.0)
                        for a in range(len(lobe) - 1, -1, -1):
                            f = f * x + np.float32(lobe[a])
                        v[k, j] = v[k, j] / min(max(f, lo_f), hi_f)
                for j in range(inside):
                    usable[k, j] = line[j] != sat
                    vmax[j] = max(vmax[j], v[k, j])
                    vmin[j] = min(vmin[j], v[k, j])
                for j in range(inside, m):
                    v[k, j] = 0.0
                    usable[k, j] = False
            if ptm is not None:
                # Samples all within ptm.flat of the brightest carry no direction (all clipped,
                # all black, one value): as ptmcore.robustptm.robust_ptm decides it.
                for j in range(m):
                    same[j] = np.float64(vmax[j]) - np.float64(vmin[j]) <= ptm.flat * np.float64(vmax[j])
            # Step 1: without dark (shadowed) and clipped samples.
            for j in range(m):
                vmax[j] = max(dark * vmax[j], np.float32(1e-4))
            for k in range(n):
                for j in range(m):
                    w[k, j] = np.float32(1.0) if (v[k, j] > vmax[j]) & usable[k, j] else np.float32(0.0)
            _sums(w, v, basis, m, sums)
            _solve(sums, zero, r, SINGULAR, m, c, ok)
            _to_normal(c, m, back3, g32, unit, rho)
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
                        in_cone = (lit > min_shading32) & (half < cos_cone) & usable[k, j]
                        w2[k, j] = np.float32(1.0) if in_cone else np.float32(0.0)
                _sums(w2, v, basis, m, sums)
                _solve(sums, c, r, 1e-3, m, c2, ok2)
                _to_normal(c2, m, back3, g32b, unit2, rho2)
                for j in range(m):
                    # Where the cone's fit is ill posed or its normal left the cone, the first
                    # estimate stays: the cone's fit is only meant to undo a highlight's pull.
                    agree = unit2[0, j] * unit[0, j] + unit2[1, j] * unit[1, j] + unit2[2, j] * unit[2, j]
                    take[j] = ok2[j] and agree > cos_cone
                    if take[j]:
                        for a in range(3):
                            c[a, j] = c2[a, j]
                for k in range(n):
                    for j in range(m):
                        # Both read first: a select of two values vectorises, one of two
                        # addresses does not.
                        cone_w, first_w = w2[k, j], w[k, j]
                        w[k, j] = cone_w if take[j] else first_w
                _to_normal(c, m, back3, g32, unit, rho)
            # Step 3: robust passes.
            for t in range(iterations):
                for j in range(m):
                    floor[j] = np.float32(min_shading * rho[j])
                    num[j] = 0.0
                    den[j] = 0.0
                # Predictions, candidates and residuals, and in the same pass the residuals'
                # RMS under the previous weights (the scale; see ptmcore.robust.reweight); a
                # block of photographs at a time, as in _sums.
                for k0 in range(0, n, _BLOCK):
                    for j in range(m):
                        gx, gy, gz = g32[0, j], g32[1, j], g32[2, j]
                        sq, sw = num[j], den[j]
                        for k in range(k0, k0 + _BLOCK):
                            p = dirs[k, 0] * gx + dirs[k, 1] * gy + dirs[k, 2] * gz
                            cand[k, j] = (p > floor[j]) & usable[k, j] & (v[k, j] >= cast * p)
                            res_kj = v[k, j] - p
                            res[k, j] = res_kj
                            sq += w[k, j] * res_kj * res_kj
                            sw += w[k, j]
                        num[j], den[j] = sq, sw
                if t > 0 or cone:
                    # The cone's fit's residuals over its own samples first (r parameters
                    # fitted to them), then the previous pass's, divided by the consistency.
                    dof = np.float32(0.0) if t > 0 else np.float32(r)
                    for j in range(m):
                        scale[j] = math.sqrt(num[j] / max(den[j] - dof, np.float32(1.0)))
                        if t > 0:
                            scale[j] = np.float32(scale[j]) / consistency
                else:
                    _median_scale(res, cand, m, scale)
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
                            q = max(res[k, j] * hi[j], res[k, j] * lo[j])
                            q = max(np.float32(1.0) - q * q, np.float32(0.0))
                            w[k, j] = q * q if cand[k, j] else np.float32(0.0)
                else:
                    for k in range(n):
                        for j in range(m):
                            keep = (res[k, j] <= hi[j]) & (res[k, j] >= lo[j]) & cand[k, j]
                            w[k, j] = np.float32(1.0) if keep else np.float32(0.0)
                _sums(w, v, basis, m, sums)
                _solve(sums, c, r, SINGULAR, m, c2, ok2)
                for j in range(m):
                    if ok2[j]:
                        for a in range(3):
                            c[a, j] = c2[a, j]
                    ok[j] = ok[j] | ok2[j]
                _to_normal(c, m, back3, g32, unit, rho)
            # The weights' sums: the samples used, in both results.
            for j in range(m):
                total[j] = 0.0
            for k in range(n):
                for j in range(m):
                    total[j] += w[k, j]
            if normals is not None:
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
                for j in range(inside):
                    samples[row, c0 + j] = np.uint16(round(total[j]))
            if ptm is not None:
                _ptm_fit(ptm, v, w, m, inside, row, c0, p_sums, p_rhs, p_gram, p_low, p_sol, p_work, total, same)
