import math

import numpy as np
import pytest
from PIL import Image

from reconstruct.calibration.lightcheck import PLOT_MARGIN, check_lights, plot_positions, report_text, write_polar_plot


def sph(elev_deg, azim_deg) -> np.ndarray:
    el, az = np.radians(elev_deg), np.radians(azim_deg)
    el, az = np.broadcast_arrays(el, az)
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)


def synthetic_dome() -> np.ndarray:
    """Four rings (8, 8, 6 and 4 lights) and one light at the zenith: 27 lights."""
    rings = [
        sph(np.full(8, 15.0), np.arange(8) * 45.0),
        sph(np.full(8, 35.0), 22.5 + np.arange(8) * 45.0),
        sph(np.full(6, 55.0), np.arange(6) * 60.0),
        sph(np.full(4, 75.0), 45.0 + np.arange(4) * 90.0),
        sph(np.array([90.0]), np.array([0.0])),
    ]
    return np.vstack(rings)


def ring() -> np.ndarray:
    return sph(np.full(24, 30.0), np.arange(24) * 15.0)


def test_synthetic_dome_numbers():
    r = check_lights(synthetic_dome())
    assert r.count == 27
    assert r.rank.rank == 6 and r.rank.causes == []
    assert r.condition == r.rank.condition and 1 < r.condition < 30
    assert r.elevation_range == pytest.approx((15.0, 90.0))
    np.testing.assert_array_equal(r.elevation_edges, [0, 15, 30, 45, 60, 75, 90])
    np.testing.assert_array_equal(r.elevation_counts, [0, 8, 8, 6, 0, 5])
    # The 15° and 35° rings interleave every 22.5°; the zenith light has no azimuth.
    assert r.azimuth_gap == pytest.approx(22.5)
    assert 0.3 < r.coverage < 0.9
    assert r.warnings == []


def test_ring_numbers():
    r = check_lights(ring())
    assert r.count == 24
    assert r.rank.rank == 5
    np.testing.assert_array_equal(r.elevation_counts, [0, 0, 24, 0, 0, 0])
    assert r.elevation_range == pytest.approx((30.0, 30.0))
    assert r.azimuth_gap == pytest.approx(15.0)
    assert any("all 24 lights at elevation 30.0°" in w for w in r.warnings)
    assert any("rank 5 of 6" in w for w in r.warnings)


def test_coverage_of_one_light_is_its_cap():
    # A cap of angular radius θ has solid angle 2π(1 − cos θ); the hemisphere 2π.
    r = check_lights(sph(np.array([90.0]), np.array([0.0])), coverage_radius=15.0)
    assert r.coverage == pytest.approx(1 - math.cos(math.radians(15)), abs=2e-3)
    r = check_lights(sph(np.array([90.0]), np.array([0.0])), coverage_radius=90.0)
    assert r.coverage == pytest.approx(1.0)


def test_coverage_matches_monte_carlo():
    d = synthetic_dome()
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200_000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p[:, 2] = np.abs(p[:, 2])
    angle = np.degrees(np.arccos(np.clip(p @ d.T, -1, 1))).min(axis=1)
    assert check_lights(d).coverage == pytest.approx(np.mean(angle <= 15.0), abs=5e-3)


def test_gap_and_duplicate_warnings():
    d = sph(np.array([20.0, 40, 60, 30, 50, 25, 40]), np.array([0.0, 30, 60, 90, 120, 45, 0]))
    d = np.vstack([d, d[:1]])
    r = check_lights(d)
    assert r.rank.rank == 6
    assert r.azimuth_gap == pytest.approx(240.0)
    assert r.azimuth_gap_start == pytest.approx(120.0)
    assert any("no light from azimuth 120° to 0° (a gap of 240°)" in w for w in r.warnings)
    assert any("duplicate light directions (photographs 1 and 8)" in w for w in r.warnings)


def test_report_text():
    text = report_text(check_lights(ring()))
    assert text.splitlines()[0].startswith("24 lights, elevation 30.0° to 30.0°")
    assert "30–45°: 24" in text
    assert "rank 5 of 6" in text
    assert "largest azimuth gap 15.0°" in text
    assert "warning: all 24 lights at elevation 30.0°" in text
    assert "no problems found" in report_text(check_lights(synthetic_dome()))


