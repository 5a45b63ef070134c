import numpy as np
import pytest

from ptmcore.errors import InputError
from ptmcore.lp import read_lp, write_lp


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
        ("1\na.jpg 1 0 0\n", "horizon"),
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
