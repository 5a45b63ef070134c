"""``reconstruct integrate``: normal maps made elsewhere into height maps and meshes."""

import numpy as np
import pytest
import tifffile
from PIL import Image


from helpers import sphere_normals, run_cli as _run


@pytest.fixture(scope="module")
def sphere_maps(tmp_path_factory):
    folder = tmp_path_factory.mktemp("maps")
    n, mask = sphere_normals(64, 80, 28.0)
    n16 = np.round((n + 1) * 32767.5).astype(np.uint16)
    tifffile.imwrite(folder / "n16.tif", n16, photometric="rgb")
    n8 = np.round((n + 1) * 127.5).astype(np.uint8)
    n8[~mask] = 0  # a black background, as many tools write it
    Image.fromarray(n8).save(folder / "n8.png")
    Image.fromarray(n8).save(folder / "normals.jpg", quality=95)
    np.save(folder / "n.npy", n)
    return folder, n, mask


@pytest.mark.parametrize("name", ["n16.tif", "n8.png", "normals.jpg", "n.npy"])
def test_every_kind_of_normal_map_integrates_to_the_sphere(tmp_path, capsys, sphere_maps, name):
    folder, n, mask = sphere_maps
    out = tmp_path / "out"
    code, stdout, err = _run(["integrate", folder / name, "-o", out, "-q"], capsys)
    assert code == 0, err
    height = tifffile.imread(out / "height.tif")
    assert height.shape == (64, 80)
    # The sphere bulges towards the camera: centre above the inner rim, whatever the encoding.
    assert height[32, 40] > height[32, 16] + 5
    if name == "n8.png":
        assert np.isnan(height[0, 0])  # the black background is outside the object
    assert (out / "mesh.obj").exists() and (out / "report.json").exists()


def test_integrate_bad_inputs(tmp_path, capsys):
    code, _, err = _run(["integrate", tmp_path / "none.png", "-o", tmp_path / "o"], capsys)
    assert code == 2 and "not found" in err
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(tmp_path / "grey.png")
    code, _, err = _run(["integrate", tmp_path / "grey.png", "-o", tmp_path / "o"], capsys)
    assert code == 2 and "three channels" in err
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "black.png")
    code, _, err = _run(["integrate", tmp_path / "black.png", "-o", tmp_path / "o"], capsys)
    assert code == 2 and "no valid normal" in err


def test_run_with_auto_mask_flattening_decimation_solid_and_glb(tmp_path, capsys):
    import json

    import trimesh

    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(90, 120), n_lights=24, seed=6)
    out = tmp_path / "out"
    code, _, err = _run(["run", info.folder, "-o", out, "--pixel-size", info.pixel_size, "--mask", "auto",
                         "--flatten", "plane", "--decimate", "3000", "--solid", "2", "--glb", "-q"], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert report["inputs"]["mask"] == "automatic"
    truth = np.asarray(Image.open(info.ground_truth_dir / "mask.png")) > 0
    found = np.asarray(Image.open(out / "mask.png")) > 0
    assert (found & truth).sum() / (found | truth).sum() > 0.95
    assert np.isnan(tifffile.imread(out / "height.tif")[~found]).all()
    # Quadric decimation stops within a few triangles of its target.
    assert abs(report["mesh"]["faces"] - 3000) <= 30 and report["mesh"]["decimation"]["max_error"] > 0
    solid = trimesh.load(out / "solid.stl")
    assert solid.is_watertight and solid.volume > 0
    scene = trimesh.load(out / "mesh.glb")
    assert len(scene.geometry) == 1


def test_run_rejects_conflicting_mesh_options(tmp_path, capsys):
    from data_synthetic import write_capture

    info = write_capture(tmp_path / "cap", "tablet", shape=(40, 50), n_lights=12, seed=6)
    code, _, err = _run(["run", info.folder, "-o", tmp_path / "o", "--decimate", "100", "--max-error", "0.1"], capsys)
    assert code == 2 and "not both" in err


def test_auto_integrator_follows_the_mask_and_the_normals(tmp_path, capsys, sphere_maps):
    import json

    folder, _, _ = sphere_maps
    # A sphere inside its outline has no depth step: with the mask, auto tries bilateral
    # integration, which cuts no edge, and integrates by least squares on the mask.
    for name, extra, used, why in [
            ("plain", [], "dct", "no mask"),
            ("masked", ["--mask", folder / "n8.png"], "masked", "no depth step (0 edges cut"),
            ("bilateral", ["--integrator", "bilateral"], "bilateral", "chosen"),
            ("least-squares", ["--mask", folder / "n8.png", "--integrator", "masked"], "masked", "chosen")]:
        out = tmp_path / name
        code, _, err = _run(["integrate", folder / "n16.tif", "-o", out, "-q", *extra], capsys)
        assert code == 0, err
        mesh = json.loads((out / "report.json").read_text())["mesh"]
        assert mesh["integrator"] == used and why in mesh["integrator_reason"]


def test_perspective_camera_option(tmp_path, capsys, sphere_maps):
    import json

    folder, _, _ = sphere_maps
    out = tmp_path / "persp"
    code, _, err = _run(["integrate", folder / "n16.tif", "-o", out, "--intrinsics", "80,80,39.5,31.5",
                         "--distance", "250", "-q"], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    assert report["height_unit"] == "mm" and report["parameters"]["intrinsics"] == "80,80,39.5,31.5"
    code, _, err = _run(["integrate", folder / "n16.tif", "-o", tmp_path / "x", "--intrinsics", "80,80,1"], capsys)
    assert code == 2 and "--intrinsics" in err
    code, _, err = _run(["integrate", folder / "n16.tif", "-o", tmp_path / "x", "--intrinsics", "80,80,1,1",
                         "--integrator", "fc"], capsys)
    assert code == 2 and "perspective" in err
