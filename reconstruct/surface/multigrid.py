"""Weighted graph Laplacians of a pixel grid and an aggregation multigrid for them.

The operator of a least-squares integration on a masked pixel grid is the weighted 5-point
graph Laplacian DᵀWD, one weight per pair of 4-neighbours (0 where the pair has no gradient
equation). :class:`_Grid` applies it as a stencil on 2-D arrays, :func:`masked_laplacian`
assembles it as a sparse matrix, and :class:`_Multigrid` is a V-cycle preconditioner for
conjugate gradients that coarsens by 2×2 reshapes.

Hand-written rather than taken from pyamg (not a dependency of the project): aggregating
2×2 blocks of the grid keeps every level a 5-point stencil on 2-D float32 arrays, applied
without assembling sparse matrices; only the coarsest level (at most 4096 pixels) is a sparse
LU. It has not been benchmarked against pyamg.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg

__all__ = ["masked_laplacian"]


def masked_laplacian(wx: np.ndarray, wy: np.ndarray) -> "scipy.sparse.csr_matrix":
    """Weighted 5-point graph Laplacian DᵀWD of a pixel grid as a scipy.sparse matrix.

    Parameters
    ----------
    wx : numpy.ndarray
        ``(H, W−1)`` weights of the equations z[i, j+1] − z[i, j] = …; 0 removes an equation.
    wy : numpy.ndarray
        ``(H−1, W)`` weights of the equations z[i+1, j] − z[i, j] = ….

    Returns
    -------
    scipy.sparse.csr_matrix
        ``(H·W, H·W)`` float64 matrix, pixels in row-major order. Pixels without an equation
        have an empty row.
    """
    h, w = wy.shape[0] + 1, wx.shape[1] + 1
    n = h * w
    # Off-diagonals in the flat order: the right neighbour is +1 (absent at a row's end, so
    # a zero is spliced in there), the lower neighbour is +W.
    right = np.zeros((h, w), dtype=np.float64)
    right[:, :-1] = wx
    right = right.ravel()[:-1]
    down = np.asarray(wy, dtype=np.float64).ravel()
    diag = np.zeros(n, dtype=np.float64)
    diag[:-1] += right
    diag[1:] += right
    diag[:-w] += down
    diag[w:] += down
    diagonals, offsets = [diag, -down, -down], [0, w, -w]
    if w > 1:  # a one-column grid has no horizontal pair (and w = 1 would repeat an offset)
        diagonals += [-right, -right]
        offsets += [1, -1]
    return scipy.sparse.diags(diagonals, offsets, shape=(n, n), format="csr")


class _Grid:
    """The weighted Laplacian of one grid level as a 5-point stencil on 2-D arrays."""

    def __init__(self, wx: np.ndarray, wy: np.ndarray, dtype: type) -> None:
        self.wx = wx.astype(dtype, copy=False)
        self.wy = wy.astype(dtype, copy=False)
        self.shape = (wy.shape[0] + 1, wx.shape[1] + 1)
        d = np.zeros(self.shape, dtype=dtype)
        d[:, :-1] += self.wx
        d[:, 1:] += self.wx
        d[:-1, :] += self.wy
        d[1:, :] += self.wy
        self.diag = d
        with np.errstate(divide="ignore"):
            inv = np.where(d > 0, 1.0 / d, 0.0).astype(dtype)
        self.inv_diag = inv  # 0 off the domain: Jacobi leaves those pixels at 0

    def matvec(self, z: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """A·z = Σ_edges w·(z_i − z_j) accumulated at both ends."""
        out = np.multiply(self.diag, z, out=out)
        t = self.wx * z[:, 1:]
        out[:, :-1] -= t
        np.multiply(self.wx, z[:, :-1], out=t)
        out[:, 1:] -= t
        del t
        t = self.wy * z[1:, :]
        out[:-1, :] -= t
        np.multiply(self.wy, z[:-1, :], out=t)
        out[1:, :] -= t
        return out

    def coarsen(self) -> "_Grid":
        """Galerkin coarse level PᵀAP for piecewise-constant P over 2×2 blocks.

        With P constant on each block, PᵀAP is again a 5-point graph Laplacian whose edge
        weights are the sums of the fine weights crossing between two blocks (the edges
        inside a block cancel), so no sparse triple product is needed.
        """
        h, w = self.shape
        hc, wc = (h + 1) // 2, (w + 1) // 2
        wx = np.zeros((2 * hc, 2 * wc - 1), dtype=self.wx.dtype)
        wx[:h, : w - 1] = self.wx
        wy = np.zeros((2 * hc - 1, 2 * wc), dtype=self.wy.dtype)
        wy[: h - 1, :w] = self.wy
        cwx = wx[:, 1::2].reshape(hc, 2, wc - 1).sum(axis=1)
        cwy = wy[1::2, :].reshape(hc - 1, wc, 2).sum(axis=2)
        return _Grid(cwx, cwy, self.wx.dtype.type)


def _restrict(r: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pᵀr: sums over 2×2 blocks (zero-padded to even size)."""
    h, w = r.shape
    hc, wc = shape
    if (2 * hc, 2 * wc) != (h, w):
        padded = np.zeros((2 * hc, 2 * wc), dtype=r.dtype)
        padded[:h, :w] = r
        r = padded
    return r.reshape(hc, 2, wc, 2).sum(axis=(1, 3))


