"""ptmcore.bases: every basis fitted from a stack, scored by leave-one-out, the best chosen."""

from pathlib import Path

import numpy as np
import pytest

from data_synthetic import dome_lights
from ptmcore.bases import (
    AUTO,
    NAMES,
    PCA_PLANES,
    BasisChoice,
    _lrgb,
    choose_basis,
    fit_published,
    least_squares_matrix,
    sample_stack,
    score_bases,
    viewer_distance_weights,
)
from ptmcore.images import LUMA_WEIGHTS, ImageStack, linear_to_srgb
from ptmcore.neural import NeuralParameters
from ptmcore.interpolation import (
    bilinear_loo_matrix,
    bilinear_weights,
    default_sigma,
    pca,
    rbf_loo_matrix,
    rbf_weights,
    resample_matrix,
)
from ptmcore.published import ptm_weights

DIRS = dome_lights(36)


def _stack(luminance: np.ndarray, chroma: np.ndarray) -> ImageStack:
    codes = np.rint(np.clip(luminance, 0, 1) * 65534).astype(np.uint16)
    n = len(luminance)
    return ImageStack(codes, chroma.astype(np.float32), [Path(f"{i}.tif") for i in range(n)], 16, False,
                      np.zeros(n, np.int64))


def _ptm_scene(shape=(24, 20), seed=0, dark=1.0):
    """Luminance exactly a PTM of the light per pixel (OpenLIME order), a colour per pixel."""
    rng = np.random.default_rng(seed)
    h, w = shape
    coef = np.empty((h, w, 6))
    coef[..., 0] = rng.uniform(0.25, 0.45, (h, w))
    coef[..., 1:3] = rng.uniform(-0.12, 0.12, (h, w, 2))
    coef[..., 3:] = rng.uniform(-0.06, 0.03, (h, w, 3))
    lum = np.einsum("nk,hwk->nhw", ptm_weights(DIRS), coef) * dark
    chroma = rng.uniform(0.5, 1.5, (h, w, 3))
    chroma /= (chroma @ LUMA_WEIGHTS)[..., None]
    return lum.astype(np.float32), chroma.astype(np.float32)


def test_lrgb_split_is_exact_for_a_colour_times_a_luminance():
    rng = np.random.default_rng(1)
    colour = rng.uniform(0.1, 0.9, (50, 3))
    lum = rng.uniform(0.0, 1.0, (12, 50))
    samples = lum[..., None] * colour[None]
    values, col = _lrgb(samples.astype(np.float64))
    np.testing.assert_allclose(col[None] * values[..., None], samples, atol=1e-9)
    assert col.max() <= 1 + 1e-12


def test_lrgb_split_keeps_a_saturated_colour_unclipped():
    # Pure blue of luminance 0.5: its blue channel is 0.5 / 0.0722 > 1 in units of luminance.
    samples = np.zeros((5, 1, 3))
    samples[:, 0, 2] = np.linspace(0.2, 1.0, 5)
    values, col = _lrgb(samples)
    np.testing.assert_allclose(col[None] * values[..., None], samples, atol=1e-12)
    assert col.max() == pytest.approx(1.0)


def test_a_ptm_scene_is_predicted_exactly_by_the_ptm_in_linear_light():
    lum, chroma = _ptm_scene()
    scores = {(s.name, s.encoding): s for s in score_bases(lum.reshape(len(DIRS), -1), chroma.reshape(-1, 3), DIRS,
                                                           ("ptm", "rbf"), ("linear",))}
    assert scores["ptm", "linear"].prediction < 0.05  # levels: float32 samples' rounding, amplified in the darks
    assert scores["rbf", "linear"].prediction > 10 * scores["ptm", "linear"].prediction


def _brute_force_lrgb(name, encoding, lum, chroma):
    """Leave each light out, refit the basis on the rest, predict it: RMS in 8-bit sRGB levels."""
    observed = chroma[None] * lum[..., None]
    fitted = np.clip(observed, 0, 1)
    fitted = linear_to_srgb(fitted).astype(np.float64) if encoding == "srgb" else fitted.astype(np.float64)
    values, colour = _lrgb(fitted)
    b = least_squares_matrix(name, DIRS)
    err = []
    for i in range(len(DIRS)):
        keep = np.arange(len(DIRS)) != i
        coef = np.linalg.lstsq(b[keep], values[keep], rcond=None)[0]
        pred = colour * (b[i] @ coef)[:, None]
        shown = 255 * (np.clip(pred, 0, 1) if encoding == "srgb" else linear_to_srgb(np.clip(pred, 0, 1)))
        err.append(shown - 255 * linear_to_srgb(np.clip(observed[i], 0, 1)))
    return float(np.sqrt(np.mean(np.square(err))))


