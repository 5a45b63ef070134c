"""``reconstruct preview``: loading sources, relighting, measuring, and the window's callbacks
rendered off-screen (EGL or OSMesa on machines without a display)."""

import dataclasses
import json
import shutil

import numpy as np
import pytest
import tifffile
from helpers import run_cli

from data_synthetic import write_capture
from ptmcore.errors import InputError
from ptmcore.published import PublishedBasis
from ptmcore.relight import light_direction
from reconstruct.compare.figures import write_distance_ply
from reconstruct.pipeline import RunOptions, run_capture
from reconstruct.report.web import export_relightable
from reconstruct.report.webread import read_relightable
from reconstruct.viewer.measurements import free_paths
from reconstruct.viewer.preview import _BACKGROUND, build_plotter
from reconstruct.viewer.scene import (
    MODES,
    PreviewScene,
    distance,
    load_scene,
    mode_colors,
    profile,
    relit_texture,
)
from reconstruct.viewer.relighting import load_source, render

SIZE = (320, 240)
LIMIT = 0.4


def light_from_angles(azimuth, elevation):
    return light_direction(azimuth_deg=azimuth, elevation_deg=elevation)


def _known_distance(xyz: np.ndarray) -> np.ndarray:
    """The signed distances written into the test's distances.ply: a ramp across the object."""
    return 0.01 * xyz[:, 0] + 0.005 * xyz[:, 1]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """An output folder of a small synthetic tablet, with a comparison's distances.ply."""
    root = tmp_path_factory.mktemp("preview")
    info = write_capture(root / "cap", scene="tablet", shape=(72, 96), n_lights=16, seed=0)
    out = run_capture(root / "cap", root / "out", RunOptions(pixel_size=info.pixel_size, mask="auto")).output
    import trimesh

    mesh = trimesh.load(out / "mesh.ply", process=False)
    write_distance_ply(out / "distances.ply", mesh.vertices, mesh.faces, _known_distance(mesh.vertices), LIMIT)
    (out / "comparison.json").write_text(json.dumps({"colour_range_mm": [-LIMIT, LIMIT]}))
    return out


@pytest.fixture(scope="module")
def scene(folder):
    return load_scene(folder)


@pytest.fixture
def window(scene):
    w = build_plotter(scene, off_screen=True, size=SIZE)
    yield w
    w.close()


def _foreground(image: np.ndarray) -> float:
    """Share of pixels that differ from the background colour."""
    background = np.round(np.array(_BACKGROUND) * 255)
    return float(np.mean(np.abs(image.astype(float) - background).max(axis=-1) > 8))


# --- the scene --------------------------------------------------------------------------


def test_folder_scene_follows_the_output_layout(folder, scene):
    report = json.loads((folder / "report.json").read_text())
    height = tifffile.imread(folder / "height.tif")
    s = report["parameters"]["pixel_size"]
    assert scene.modes == MODES
    assert scene.unit == "mm" and scene.pixel_size == pytest.approx(s)
    # Small enough for step 1: every vertex is a pixel at x = col·s, y = −row·s, z = height.
    rows = np.rint(-scene.vertices[:, 1] / s).astype(int)
    cols = np.rint(scene.vertices[:, 0] / s).astype(int)
    np.testing.assert_allclose(scene.vertices[:, 2], height[rows, cols], atol=1e-6)
    assert np.count_nonzero(np.isfinite(height)) == len(scene.vertices)
    # The comparison's signed distances land on the vertices they belong to.
    np.testing.assert_allclose(scene.vertex_distance, _known_distance(scene.vertices), atol=1e-5)
    assert scene.distance_limit == pytest.approx(LIMIT)