def _prolong(e: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pe: each coarse value copied to its 2×2 block, cropped to the fine shape."""
    h, w = shape
    return np.repeat(np.repeat(e, 2, axis=0), 2, axis=1)[:h, :w]


class _Multigrid:
    """Aggregation V-cycle (2×2 blocks) used as a symmetric preconditioner for CG.

    Damped Jacobi smoothing, the same number of sweeps before and after the coarse
    correction, and a fixed over-correction factor keep the operator symmetric positive
    definite on the range of A, as CG requires. Piecewise-constant interpolation makes the
    Galerkin coarse operator too weak by about 2 for the Laplacian; the over-correction
    (Braess 1995; Notay's aggregation AMG) compensates for it. The coarsest level is
    solved with a sparse LU of A + εI and projected onto the zero-mean vectors of each
    connected component, so the preconditioner is symmetric and adds no constant.
    """

    def __init__(
        self,
        grid: _Grid,
        *,
        smooth: int = 1,
        omega: float = 0.8,
        over: float = 1.6,
        coarsest: int = 4096,
    ) -> None:
        self.levels = [grid]
        while self.levels[-1].diag.size > coarsest and min(self.levels[-1].shape) > 2:
            self.levels.append(self.levels[-1].coarsen())
        self.smooth, self.omega, self.over = smooth, omega, over
        last = self.levels[-1]
        a = masked_laplacian(last.wx, last.wy)
        d = a.diagonal()
        eps = 1e-8 * (d.max() if d.size and d.max() > 0 else 1.0)
        # Rows without equations get a unit diagonal; they solve to 0 since their rhs is 0.
        reg = scipy.sparse.diags(np.where(d > 0, eps, 1.0))
        self.lu = scipy.sparse.linalg.splu((a + reg).tocsc())
        _, labels = scipy.sparse.csgraph.connected_components(a, directed=False)
        self.labels = labels
        self.counts = np.bincount(labels).astype(np.float64)

    def _project(self, v: np.ndarray) -> np.ndarray:
        means = np.bincount(self.labels, weights=v) / self.counts
        return v - means[self.labels]

    def _cycle(self, level: int, b: np.ndarray) -> np.ndarray:
        g = self.levels[level]
        if level == len(self.levels) - 1:
            rhs = self._project(b.ravel().astype(np.float64))
            x = self._project(self.lu.solve(rhs))
            x[g.diag.ravel() == 0] = 0.0
            return x.reshape(g.shape).astype(b.dtype, copy=False)
        om = b.dtype.type(self.omega)
        x = b * g.inv_diag
        x *= om
        r = np.empty_like(b)
        for _ in range(self.smooth - 1):
            np.subtract(b, g.matvec(x, out=r), out=r)
            r *= g.inv_diag
            r *= om
            x += r
        np.subtract(b, g.matvec(x, out=r), out=r)
        coarse = self._cycle(level + 1, _restrict(r, self.levels[level + 1].shape))
        e = _prolong(coarse, g.shape)
        x += b.dtype.type(self.over) * e
        del e, coarse
        for _ in range(self.smooth):
            np.subtract(b, g.matvec(x, out=r), out=r)
            r *= g.inv_diag
            r *= om
            x += r
        return x

    def __call__(self, r: np.ndarray) -> np.ndarray:
        dtype = self.levels[0].wx.dtype
        return self._cycle(0, r.astype(dtype, copy=False)).astype(np.float64, copy=False)