@pytest.mark.parametrize("name", ["ptm", "hsh3"])
@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_least_squares_prediction_matches_refitting_without_each_light(name, encoding):
    rng = np.random.default_rng(2)
    lum, chroma = _ptm_scene(seed=3)
    lum = (lum + rng.normal(0, 0.02, lum.shape)).astype(np.float32)
    lum2, chroma2 = lum.reshape(len(DIRS), -1), chroma.reshape(-1, 3)
    (score,) = score_bases(lum2, chroma2, DIRS, (name,), (encoding,))
    assert score.prediction == pytest.approx(_brute_force_lrgb(name, encoding, lum2, chroma2), rel=1e-3)


@pytest.mark.parametrize("name", ["rbf", "bilinear"])
def test_interpolation_prediction_matches_interpolating_the_other_lights(name):
    lum, chroma = _ptm_scene(seed=4)
    lum2, chroma2 = lum.reshape(len(DIRS), -1), chroma.reshape(-1, 3)
    (score,) = score_bases(lum2, chroma2, DIRS, (name,), ("linear",))
    # By hand: compress the RGB samples with the principal components, predict each light
    # from the others with the basis's own interpolation.
    observed = np.clip(chroma2[None] * lum2[..., None], 0, 1).astype(np.float64)
    vectors = observed.transpose(1, 0, 2).reshape(observed.shape[1], -1)
    mean, comp = pca(vectors, PCA_PLANES)
    compressed = (mean + (vectors - mean) @ comp.T @ comp).reshape(-1, len(DIRS), 3).transpose(1, 0, 2)
    sigma = default_sigma(DIRS)
    p = rbf_loo_matrix(DIRS, sigma) if name == "rbf" else bilinear_loo_matrix(DIRS, 8, sigma)
    # ... and relight it at the lights themselves from all of them.
    q = (rbf_weights(DIRS, DIRS, sigma) if name == "rbf"
         else bilinear_weights(DIRS, 8) @ resample_matrix(DIRS, 8, sigma))

    def square_error(matrix):  # per light, in 8-bit sRGB levels
        shown = 255 * linear_to_srgb(np.clip(np.einsum("ij,jpc->ipc", matrix, compressed), 0, 1))
        return np.mean((shown - 255 * linear_to_srgb(observed)) ** 2, axis=(1, 2))

    left_out, at_light = square_error(p), square_error(q)
    share, spread = viewer_distance_weights(DIRS)
    expected = np.sqrt(np.sum(share * at_light + spread * np.maximum(left_out - at_light, 0)))
    assert score.prediction == pytest.approx(float(expected), rel=1e-4)
    # Between the error at the lights and the leave-one-out error.
    assert np.sqrt(np.mean(at_light)) * 0.9 < score.prediction < np.sqrt(np.mean(left_out))


