"""One decoding pass for everything (issue 14): the stack, the colour, HP's PTM (LRGB and RGB
format) and the HSH come from one read of each photograph, and equal, bit for bit, what the two
passes made before (the OpenCV reduction of ``load_stack``, then the NumPy sums of the streamed
fits, both reproduced here as references)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

import ptmcore.reduce as reduce_module
import ptmcore.streaming as streaming
from data_synthetic import write_capture
from ptmcore.errors import InputError
from ptmcore.fit import fit_matrix
from ptmcore.hsh import hsh_fit_matrix
from ptmcore.images import (
    LUMA_WEIGHTS,
    UINT16_TABLE,
    ImageStack,
    _chroma_in_place,
    linear_to_srgb,
    load_stack,
    load_stack_and_fits,
    read_image,
    srgb_to_linear,
)
from ptmcore.intensity import apply_intensities, estimate_intensities
from ptmcore.lp import LightSet, read_lp
from ptmcore.ptmencoded import HP_LUMA_WEIGHTS, EncodedFit, fit_ptm_encoded, fit_ptm_rgb_encoded
from ptmcore.ptmfile import write_ptm
from ptmcore.rtifile import fit_rti_hsh, write_rti_hsh
from reconstruct.pipeline import RunOptions, load_capture, run_capture
from reconstruct.pipeline.stages import fit_relighting

# --- the two passes as they were -------------------------------------------------------------


def _old_stack(photos: list[np.ndarray], linearize: bool = True, gains: np.ndarray | None = None):
    """The OpenCV reduction of ``load_stack`` before the fused kernel: codes, chroma, clip counts."""
    import cv2

    h, w = photos[0].shape[:2]
    lum = np.empty((len(photos), h, w), np.uint16)
    channel_sum = np.zeros((h, w, 3), np.float32)
    counts = []
    for k, img in enumerate(photos):
        weights = LUMA_WEIGHTS if gains is None else (LUMA_WEIGHTS * gains[k]).astype(np.float32)
        grey = img.ndim == 2
        if img.dtype == np.float32:
            lin = np.clip(img, 0.0, 1.0)
            contrib = np.round((lin[..., None] if grey else lin) * (weights * np.float32(65534.0))).astype(np.uint16)
            clipped = (img >= 1.0) if grey else (img >= 1.0).any(axis=2)
        else:
            block = cv2.merge([img, img, img]) if grey else np.ascontiguousarray(img)
            if img.dtype == np.uint8:
                v = np.arange(256, dtype=np.float32) / np.float32(255.0)
                table = np.round((srgb_to_linear(v) if linearize else v)[None, :, None] * weights * 65534.0)
                contrib = cv2.LUT(block, table.astype(np.uint16))
                top = 254
            else:
                contrib = cv2.transform(block, np.diag(weights * np.float32(65534.0 / 65535.0)))
                top = 65534
            clipped = cv2.inRange(block, (0, 0, 0), (top, top, top)) == 0
        out = cv2.transform(contrib, np.ones((1, 3), np.float32))
        np.minimum(out, np.uint16(65534), out=out)
        out[clipped] = 65535
        lum[k] = out
        counts.append(int(clipped.sum()))
        cv2.accumulate(contrib, channel_sum)
    return lum, _chroma_in_place(channel_sum), np.array(counts)


def _encoded(img: np.ndarray) -> np.ndarray:
    """The old ``streaming.encoded_rows``: float32 (H, W, 3) in 0..255 units."""
    if img.dtype == np.uint8:
        out = img.astype(np.float32)
    elif img.dtype == np.uint16:
        out = img.astype(np.float32) * np.float32(1 / 257)
    else:
        out = img.astype(np.float32) * np.float32(255)
    if out.ndim == 2:
        out = out[..., None]
    return np.repeat(out, 3, axis=2) if out.shape[2] == 1 else out


def _old_lrgb(photos: list[np.ndarray], directions: np.ndarray, solver: str = "pinv"):
    """The old NumPy sums and finish of ``fit_ptm_encoded``."""
    pinv = fit_matrix(directions, solver).astype(np.float32)
    wr, wg, wb = (np.float32(x) for x in HP_LUMA_WEIGHTS)
    shape = photos[0].shape[:2]
    acc, peak = np.zeros((6,) + shape, np.float32), np.zeros(shape, np.float32)
    cy, y2 = np.zeros((3,) + shape, np.float32), np.zeros(shape, np.float32)
    for k, img in enumerate(photos):
        c = _encoded(img)
        y = c[..., 0] * wr + c[..., 1] * wg + c[..., 2] * wb
        for j in range(6):
            acc[j] += y * pinv[j, k]
        np.maximum(peak, y, out=peak)
        for j in range(3):
            cy[j] += c[..., j] * y
        y2 += y * y
    with np.errstate(divide="ignore", invalid="ignore"):
        norm = np.where(peak > 0, np.float32(255) / peak, np.float32(0))[..., None]
        coefficients = np.moveaxis(acc, 0, -1) * norm
        colour = np.floor(peak[..., None] * np.moveaxis(cy, 0, -1) / y2[..., None])
    rgb = np.clip(np.nan_to_num(colour, nan=0.0, posinf=255.0), 0, 255).astype(np.uint8)
    return coefficients, rgb


def _old_channels(photos: list[np.ndarray], matrix: np.ndarray) -> np.ndarray:
    """The old ``streaming.fit_channels``: (H, W, 3, K)."""
    m = np.asarray(matrix, np.float32)
    acc = np.zeros((3, m.shape[0]) + photos[0].shape[:2], np.float32)
    for k, img in enumerate(photos):
        c = _encoded(img)
        for ch in range(3):
            for j in range(m.shape[0]):
                acc[ch, j] += c[..., ch] * m[j, k]
    return np.moveaxis(acc, (0, 1), (2, 3))


def _hsh_matrix(directions: np.ndarray) -> np.ndarray:
    return (hsh_fit_matrix(directions, 3) / 255.0).astype(np.float32)


def _assert_same_stack(stack: ImageStack, photos: list[np.ndarray], **kw) -> None:
    lum, chroma, counts = _old_stack(photos, **kw)
    np.testing.assert_array_equal(stack.luminance, lum)
    # Sums of integer contributions are exact in float32 whatever the order: the chroma too.
    np.testing.assert_array_equal(stack.chroma, chroma)
    np.testing.assert_array_equal(stack.saturated, counts)


# --- fixtures --------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=["jpeg8", "tiff16"])
def synthetic(request, tmp_path_factory):
    """A small capture of odd size with clipped highlights, and its photographs as arrays."""
    folder = tmp_path_factory.mktemp(request.param) / "cap"
    info = write_capture(folder, "tablet", shape=(37, 53), n_lights=11, encoding=request.param, seed=5,
                         specular=0.8, shininess=8.0)
    lights = read_lp(info.lp_path)
    photos = [read_image(p) for p in lights.paths]
    return lights, photos


@pytest.fixture(params=["default", "small bands, one photograph per thread"])
def schedule(request, monkeypatch):
    """Default bands and groups, or many bands of a few rows and groups of one photograph per
    thread, so that many groups follow each other."""
    if request.param != "default":
        monkeypatch.setattr(reduce_module, "_BAND_PIXELS", 100)
        monkeypatch.setattr(reduce_module, "_GROUP_BYTES", 1)
    return request.param


# --- the fused pass equals the two passes ------------------------------------------------------


def test_fixture_one_pass_gives_ptmfitters_file_and_the_old_stack(shared_fixture, tmp_path):
    lights = read_lp(shared_fixture / "reference_8x5.lp")
    photos = [read_image(p) for p in lights.paths]
    stack, fits = load_stack_and_fits(lights.paths, fit=EncodedFit(lights.directions, "lrgb"), threads=2)
    _assert_same_stack(stack, photos)
    write_ptm(tmp_path / "one.ptm", fits.coefficients, fits.rgb)
    assert (tmp_path / "one.ptm").read_bytes() == (shared_fixture / "reference_8x5.ptm").read_bytes()
    old_c, old_rgb = _old_lrgb(photos, lights.directions)
    np.testing.assert_array_equal(fits.coefficients, old_c)
    np.testing.assert_array_equal(fits.rgb, old_rgb)


def test_fixture_rgb_format_and_hsh_in_one_pass(shared_fixture):
    lights = read_lp(shared_fixture / "reference_8x5.lp")
    photos = [read_image(p) for p in lights.paths]
    stack, fits = load_stack_and_fits(lights.paths, fit=EncodedFit(lights.directions, "rgb", hsh_order=3))
    _assert_same_stack(stack, photos)
    assert fits.rgb is None
    np.testing.assert_array_equal(fits.coefficients, _old_channels(photos, fit_matrix(lights.directions)))
    np.testing.assert_array_equal(fits.hsh, _old_channels(photos, _hsh_matrix(lights.directions)))


@pytest.mark.parametrize("threads", [1, 2])
def test_synthetic_one_pass_equals_two_passes(synthetic, schedule, threads):
    lights, photos = synthetic
    d = lights.directions
    stack, fits = load_stack_and_fits(lights.paths, fit=EncodedFit(d, "lrgb", hsh_order=3), threads=threads)
    _assert_same_stack(stack, photos)
    assert stack.saturated.sum() > 0  # the highlights clip: the marks are exercised
    old_c, old_rgb = _old_lrgb(photos, d)
    np.testing.assert_array_equal(fits.coefficients, old_c)
    np.testing.assert_array_equal(fits.rgb, old_rgb)
    np.testing.assert_array_equal(fits.hsh, _old_channels(photos, _hsh_matrix(d)))

    _, rgb_fits = load_stack_and_fits(lights.paths, fit=EncodedFit(d, "rgb", solver="lstsq"), threads=threads)
    np.testing.assert_array_equal(rgb_fits.coefficients, _old_channels(photos, fit_matrix(d, "lstsq")))
    assert rgb_fits.hsh is None


def test_streamed_fits_of_files_equal_the_old_sums(synthetic):
    """The second pass (still the public API, and the fallback) goes through the same kernel."""
    lights, photos = synthetic
    d = lights.directions
    c, rgb = fit_ptm_encoded(lights.paths, d, threads=2)
    old_c, old_rgb = _old_lrgb(photos, d)
    np.testing.assert_array_equal(c, old_c)
    np.testing.assert_array_equal(rgb, old_rgb)
    np.testing.assert_array_equal(fit_ptm_rgb_encoded(lights.paths, d), _old_channels(photos, fit_matrix(d)))
    np.testing.assert_array_equal(fit_rti_hsh(lights.paths, d, 3), _old_channels(photos, _hsh_matrix(d)))


def test_grey_float_and_mixed_photographs(tmp_path):
    """Grey PNGs and float TIFFs through the stack; arrays of mixed kinds (grey and colour,
    read-only and writeable) through the encoded fits."""
    rng = np.random.default_rng(4)
    d = np.array([[0.6 * np.cos(a), 0.6 * np.sin(a), 0.8] for a in np.linspace(0, 6, 7)])
    grey = [rng.integers(0, 256, (9, 11), dtype=np.uint8) for _ in range(7)]
    grey[2][0, :4] = 255
    paths = []
    for k, img in enumerate(grey):
        paths.append(tmp_path / f"g{k}.png")
        Image.fromarray(img).save(paths[-1])
    stack, fits = load_stack_and_fits(paths, fit=EncodedFit(d, "lrgb", hsh_order=2), threads=2)
    _assert_same_stack(stack, grey)
    old_c, old_rgb = _old_lrgb(grey, d)
    np.testing.assert_array_equal(fits.coefficients, old_c)
    np.testing.assert_array_equal(fits.rgb, old_rgb)

    floats = [rng.uniform(-0.1, 1.2, (9, 11, 3)).astype(np.float32) for _ in range(7)]
    fpaths = []
    for k, img in enumerate(floats):
        fpaths.append(tmp_path / f"f{k}.tif")
        tifffile.imwrite(fpaths[-1], img, photometric="rgb")
    stack, fits = load_stack_and_fits(fpaths, fit=EncodedFit(d, "lrgb"), threads=2)
    assert stack.bit_depth == 32
    _assert_same_stack(stack, floats)
    old_c, old_rgb = _old_lrgb(floats, d)
    np.testing.assert_array_equal(fits.coefficients, old_c)
    np.testing.assert_array_equal(fits.rgb, old_rgb)

    colour = rng.integers(0, 256, (9, 11, 3), dtype=np.uint8)
    frozen = colour.copy()
    frozen.flags.writeable = False
    mixed = [grey[0], colour, frozen, grey[3], np.asarray(floats[4], np.float64), grey[5], colour[..., ::-1]]
    c, rgb = fit_ptm_encoded(mixed, d, threads=2)
    old_c, old_rgb = _old_lrgb([m if m.dtype != np.float64 else m.astype(np.float32) for m in mixed], d)
    np.testing.assert_array_equal(c, old_c)
    np.testing.assert_array_equal(rgb, old_rgb)


def test_16_bit_and_gains_keep_the_old_codes(synthetic):
    lights, photos = synthetic
    gains = np.random.default_rng(1).uniform(0.5, 1.0, (len(photos), 3)).astype(np.float32)
    stack = load_stack(lights.paths, channel_gains=gains, linearize=False, threads=2)
    _assert_same_stack(stack, photos, gains=gains, linearize=False)


# --- each photograph read once -----------------------------------------------------------------


def _count_reads(monkeypatch) -> dict[Path, int]:
    reads: dict[Path, int] = {}
    original = streaming.read_image

    def counting(path, **kw):
        reads[Path(path)] = reads.get(Path(path), 0) + 1
        return original(path, **kw)

    monkeypatch.setattr(streaming, "read_image", counting)
    return reads


def test_run_reads_each_photograph_once(tmp_path, monkeypatch):
    info = write_capture(tmp_path / "cap", "tablet", shape=(40, 52), n_lights=12, encoding="jpeg8", seed=2)
    lights = read_lp(info.lp_path)
    reads = _count_reads(monkeypatch)
    import reconstruct.pipeline.stages as stages

    def no_second_pass(*args, **kw):
        raise AssertionError("the photographs were fitted a second time")

    with monkeypatch.context() as m:
        for name in ("fit_ptm_encoded", "fit_ptm_rgb_encoded", "fit_rti_hsh"):
            m.setattr(stages, name, no_second_pass)
        result = run_capture(tmp_path / "cap", tmp_path / "out", RunOptions(pixel_size=0.05, hsh=True, threads=2))
    assert reads == {p: 1 for p in lights.paths}
    # The files are those of the second pass.
    photos = [read_image(p) for p in lights.paths]
    c, rgb = _old_lrgb(photos, lights.directions)
    write_ptm(tmp_path / "old.ptm", c, rgb)
    assert result.files["coefficients.ptm"].read_bytes() == (tmp_path / "old.ptm").read_bytes()
    write_rti_hsh(tmp_path / "old.rti", _old_channels(photos, _hsh_matrix(lights.directions)), order=3)
    assert result.files["coefficients.rti"].read_bytes() == (tmp_path / "old.rti").read_bytes()
    assert any(name.startswith("web/") for name in result.files)  # the LRGB PTM's web export


def test_rgb_format_run_uses_the_decoding_pass(tmp_path, monkeypatch):
    info = write_capture(tmp_path / "cap", "tablet", shape=(30, 41), n_lights=9, encoding="tiff16", seed=6)
    lights = read_lp(info.lp_path)
    # Linear files of 16-bit photographs are their samples as stored, which the old sums made.
    options = RunOptions(ptm_format="rgb", ptm_encoding="linear")
    loaded = load_capture(tmp_path / "cap", options)
    assert loaded.fits is not None and loaded.fits.rgb is None
    reads = _count_reads(monkeypatch)
    relit = fit_relighting(loaded.lights, options, tmp_path, fits=loaded.fits)
    assert reads == {}
    assert loaded.fits.coefficients is None  # handed over, its memory gone with the caller's
    photos = [read_image(p) for p in lights.paths]
    write_ptm(tmp_path / "old.ptm", _old_channels(photos, fit_matrix(lights.directions)))
    assert (tmp_path / "coefficients.ptm").read_bytes() == (tmp_path / "old.ptm").read_bytes()
    assert relit.names == ["coefficients.ptm"]


# --- fallback when the photographs or lights changed -------------------------------------------


def test_dropped_photographs_and_other_lights_fall_back_to_the_files(synthetic, tmp_path, monkeypatch):
    lights, photos = synthetic
    d = lights.directions
    # The files' encoding in which they are the samples as stored, which the old sums made.
    opt = RunOptions(hsh=True, ptm_encoding="linear" if photos[0].dtype == np.uint16 else "srgb")

    def fits():
        return load_stack_and_fits(lights.paths, fit=EncodedFit(d, "lrgb", hsh_order=3, encoding=opt.ptm_encoding))[1]

    keep = np.ones(len(photos), bool)
    keep[[1, 4]] = False  # e.g. photographs without a usable sphere highlight
    subset = LightSet([p for p, k in zip(lights.paths, keep) if k], d[keep], None)
    moved = d.copy()
    moved[0] = [0.0, 0.6, 0.8]
    cases = {
        "dropped": (subset, opt),
        "other directions": (LightSet(lights.paths, moved, None), opt),
        "other solver": (lights, dataclasses.replace(opt, solver="lstsq")),
        "other format": (lights, dataclasses.replace(opt, ptm_format="rgb")),
    }
    for name, (used, options) in cases.items():
        made = fits()
        reads = _count_reads(monkeypatch)
        out = tmp_path / name
        out.mkdir()
        fit_relighting(used, options, out, fits=made)
        assert set(reads) == set(used.paths), name
        expected = tmp_path / f"{name}.ptm"
        kept = [read_image(p) for p in used.paths]
        if options.ptm_format == "lrgb":
            write_ptm(expected, *_old_lrgb(kept, used.directions, options.solver))
        else:
            write_ptm(expected, _old_channels(kept, fit_matrix(used.directions, options.solver)))
        assert (out / "coefficients.ptm").read_bytes() == expected.read_bytes(), name
        write_rti_hsh(tmp_path / f"{name}.rti", _old_channels(kept, _hsh_matrix(used.directions)), order=3)
        assert (out / "coefficients.rti").read_bytes() == (tmp_path / f"{name}.rti").read_bytes(), name


def test_fits_know_what_they_were_made_of(synthetic):
    lights, _ = synthetic
    _, fits = load_stack_and_fits(lights.paths, fit=EncodedFit(lights.directions, "lrgb"))
    assert fits.matches(lights.paths, lights.directions, "pinv")
    assert fits.matches([str(p) for p in lights.paths], lights.directions.tolist(), "pinv")
    assert not fits.matches(lights.paths[:-1], lights.directions[:-1], "pinv")
    assert not fits.matches(lights.paths, lights.directions, "rohde")
    assert fits.take_hsh(3) is None and fits.take_ptm("rgb") is None
    coefficients, rgb = fits.take_ptm("lrgb")
    assert coefficients.shape == (37, 53, 6) and rgb.shape == (37, 53, 3)
    assert fits.take_ptm("lrgb") is None  # handed over once


def test_a_bad_photograph_stops_the_pass_with_its_name(synthetic, tmp_path, monkeypatch):
    lights, photos = synthetic
    monkeypatch.setattr(reduce_module, "_GROUP_BYTES", 1)
    monkeypatch.setattr(reduce_module, "_BAND_PIXELS", 200)
    paths = list(lights.paths)
    broken = tmp_path / paths[6].name
    broken.write_bytes(paths[6].read_bytes()[:50])
    paths[6] = broken
    with pytest.raises(InputError, match=broken.name):
        load_stack_and_fits(paths, fit=EncodedFit(lights.directions, "lrgb"), threads=2)
    small = tmp_path / ("small" + paths[8].suffix)
    Image.fromarray(np.zeros((5, 5), np.uint8)).save(small.with_suffix(".png"))
    paths[6], paths[8] = lights.paths[6], small.with_suffix(".png")
    with pytest.raises(InputError, match="same size"):
        load_stack_and_fits(paths, fit=EncodedFit(lights.directions, "lrgb"), threads=2)


#: Bytes per pixel of a run's sums while decoding with HP's LRGB fit: colour 3, PTM 6 and 5
#: more, float32.
_LRGB_SUMS = 56


@pytest.mark.parametrize(("frame", "dtype", "threads", "photos"), [
    ((4000, 6000), np.uint8, 2, 4),  # 24 MP: 288 MB, under 300 MB
    ((3600, 5000), np.uint8, 2, 5),
    ((3000, 4000), np.uint8, 2, 7),  # 12 MP: eight would fit in 300 MB but pass the run's bound
    ((2000, 3000), np.uint8, 2, 8),
    ((100, 100), np.uint8, 2, 8),
    ((4000, 6000), np.uint16, 2, 2),
    ((5792, 8688), np.uint8, 2, 2),  # 50 MP: 300 MB holds 2
    ((8000, 12000), np.uint8, 2, 2),  # one per thread, whatever the budget
    ((8000, 12000), np.uint8, 1, 1),
])
def test_a_group_stays_within_the_runs_memory_bound(frame, dtype, threads, photos):
    first = np.broadcast_to(np.zeros((), dtype), (*frame, 3))
    n = reduce_module._group_size(first, threads, _LRGB_SUMS * frame[0] * frame[1])
    assert n == photos
    # The group's room in the README's 400 MB + 70 bytes per pixel, beside the sums' 56 and
    # the process's own 270-290 MB.
    if n > threads:
        assert n * first.nbytes <= min(reduce_module._GROUP_BYTES, (100 << 20) + 14 * frame[0] * frame[1])


def test_48_photographs_of_24_megapixels_peak_under_2e9_bytes():
    # The 2 GB target read as bytes, from the peak's parts while decoding: the process's own
    # (at most 290 MiB measured), 56 bytes per pixel of sums and the group. Groups of 6 (450 MB)
    # measured 1960 MiB, 2.06e9 bytes.
    first = np.broadcast_to(np.zeros((), np.uint8), (4000, 6000, 3))
    n = reduce_module._group_size(first, 2, _LRGB_SUMS * 4000 * 6000)
    assert (290 << 20) + 56 * 4000 * 6000 + n * first.nbytes <= 2e9


def test_larger_sums_leave_a_smaller_group():
    # RGB-format PTM sums (3 × 6 floats) and colour instead of LRGB's 14 floats a pixel.
    first = np.broadcast_to(np.zeros((), np.uint8), (3000, 4000, 3))
    lrgb = reduce_module._group_size(first, 2, _LRGB_SUMS * 3000 * 4000)
    rgb = reduce_module._group_size(first, 2, (3 + 18) * 4 * 3000 * 4000)
    assert rgb < lrgb
    assert rgb == 2  # nothing left beside the sums: one photograph per thread


def test_the_group_rule_uses_the_readmes_bound():
    # One definition, used by the group rule and the pipeline's stack plan, and the formula the
    # README gives users.
    from ptmcore.resources import RUN_BASE_MB, RUN_BYTES_PER_PIXEL

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert f"≈ {RUN_BASE_MB} MB + {RUN_BYTES_PER_PIXEL} × W × H bytes" in readme


# --- the stack's table and 8-bit storage -------------------------------------------------------


def test_uint16_table_is_the_old_arithmetic(synthetic):
    lights, _ = synthetic
    stack = load_stack(lights.paths)
    assert stack.table is UINT16_TABLE and stack.table.dtype == np.float32 and stack.table.shape == (65536,)
    assert UINT16_TABLE[65535] == 1.0 and UINT16_TABLE[65534] == 1.0 and UINT16_TABLE[0] == 0.0
    values, saturated = stack.band(3, 20, 5, 40)
    raw = stack.luminance[:, 3:20, 5:40]
    old = np.minimum(raw.astype(np.float32) * np.float32(1.0 / 65534.0), 1.0)
    np.testing.assert_array_equal(values, old)
    np.testing.assert_array_equal(saturated, raw == 65535)
    assert stack.select(np.arange(len(stack)) % 2 == 0).table is stack.table


def test_8_bit_storage_of_8_bit_photographs(synthetic):
    lights, photos = synthetic
    wide = load_stack(lights.paths)
    auto = load_stack(lights.paths, storage="auto", threads=2)
    if photos[0].dtype != np.uint8:  # 16-bit photographs keep 16-bit codes
        assert auto.luminance.dtype == np.uint16
        np.testing.assert_array_equal(auto.luminance, wide.luminance)
        return
    assert auto.luminance.dtype == np.uint8 and auto.table.shape == (256,) and auto.table.dtype == np.float32
    assert auto.saturated_code == 255 and auto.table[255] == 1.0
    np.testing.assert_allclose(auto.table[:255], srgb_to_linear(np.arange(255) / 255.0), rtol=1e-6)
    clipped = wide.luminance == 65535
    expected = np.minimum(np.rint(255 * linear_to_srgb(wide.luminance / 65534.0)), 254)
    np.testing.assert_array_equal(auto.luminance[~clipped], expected[~clipped])
    assert np.all(auto.luminance[clipped] == 255) and clipped.any()
    np.testing.assert_array_equal(auto.saturated, wide.saturated)
    np.testing.assert_array_equal(auto.chroma, wide.chroma)
    values, saturated = auto.band(0, 37)
    np.testing.assert_array_equal(saturated, clipped)
    np.testing.assert_array_equal(values, auto.table[auto.luminance])

    def within_a_step(codes, coarse, fine):
        # Rounded in sRGB: the value lies between the neighbouring codes' values.
        c = codes.astype(int)
        step = np.maximum(auto.table[np.minimum(c + 1, 255)] - auto.table[c], auto.table[c] - auto.table[np.maximum(c - 1, 0)])
        return np.all((np.abs(coarse - fine) <= step + 1e-6)[~clipped])

    assert within_a_step(auto.luminance, values, wide.band(0, 37)[0])

    # Intensities read and write the 8-bit codes.
    factors = estimate_intensities(auto, lights.directions)
    np.testing.assert_allclose(factors, estimate_intensities(wide, lights.directions), rtol=0.02)
    halved = apply_intensities(auto, np.full(len(auto), 2.0))
    assert halved.luminance.dtype == np.uint8 and halved.table is auto.table
    v2, s2 = halved.band(0, 37)
    np.testing.assert_array_equal(s2, clipped)
    assert within_a_step(halved.luminance, v2, values / 2)
    brighter = apply_intensities(auto, np.full(len(auto), 0.5))
    assert (brighter.luminance == 255).sum() >= (auto.luminance == 255).sum()


def test_8_bit_storage_only_where_it_loses_nothing(synthetic):
    lights, photos = synthetic
    if photos[0].dtype != np.uint8:
        pytest.skip("8-bit photographs only")
    gains = np.full((len(photos), 3), 0.9, np.float32)
    assert load_stack(lights.paths, storage="auto", channel_gains=gains).luminance.dtype == np.uint16
    assert load_stack(lights.paths, storage="auto", linearize=False).luminance.dtype == np.uint16
    with pytest.raises(ValueError, match="storage"):
        load_stack(lights.paths, storage="uint8")


def test_image_stack_checks_its_table():
    lum = np.zeros((3, 2, 2), np.uint16)
    stack = ImageStack(lum, np.ones((2, 2, 3), np.float32), [], 16, False, np.zeros(3, np.int64))
    assert stack.table is UINT16_TABLE
    with pytest.raises(ValueError, match="table"):
        ImageStack(lum, np.ones((2, 2, 3), np.float32), [], 16, False, np.zeros(3, np.int64),
                   np.zeros(256, np.float32))


@pytest.mark.parametrize("storage", ["uint16", "auto"])
def test_photograph_arrays_with_nan_or_inf_are_refused(storage):
    # Files with them are refused by read_image; arrays reached the kernel, where a NaN's
    # luminance code indexed out of the 8-bit table (a crash with an 8-bit first photograph).
    rng = np.random.default_rng(1)
    images = [rng.integers(0, 256, (4, 300, 3), dtype=np.uint8) for _ in range(3)]
    for bad in (np.nan, np.inf, -np.inf):
        f = rng.uniform(0, 1, (4, 300, 3)).astype(np.float32)
        f[1, 5, 0] = bad
        with pytest.raises(ValueError, match="image 3: contains NaN or infinite values"):
            reduce_module.reduce_photographs([*images, f], storage=storage, threads=1)


def test_float_photographs_take_channel_gains():
    # The float samples' placeholder tables are one per set of gains, as the integer ones.
    rng = np.random.default_rng(2)
    images = [rng.uniform(0, 1, (5, 40, 3)).astype(np.float32) for _ in range(3)]
    gains = np.array([[1, 1, 1], [0.5, 0.5, 0.5], [1, 0.25, 1]], np.float32)
    gained = reduce_module.reduce_photographs(images, channel_gains=gains, threads=1)
    scaled = reduce_module.reduce_photographs([im * g for im, g in zip(images, gains)], threads=1)
    # The same light, rounded in another order: codes within one step.
    assert np.abs(gained.luminance.astype(int) - scaled.luminance).max() <= 1
    np.testing.assert_allclose(gained.chroma, scaled.chroma, rtol=1e-3, atol=1e-3)
