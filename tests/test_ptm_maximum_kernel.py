"""The compiled PTM maximum (ptmcore.maximum) against the NumPy steps it replaces.

The reference below is ``ptm_maximum``, ``_circle_maximum`` and ``normals_from_ptm`` as
ptmcore/normals.py had them before the kernel, unchanged; flat PTMs (ptmcore.normals.FLAT) have
since had their maximum at (0, 0) and no normal, which :func:`expected_maximum` and
:func:`expected_normals` apply to it.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ptmcore.bands import band_rows
from ptmcore.fit import fit_matrix
from ptmcore.normals import FLAT, normals_from_ptm, ptm_maximum

from helpers import dome, sphere_normals

# The reference's NumPy passes warn of the NaN and inf they make from such coefficients; the
# kernel makes the same values without a word.
pytestmark = pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning", "ignore:overflow:RuntimeWarning")

# --------------------------------------------------------------------------------------------
# The NumPy steps, as they were

_CIRCLE_SAMPLES = 72
_NEWTON_STEPS = 4


def _circle_maximum(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Direction (lu, lv) on the unit circle that maximises each PTM polynomial.

    ``a`` is (P, 6). On the circle, L(θ) = a0 c² + a1 s² + a2 c s + a3 c + a4 s + a5 has no
    closed-form maximum (its stationary points solve a quartic), so it is sampled every 5° and
    the best sample is refined by Newton's method on L'(θ).
    """
    a = a.astype(np.float64)
    theta = np.linspace(0.0, 2 * np.pi, _CIRCLE_SAMPLES, endpoint=False)
    c, s = np.cos(theta), np.sin(theta)
    basis = np.stack([c * c, s * s, c * s, c, s, np.zeros_like(c)])  # a5 does not move the maximum
    t = theta[np.argmax(a @ basis, axis=1)]
    d_a = a[:, 1] - a[:, 0]
    for _ in range(_NEWTON_STEPS):
        c, s = np.cos(t), np.sin(t)
        c2, s2 = np.cos(2 * t), np.sin(2 * t)
        d1 = d_a * s2 + a[:, 2] * c2 - a[:, 3] * s + a[:, 4] * c
        d2 = 2 * d_a * c2 - 2 * a[:, 2] * s2 - a[:, 3] * c - a[:, 4] * s
        # Only step where the curvature says we are near a maximum; the sample is already
        # within 2.5° of it.
        ok = d2 < 0
        t = np.where(ok, t - np.clip(d1 / np.where(ok, d2, -1.0), -0.05, 0.05), t)
    return np.cos(t), np.sin(t)


