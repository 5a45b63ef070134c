"""Interpolating relighting bases (relight's ``rbf`` and ``bilinear``) and their PCA.

Relight's ``rbf`` and ``bilinear`` bases (relight's own web format, shown by OpenLIME) do not fit
a function of the light per pixel, as PTM and HSH do. They keep the photographs themselves,
compressed: each pixel's RGB values under the D basis directions form a 3·D vector, all pixels
share a principal-component basis of those vectors (:func:`pca`), and each pixel stores only its
first few coordinates in it. Relighting under a new light interpolates the basis between the D
directions with weights that depend only on the light:

* ``rbf``: the D directions are the capture's N lights, weighed by normalised Gaussians of their
  distance to the new light (:func:`rbf_weights`);
* ``bilinear``: the D directions are the R×R nodes of a grid over the hemisphere
  (:func:`grid_directions`), weighed bilinearly (:func:`bilinear_weights`). The photographs'
  values are first resampled onto the nodes (:func:`resample_matrix`).

Both are linear in the photographs, so leaving light i out and predicting its photograph from the
others is one N×N matrix applied to the stack (:func:`rbf_loo_matrix`,
:func:`bilinear_loo_matrix`): the leave-one-out error that :mod:`ptmcore.loo` computes for PTM and
HSH, for these bases (without the PCA truncation, which is per capture, not per light).

Frame: x right, y up, z towards the camera; light directions are unit (N, 3) vectors.

Definitions, read (not copied) from:

* OpenLIME (cnr-isti-vclab/openlime) ``src/ShaderRTI.js``, classes ``RBF`` (``rbf``: weights
  ``exp(−|l_i − q|²/σ²)``, normalised, those ≤ 0.001 dropped, the rest renormalised) and ``BLN``
  (``lightWeights``: the octahedral map rotated by 45°, node ``x + y·R``); the same in relight's
  ``src/rti.cpp`` (``Rti::lightWeightsRbf``, ``Rti::lightWeightsBilinear``).
* relight's builder, ``relight-cli/rtibuilder.cpp`` (later ``src/cli/rtibuilder.cpp``):
  ``fromOcta`` (the grid's node directions), ``RtiBuilder::buildResampleMap`` (the resampling
  below), ``RtiBuilder::pickBasePCA`` and ``src/eigenpca.h`` (the PCA); defaults in ``src/rti.h``
  (``sigma = 0.125`` "for ~100 images", ``regularization = 0.1``, ``resolution = 8``,
  ``nplanes = 9``) and ``relight-cli/main.cpp`` (``-S``, ``-R``, ``-r`` 0 or 3…20, ``-p``);
  RelightLab's ``relightlab/rtitask.cpp`` (``RtiTask::setProject``: ``sigma = 0.125·100/N``).

Relight's resampling onto the grid (``buildResampleMap``) solves, for the node values x given the
photographs' values b, ``min |A x − b|² + k |x − B b|²``: A (N × R²) holds each light's bilinear
weights on the grid (the viewer's interpolation, so the fit reproduces the photographs when
relit), B (R² × N) the RBF weights of the lights at each node (relative threshold 0.005 instead of
the viewer's 0.001), a prior that fills nodes no light reaches; k is ``regularization``. Its
closed form is ``x = (AᵀA + kI)⁻¹ (Aᵀ + k B) b`` (relight writes the same as
``B + (AᵀA + kI)⁻¹ Aᵀ (I − A B)``); relight then drops the entries of that R² × N matrix of
magnitude ≤ 0.005 without renormalising, and so does :func:`resample_matrix` by default.

Relight's PCA (``pickBasePCA``, MRGB colour space): one record per sampled pixel, the RGB values
under each of the D directions interleaved (``r0 g0 b0 r1 g1 b1 …``, 0–255), the mean over the
samples subtracted, the eigenvectors of the covariance (``SelfAdjointEigenSolver`` of
``XᵀX/(P − 1)``) of the ``nplanes`` largest eigenvalues kept (9 by default), each normalised to
unit length; the mean is stored clamped to 0–255. :func:`pca` does the same on float64 rows.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "RBF_THRESHOLD",
    "RELIGHT_SIGMA",
    "RESAMPLE_CUTOFF",
    "RESAMPLE_THRESHOLD",
    "DEFAULT_PLANES",
    "DEFAULT_REGULARIZATION",
    "DEFAULT_RESOLUTION",
    "bilinear_loo_matrix",
    "bilinear_weights",
    "default_sigma",
    "grid_directions",
    "pca",
    "rbf_loo_matrix",
    "rbf_weights",
    "resample_matrix",
]

#: OpenLIME and relight drop normalised RBF weights at or below this, then renormalise.
RBF_THRESHOLD = 0.001
#: relight's builder drops normalised RBF weights of the lights at a grid node at or below this.
RESAMPLE_THRESHOLD = 0.005
#: relight's builder drops entries of the resampling matrix of magnitude at or below this.
RESAMPLE_CUTOFF = 0.005
#: relight's fixed default sigma (``src/rti.h``, relight-cli ``-S``), "for ~100 images".
RELIGHT_SIGMA = 0.125
#: relight's default weight of the RBF prior in the bilinear resampling (relight-cli ``-R``).
DEFAULT_REGULARIZATION = 0.1
#: relight's default side of the bilinear grid (relight-cli ``-r``).
DEFAULT_RESOLUTION = 8
#: relight's default number of PCA planes (relight-cli ``-p``).
DEFAULT_PLANES = 9


# ---------------------------------------------------------------------------------------------
# Checks


def _vectors(a: np.ndarray, name: str) -> np.ndarray:
    """``a`` as a finite float64 (N, 3) array of non-zero vectors, N ≥ 1."""
    v = np.asarray(a, dtype=np.float64)
    if v.ndim == 1 and v.shape == (3,):
        v = v[None]
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 1:
        raise ValueError(f"{name} must have shape (N, 3) with N ≥ 1, got {np.shape(a)}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} contain NaN or infinite values")
    if np.any(np.abs(v).sum(axis=1) == 0):
        raise ValueError(f"{name} contain a zero vector, which has no direction")
    return v


def _sigma(sigma: float) -> float:
    s = float(sigma)
    if not np.isfinite(s) or s <= 0:
        raise ValueError(f"sigma must be a positive finite number, got {sigma!r}")
    return s


def _resolution(resolution: int) -> int:
    if isinstance(resolution, bool) or int(resolution) != resolution:
        raise ValueError(f"resolution must be an integer, got {resolution!r}")
    r = int(resolution)
    if r < 2:
        raise ValueError(f"resolution must be at least 2 (a grid needs two nodes a side), got {r}")
    return r


def _nonnegative(value: float, name: str) -> float:
    v = float(value)
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"{name} must be a finite number ≥ 0, got {value!r}")
    return v


# ---------------------------------------------------------------------------------------------
# RBF


def _normalise_rows(log_w: np.ndarray, threshold: float) -> np.ndarray:
    """Normalised Gaussian weights from their logarithms (−∞ for an excluded light), along the
    last axis, with weights ≤ ``threshold`` dropped and the rest renormalised."""
    # Shifting by the row's largest log-weight changes nothing after normalisation but keeps
    # exp from underflowing: a query 1 away from every light gives exp(−64) with σ = 0.125, 0 in
    # relight's float32, and exp(−1600) with σ = 0.025, 0 even in OpenLIME's float64 (0/0
    # there); here the nearest light always weighs exp(0) = 1.
    w = np.exp(log_w - log_w.max(axis=-1, keepdims=True))
    w /= w.sum(axis=-1, keepdims=True)
    keep = w > threshold
    # A row with nothing above the threshold (more than 1/threshold lights and a huge σ) would
    # be 0/0 in OpenLIME; keep its weights as they are, the limit of a flat kernel.
    keep |= ~keep.any(axis=-1, keepdims=True)
    w = np.where(keep, w, 0.0)
    w /= w.sum(axis=-1, keepdims=True)
    return w


def _squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a_i − b_j|² (M × N), from differences (not |a|² + |b|² − 2ab, which cancels)."""
    d = a[:, None, :] - b[None, :, :]
    return np.einsum("mnk,mnk->mn", d, d)


