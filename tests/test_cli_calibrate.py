"""``reconstruct calibrate`` and ``reconstruct run`` on a capture with spheres and no .lp."""

import json

import numpy as np
import pytest


from helpers import run_cli as _run
from ptmcore.lp import read_lp


@pytest.fixture(scope="module")
def sphere_capture(tmp_path_factory):
    from data_synthetic.spheres import render_sphere_capture

    root = tmp_path_factory.mktemp("spheres")
    info = render_sphere_capture(root / "cap", n_lights=16, hidden=(3,), seed=2)
    # Only the photographs stay in the capture folder: the truth goes beside it.
    for name in ("truth.lp", "truth.npy"):
        if (root / "cap" / name).exists():
            (root / "cap" / name).rename(root / name)
    return info, root


def test_calibrate_writes_an_lp_close_to_the_truth(sphere_capture, tmp_path, capsys):
    info, root = sphere_capture
    lp = tmp_path / "lights.lp"
    code, stdout, err = _run(["calibrate", root / "cap", "-o", lp, "--diagnostic", tmp_path / "d.png"], capsys)
    assert code == 0, err
    assert "img_003" in stdout and (tmp_path / "d.png").exists() and (tmp_path / "d_lights.png").exists()
    lights = read_lp(lp)
    truth = np.load(root / "truth.npy")
    names = [p.name for p in sorted((root / "cap").iterdir())]
    expected = truth[[names.index(p.name) for p in lights.paths]]
    err_deg = np.degrees(np.arccos(np.clip((lights.directions * expected).sum(axis=1), -1, 1)))
    assert len(lights) == 15 and err_deg.mean() < 0.5 and err_deg.max() < 2.0


def test_run_without_lp_calibrates_and_masks_the_spheres(sphere_capture, tmp_path, capsys):
    info, root = sphere_capture
    out = tmp_path / "out"
    code, stdout, err = _run(["run", root / "cap", "-o", out, "-q"], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["layout"] == "capture with spheres (calibrated)"
    assert report["inputs"]["photographs"] == 15
    import tifffile

    height = tifffile.imread(out / "height.tif")
    cx, cy, r = info.spheres[0]
    assert np.isnan(height[int(cy), int(cx)])  # the sphere is not part of the surface


def test_bad_sphere_hint(sphere_capture, tmp_path, capsys):
    _, root = sphere_capture
    code, _, err = _run(["calibrate", root / "cap", "-o", tmp_path / "l.lp", "--sphere", "1,2"], capsys)
    assert code == 2 and "--sphere" in err