def test_relit_texture_is_the_published_basis(folder, scene):
    """The relit view shows the basis the run chose and published in web/, as its page does;
    RTIViewer's modes stay the PTM's."""
    light = light_from_angles(120, 35)
    published = read_relightable(folder / "web")
    assert scene.published is not None and scene.published.name == published.name
    np.testing.assert_array_equal(relit_texture(scene, light), published.display(light))
    np.testing.assert_array_equal(mode_colors(scene, "relit", light), published.display(light))
    other = relit_texture(scene, light_from_angles(300, 35))
    assert np.abs(other.astype(int) - relit_texture(scene, light)).mean() > 2
    assert scene.coefficients is not None and "specular" in scene.modes
    with pytest.raises(ValueError, match="horizon"):
        relit_texture(scene, (0.3, 0.2, -0.5))


def test_relit_texture_is_the_ptm_without_a_published_basis(folder, tmp_path):
    """An older folder (web/ of the PTM itself, or none) shows its PTM relit, as before."""
    from ptmcore.relight import display_srgb

    copy = tmp_path / "old"
    shutil.copytree(folder, copy)
    viewer = json.loads((copy / "web" / "viewer.json").read_text())
    del viewer["basis"]  # export_openlime's viewer.json names no basis
    (copy / "web" / "viewer.json").write_text(json.dumps(viewer))
    scene = load_scene(copy)
    assert scene.published is None
    light = light_from_angles(120, 35)
    rendered = render(load_source(copy), light)
    assert not isinstance(load_source(copy), PublishedBasis)
    np.testing.assert_array_equal(relit_texture(scene, light),
                                  display_srgb(rendered) if scene.linear_ptm else rendered)


def test_a_linear_published_basis_is_shown_display_encoded(folder, tmp_path):
    """A basis of linear light (its viewer.json says so) is encoded for display once, as its page
    encodes it, whatever report.json says of the PTM."""
    copy = tmp_path / "linear_basis"
    shutil.copytree(folder, copy)
    basis = dataclasses.replace(read_relightable(copy / "web"), encoding="linear")
    export_relightable(copy / "web", basis, tiles=False)
    scene = load_scene(copy)
    assert scene.published.encoding == "linear" and not scene.linear_ptm
    light = light_from_angles(120, 35)
    read = read_relightable(copy / "web")
    np.testing.assert_array_equal(relit_texture(scene, light), read.display(light))
    raw = np.rint(np.clip(read.render(light), 0, 1) * 255)
    assert relit_texture(scene, light).mean() > raw.mean() + 20  # not dark


def test_a_published_basis_of_another_size_is_refused(folder, tmp_path):
    copy = tmp_path / "mismatch"
    shutil.copytree(folder, copy)
    small = read_relightable(copy / "web", max_side=40)
    export_relightable(copy / "web", small, tiles=False)
    with pytest.raises(InputError, match="web/info.json is"):
        load_scene(copy)


@pytest.mark.parametrize("source", ["folder", "bare_ptm"])
def test_a_linear_ptm_is_shown_display_encoded(folder, tmp_path, source):
    """A PTM whose report.json says it holds linear light (16-bit captures) is encoded as sRGB in
    every lit view, in its output folder (without a published basis) and as a .ptm beside that
    report."""
    from ptmcore.relight import display_srgb, specular_enhancement

    copy = tmp_path / "linear"
    shutil.copytree(folder, copy)
    shutil.rmtree(copy / "web")
    report = json.loads((copy / "report.json").read_text())
    report.setdefault("ptm", {})["encoding"] = "linear"
    (copy / "report.json").write_text(json.dumps(report))
    scene = load_scene(copy if source == "folder" else copy / "coefficients.ptm")
    assert scene.linear_ptm
    light = light_from_angles(120, 35)
    raw = render(load_source(copy), light)
    np.testing.assert_array_equal(relit_texture(scene, light), display_srgb(raw))
    assert relit_texture(scene, light).mean() > raw.mean() + 20  # not dark
    spec = mode_colors(scene, "specular", light)
    expected = display_srgb(specular_enhancement(scene.coefficients, scene.rgb, light))
    assert np.abs(spec.astype(int) - expected).max() <= 1
    (copy / "report.json").unlink()
    assert not load_scene(copy / "coefficients.ptm").linear_ptm  # a bare .ptm says nothing