def reference_ptm_maximum(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(coefficients, dtype=np.float64).reshape(-1, 6)
    a0, a1, a2, a3, a4 = (a[:, k] for k in range(5))
    den = 4 * a0 * a1 - a2 * a2
    concave = (a0 < 0) & (den > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        lu = np.where(concave, (a2 * a4 - 2 * a1 * a3) / den, 0.0)
        lv = np.where(concave, (a2 * a3 - 2 * a0 * a4) / den, 0.0)
    interior = concave & (lu * lu + lv * lv < 1.0)
    boundary = ~interior
    if boundary.any():
        lu[boundary], lv[boundary] = _circle_maximum(a[boundary])
    shape = np.shape(coefficients)[:-1]
    return (
        lu.reshape(shape).astype(np.float32),
        lv.reshape(shape).astype(np.float32),
        interior.reshape(shape),
    )


def reference_normals_from_ptm(coefficients: np.ndarray) -> np.ndarray:
    h, w = coefficients.shape[:2]
    out = np.empty((h, w, 3), dtype=np.float32)
    step = band_rows(1, w, 6 * 8 * 4)
    for r0 in range(0, h, step):
        lu, lv, _ = reference_ptm_maximum(coefficients[r0 : r0 + step])
        out[r0 : r0 + step, :, 0] = lu
        out[r0 : r0 + step, :, 1] = lv
        out[r0 : r0 + step, :, 2] = np.sqrt(np.clip(1.0 - lu * lu - lv * lv, 0.0, 1.0))
    return out


def _flat(coefficients: np.ndarray) -> np.ndarray:
    """Where a PTM is flat (ptmcore.normals.FLAT), as the kernel decides it in float64."""
    a = np.abs(np.asarray(coefficients).astype(np.float64))
    with np.errstate(invalid="ignore"):
        shape = a[..., 0] + a[..., 1] + a[..., 2] + a[..., 3] + a[..., 4]  # in the kernel's order
        return (shape <= FLAT * a[..., 5]) & (a[..., 5] < np.inf)


def expected_maximum(coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reference's maximum, at (0, 0) and not interior where the PTM is flat."""
    lu, lv, interior = reference_ptm_maximum(coefficients)
    flat = _flat(coefficients)
    return np.where(flat, np.float32(0), lu), np.where(flat, np.float32(0), lv), interior & ~flat


def expected_normals(coefficients: np.ndarray) -> np.ndarray:
    """The reference's normals, (0, 0, 1) where the PTM is flat."""
    return np.where(_flat(coefficients)[..., None], np.float32([0, 0, 1]), reference_normals_from_ptm(coefficients))


# --------------------------------------------------------------------------------------------
# Coefficient maps


def _with_maximum_at(lu0, lv0, a0, a1, a2):
    """a3, a4 that put the stationary point of a0 lu² + a1 lv² + a2 lu lv + … at (lu0, lv0)."""
    return -(2 * a0 * lu0 + a2 * lv0), -(a2 * lu0 + 2 * a1 * lv0)


def mixed_map(shape: tuple[int, int], seed: int = 0, non_finite: bool = False) -> np.ndarray:
    """float64 coefficients (H, W, 6) of every kind of polynomial, mixed pixel by pixel.

    Concave with the stationary point inside the disk, about on its rim and far outside;
    convex; saddles; linear; concave only in one direction; plain normal noise; and, with
    ``non_finite``, NaN and ±inf in every coefficient (a5 included).
    """
    rng = np.random.default_rng(seed)
    n = int(np.prod(shape))
    kind = rng.integers(0, 8, n)
    a = rng.normal(size=(n, 6))
    # Concave: a0 < 0 and 4 a0 a1 > a2².
    a0 = -rng.uniform(0.05, 2.0, n)
    a1 = -rng.uniform(0.05, 2.0, n)
    a2 = rng.uniform(-1.0, 1.0, n) * np.sqrt(4 * a0 * a1) * 0.99
    radius = np.select([kind == 0, kind == 1, kind == 2], [rng.uniform(0, 0.999, n), rng.uniform(0.98, 1.02, n),
                                                           rng.uniform(1.5, 20.0, n)], 0.0)
    angle = rng.uniform(0, 2 * np.pi, n)
    a3, a4 = _with_maximum_at(radius * np.cos(angle), radius * np.sin(angle), a0, a1, a2)
    concave = kind <= 2
    a[concave, :5] = np.stack([a0, a1, a2, a3, a4], axis=1)[concave]
    a[kind == 3, :2] = np.abs(a[kind == 3, :2])  # convex (mostly)
    a[kind == 4, 1] = -np.sign(a[kind == 4, 0]) * np.abs(a[kind == 4, 1])  # saddle
    a[kind == 5, :3] = 0.0  # linear: straight up the gradient
    a[kind == 6, 0], a[kind == 6, 2] = 0.0, 0.0  # concave along one axis only (a1 < 0 half the time)
    a *= rng.uniform(0.01, 100.0, (n, 1))
    if non_finite:
        bad = rng.random((n, 6)) < 0.04
        a[bad] = rng.choice([np.nan, np.inf, -np.inf], bad.sum())
    return a.reshape(shape + (6,))


def fitted_map(shape: tuple[int, int], seed: int = 0, n_lights: int = 40) -> np.ndarray:
    """float32 PTMs fitted to a Lambertian sphere on a flat background under a dome of lights
    (with attached shadows), like a capture's: maxima inside the disk and, at the sphere's
    steep rim, on its boundary."""
    h, w = shape
    normals, _ = sphere_normals(h, w, 0.45 * min(h, w))
    dirs = dome(n_lights, seed=seed, min_elev=10.0, max_elev=85.0).astype(np.float32)
    matrix = fit_matrix(dirs).astype(np.float32)  # (6, N)
    shading = np.maximum(normals.reshape(-1, 3) @ dirs.T, 0.0)  # (P, N)
    albedo = np.random.default_rng(seed).uniform(0.2, 0.9, (h * w, 1)).astype(np.float32)
    return ((albedo * shading) @ matrix.T).reshape(h, w, 6)


def _assert_same(coefficients, threads):
    lu, lv, interior = ptm_maximum(coefficients, threads=threads)
    want_lu, want_lv, want_interior = expected_maximum(coefficients)
    assert lu.dtype == lv.dtype == np.float32 and interior.dtype == bool
    assert lu.shape == lv.shape == interior.shape == want_lu.shape
    np.testing.assert_array_equal(lu, want_lu)
    np.testing.assert_array_equal(lv, want_lv)
    np.testing.assert_array_equal(interior, want_interior)
    if np.ndim(coefficients) == 3:
        normals = normals_from_ptm(coefficients, threads=threads)
        assert normals.dtype == np.float32
        np.testing.assert_array_equal(normals, expected_normals(coefficients))


# --------------------------------------------------------------------------------------------
# Equal to the bit
#
# The kernel adds the terms of L at the 72 samples in their written order, where the NumPy
# steps had a BLAS matrix product (its order and fused multiply-adds are the library's). That
# can move which sample wins only where two samples tie to within rounding, which takes a
# symmetric polynomial (test_ties_are_broken_between_equal_maxima), not continuous random
# coefficients: those are compared bit for bit.


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (7, 1), (2, 2), (37, 53), (300, 500)])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("threads", [1, 2])
def test_random_maps_to_the_bit(shape, dtype, threads):
    # (300, 500) is three bands of rows.
    _assert_same(mixed_map(shape, seed=shape[0] * shape[1]).astype(dtype), threads)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("threads", [1, 2])
def test_non_finite_coefficients_as_the_numpy_steps(dtype, threads):
    a = mixed_map((120, 90), seed=5, non_finite=True).astype(dtype)
    _assert_same(a, threads)
    lu, _, _ = ptm_maximum(a, threads=threads)
    assert np.isnan(lu).any()  # the case is exercised


def test_every_non_finite_coefficient_alone():
    base = mixed_map((8, 12), seed=9)
    rows = []
    for k in range(6):
        for value in (np.nan, np.inf, -np.inf):
            b = base.copy()
            b[..., k] = value
            rows.append(b)
    _assert_same(np.concatenate(rows), threads=2)


@pytest.mark.parametrize("threads", [1, 2])
def test_fitted_sphere_to_the_bit(threads):
    a = fitted_map((150, 170))
    _, _, interior = reference_ptm_maximum(a)
    assert interior.any() and not interior.all()
    _assert_same(a, threads)


@pytest.mark.parametrize(
    "view",
    [
        lambda a: a[::2, 1::3],  # strided rows and columns
        lambda a: a[::-1, ::-1],  # negative strides
        lambda a: a.swapaxes(0, 1),  # column-major pixels
        lambda a: np.concatenate([a, a], axis=-1)[..., ::2],  # strided coefficients
        lambda a: np.asfortranarray(a),
    ],
)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_non_contiguous_views(view, dtype):
    a = view(mixed_map((64, 48), seed=11, non_finite=True).astype(dtype))
    assert not a.flags.c_contiguous
    _assert_same(a, threads=2)


@pytest.mark.parametrize("dtype", [np.float16, np.int16, np.longdouble, ">f8", ">f4"])
def test_other_types_converted_as_before(dtype):
    a = mixed_map((40, 30), seed=13)
    a = (a * 10 if np.dtype(dtype).kind == "i" else a).astype(dtype)
    _assert_same(a, threads=2)


@pytest.mark.parametrize("shape", [(6,), (1, 6), (250, 6), (3, 4, 5, 6), (0, 6), (0, 4, 6), (4, 0, 6)])
def test_any_leading_shape(shape):
    a = mixed_map((1, int(np.prod(shape[:-1]))), seed=17).reshape(shape)
    _assert_same(a, threads=2)


def test_threads_do_not_change_the_result():
    a = fitted_map((400, 330)).astype(np.float32)
    one = normals_from_ptm(a, threads=1)
    np.testing.assert_array_equal(normals_from_ptm(a, threads=2), one)
    np.testing.assert_array_equal(normals_from_ptm(a), one)


def test_the_whole_map_is_not_copied_to_float64(monkeypatch):
    """A band at a time is all that is converted (here: float16 → float64), and float32 and
    float64 are read where they are."""
    from ptmcore import maximum

    seen = []
    kernel = maximum.maximum_rows

    def spy(a, *args):
        seen.append(a)
        return kernel(a, *args)

    monkeypatch.setattr(maximum, "maximum_rows", spy)
    monkeypatch.setattr(maximum, "_BAND_PIXELS", 1000)
    big = mixed_map((90, 50), seed=19).astype(np.float32)[:, ::2]
    normals_from_ptm(big, threads=2)
    assert all(np.shares_memory(a, big) for a in seen)
    seen.clear()
    normals_from_ptm(big.astype(np.float16), threads=2)
    assert all(a.dtype == np.float64 for a in seen)
    assert max(a.shape[0] for a in seen) == 1000 // 25 and len(seen) == 3


# --------------------------------------------------------------------------------------------
# Ties


def _value(a, lu, lv):
    lu, lv = lu.astype(np.float64), lv.astype(np.float64)
    return a[..., 0] * lu * lu + a[..., 1] * lv * lv + a[..., 2] * lu * lv + a[..., 3] * lu + a[..., 4] * lv


def _assert_same_or_tied(a, got, want):
    """Equal, or where not, two maxima on the circle with the same value: ties.

    A symmetric polynomial (a3 = a4 = 0, or a2 = a3 = 0, …) takes its maximum at two mirror
    directions whose samples have the same value but for rounding; the NumPy steps' BLAS
    product rounded them otherwise (and otherwise again for one pixel than for many) than the
    kernel's sums in order, so each may start Newton's steps at the other one.
    """
    (lu, lv, interior), (want_lu, want_lv, want_interior) = got, want
    np.testing.assert_array_equal(interior, want_interior)
    differ = (lu != want_lu) | (lv != want_lv)
    differ &= ~(np.isnan(lu) & np.isnan(want_lu))
    assert not (interior & differ).any()
    scale = 1.0 + np.abs(a[..., :5]).sum(axis=-1)
    # Float32 directions: the value is known to about 1e-7 of the scale.
    np.testing.assert_allclose(_value(a, lu, lv)[differ] / scale[differ],
                               _value(a, want_lu, want_lv)[differ] / scale[differ], rtol=0, atol=1e-6)
    return differ


def _symmetric(a):
    """Polynomials that are their own mirror images under θ → θ + π, −θ or π − θ."""
    zero = a[..., 2:5] == 0
    return zero[..., [1, 2]].all(axis=-1) | zero[..., [0, 2]].all(axis=-1) | zero[..., [0, 1]].all(axis=-1)


def test_ties_are_broken_between_equal_maxima():
    a = np.random.default_rng(23).integers(-3, 4, size=(20000, 6)).astype(np.float64)
    want = expected_maximum(a)
    differ = _assert_same_or_tied(a, ptm_maximum(a), want)
    # The case is exercised: symmetric polynomials with their maximum on the circle. Whether
    # rounding breaks a tie otherwise than the kernel does is the CPU's and the BLAS library's
    # (none do with OpenBLAS's kernels for CPUs without FMA).
    assert (_symmetric(a) & ~want[2]).sum() > 500
    # Only symmetric polynomials differ.
    assert _symmetric(a[differ]).all()


_coefficient = st.one_of(
    st.floats(-8.0, 8.0, width=32),
    st.sampled_from([0.0, 1.0, -1.0, 0.5, np.nan, np.inf, -np.inf, 1e30, -1e30, 1e-30]),
)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays(np.float64, st.tuples(st.integers(1, 4), st.integers(1, 5), st.just(6)), elements=_coefficient),
       st.sampled_from([np.float32, np.float64]))