def rbf_weights(lights: np.ndarray, query: np.ndarray, sigma: float, *,
                threshold: float = RBF_THRESHOLD) -> np.ndarray:
    """OpenLIME's RBF weights of the lights at query directions.

    ``w_i = exp(−|l_i − q|² / σ²)``, normalised to sum 1; weights ≤ ``threshold`` are then
    dropped and the rest renormalised (ShaderRTI's ``RBF.rbf``, relight's
    ``Rti::lightWeightsRbf``).

    Parameters
    ----------
    lights : ndarray, shape (N, 3)
        The basis directions (the capture's unit light vectors), used as given.
    query : ndarray, shape (M, 3) or (3,)
        Directions to weigh the lights at; unit vectors, as the viewers make them.
    sigma : float
        The Gaussians' width, in units of the distance between unit vectors (> 0).
    threshold : float
        Normalised weights at or below this are dropped (OpenLIME: 0.001; relight's resampling:
        :data:`RESAMPLE_THRESHOLD`).

    Returns
    -------
    ndarray, shape (M, N), float64
        Non-negative rows summing to 1.

    Raises
    ------
    ValueError
        If an array has the wrong shape or non-finite values, or ``sigma`` ≤ 0.

    Notes
    -----
    Computed with the largest weight of each row scaled to 1 before normalising, which gives
    OpenLIME's result wherever its sum of weights does not underflow, and the nearest lights'
    weights where it does (OpenLIME divides 0 by 0 there). A row with no weight above
    ``threshold`` (possible only with more than 1/threshold lights) keeps all its weights.
    """
    lights = _vectors(lights, "lights")
    query = _vectors(query, "query directions")
    sigma = _sigma(sigma)
    threshold = _nonnegative(threshold, "threshold")
    return _normalise_rows(-_squared_distances(query, lights) / (sigma * sigma), threshold)