def test_the_maxima_are_computed_once_and_shared(folder, scene):
    from ptmcore.normals import normals_from_ptm
    from ptmcore.relight import diffuse_gain

    np.testing.assert_array_equal(scene.maximum, normals_from_ptm(scene.coefficients))
    np.testing.assert_array_equal(scene.gained(3.0), diffuse_gain(scene.coefficients, 3.0))
    ptm = load_scene(folder / "coefficients.ptm")
    assert ptm.maximum is ptm.normals  # a PTM file's normals are its maxima


def test_large_sources_are_bounded(folder):
    small = load_scene(folder, max_vertices=600, max_texture=40)
    assert len(small.vertices) <= 600
    assert max(small.coefficients.shape[:2]) == 40 and small.rgb.shape[:2] == small.coefficients.shape[:2]
    assert small.normals.shape[:2] == small.coefficients.shape[:2]
    np.testing.assert_allclose(np.linalg.norm(small.normals, axis=-1), 1, atol=1e-5)
    assert relit_texture(small, (0, 0, 1)).shape == small.coefficients.shape[:2] + (3,)
    # The published basis is read at the texture's size (a DCT-scaled decode) and averaged to
    # it: the relit texture is the full-size one averaged, within a few levels.
    import cv2

    assert small.published.planes.shape[:2] == small.coefficients.shape[:2]
    light = light_from_angles(60, 40)
    full = read_relightable(folder / "web").display(light)
    h, w = small.coefficients.shape[:2]
    expected = cv2.resize(full, (w, h), interpolation=cv2.INTER_AREA).astype(int)
    assert np.abs(relit_texture(small, light).astype(int) - expected).mean() < 3


def test_lambert_relight_without_a_ptm():
    normals = np.zeros((4, 5, 3), np.float32)
    normals[..., 2] = 1
    normals[0, 0] = (1, 0, 0)  # facing right: dark under a light from the left
    albedo = np.full((4, 5, 3), 200, np.uint8)
    grid = PreviewScene("flat", np.zeros((3, 3), np.float32), np.array([[0, 1, 2]]), "pixel",
                        normals=normals, albedo=albedo)
    image = relit_texture(grid, light_from_angles(180, 30))
    # sRGB 200 is 0.578 linear; half of it (sin 30°) encodes as 147.
    linear = ((200 / 255 + 0.055) / 1.055) ** 2.4 * 0.5
    expected = 255 * (1.055 * linear ** (1 / 2.4) - 0.055)
    assert abs(int(image[1, 1, 0]) - expected) <= 1
    assert image[0, 0].max() == 0
    assert mode_colors(grid, "albedo") is albedo
    np.testing.assert_array_equal(mode_colors(grid, "normals")[1, 1], (128, 128, 255))


def test_profile_follows_the_height_map(scene):
    height = scene.height
    s = scene.pixel_size
    row = 36
    cols = np.flatnonzero(np.isfinite(height[row]))
    c0, c1 = cols[0] + 2, cols[-1] - 2
    p0, p1 = np.array([c0 * s, -row * s, 0.0]), np.array([c1 * s, -row * s, 0.0])
    along, heights = profile(scene, p0, p1, c1 - c0 + 1)
    np.testing.assert_allclose(along, (np.arange(c0, c1 + 1) - c0) * s, atol=1e-9)
    np.testing.assert_allclose(heights, height[row, c0:c1 + 1], atol=1e-5)


def test_profile_on_a_mesh_file_matches_the_height_map(folder, scene):
    mesh = load_scene(folder / "mesh.ply")
    p0, p1 = scene.vertices[200], scene.vertices[-300]
    _, expected = profile(scene, p0, p1, 60)
    _, found = profile(mesh, p0, p1, 60)
    both = np.isfinite(expected) & np.isfinite(found)
    assert both.mean() > 0.9
    # Triangles and bilinear interpolation agree at the vertices and differ by the cell's
    # twist between them (a few µm here, where the heights span 4 mm).
    np.testing.assert_allclose(found[both], expected[both], atol=0.01)
    assert np.abs(found[both] - expected[both]).mean() < 2e-3