def test_property_as_the_numpy_steps(a, dtype):
    a = a.astype(dtype)
    with np.errstate(over="ignore", invalid="ignore"):
        got, want = ptm_maximum(a, threads=1), expected_maximum(a)
        finite = np.isfinite(a).all(axis=-1)
    # Samples that are not finite are inf or NaN whatever the order of the sum: pixels with
    # such coefficients are compared to the bit, the others allowing for ties.
    a64 = a.astype(np.float64)
    _assert_same_or_tied(np.where(finite[..., None], a64, 0.0),
                         tuple(np.where(finite, g, 0) for g in got), tuple(np.where(finite, w, 0) for w in want))
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g[~finite], w[~finite])
    valid = np.empty(a.shape[:-1], bool)
    normals = normals_from_ptm(a, threads=1, valid=valid)
    np.testing.assert_array_equal(normals[..., 0], got[0])
    np.testing.assert_array_equal(normals[..., 1], got[1])
    np.testing.assert_array_equal(valid, ~_flat(a) & np.isfinite(got[0]) & np.isfinite(got[1]))
    z = expected_normals(a)[..., 2]
    same = (got[0] == want[0]) & (got[1] == want[1]) | ~finite
    np.testing.assert_array_equal(normals[..., 2][same], z[same])


# --------------------------------------------------------------------------------------------


def test_numba_is_imported_only_when_used():
    """`import ptmcore` does not import numba (a second); the first maximum does."""
    import subprocess
    import sys

    code = ("import sys, ptmcore, ptmcore.normals; print('numba' in sys.modules, 'ptmcore.maximum' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


@pytest.mark.parametrize("shape", [(4, 5, 3), (4, 5, 8), (20, 6), (6,)])
def test_normals_from_ptm_refuses_other_shapes(shape):
    # The kernel does not check its indices: a map of another shape must not reach it.
    with pytest.raises(ValueError, match="must be \\(H, W, 6\\)"):
        normals_from_ptm(np.zeros(shape, np.float32))
