"""ptmcore.displaykernel: the compiled display encoding and LRGB split against the NumPy steps."""

import numpy as np
import pytest

from ptmcore.bases import _display, _lrgb
from ptmcore.displaykernel import CURVE_POINTS, display_by_pixel, display_samples, lrgb_samples
from ptmcore.images import linear_to_srgb


def _samples(n=20, p=3000, seed=0):
    rng = np.random.default_rng(seed)
    lum = rng.uniform(0, 1.2, (n, p)).astype(np.float32) ** 2  # some above 1: clipped
    lum[:, :50] = 0.0  # black pixels
    lum[3, 60:90] = 1e-4  # deep shadows, on the curve's linear toe
    chroma = rng.uniform(0.3, 1.8, (p, 3)).astype(np.float32)
    return lum, chroma


def test_tabulated_curve_is_within_two_hundredths_of_an_8_bit_step():
    v = np.linspace(0, 1, 2_000_001, dtype=np.float64)
    shown = display_samples(v[None].astype(np.float32), np.ones((v.size, 3), np.float32))[0, :, 0]
    error = np.abs(shown - linear_to_srgb(v))
    assert error.max() < 2e-5, error.max()
    assert CURVE_POINTS >= 1024


@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_display_samples_match_numpy(encoding):
    lum, chroma = _samples()
    expected = _display(chroma[None].astype(np.float64) * lum[..., None], encoding)
    np.testing.assert_allclose(display_samples(lum, chroma, encoding), expected, atol=2e-5)


@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_display_by_pixel_is_the_same_values_by_pixel_then_channel(encoding):
    lum, chroma = _samples(n=7, p=500, seed=3)
    np.testing.assert_array_equal(display_by_pixel(lum, chroma, encoding),
                                  display_samples(lum, chroma, encoding).transpose(1, 2, 0))


@pytest.mark.parametrize("encoding", ["srgb", "linear"])
def test_lrgb_samples_match_the_numpy_split(encoding):
    lum, chroma = _samples(seed=1)
    values, colour = lrgb_samples(lum, chroma, encoding)
    ref_values, ref_colour = _lrgb(_display(chroma[None].astype(np.float64) * lum[..., None], encoding))
    assert values.dtype == colour.dtype == np.float32
    np.testing.assert_allclose(values, ref_values, atol=1e-4)
    np.testing.assert_allclose(colour, ref_colour, atol=1e-4)
    assert np.all(colour[:50] == 0) and np.all(values[:, :50] == 0)  # black stays black, no NaN
    assert colour.max() <= 1.0


def test_mismatched_shapes_and_unknown_encodings_are_refused():
    lum, chroma = _samples(p=10)
    with pytest.raises(ValueError, match="agree"):
        lrgb_samples(lum, chroma[:5])
    with pytest.raises(ValueError, match="encoding"):
        display_samples(lum, chroma, "gamma")