def default_sigma(lights: np.ndarray) -> float:
    """Relight's default RBF width for a capture: ``0.125 · 100 / N``.

    RelightLab (``RtiTask::setProject`` in ``relightlab/rtitask.cpp``) scales the builder's
    width with the number of photographs N, from relight's default of 0.125 "for ~100 images"
    (``src/rti.h``), which relight-cli uses for every capture unless given ``-S``
    (:data:`RELIGHT_SIGMA`). Relight does not look at the lights' spacing, only their number.

    Parameters
    ----------
    lights : ndarray, shape (N, 3)
        The capture's light directions.

    Returns
    -------
    float
    """
    return RELIGHT_SIGMA * 100.0 / len(_vectors(lights, "lights"))


def rbf_loo_matrix(lights: np.ndarray, sigma: float, *,
                   threshold: float = RBF_THRESHOLD) -> np.ndarray:
    """Leave-one-out predictor of the RBF basis: light i's sample from the other lights.

    Row i holds :func:`rbf_weights` of light i over the lights without i, with 0 at i, so
    ``M @ samples`` predicts every photograph from all the others.

    Parameters
    ----------
    lights : ndarray, shape (N, 3)
        The capture's unit light directions, N ≥ 2.
    sigma : float
        The Gaussians' width (e.g. :func:`default_sigma` of the whole capture).
    threshold : float
        As for :func:`rbf_weights`.

    Returns
    -------
    ndarray, shape (N, N), float64
        Zero diagonal, non-negative rows summing to 1.
    """
    lights = _vectors(lights, "lights")
    if len(lights) < 2:
        raise ValueError("leaving a light out needs at least 2 lights")
    sigma = _sigma(sigma)
    threshold = _nonnegative(threshold, "threshold")
    log_w = -_squared_distances(lights, lights) / (sigma * sigma)
    np.fill_diagonal(log_w, -np.inf)  # light i is not among its own predictors
    return _normalise_rows(log_w, threshold)


# ---------------------------------------------------------------------------------------------
# Bilinear grid


