"""Reading photometric-stereo dataset folders (DiLiGenT layout)."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from ptmcore.errors import InputError
from ptmcore.images import LUMA_WEIGHTS, SATURATED
from ptmcore.normals import angular_error, photometric_stereo
from ptmcore.psdataset import is_ps_dataset, read_ps_dataset

from helpers import dome, sphere_normals

H, W = 48, 56
#: Reflectance per channel: a coloured object, so the per-channel division shows in chroma.
ALBEDO = np.array([0.55, 0.40, 0.25])


def _write_png16_rgb(path: Path, rgb: np.ndarray) -> None:
    # OpenCV writes BGR: reverse so that the file holds R, G, B as the layout says.
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))


def _scene(n: int = 12, seed: int = 0, low: float = 0.5, high: float = 1.6):
    dirs = dome(n, seed=seed, min_elev=25, max_elev=80)
    normals, mask = sphere_normals(H, W, radius=21.0)
    intens = np.random.default_rng(seed + 1).uniform(low, high, (n, 3))
    shading = np.maximum(np.einsum("kc,hwc->khw", dirs, normals), 0.0) * mask  # (N, H, W)
    unit = shading[..., None] * ALBEDO  # (N, H, W, 3) under lights of unit strength
    return dirs, normals, mask, intens, unit


def _write_dataset(folder: Path, n: int = 12, seed: int = 0, low: float = 0.5, high: float = 1.6, *,
                   gt: bool = True, with_mask: bool = True):
    """A rendered Lambertian sphere in the DiLiGenT layout; returns what was written."""
    folder.mkdir(parents=True, exist_ok=True)
    dirs, normals, mask, intens, unit = _scene(n, seed, low, high)
    names = [f"{k + 1:03d}.png" for k in range(n)]
    for k, name in enumerate(names):
        img = unit[k] * intens[k]  # what a light of this strength gives
        assert img.max() < 1.0
        _write_png16_rgb(folder / name, np.round(img * 65535).astype(np.uint16))
    (folder / "filenames.txt").write_text("\n".join(names) + "\n")
    np.savetxt(folder / "light_directions.txt", dirs, fmt="%.8f")
    np.savetxt(folder / "light_intensities.txt", intens, fmt="%.8f")
    if with_mask:
        cv2.imwrite(str(folder / "mask.png"), (mask * 255).astype(np.uint8))
    if gt:
        code = np.round((normals + 1) / 2 * 65535).astype(np.uint16)
        code[~mask] = 0  # DiLiGenT's background is black
        _write_png16_rgb(folder / "Normal_gt.png", code)
    return dirs, normals, mask, intens, unit


@pytest.fixture
def dataset(tmp_path):
    folder = tmp_path / "ballPNG"
    return folder, _write_dataset(folder)


def test_reads_lights_intensities_mask_and_ground_truth(dataset):
    folder, (dirs, normals, mask, intens, _) = dataset
    assert is_ps_dataset(folder)
    ds = read_ps_dataset(folder, threads=2)
    assert len(ds) == 12 and ds.stack.shape == (H, W)
    assert [p.name for p in ds.lights.paths] == [f"{k:03d}.png" for k in range(1, 13)]
    assert ds.lights.source == folder / "light_directions.txt"
    np.testing.assert_allclose(ds.lights.directions, dirs, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(ds.lights.directions, axis=1), 1.0)
    np.testing.assert_allclose(ds.intensities, intens, atol=1e-7)
    assert ds.intensities.shape == (12, 3) and ds.intensities.dtype == np.float64
    np.testing.assert_array_equal(ds.mask, mask)
    gt = ds.ground_truth_normals
    assert gt.dtype == np.float32 and gt.shape == (H, W, 3)
    # 16-bit quantisation: half a code is 7.6e-6 per component (then renormalised).
    np.testing.assert_allclose(gt[mask], normals[mask], atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(gt[mask], axis=1), 1.0, atol=1e-6)
    assert np.all(gt[~mask] == 0)


def test_intensities_are_divided_out_per_channel(dataset):
    folder, (_, _, mask, intens, unit) = dataset
    ds = read_ps_dataset(folder)
    # Some intensities are below 1, so the stack is the unit-strength render times the
    # smallest one (no sample pushed past the stored range).
    assert ds.intensity_scale == pytest.approx(intens.min())
    expected = (unit @ LUMA_WEIGHTS.astype(np.float64)) * ds.intensity_scale
    values, saturated = ds.stack.band(0, H)
    assert not saturated.any()
    # One 16-bit code of the file, divided by the intensity, plus the stored rounding.
    np.testing.assert_allclose(values, expected, atol=3e-5)
    # Chroma is the object's colour, not the lights': the division is per channel. (Channel
    # sums are kept as uint16 luminance contributions, so a dim blue channel, weight 0.07 times
    # an intensity gain, keeps about 11 bits: 0.2 % here, far below the 8-bit colour it becomes.)
    colour = ALBEDO / (ALBEDO @ LUMA_WEIGHTS)
    np.testing.assert_allclose(ds.stack.chroma[mask], np.broadcast_to(colour, (mask.sum(), 3)), rtol=2e-3)
    assert ds.stack.linearized is False and ds.stack.bit_depth == 16


def test_intensities_of_at_least_one_leave_the_scale_alone(tmp_path):
    dirs, _, _, intens, unit = _write_dataset(tmp_path / "d", low=1.0, high=1.3)
    ds = read_ps_dataset(tmp_path / "d")
    assert ds.intensity_scale == 1.0
    values, _ = ds.stack.band(0, H)
    np.testing.assert_allclose(values, unit @ LUMA_WEIGHTS.astype(np.float64), atol=3e-5)


def test_photometric_stereo_on_the_dataset_is_accurate(dataset):
    folder, (_, normals, mask, _, _) = dataset
    ds = read_ps_dataset(folder)
    ps = photometric_stereo(ds.stack, ds.lights.directions)
    err = angular_error(ps.normals[ds.mask], ds.ground_truth_normals[ds.mask])
    assert err.max() < 0.5, (err.mean(), err.max())
    assert angular_error(ps.normals, normals, mask).mean() < 0.1


def test_without_the_division_photometric_stereo_is_worse(dataset):
    # The test above means something only if the uneven intensities would have hurt.
    folder, (dirs, normals, mask, intens, unit) = dataset
    from helpers import stack_from_luminance

    raw = stack_from_luminance((unit * intens[:, None, None, :]) @ LUMA_WEIGHTS.astype(np.float64))
    err = angular_error(photometric_stereo(raw, dirs).normals, normals, mask)
    assert err.mean() > 2.0


def test_progress_threads_and_optional_files(tmp_path):
    _write_dataset(tmp_path / "d", gt=False, with_mask=False)
    calls = []
    ds = read_ps_dataset(tmp_path / "d", threads=1, progress=calls.append)
    assert calls == [1] * 12
    assert ds.mask is None and ds.ground_truth_normals is None


def test_accepts_the_light_directions_file_and_numbered_images_without_a_list(dataset):
    folder, (dirs, *_) = dataset
    (folder / "filenames.txt").unlink()
    ds = read_ps_dataset(folder / "light_directions.txt")
    assert ds.folder == folder
    assert [p.name for p in ds.lights.paths] == [f"{k:03d}.png" for k in range(1, 13)]


def test_clipped_samples_stay_clipped(dataset):
    folder, _ = dataset
    img = cv2.imread(str(folder / "003.png"), cv2.IMREAD_UNCHANGED)
    img[5, 7, 1] = 65535  # one channel at the top of the range
    cv2.imwrite(str(folder / "003.png"), img)
    ds = read_ps_dataset(folder)
    assert ds.stack.luminance[2, 5, 7] == SATURATED
    assert ds.stack.saturated[2] == 1 and ds.stack.saturated.sum() == 1


def test_normal_gt_mat_is_read_when_there_is_no_png(dataset):
    from scipy.io import savemat

    folder, (_, normals, mask, _, _) = dataset
    (folder / "Normal_gt.png").unlink()
    n = normals.copy()
    n[~mask] = 0
    savemat(folder / "Normal_gt.mat", {"Normal_gt": n.astype(np.float64)})
    ds = read_ps_dataset(folder)
    np.testing.assert_allclose(ds.ground_truth_normals[mask], normals[mask], atol=1e-6)
    assert np.all(ds.ground_truth_normals[~mask] == 0)


def test_8_bit_normal_map_and_grey_mask_codes(dataset):
    folder, (_, normals, mask, _, _) = dataset
    code = np.round((normals + 1) / 2 * 255).astype(np.uint8)
    code[~mask] = 0
    cv2.imwrite(str(folder / "Normal_gt.png"), code[..., ::-1])
    cv2.imwrite(str(folder / "mask.png"), mask.astype(np.uint8))  # 0/1 codes
    ds = read_ps_dataset(folder)
    np.testing.assert_array_equal(ds.mask, mask)
    np.testing.assert_allclose(ds.ground_truth_normals[mask], normals[mask], atol=6e-3)
    assert np.all(ds.ground_truth_normals[~mask] == 0)


def test_is_ps_dataset(tmp_path):
    assert not is_ps_dataset(tmp_path)
    assert not is_ps_dataset(tmp_path / "missing")
    (tmp_path / "light_directions.txt").write_text("0 0 1\n")
    assert not is_ps_dataset(tmp_path)
    (tmp_path / "filenames.txt").write_text("001.png\n")
    assert is_ps_dataset(tmp_path)
    assert not is_ps_dataset(tmp_path / "filenames.txt")


# --- bad input: every problem is an InputError naming the file -------------------------------


def _expect(folder: Path, culprit: str, *words: str) -> InputError:
    with pytest.raises(InputError) as info:
        read_ps_dataset(folder)
    err = info.value
    assert err.path is not None and Path(err.path).name == culprit, str(err)
    for w in words:
        assert w in err.problem, str(err)
    return err


@pytest.mark.parametrize("name", ["light_directions.txt", "light_intensities.txt", "007.png"])
def test_missing_file(dataset, name):
    folder, _ = dataset
    (folder / name).unlink()
    _expect(folder, name, "not found")


def test_missing_file_list_without_numbered_images(dataset):
    folder, _ = dataset
    (folder / "filenames.txt").unlink()
    (folder / "012.png").unlink()
    _expect(folder, "filenames.txt", "not found")


def test_missing_folder(tmp_path):
    _expect(tmp_path / "nowhere", "nowhere", "not found")


def test_count_mismatch_file_list(dataset):
    folder, _ = dataset
    names = (folder / "filenames.txt").read_text().splitlines()
    (folder / "filenames.txt").write_text("\n".join(names[:-1]))
    _expect(folder, "filenames.txt", "11 images", "12 lights")


def test_count_mismatch_intensities(dataset):
    folder, _ = dataset
    lines = (folder / "light_intensities.txt").read_text().splitlines()
    (folder / "light_intensities.txt").write_text("\n".join(lines + ["1 1 1"]))
    _expect(folder, "light_intensities.txt", "13 intensities", "12 lights")


def test_count_mismatch_directions(dataset):
    folder, _ = dataset
    lines = (folder / "light_directions.txt").read_text().splitlines()
    (folder / "light_directions.txt").write_text("\n".join(lines[:-2]))
    _expect(folder, "filenames.txt", "12 images", "10 lights")


@pytest.mark.parametrize(
    "name, line, words",
    [
        ("light_directions.txt", "0.1 0.2 abc", ("line 4", "not a number")),
        ("light_directions.txt", "0.1 0.2", ("line 4", "3 number")),
        ("light_directions.txt", "0.1 nan 0.9", ("line 4", "not a number")),
        ("light_directions.txt", "0.1 1e999 0.9", ("line 4", "not finite")),
        ("light_intensities.txt", "1.0 x 1.0", ("line 4", "not a number")),
        ("light_intensities.txt", "1.0 1.0", ("line 4",)),
        ("light_intensities.txt", "1.0 0 1.0", ("line 4", "positive")),
        ("light_intensities.txt", "1.0 1.0 -0.5", ("line 4", "positive")),
        ("light_directions.txt", "0.3 0.2 -0.1", ("line 4", "horizon")),
        ("light_directions.txt", "0.3 0.2 -0.9", ("line 4", "horizon")),
        ("light_directions.txt", "0 0 0", ("line 4", "zero length")),
    ],
)
def test_bad_lines(dataset, name, line, words):
    folder, _ = dataset
    lines = (folder / name).read_text().splitlines()
    lines[3] = line
    (folder / name).write_text("\n".join(lines) + "\n")
    _expect(folder, name, *words)


def test_mask_of_another_size(dataset):
    folder, _ = dataset
    cv2.imwrite(str(folder / "mask.png"), np.full((H + 2, W, 3), 255, np.uint8))
    _expect(folder, "mask.png", f"{W}×{H + 2}", f"{W}×{H}")


def test_normal_map_of_another_size(dataset):
    folder, _ = dataset
    cv2.imwrite(str(folder / "Normal_gt.png"), np.zeros((H, W - 1, 3), np.uint16))
    _expect(folder, "Normal_gt.png", f"{W - 1}×{H}")


def test_image_of_another_size(dataset):
    folder, _ = dataset
    cv2.imwrite(str(folder / "005.png"), np.zeros((H, W + 3, 3), np.uint16))
    _expect(folder, "005.png", "same size")


def test_corrupt_image(dataset):
    folder, _ = dataset
    (folder / "004.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    _expect(folder, "004.png", "cannot decode")


def test_too_few_images(tmp_path):
    _write_dataset(tmp_path / "d", n=2)
    _expect(tmp_path / "d", "light_directions.txt", "at least 3")


def test_photographs_as_stored_without_the_division(dataset):
    folder, (dirs, normals, mask, intens, unit) = dataset
    ds = read_ps_dataset(folder, divide_intensities=False)
    assert ds.intensity_scale == 1.0
    stored = (unit * intens[:, None, None, :]) @ LUMA_WEIGHTS.astype(np.float64)
    np.testing.assert_allclose(ds.stack.table[ds.stack.luminance], stored, atol=2e-4)


def test_run_estimates_intensities_on_the_photographs_as_stored(dataset, tmp_path):
    # Estimating on photographs already divided by the given intensities would find factors of
    # about 1 and say nothing of the lamps.
    from reconstruct.pipeline import RunOptions, load_capture

    folder, (_, _, _, intens, _) = dataset
    loaded = load_capture(folder, RunOptions(intensities="estimate"))
    found = np.asarray(loaded.intensities["factors"], dtype=np.float64)
    given = intens @ LUMA_WEIGHTS.astype(np.float64)
    ratio = found / given
    # Divided first, the ratio would vary as the given intensities do (25 % here).
    assert np.std(ratio) / np.mean(ratio) < 0.05, ratio