def test_a_mesh_file_keeps_its_own_normals_and_texture(tmp_path):
    # A run's mesh.ply carries the measured normals, which the triangles cannot give (here a
    # flat grid whose normals lean 37° to the right); its per-vertex texture is sampled as is.
    from reconstruct.mesh.grid import grid_mesh
    from reconstruct.mesh.ply import write_ply
    from ptmcore.png import write_png

    h, w = 6, 8
    texture = np.zeros((h, w, 3), np.uint8)
    texture[..., 0] = np.arange(w) * 30
    normals = np.broadcast_to(np.float32([0.6, 0.0, 0.8]), (h, w, 3))
    mesh = grid_mesh(np.zeros((h, w), np.float32), texture=texture, pixel_size=0.1, normals=normals)
    write_ply(tmp_path / "mesh.ply", mesh, texture_file="mesh_texture.png")
    write_png(tmp_path / "mesh_texture.png", texture)
    scene = load_scene(tmp_path / "mesh.ply")
    assert len(scene.vertices) == h * w
    np.testing.assert_allclose(scene.normals, np.broadcast_to([0.6, 0.0, 0.8], (h * w, 3)), atol=1e-5)
    columns = np.round(scene.vertices[:, 0] / 0.1).astype(int)
    np.testing.assert_allclose(scene.albedo[:, 0], columns * 30, atol=2)


def test_distance_between_points():
    assert distance((0, 0, 0), (3, 4, 12)) == pytest.approx(13.0)


def test_other_sources(folder):
    ptm = load_scene(folder / "coefficients.ptm")
    assert ptm.modes == ("relit", "albedo", "normals", "specular", "diffuse-gain", "relief") and ptm.unit == "pixel"
    assert np.ptp(ptm.vertices[:, 2]) == 0  # a flat plane carrying the PTM
    mesh = load_scene(folder / "mesh.ply")
    assert mesh.unit == "mm" and mesh.uv is None and mesh.albedo.shape == (len(mesh.vertices), 3)
    assert mesh.modes == ("relit", "albedo", "normals", "height")  # no PTM, no normal map
    lit = relit_texture(mesh, light_from_angles(0, 20))
    assert lit.shape == mesh.albedo.shape
    assert np.abs(lit.astype(int) - relit_texture(mesh, light_from_angles(180, 20))).mean() > 2


@pytest.mark.parametrize("name", ["missing", "mask.png", "empty_dir"])
def test_bad_sources(folder, tmp_path, name):
    path = folder / name if name == "mask.png" else tmp_path / name
    if name == "empty_dir":
        path.mkdir()
    with pytest.raises(InputError) as err:
        load_scene(path)
    assert str(path) in str(err.value)


# --- the window, off-screen ---------------------------------------------------------------


def test_screenshot_shows_the_object(window):
    image = window.screenshot()
    assert image.shape == (SIZE[1], SIZE[0], 3) and image.dtype == np.uint8
    assert 0.2 < _foreground(image) < 0.95


def test_moving_the_light_relights_the_texture(window, scene):
    before = window.screenshot()
    window.on_light(315, 20)
    np.testing.assert_array_equal(np.asarray(window.colors).reshape(relit_texture(scene, (0, 0, 1)).shape),
                                  relit_texture(scene, light_from_angles(315, 20)))
    after = window.screenshot()
    assert np.abs(after.astype(int) - before).mean() > 2
    # The disk's marker points where the light comes from, as seen.
    marker = np.array(window.disk._marker.GetPosition())
    expected = window.disk.centre + window.disk.radius * light_from_angles(315, 20)[:2]
    np.testing.assert_allclose(marker, expected, atol=1e-6)


