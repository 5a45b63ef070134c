"""Per-pixel weighted least squares, vectorised over the pixels of a band.

The robust fits (:mod:`ptmcore.robust`, :mod:`ptmcore.robustptm`) give every pixel its own
weights, so every pixel has its own least-squares problem. Each is solved through its normal
equations. The sums ``Σ w φ φᵀ`` (unique entries of the basis functions' outer products) come
from one matrix product for all pixels of a band, and ``Σ w φ L`` from another. A Cholesky
factorisation in float64 then solves them, vectorised over the pixels. The basis is first
orthonormalised over the photographs (SVD of the light matrix). That keeps the float32 sums well
conditioned, and it makes rank-deficient light sets (all lights on one ring) solvable, with the
minimum-norm coefficients that :func:`ptmcore.fit.fit_ptm` also gives. A small ridge towards
the previous estimate keeps a pixel that has too few usable samples where it was.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "SINGULAR",
    "Basis",
    "blocked_matmul",
    "cholesky_solve",
    "orthonormal_basis",
    "packed_index",
    "weighted_fit",
]

#: Pixels per chunk of the batched Cholesky solves: their work arrays then stay in the cache.
_CHUNK = 8192
#: Ridge of the per-pixel solves, relative to the mean eigenvalue of the normal matrix.
_RIDGE = 1e-6
#: A normal matrix is singular when its determinant is below this × (mean eigenvalue)^rank.
SINGULAR = 1e-6
#: Multiply-adds of a matrix product that OpenBLAS does in one thread.
_BLAS_ONE_THREAD = 1 << 18


@dataclass(frozen=True)
class Basis:
    """A model's basis functions at the N lights, orthonormalised.

    Attributes
    ----------
    u : ndarray, shape (N, r), float32
        Orthonormal columns that span the basis functions.
    back : ndarray, shape (m, r), float64
        Maps a solution in ``u`` to the model's own m coefficients.
    outer : ndarray, shape (N, K), float32
        Products of the pairs of columns of ``[u, extra]`` (upper triangle, row by row), so
        ``outer.T @ weights`` gives every pixel's weighted sums at once.
    gram_rows : ndarray, shape (r(r + 1)/2,)
        Rows of those sums that make the normal matrix, packed as :func:`packed_index` expects.
    extra_rows : list of ndarray, shape (r,)
        For each extra column z, the rows that hold ``Σ w u z``.
    """

    u: np.ndarray
    back: np.ndarray
    outer: np.ndarray
    gram_rows: np.ndarray
    extra_rows: list[np.ndarray]

    @property
    def rank(self) -> int:
        return self.u.shape[1]


def packed_index(k: int) -> np.ndarray:
    """Index of entry (i, j) of a symmetric k×k matrix stored as its upper triangle."""
    index = np.zeros((k, k), dtype=np.intp)
    i, j = np.triu_indices(k)
    index[i, j] = index[j, i] = np.arange(len(i))
    return index


def orthonormal_basis(phi: np.ndarray, extra: np.ndarray | None = None) -> Basis:
    """Orthonormalise the N×m basis ``phi``. The columns of ``extra`` (N×e) are fitted too,
    with the same weights, at no extra factorisation."""
    # Imported here: solvers imports SciPy, which `import ptmcore` (the command line's start)
    # does not need.
    from .solvers import rank_tolerance

    u, s, vt = np.linalg.svd(phi, full_matrices=False)
    # The rank as ptmcore.solvers decides it: a ring of lights read from an .lp file is only
    # singular up to the file's rounding.
    rank = int(np.count_nonzero(s > rank_tolerance(float(s[0]), len(phi))))
    u, s, vt = u[:, :rank], s[:rank], vt[:rank]
    cols = u if extra is None else np.column_stack([u, extra])
    k = cols.shape[1]
    i, j = np.triu_indices(k)
    index = packed_index(k)
    gram_rows = np.array([index[a, b] for a in range(rank) for b in range(a, rank)])
    extra_rows = [index[:rank, z] for z in range(rank, k)]
    outer = (cols[:, i] * cols[:, j]).astype(np.float32)
    return Basis(u.astype(np.float32), vt.T / s, outer, gram_rows, extra_rows)


def blocked_matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a small ``a`` (k, N) and a band ``b`` (N, P).

    These products have only a few rows. Given a whole band, BLAS splits each one over its own
    threads on top of the band threads, and on two cores that made the fits 1.5 to 10 times
    slower, depending on the load. Blocks of columns small enough for BLAS to keep to
    one thread run as fast as the best case, and at a steady speed.
    """
    k, n = a.shape
    p = b.shape[1]
    step = max(64, _BLAS_ONE_THREAD // max(1, k * n))
    if p <= step:
        return a @ b
    out = np.empty((k, p), dtype=np.result_type(a, b))
    for p0 in range(0, p, step):
        np.matmul(a, b[:, p0 : p0 + step], out=out[:, p0 : p0 + step])
    return out


def cholesky_solve(
    gram: np.ndarray, rhs: list[np.ndarray], prior: list[np.ndarray] | None,
    singular: float = SINGULAR,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Solve ``(G + λI) x = b + λ x_prior`` for every pixel.

    Parameters
    ----------
    gram : ndarray, shape (r(r + 1)/2, P), float64
        Each pixel's r×r normal matrix G as its upper triangle (see :func:`packed_index`).
    rhs : list of ndarray, shape (r, P), float64
        Right-hand sides b.
    prior : list of ndarray, shape (r, P), or None
        Where a pixel's G is (nearly) singular, its solution tends to these (or to 0).
    singular : float
        G is well posed where det G > singular × (mean eigenvalue)^r.

    Returns
    -------
    solutions : list of ndarray, shape (r, P)
    well_posed : ndarray, shape (P,), bool
        Where G alone is far from singular.

    The factorisation works on the r(r + 1)/2 entries, each a vector over the pixels. That is
    about r³/6 vector operations. The alternatives, P LAPACK calls or a batched call on a
    (P, r, r) copy, were 3 to 7 times slower here.
    """
    r = rhs[0].shape[0]
    index = packed_index(r)
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
        x = list(y)
        for i in reversed(range(r)):
            s = y[i]
            for k in range(i + 1, r):
                s = s - low[k][i] * x[k]
            x[i] = s / low[i][i]
        solutions.append(np.stack(x))
    well_posed = log_det > r * np.log(np.maximum(mean_eig, 1e-30)) + np.log(singular)
    return solutions, well_posed


def weighted_fit(
    basis: Basis, v: np.ndarray, weights: np.ndarray, prior: list[np.ndarray] | None,
    singular: float = SINGULAR,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Per-pixel weighted least squares of ``v`` (N, P) and of the basis's extra columns.

    Returns the solutions in the orthonormal basis, [data, extra columns...], each (r, P)
    float64, and where the system was well posed.
    """
    sums = blocked_matmul(basis.outer.T, weights).astype(np.float64)  # (K, P)
    rhs = [blocked_matmul(basis.u.T, weights * v).astype(np.float64)] + [sums[rows] for rows in basis.extra_rows]
    gram = sums[basis.gram_rows]
    p = v.shape[1]
    if p <= _CHUNK:
        return cholesky_solve(gram, rhs, prior, singular)
    solutions = [np.empty_like(b) for b in rhs]
    well_posed = np.empty(p, dtype=bool)
    for p0 in range(0, p, _CHUNK):
        part = slice(p0, p0 + _CHUNK)
        sol, ok = cholesky_solve(gram[:, part], [b[:, part] for b in rhs],
                                 None if prior is None else [x[:, part] for x in prior], singular)
        for out, x in zip(solutions, sol):
            out[:, part] = x
        well_posed[part] = ok
    return solutions, well_posed
