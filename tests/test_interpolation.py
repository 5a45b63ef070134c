"""RBF, bilinear-grid and PCA maths of relight's interpolating bases (ptmcore.interpolation).

The references below are written plainly, loop by loop, after OpenLIME's ``ShaderRTI.js``
(``RBF.rbf``, ``BLN.lightWeights``) and relight's ``rtibuilder.cpp`` (``fromOcta``,
``buildResampleMap``), so the vectorised module is checked against the definitions.
"""

import math

import numpy as np
import pytest

from ptmcore.interpolation import (
    DEFAULT_PLANES,
    DEFAULT_REGULARIZATION,
    DEFAULT_RESOLUTION,
    RELIGHT_SIGMA,
    bilinear_loo_matrix,
    bilinear_weights,
    default_sigma,
    grid_directions,
    pca,
    rbf_loo_matrix,
    rbf_weights,
    resample_matrix,
)

from helpers import dome

# ---------------------------------------------------------------------------------------------
# Plain references


def ref_rbf(lights, q, sigma, threshold=0.001):
    """ShaderRTI's RBF.rbf, one query."""
    radius = 1 / (sigma * sigma)
    weights = []
    tot = 0.0
    for i, light in enumerate(lights):
        d2 = sum((light[k] - q[k]) ** 2 for k in range(3))
        w = math.exp(-radius * d2)
        weights.append([i, w])
        tot += w
    for pair in weights:
        pair[1] /= tot
    kept = [pair for pair in weights if pair[1] > threshold]
    tot = sum(pair[1] for pair in kept)
    out = np.zeros(len(lights))
    for i, w in kept:
        out[i] = w / tot
    return out


def ref_bln(q, resolution):
    """ShaderRTI's BLN.lightWeights, as weights of the R² nodes, one query."""
    s = abs(q[0]) + abs(q[1]) + abs(q[2])
    x = (q[0] + q[1]) / s
    y = (q[1] - q[0]) / s
    x = (x + 1.0) / 2.0 * (resolution - 1.0)
    y = (y + 1.0) / 2.0 * (resolution - 1.0)
    sx = min(resolution - 2, max(0, math.floor(x)))
    sy = min(resolution - 2, max(0, math.floor(y)))
    dx, dy = x - sx, y - sy
    out = np.zeros(resolution * resolution)
    out[sx + sy * resolution] += (1 - dx) * (1 - dy)
    out[sx + 1 + sy * resolution] += dx * (1 - dy)
    out[sx + (sy + 1) * resolution] += (1 - dx) * dy
    out[sx + 1 + (sy + 1) * resolution] += dx * dy
    return out


def ref_from_octa(x, y, resolution):
    """relight's fromOcta."""
    ox = 2.0 * x / (resolution - 1) - 1.0
    oy = 2.0 * y / (resolution - 1) - 1.0
    gx = (ox - oy) / 2.0
    gy = (ox + oy) / 2.0
    n = np.array([gx, gy, 1.0 - abs(gx) - abs(gy)])
    if n[2] < 0:
        n[2] = 0
    return n / np.linalg.norm(n)


def ref_resample(lights, resolution, sigma, k=0.1, cutoff=0.005):
    """relight's buildResampleMap, in its own form B + (AᵀA + kI)⁻¹ Aᵀ (I − A B)."""
    n = len(lights)
    d = resolution * resolution
    b = np.zeros((d, n))
    for y in range(resolution):
        for x in range(resolution):
            node = ref_from_octa(x, y, resolution)
            b[x + y * resolution] = ref_rbf(lights, node, sigma, threshold=0.005)
    a = np.zeros((n, d))
    for i, light in enumerate(lights):
        lx, ly = light[0], light[1]
        lz = math.sqrt(1 - lx * lx - ly * ly)
        a[i] = ref_bln([lx, ly, lz], resolution)
    inv = np.linalg.inv(a.T @ a + k * np.eye(d))
    m = b + inv @ (a.T @ (np.eye(n) - a @ b))
    if cutoff > 0:
        m[np.abs(m) <= cutoff] = 0.0
    return m