def _grid_coordinates(directions: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous grid coordinates (x, y) in [0, R − 1] of directions (the rotated octahedral
    map of OpenLIME's ``BLN.lightWeights``)."""
    lx, ly, lz = directions.T
    s = np.abs(lx) + np.abs(ly) + np.abs(lz)
    # The octahedral map sends the upper hemisphere onto the diamond |u| + |v| ≤ 1; rotating it
    # by 45° (and scaling by √2) makes the diamond the square [−1, 1]².
    x = (lx + ly) / s
    y = (ly - lx) / s
    return (x + 1) / 2 * (resolution - 1), (y + 1) / 2 * (resolution - 1)


def bilinear_weights(query: np.ndarray, resolution: int) -> np.ndarray:
    """OpenLIME's bilinear weights of the grid nodes at query directions.

    A direction (x, y, z) goes to ``u = (x + y)/s``, ``v = (y − x)/s`` with
    ``s = |x| + |y| + |z|`` (the octahedral map rotated by 45°), then to grid coordinates
    ``X = (u + 1)/2 · (R − 1)``, ``Y = (v + 1)/2 · (R − 1)``; the cell's corner is
    ``(sx, sy) = clip(floor(X, Y), 0, R − 2)`` and the four nodes around it get the bilinear
    weights of ``(X − sx, Y − sy)``. Node (x, y) is column ``x + y·R``.

    Parameters
    ----------
    query : ndarray, shape (M, 3) or (3,)
        Directions; their length does not matter. Lower-hemisphere directions map as their
        mirror image in the horizon (only |z| enters).
    resolution : int
        The grid's side R ≥ 2.

    Returns
    -------
    ndarray, shape (M, R²), float64
        Non-negative rows summing to 1, at most four non-zero entries each.
    """
    query = _vectors(query, "query directions")
    r = _resolution(resolution)
    x, y = _grid_coordinates(query, r)
    sx = np.clip(np.floor(x), 0, r - 2).astype(np.intp)
    sy = np.clip(np.floor(y), 0, r - 2).astype(np.intp)
    dx, dy = x - sx, y - sy
    rows = np.arange(len(query))
    w = np.zeros((len(query), r * r))
    base = sx + sy * r
    # np.add.at: at R = 2 … the four corners are distinct, but add rather than assign anyway.
    np.add.at(w, (rows, base), (1 - dx) * (1 - dy))
    np.add.at(w, (rows, base + 1), dx * (1 - dy))
    np.add.at(w, (rows, base + r), (1 - dx) * dy)
    np.add.at(w, (rows, base + r + 1), dx * dy)
    return w


def grid_directions(resolution: int) -> np.ndarray:
    """The unit directions of the bilinear grid's nodes (relight's ``fromOcta``).

    Node (x, y), row ``x + y·R``: ``u = 2x/(R − 1) − 1``, ``v = 2y/(R − 1) − 1``, rotated back by
    45° to ``X = (u − v)/2``, ``Y = (u + v)/2``, on the octahedron ``z = 1 − |X| − |Y|``,
    normalised. Since ``|X| + |Y| = max(|u|, |v|) ≤ 1``, no node falls below the horizon: the
    nodes on the grid's border are on it (z = 0), all others above. (Relight sets a negative z to
    0, which only catches rounding; so does this function.) The corners are ±x and ±y.

    Parameters
    ----------
    resolution : int
        The grid's side R ≥ 2.

    Returns
    -------
    ndarray, shape (R², 3), float64
    """
    r = _resolution(resolution)
    t = 2.0 * np.arange(r) / (r - 1) - 1.0
    u = np.tile(t, r)  # node x + y·R: x varies fastest
    v = np.repeat(t, r)
    gx, gy = (u - v) / 2, (u + v) / 2
    gz = np.maximum(1.0 - np.abs(gx) - np.abs(gy), 0.0)
    n = np.column_stack([gx, gy, gz])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _regularization(value: float) -> float:
    k = float(value)
    if not np.isfinite(k) or k <= 0:
        # k = 0 leaves nodes that no light's cell touches undetermined (AᵀA is singular).
        raise ValueError(f"regularization must be a positive finite number, got {value!r}")
    return k


def resample_matrix(lights: np.ndarray, resolution: int, sigma: float | None = None, *,
                    regularization: float = DEFAULT_REGULARIZATION,
                    threshold: float = RESAMPLE_THRESHOLD,
                    cutoff: float = RESAMPLE_CUTOFF) -> np.ndarray:
    """Relight's resampling of the photographs onto the bilinear grid (its "resample map").

    The node values are ``x = M b`` for the photographs' values b, with
    ``M = (AᵀA + kI)⁻¹ (Aᵀ + k B)``, the minimiser of ``|A x − b|² + k |x − B b|²``: A (N × R²)
    is :func:`bilinear_weights` of the lights (so relighting the grid at a light reproduces its
    photograph as well as the grid can), B (R² × N) is :func:`rbf_weights` of the lights at the
    nodes (:func:`grid_directions`, threshold 0.005), a smooth prior that decides the nodes no
    light is near, and k = ``regularization``. Entries of M of magnitude ≤ ``cutoff`` are then
    dropped, as relight does (without renormalising, so rows sum to 1 only up to the dropped
    entries; ``cutoff=0`` keeps them all and the rows sum to 1 exactly).

    Parameters
    ----------
    lights : ndarray, shape (N, 3)
        The capture's unit light directions.
    resolution : int
        The grid's side R ≥ 2 (relight: 8 by default, 3…20 allowed).
    sigma : float, optional
        Width of the RBF prior (default: :func:`default_sigma` of ``lights``).
    regularization : float
        Weight k > 0 of the prior (relight: 0.1).
    threshold : float
        Relative RBF weights at or below this are dropped from B (relight: 0.005).
    cutoff : float
        Entries of M at or below this magnitude are dropped (relight: 0.005; 0 keeps all).

    Returns
    -------
    ndarray, shape (R², N), float64
        Row ``x + y·R`` gives node (x, y)'s value as a combination of the photographs.
    """
    lights = _vectors(lights, "lights")
    r = _resolution(resolution)
    sigma = default_sigma(lights) if sigma is None else _sigma(sigma)
    k = _regularization(regularization)
    threshold = _nonnegative(threshold, "threshold")
    cutoff = _nonnegative(cutoff, "cutoff")
    a = bilinear_weights(lights, r)
    b = rbf_weights(lights, grid_directions(r), sigma, threshold=threshold)
    m = np.linalg.solve(a.T @ a + k * np.eye(r * r), a.T + k * b)
    return np.where(np.abs(m) > cutoff, m, 0.0) if cutoff > 0 else m


def bilinear_loo_matrix(lights: np.ndarray, resolution: int, sigma: float | None = None, *,
                        regularization: float = DEFAULT_REGULARIZATION,
                        threshold: float = RESAMPLE_THRESHOLD,
                        cutoff: float = RESAMPLE_CUTOFF) -> np.ndarray:
    """Leave-one-out predictor of the bilinear basis: light i's sample from the other lights.

    For each light i the grid is built from the other N − 1 lights
    (:func:`resample_matrix` without light i, with the same ``sigma`` and other parameters) and
    relit at light i (:func:`bilinear_weights`); row i holds the resulting weights of the other
    lights, 0 at i.

    Parameters
    ----------
    lights : ndarray, shape (N, 3)
        The capture's unit light directions, N ≥ 2.
    resolution : int
        The grid's side R ≥ 2.
    sigma : float, optional
        Width of the RBF prior, the same for every i (default: :func:`default_sigma` of all N
        lights, the capture's setting being evaluated).
    regularization, threshold, cutoff
        As for :func:`resample_matrix`.

    Returns
    -------
    ndarray, shape (N, N), float64
        Zero diagonal; rows sum to 1 up to the entries ``cutoff`` drops (exactly with
        ``cutoff=0``).

    Notes
    -----
    Without light i, B's rows are renormalised over the remaining lights (and re-thresholded),
    so B is recomputed for each i; AᵀA loses a rank-one term, handled by Sherman–Morrison from
    one R² × R² inverse. The lights are batched a few at a time to bound memory (N·R²·N floats
    at once would be 290 MB for 300 lights on a 20×20 grid).
    """
    lights = _vectors(lights, "lights")
    n = len(lights)
    if n < 2:
        raise ValueError("leaving a light out needs at least 2 lights")
    r = _resolution(resolution)
    sigma = default_sigma(lights) if sigma is None else _sigma(sigma)
    k = _regularization(regularization)
    threshold = _nonnegative(threshold, "threshold")
    cutoff = _nonnegative(cutoff, "cutoff")
    d = r * r
    a_full = bilinear_weights(lights, r)  # (N, D); also each light's relighting weights
    # Without light i, AᵀA + kI loses the rank-one term a_i a_iᵀ; by Sherman–Morrison its
    # inverse is H + u_i u_iᵀ / (1 − h_i) with H = (AᵀA + kI)⁻¹, u_i = H a_i, h_i = a_iᵀ u_i.
    # AᵀA + kI − a_i a_iᵀ = A_iᵀA_i + kI ⪰ kI, so 1 − h_i = 1 / (1 + a_iᵀ(A_iᵀA_i + kI)⁻¹a_i)
    # ≥ k / (k + |a_i|²) ≥ k / (k + 1): the division is safe. H is well conditioned for the
    # same reason (eigenvalues between k and k + N).
    h_inv = np.linalg.inv(a_full.T @ a_full + k * np.eye(d))
    h_inv = (h_inv + h_inv.T) / 2
    u_all = a_full @ h_inv  # row i: u_iᵀ
    lev = np.einsum("nd,nd->n", u_all, a_full)  # h_i
    h_at = h_inv @ a_full.T  # H Aᵀ (D, N)
    log_b = -_squared_distances(grid_directions(r), lights) / (sigma * sigma)  # (D, N)
    out = np.zeros((n, n))
    # Lights per batch: about a million floats (8 MB) in each of the (c, D, N) arrays.
    chunk = max(1, min(n, 1_000_000 // (d * n)))
    for start in range(0, n, chunk):
        idx = np.arange(start, min(n, start + chunk))
        c = len(idx)
        ci = np.arange(c)
        # B without light i: log-weight −∞ in column i, rows renormalised over the others.
        lb = np.broadcast_to(log_b, (c, d, n)).copy()
        lb[ci, :, idx] = -np.inf
        b = _normalise_rows(lb, threshold)
        # H (Aᵀ + k B) with light i's column of Aᵀ and B zero: one product for the batch.
        hx = (h_inv @ b.transpose(1, 0, 2).reshape(d, c * n)).reshape(d, c, n).transpose(1, 0, 2)
        hx *= k
        hx += h_at[None]
        hx[ci, :, idx] = 0.0
        # (H + u uᵀ/(1 − h)) X = H X + u (uᵀ X)/(1 − h), and uᵀ X = a_iᵀ H X since H is symmetric.
        corr = np.einsum("cd,cdn->cn", a_full[idx], hx) / (1.0 - lev[idx])[:, None]
        m = hx + u_all[idx][:, :, None] * corr[:, None, :]
        if cutoff > 0:
            m = np.where(np.abs(m) > cutoff, m, 0.0)
        out[idx] = np.einsum("cd,cdn->cn", a_full[idx], m)
    out[np.arange(n), np.arange(n)] = 0.0  # exactly 0 already; make it so against rounding
    return out


# ---------------------------------------------------------------------------------------------
# PCA


def pca(samples: np.ndarray, k: int = DEFAULT_PLANES) -> tuple[np.ndarray, np.ndarray]:
    """The mean and the ``k`` principal components of the rows of ``samples``.

    As relight's ``pickBasePCA``: the mean is subtracted and the components are the unit
    eigenvectors of the covariance with the ``k`` largest eigenvalues, largest first.

    Parameters
    ----------
    samples : ndarray, shape (P, D)
        One row per sampled pixel (relight: the RGB values under each basis direction,
        interleaved, ``D = 3·directions``).
    k : int
        Number of components, 1 ≤ k ≤ D (relight: ``nplanes``, 9 by default).

    Returns
    -------
    mean : ndarray, shape (D,), float64
    components : ndarray, shape (k, D), float64
        Orthonormal rows. Each is signed so that its entry of largest magnitude is positive
        (the first such entry on a tie), so the result does not depend on the LAPACK/BLAS.
        Components of equal variance are determined only up to a rotation among themselves.

    Notes
    -----
    With P ≥ D (the usual case: tens of thousands of pixels, D = 3·N ≤ a few thousand) the
    eigenvectors of the D × D scatter matrix are found with ``eigh``, as relight does: forming
    it costs one P × D × D product and D² memory, where a thin SVD of the P × D data would also
    build a P × D factor. Squaring the data halves the relative precision of the small
    eigenvalues only; the leading components, relative to the largest, keep float64 accuracy.
    With fewer rows than columns the thin SVD of the centred data is the cheaper of the two and
    is used instead, completed by the scatter matrix's eigenvectors if ``k`` exceeds P.
    """
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"samples must have shape (P, D) with P, D ≥ 1, got {np.shape(samples)}")
    if not np.all(np.isfinite(x)):
        raise ValueError("samples contain NaN or infinite values")
    p, d = x.shape
    if isinstance(k, bool) or int(k) != k or not 1 <= int(k) <= d:
        raise ValueError(f"k must be an integer from 1 to {d} (the samples' width), got {k!r}")
    k = int(k)
    mean = x.mean(axis=0)
    xc = x - mean
    if p < d and k <= p:
        _, _, vt = np.linalg.svd(xc, full_matrices=False)
        comps = vt[:k]
    else:
        scatter = xc.T @ xc
        scatter = (scatter + scatter.T) / 2  # exactly symmetric for eigh
        _, vecs = np.linalg.eigh(scatter)  # ascending eigenvalues
        comps = vecs[:, ::-1][:, :k].T
    comps = comps / np.linalg.norm(comps, axis=1, keepdims=True)
    lead = np.argmax(np.abs(comps), axis=1)
    signs = np.sign(comps[np.arange(k), lead])
    signs[signs == 0] = 1.0
    return mean, comps * signs[:, None]
