"""The NumPy NeuralRTI (ptmcore.neural): its gradients, its training, its API's checks, its
published form (ptmcore.published.neural_basis)."""

import numpy as np
import pytest

from ptmcore import neural
from ptmcore.images import linear_to_srgb
from ptmcore.neural import (
    NeuralParameters,
    apply_decoder,
    decode,
    dequantize_codes,
    encode,
    held_out_error,
    quantize_codes,
    train_neural,
)
from ptmcore.published import neural_basis

from helpers import dome

# min_steps=1: one pass over these tests' few pixels per epoch, not the steps a large capture
# is given.
SMALL = NeuralParameters(encoder_widths=(16, 16), hidden=16, epochs=4, batch_size=32, learning_rate=1e-2,
                         min_steps=1)


def lambertian(pixels: int, directions: np.ndarray, seed: int = 0) -> np.ndarray:
    """Display RGB (P, N, 3) of matte pixels with normals tilted up to about 35° and colours
    of albedo 0.2–0.8 per channel."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(pixels, 3))
    normals[:, 2] = np.abs(normals[:, 2]) + 1.5
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = rng.uniform(0.2, 0.8, (pixels, 1, 3))
    shading = np.clip(normals @ directions.T, 0, None)[..., None]
    return linear_to_srgb(albedo * shading).astype(np.float32)


def _elu(z):
    return np.where(z > 0, z, np.expm1(np.minimum(z, 0)))


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(1)
    params = NeuralParameters(code_size=3, encoder_widths=(5, 4), hidden=6)
    encoder, decoder = neural._initial_layers(4, params, rng)
    assert [w.shape for w, _ in decoder] == [(5, 6), (6, 6), (6, 3)]  # OpenLIME's decoder

    # float64 copies, biases made non-zero so every term of the backward pass is exercised
    def perturbed(layers):
        return [(w.astype(np.float64) + 0.1 * rng.standard_normal(w.shape),
                 b.astype(np.float64) + 0.1 * rng.standard_normal(b.shape)) for w, b in layers]

    encoder, decoder = perturbed(encoder), perturbed(decoder)
    x = rng.standard_normal((4, 12))
    target = rng.random((4, 5, 3))
    lights = rng.standard_normal((5, 2))
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
    np.testing.assert_allclose(neural._elu(z.copy()), _elu(z), atol=1e-15)


def test_training_reduces_the_loss():
    d = dome(24, seed=2)
    samples = lambertian(1500, d, seed=3)
    model = train_neural(samples, d, SMALL)
    assert model.loss.shape == (SMALL.epochs,)
    assert np.all(np.isfinite(model.loss))
    assert model.loss[-1] < 0.3 * model.loss[0]


def test_lambertian_learned_at_held_out_lights():
    # 60 epochs of 3000 pixels: about two seconds. An RGB PTM fitted to the same display
    # values gets 8.6 levels at these held-out lights (sRGB-encoded shading is not its
    # quadratic); the network gets 7.4, and keeps improving with more epochs.
    d = dome(40, seed=1)
    samples = lambertian(3000, d, seed=0)
    params = NeuralParameters(encoder_widths=(32, 32), hidden=32, epochs=60, batch_size=64, learning_rate=1e-2,
                              min_steps=1)
    assert held_out_error(samples, d, np.arange(0, 40, 4), params) < 8.0


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


def test_encode_and_decode():
    d = dome(12, seed=6)
    samples = lambertian(700, d, seed=7)
    model = train_neural(samples, d, SMALL)
    codes = encode(model, samples, threads=2)
    assert codes.shape == (700, SMALL.code_size) and codes.dtype == np.float32
    # in chunks or at once, the same codes
    monkey = neural.CHUNK_PIXELS
    try:
        neural.CHUNK_PIXELS = 64
        np.testing.assert_allclose(encode(model, samples, threads=2), codes, atol=1e-6)
    finally:
        neural.CHUNK_PIXELS = monkey
    light = np.array([0.3, -0.2, 0.9])
    rgb = decode(model, codes, light)
    assert rgb.shape == (700, 3) and rgb.dtype == np.float32
    # The decoder, written out per pixel: [code, lu, lv] through the three layers.
    (w1, b1), (w2, b2), (w3, b3) = model.decoder
    unit = light / np.linalg.norm(light)
    x = np.hstack([codes, np.broadcast_to(unit[:2], (700, 2))]).astype(np.float64)
    expected = _elu(_elu(x @ w1 + b1) @ w2 + b2) @ w3 + b3
    np.testing.assert_allclose(rgb, expected, atol=1e-5)
    # (..., k) codes give (..., 3) images
    image = apply_decoder(model.decoder, codes.reshape(20, 35, -1), light)
    np.testing.assert_allclose(image.reshape(-1, 3), rgb, atol=1e-6)


def test_published_neural_basis_renders_as_the_decoder():
    d = dome(12, seed=6)
    samples = lambertian(20 * 35, d, seed=7)
    model = train_neural(samples, d, SMALL)
    codes = encode(model, samples).reshape(20, 35, -1)
    basis = neural_basis(model, codes)
    assert (basis.type, basis.colorspace, basis.encoding, basis.name, basis.shape) == (
        "neural", "rgb", "srgb", "neural", (20, 35))
    light = np.array([-0.4, 0.5, 0.7])
    np.testing.assert_array_equal(basis.render(light), decode(model, codes, light))
    shown = basis.display(light)
    assert shown.dtype == np.uint8 and shown.shape == (20, 35, 3)
    np.testing.assert_array_equal(shown, np.rint(np.clip(decode(model, codes, light), 0, 1) * 255))
    with pytest.raises(ValueError, match="no weights"):
        basis.weights(light)
    with pytest.raises(ValueError, match=r"\(H, W, 9\)"):
        neural_basis(model, codes[..., :8])


def test_quantized_codes_round_trip():
    rng = np.random.default_rng(8)
    codes = rng.normal(size=(4, 5, 9)).astype(np.float32) * rng.uniform(0.1, 10, 9).astype(np.float32)
    codes[..., 4] = 1.5  # a constant number: bytes 0, decoded exactly
    planes, low, high = quantize_codes(codes)
    assert planes.dtype == np.uint8 and planes.shape == codes.shape
    np.testing.assert_array_equal(low, codes.reshape(-1, 9).min(0))
    np.testing.assert_array_equal(high, codes.reshape(-1, 9).max(0))
    assert np.all(planes[..., 4] == 0)
    others = np.r_[0:4, 5:9]
    assert np.all(planes[..., others].reshape(-1, 8).min(0) == 0)
    assert np.all(planes[..., others].reshape(-1, 8).max(0) == 255)
    step = (high - low) / 255
    back = dequantize_codes(planes, low, high)
    assert np.all(np.abs(back - codes) <= step / 2 + 1e-6 * np.abs(codes).max())
    assert np.all(back[..., 4] == 1.5)
    # Quantising again gives the same bytes: the published codes are stable.
    np.testing.assert_array_equal(quantize_codes(back)[0], planes)


def test_bad_input_raises():
    d = dome(10, seed=9)
    good = lambertian(50, d)
    with pytest.raises(ValueError, match="NaN or infinite"):
        bad = good.copy()
        bad[3, 2, 1] = np.nan
        train_neural(bad, d, SMALL)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        train_neural(good, d[:, :2], SMALL)
    with pytest.raises(ValueError, match="9 light directions for samples of 10 lights"):
        train_neural(good, d[:9], SMALL)
    with pytest.raises(ValueError, match="zero vector"):
        zero = d.copy()
        zero[0] = 0
        train_neural(good, zero, SMALL)
    with pytest.raises(ValueError, match=r"\(pixels, lights, 3\)"):
        train_neural(good[..., 0], d, SMALL)
    with pytest.raises(ValueError, match="held-out indices"):
        held_out_error(good, d, [10], SMALL)
    with pytest.raises(ValueError, match="at least 3 are needed"):
        held_out_error(good, d, np.arange(8), SMALL)
    with pytest.raises(ValueError, match="epochs must be at least 1"):
        NeuralParameters(epochs=0)
    with pytest.raises(ValueError, match="hidden must be at least 1"):
        NeuralParameters(hidden=0)
    with pytest.raises(ValueError, match="encoder_widths"):
        NeuralParameters(encoder_widths=())
    with pytest.raises(ValueError, match="learning_rate"):
        NeuralParameters(learning_rate=float("nan"))
    model = train_neural(good, d, SMALL)
    with pytest.raises(ValueError, match="reads 10 samples per pixel, not 9"):
        encode(model, good[:, :9])
    with pytest.raises(ValueError, match="codes must end in an axis of 9"):
        decode(model, np.zeros((3, 4, 8)), d[0])
    with pytest.raises(ValueError, match="zero vector"):
        decode(model, np.zeros((3, 9)), np.zeros(3))


def test_a_small_capture_gets_min_steps(monkeypatch):
    import ptmcore.neural as neural

    calls = []
    real = neural._batch_gradients
    monkeypatch.setattr(neural, "_batch_gradients", lambda *a: calls.append(1) or real(*a))
    d = dome(12, seed=2)
    samples = lambertian(100, d, seed=2)  # 4 batches of 32 a pass, the last of 4 pixels
    model = train_neural(samples, d, NeuralParameters(**{**SMALL.__dict__, "epochs": 2, "min_steps": 40}))
    assert len(calls) == 40 and model.loss.shape == (2,)
    calls.clear()
    train_neural(samples, d, NeuralParameters(**{**SMALL.__dict__, "epochs": 2, "min_steps": 1}))
    assert len(calls) == 8