def grid_xy(q, resolution):
    """Continuous grid coordinates of a direction, as BLN computes them."""
    s = np.abs(q).sum()
    x = ((q[0] + q[1]) / s + 1) / 2 * (resolution - 1)
    y = ((q[1] - q[0]) / s + 1) / 2 * (resolution - 1)
    return x, y


def hemisphere(n, seed):
    """Random unit directions over the whole upper hemisphere, horizon included."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v[:, 2] = np.abs(v[:, 2])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------------------
# Defaults


def test_relight_defaults():
    assert RELIGHT_SIGMA == 0.125
    assert DEFAULT_REGULARIZATION == 0.1
    assert DEFAULT_RESOLUTION == 8
    assert DEFAULT_PLANES == 9


def test_default_sigma_scales_with_the_number_of_lights_like_relightlab():
    assert default_sigma(dome(100)) == pytest.approx(0.125, rel=1e-12)
    assert default_sigma(dome(50)) == pytest.approx(0.25, rel=1e-12)
    assert default_sigma(dome(250)) == pytest.approx(0.05, rel=1e-12)


# ---------------------------------------------------------------------------------------------
# RBF


@pytest.mark.parametrize("sigma", [0.05, 0.125, 0.3, 1.0])
def test_rbf_weights_match_openlime(sigma):
    lights = dome(45, seed=1)
    queries = np.vstack([hemisphere(20, seed=2), lights[:3]])
    w = rbf_weights(lights, queries, sigma)
    assert w.shape == (23, 45) and w.dtype == np.float64
    expected = np.stack([ref_rbf(lights, q, sigma) for q in queries])
    np.testing.assert_allclose(w, expected, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    assert np.all(w >= 0)
    # Dropped weights are exactly 0, kept ones above the threshold before renormalising.
    assert np.all((w == 0) | (w > 0.001))


def test_rbf_weights_at_a_light_with_small_sigma_give_that_light():
    lights = dome(30, seed=3)
    w = rbf_weights(lights, lights, 0.01)
    np.testing.assert_allclose(w, np.eye(30), atol=1e-12)


def test_rbf_weights_do_not_underflow_far_from_every_light():
    # exp(−|l − q|²/σ²) is 0 in floating point for every light here; the nearest light wins.
    lights = dome(20, seed=4, min_elev=60, max_elev=85)
    query = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    w = rbf_weights(lights, query, 0.01)
    assert np.all(np.isfinite(w))
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    for row, q in zip(w, query):
        nearest = np.argmin(((lights - q) ** 2).sum(axis=1))
        assert row[nearest] == pytest.approx(1.0)


def test_rbf_threshold_keyword_and_single_query():
    lights = dome(25, seed=5)
    q = hemisphere(1, seed=6)[0]
    w = rbf_weights(lights, q, 0.4, threshold=0.005)
    np.testing.assert_allclose(w[0], ref_rbf(lights, q, 0.4, threshold=0.005), rtol=1e-9,
                               atol=1e-15)
    # With no threshold all weights stay.
    assert np.all(rbf_weights(lights, q, 0.4, threshold=0.0) > 0)


# ---------------------------------------------------------------------------------------------
# Bilinear grid


@pytest.mark.parametrize("resolution", [2, 3, 8, 13])
def test_bilinear_weights_match_openlime(resolution):
    queries = np.vstack([hemisphere(40, seed=resolution), dome(10, seed=7),
                         [[0, 0, 1], [1, 0, 0], [0, -1, 0], [-0.6, 0.8, 0]]])
    w = bilinear_weights(queries, resolution)
    assert w.shape == (len(queries), resolution**2)
    expected = np.stack([ref_bln(q, resolution) for q in queries])
    np.testing.assert_allclose(w, expected, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-12)
    assert np.all(w >= -1e-15)
    assert np.all((np.abs(w) > 1e-15).sum(axis=1) <= 4)


def test_bilinear_weights_ignore_the_length_of_the_direction():
    q = hemisphere(12, seed=8)
    np.testing.assert_allclose(bilinear_weights(3.7 * q, 8), bilinear_weights(q, 8), atol=1e-14)


@pytest.mark.parametrize("resolution", [2, 3, 8, 13, 20])
def test_grid_directions_match_relight_and_stay_on_the_upper_hemisphere(resolution):
    g = grid_directions(resolution)
    assert g.shape == (resolution**2, 3)
    expected = np.array([ref_from_octa(i % resolution, i // resolution, resolution)
                         for i in range(resolution**2)])
    np.testing.assert_allclose(g, expected, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, rtol=1e-12)
    assert np.all(g[:, 2] >= 0)
    # The border of the grid is the horizon; every inner node is above it.
    xs, ys = np.arange(resolution**2) % resolution, np.arange(resolution**2) // resolution
    border = (xs == 0) | (ys == 0) | (xs == resolution - 1) | (ys == resolution - 1)
    np.testing.assert_allclose(g[border, 2], 0.0, atol=1e-15)
    assert np.all(g[~border, 2] > 0)
    # Corners: node (0, 0) is −y, (R−1, 0) is +x, (0, R−1) is −x, (R−1, R−1) is +y.
    r = resolution
    np.testing.assert_allclose(g[[0, r - 1, (r - 1) * r, r * r - 1]],
                               [[0, -1, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0]], atol=1e-14)


@pytest.mark.parametrize("resolution", [2, 3, 8, 13, 20])
def test_grid_round_trip(resolution):
    # Each node's direction maps back onto that node alone.
    w = bilinear_weights(grid_directions(resolution), resolution)
    np.testing.assert_allclose(w, np.eye(resolution**2), atol=1e-9)


@pytest.mark.parametrize("resolution", [2, 5, 8])
def test_bilinear_weights_reproduce_a_linear_function_of_the_node_coordinates(resolution):
    nodes = np.arange(resolution**2)
    f = 0.3 + 1.7 * (nodes % resolution) - 0.9 * (nodes // resolution)
    queries = np.vstack([hemisphere(50, seed=9), dome(10, seed=10)])
    got = bilinear_weights(queries, resolution) @ f
    expected = [0.3 + 1.7 * x - 0.9 * y for x, y in (grid_xy(q, resolution) for q in queries)]
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Resampling onto the grid


@pytest.mark.parametrize(("n", "resolution", "sigma"), [(40, 8, None), (25, 5, 0.3),
                                                        (60, 8, 0.125), (30, 3, None)])
def test_resample_matrix_matches_relights_builder(n, resolution, sigma):
    lights = dome(n, seed=n)
    s = default_sigma(lights) if sigma is None else sigma
    m = resample_matrix(lights, resolution, sigma)
    assert m.shape == (resolution**2, n)
    expected = ref_resample(lights, resolution, s)
    np.testing.assert_allclose(m, expected, rtol=1e-8, atol=1e-10)
    # Without relight's pruning of small entries the rows sum to 1 exactly.
    m0 = resample_matrix(lights, resolution, sigma, cutoff=0.0)
    np.testing.assert_allclose(m0, ref_resample(lights, resolution, s, cutoff=0.0), rtol=1e-8,
                               atol=1e-12)
    np.testing.assert_allclose(m0.sum(axis=1), 1.0, rtol=1e-10)
    # The pruning changes the sums only a little.
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=0.1)


def test_resample_matrix_regularization_keyword():
    lights = dome(30, seed=11)
    m = resample_matrix(lights, 6, 0.2, regularization=1.0, cutoff=0.0)
    np.testing.assert_allclose(m, ref_resample(lights, 6, 0.2, k=1.0, cutoff=0.0), rtol=1e-8,
                               atol=1e-12)


def test_resampling_a_constant_gives_that_constant_at_every_node():
    lights = dome(35, seed=12)
    m = resample_matrix(lights, 8, cutoff=0.0)
    np.testing.assert_allclose(m @ np.full(35, 0.7), 0.7, rtol=1e-10)


# ---------------------------------------------------------------------------------------------
# Leave-one-out predictors


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rbf_loo_matrix_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(8, 60))
    lights = hemisphere(n, seed=seed + 20)
    sigma = float(rng.uniform(0.05, 0.6))
    m = rbf_loo_matrix(lights, sigma)
    assert m.shape == (n, n)
    np.testing.assert_array_equal(np.diag(m), 0.0)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, rtol=1e-12)
    for i in range(n):
        others = np.delete(np.arange(n), i)
        expected = np.zeros(n)
        expected[others] = ref_rbf(lights[others], lights[i], sigma)
        np.testing.assert_allclose(m[i], expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize(("seed", "resolution"), [(0, 8), (1, 5), (2, 3), (3, 8)])
def test_bilinear_loo_matrix_matches_brute_force(seed, resolution):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(12, 50))
    lights = dome(n, seed=seed + 30, min_elev=10, max_elev=85)
    sigma = default_sigma(lights)  # of the whole capture, for every left-out light
    for cutoff in (0.0, 0.005):
        m = bilinear_loo_matrix(lights, resolution, cutoff=cutoff)
        assert m.shape == (n, n)
        np.testing.assert_array_equal(np.diag(m), 0.0)
        for i in range(n):
            others = np.delete(np.arange(n), i)
            grid = ref_resample(lights[others], resolution, sigma, cutoff=cutoff)
            expected = np.zeros(n)
            expected[others] = ref_bln(lights[i], resolution) @ grid
            np.testing.assert_allclose(m[i], expected, rtol=1e-7, atol=1e-10)
        if cutoff == 0.0:
            np.testing.assert_allclose(m.sum(axis=1), 1.0, rtol=1e-10)
        else:
            np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=0.1)


def test_bilinear_loo_matrix_batches_give_the_same_rows():
    # Enough lights on a fine grid that the lights are processed in several batches.
    lights = dome(120, seed=40, min_elev=10, max_elev=85)
    m = bilinear_loo_matrix(lights, 12, 0.1, cutoff=0.0)
    for i in (0, 57, 119):
        others = np.delete(np.arange(120), i)
        grid = resample_matrix(lights[others], 12, 0.1, cutoff=0.0)
        np.testing.assert_allclose(m[i, others], bilinear_weights(lights[i], 12)[0] @ grid,
                                   rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, rtol=1e-10)


def test_loo_predictors_reproduce_a_constant_stack():
    lights = dome(40, seed=41)
    stack = np.full((40, 3, 4), 0.42)
    for m in (rbf_loo_matrix(lights, 0.2), bilinear_loo_matrix(lights, 8, cutoff=0.0)):
        np.testing.assert_allclose(np.tensordot(m, stack, axes=1), stack, rtol=1e-10)


# ---------------------------------------------------------------------------------------------
# PCA


@pytest.mark.parametrize(("p", "d", "k"), [(500, 30, 4), (20, 60, 5), (200, 9, 9), (7, 12, 10)])
def test_pca_reproduces_rank_k_data_exactly(p, d, k):
    rng = np.random.default_rng(p + d)
    rank = min(k, p - 1)
    data = rng.normal(size=(p, rank)) @ rng.normal(size=(rank, d)) * 20 + rng.uniform(0, 255, d)
    mean, comps = pca(data, k)
    assert mean.shape == (d,) and comps.shape == (k, d)
    assert mean.dtype == np.float64 and comps.dtype == np.float64
    np.testing.assert_allclose(mean, data.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose(comps @ comps.T, np.eye(k), atol=1e-10)
    centred = data - mean
    np.testing.assert_allclose(centred @ comps.T @ comps, centred, rtol=1e-6, atol=1e-8)


def test_pca_components_are_the_leading_ones_in_order():
    rng = np.random.default_rng(3)
    # Well separated variances along known orthonormal directions.
    q, _ = np.linalg.qr(rng.normal(size=(15, 15)))
    scales = np.array([50.0, 20.0, 8.0, 3.0] + [0.1] * 11)
    data = (rng.normal(size=(4000, 15)) * scales) @ q.T
    _, comps = pca(data, 3)
    # Compare the spans direction by direction, up to sign.
    _, _, vt = np.linalg.svd(data - data.mean(axis=0), full_matrices=False)
    np.testing.assert_allclose(np.abs(np.sum(comps * vt[:3], axis=1)), 1.0, rtol=1e-8)


def test_pca_signs_are_deterministic():
    rng = np.random.default_rng(5)
    data = rng.normal(size=(300, 12)) * np.linspace(10, 1, 12)
    _, comps = pca(data, 4)
    # Largest-magnitude entry of every component is positive.
    lead = comps[np.arange(4), np.argmax(np.abs(comps), axis=1)]
    assert np.all(lead > 0)
    # Negating or reordering the samples changes neither the components nor their signs.
    _, comps_neg = pca(-data, 4)
    np.testing.assert_allclose(comps_neg, comps, atol=1e-9)
    _, comps_perm = pca(data[rng.permutation(300)], 4)
    np.testing.assert_allclose(comps_perm, comps, atol=1e-9)
    # Both solvers agree: 10 rows of 12 values take the SVD path, the same rows twice (same
    # mean, scatter doubled) the eigenvectors of the scatter matrix.
    few = data[:10]
    _, c_svd = pca(few, 3)
    _, c_eig = pca(np.vstack([few, few]), 3)
    np.testing.assert_allclose(c_svd, c_eig, atol=1e-8)


# ---------------------------------------------------------------------------------------------
# Bad input


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: rbf_weights(np.full((3, 3), np.nan), np.eye(3), 0.1), "NaN"),
        (lambda: rbf_weights(dome(5), np.eye(3)[:, :2], 0.1), "shape"),
        (lambda: rbf_weights(np.zeros((0, 3)), np.eye(3), 0.1), "shape"),
        (lambda: rbf_weights(dome(5), np.eye(3), 0.0), "sigma"),
        (lambda: rbf_weights(dome(5), np.eye(3), -1.0), "sigma"),
        (lambda: rbf_weights(dome(5), np.eye(3), np.nan), "sigma"),
        (lambda: rbf_weights(dome(5), np.zeros((1, 3)), 0.1), "zero vector"),
        (lambda: rbf_weights(dome(5), np.eye(3), 0.1, threshold=-0.1), "threshold"),
        (lambda: rbf_loo_matrix(dome(1), 0.1), "at least 2"),
        (lambda: rbf_loo_matrix(dome(5), 0.0), "sigma"),
        (lambda: bilinear_weights(dome(3), 1), "resolution"),
        (lambda: bilinear_weights(dome(3), 2.5), "resolution"),
        (lambda: bilinear_weights(np.array([[0.0, np.inf, 1.0]]), 8), "NaN"),
        (lambda: grid_directions(1), "resolution"),
        (lambda: grid_directions(0), "resolution"),
        (lambda: resample_matrix(dome(5), 1), "resolution"),
        (lambda: resample_matrix(dome(5), 8, sigma=0.0), "sigma"),
        (lambda: resample_matrix(dome(5), 8, regularization=0.0), "regularization"),
        (lambda: resample_matrix(dome(5), 8, cutoff=-1.0), "cutoff"),
        (lambda: resample_matrix(dome(5)[:, :2], 8), "shape"),
        (lambda: bilinear_loo_matrix(dome(1), 8), "at least 2"),
        (lambda: bilinear_loo_matrix(dome(5), 1), "resolution"),
        (lambda: bilinear_loo_matrix(dome(5), 8, sigma=-0.2), "sigma"),
        (lambda: default_sigma(np.zeros((0, 3))), "shape"),
        (lambda: pca(np.zeros((5, 4)), 0), "k must be"),
        (lambda: pca(np.zeros((5, 4)), 5), "k must be"),
        (lambda: pca(np.zeros((5, 4)), 2.5), "k must be"),
        (lambda: pca(np.zeros(5), 1), "shape"),
        (lambda: pca(np.array([[1.0, np.nan], [0.0, 1.0]]), 1), "NaN"),
    ],
)
def test_bad_input_raises_value_error(call, message):
    with pytest.raises(ValueError, match=message):
        call()
