import numpy as np
import pytest

from ptmcore.errors import InputError
from ptmcore.lp import HORIZON_CLAMP_DEG, MIN_ELEVATION_DEG, read_lp, write_lp


def _write(tmp_path, text, name="lights.lp"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_reads_names_with_spaces_windows_paths_and_normalises(tmp_path):
    p = _write(
        tmp_path,
        "3\n"
        "img 000.jpg 0.5 0 0.8660254\n"
        "C:\\Users\\me\\capture\\img_001.jpg -0.5 0.0 0.8660254\n"
        "sub/img_002.jpg 0 1 1\n",
    )
    lights = read_lp(p)
    assert [q.name for q in lights.paths] == ["img 000.jpg", "img_001.jpg", "img_002.jpg"]
    assert lights.paths[0] == tmp_path / "img 000.jpg"
    assert lights.paths[1] == tmp_path / "img_001.jpg"
    assert lights.paths[2] == tmp_path / "sub" / "img_002.jpg"
    np.testing.assert_allclose(np.linalg.norm(lights.directions, axis=1), 1.0)
    np.testing.assert_allclose(lights.directions[2], [0, 2**-0.5, 2**-0.5])


def test_round_trip(tmp_path):
    d = np.array([[0.6, 0.0, 0.8], [0.0, -0.6, 0.8], [0.0, 0.0, 1.0]])
    write_lp(tmp_path / "a.lp", ["a.png", "b.png", "c.png"], d)
    lights = read_lp(tmp_path / "a.lp")
    np.testing.assert_allclose(lights.directions, d, atol=1e-6)


def test_reads_hp_fixture(shared_fixture):
    lights = read_lp(shared_fixture / "reference_8x5.lp")
    assert len(lights) == 12
    assert all(p.exists() for p in lights.paths)


@pytest.mark.parametrize(
    "text, message",
    [
        ("", "empty"),
        ("three\na.jpg 0 0 1\n", "number of photographs"),
        ("2\na.jpg 0 0 1\n", "declares 2 photographs but lists 1"),
        ("1\na.jpg 0 zero 1\n", "not three numbers"),
        ("1\na.jpg 0 1\n", "expected 'filename x y z'"),
        ("1\na.jpg 0 0 0\n", "zero length"),
        ("1\na.jpg 1 0 -0.2\n", "below the horizon"),
        ("1\na.jpg 0.5 0 -0.8\n", "horizon"),
        ("1\na.jpg nan 0 1\n", "not three numbers"),
        ("1\na.jpg 1e999 0 1\n", "not finite"),
    ],
)
def test_malformed_files_name_the_problem(tmp_path, text, message):
    p = _write(tmp_path, text)
    with pytest.raises(InputError, match=message) as exc:
        read_lp(p)
    assert str(p) in str(exc.value)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_lp(tmp_path / "nope.lp")


def test_a_light_just_below_the_horizon_is_raised_to_a_grazing_one_with_a_warning(tmp_path):
    # A hand-held capture's sphere put one light 0.1° below the horizon: the capture is used,
    # that light raised to the lowest elevation used, its azimuth kept, and named.
    below = np.radians(-0.1)
    azimuth = np.radians(30.0)
    vec = (np.cos(below) * np.cos(azimuth), np.cos(below) * np.sin(azimuth), np.sin(below))
    text = "4\na.jpg 0 0 1\nb.jpg 0.5 0 0.866\nc.jpg 0 0.5 0.866\nd.jpg {:.6f} {:.6f} {:.6f}\n".format(*vec)
    lights = read_lp(_write(tmp_path, text))
    d = lights.directions[3]
    assert np.degrees(np.arcsin(d[2])) == pytest.approx(MIN_ELEVATION_DEG, abs=1e-6)
    assert np.degrees(np.arctan2(d[1], d[0])) == pytest.approx(30.0, abs=1e-4)
    assert np.linalg.norm(d) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(lights.directions[:3, 2], [1.0, 0.866, 0.866], atol=1e-3)
    (warning,) = [w for w in lights.warnings if "horizon" in w]
    assert "line 5" in warning and "'d.jpg'" in warning and "-0.10°" in warning


def test_a_light_well_below_the_horizon_is_still_refused(tmp_path):
    low = np.radians(-HORIZON_CLAMP_DEG - 0.5)
    text = f"3\na.jpg 0 0 1\nb.jpg 0.5 0 0.866\nc.jpg {np.cos(low):.6f} 0 {np.sin(low):.6f}\n"
    with pytest.raises(InputError, match="line 4.*below the horizon"):
        read_lp(_write(tmp_path, text))