def test_every_mode_renders(window, scene):
    images = {}
    for mode in scene.modes:
        window.set_mode(mode)
        images[mode] = window.screenshot()
        assert _foreground(images[mode]) > 0.2, mode
    for mode in scene.modes[1:]:
        assert np.abs(images[mode].astype(int) - images["relit"]).mean() > 2, mode
    window.set_mode("height")
    assert window.plotter.scalar_bars["height (mm)"].GetVisibility()
    assert not window.plotter.scalar_bars["distance to scan (mm)"].GetVisibility()
    with pytest.raises(ValueError):
        window.set_mode("sparkle")


def test_two_picks_measure_a_distance_and_a_profile(window, scene):
    p0, p1 = scene.vertices[150], scene.vertices[-400]
    window.on_pick(p0)
    assert window.last_distance is None
    window.on_pick(p1)
    assert window.last_distance == pytest.approx(np.linalg.norm(p1.astype(float) - p0))
    window.toggle_profile()
    window.on_pick(p0)
    window.on_pick(p1)
    along, heights = window.last_profile
    expected_along, expected_heights = profile(scene, p0, p1, len(along))
    np.testing.assert_allclose(along, expected_along)
    np.testing.assert_allclose(heights, expected_heights)
    assert window.strip.shown
    # The profile has its own strip below the view: the view shrinks above it.
    assert window.plotter.renderer.GetViewport()[1] == pytest.approx(window.strip.fraction)
    assert _foreground(window.screenshot()) > 0.2
    window.toggle_profile()
    assert not window.strip.shown and window.plotter.renderer.GetViewport()[1] == 0


def test_export_is_the_last_measurement_made_whatever_was_picked_since(scene, tmp_path):
    # A name with dots: the files keep it whole (not "tablet_v1.csv").
    w = build_plotter(dataclasses.replace(scene, name="tablet_v1.2"), off_screen=True, size=SIZE, output=tmp_path)
    try:
        p0, p1, p2 = scene.vertices[150], scene.vertices[-400], scene.vertices[300]
        w.on_pick(p0)
        w.on_pick(p1)
        w.on_pick(p2)  # a new first point: the distance p0-p1 is still the last measured
        (csv_path,) = w.export_measurement()
        assert csv_path == tmp_path / "preview" / "tablet_v1.2_distance.csv"
        row = [float(v) for v in csv_path.read_text().splitlines()[1].split(",")]
        np.testing.assert_allclose(row[:6], np.concatenate([p0, p1]), rtol=1e-5, atol=1e-6)
        assert row[6] == pytest.approx(np.linalg.norm(p1.astype(float) - p0), rel=1e-5)
        w.toggle_profile()  # the picks are dropped; the distance is still what e exports
        assert w.export_measurement()[0] == tmp_path / "preview" / "tablet_v1.2_distance_1.csv"
        w.on_pick(p0)
        w.on_pick(p1)
        w.toggle_profile()
        written = w.export_measurement()
        assert written == [tmp_path / "preview" / "tablet_v1.2_profile.csv",
                           tmp_path / "preview" / "tablet_v1.2_profile.png"]
        lines = written[0].read_text().splitlines()
        assert lines[0] == "along_mm,x_mm,y_mm,height_mm" and len(lines) == 1 + len(w.last_profile[0])
        first = [float(v) for v in lines[1].split(",")]
        np.testing.assert_allclose(first[1:3], p0[:2], rtol=1e-5, atol=1e-6)
        assert written[1].stat().st_size > 1000
    finally:
        w.close()


def test_opening_the_window_colours_the_first_view_once(scene, monkeypatch):
    from reconstruct.viewer import preview

    calls = []
    monkeypatch.setattr(preview, "mode_colors", lambda *a, **k: calls.append(a[1]) or mode_colors(*a, **k))
    build_plotter(scene, off_screen=True, size=SIZE, mode="specular").close()
    assert calls == ["specular"]


def test_free_paths_keep_dotted_names(tmp_path):
    csv_path, png_path = free_paths(tmp_path / "preview", "tablet_v1.2_profile", (".csv", ".png"))
    assert (csv_path.name, png_path.name) == ("tablet_v1.2_profile.csv", "tablet_v1.2_profile.png")
    png_path.write_bytes(b"")
    assert [p.name for p in free_paths(tmp_path / "preview", "tablet_v1.2_profile", (".csv", ".png"))] == [
        "tablet_v1.2_profile_1.csv", "tablet_v1.2_profile_1.png"]


