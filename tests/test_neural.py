"""The NumPy NeuralRTI (ptmcore.neural): its gradients, its training, its API's checks."""

import numpy as np
import pytest

from ptmcore import neural
from ptmcore.neural import (
    NeuralParameters,
    dequantize_codes,
    encode,
    held_out_error,
    quantize_codes,
    relight,
    train_neural,
)

from helpers import dome, stack_from_luminance

SMALL = NeuralParameters(encoder_widths=(16, 16), decoder_widths=(16, 16), epochs=4, batch_size=32,
                         learning_rate=1e-2)


def lambertian(pixels: int, directions: np.ndarray, seed: int = 0) -> np.ndarray:
    """Luminance of matte pixels with normals tilted up to about 35° and albedos 0.2–0.8."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(pixels, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 1.5
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.2, 0.8, (pixels, 1))
    return (albedo * np.clip(normals @ directions.T, 0, None)).astype(np.float32)


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(1)
    params = NeuralParameters(code_size=3, encoder_widths=(5, 4), decoder_widths=(6, 5))
    encoder, decoder = neural._initial_layers(7, params, rng)

    # float64 copies, biases made non-zero so every term of the backward pass is exercised
    def perturbed(layers):
        return [(w.astype(np.float64) + 0.1 * rng.standard_normal(w.shape),
                 b.astype(np.float64) + 0.1 * rng.standard_normal(b.shape)) for w, b in layers]

    encoder, decoder = perturbed(encoder), perturbed(decoder)
    x = rng.standard_normal((4, 7))
    target = rng.random((4, 7))
    lights = rng.standard_normal((7, 2))
    _, enc_grads, dec_grads = neural._loss_and_gradients(encoder, decoder, x, target, lights)
    h = 1e-6
    for layers, grads in ((encoder, enc_grads), (decoder, dec_grads)):
        for (w, b), (gw, gb) in zip(layers, grads):
            for p, g in ((w, gw), (b, gb)):
                assert g.shape == p.shape
                numeric = np.zeros_like(p)
                for idx in np.ndindex(p.shape):
                    old = p[idx]
                    p[idx] = old + h
                    up = neural._loss_and_gradients(encoder, decoder, x, target, lights)[0]
                    p[idx] = old - h
                    down = neural._loss_and_gradients(encoder, decoder, x, target, lights)[0]
                    p[idx] = old
                    numeric[idx] = (up - down) / (2 * h)
                np.testing.assert_allclose(g, numeric, rtol=1e-5, atol=1e-8)


def test_elu_identity():
    z = np.linspace(-20, 5, 1001)
    expected = np.where(z > 0, z, np.expm1(np.minimum(z, 0)))
    np.testing.assert_allclose(neural._elu(z.copy()), expected, atol=1e-15)


def test_training_reduces_the_loss():
    d = dome(24, seed=2)
    samples = lambertian(1500, d, seed=3)
    model = train_neural(samples, d, SMALL)
    assert model.loss.shape == (SMALL.epochs,)
    assert np.all(np.isfinite(model.loss))
    assert model.loss[-1] < 0.3 * model.loss[0]


def test_lambertian_learned_at_held_out_lights():
    # 60 epochs of 3000 pixels: about two seconds. PTM's own held-out error here is 5.4 levels
    # (a Lambertian surface without shadows is nearly its quadratic); the network gets about
    # 6.7 and keeps improving with more epochs.
    d = dome(40, seed=1)
    samples = lambertian(3000, d, seed=0)
    params = NeuralParameters(encoder_widths=(32, 32), decoder_widths=(32, 32), epochs=60, batch_size=64,
                              learning_rate=1e-2)
    assert held_out_error(samples, d, np.arange(0, 40, 4), params) < 9.0


def test_deterministic_with_a_seed():
    d = dome(16, seed=4)
    samples = lambertian(600, d, seed=5)
    a = train_neural(samples, d, SMALL, threads=2)
    b = train_neural(samples, d, SMALL, threads=2)
    for (wa, ba), (wb, bb) in zip(a.encoder + a.decoder, b.encoder + b.decoder):
        np.testing.assert_allclose(wa, wb, atol=1e-5)
        np.testing.assert_allclose(ba, bb, atol=1e-5)
    c = train_neural(samples, d, NeuralParameters(**{**SMALL.__dict__, "seed": 1}), threads=2)
    assert not np.allclose(a.decoder[0][0], c.decoder[0][0], atol=1e-3)


def test_threads_change_only_rounding():
    d = dome(16, seed=4)
    samples = lambertian(600, d, seed=5)
    one = train_neural(samples, d, SMALL, threads=1)
    two = train_neural(samples, d, SMALL, threads=2)
    np.testing.assert_allclose(one.loss, two.loss, rtol=1e-3)


def test_encode_stack_equals_samples_and_relight_shapes():
    d = dome(12, seed=6)
    h, w = 5, 7
    values = lambertian(h * w, d, seed=7).T.reshape(12, h, w)
    stack = stack_from_luminance(values)
    model = train_neural(values.reshape(12, -1).T, d, SMALL)
    codes = encode(model, stack, threads=2)
    assert codes.shape == (h, w, SMALL.code_size)
    from_samples = encode(model, stack.band(0, h)[0].reshape(12, -1).T)
    np.testing.assert_allclose(codes.reshape(-1, SMALL.code_size), from_samples, atol=1e-5)
    image = relight(model, codes, np.array([0.3, -0.2, 0.9]))
    assert image.shape == (h, w) and image.dtype == np.float32
    assert np.all((image >= 0) & (image <= 1))


def test_quantized_codes_round_trip():
    codes = np.random.default_rng(8).normal(size=(4, 5, 9)).astype(np.float32)
    planes, bias, scale = quantize_codes(codes)
    assert planes.dtype == np.uint8 and planes.min() == 0 and planes.max() == 255
    np.testing.assert_allclose(dequantize_codes(planes, bias, scale), codes, atol=scale / 2 + 1e-6)


def test_bad_input_raises():
    d = dome(10, seed=9)
    good = lambertian(50, d)
    with pytest.raises(ValueError, match="NaN or infinite"):
        bad = good.copy()
        bad[3, 2] = np.nan
        train_neural(bad, d, SMALL)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        train_neural(good, d[:, :2], SMALL)
    with pytest.raises(ValueError, match="9 light directions for samples of 10 lights"):
        train_neural(good, d[:9], SMALL)
    with pytest.raises(ValueError, match="zero vector"):
        zero = d.copy()
        zero[0] = 0
        train_neural(good, zero, SMALL)
    with pytest.raises(ValueError, match=r"\(pixels, lights\)"):
        train_neural(good[0], d, SMALL)
    with pytest.raises(ValueError, match="held-out indices"):
        held_out_error(good, d, [10], SMALL)
    with pytest.raises(ValueError, match="at least 3 are needed"):
        held_out_error(good, d, np.arange(8), SMALL)
    with pytest.raises(ValueError, match="epochs must be at least 1"):
        NeuralParameters(epochs=0)
    with pytest.raises(ValueError, match="decoder_widths"):
        NeuralParameters(decoder_widths=())
    with pytest.raises(ValueError, match="learning_rate"):
        NeuralParameters(learning_rate=float("nan"))
    model = train_neural(good, d, SMALL)
    with pytest.raises(ValueError, match="reads 10 samples per pixel, not 9"):
        encode(model, good[:, :9])
    with pytest.raises(ValueError, match="reads 10 photographs, the stack has 9"):
        encode(model, stack_from_luminance(good[:, :9].T.reshape(9, 5, 10)))
    with pytest.raises(ValueError, match="codes must end in an axis of 9"):
        relight(model, np.zeros((3, 4, 8)), d[0])
