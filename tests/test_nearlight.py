"""Near lights: triangulation from two spheres, per-pixel light fields, near PS and PTM fit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from helpers import stack_from_luminance

from data_synthetic.nearlight import render_nearlight_capture
from data_synthetic.spheres import render_sphere_capture
from ptmcore.errors import InputError
from ptmcore.fit import light_matrix
from ptmcore.images import load_stack
from ptmcore.nearlight import (
    fit_ptm_near,
    light_field,
    near_photometric_stereo,
    read_light_positions,
    typical_distance,
    write_light_positions,
)
from ptmcore.normals import angular_error, photometric_stereo
from reconstruct.surface.accuracy import load_ground_truth
from reconstruct.calibration.calibrate import Calibration, calibrate_stack
from reconstruct.calibration.triangulate import (
    BEHIND,
    OK,
    PARALLEL,
    TOO_FEW,
    lights_are_near,
    triangulate,
)

SPHERES = [(60.0, 50.0, 40.0), (420.0, 300.0, 45.0)]


def _exact_highlight(light: np.ndarray, sphere, height: float) -> tuple[float, float]:
    """Image position of the mirror highlight of a point light on a sphere (orthographic)."""
    cx, cy, r = sphere
    centre = np.array([cx, -cy, height])
    s = np.array([0.0, 0.0, 1.0])
    for _ in range(200):  # fixed point: s bisects the view and the direction to the light
        l = light - (centre + r * s)
        half = l / np.linalg.norm(l) + [0.0, 0.0, 1.0]
        s = half / np.linalg.norm(half)
    return cx + r * s[0], cy - r * s[1]


def _calibration(lights: np.ndarray, spheres=SPHERES, heights=None, missing=()) -> Calibration:
    heights = [s[2] for s in spheres] if heights is None else heights
    m, n = len(spheres), len(lights)
    hl = np.array([[_exact_highlight(p, s, hc) for p in lights] for s, hc in zip(spheres, heights)])
    conf = np.ones((m, n))
    for i, k in missing:
        hl[i, k] = np.nan
        conf[i, k] = 0.0
    nan = np.full((n, 3), np.nan)
    return Calibration(directions=nan, confidence=np.zeros(n), sphere_directions=np.full((m, n, 3), np.nan),
                       sphere_confidence=conf, highlights=hl, disagreement_deg=np.full(n, np.nan),
                       spheres=list(spheres), names=[f"img_{k}" for k in range(n)])


LIGHTS = np.array([[240.0, -180.0, 600.0], [-300.0, 100.0, 350.0], [900.0, -700.0, 250.0]])


def test_triangulation_of_exact_rays_recovers_the_light():
    tri = triangulate(_calibration(LIGHTS))
    assert tri.status == [OK] * 3
    np.testing.assert_allclose(tri.positions, LIGHTS, atol=1e-6)
    assert np.all(tri.residual < 1e-6)
    assert np.all(tri.rays == 2)


def test_triangulation_uses_given_sphere_heights():
    heights = [40.0, 120.0]  # the second sphere stands on a pedestal
    tri = triangulate(_calibration(LIGHTS, heights=heights), heights=heights)
    np.testing.assert_allclose(tri.positions, LIGHTS, atol=1e-6)
    # Assuming both rest on the plane misplaces the light and the rays no longer meet (or
    # meet behind a sphere, which is reported).
    wrong = triangulate(_calibration(LIGHTS, heights=heights))
    ok = wrong.usable
    assert ok.sum() >= 2 and wrong.status[2] == BEHIND
    assert np.linalg.norm(wrong.positions[ok] - LIGHTS[ok], axis=1).min() > 10


def test_distant_and_half_seen_lights_are_flagged_not_invented():
    far = np.array([[1e8, 2e7, 9e7], [240.0, -180.0, 600.0]])
    tri = triangulate(_calibration(far, missing=[(1, 1)]))
    assert tri.status == [PARALLEL, TOO_FEW]
    assert np.isnan(tri.positions).all()
    assert not tri.usable.any()
    assert tri.angle_deg[0] < 1.0 and np.isnan(tri.angle_deg[1])
    assert not lights_are_near(tri, (384, 512))


def test_light_positions_round_trip(tmp_path):
    names = ["img 000.png", "a,b.png", "c.tif"]
    path = tmp_path / "lights.csv"
    write_light_positions(path, names, LIGHTS)
    got_names, got = read_light_positions(path)
    assert got_names == names
    np.testing.assert_allclose(got, LIGHTS, atol=1e-4)
    assert path.read_text().splitlines()[0] == "name,x,y,z"
    with pytest.raises(ValueError):
        write_light_positions(path, names[:2], np.array([[0.0, 0, 1], [np.nan, 0, 1]]))


@pytest.mark.parametrize("text", [
    "",
    "img,x,y,z\na.png,1,2,3\n",
    "name,x,y,z\n",
    "name,x,y,z\na.png,1,2\n",
    "name,x,y,z\na.png,1,two,3\n",
    "name,x,y,z\na.png,1,2,nan\n",
    "name,x,y,z\na.png,1,2,-5\n",
    "name,x,y,z\n,1,2,3\n",
])
def test_malformed_light_positions_are_input_errors(tmp_path, text):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(InputError):
        read_light_positions(path)
    with pytest.raises(InputError):
        read_light_positions(tmp_path / "missing.csv")


def test_light_field_matches_the_direct_formula():
    rows, width = slice(5, 9), 7
    heights = np.random.default_rng(0).uniform(0, 3, (4, width))
    dirs, fall = light_field(LIGHTS, rows, width, reference_distance=500.0, heights=heights)
    assert dirs.shape == (3, 4, width, 3) and fall.shape == (3, 4, width)
    assert dirs.dtype == np.float32 and fall.dtype == np.float32
    r, c = np.mgrid[5:9, 0:width]
    for k, p in enumerate(LIGHTS):
        d = p - np.stack([c, -r, heights], axis=-1)
        dist = np.linalg.norm(d, axis=-1)
        np.testing.assert_allclose(dirs[k], d / dist[..., None], atol=1e-6)
        np.testing.assert_allclose(fall[k], (500.0 / dist) ** 2, rtol=1e-5)


def test_fit_ptm_near_reproduces_a_known_ptm():
    h, w = 12, 10
    rng = np.random.default_rng(3)
    positions = np.array([[5 + 400 * np.cos(a), -6 + 400 * np.sin(a), z]
                          for a, z in zip(rng.uniform(0, 2 * np.pi, 20), rng.uniform(150, 500, 20))])
    coef = rng.uniform(-0.1, 0.1, (h, w, 6)).astype(np.float32)
    coef[..., 5] += 0.4
    dirs, fall = light_field(positions, slice(0, h), w, reference_distance=300.0)
    basis = light_matrix(dirs.reshape(-1, 3)).reshape(20, h, w, 6)
    values = np.einsum("nhwk,hwk->nhw", basis, coef) * fall
    assert 0.02 < values.min() and values.max() < 1  # no clipping in the stored stack
    ptm = fit_ptm_near(stack_from_luminance(values), positions, reference_distance=300.0)
    np.testing.assert_allclose(ptm.coefficients, coef, atol=2e-4)
    # The fitted PTM, relit with each pixel's own lights, gives back the observations.
    assert np.abs(np.einsum("nhwk,hwk->nhw", basis, ptm.coefficients) * fall - values).max() < 1e-3


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("nearlight")
    info = render_nearlight_capture(out, shape=(200, 260), n_lights=16, seed=2, encoding="tiff16")
    return info, load_stack(info.image_paths), load_ground_truth(info.ground_truth_dir)


def test_capture_files(capture):
    info, _, truth = capture
    names, pos = read_light_positions(info.positions_csv)
    assert names == [p.name for p in info.image_paths]
    np.testing.assert_allclose(pos, info.positions, atol=1e-3)
    assert truth.normals.shape == (200, 260, 3) and truth.mask.shape == (200, 260)
    # The spheres are outside the object's mask, the rest of the frame inside.
    for cx, cy, r in info.spheres:
        assert not truth.mask[int(cy), int(cx)]
    assert 0.6 < truth.mask.mean() < 0.9
    dist = np.linalg.norm(info.positions - [129.5, -99.5, 0.0], axis=1)
    assert dist.min() >= 260 - 1e-6 and dist.max() <= 520 + 1e-6


def test_near_ps_with_true_positions_is_exact_without_noise(tmp_path):
    info = render_nearlight_capture(tmp_path, shape=(96, 128), n_lights=12, seed=5,
                                    encoding="tiff16", noise=0.0)
    stack, truth = load_stack(info.image_paths), load_ground_truth(info.ground_truth_dir)
    heights = np.load(info.ground_truth_dir / "height.npy") / info.pixel_size
    res = near_photometric_stereo(stack, info.positions, heights=heights)
    err = angular_error(res.normals, truth.normals, truth.mask)
    # Only 16-bit quantisation is left: measured mean 0.0003°, max 0.02°.
    assert err.mean() < 0.01 and err.max() < 0.2
    assert res.valid[truth.mask].all()


def test_near_ps_with_true_positions_recovers_normals(capture):
    info, stack, truth = capture
    heights = np.load(info.ground_truth_dir / "height.npy") / info.pixel_size
    res = near_photometric_stereo(stack, info.positions, heights=heights)
    err = angular_error(res.normals, truth.normals, truth.mask)
    # Sensor noise 0.003 limits it: measured mean 0.18°, 99th percentile 0.53°.
    assert err.mean() < 0.3 and np.percentile(err, 99) < 0.9
    # On the base plane (relief of up to ~10 px neglected): measured mean 0.28°.
    flat = angular_error(near_photometric_stereo(stack, info.positions).normals, truth.normals, truth.mask)
    assert flat.mean() < 0.5


def test_calibrate_triangulate_near_ps_halves_the_error(capture):
    info, stack, truth = capture
    cal = calibrate_stack(stack, disagreement_tol_deg=180.0)
    tri = triangulate(cal)
    assert tri.usable.all()
    err = np.linalg.norm(tri.positions - info.positions, axis=1)
    dist = np.linalg.norm(info.positions - [129.5, -99.5, 0.0], axis=1)
    assert np.median(err / dist) < 0.02
    assert lights_are_near(tri, stack.shape)
    distant = photometric_stereo(stack, cal.directions)
    near = near_photometric_stereo(stack, tri.positions)
    e_far = angular_error(distant.normals, truth.normals, truth.mask).mean()
    e_near = angular_error(near.normals, truth.normals, truth.mask).mean()
    assert e_near <= 0.5 * e_far
    assert e_near < 1.5
    assert typical_distance(tri.positions, stack.shape) == pytest.approx(
        typical_distance(info.positions, stack.shape), rel=0.03)


def test_distant_sphere_capture_is_not_near(tmp_path):
    info = render_sphere_capture(tmp_path, n_lights=8, seed=0)
    cal = calibrate_stack(load_stack(info.image_paths), spheres=list(info.spheres))
    tri = triangulate(cal)
    assert not lights_are_near(tri, info.shape)
    assert all(s != OK for s in tri.status)


# --------------------------------------------------------------------------- the pipeline


def _spheres_only(info, folder):
    """The capture's photographs and ground truth without its .lp: a highlight-RTI capture."""
    import shutil

    folder.mkdir()
    for p in info.image_paths:
        shutil.copy(p, folder / p.name)
    shutil.copytree(info.ground_truth_dir, folder / "ground_truth")
    return folder


