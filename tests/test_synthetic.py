"""Tests of the synthetic capture generator: determinism, formats, ground-truth consistency."""

from __future__ import annotations

import filecmp
import json
import re
from pathlib import Path

import numpy as np
import pytest
import tifffile
import trimesh
from PIL import Image
from scipy import ndimage

from data_synthetic import (
    SCENES,
    Surface,
    cast_shadow_mask,
    clay_tablet,
    dome_lights,
    render,
    ring_lights,
    sphere_cap,
    write_capture,
)
from data_synthetic.__main__ import main
from data_synthetic.encoding import write_jpeg8
from ptmcore.errors import InputError

SHAPE = (64, 96)


def srgb_reference(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 encoding, written out independently of the package."""
    linear = np.asarray(linear, dtype=np.float64)
    return np.where(linear <= 0.0031308, 12.92 * linear,
                    1.055 * np.abs(linear) ** (1 / 2.4) - 0.055)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors along the last axis."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def fd_normals(height: np.ndarray, pixel_size: float) -> np.ndarray:
    """Central-difference normals of the interior pixels, straight from the conventions."""
    h = height.astype(np.float64)
    dz_dx = (h[1:-1, 2:] - h[1:-1, :-2]) / (2 * pixel_size)
    dz_dy = -(h[2:, 1:-1] - h[:-2, 1:-1]) / (2 * pixel_size)  # y up, rows down
    return np.stack([-dz_dx, -dz_dy, np.ones_like(dz_dx)], axis=-1)


def read_lp(path: Path) -> tuple[list[str], np.ndarray]:
    lines = path.read_text().splitlines()
    n = int(lines[0])
    names, dirs = [], []
    for line in lines[1:]:
        name, *xyz = line.split()
        names.append(name)
        dirs.append([float(v) for v in xyz])
    assert len(names) == n
    return names, np.array(dirs)


@pytest.fixture(scope="module")
def tablet_capture(tmp_path_factory: pytest.TempPathFactory):
    out = tmp_path_factory.mktemp("tablet") / "capture"
    return write_capture(out, "tablet", SHAPE, 12, "tiff16", seed=3)


def test_same_seed_gives_identical_files(tmp_path: Path, tablet_capture) -> None:
    again = write_capture(tmp_path / "again", "tablet", SHAPE, 12, "tiff16", seed=3)
    first = sorted(p.relative_to(tablet_capture.folder)
                   for p in tablet_capture.folder.rglob("*") if p.is_file())
    second = sorted(p.relative_to(again.folder) for p in again.folder.rglob("*") if p.is_file())
    assert first == second
    _, mismatch, errors = filecmp.cmpfiles(tablet_capture.folder, again.folder,
                                           [str(p) for p in first], shallow=False)
    assert mismatch == [] and errors == []

    other = write_capture(tmp_path / "other", "tablet", SHAPE, 12, "tiff16", seed=4)
    assert not np.array_equal(np.load(other.ground_truth_dir / "height.npy"),
                              np.load(tablet_capture.ground_truth_dir / "height.npy"))


def test_capture_layout_and_lp_format(tablet_capture) -> None:
    folder, gt = tablet_capture.folder, tablet_capture.ground_truth_dir
    assert tablet_capture.lp_path == folder / "lights.lp"
    assert gt == folder / "ground_truth"
    assert tablet_capture.shape == SHAPE
    assert tablet_capture.pixel_size == pytest.approx(80.0 / 96)
    expected_images = [f"img_{i:03d}.tif" for i in range(12)]
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        expected_images + ["lights.lp", "scan.ply", "ground_truth"])
    assert sorted(p.name for p in gt.iterdir()) == sorted(
        ["normals.npy", "height.npy", "albedo.npy", "mask.png", "scene.json",
         "scan_transform.txt"])

    lines = tablet_capture.lp_path.read_text().split("\n")
    assert lines[0] == "12" and lines[-1] == "" and len(lines) == 14
    pattern = re.compile(r"^img_\d{3}\.tif( -?\d+\.\d{6}){3}$")
    assert all(pattern.match(line) for line in lines[1:-1])
    names, dirs = read_lp(tablet_capture.lp_path)
    assert names == expected_images
    np.testing.assert_allclose(dirs, dome_lights(12), atol=1e-6)

    image = tifffile.imread(folder / names[0])
    assert image.shape == (*SHAPE, 3) and image.dtype == np.uint16
    normals = np.load(gt / "normals.npy")
    assert normals.shape == (*SHAPE, 3) and normals.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-5)
    assert np.load(gt / "height.npy").dtype == np.float32
    albedo = np.load(gt / "albedo.npy")
    assert albedo.shape == (*SHAPE, 3) and albedo.dtype == np.float32
    assert 0 <= albedo.min() and albedo.max() <= 1
    with Image.open(gt / "mask.png") as mask_image:
        assert mask_image.mode == "L"
        mask = np.asarray(mask_image)
    assert set(np.unique(mask)) == {0, 255}

    scene = json.loads((gt / "scene.json").read_text())
    assert scene["scene"] == "tablet" and scene["shape"] == list(SHAPE)
    assert scene["seed"] == 3 and scene["encoding"] == "tiff16"
    assert scene["lights"]["count"] == 12
    assert scene["pixel_size_mm"] == pytest.approx(tablet_capture.pixel_size)
    assert set(scene["render"]) >= {"specular", "shininess", "cast_shadows", "ambient", "noise"}
    np.testing.assert_array_equal(np.loadtxt(gt / "scan_transform.txt"),
                                  np.array(scene["scan_transform"]))


@pytest.mark.parametrize("name", sorted(SCENES))
def test_normals_agree_with_height_finite_differences(name: str) -> None:
    surface = SCENES[name]((96, 128), pixel_size=0.5, seed=1)
    assert surface.name == name and surface.pixel_size == 0.5
    assert surface.height.dtype == surface.normals.dtype == surface.albedo.dtype == np.float32
    fd = fd_normals(surface.height, surface.pixel_size)
    stored = surface.normals[1:-1, 1:-1]
    # The sphere's analytic normals jump at the rim, where differences straddle the kink.
    inside = ndimage.binary_erosion(surface.mask, iterations=2)[1:-1, 1:-1]
    outside = ~ndimage.binary_dilation(surface.mask, iterations=2)[1:-1, 1:-1]
    errors = angle_deg(fd, stored)
    assert inside.sum() > 0.2 * inside.size
    assert np.median(errors[inside]) < 0.05
    assert np.percentile(errors[inside], 99) < 0.5
    assert errors[outside].max() < 1e-3


def test_normals_follow_the_frame_convention() -> None:
    tablet = clay_tablet(SHAPE, seed=0)
    rows, cols = np.nonzero(tablet.mask)
    mid_row, mid_col = SHAPE[0] // 2, SHAPE[1] // 2
    # The rim slopes down away from the tablet: right edge faces +x, top edge faces +y.
    right_rim = tablet.normals[mid_row, cols.max() - 1]
    top_rim = tablet.normals[rows.min() + 1, mid_col]
    assert right_rim[0] > 0.2 and abs(right_rim[1]) < 0.1
    assert top_rim[1] > 0.2 and abs(top_rim[0]) < 0.1
    assert tablet.height[tablet.mask].min() >= 0 and tablet.height[~tablet.mask].max() == 0
    assert np.degrees(np.arccos(tablet.normals[..., 2].min())) < 60

    sphere = sphere_cap(SHAPE)
    centre = np.array(SHAPE) // 2
    np.testing.assert_allclose(sphere.normals[centre[0], centre[1]], [0, 0, 1], atol=0.05)
    assert sphere.normals[centre[0] - 10, centre[1], 1] > 0.3  # above the centre: faces up
    assert sphere.normals[centre[0], centre[1] + 10, 0] > 0.3  # right of it: faces right
    assert np.degrees(np.arccos(sphere.normals[..., 2].min())) <= 70.01


def test_lambertian_fit_of_16bit_images_recovers_ground_truth_normals(tmp_path: Path) -> None:
    info = write_capture(tmp_path / "lambert", "tablet", SHAPE, 48, "tiff16", seed=0,
                         cast_shadows=False, specular=0.0, noise=0.0)
    names, lights = read_lp(info.lp_path)
    stack = np.stack([tifffile.imread(info.folder / n) for n in names]).astype(np.float64)
    intensity = stack.mean(axis=-1) / 65535.0  # (N, H, W); grey keeps the fit per pixel
    truth = np.load(info.ground_truth_dir / "normals.npy").astype(np.float64)
    mask = np.asarray(Image.open(info.ground_truth_dir / "mask.png")) > 0

    n_obj = truth[mask]  # (P, 3)
    samples = intensity[:, mask].T  # (P, N)
    weights = (n_obj @ lights.T > 0).astype(np.float64)
    assert weights.sum(axis=1).min() >= 3
    normal_matrix = np.einsum("pn,ni,nj->pij", weights, lights, lights)
    rhs = np.einsum("pn,pn,ni->pi", weights, samples, lights)
    b = np.linalg.solve(normal_matrix, rhs[..., None])[..., 0]
    errors = angle_deg(b, n_obj)
    assert np.median(errors) < 0.1
    assert np.percentile(errors, 99) < 1.0
    albedo = np.load(info.ground_truth_dir / "albedo.npy")[mask].mean(axis=-1)
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), albedo, rtol=5e-3)


@pytest.mark.parametrize("azimuth_deg", [0.0, 90.0, 225.0])
def test_cast_shadows_for_low_light_but_not_from_zenith(azimuth_deg: float) -> None:
    tablet = clay_tablet(SHAPE, seed=0)
    elevation, azimuth = np.radians(15.0), np.radians(azimuth_deg)
    light = np.array([np.cos(elevation) * np.cos(azimuth),
                      np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    shadow = cast_shadow_mask(tablet.height, tablet.pixel_size, light)
    facing = tablet.normals @ light > 0
    cast = shadow & facing
    assert cast.sum() > 0.02 * cast.size
    # The tablet shades the table on its far side from the light: measure every pixel's
    # position along the light's horizontal direction (x = col, y = −row).
    rows, cols = np.indices(SHAPE)
    towards_light = cols * np.cos(azimuth) - rows * np.sin(azimuth)
    on_table = towards_light[cast & ~tablet.mask]
    assert on_table.size > 0
    assert np.median(on_table) < towards_light[tablet.mask].mean() - 0.3 * SHAPE[0]
    assert not cast[towards_light > towards_light[tablet.mask].max() + 2].any()

    lit = render(tablet, light[None], cast_shadows=False, noise=0.0)[0]
    shaded = render(tablet, light[None], cast_shadows=True, noise=0.0)[0]
    assert np.all(shaded[cast] == 0) and np.all(lit[cast].max(axis=-1) > 0)
    np.testing.assert_array_equal(shaded[~shadow], lit[~shadow])

    zenith = np.array([0.0, 0.0, 1.0])
    assert not cast_shadow_mask(tablet.height, tablet.pixel_size, zenith).any()
    np.testing.assert_array_equal(render(tablet, zenith[None], cast_shadows=True, noise=0),
                                  render(tablet, zenith[None], cast_shadows=False, noise=0))


def test_specular_highlight_adds_to_lit_pixels_and_saturates(tmp_path: Path) -> None:
    sphere = sphere_cap(SHAPE)
    light = np.array([[0.0, 0.0, 1.0]])
    matte = render(sphere, light, noise=0.0)[0]
    shiny = render(sphere, light, specular=1.0, shininess=20.0, noise=0.0)[0]
    extra = (shiny - matte)[..., 0]
    np.testing.assert_allclose(shiny - matte, np.repeat(extra[..., None], 3, axis=-1))  # white
    assert extra.max() == pytest.approx(1.0, abs=0.01)  # n = h near the apex
    assert extra[sphere.mask].min() < 0.01  # the lobe falls off towards the rim

    info = write_capture(tmp_path / "shiny", "sphere", SHAPE, lights=light, specular=1.0,
                         noise=0.0, scan_points=0)
    assert tifffile.imread(info.image_paths[0]).max() == 65535  # clipped like a camera


@pytest.mark.parametrize("grey", [0.002, 0.05, 0.2, 0.5])
def test_jpeg_of_flat_grey_follows_srgb_curve(tmp_path: Path, grey: float) -> None:
    flat = Surface(
        height=np.zeros(SHAPE, np.float32),
        normals=np.broadcast_to(np.float32([0, 0, 1]), (*SHAPE, 3)).copy(),
        mask=np.ones(SHAPE, bool),
        albedo=np.full((*SHAPE, 3), grey, np.float32),
        pixel_size=1.0,
        name="flat",
    )
    radiance = render(flat, np.array([[0.0, 0.0, 1.0]]), noise=0.0)[0]
    write_jpeg8(tmp_path / "grey.jpg", radiance)
    with Image.open(tmp_path / "grey.jpg") as image:
        assert image.mode == "RGB"
        decoded = np.asarray(image, dtype=np.float64)
    # A 2.2 gamma would be off by 1–8 levels at these greys.
    assert decoded.mean() == pytest.approx(255 * srgb_reference(grey), abs=0.6)


def test_jpeg_capture_is_srgb_encoding_of_tiff_capture(tmp_path: Path) -> None:
    jpeg = write_capture(tmp_path / "jpeg", "sphere", SHAPE, 6, "jpeg8", seed=2, noise=0.0)
    tiff = write_capture(tmp_path / "tiff", "sphere", SHAPE, 6, "tiff16", seed=2, noise=0.0)
    assert [p.suffix for p in jpeg.image_paths] == [".jpg"] * 6
    assert read_lp(jpeg.lp_path)[0][0] == "img_000.jpg"
    for jpg_path, tif_path in zip(jpeg.image_paths, tiff.image_paths):
        with Image.open(jpg_path) as image:
            decoded = np.asarray(image, dtype=np.float64)
        expected = 255 * srgb_reference(tifffile.imread(tif_path) / 65535.0)
        assert decoded.mean() == pytest.approx(expected.mean(), abs=0.5)
        assert np.abs(decoded - expected).mean() < 1.0


def test_scan_transform_maps_points_back_onto_surface(tablet_capture) -> None:
    gt = tablet_capture.ground_truth_dir
    scene = json.loads((gt / "scene.json").read_text())
    transform = np.array(scene["scan_transform"])
    rotation, translation = transform[:3, :3], transform[:3, 3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    assert np.degrees(np.arccos((np.trace(rotation) - 1) / 2)) >= 10
    assert np.linalg.norm(translation) >= 20

    cloud = trimesh.load(tablet_capture.scan_path)
    points = np.asarray(cloud.vertices, dtype=np.float64)
    assert len(points) == SHAPE[0] * SHAPE[1] // 4 == scene["scan"]["points"]
    back = (points - translation) @ rotation  # inverse of a rigid transform
    s = tablet_capture.pixel_size
    rows, cols = -back[:, 1] / s, back[:, 0] / s
    assert rows.min() >= -1e-3 and rows.max() <= SHAPE[0] - 1 + 1e-3
    assert cols.min() >= -1e-3 and cols.max() <= SHAPE[1] - 1 + 1e-3
    height = np.load(gt / "height.npy").astype(np.float64)
    residual = back[:, 2] - ndimage.map_coordinates(height, [rows, cols], order=1)
    assert abs(residual.mean()) < 0.005
    assert residual.std() == pytest.approx(scene["scan"]["noise_mm"], rel=0.15)
    # Without undoing the transform the points would be nowhere near the surface.
    assert np.abs(points[:, 2] - back[:, 2]).mean() > 1.0


def test_dome_and_ring_layouts() -> None:
    lights = dome_lights(48)
    assert lights.shape == (48, 3) and lights.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 1.0)
    elevation = np.degrees(np.arcsin(lights[:, 2]))
    assert elevation.min() == pytest.approx(15) and elevation.max() == pytest.approx(75)
    assert len(np.unique(np.round(elevation, 6))) >= 3
    azimuth = np.sort(np.arctan2(lights[:, 1], lights[:, 0]))
    gaps = np.diff(np.concatenate([azimuth, azimuth[:1] + 2 * np.pi]))
    assert gaps.max() < np.radians(30)
    np.testing.assert_array_equal(dome_lights(24, seed=5), dome_lights(24, seed=5))
    assert not np.array_equal(dome_lights(24, seed=5), dome_lights(24))

    ring = ring_lights(8, 30.0)
    np.testing.assert_allclose(ring[:, 2], np.sin(np.radians(30)))
    lu, lv = ring[:, 0], ring[:, 1]
    ptm_basis = np.stack([lu**2, lv**2, lu * lv, lu, lv, np.ones(8)], axis=1)
    assert np.linalg.matrix_rank(ptm_basis) == 5


@pytest.mark.parametrize("kwargs", [
    {"scene": "teapot"}, {"encoding": "png"}, {"shape": (4, 4)}, {"n_lights": 2},
    {"seed": -1}, {"noise": -0.1}, {"pixel_size": 0.0}, {"min_elevation_deg": 0.0},
    {"lights": np.array([[1.0, 0.0, 0.0]])},
])
def test_bad_capture_arguments_raise_input_error(tmp_path: Path, kwargs: dict) -> None:
    with pytest.raises(InputError):
        write_capture(tmp_path / "bad", **{"shape": SHAPE, **kwargs})
    assert not (tmp_path / "bad").exists()


def test_ring_layout_capture(tmp_path: Path) -> None:
    info = write_capture(tmp_path / "ring", "sphere", SHAPE, lights=ring_lights(8, 30.0),
                         scan_points=0)
    names, dirs = read_lp(info.lp_path)
    assert len(names) == 8
    np.testing.assert_allclose(dirs[:, 2], np.sin(np.radians(30)), atol=1e-6)
    scene = json.loads((info.ground_truth_dir / "scene.json").read_text())
    assert scene["lights"]["layout"] == "custom" and scene["scan"]["file"] is None


def test_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli"
    assert main([str(out), "--scene", "sphere", "--size", "40x32", "--lights", "6",
                 "--encoding", "jpeg8", "--seed", "1", "--scan-points", "0"]) == 0
    assert len(list(out.glob("img_*.jpg"))) == 6
    assert not (out / "scan.ply").exists()
    assert np.load(out / "ground_truth" / "height.npy").shape == (32, 40)

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    assert main([str(blocker), "--size", "40x32"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(blocker) in err

    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    assert "--encoding" in capsys.readouterr().out


def test_command_line_renders_glossy_spheres_beside_the_object(tmp_path: Path, capsys) -> None:
    """``--spheres 2``: two dark discs in opposite corners, clear of the tablet, each with a
    bright highlight, and no light file beside the photographs (the truth is in ground_truth/)."""
    out = tmp_path / "spheres"
    assert main([str(out), "--size", "256x192", "--lights", "8", "--scan-points", "0", "--spheres", "2"]) == 0
    assert "glossy sphere" in capsys.readouterr().out
    assert not list(out.glob("*.lp"))
    names, dirs = read_lp(out / "ground_truth" / "lights.lp")
    assert [Path(n).name for n in names] == [f"img_{k:03d}.tif" for k in range(8)]
    assert all((out / "ground_truth" / n).resolve().exists() for n in names)  # relative to the .lp
    scene = json.loads((out / "ground_truth" / "scene.json").read_text())
    spheres = [(s["cx"], s["cy"], s["r"]) for s in scene["spheres"]]
    assert len(spheres) == 2 and spheres[0][0] < 128 < spheres[1][0] and spheres[0][1] < 96 < spheres[1][1]
    mask = np.asarray(Image.open(out / "ground_truth" / "mask.png")) > 0
    rows, cols = np.mgrid[0:192, 0:256]
    image = tifffile.imread(out / "img_000.tif").astype(float) / 65535
    for cx, cy, r in spheres:
        disc = (cols - cx) ** 2 + (rows - cy) ** 2 < r**2
        assert r >= 12 and not (disc & mask).any()
        sphere = image[disc].mean(axis=1)
        assert np.median(sphere) < 0.05 and sphere.max() > 0.9  # black, with a highlight


def test_spheres_that_do_not_fit_are_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="spheres must be 0 to 4"):
        write_capture(tmp_path / "a", "tablet", SHAPE, n_lights=6, spheres=5, scan_points=0)
    with pytest.raises(InputError, match="corner"):
        write_capture(tmp_path / "b", "tablet", SHAPE, n_lights=6, spheres=1, scan_points=0)


def test_a_light_a_hair_above_the_horizon_casts_shadows_without_overflow():
    """Found by hypothesis (``--ring-elevation 2.2e-313``): the ray's climb per step is subnormal."""
    from data_synthetic.shadows import cast_shadow_mask

    height = np.zeros((8, 12))
    height[:, 6] = 1.0  # a wall
    tiny = np.radians(2.2250738585e-313)
    mask = cast_shadow_mask(height, 5.0, np.array([np.cos(tiny), 0.0, np.sin(tiny)]))
    assert mask.shape == (8, 12) and mask[:, :6].all() and not mask[:, 7:].any()