def test_viewer_lights_fall_among_the_capture_lights_as_a_brute_force_count_says():
    rng = np.random.default_rng(3)
    lights = np.vstack([DIRS, [0.0, 0.0, 1.0]])
    share, spread = viewer_distance_weights(lights, count=2000)
    assert share.shape == spread.shape == (len(lights),) and share.sum() == pytest.approx(1.0)
    # Monte Carlo over random directions of the hemisphere, as the docstring defines it.
    v = rng.normal(size=(100_000, 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    gaps = np.linalg.norm(lights[:, None] - lights[None], axis=2)
    np.fill_diagonal(gaps, np.inf)
    spacing = gaps.min(axis=1)
    dist = np.linalg.norm(v[:, None] - lights[None], axis=2)
    near, d = dist.argmin(axis=1), dist.min(axis=1)
    keep = d <= spacing.max()
    mc_share = np.bincount(near[keep], minlength=len(lights)) / keep.sum()
    mc_spread = np.bincount(near[keep], weights=(d[keep] / spacing[near[keep]]) ** 2, minlength=len(lights)) / keep.sum()
    np.testing.assert_allclose(share, mc_share, atol=0.01)
    assert spread.sum() == pytest.approx(mc_spread.sum(), rel=0.05)
    # A viewer's light is on average well within a spacing of the nearest photograph.
    assert 0.1 < spread.sum() < 0.5


def test_storage_in_8_bit_linear_planes_costs_the_shadows_levels():
    # A dark object: the same prediction, but 8-bit linear planes posterise its levels.
    lum, chroma = _ptm_scene(dark=0.08)
    by = {(s.name, s.encoding): s for s in score_bases(lum.reshape(len(DIRS), -1), chroma.reshape(-1, 3), DIRS,
                                                       ("ptm",), ("srgb", "linear"))}
    assert by["ptm", "linear"].storage > 2 * by["ptm", "srgb"].storage


@pytest.mark.parametrize("name", [n for n in NAMES if n != "neural"])  # neural: its own tests below
@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_fit_published_renders_the_photographs_it_was_fitted_to(name, encoding):
    lum, chroma = _ptm_scene(shape=(18, 16), seed=5)
    stack = _stack(lum, chroma)
    basis = fit_published(stack, DIRS, name, encoding, threads=2)
    assert basis.planes.shape[:2] == (18, 16) and basis.planes.dtype == np.float32
    assert basis.name == name and basis.encoding == encoding
    errors = []
    for i in (0, 7, 20, 35):
        truth = 255 * linear_to_srgb(np.clip(chroma * lum[i][..., None], 0, 1))
        errors.append(np.abs(basis.display(DIRS[i]).astype(np.float64) - truth).mean())
    # The PTM scene is in the PTM's span; HSH and the compressed interpolations come close.
    limit = {"ptm": 1.0, "rbf": 4.0, "bilinear": 8.0}.get(name, 6.0)
    assert max(errors) < limit, errors


def test_published_forms_match_openlime():
    lum, chroma = _ptm_scene(shape=(8, 8))
    stack = _stack(lum, chroma)
    ptm = fit_published(stack, DIRS, "ptm")
    assert (ptm.type, ptm.colorspace, ptm.planes.shape[2], ptm.colour.dtype) == ("ptm", "lrgb", 6, np.uint8)
    hsh = fit_published(stack, DIRS, "hsh4")
    assert (hsh.type, hsh.order, hsh.planes.shape[2]) == ("hsh", 4, 16)
    rbf = fit_published(stack, DIRS, "rbf")
    assert (rbf.type, rbf.colorspace, rbf.basis.shape) == ("rbf", "mrgb", (PCA_PLANES + 1, len(DIRS), 3))
    assert rbf.sigma > 0 and rbf.lights.shape == (len(DIRS), 3)
    bln = fit_published(stack, DIRS, "bilinear")
    assert (bln.type, bln.resolution, bln.basis.shape) == ("bln", 8, (PCA_PLANES + 1, 64, 3))


def test_interpolating_bases_keep_more_planes_than_relight_and_lose_less():
    # A scene outside the span of 9 components: each pixel's response is a lobe at its own
    # direction, so more principal components must reproduce the photographs more closely.
    rng = np.random.default_rng(4)
    normals = rng.normal(size=(12 * 12, 3)) * [0.5, 0.5, 0.0] + [0.0, 0.0, 1.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    lum = (0.1 + 0.8 * np.clip(DIRS @ normals.T, 0, 1) ** 20).reshape(len(DIRS), 12, 12).astype(np.float32)
    chroma = np.ones((12, 12, 3), np.float32)
    stack = _stack(lum, chroma)
    assert PCA_PLANES == 18
    for name in ("rbf", "bilinear"):
        few = fit_published(stack, DIRS, name, planes=9)
        many = fit_published(stack, DIRS, name)
        assert few.planes.shape[2] == 9 and many.planes.shape[2] == PCA_PLANES == many.basis.shape[0] - 1
        if name == "rbf":  # at the lights an RBF basis reproduces its compressed photographs
            truth = 255 * linear_to_srgb(np.clip(lum[..., None] * chroma, 0, 1))
            err = [np.mean([np.abs(b.display(d).astype(float) - t).mean() for d, t in zip(DIRS[::5], truth[::5])])
                   for b in (few, many)]
            assert err[1] < err[0], err
    # A capture of few lights keeps every number of its pixels, not more.
    small = fit_published(_stack(lum[:4], chroma), DIRS[:4], "rbf")
    assert small.planes.shape[2] == 12
    with pytest.raises(ValueError, match="planes"):
        fit_published(stack, DIRS, "rbf", planes=0)


def test_choose_basis_reports_every_candidate_best_first():
    lum, chroma = _ptm_scene(shape=(30, 30), seed=6)
    choice = choose_basis(_stack(lum, chroma), DIRS)
    assert isinstance(choice, BasisChoice)
    assert {(s.name, s.encoding) for s in choice.scores} == {(n, e) for n in AUTO for e in ("srgb", "linear")}
    rms = [s.rms for s in choice.scores]
    assert rms == sorted(rms)
    assert (choice.name, choice.encoding) == (choice.scores[0].name, choice.scores[0].encoding)
    assert choice.name == "ptm"  # the scene is a PTM
    d = choice.to_dict()
    assert d["name"] == "ptm" and d["chosen_by"] == "leave-one-out" and d["margin_db"] >= 0
    assert len(d["scores"]) == 12 and d["unit"] == "8-bit sRGB levels"


def test_choose_basis_with_one_candidate_is_asked_for():
    lum, chroma = _ptm_scene(shape=(10, 10))
    choice = choose_basis(_stack(lum, chroma), DIRS, candidates=("hsh3",), encodings=("linear",))
    assert (choice.name, choice.encoding, choice.chosen_by) == ("hsh3", "linear", "asked")


def test_too_few_lights_for_every_candidate_fall_back_to_the_ptm():
    lum, chroma = _ptm_scene(shape=(6, 6))
    choice = choose_basis(_stack(lum[:6], chroma), DIRS[:6], candidates=("hsh3", "rbf"))
    assert choice.name == "ptm" and choice.scores == ()


def test_sample_stack_leaves_out_the_dark_background_and_pixels_outside_the_mask():
    lum, chroma = _ptm_scene(shape=(40, 40))
    lum[:, :, :10] = 0.0
    mask = np.ones((40, 40), bool)
    mask[30:] = False
    values, col = sample_stack(_stack(lum, chroma), count=400, mask=mask)
    assert values.shape[0] == len(DIRS) and col.shape == (values.shape[1], 3)
    assert values.mean(axis=0).min() > 0.02 * values.mean(axis=0).max()
    assert values.shape[1] < 400 * 0.75 * 0.8


def test_bad_names_and_encodings_are_refused():
    lum, chroma = _ptm_scene(shape=(6, 6))
    with pytest.raises(ValueError, match="unknown relighting basis"):
        fit_published(_stack(lum, chroma), DIRS, "sh9")
    with pytest.raises(ValueError, match="encoding"):
        fit_published(_stack(lum, chroma), DIRS, "ptm", "gamma")
    with pytest.raises(ValueError, match="chroma"):
        score_bases(lum.reshape(len(DIRS), -1), chroma[:2].reshape(-1, 3), DIRS)


#: Training for these tests' 900 pixels: 20 passes, not the steps of a large capture.
FEW_STEPS = NeuralParameters(min_steps=1)


def test_fit_published_neural_relights_the_photographs():
    lum, chroma = _ptm_scene(shape=(30, 30), seed=8)
    basis = fit_published(_stack(lum, chroma), DIRS, "neural", threads=2, neural=FEW_STEPS)
    assert (basis.type, basis.colorspace, basis.name, basis.planes.shape) == ("neural", "rgb", "neural", (30, 30, 9))
    errors = [np.abs(basis.display(DIRS[i]).astype(np.float64)
                     - 255 * linear_to_srgb(np.clip(chroma * lum[i][..., None], 0, 1))).mean() for i in (0, 9, 30)]
    # 900 pixels, a few hundred steps of training: a rough fit, far better than a flat image.
    flat = np.abs(255 * linear_to_srgb(np.clip(chroma * lum[0][..., None], 0, 1)) - 128).mean()
    assert max(errors) < 12 and max(errors) < flat / 3, errors
    with pytest.raises(ValueError, match="sRGB"):
        fit_published(_stack(lum, chroma), DIRS, "neural", "linear")


def test_choose_basis_scores_neural_on_held_out_lights():
    lum, chroma = _ptm_scene(shape=(30, 30), seed=9)
    choice = choose_basis(_stack(lum, chroma), DIRS, candidates=("ptm", "hsh3", "neural"), threads=2,
                          neural=FEW_STEPS)
    by = {(s.name, s.encoding): s for s in choice.scores}
    neural = by["neural", "srgb"]
    assert neural.measured_by == "held-out lights" and ("neural", "linear") not in by
    assert neural.planes == 9 and neural.storage > 0 and np.isfinite(neural.psnr)
    assert choice.name == "ptm" and choice.chosen_by == "leave-one-out"  # the scene is a PTM
    # Too few lights to hold a sixth out: neural is left out, the others still scored.
    few = choose_basis(_stack(lum[:12], chroma), DIRS[:12], candidates=("ptm", "neural"))
    assert [s.name for s in few.scores] == ["ptm", "ptm"]


def test_the_learned_basis_reports_its_training_as_rows():
    """Training reports the image's rows once more (an epoch a share), then the encoding its rows:
    a progress bar in rows moves while the network trains."""
    lum, chroma = _ptm_scene(shape=(30, 30), seed=8)
    few = NeuralParameters(min_steps=1, epochs=7)
    fitted: list[int] = []
    fit_published(_stack(lum, chroma), DIRS, "neural", neural=few, progress=fitted.append)
    assert sum(fitted) == 2 * 30 and len(fitted) > 7
    scored: list[int] = []
    choose_basis(_stack(lum, chroma), DIRS, candidates=("ptm", "neural"), neural=few, progress=scored.append)
    assert sum(scored) == 30 and len(scored) == 7
