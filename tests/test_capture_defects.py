"""Issue 37 (part): captures as they come — the ambient frame, the camera's drift, `reconstruct check`."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import shift as ndshift

from data_synthetic import write_capture
from data_synthetic.encoding import write_tiff16
from data_synthetic.lights import dome_lights
from data_synthetic.render import render
from data_synthetic.surfaces import SCENES
from ptmcore.align import ALIGN_THRESHOLD_PX, DriftProbe, measure_drift, warp_photograph
from ptmcore.corrections import Corrections, to_linear_rgb
from ptmcore.images import read_image, srgb_to_linear


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "reconstruct", *args], capture_output=True, text=True)


def test_to_linear_rgb_takes_every_sample_type():
    u8 = np.array([[0, 128, 255]], np.uint8)
    assert np.allclose(to_linear_rgb(u8)[..., 0], srgb_to_linear(u8 / 255.0), atol=1e-6)
    assert np.allclose(to_linear_rgb(u8, linearize=False)[..., 1], u8 / 255.0, atol=1e-6)
    u16 = np.full((2, 3, 3), 65535, np.uint16)
    assert np.allclose(to_linear_rgb(u16), 1.0)
    f = np.random.default_rng(0).random((4, 5, 3)).astype(np.float32)
    out = to_linear_rgb(f)
    assert np.array_equal(out, f) and not np.shares_memory(out, f)


def test_no_correction_leaves_the_photograph_as_decoded():
    img = np.zeros((4, 4, 3), np.uint8)
    assert Corrections().apply(0, img) is img


@pytest.fixture(scope="module")
def ambient_capture(tmp_path_factory) -> tuple[Path, Path, Path]:
    root = tmp_path_factory.mktemp("ambient")
    write_capture(root / "clean", shape=(96, 128), n_lights=24, seed=2, scan_points=0)
    write_capture(root / "room", shape=(96, 128), n_lights=24, seed=2, scan_points=0, ambient=0.1)
    albedo = np.load(root / "room" / "ground_truth" / "albedo.npy")
    write_tiff16(root / "lamps_off.tif", (0.1 * albedo).astype(np.float32))
    return root / "clean", root / "room", root / "lamps_off.tif"


def _mean_error(out: Path) -> float:
    return json.loads((out / "report.json").read_text())["accuracy"]["normals"]["mean_deg"]


def test_the_ambient_frame_is_subtracted(ambient_capture, tmp_path):
    clean, room, lamps_off = ambient_capture
    for name, capture, extra in [("clean", clean, ()), ("room", room, ()), ("fixed", room, ("--ambient", str(lamps_off)))]:
        assert _cli("run", str(capture), "-o", str(tmp_path / name), "-q", *extra).returncode == 0
    clean_err, room_err, fixed_err = (_mean_error(tmp_path / n) for n in ("clean", "room", "fixed"))
    assert room_err > 2 * clean_err  # room light flattens the normals
    assert fixed_err <= 1.2 * clean_err
    checks = json.loads((tmp_path / "fixed" / "report.json").read_text())["capture_checks"]
    assert checks["ambient"]["frame"] == str(lamps_off)


def test_a_lit_photograph_as_ambient_frame_is_refused(ambient_capture, tmp_path):
    _, room, _ = ambient_capture
    result = _cli("run", str(room), "-o", str(tmp_path / "out"), "--ambient", str(room / "img_000.tif"))
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "lamp on" in result.stderr and "img_000.tif" in result.stderr
    assert not (tmp_path / "out").exists()


def test_an_ambient_frame_of_another_size_is_refused(ambient_capture, tmp_path):
    _, room, _ = ambient_capture
    small = tmp_path / "small.tif"
    write_tiff16(small, np.zeros((10, 12, 3), np.float32))
    result = _cli("run", str(room), "-o", str(tmp_path / "out"), "--ambient", str(small))
    assert result.returncode == 2 and "12×10" in result.stderr and "128×96" in result.stderr


def _shifted(image: np.ndarray, rows: float, cols: float) -> np.ndarray:
    """An (H, W, 3) image moved by (rows, cols) pixels (quintic spline, edges repeated), channel
    by channel: the same as shifting the 3-D array by (rows, cols, 0), whose spline along the
    channels is exact at their integer positions, at a sixth of the work."""
    return np.stack([ndshift(image[..., c], (rows, cols), order=5, mode="nearest") for c in range(image.shape[2])],
                    axis=-1)


@pytest.fixture(scope="module")
def rendered() -> tuple[np.ndarray, np.ndarray]:
    lights = dome_lights(36, 15, 75)
    surface = SCENES["tablet"]((256, 320), pixel_size=None, seed=4)
    return np.clip(render(surface, lights, noise=0.003, seed=4), 0, 1).astype(np.float32), lights


def _drift(images: np.ndarray, lights: np.ndarray):
    probe = DriftProbe(images.shape[1:3], len(images))
    for k, img in enumerate(images):
        probe.take(k, img, False)
    return measure_drift(probe, lights)


def test_a_steady_capture_raises_no_alarm(rendered):
    images, lights = rendered
    drift = _drift(images, lights)
    assert not drift.needs_alignment()
    assert drift.largest()[1] < ALIGN_THRESHOLD_PX


def test_displaced_photographs_are_found(rendered):
    images, lights = rendered
    moved = images.copy()
    for k in range(1, len(moved), 2):  # every other photograph: 3 rows down, 4 columns right
        moved[k] = _shifted(images[k], 3, 4)
    drift = _drift(moved, lights)
    assert drift.needs_alignment()
    # The first photograph's frame is kept (two equal groups: the one the capture started in).
    shifted = np.median(drift.offsets[1::2], axis=0)
    assert np.allclose(shifted, [4, -3], atol=0.4)  # x right, y up
    assert np.allclose(np.median(drift.offsets[0::2], axis=0), 0, atol=0.2)


def test_a_bump_half_way_is_found_whole(rendered):
    # The photographs after the bump are the dome's upper rings: one half of the light layout
    # (the earlier design, registering against the relit PTM, read 6.8 px for 5 px here).
    images, lights = rendered
    moved = images.copy()
    half = len(moved) // 2
    for k in range(half, len(moved)):
        moved[k] = _shifted(images[k], 3, 4)
    drift = _drift(moved, lights)
    assert drift.needs_alignment()
    # Within half a pixel, short of the threshold (0.75 px): the largest errors are on a few
    # photographs whose lights' neighbours are far (this 36-light dome's top ring).
    assert np.abs(drift.offsets[:half]).max() < 0.5
    assert np.abs(drift.offsets[half:] - [4, -3]).max() < 0.5
    assert np.median(np.abs(drift.offsets[half:] - [4, -3])) < 0.25
    # The photographs of the common frame are left as they are; the others are resampled.
    still = np.all(drift.resampling()[:half] == [[1, 0, 0], [0, 1, 0]], axis=(1, 2))
    assert still.mean() > 0.5 and not np.any(np.all(drift.resampling()[half:] == [[1, 0, 0], [0, 1, 0]], axis=(1, 2)))


def test_a_sub_pixel_drift_and_a_shaking_camera_are_measured(rendered):
    images, lights = rendered
    for truth, beyond in ((np.tile([[0.0, 0.0], [0.48, 0.64]], (len(images) // 2, 1)), False),  # 0.8 px
                          (np.random.default_rng(5).uniform(-2, 2, (len(images), 2)), True)):  # rows, columns
        moved = np.stack([_shifted(img, *t) for img, t in zip(images, truth)])
        drift = _drift(moved, lights)
        found = np.stack([-drift.offsets[:, 1], drift.offsets[:, 0]], axis=1)
        error = found - truth
        assert drift.needs_alignment() == beyond  # the threshold is 1 px
        error = np.abs(error - np.median(error, axis=0))
        assert error.max() < 0.5 and np.median(error) < 0.15


def test_a_small_rotation_is_measured():
    from scipy.ndimage import affine_transform

    # Five tiles, so a rotation, from a frame of 768 px on its shorter side on.
    lights = dome_lights(24, 15, 75)
    images = np.clip(render(SCENES["tablet"]((768, 800), pixel_size=None, seed=4), lights, seed=4), 0, 1)
    images = images.astype(np.float32)
    h, w = images.shape[1:3]
    t = np.radians(0.5)
    rot = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    centre = np.array([(h - 1) / 2, (w - 1) / 2])
    moved = images.copy()
    for k in range(1, len(moved), 2):
        moved[k] = np.stack([affine_transform(images[k][..., c], rot, centre - rot @ centre, order=5, mode="nearest")
                             for c in range(3)], axis=-1)
    drift = _drift(moved, lights)
    assert drift.needs_alignment()
    # Half the photographs turned by 0.5° against the other half (either may be the frame).
    turned = np.median(drift.rotation_deg[1::2]) - np.median(drift.rotation_deg[0::2])
    assert abs(abs(turned) - 0.5) < 0.1


def test_a_steady_glossy_capture_is_not_taken_for_a_turned_camera():
    # Highlights move with the light and drag a tile's details with them (7 px in one of the
    # five); with that tile left out, three corners and a rotation used to explain the other
    # tiles' biased offsets as a turn of ±0.1°, and the photographs were resampled.
    # Measured: 3.4 px read before, none now (24 lights; 1.6 px of 48 in benchmarks/drift.py).
    lights = dome_lights(24, 15, 75)
    images = np.clip(render(SCENES["tablet"]((768, 1024), pixel_size=None, seed=0), lights, seed=0,
                            specular=0.5, shininess=40.0), 0, 1).astype(np.float32)
    drift = _drift(images, lights)
    assert not drift.needs_alignment(), drift.largest()


def test_a_featureless_capture_is_not_measured():
    lights = dome_lights(24, 20, 70)
    flat = np.broadcast_to((0.5 * np.clip(lights[:, 2], 0, 1))[:, None, None, None], (24, 96, 96, 3)).astype(np.float32)
    drift = _drift(flat, lights)
    assert not drift.needs_alignment() and np.all(drift.confidence == 0)


def test_warp_photograph():
    rng = np.random.default_rng(1)
    img = rng.random((40, 50, 3)).astype(np.float32)
    identity = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    assert np.allclose(warp_photograph(img, identity), img, atol=1e-6)
    # The common frame's pixel (c, r) lies at (c + 2, r + 1) in the photograph.
    moved = warp_photograph(img, np.array([[1.0, 0, 2], [0, 1.0, 1]]))
    assert np.allclose(moved[:-1, :-2], img[1:, 2:], atol=1e-5)


def test_check_reports_a_steady_capture(ambient_capture, tmp_path):
    clean, _, _ = ambient_capture
    found = tmp_path / "check.json"
    result = _cli("check", str(clean), "--json", str(found))
    assert result.returncode == 0, result.stderr
    assert "Nothing to act on" in result.stdout
    data = json.loads(found.read_text())
    assert data["photographs"] == 24 and data["checks"]["lights"]["rank"] == 6


def test_check_names_black_photographs(ambient_capture, tmp_path):
    import shutil

    import tifffile

    clean, _, _ = ambient_capture
    capture = tmp_path / "cap"
    shutil.copytree(clean, capture)
    tifffile.imwrite(capture / "img_003.tif", np.zeros((96, 128, 3), np.uint16))
    result = _cli("check", str(capture))
    assert result.returncode == 0 and "mostly black" in result.stdout and "img_003.tif" in result.stdout


def test_room_light_is_warned_of_and_gone_once_subtracted(ambient_capture, tmp_path):
    _, room, lamps_off = ambient_capture
    for name, extra in (("room", ()), ("fixed", ("--ambient", str(lamps_off)))):
        assert _cli("run", str(room), "-o", str(tmp_path / name), "-q", *extra).returncode == 0
    room_report = json.loads((tmp_path / "room" / "report.json").read_text())
    fixed_report = json.loads((tmp_path / "fixed" / "report.json").read_text())
    assert room_report["capture_checks"]["stray_light"]["warned"]
    assert abs(room_report["capture_checks"]["stray_light"]["level"] - 0.1) < 0.02
    assert any(w.startswith("stray light") for w in room_report["warnings"])
    assert not fixed_report["capture_checks"]["stray_light"]["warned"]
    assert not any(w.startswith("stray light") for w in fixed_report["warnings"])


def test_check_warns_of_room_light(ambient_capture):
    _, room, _ = ambient_capture
    result = _cli("check", str(room))
    assert result.returncode == 0 and "stray light" in result.stdout


@pytest.fixture(scope="module")
def uneven_capture(tmp_path_factory) -> tuple[Path, Path, Path]:
    """A tablet under lamps that light the frame unevenly (vignetting, each lamp's cone), its
    board under the same lamps, and the same tablet under even lamps."""
    from data_synthetic import illumination as synth
    from ptmcore.lp import write_lp

    root = tmp_path_factory.mktemp("uneven")
    shape, lights = (96, 128), dome_lights(24, 15, 75)
    surface = SCENES["tablet"](shape, pixel_size=None, seed=5)
    radiance = np.clip(render(surface, lights, noise=0.003, seed=5), 0, 1).astype(np.float32)
    gains = (synth.vignetting(shape, 0.6), synth.lamp_cone(shape, lights))
    names = [f"img_{k:03d}.tif" for k in range(len(lights))]
    for folder, images in (("even", radiance), ("uneven", synth.apply_gains(radiance.copy(), *gains))):
        (root / folder / "ground_truth").mkdir(parents=True)
        for name, image in zip(names, images):
            write_tiff16(root / folder / name, np.clip(image, 0, 1))
        write_lp(root / folder / "lights.lp", names, lights)
        np.save(root / folder / "ground_truth" / "normals.npy", surface.normals.astype(np.float32))
    synth.write_board_capture(root / "board", np.clip(synth.render_board(shape, lights, *gains, seed=6), 0, 1), names)
    return root / "even", root / "uneven", root / "board"


def test_the_flat_field_evens_the_lamps_out(uneven_capture, tmp_path):
    even, uneven, board = uneven_capture
    for name, capture, extra in (("even", even, ()), ("uneven", uneven, ()),
                                 ("fixed", uneven, ("--flat-field", str(board)))):
        result = _cli("run", str(capture), "-o", str(tmp_path / name), "-q", *extra)
        assert result.returncode == 0, result.stderr
    even_err, uneven_err, fixed_err = (_mean_error(tmp_path / n) for n in ("even", "uneven", "fixed"))
    assert uneven_err > 2 * even_err
    assert fixed_err <= 1.2 * even_err
    checks = json.loads((tmp_path / "fixed" / "report.json").read_text())["capture_checks"]
    assert checks["flat_field"]["capture"] == str(board)


def test_a_board_of_another_light_count_is_refused(uneven_capture, tmp_path):
    import shutil

    _, uneven, board = uneven_capture
    short = tmp_path / "board"
    shutil.copytree(board, short)
    sorted(short.glob("*.tif"))[-1].unlink()
    result = _cli("run", str(uneven), "-o", str(tmp_path / "out"), "--flat-field", str(short))
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


def test_a_grey_card_gives_the_intensities(uneven_capture, tmp_path):
    even, _, _ = uneven_capture
    result = _cli("run", str(even), "-o", str(tmp_path / "out"), "-q", "--reference-region", "2,2,12,10")
    assert result.returncode == 0, result.stderr
    found = json.loads((tmp_path / "out" / "report.json").read_text())["intensities"]
    assert found["source"] == "reference region 2,2,12,10" and len(found["factors"]) == 24
    bad = _cli("run", str(even), "-o", str(tmp_path / "bad"), "--reference-region", "120,90,20,20")
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1
    both = _cli("run", str(even), "-o", str(tmp_path / "both"), "--reference-region", "2,2,4,4", "--intensities", "estimate")
    assert both.returncode == 2 and "either" in both.stderr


def test_a_raw_capture_runs_as_its_linear_tiffs(tmp_path):
    # The same capture as 16-bit linear TIFFs and as DNGs (an RGGB mosaic under a camera white
    # balance, with a per-photograph as-shot balance as an automatic white balance would give):
    # developed with the first photograph's balance, the normals are close to the TIFFs'. Not
    # equal: the TIFFs hold three colours a pixel, the DNGs one, which LibRaw's demosaicing
    # interpolates (0.65° against 0.38° at 240 × 192, 2026-11-29).
    from data_synthetic.raw import write_dng

    tiffs = tmp_path / "tiff"
    write_capture(tiffs, shape=(192, 240), n_lights=24, seed=3, scan_points=0)
    dngs = tmp_path / "dng"
    dngs.mkdir()
    lines = (tiffs / "lights.lp").read_text().splitlines()
    out_lines = [lines[0]]
    for k, line in enumerate(lines[1:]):
        name, *rest = line.split()
        linear = read_image(tiffs / name).astype(np.float32) / np.float32(65535)
        dng = Path(name).with_suffix(".dng").name
        write_dng(dngs / dng, linear, neutral=(0.55, 1.0, 0.7), as_shot=(0.55 + 0.01 * (k % 3), 1.0, 0.7))
        out_lines.append(" ".join([dng, *rest]))
    (dngs / "lights.lp").write_text("\n".join(out_lines) + "\n")
    errors = {}
    for name, capture in (("tiff", tiffs), ("dng", dngs)):
        out = tmp_path / f"out_{name}"
        result = _cli("run", str(capture), "-o", str(out), "--ground-truth", str(tiffs / "ground_truth"))
        assert result.returncode == 0, result.stderr
        errors[name] = _mean_error(out)
        report = json.loads((out / "report.json").read_text())
    assert "camera RAW" in report["capture_checks"]["colour"]
    assert errors["dng"] < 2 * errors["tiff"], errors


def test_a_run_reports_a_photograph_exposed_differently(tmp_path):

    capture = tmp_path / "capture"
    write_capture(capture, shape=(96, 128), n_lights=24, seed=2, scan_points=0)
    darker = sorted(capture.glob("img_*.tif"))[5]
    write_tiff16(darker, read_image(darker).astype(np.float32) / np.float32(65535 * 3))
    out = tmp_path / "out"
    result = _cli("run", str(capture), "-o", str(out))
    assert result.returncode == 0, result.stderr
    report = json.loads((out / "report.json").read_text())
    odd = report["capture_checks"]["exposure"]["odd_brightness"]
    assert list(odd) == [darker.name] and odd[darker.name] < 0.5
    assert any("brighter or darker than their light's elevation" in w for w in report["warnings"])
    assert "Exposure" in (out / "report.html").read_text()


def test_align_off_reports_the_drift_without_undoing_it(tmp_path):
    capture = tmp_path / "capture"
    write_capture(capture, shape=(192, 256), n_lights=24, seed=3, scan_points=0)
    for path in sorted(capture.glob("img_*.tif"))[12:]:  # the tripod bumped half-way
        img = read_image(path).astype(np.float32) / np.float32(65535)
        write_tiff16(path, np.clip(_shifted(img, 3, 4), 0, 1))
    reports = {}
    for align in ("off", "auto"):
        out = tmp_path / align
        result = _cli("run", str(capture), "-o", str(out), "--align", align)
        assert result.returncode == 0, result.stderr
        reports[align] = json.loads((out / "report.json").read_text())
    for align, report in reports.items():
        drift = report["capture_checks"]["drift"]
        assert drift["largest_px"] > 4 and drift["aligned"] == (align == "auto")
        assert any("the camera moved" in w for w in report["warnings"])
    assert any("not aligned" in w for w in reports["off"]["warnings"])


def test_a_glossy_sheen_on_a_whole_ring_is_not_an_exposure_change():
    """The photographs of a ring of high lights all bright (a glossy flat object's sheen) are
    not odd; one photograph of a ring made darker still is."""
    from data_synthetic import dome_lights
    from reconstruct.pipeline.defects import exposure_finding

    dirs = dome_lights(49)
    names = [f"img_{k:03d}.tif" for k in range(49)]
    rng = np.random.default_rng(0)
    luminance = (0.3 * dirs[:, 2][:, None, None] * rng.uniform(0.8, 1.2, (49, 8, 8))).astype(np.float32)
    top = np.flatnonzero(dirs[:, 2] > 0.95)
    assert len(top) >= 3
    luminance[top] *= 2.9  # the sheen: every photograph of the top ring
    finding, warnings = exposure_finding(luminance, np.zeros(49), dirs, names)
    assert finding["odd_brightness"] == {} and warnings == []
    ring = np.flatnonzero(np.abs(dirs[:, 2] - dirs[5, 2]) < 1e-6)
    assert 5 in ring and len(ring) >= 3
    luminance[5] /= 3  # a lamp that fired weakly
    finding, warnings = exposure_finding(luminance, np.zeros(49), dirs, names)
    assert list(finding["odd_brightness"]) == [names[5]] and len(warnings) == 1