def test_help_reset_and_screenshot_keys(window, tmp_path, monkeypatch):
    window.toggle_help()
    assert "screenshot" in window._help.GetText(window._help.UpperLeft)
    window.toggle_help()
    assert "screenshot" not in window._help.GetText(window._help.UpperLeft)
    window.plotter.camera.azimuth = 40
    window.reset_view()
    np.testing.assert_allclose(window.plotter.camera.direction, (0, 0, -1), atol=1e-6)
    # Screenshots go into preview/ of the result's folder, named after the source and view.
    assert window.output == window.scene.folder
    window.output = tmp_path
    first, second = window.save_screenshot(), window.save_screenshot()
    name = window.scene.name
    assert first == tmp_path / "preview" / f"{name}_relit.png"
    assert second == tmp_path / "preview" / f"{name}_relit_1.png"
    assert first.stat().st_size > 1000 and second.is_file()
    assert str(second) in window.message  # it says where


def test_mesh_source_window_relights_vertex_colours(folder):
    mesh = load_scene(folder / "mesh.ply")
    w = build_plotter(mesh, off_screen=True, size=SIZE, azimuth=0, elevation=20)
    try:
        before = w.screenshot()
        w.on_light(180, 20)
        np.testing.assert_array_equal(np.asarray(w.colors), relit_texture(mesh, light_from_angles(180, 20)))
        assert np.abs(w.screenshot().astype(int) - before).mean() > 2
    finally:
        w.close()


