"""``integrate_auto``: bilateral integration kept where it finds depth steps, least squares
where the surface is continuous."""

from __future__ import annotations

import numpy as np
import pytest

from data_synthetic import clay_tablet
from data_synthetic.sphere import sphere_cap
from reconstruct.surface import discontinuity_preserving, integrate, integrate_auto
from reconstruct.surface.choose import MIN_CUT_EDGES
from test_integrate_masked import _cap_on_tilted_plane, _disk, _noisy, _rmse, _step, _tent
from test_perspective import CAM, H, W, _made, _real_object, _scissor_step


def _normals(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    n = np.stack([-p, -q, np.ones_like(p)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def test_a_smooth_tablet_is_integrated_by_least_squares():
    # The case: a domed clay tablet's true normals on its outline. Bilateral
    # integration leans towards the flatter side wherever the slope changes; measured at
    # 288 × 384: masked 0.0071 mm, bilateral 0.0089 mm; least squares weighed by nz², as
    # auto integrates a continuous surface, within a few per cent of masked.
    tablet = clay_tablet((288, 384))
    chosen = integrate_auto(tablet.normals, tablet.mask, pixel_size=tablet.pixel_size)
    assert chosen.method == "masked" and chosen.cut_edges == 0
    assert "no depth step" in chosen.reason and "nz²" in chosen.reason
    weighted = integrate(tablet.normals, "masked", mask=tablet.mask, pixel_size=tablet.pixel_size,
                         steep_weights=True)
    np.testing.assert_array_equal(chosen.height, weighted)
    error = _rmse(chosen.height, tablet.height, tablet.mask)
    masked = integrate(tablet.normals, "masked", mask=tablet.mask, pixel_size=tablet.pixel_size)
    bilateral = integrate(tablet.normals, "bilateral", mask=tablet.mask, pixel_size=tablet.pixel_size)
    assert error < 1.1 * _rmse(masked, tablet.height, tablet.mask)
    assert error < 0.9 * _rmse(bilateral, tablet.height, tablet.mask)


def test_steep_weights_trust_noisy_steep_normals_less():
    # A sphere cap cut at 80° with 1° of normal noise (a gradient moves by up to 0.6 there):
    # least squares weighed by nz² against unweighted. Measured: 0.065 → 0.059 px.
    cap = sphere_cap((128, 128), max_slope_deg=80.0)
    rng = np.random.default_rng(0)
    n = cap.normals + rng.normal(0.0, np.radians(1.0), cap.normals.shape)
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    z = cap.height / cap.pixel_size
    plain = _rmse(integrate(n, "masked", mask=cap.mask), z, cap.mask)
    weighted = _rmse(integrate(n, "masked", mask=cap.mask, steep_weights=True), z, cap.mask)
    assert weighted < 0.95 * plain, (plain, weighted)
    with pytest.raises(ValueError, match="masked"):
        integrate(n, "dct", steep_weights=True)


@pytest.mark.parametrize("surface", [_cap_on_tilted_plane, _tent])
def test_no_edge_is_cut_on_continuous_surfaces(surface):
    z, p, q = surface()
    p, q = _noisy(p, q, 0.005)
    _, info = discontinuity_preserving(p, q, _disk(), return_info=True)
    assert info["cut_edges"] == 0


def test_a_step_is_kept():
    z, p, q = _step()
    p, q = _noisy(p, q, 0.005)
    mask = _disk()
    chosen = integrate_auto(_normals(p, q), mask)
    assert chosen.method == "bilateral" and chosen.cut_edges >= MIN_CUT_EDGES
    assert f"{chosen.cut_edges} edges cut" in chosen.reason
    # Measured: masked 4.64 px, bilateral 0.06 px.
    assert _rmse(chosen.height, z, mask) < 0.5


def test_a_perspective_step_is_kept():
    depth, n = _scissor_step()
    n = n + np.random.default_rng(0).normal(0.0, 0.005, n.shape)
    mask = np.ones((H, W), dtype=bool)
    chosen = integrate_auto(n, mask, intrinsics=CAM, distance=1.0)
    assert chosen.method == "bilateral", chosen.reason
    assert _made(chosen.height, depth, mask) < 1.0  # masked least squares: 6.33 mm


def test_real_cat_keeps_its_occluding_contours():
    normals, mask, camera, depth = _real_object("cat")
    chosen = integrate_auto(normals, mask, intrinsics=camera, distance=1.0)
    assert chosen.method == "bilateral", chosen.reason
    inside = mask & np.isfinite(chosen.height) & np.isfinite(depth)
    assert _made(chosen.height, depth, inside) < 0.3  # masked least squares: 2.24 mm


def test_without_a_mask_or_with_a_large_one():
    z, p, q = _cap_on_tilted_plane()
    n = _normals(p, q)
    assert integrate_auto(n).method == "dct"
    chosen = integrate_auto(n, _disk(), bilateral_pixels=100)
    assert chosen.method == "masked" and chosen.cut_edges is None
    assert "--integrator bilateral" in chosen.reason
