"""The PTM light system ``Λ·a = L``: its rank, why it is lost, and its {1}-inverses.

Λ is the N×6 light matrix of :func:`ptmcore.fit.light_matrix`, one row
``[lu², lv², lu·lv, lu, lv, 1]`` per photograph. It is the same for every pixel, so a solver
is one 6×N matrix X and the coefficients of all pixels are ``X @ L``.

Following Malešević, Obradović et al. ("Application of polynomial texture mapping in process
of digitalization of cultural heritage"), every X with ``Λ·X·Λ = Λ`` (a {1}-inverse) is
written in Rohde's form ::

    Λ^(1) = P · [[I_ρ, U], [V, W]] · Q,      Q·Λ·P = [[I_ρ, 0], [0, 0]],

with ρ the rank of Λ, P (6×6) and Q (N×N) regular and U (ρ×(N−ρ)), V ((6−ρ)×ρ),
W ((6−ρ)×(N−ρ)) arbitrary. When the system is consistent every member gives an exact
solution, and the solutions are ``X·L`` plus the null space of Λ. The Moore–Penrose
pseudoinverse Λ⁺ is the member that gives the least-squares solution of minimum norm, which
is what the pipeline uses.

Rank is decided with a tolerance derived from the precision of the light directions
(:data:`LP_PRECISION`, the sixth decimal that ``.lp`` files carry), because real layouts that
are singular in theory (a cupola with every lamp at one elevation) are only singular up to
that rounding once written to a file; see :func:`analyse_lights`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .fit import light_matrix

__all__ = [
    "LP_PRECISION",
    "RankInfo",
    "analyse_lights",
    "duplicate_groups",
    "rank_tolerance",
    "rohde_factors",
    "solve_matrix",
]

#: Uncertainty of one light-direction component: one unit of the sixth decimal, which is what
#: ``.lp`` files (RTIBuilder, :func:`ptmcore.lp.write_lp`) carry.
LP_PRECISION = 1e-6

Method = Literal["pinv", "lstsq", "rohde"]
Factorisation = Literal["svd", "qr"]

_TERMS = ("lu²", "lv²", "lu·lv", "lu", "lv", "1")


@dataclass
class RankInfo:
    """Rank of a light layout's matrix Λ and what it means for the fit.

    Attributes
    ----------
    rank : int
        Numerical rank ρ of Λ (0..6): singular values above `tolerance`.
    singular_values : ndarray, shape (min(N, 6),)
        Singular values of Λ, largest first.
    condition : float
        σ_max / σ_ρ, the condition number of the part of Λ that is kept (the singular values
        above `tolerance`); it bounds how much noise in the photographs is amplified in the
        fitted coefficients. ``inf`` only if no singular value is kept. The condition number of
        the full Λ is infinite whenever ``rank < 6``.
    tolerance : float
        Singular values at or below this are treated as zero.
    causes : list of str
        Why the rank is below 6, in plain words, ending with what that does to the fit; empty
        when the rank is 6.
    null_space : ndarray, shape (6, 6 − rank)
        Orthonormal basis of the coefficient combinations the lights cannot determine.
    """

    rank: int
    singular_values: np.ndarray
    condition: float
    tolerance: float
    causes: list[str]
    null_space: np.ndarray

    @property
    def deficient(self) -> bool:
        """Whether some combination of the six coefficients is undetermined."""
        return self.rank < 6


def _as_lights(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] not in (2, 3):
        raise ValueError(f"expected light directions of shape (N, 3) or (N, 2), got {d.shape}")
    if len(d) == 0:
        raise ValueError("no light directions given")
    if not np.all(np.isfinite(d)):
        raise ValueError("light directions are not all finite")
    return d


def rank_tolerance(sigma_max: float, count: int, precision: float = LP_PRECISION) -> float:
    """Singular values of Λ at or below which a light layout is treated as singular.

    Parameters
    ----------
    sigma_max : float
        Largest singular value of Λ.
    count : int
        Number of lights N.
    precision : float
        Unit of the last digit of each direction component (``1e-6`` for ``.lp`` files). Zero
        gives the floating-point tolerance alone.

    Returns
    -------
    float
        ``max(√(14·N)·precision, max(N, 6)·ε·σ_max)``.

    Notes
    -----
    Rounding each component to `precision` moves it by at most ``precision/2``; after
    renormalising, (lu, lv) has moved by at most ``√3·precision/2 < √2·precision``. A row of Λ
    depends on (lu, lv) through the Jacobian ``[[2lu, 0], [0, 2lv], [lv, lu], [1, 0], [0, 1],
    [0, 0]]``, whose norm is at most ``√(5(lu² + lv²) + 2) ≤ √7``, so a row moves by at most
    ``√14·precision`` and the whole matrix by ``‖ΔΛ‖₂ ≤ ‖ΔΛ‖_F ≤ √(14N)·precision``. By Weyl's
    inequality no singular value below that can be told apart from zero: the layout may be
    exactly singular and only look regular because of rounding. For 24 lamps at one elevation
    written with six decimals the smallest singular value is below 10⁻⁶ and the tolerance
    1.8·10⁻⁵, while real domes have σ_min of 10⁻² or more. A purely relative tolerance
    (e.g. ``1e-6·σ_max``) would also separate these cases but has no reason behind its
    constant; the floating-point term is numpy's default for exact data.
    """
    eps_term = max(count, 6) * np.finfo(np.float64).eps * sigma_max
    return float(max(math.sqrt(14.0 * count) * precision, eps_term))


def duplicate_groups(directions: np.ndarray, *, precision: float = LP_PRECISION) -> list[list[int]]:
    """Photographs whose lights give the same row of Λ.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Light directions (only lu = x and lv = y matter).
    precision : float
        Unit of the last digit of each component; lights closer than twice that in (lu, lv)
        count as the same.

    Returns
    -------
    list of list of int
        Groups of 0-based photograph indices, each sorted, in order of their first member;
        lights without a duplicate are not listed.
    """
    d = _as_lights(directions)[:, :2]
    # Two roundings of one direction differ by up to √3·precision in (lu, lv).
    radius = max(2.0 * precision, 1e-12)
    pairs = cKDTree(d).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return []
    n = len(d)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    groups = [np.flatnonzero(labels == lab).tolist() for lab in np.flatnonzero(sizes > 1)]
    return sorted(groups, key=lambda g: g[0])


def _decompose(lam: np.ndarray, precision: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, float]:
    u, s, vt = np.linalg.svd(lam, full_matrices=True)
    tol = rank_tolerance(float(s[0]), len(lam), precision)
    return u, s, vt, int(np.count_nonzero(s > tol)), tol


def _photographs(group: list[int]) -> str:
    names = [str(k + 1) for k in group]
    return ", ".join(names[:-1]) + " and " + names[-1]


def _is_null(lam: np.ndarray, vectors: np.ndarray, tol: float) -> bool:
    # A combination the lights cannot see: Λ·n is no larger than the rounding of Λ could make
    # it, i.e. n lies in the numerical null space that the rank decision uses.
    vectors = np.atleast_2d(vectors)
    return bool(np.all(np.linalg.norm(vectors @ lam.T, axis=1) <= tol * np.linalg.norm(vectors, axis=1)))


def _conic(vector: np.ndarray) -> str:
    v = vector / vector[np.argmax(np.abs(vector))]
    parts = []
    for c, term in zip(v, _TERMS):
        if abs(c) < 1e-3:
            continue
        mag = f"{abs(c):.3g}"
        body = mag if term == "1" else (term if mag == "1" else f"{mag}·{term}")
        parts.append(("− " if c < 0 else "+ ") + body)
    text = " ".join(parts)
    return (text[2:] if text.startswith("+ ") else "−" + text[2:]) + " = 0"


def _geometric_causes(
    d: np.ndarray, lam: np.ndarray, tol: float, distinct: np.ndarray
) -> tuple[list[str], list[np.ndarray]]:
    """Recognised layouts that make Λ singular, with the null vectors each implies."""
    n = len(d)
    lu, lv = d[:, 0], d[:, 1]
    if d.shape[1] == 3:
        z = d[:, 2] / np.linalg.norm(d, axis=1)
    else:
        z = np.sqrt(np.clip(1 - lu * lu - lv * lv, 0, 1))
    pts = d[distinct, :2]

    # (lu, lv) on one straight line a·lu + b·lv + c = 0: that line times lu, lv and 1 are three
    # null vectors. Through the origin it is a vertical plane through the camera axis.
    for through_origin in (True, False):
        centre = np.zeros(2) if through_origin else pts.mean(axis=0)
        a, b = np.linalg.svd(pts - centre, full_matrices=True)[2][-1]
        c = -(a * centre[0] + b * centre[1])
        cand = np.array([[a, 0, b, c, 0, 0], [0, b, a, 0, c, 0], [0, 0, 0, a, b, c]])
        if _is_null(lam, cand, tol):
            if through_origin:
                az = math.degrees(math.atan2(-a, b)) % 180.0
                text = (
                    f"all lights in one vertical plane (azimuths {az:.1f}° and {az + 180:.1f}°): "
                    "their (lu, lv) lie on a line through the centre, so only the light's position "
                    "along that line is seen and three combinations of coefficients are undetermined"
                )
            else:
                text = (
                    "all lights in one plane parallel to the camera axis: their (lu, lv) lie on the "
                    f"straight line {_conic(np.array([0, 0, 0, a, b, c]))}, so three combinations of "
                    "coefficients are undetermined"
                )
            return [text], list(cand)

    r2 = lu * lu + lv * lv
    ring = np.array([1.0, 1.0, 0.0, 0.0, 0.0, -float(r2.mean())])
    if _is_null(lam, ring, tol):
        elev = math.degrees(math.atan2(float(z.mean()), math.sqrt(float(r2.mean()))))
        text = (
            f"all {n} lights at elevation {elev:.1f}°: lu² + lv² is constant, so lu² and lv² "
            "cannot be separated from the constant term"
        )
        return [text], [ring]

    # Lights in one plane p·d = c lie on a circle of the sphere; squaring p3·z = c − p1·lu − p2·lv
    # with z² = 1 − lu² − lv² gives the ellipse their (lu, lv) lie on.
    if d.shape[1] == 3:
        unit = d[distinct] / np.linalg.norm(d[distinct], axis=1, keepdims=True)
        h = np.linalg.svd(np.column_stack([unit, -np.ones(len(unit))]), full_matrices=True)[2][-1]
        p, c = h[:3] / np.linalg.norm(h[:3]), h[3] / np.linalg.norm(h[:3])
        p1, p2, p3 = p
        ellipse = np.array(
            [-p3 * p3 - p1 * p1, -p3 * p3 - p2 * p2, -2 * p1 * p2, 2 * c * p1, 2 * c * p2, p3 * p3 - c * c]
        )
        if _is_null(lam, ellipse, tol):
            tilt = math.degrees(math.acos(min(1.0, abs(p3))))
            if abs(c) < 1e-3:
                where = "through the centre of the dome (a great circle)"
            else:
                where = f"tilted {tilt:.1f}° from the horizontal"
            text = (
                f"all lights in one plane {where}: their (lu, lv) lie on the ellipse "
                f"{_conic(ellipse)}, so one combination of coefficients is undetermined"
            )
            return [text], [ellipse]
    return [], []


def _causes(
    d: np.ndarray, lam: np.ndarray, vt: np.ndarray, rank: int, tol: float, precision: float
) -> list[str]:
    n = len(d)
    if rank >= 6:
        return []
    causes: list[str] = []
    if n < 6:
        causes.append(f"only {n} photograph{'s' if n != 1 else ''} for 6 coefficients")
    groups = duplicate_groups(d, precision=precision)
    for g in groups:
        causes.append(f"duplicate light directions (photographs {_photographs(g)})")
    first = np.ones(n, dtype=bool)
    for g in groups:
        first[g[1:]] = False
    n_distinct = int(first.sum())
    if groups and n_distinct < 6:
        causes.append(f"only {n_distinct} distinct light directions for 6 coefficients")

    # The count explains 6 − min(distinct, 6) lost dimensions (five points always lie on a
    # conic); only what is lost beyond that needs a geometric reason.
    beyond = min(n_distinct, 6) - rank
    if beyond > 0:
        texts, vectors = _geometric_causes(d, lam, tol, first)
        causes += texts
        explained = np.linalg.matrix_rank(np.array(vectors), tol=1e-9) if vectors else 0
        if explained < beyond:
            null = vt[rank:].T
            if vectors:
                e = scipy.linalg.orth(np.array(vectors).T)
                null = null - e @ (e.T @ null)
            basis, strength, _ = np.linalg.svd(null, full_matrices=False)
            # Directions the recognised causes already cover have collapsed to ~0 here.
            left = basis[:, strength > 1e-6][:, : beyond - explained]
            for v in left.T:
                causes.append(
                    f"the lights lie on the curve {_conic(v)} in (lu, lv), so that combination "
                    "of coefficients is undetermined"
                )
    k = 6 - rank
    causes.append(
        "the fit returns the minimum-norm solution: relighting at these light directions matches "
        "the least-squares fit, but other light directions are extrapolated, with the "
        f"{'one combination' if k == 1 else f'{k} combinations'} of coefficients the lights cannot see "
        "set to zero"
    )
    return causes


def analyse_lights(directions: np.ndarray, *, precision: float = LP_PRECISION) -> RankInfo:
    """Rank of a light layout's PTM matrix Λ, and why it falls short of 6.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Unit vectors towards the lights (x right, y up, z towards the camera).
    precision : float
        Unit of the last digit of each component; ``1e-6`` for ``.lp`` files, larger for a
        hand-measured dome, 0 to decide the rank at floating-point precision. See
        :func:`rank_tolerance`.

    Returns
    -------
    RankInfo

    Notes
    -----
    The causes are found by testing the null space: duplicates and too few lights are
    counted; a line in (lu, lv) (lights in a plane parallel to the camera axis), the ring
    ``lu² + lv² = r²`` (one elevation, null vector ∝ (1, 1, 0, 0, 0, −r²)) and an ellipse
    (lights in one tilted plane) are each tested as null vectors ``n`` with ``‖Λn‖ ≤ tol·‖n‖``.
    Whatever the null space holds beyond those is reported as the conic the lights lie on.
    Photographs are numbered from 1, as the lines of an ``.lp`` file.
    """
    d = _as_lights(directions)
    lam = light_matrix(d)
    _, s, vt, rank, tol = _decompose(lam, precision)
    condition = float(s[0] / s[rank - 1]) if rank else math.inf
    return RankInfo(
        rank=rank,
        singular_values=s,
        condition=condition,
        tolerance=tol,
        causes=_causes(d, lam, vt, rank, tol, precision),
        null_space=vt[rank:].T.copy(),
    )


def rohde_factors(
    directions: np.ndarray, *, factorisation: Factorisation = "svd", precision: float = LP_PRECISION
) -> tuple[np.ndarray, np.ndarray, int]:
    """Regular P (6×6) and Q (N×N) with ``Q·Λ·P = [[I_ρ, 0], [0, 0]]``.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Light directions.
    factorisation : {"svd", "qr"}
        ``"svd"``: from ``Λ = U_s·Σ·V_sᵀ``, ``P = V_s`` and ``Q = [Σ_ρ⁻¹·U_ρᵀ; U_⊥ᵀ]``.
        ``"qr"``: from the column-pivoted QR ``Λ·Π = Q_r·[[R11, R12], [0, R22]]``,
        ``Q = Q_rᵀ`` and ``P = Π·[[R11⁻¹, −R11⁻¹·R12], [0, I]]``.
    precision : float
        Precision of the directions, which sets the rank (see :func:`rank_tolerance`).

    Returns
    -------
    P : ndarray, shape (6, 6)
    Q : ndarray, shape (N, N)
    rank : int
        ρ, decided from the singular values for both factorisations.

    Notes
    -----
    The trailing block of ``Q·Λ·P`` is zero up to the discarded singular values (SVD) or R22
    (QR), both at most about the rank tolerance.
    """
    d = _as_lights(directions)
    lam = light_matrix(d)
    u, s, vt, rank, _ = _decompose(lam, precision)
    if factorisation == "svd":
        q = np.vstack([u[:, :rank].T / s[:rank, None], u[:, rank:].T])
        return vt.T.copy(), q, rank
    if factorisation == "qr":
        qr, r, piv = scipy.linalg.qr(lam, pivoting=True)
        r11_inv = scipy.linalg.solve_triangular(r[:rank, :rank], np.eye(rank))
        block = np.eye(6)
        block[:rank, :rank] = r11_inv
        block[:rank, rank:] = -r11_inv @ r[:rank, rank:]
        p = np.eye(6)[:, piv] @ block
        return p, qr.T.copy(), rank
    raise ValueError(f"factorisation must be 'svd' or 'qr', not {factorisation!r}")


def _block(name: str, value: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    if value is None:
        return np.zeros(shape)
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape} for this layout (rank and count), got {arr.shape}")
    return arr


def solve_matrix(
    directions: np.ndarray,
    method: Method = "pinv",
    *,
    U: np.ndarray | None = None,
    V: np.ndarray | None = None,
    W: np.ndarray | None = None,
    factorisation: Factorisation = "svd",
    precision: float = LP_PRECISION,
) -> np.ndarray:
    """A 6×N {1}-inverse X of the light matrix: the coefficients of every pixel are ``X @ L``.

    Parameters
    ----------
    directions : ndarray, shape (N, 3) or (N, 2)
        Light directions, one per photograph.
    method : {"pinv", "lstsq", "rohde"}
        ``"pinv"`` (default): the Moore–Penrose pseudoinverse Λ⁺ from the SVD, with singular
        values at or below the rank tolerance dropped, so the least-squares solution of minimum
        norm. ``"lstsq"``: :func:`scipy.linalg.lstsq` (LAPACK ``gelsd``) applied to the N×N
        identity with the same cut-off; the same matrix computed independently, as a check.
        ``"rohde"``: ``P·[[I_ρ, U], [V, W]]·Q`` with P and Q from :func:`rohde_factors`.
    U, V, W : ndarray, optional
        Rohde's free blocks, of shapes ρ×(N−ρ), (6−ρ)×ρ and (6−ρ)×(N−ρ); zero when omitted.
        Only for ``method="rohde"``.
    factorisation : {"svd", "qr"}
        Where P and Q come from (``"rohde"`` only).
    precision : float
        Precision of the directions, which sets the rank (see :func:`rank_tolerance`).

    Returns
    -------
    ndarray, shape (6, N), float64
        X with ``Λ·X·Λ = Λ`` (up to the dropped singular values).

    Raises
    ------
    ValueError
        For an unknown method or factorisation, free blocks given to another method, or free
        blocks of the wrong shape.

    Notes
    -----
    With U = V = W = 0 the SVD-based Rohde form is exactly Λ⁺: ``P·[[I, 0], [0, 0]]·Q =
    V_ρ·Σ_ρ⁻¹·U_ρᵀ``. The QR-based one is a reflexive inverse (``X·Λ·X = X``) whose ``Λ·X`` is
    the orthogonal projection onto the range of Λ, so it still gives a least-squares solution,
    the "basic" one with zeros in the coefficients not chosen as pivots; it is not of minimum
    norm because P is not orthogonal. Non-zero V or W add null-space vectors to the solution;
    non-zero U or W make the residual depend on the part of L outside the range of Λ, so the
    solution is no longer least squares for inconsistent data.
    """
    d = _as_lights(directions)
    n = len(d)
    if method != "rohde" and (U is not None or V is not None or W is not None):
        raise ValueError("U, V and W are only used by method='rohde'")
    if method == "pinv":
        lam = light_matrix(d)
        u, s, vt, rank, _ = _decompose(lam, precision)
        return (vt[:rank].T / s[:rank]) @ u[:, :rank].T
    if method == "lstsq":
        lam = light_matrix(d)
        s = np.linalg.svd(lam, compute_uv=False)
        tol = rank_tolerance(float(s[0]), n, precision)
        # gelsd drops singular values below cond·σ_max; nudging the cut-off keeps a singular
        # value exactly at the tolerance dropped, as in "pinv".
        cond = np.nextafter(tol / s[0], np.inf)
        x, _, _, _ = scipy.linalg.lstsq(lam, np.eye(n), cond=cond, lapack_driver="gelsd")
        return x
    if method == "rohde":
        p, q, rank = rohde_factors(d, factorisation=factorisation, precision=precision)
        middle = np.block(
            [
                [np.eye(rank), _block("U", U, (rank, n - rank))],
                [_block("V", V, (6 - rank, rank)), _block("W", W, (6 - rank, n - rank))],
            ]
        )
        return p @ middle @ q
    raise ValueError(f"method must be 'pinv', 'lstsq' or 'rohde', not {method!r}")