def test_keys_and_right_clicks_drive_the_callbacks(scene, monkeypatch, tmp_path):
    # A window with an interactor but no display: VTK renders through EGL, and the events are
    # sent as the X server would send them.
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    w = build_plotter(scene, off_screen=False, size=SIZE, output=tmp_path)
    w.plotter.show(auto_close=False, interactive_update=True)  # returns without an event loop
    interactor = w.plotter.iren.interactor

    def press(key):
        interactor.SetKeyCode(key if len(key) == 1 else "\0")
        interactor.SetKeySym(key)
        interactor.KeyPressEvent()
        interactor.CharEvent()
        interactor.KeyReleaseEvent()

    try:
        press("2")
        assert w.mode == "albedo"
        press("5")
        assert w.mode == "distance"
        press("1")
        before = np.asarray(w.colors).copy()
        camera = w.plotter.camera_position, w.plotter.camera.parallel_scale
        lu, lv = light_from_angles(w.azimuth, w.elevation)[:2]
        press("Left")
        press("Up")
        # Left moves the light to the left as seen (x falls), Up upwards; the camera stays.
        np.testing.assert_allclose(light_from_angles(w.azimuth, w.elevation)[:2], (lu - 0.1, lv + 0.1), atol=1e-9)
        assert (w.plotter.camera_position, w.plotter.camera.parallel_scale) == camera
        assert not np.array_equal(np.asarray(w.colors), before)
        press("w")  # VTK's wireframe key is not ours: the surface stays a surface
        assert w.plotter.renderer.actors["colour"].GetProperty().GetRepresentation() == 2
        press("h")
        assert w.help_shown
        press("s")
        assert (tmp_path / "preview" / f"{scene.name}_relit.png").is_file()
        w.plotter.render()
        w.plotter.iren._mouse_right_button_click(SIZE[0] // 2, SIZE[1] // 2)
        w.plotter.iren._mouse_right_button_click(SIZE[0] // 2 + 40, SIZE[1] // 2 + 20)
        assert len(w.picks) == 2 and w.last_distance > 0
        press("e")
        assert (tmp_path / "preview" / f"{scene.name}_distance.csv").is_file()
        press("m")
        assert w.profile_mode and w.picks == []
        press("plus")
        press("plus")
        assert w.style.exaggeration == 3
        assert w.plotter.renderer.actors["colour"].GetScale() == (1, 1, 3)
        press("q")
        assert w.closed
    finally:
        w.close()


# --- the command ------------------------------------------------------------------------


def test_cli_screenshot(folder, tmp_path, capsys):
    from PIL import Image

    shots = {}
    # --light is x,y,z as in `reconstruct relight`: (1, 1, √(2/3)) is azimuth 45°, elevation 30°.
    z = float(np.sqrt(2 / 3))
    for name, light in (("45,30", ["--azimuth", "45", "--elevation", "30"]),
                        ("225,30", ["--azimuth", "225", "--elevation", "30"]),
                        ("xyz", ["--light", f"1,1,{z}"])):
        path = tmp_path / f"shot_{name.replace(',', '_')}.png"
        code, _, err = run_cli(["preview", folder, "--screenshot", path, *light, "--size", "200x150"], capsys)
        assert code == 0, err
        shots[name] = np.asarray(Image.open(path).convert("RGB"))
        assert shots[name].shape == (150, 200, 3)
    assert np.abs(shots["45,30"].astype(int) - shots["225,30"]).mean() > 2
    assert np.abs(shots["45,30"].astype(int) - shots["xyz"]).mean() < 0.5
    code, _, err = run_cli(["preview", folder / "coefficients.ptm", "--screenshot", tmp_path / "p.png",
                            "--mode", "normals", "--size", "200x150"], capsys)
    assert code == 0, err
    assert (tmp_path / "p.png").is_file()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["nowhere", "--screenshot", "x.png"], "not found"),
        (["{ptm}", "--mode", "height", "--screenshot", "x.png"], "no height view"),
        (["{folder}", "--light", "10", "--screenshot", "x.png"], "--light"),
        (["{folder}", "--elevation", "95", "--screenshot", "x.png"], "elevation"),
        (["{folder}", "--light", "0,0,-1", "--screenshot", "x.png"], "below the horizon"),
        (["{folder}", "--light", "0,0,1", "--azimuth", "10", "--screenshot", "x.png"], "--light"),
        (["{folder}", "--size", "10x10", "--screenshot", "x.png"], "--size"),
        (["{folder}"], "--screenshot"),
    ],
)
def test_cli_bad_input(folder, tmp_path, capsys, monkeypatch, args, needle):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.chdir(tmp_path)
    args = [a.format(folder=folder, ptm=folder / "coefficients.ptm") for a in args]
    code, _, err = run_cli(["preview", *args], capsys)
    lines = [ln for ln in err.splitlines() if ln.startswith("reconstruct")]
    assert code == 2 and len(lines) == 1 and needle in lines[0], err
    assert not (tmp_path / "x.png").exists()


def test_comparison_in_another_folder(folder, tmp_path):
    rec, cmp_ = tmp_path / "rec", tmp_path / "vs_scan"
    shutil.copytree(folder, rec)
    cmp_.mkdir()
    for name in ("distances.ply", "comparison.json"):
        (rec / name).rename(cmp_ / name)
    assert "distance" not in load_scene(rec).modes
    scene = load_scene(rec, comparison=cmp_)
    np.testing.assert_allclose(scene.vertex_distance, _known_distance(scene.vertices), atol=1e-5)
    with pytest.raises(InputError, match="distances.ply"):
        load_scene(rec, comparison=rec)


def test_folder_without_ptm_relights_from_normals(folder, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(folder, copy)
    (copy / "coefficients.ptm").unlink()
    scene = load_scene(copy)
    # The published basis alone: relit, but no specular enhancement nor diffuse gain.
    assert scene.coefficients is None and scene.published is not None
    assert "relit" in scene.modes and "specular" not in scene.modes and "diffuse-gain" not in scene.modes
    shutil.rmtree(copy / "web")
    scene = load_scene(copy)
    assert scene.coefficients is None and scene.published is None and "relit" in scene.modes
    a, b = relit_texture(scene, light_from_angles(0, 25)), relit_texture(scene, light_from_angles(180, 25))
    assert np.abs(a.astype(int) - b).mean() > 2