def test_run_without_lp_triangulates_near_lights(capture, tmp_path, capsys):
    from helpers import run_cli

    info = capture[0]
    cap = _spheres_only(info, tmp_path / "cap")
    code, _, err = run_cli(["run", cap, "-o", tmp_path / "near"], capsys)
    assert code == 0, err
    import json

    near = json.loads((tmp_path / "near" / "report.json").read_text())
    assert near["light_model"]["type"] == "near"
    names, pos = read_light_positions(tmp_path / "near" / "light_positions.csv")
    assert len(names) == len(info.image_paths)
    assert np.median(np.linalg.norm(pos - info.positions, axis=1)) < 0.02 * 260

    # Against the true directions from the image centre, one per photograph (what an .lp holds).
    import shutil

    shutil.copy(info.folder / "truth.lp", cap / "lights.lp")
    code, _, err = run_cli(["run", cap, "-o", tmp_path / "far", "--light-positions", "none"], capsys)
    assert code == 0, err
    far = json.loads((tmp_path / "far" / "report.json").read_text())
    assert far["light_model"]["type"] == "distant"
    e_near = near["accuracy"]["normals"]["mean_deg"]
    e_far = far["accuracy"]["normals"]["mean_deg"]
    assert e_near <= 0.5 * e_far and e_near < 1.5