def test_plot_positions_follow_the_project_frame():
    size = 400
    rim = size * (0.5 - PLOT_MARGIN)
    pos = plot_positions(sph(np.array([90.0, 0.0, 30.0, 45.0]), np.array([0.0, 0.0, 90.0, 180.0])), size)
    np.testing.assert_allclose(pos[0], [200, 200], atol=1e-9)  # zenith at the centre
    np.testing.assert_allclose(pos[1], [200 + rim, 200], atol=1e-9)  # from the right: right, on the rim
    np.testing.assert_allclose(pos[2], [200, 200 - rim * 60 / 90], atol=1e-9)  # from the top: up
    np.testing.assert_allclose(pos[3], [200 - rim / 2, 200], atol=1e-9)


def test_polar_plot_png(tmp_path):
    path = tmp_path / "lights.png"
    d = synthetic_dome()
    write_polar_plot(path, d, title="synthetic dome", size=500)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lights.png"]  # no temporary left
    img = np.asarray(Image.open(path).convert("L")).astype(int)
    assert img.shape == (500, 500)
    # Light 1: elevation 15°, azimuth 0° → right of the centre at 75/90 of the rim radius.
    rim = 500 * (0.5 - PLOT_MARGIN)
    x, y = 250 + rim * 75 / 90, 250
    assert img[int(y), int(x)] < 80
    # Every light's centre is dark; the background between them is white.
    for px, py in plot_positions(d, 500):
        assert img[int(py), int(px)] < 80
    assert img[250 + 20, 250 + 110] > 200  # between rings, spokes and lights
    assert img[5, 480] > 240  # empty corner


def test_polar_plot_of_one_light_rejects_tiny_sizes(tmp_path):
    with pytest.raises(ValueError, match="at least 200"):
        write_polar_plot(tmp_path / "x.png", ring(), size=100)


def test_bad_directions():
    with pytest.raises(ValueError, match="shape"):
        check_lights(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="non-zero"):
        check_lights(np.zeros((3, 3)))


@pytest.mark.parametrize("names, expected", [
    (["IMG_0009.JPG", "IMG_0010.JPG", "IMG_0011.JPG"], ["0009", "0010", "0011"]),
    # A shared digit is not cut off a number: 010, 011, not 0, 1.
    (["img_010.tif", "img_011.tif"], ["010", "011"]),
    (["/data/dome/tablet_N_raking.png", "C:\\dome\\tablet_S_raking.png"], ["N", "S"]),
    # Shortening that would leave a label empty keeps the names' stems.
    (["img.jpg", "img2.jpg"], ["img", "img2"]),
    (["only.jpg"], ["only"]),
])
def test_short_labels(names, expected):
    from reconstruct.calibration.lightcheck import short_labels

    assert short_labels(names) == expected


def test_polar_plot_labels_fifty_photographs_by_name_without_overlap():
    """Each light is labelled by its photograph's name, not its position in the .lp, and the
    labels of a 50-light dome do not cover one another."""
    from data_synthetic import dome_lights
    from reconstruct.calibration.lightcheck import _polar_figure

    d = dome_lights(50, seed=3)
    order = np.random.default_rng(0).permutation(50)  # the .lp need not list them in name order
    names = [f"BM_12345_{k + 101:04d}.JPG" for k in order]
    fig = _polar_figure(d, names, "dome", 640)
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    texts = [t for t in ax.texts if t.get_text().isdigit()]
    assert [t.get_text() for t in texts] == [f"{k + 101:04d}" for k in order]
    boxes = [t.get_window_extent(renderer) for t in texts]
    for i, a in enumerate(boxes):
        assert 0 <= a.x0 and a.x1 <= 640 and 0 <= a.y0 and a.y1 <= 640
        for b in boxes[i + 1:]:
            assert not a.overlaps(b), (a, b)


def test_polar_plot_names_must_match_the_lights(tmp_path):
    with pytest.raises(ValueError, match="names"):
        write_polar_plot(tmp_path / "x.png", ring(), names=["a.jpg", "b.jpg"])
