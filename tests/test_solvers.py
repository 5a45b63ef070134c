import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ptmcore.fit import fit_matrix, light_matrix
from ptmcore.lp import read_lp, write_lp
from ptmcore.solvers import (
    LP_PRECISION,
    analyse_lights,
    duplicate_groups,
    rank_tolerance,
    rohde_factors,
    solve_matrix,
)

from helpers import dome


def sph(elev_deg, azim_deg) -> np.ndarray:
    """Unit vectors from elevation and azimuth in degrees (azimuth 0 = +x, 90 = +y)."""
    el, az = np.radians(elev_deg), np.radians(azim_deg)
    el, az = np.broadcast_arrays(el, az)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def ring(n: int = 24, elev: float = 30.0, start: float = 0.0) -> np.ndarray:
    return sph(np.full(n, elev), start + np.arange(n) * 360.0 / n)


def tilted_circle(n: int = 12) -> np.ndarray:
    """Lights on a circle of 40° radius around an axis at elevation 70°: one tilted plane."""
    axis = sph(70.0, 30.0)
    e1 = np.cross(axis, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)[:, None]
    r = np.radians(40.0)
    return np.cos(r) * axis + np.sin(r) * (np.cos(t) * e1 + np.sin(t) * e2)


def through_lp(directions: np.ndarray, folder) -> np.ndarray:
    path = folder / "lights.lp"
    write_lp(path, [f"img_{k:03d}.jpg" for k in range(len(directions))], directions)
    return read_lp(path).directions


def duplicated() -> np.ndarray:
    d = dome(5, seed=1)
    return np.vstack([d, d[[0, 3]]])  # photographs 6 and 7 repeat 1 and 4


LAYOUTS = {
    "dome": lambda: dome(24, seed=0),
    "ring": lambda: ring(24, 30.0),
    "duplicated": duplicated,
    "five": lambda: dome(5, seed=2),
    "vertical_plane": lambda: sph([20, 40, 60, 80, 30, 50, 70], [40, 40, 40, 40, 220, 220, 220]),
    "tilted_plane": tilted_circle,
    "ring_with_duplicate": lambda: np.vstack([ring(6, 30.0), ring(6, 30.0)[:1]]),
}


@pytest.fixture(params=[*LAYOUTS, "ring_lp"])
def layout(request, tmp_path) -> np.ndarray:
    if request.param == "ring_lp":
        return through_lp(ring(24, 30.0, start=7.3), tmp_path)
    return LAYOUTS[request.param]()


def free_blocks(rank: int, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "U": rng.normal(size=(rank, n - rank)),
        "V": rng.normal(size=(6 - rank, rank)),
        "W": rng.normal(size=(6 - rank, n - rank)),
    }