def test_run_with_lp_uses_the_positions_beside_it(capture, tmp_path, capsys):
    import json
    import shutil

    from helpers import run_cli

    info = capture[0]
    cap = _spheres_only(info, tmp_path / "cap")
    shutil.copy(info.folder / "truth.lp", cap / "lights.lp")
    shutil.copy(info.positions_csv, cap / "light_positions.csv")
    code, _, err = run_cli(["run", cap, "-o", tmp_path / "out", "--mask", cap / "ground_truth" / "mask.png"], capsys)
    assert code == 0, err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["light_model"]["type"] == "near"
    assert report["accuracy"]["normals"]["mean_deg"] < 1.0

    # A photograph of the .lp without a position: one line naming the file, exit 2.
    lines = (cap / "light_positions.csv").read_text().splitlines()
    (cap / "light_positions.csv").write_text("\n".join(lines[:-1]) + "\n")
    code, _, err = run_cli(["run", cap, "-o", tmp_path / "bad"], capsys)
    assert code == 2 and "light_positions.csv" in err and "no light position" in err
    assert len(err.strip().splitlines()) == 1


def test_calibrate_writes_near_light_files_that_run_uses(capture, tmp_path, capsys):
    import json

    from helpers import run_cli

    info = capture[0]
    cap = _spheres_only(info, tmp_path / "cap")
    code, out, err = run_cli(["calibrate", cap, "-o", cap / "lights.lp", "--diagnostic", tmp_path / "cal.png"], capsys)
    assert code == 0, err
    assert "near lights" in out and (cap / "light_positions.csv").is_file()
    names, pos = read_light_positions(cap / "light_positions.csv")
    lp_names = [line.split()[0] for line in (cap / "lights.lp").read_text().splitlines()[1:]]
    assert names == lp_names == [p.name for p in info.image_paths]
    assert np.median(np.linalg.norm(pos - info.positions, axis=1)) < 0.02 * 260
    assert (tmp_path / "cal.png").is_file() and (tmp_path / "cal_lights.png").is_file()

    code, _, err = run_cli(["run", cap, "-o", tmp_path / "out"], capsys)
    assert code == 0, err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["light_model"]["type"] == "near"
    assert report["light_model"]["source"].endswith("light_positions.csv")


