"""Room light and uneven lamps (issue 37): the ambient frame, the flat field, the grey card and
stray light measured without an ambient frame (ptmcore.illumination)."""

from pathlib import Path

import numpy as np
import pytest

from data_synthetic import clay_tablet, dome_lights, render, sphere_cap
from data_synthetic import illumination as synth
from data_synthetic.encoding import to_uint8_srgb, to_uint16_linear, write_jpeg8, write_png8, write_tiff16
from ptmcore.errors import InputError
from ptmcore.images import LUMA_WEIGHTS, linear_to_srgb, read_image, srgb_to_linear
from ptmcore.illumination import (
    STRAY_LIGHT_WARN,
    check_ambient,
    estimate_stray_light,
    load_flat_field,
    parse_region,
    read_ambient,
    reference_intensities,
    subtract_ambient,
)

SHAPE = (96, 128)
REAL_CAT = Path(__file__).resolve().parents[1].parent / "shared" / "real" / "diligent_cat"


def _one_line(exc: pytest.ExceptionInfo, path) -> str:
    text = str(exc.value)
    assert "\n" not in text
    assert str(path) in text
    return text


@pytest.fixture(scope="module")
def tablet():
    """A small tablet under 24 dome lights from 15°: clean linear radiance, lights, surface."""
    surface = clay_tablet(SHAPE, seed=3)
    lights = dome_lights(24, 15, 75)
    return render(surface, lights, seed=1, noise=0.002), lights, surface


# --- ambient frame ---------------------------------------------------------------------------


def test_ambient_read_in_linear_light_from_8_16_bit_and_grey(tmp_path):
    rng = np.random.default_rng(0)
    frame = rng.uniform(0.0, 0.2, (*SHAPE, 3)).astype(np.float32)
    write_tiff16(tmp_path / "a16.tif", frame)
    write_png8(tmp_path / "a8.png", frame)
    got16 = read_ambient(tmp_path / "a16.tif", SHAPE)
    got8 = read_ambient(tmp_path / "a8.png", SHAPE)
    assert got16.dtype == np.float32 and got16.shape == (*SHAPE, 3)
    np.testing.assert_allclose(got16, to_uint16_linear(frame) / 65535.0, atol=1e-6)
    np.testing.assert_allclose(got8, srgb_to_linear(to_uint8_srgb(frame) / 255.0), atol=1e-6)
    import tifffile

    tifffile.imwrite(tmp_path / "grey.tif", to_uint16_linear(frame[..., 1]))
    grey = read_ambient(tmp_path / "grey.tif", SHAPE)
    assert grey.shape == (*SHAPE, 3) and np.array_equal(grey[..., 0], grey[..., 2])


def test_ambient_of_another_size_is_refused_naming_both(tmp_path):
    write_tiff16(tmp_path / "amb.tif", np.zeros((50, 60, 3), np.float32))
    with pytest.raises(InputError) as exc:
        read_ambient(tmp_path / "amb.tif", SHAPE)
    text = _one_line(exc, tmp_path / "amb.tif")
    assert "60×50" in text and "128×96" in text


def test_subtracting_the_ambient_frame_restores_the_clean_radiance(tablet, tmp_path):
    radiance, lights, surface = tablet
    clean = np.clip(radiance, 0, 1)
    ambient = synth.ambient_frame(surface.albedo, 0.1, gradient=0.3)
    write_tiff16(tmp_path / "ambient.tif", ambient)
    frame = read_ambient(tmp_path / "ambient.tif", SHAPE)
    for k in (0, 7, 23):
        photo = to_uint16_linear(synth.add_ambient(clean[k:k + 1].copy(), ambient)[0]) / np.float32(65535)
        photo = photo.astype(np.float32)
        # Band by band, as the decoding pass does.
        for r0 in range(0, SHAPE[0], 40):
            rows = slice(r0, min(SHAPE[0], r0 + 40))
            subtract_ambient(photo[rows], frame, rows)
        assert photo.min() >= 0
        np.testing.assert_allclose(photo, clean[k], atol=2e-4)


def test_ambient_brighter_than_the_photographs_is_refused(tablet, tmp_path):
    radiance, lights, surface = tablet
    paths = []
    for k, image in enumerate(radiance):
        paths.append(tmp_path / f"img_{k:02d}.jpg")
        write_jpeg8(paths[-1], image)
    good = synth.ambient_frame(surface.albedo, 0.1)
    check_ambient(good, paths, tmp_path / "ambient.jpg")  # room light: accepted
    lamp_on = np.clip(radiance[12], 0, 1)  # a photograph given as the ambient frame
    with pytest.raises(InputError) as exc:
        check_ambient(lamp_on, paths, tmp_path / "ambient.jpg")
    assert "brighter than the photographs" in _one_line(exc, tmp_path / "ambient.jpg")