def inverses(d: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    rank = analyse_lights(d).rank
    rng = np.random.default_rng(seed)
    return {
        "pinv": solve_matrix(d),
        "lstsq": solve_matrix(d, "lstsq"),
        "rohde": solve_matrix(d, "rohde"),
        "rohde_qr": solve_matrix(d, "rohde", factorisation="qr"),
        "rohde_uvw": solve_matrix(d, "rohde", **free_blocks(rank, len(d), rng)),
        "rohde_qr_uvw": solve_matrix(d, "rohde", factorisation="qr", **free_blocks(rank, len(d), rng)),
    }


def g_inverse_error_bound(d: np.ndarray, x: np.ndarray) -> float:
    # Λ·X·Λ − Λ is made of the dropped singular values times the free blocks: zero for an
    # exactly singular layout, about σ_max·σ_{ρ+1}·‖X‖ for one rounded in an .lp file.
    info = analyse_lights(d)
    dropped = info.singular_values[info.rank :].max(initial=0.0)
    s = info.singular_values[0]
    return 1e-12 * s + 10 * dropped * (1 + s * np.linalg.norm(x, 2)) * (1 + s)


# ---------------------------------------------------------------- {1}-inverse property


def test_every_method_is_a_generalised_inverse(layout):
    lam = light_matrix(layout)
    for name, x in inverses(layout).items():
        assert x.shape == (6, len(layout)), name
        err = np.abs(lam @ x @ lam - lam).max()
        assert err <= g_inverse_error_bound(layout, x), (name, err)


@settings(max_examples=30, deadline=None)
@given(
    name=st.sampled_from(sorted(LAYOUTS)),
    seed=st.integers(0, 2**32 - 1),
    scale=st.floats(1e-3, 1e3),
    factorisation=st.sampled_from(["svd", "qr"]),
)
def test_any_free_blocks_give_a_generalised_inverse(name, seed, scale, factorisation):
    d = LAYOUTS[name]()
    lam = light_matrix(d)
    rank = analyse_lights(d).rank
    blocks = {k: scale * v for k, v in free_blocks(rank, len(d), np.random.default_rng(seed)).items()}
    x = solve_matrix(d, "rohde", factorisation=factorisation, **blocks)
    np.testing.assert_allclose(lam @ x @ lam, lam, atol=1e-9 * (1 + scale) ** 2)


def test_pinv_equals_lstsq(layout):
    p = solve_matrix(layout, "pinv")
    np.testing.assert_allclose(solve_matrix(layout, "lstsq"), p, atol=1e-10 * (1 + np.abs(p).max()))


def test_pinv_is_moore_penrose_and_matches_fit_matrix_for_regular_layouts():
    d = dome(24, seed=4)
    lam, x = light_matrix(d), solve_matrix(d)
    np.testing.assert_allclose(x @ lam @ x, x, atol=1e-12)
    np.testing.assert_allclose(lam @ x, (lam @ x).T, atol=1e-12)
    np.testing.assert_allclose(x @ lam, (x @ lam).T, atol=1e-12)
    np.testing.assert_allclose(x, fit_matrix(d), atol=1e-12)


def test_svd_rohde_with_zero_blocks_is_the_pseudoinverse(layout):
    np.testing.assert_allclose(solve_matrix(layout, "rohde"), solve_matrix(layout), atol=1e-10)


def test_qr_rohde_with_zero_blocks_is_reflexive_least_squares_but_not_minimum_norm():
    d = ring(24, 30.0)
    lam = light_matrix(d)
    x = solve_matrix(d, "rohde", factorisation="qr")
    np.testing.assert_allclose(x @ lam @ x, x, atol=1e-12)
    np.testing.assert_allclose(lam @ x, (lam @ x).T, atol=1e-12)  # so Λ·X·L is the LS fit
    assert np.abs(x - solve_matrix(d)).max() > 1e-3


@pytest.mark.parametrize("factorisation", ["svd", "qr"])
def test_rohde_factors_reduce_to_normal_form(layout, factorisation):
    p, q, rank = rohde_factors(layout, factorisation=factorisation)
    lam = light_matrix(layout)
    normal = np.zeros_like(lam)
    normal[:rank, :rank] = np.eye(rank)
    info = analyse_lights(layout)
    dropped = info.singular_values[rank:].max(initial=0.0)
    # The trailing block holds the dropped singular values (or R22 for QR).
    np.testing.assert_allclose(q @ lam @ p, normal, atol=1e-10 + 10 * dropped * np.linalg.norm(p, 2))
    assert np.linalg.matrix_rank(p) == 6 and np.linalg.matrix_rank(q) == len(layout)


# ---------------------------------------------------------------- solutions of Λ·a = L


def test_consistent_system_every_inverse_solves_it_and_solutions_differ_by_null_vectors():
    for d in (ring(24, 30.0), duplicated(), LAYOUTS["vertical_plane"](), dome(5, seed=3), dome(24)):
        lam = light_matrix(d)
        info = analyse_lights(d)
        rng = np.random.default_rng(7)
        a_true = rng.normal(size=(6, 4))  # four pixels
        values = lam @ a_true
        base = solve_matrix(d) @ values
        null = info.null_space
        for name, x in inverses(d, seed=11).items():
            a = x @ values
            np.testing.assert_allclose(lam @ a, values, atol=1e-10, err_msg=name)
            diff = a - base
            np.testing.assert_allclose(diff - null @ (null.T @ diff), 0, atol=1e-9, err_msg=name)
        # ... and every solution is one of them: a_true = X·L + (I − X·Λ)·z for some z.
        x = solve_matrix(d)
        np.testing.assert_allclose(x @ values + (np.eye(6) - x @ lam) @ a_true, a_true, atol=1e-10)


def test_inconsistent_system_pinv_gives_least_squares_minimum_norm():
    d = np.vstack([ring(6, 30.0), ring(6, 30.0)[:1]])
    lam = light_matrix(d)
    info = analyse_lights(d)
    values = np.random.default_rng(5).uniform(0.2, 0.8, size=(len(d), 3))
    a = solve_matrix(d) @ values
    # Least squares: the residual is orthogonal to the range of Λ (normal equations) ...
    np.testing.assert_allclose(lam.T @ (lam @ a - values), 0, atol=1e-12)
    # ... and minimum norm: no component along the null space.
    np.testing.assert_allclose(info.null_space.T @ a, 0, atol=1e-12)
    best = np.linalg.norm(lam @ a - values, axis=0)
    assert np.all(best > 1e-3)  # really inconsistent
    for name, x in inverses(d, seed=2).items():
        b = x @ values
        resid = np.linalg.norm(lam @ b - values, axis=0)
        assert np.all(resid >= best - 1e-12), name
        if np.allclose(resid, best, atol=1e-12):  # another least-squares solution: longer
            assert np.all(np.linalg.norm(b, axis=0) >= np.linalg.norm(a, axis=0) - 1e-12), name
    z = np.random.default_rng(1).normal(size=(info.null_space.shape[1], 3))
    assert np.all(np.linalg.norm(a + info.null_space @ z, axis=0) > np.linalg.norm(a, axis=0))


# ---------------------------------------------------------------- rank and causes


def test_ring_read_from_lp_with_six_decimals_has_rank_5(tmp_path):
    d = through_lp(ring(24, 30.0, start=7.3), tmp_path)
    lam = light_matrix(d)
    # Rounding makes the matrix regular to floating point, which is why the tolerance is needed.
    assert np.linalg.matrix_rank(lam) == 6
    info = analyse_lights(d)
    assert info.rank == 5 and info.deficient
    assert info.singular_values[-1] < info.tolerance < info.singular_values[-2]
    assert info.tolerance == pytest.approx(np.sqrt(14 * 24) * LP_PRECISION)
    assert info.condition == pytest.approx(info.singular_values[0] / info.singular_values[4])
    expected = np.array([1, 1, 0, 0, 0, -0.75]) / np.linalg.norm([1, 1, 0, 0, 0, -0.75])
    assert info.null_space.shape == (6, 1)
    assert abs(info.null_space[:, 0] @ expected) == pytest.approx(1, abs=1e-6)
    ring_cause = "all 24 lights at elevation 30.0°: lu² + lv² is constant"
    assert any(c.startswith(ring_cause) for c in info.causes)
    assert "minimum-norm solution" in info.causes[-1]
    # At floating-point precision the same file would count as regular.
    assert analyse_lights(d, precision=0).rank == 6


def test_fitting_the_rounded_ring_stays_bounded(tmp_path):
    d = through_lp(ring(24, 30.0, start=7.3), tmp_path)
    assert np.linalg.norm(solve_matrix(d), 2) < 10
    assert np.linalg.norm(fit_matrix(d), 2) < 10  # the pipeline's fit uses the same cut
    assert np.linalg.norm(np.linalg.pinv(light_matrix(d)), 2) > 1e5  # an untruncated one blows up


def test_rank_5_ring_does_not_swallow_a_real_elevation_spread():
    d = sph(np.tile([29.0, 31.0], 12), np.arange(24) * 15.0)
    info = analyse_lights(d)
    assert info.rank == 6 and info.causes == []


def test_five_photographs():
    info = analyse_lights(dome(5, seed=2))
    assert info.rank == 5
    assert "only 5 photographs for 6 coefficients" in info.causes
    assert not any("elevation" in c or "plane" in c for c in info.causes)


def test_duplicates_are_named_with_photograph_numbers():
    d = duplicated()
    assert duplicate_groups(d) == [[0, 5], [3, 6]]
    info = analyse_lights(d)
    assert info.rank == 5
    assert "duplicate light directions (photographs 1 and 6)" in info.causes
    assert "duplicate light directions (photographs 4 and 7)" in info.causes
    assert "only 5 distinct light directions for 6 coefficients" in info.causes


def test_duplicates_within_lp_rounding_are_found(tmp_path):
    d = dome(8, seed=3)
    d = np.vstack([d, d[2] + [4e-7, -3e-7, 0.0], d[2]])
    assert duplicate_groups(through_lp(d, tmp_path)) == [[2, 8, 9]]
    assert duplicate_groups(np.vstack([d[:8], d[2] + [1e-4, 0.0, 0.0]])) == []


def test_one_duplicate_among_seven_leaves_full_rank():
    d = dome(6, seed=0)
    info = analyse_lights(np.vstack([d, d[:1]]))
    assert info.rank == 6 and info.causes == [] and info.null_space.shape == (6, 0)


def test_vertical_plane():
    info = analyse_lights(LAYOUTS["vertical_plane"]())
    assert info.rank == 3
    assert any("one vertical plane (azimuths 40.0° and 220.0°)" in c for c in info.causes)
    assert "3 combinations" in info.causes[-1]


def test_plane_parallel_to_camera_axis():
    y = np.linspace(-0.8, 0.8, 9)
    d = np.stack([np.full(9, 0.3), y, np.sqrt(1 - 0.09 - y * y)], axis=1)
    info = analyse_lights(d)
    assert info.rank == 3
    assert any("parallel to the camera axis" in c and "lu − 0.3 = 0" in c for c in info.causes)


def test_tilted_plane():
    info = analyse_lights(tilted_circle())
    assert info.rank == 5
    assert any("one plane tilted 20.0° from the horizontal" in c for c in info.causes)


def test_other_conic_is_described_by_its_equation():
    t = np.linspace(0, 2 * np.pi, 10, endpoint=False)
    lu, lv = np.sqrt(0.5) * np.cos(t), 0.5 * np.sin(t)  # 0.5·lu² + lv² = 0.25: not a plane
    info = analyse_lights(np.stack([lu, lv, np.sqrt(1 - lu * lu - lv * lv)], axis=1))
    assert info.rank == 5
    assert any("0.5·lu² + lv² − 0.25 = 0" in c for c in info.causes)


def test_regular_dome():
    info = analyse_lights(dome(40, seed=0))
    assert info.rank == 6 and info.causes == []
    assert 1 < info.condition < 50
    assert info.singular_values.shape == (6,)


def test_tolerance_formula():
    assert rank_tolerance(5.0, 24) == pytest.approx(np.sqrt(14 * 24) * 1e-6)
    assert rank_tolerance(5.0, 24, precision=0) == pytest.approx(24 * np.finfo(float).eps * 5.0)
    # Coarser directions (a hand-measured dome) make the decision more lenient.
    assert rank_tolerance(5.0, 24, precision=1e-3) == pytest.approx(np.sqrt(14 * 24) * 1e-3)


def test_two_dimensional_directions_are_accepted():
    d = dome(12, seed=2)
    np.testing.assert_allclose(solve_matrix(d[:, :2]), solve_matrix(d))
    assert analyse_lights(ring(12, 45.0)[:, :2]).rank == 5


# ---------------------------------------------------------------- argument checking


def test_free_block_shapes_are_checked():
    d = ring(24, 30.0)  # rank 5: U 5×19, V 1×5, W 1×19
    solve_matrix(d, "rohde", U=np.zeros((5, 19)), V=np.zeros((1, 5)), W=np.zeros((1, 19)))
    with pytest.raises(ValueError, match=r"U must have shape \(5, 19\)"):
        solve_matrix(d, "rohde", U=np.zeros((19, 5)))
    with pytest.raises(ValueError, match=r"V must have shape \(1, 5\)"):
        solve_matrix(d, "rohde", V=np.zeros((5, 1)))
    with pytest.raises(ValueError, match=r"W must have shape \(1, 19\)"):
        solve_matrix(d, "rohde", W=np.zeros((1, 18)))


def test_full_rank_square_layout_has_empty_free_blocks():
    d = dome(6, seed=0)
    x = solve_matrix(d, "rohde", U=np.zeros((6, 0)), V=np.zeros((0, 6)), W=np.zeros((0, 0)))
    np.testing.assert_allclose(x, np.linalg.inv(light_matrix(d)), atol=1e-9)


def test_bad_arguments():
    d = dome(10)
    with pytest.raises(ValueError, match="only used by method='rohde'"):
        solve_matrix(d, "pinv", U=np.zeros((6, 4)))
    with pytest.raises(ValueError, match="method must be"):
        solve_matrix(d, "qr")
    with pytest.raises(ValueError, match="factorisation must be"):
        solve_matrix(d, "rohde", factorisation="lu")
    with pytest.raises(ValueError, match="shape"):
        analyse_lights(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="no light"):
        analyse_lights(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="finite"):
        analyse_lights(np.array([[np.nan, 0.0, 1.0]]))