def test_near_albedo_without_photometric_stereo(capture):
    from ptmcore.nearlight import near_lambertian_albedo

    info, stack, truth = capture
    ps = near_photometric_stereo(stack, info.positions)
    albedo = near_lambertian_albedo(stack, info.positions, ps.normals)
    # Given PS's own normals it is PS's albedo (PS also drops the darkest samples).
    m = truth.mask & ps.valid
    np.testing.assert_allclose(albedo[m], ps.albedo[m], rtol=0.02)
    with pytest.raises(ValueError, match="normals"):
        near_lambertian_albedo(stack, info.positions, ps.normals[:-1])


def test_sphere_lights_of_a_near_capture(capture):
    from reconstruct.calibration.triangulate import near_lights, sphere_lights

    info, stack, _ = capture
    found = sphere_lights(stack)
    cal = found.calibration
    assert cal.shape == stack.shape
    tri = near_lights(cal)
    assert found.triangulation is not None and tri is not None
    np.testing.assert_array_equal(found.usable, tri.usable)
    np.testing.assert_allclose(found.positions, tri.positions[tri.usable])
    assert found.names == [n for n, ok in zip(cal.names, tri.usable) if ok]
    assert len(found.left_out) == int((~tri.usable).sum())
    distant = sphere_lights(stack, near=False)
    assert distant.triangulation is None and distant.positions is None
    np.testing.assert_array_equal(distant.directions, cal.directions[cal.usable])


def test_near_ptm_normals_get_an_albedo_without_photometric_stereo(capture):
    from ptmcore.nearlight import near_lambertian_albedo
    from ptmcore.normals import normals_from_ptm
    from reconstruct.pipeline import Capture, NearLights, RunOptions, estimate_normals

    info, stack, truth = capture
    calls = []
    loaded = Capture(Path("capture"), "capture with .lp", stack, lights=None, near=NearLights(info.positions, "truth"))
    found = estimate_normals(loaded, RunOptions(normals="ptm"), progress=calls.append)
    normals, albedo, undetermined = found.normals, found.albedo, found.undetermined
    want = normals_from_ptm(fit_ptm_near(stack, info.positions).coefficients)
    np.testing.assert_allclose(normals, want, atol=1e-6)
    np.testing.assert_allclose(albedo, near_lambertian_albedo(stack, info.positions, want), rtol=1e-5)
    assert undetermined == 0 and calls  # the PTM fit reports its progress
    assert angular_error(normals, truth.normals, truth.mask).mean() < 5.0