# --- flat field ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def uneven(tablet):
    """Gains of vignetting, a lamp's cone and inverse-square fall-off, lamps of unequal strength."""
    _, lights, _ = tablet
    strength = np.random.default_rng(5).uniform(0.8, 1.2, len(lights)).astype(np.float32)
    gains = (synth.vignetting(SHAPE, 0.75)[None] * synth.lamp_cone(SHAPE, lights, seed=2)
             * synth.inverse_square(SHAPE, lights, 2.5) * strength[:, None, None])
    return gains


def _write_board(folder, lights, gains, names, lp=False, labels=(), shape=SHAPE):
    board = synth.render_board(shape, lights, gains, labels=labels, dust=8, noise=0.003, seed=4)
    return synth.write_board_capture(folder, board, names, lights if lp else None)


def _relative(est, true):
    q = est / true
    return np.abs(q / np.median(q) - 1)


def test_flat_field_recovers_the_gains_despite_a_label(tablet, uneven, tmp_path):
    radiance, lights, _ = tablet
    names = [f"img_{k:02d}.tif" for k in range(len(lights))]
    _write_board(tmp_path / "flat", lights, uneven, names, labels=[(80, 10, 30, 22)])
    flat = load_flat_field(tmp_path / "flat", names, lights, SHAPE)
    est = np.stack([flat.gain_rows(k, 0, SHAPE[0]) for k in range(len(lights))])
    assert est.dtype == np.float32 and est.shape == (len(lights), *SHAPE)
    assert _relative(est, uneven).max() < 0.02
    # Band by band gives the same gain.
    np.testing.assert_array_equal(flat.gain_rows(3, 40, 60), est[3, 40:60])
    # The defective photographs divided by the gains are the clean ones.
    clean = np.clip(radiance, 0, 1)
    defective = synth.apply_gains(clean.copy(), uneven)
    corrected = defective / est[..., None]
    lit = clean > 0.05
    scale = np.median(corrected[lit] / clean[lit])
    assert np.abs(corrected[lit] / (scale * clean[lit]) - 1).max() < 0.02
    info = flat.describe()
    assert info["lights"] == len(lights) and info["worst_corner_darkening"] > 0.2
    assert "darker at the corners" in info["summary"]
    # Without the robust weights the label would show: it is rejected.
    assert min(flat.rejected) > 0.01


def test_flat_field_by_name_and_by_order(tablet, uneven, tmp_path):
    _, lights, _ = tablet
    n = len(lights)
    capture = [f"img_{k:02d}.jpg" for k in range(n)]
    # Same names (other extension), listed in another order by the board's .lp: by name.
    shuffled = list(np.random.default_rng(0).permutation(n))
    board_names = [f"img_{k:02d}.tif" for k in shuffled]
    _write_board(tmp_path / "named", lights[shuffled], uneven[shuffled], board_names, lp=True)
    by_name = load_flat_field(tmp_path / "named", capture, lights, SHAPE)
    assert by_name.matched_by == "name"
    # Other names: by sorted order.
    _write_board(tmp_path / "ordered", lights, uneven, [f"board{k:03d}.tif" for k in range(n)])
    by_order = load_flat_field(tmp_path / "ordered", capture, lights, SHAPE)
    assert by_order.matched_by == "order"
    for flat in (by_name, by_order):
        est = np.stack([flat.gain_rows(k, 0, SHAPE[0]) for k in range(n)])
        assert _relative(est, uneven).max() < 0.02


def test_flat_field_of_another_count_or_size_is_refused(tablet, uneven, tmp_path):
    _, lights, _ = tablet
    n = len(lights)
    names = [f"img_{k:02d}.tif" for k in range(n)]
    _write_board(tmp_path / "few", lights[:-2], uneven[:-2], names[:-2])
    with pytest.raises(InputError) as exc:
        load_flat_field(tmp_path / "few", names, lights, SHAPE)
    text = _one_line(exc, tmp_path / "few")
    assert f"{n - 2} photograph" in text and f"has {n}" in text
    big = np.ones((n, 100, 130), np.float32)
    _write_board(tmp_path / "big", lights, big, names, shape=(100, 130))
    with pytest.raises(InputError) as exc:
        load_flat_field(tmp_path / "big", names, lights, SHAPE)
    text = _one_line(exc, tmp_path / "big" / names[0])
    assert "130×100" in text and "128×96" in text
    with pytest.raises(InputError):
        load_flat_field(tmp_path / "missing", names, lights, SHAPE)


# --- grey card -------------------------------------------------------------------------------


def test_reference_intensities_recover_the_lamps_strengths(tablet):
    _, lights, _ = tablet
    rng = np.random.default_rng(7)
    strength = rng.uniform(0.6, 1.4, len(lights))
    card = 0.18 * strength * lights[:, 2]
    # The card's mean over a region of 8-bit pixels with noise: quantised, a little noisy.
    pixels = card[:, None] + 0.004 * rng.standard_normal((len(lights), 400))
    means = srgb_to_linear(np.round(255 * linear_to_srgb(pixels)) / 255).mean(axis=1)
    factors = reference_intensities(means, lights)
    assert np.median(factors) == pytest.approx(1.0)
    assert np.abs(_relative(factors, strength)).max() < 0.01


def test_reference_region_clipped_or_black_is_refused_naming_the_photograph(tablet):
    _, lights, _ = tablet
    means = np.full(len(lights), 0.2)
    names = [f"img_{k:02d}.jpg" for k in range(len(lights))]
    means[5] = 0.0005
    with pytest.raises(InputError) as exc:
        reference_intensities(means, lights, names=names)
    assert "black" in _one_line(exc, "img_05.jpg")
    means[5] = 0.2
    clipped = np.zeros(len(lights))
    clipped[9] = 0.3
    with pytest.raises(InputError) as exc:
        reference_intensities(means, lights, clipped=clipped, names=names)
    assert "clipped" in _one_line(exc, "img_09.jpg")


def test_parse_region():
    assert parse_region("10,20,30,40", (100, 200)) == (10, 20, 30, 40)
    assert parse_region(" 0, 0, 200 ,100", (100, 200)) == (0, 0, 200, 100)
    for bad in ("10,20,30", "a,b,c,d", "-1,0,5,5", "1.5,0,5,5", "0,0,0,5", "190,0,20,5", "0,90,5,20", ""):
        with pytest.raises(InputError) as exc:
            parse_region(bad, (100, 200))
        assert "--reference-region" in str(exc.value) and "\n" not in str(exc.value)


# --- stray light without an ambient frame --------------------------------------------------


def _grid_luminance(images: np.ndarray, step: int = 2) -> np.ndarray:
    lum = images @ LUMA_WEIGHTS
    return lum[:, step // 2::step, step // 2::step].reshape(len(images), -1)


@pytest.fixture(scope="module")
def stray_scene():
    surface = clay_tablet((128, 160), seed=1)
    lights = dome_lights(32, 15, 75)
    return surface, lights


@pytest.mark.parametrize("ambient", [0.05, 0.10])
def test_stray_light_warns_on_room_light(stray_scene, ambient):
    surface, lights = stray_scene
    images = to_uint16_linear(render(surface, lights, ambient=ambient, seed=2)) / np.float32(65535)
    found = estimate_stray_light(_grid_luminance(images), lights)
    assert found.warn and found.level == pytest.approx(ambient, abs=0.02)
    assert "room light" in found.message


@pytest.mark.parametrize("kind", ["matte", "glossy", "jpeg"])
def test_stray_light_quiet_in_a_dark_room(stray_scene, tmp_path, kind):
    surface, lights = stray_scene
    radiance = render(surface, lights, seed=2, specular=0.6 if kind == "glossy" else 0.0, shininess=40)
    if kind == "jpeg":
        for k, image in enumerate(radiance):
            write_jpeg8(tmp_path / f"{k}.jpg", image)
        images = np.stack([srgb_to_linear(read_image(tmp_path / f"{k}.jpg") / np.float32(255))
                           for k in range(len(lights))])
    else:
        images = to_uint16_linear(radiance) / np.float32(65535)
    found = estimate_stray_light(_grid_luminance(images), lights)
    assert found.level is not None and found.level < STRAY_LIGHT_WARN / 2
    assert not found.warn


def test_stray_light_not_measured_without_low_lights():
    surface = sphere_cap((64, 64), seed=0)
    lights = dome_lights(24, 70, 85)  # no lamp low enough to leave a side in attached shadow
    images = render(surface, lights, ambient=0.1, seed=0)
    found = estimate_stray_light(_grid_luminance(np.clip(images, 0, 1), 1), lights)
    assert found.level is None and not found.warn
    assert "not measured" in found.message


@pytest.mark.skipif(not REAL_CAT.exists(), reason="real captures not present")
def test_stray_light_quiet_on_a_real_dark_room_capture():
    from ptmcore.psdataset import read_ps_dataset

    data = read_ps_dataset(REAL_CAT)
    samples = data.stack.table[data.stack.grid(4)].reshape(len(data.stack), -1)
    found = estimate_stray_light(samples, data.lights.directions)
    assert found.level is not None and not found.warn
