"""A learned compact relighting basis: NeuralRTI trained on the CPU with NumPy.

Dulecha, Fanni, Ponchio, Pellacini and Giachetti, "Neural reflectance transformation imaging",
The Visual Computer 36 (2020) 2161–2174, replace the fixed bases of PTM and HSH by an
autoencoder trained on the capture's own pixels: an encoder MLP maps a pixel's N RGB samples
to a code of k = 9 numbers, a decoder MLP maps (code, lu, lv) to the pixel's RGB under the
light (lu, lv) (the x right and y up of the unit light vector). What is published is the
per-pixel codes (8-bit planes) and the small decoder, which a viewer evaluates per pixel.

The model is RGB, on display (sRGB-encoded) values in 0–1, as NeuralRTI trains on the
photographs' 8-bit values: the squared loss then weighs errors as the 8-bit sRGB measure of
:func:`held_out_error` and the eye do, instead of letting the bright highlights dominate.

The decoder is exactly what OpenLIME's ``ShaderNeural`` evaluates: two ELU hidden layers of
``hidden`` units and a linear RGB output. The encoder is NeuralRTI's (ELU hidden layers, a
linear code), of fixed widths instead of its 3N units: it is not published, and runs once per
pixel, not once per pixel and light. Glorot uniform initial weights, zero biases, Adam, as
NeuralRTI (Keras). The decoder's width is bounded by the viewers: OpenLIME keeps the decoder's
weights in fragment-shader uniforms, ``hidden²/4 + 4.25·hidden`` vec4s (with 9-number codes),
which must fit the 1024 vectors a desktop GPU gives a fragment shader (WebGL 2 guarantees only
224): 52 units at most (OpenLIME's own example has 50; NeuralRTI's 3N would need 216).

Forward and backward passes are written out here as batched matrix products, so BLAS does the
work: the decoder's first layer is split into a code part, computed once per pixel, and a
light part, computed once per light, and only their sums are formed for every (pixel, light)
pair. Each batch is split among threads (data parallel), because at these widths the
element-wise work, which NumPy does on one core, costs more than the products.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from .bands import run_bands
from .resources import thread_count

__all__ = ["Layer", "NeuralModel", "NeuralParameters", "apply_decoder", "decode", "dequantize_codes",
           "encode", "held_out_error", "quantize_codes", "train_neural"]

#: Pixels per chunk when encoding or decoding (a few megabytes of activations per thread).
CHUNK_PIXELS = 16384
#: Adam's constants (Kingma and Ba 2015; ε as Keras, which NeuralRTI used).
ADAM_BETA1, ADAM_BETA2, ADAM_EPSILON = 0.9, 0.999, 1e-7

#: One dense layer: weights (inputs, outputs) and bias (outputs,).
Layer = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class NeuralParameters:
    """How a :class:`NeuralModel` is built and trained.

    With the defaults, training on NeuralRTI's icon (402 × 395) takes 21 s with 48 of its
    photographs, 22 s with 54 and 24 s with all 72, on two cores of an AMD EPYC (OpenBLAS);
    the time grows with ``training_pixels`` × ``epochs`` and, less than in proportion, with the
    number of lights, and does not depend on the image size. Encoding every pixel takes a
    third of a second. Held out, the icon relights at 32.0 dB PSNR (48 photographs fitted, 24
    held out; 31.1 dB with 54 and 18, where an RGB PTM gets 22.2 and HSH of order 3 26.2:
    ``benchmarks/neural.py``).

    The defaults were chosen by that held-out error at a training time of at most ~30 s:
    at equal time, more epochs of a narrower decoder did as well as or better than a wider one
    (hidden 32 × 20 epochs: 32.0 and 32.9 dB for two seeds, 21–26 s; 48 × 16: 31.7 and 31.6,
    25–28 s; 52 × 16: 32.0 and 31.7, 26 s; the synthetic glossy tablet, 36 lights: 29.7
    against 28.7 dB for 48 × 16), and the narrower one is half the work per pixel in a viewer.
    Seeds differ by about ±0.5 dB.

    Attributes
    ----------
    code_size : int
        Numbers per pixel (NeuralRTI and OpenLIME: 9; OpenLIME reads no other size).
    encoder_widths : tuple of int
        Hidden layers of the encoder (NeuralRTI: three of 3N).
    hidden : int
        Units of each of the decoder's two hidden layers: what a viewer evaluates per pixel,
        and what dominates training time. A multiple of 4 wastes nothing in OpenLIME, which
        pads it to one; at most 52 for OpenLIME's uniforms (module docstring).
    epochs : int
        Passes over the training pixels (more of them in each epoch for a small capture:
        ``min_steps``).
    batch_size : int
        Pixels per step; each contributes all its lights to the loss.
    learning_rate : float
        Adam's initial step; it decays along a half cosine to ``final_rate`` × itself, so the
        last steps settle the weights without a validation split to watch.
    final_rate : float
        The learning rate at the end, as a fraction of ``learning_rate``.
    training_pixels : int
        Pixels sampled (uniformly, without replacement) to train on; all of them when there
        are fewer. Neighbouring pixels are much alike, so a sample of tens of thousands learns
        nearly what all of them would, in a fraction of the time.
    min_steps : int
        The fewest steps of training: a capture with too few pixels for them in ``epochs``
        passes has as many passes in each epoch as it takes. The default is the steps of the
        default ``training_pixels`` and ``epochs``: a 40 × 48 capture trained for 20 passes over
        its 1,920 pixels relit its photographs 12–17 levels off, where HSH of order 3 is 3.4
        levels off; with as many steps as a large capture, 1.9–2.9.
    seed : int
        Seeds the pixel sample, the initial weights and the order of the batches.
    """

    code_size: int = 9
    encoder_widths: tuple[int, ...] = (96, 96, 96)
    hidden: int = 32
    epochs: int = 20
    batch_size: int = 64
    learning_rate: float = 3e-3
    final_rate: float = 0.02
    training_pixels: int = 65536
    min_steps: int = 20480
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("code_size", "hidden", "epochs", "batch_size", "training_pixels", "min_steps"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"NeuralParameters.{name} must be at least 1, not {getattr(self, name)}")
        if len(self.encoder_widths) < 1 or min(int(w) for w in self.encoder_widths) < 1:
            raise ValueError(f"NeuralParameters.encoder_widths needs at least one hidden layer of at "
                             f"least one unit, not {self.encoder_widths}")
        if not (math.isfinite(self.learning_rate) and self.learning_rate > 0):
            raise ValueError(f"NeuralParameters.learning_rate must be positive, not {self.learning_rate}")
        if not (0 < self.final_rate <= 1):
            raise ValueError(f"NeuralParameters.final_rate must be in (0, 1], not {self.final_rate}")


@dataclass
class NeuralModel:
    """A trained encoder and decoder (:func:`train_neural`).

    Attributes
    ----------
    encoder : list of (weights, bias)
        ELU hidden layers, then the linear layer that gives the code.
    decoder : list of (weights, bias)
        Three layers, OpenLIME's: ``(k + 2) → hidden`` (rows: the code's, then lu's and lv's),
        ELU; ``hidden → hidden``, ELU; ``hidden → 3``, linear (display RGB).
    directions : ndarray, shape (N, 3)
        The lights of the encoder's inputs, in their order (unit vectors).
    input_offset, input_scale : ndarray, shape (N, 3)
        The encoder reads ``(samples - offset) * scale``, flattened light by light: each
        light's and channel's samples standardised over the training pixels, so that Glorot's
        initial weights suit every input whatever its light's brightness.
    loss : ndarray, shape (epochs,)
        Mean squared error of each epoch's steps, in display units (multiply the root by 255
        for 8-bit levels).
    """

    encoder: list[Layer]
    decoder: list[Layer]
    directions: np.ndarray
    input_offset: np.ndarray
    input_scale: np.ndarray
    loss: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    @property
    def code_size(self) -> int:
        """Numbers per pixel."""
        return self.encoder[-1][0].shape[1]


def _elu(z: np.ndarray) -> np.ndarray:
    """ELU in place: ``max(z, exp(min(z, 0)) - 1)``, equal to it since exp(z) - 1 ≥ z.

    Three vectorised passes instead of NumPy's slower ``expm1`` and ``where``.
    """
    t = np.minimum(z, 0)
    np.exp(t, out=t)
    t -= 1
    return np.maximum(z, t, out=z)


def _elu_backward(grad: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Gradient through an ELU from its output ``a``, in place: ×1 where a > 0, × (a + 1) else."""
    t = np.minimum(a, 0)
    t += 1
    grad *= t
    return grad


def _check_directions(directions: np.ndarray, n: int | None = None) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"light directions must be an (N, 3) array, not shape {d.shape}")
    if n is not None and d.shape[0] != n:
        raise ValueError(f"{d.shape[0]} light directions for samples of {n} lights")
    if not np.all(np.isfinite(d)):
        raise ValueError("light directions contain NaN or infinite values")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(norm < 1e-6):
        raise ValueError("a light direction is the zero vector")
    return (d / norm).astype(np.float32)


def _light_input(light: np.ndarray) -> np.ndarray:
    """(lu, lv) of one light, (1, 2) float32: the x and y of its unit vector."""
    return _check_directions(np.reshape(light, (1, -1)))[:, :2]


def _check_samples(samples: np.ndarray) -> np.ndarray:
    s = np.asarray(samples)
    if s.ndim != 3 or s.shape[0] < 1 or s.shape[1] < 1 or s.shape[2] != 3:
        raise ValueError(f"samples must be a (pixels, lights, 3) array of RGB, not shape {s.shape}")
    s = s.astype(np.float32, copy=False)
    if not np.all(np.isfinite(s)):
        raise ValueError("samples contain NaN or infinite values")
    return s


def _encode_rows(encoder: list[Layer], x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Codes of standardised inputs ``x`` (B, 3N), and the activations backpropagation needs."""
    acts = [x]
    for w, b in encoder[:-1]:
        acts.append(_elu(acts[-1] @ w + b))
    w, b = encoder[-1]
    return acts[-1] @ w + b, acts


def _decode_rows(decoder: list[Layer], code: np.ndarray, lights: np.ndarray
                 ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Decoder outputs (B, L, 3) for codes (B, k) at lights (L, 2), and its two hidden layers'
    activations (B·L, hidden)."""
    (w1, b1), (w2, b2), (w3, b3) = decoder
    k = code.shape[1]
    # The first layer of [code, lu, lv] is code @ W_code + light @ W_light: each part once.
    z = (code @ w1[:k])[:, None, :] + (lights @ w1[k:] + b1)[None, :, :]
    h1 = _elu(z.reshape(-1, z.shape[2]))
    h2 = _elu(h1 @ w2 + b2)
    return (h2 @ w3 + b3).reshape(code.shape[0], lights.shape[0], -1), (h1, h2)


def _loss_and_gradients(encoder: list[Layer], decoder: list[Layer], x: np.ndarray,
                        target: np.ndarray, lights: np.ndarray) -> tuple[float, list[Layer], list[Layer]]:
    """Mean squared error of the autoencoder on one batch and its gradients.

    Parameters
    ----------
    x : ndarray, shape (B, 3N)
        Standardised encoder inputs.
    target : ndarray, shape (B, L, 3)
        What the decoder should give at ``lights`` (L, 2).

    Returns
    -------
    loss : float
    encoder_grads, decoder_grads : list of (weights, bias)
        Shaped as the layers.
    """
    code, enc_acts = _encode_rows(encoder, x)
    y, (h1, h2) = _decode_rows(decoder, code, lights)
    residual = y - target
    loss = float(np.mean(residual * residual))
    bsz, nl, _ = target.shape
    (w1, _), (w2, _), (w3, _) = decoder

    g = (residual * (2.0 / residual.size)).reshape(-1, residual.shape[2]).astype(y.dtype, copy=False)
    grad3 = (h2.T @ g, g.sum(axis=0))
    g = _elu_backward(g @ w3.T, h2)
    grad2 = (h1.T @ g, g.sum(axis=0))
    g = _elu_backward(g @ w2.T, h1).reshape(bsz, nl, -1)
    k = code.shape[1]
    g_code = g.sum(axis=1)       # (B, hidden): each pixel's code meets every light
    g_light = g.sum(axis=0)      # (L, hidden): each light meets every pixel
    grad1 = (np.vstack([code.T @ g_code, lights.T @ g_light]), g_light.sum(axis=0))

    enc_grads: list[Layer] = []
    g = g_code @ w1[:k].T
    w, _ = encoder[-1]
    enc_grads.append((enc_acts[-1].T @ g, g.sum(axis=0)))
    g = g @ w.T
    for i in range(len(encoder) - 2, -1, -1):
        g = _elu_backward(g, enc_acts[i + 1])
        w, _ = encoder[i]
        enc_grads.append((enc_acts[i].T @ g, g.sum(axis=0)))
        if i:
            g = g @ w.T
    enc_grads.reverse()
    return loss, enc_grads, [grad1, grad2, grad3]


def _glorot(rng: np.random.Generator, n_in: int, n_out: int) -> Layer:
    """Glorot-uniform weights and zero bias (Keras' defaults, which NeuralRTI kept)."""
    limit = math.sqrt(6.0 / (n_in + n_out))
    return rng.uniform(-limit, limit, (n_in, n_out)).astype(np.float32), np.zeros(n_out, np.float32)


def _initial_layers(n_lights: int, params: NeuralParameters, rng: np.random.Generator
                    ) -> tuple[list[Layer], list[Layer]]:
    widths = [3 * n_lights, *params.encoder_widths, params.code_size]
    encoder = [_glorot(rng, a, b) for a, b in zip(widths[:-1], widths[1:])]
    widths = [params.code_size + 2, params.hidden, params.hidden, 3]
    decoder = [_glorot(rng, a, b) for a, b in zip(widths[:-1], widths[1:])]
    return encoder, decoder


def _batch_gradients(encoder: list[Layer], decoder: list[Layer], x: np.ndarray, target: np.ndarray,
                     lights: np.ndarray, pool: ThreadPoolExecutor | None, workers: int
                     ) -> tuple[float, list[Layer]]:
    """Loss and gradients (encoder's then decoder's layers) of one batch, its pixels split
    among ``workers`` threads.

    At these sizes the element-wise work (ELU, its gradient, the broadcast first layer) costs
    more than the matrix products and runs on one core, so splitting the batch, not BLAS's
    threads, is what uses the cores.
    """
    if pool is None or workers < 2 or len(x) < 2 * workers:
        loss, enc_g, dec_g = _loss_and_gradients(encoder, decoder, x, target, lights)
        return loss, [*enc_g, *dec_g]
    parts = np.array_split(np.arange(len(x)), workers)
    results = list(pool.map(lambda r: _loss_and_gradients(encoder, decoder, x[r], target[r], lights), parts))
    # Each part's loss is its own mean: weight by its share of the batch.
    weights = [len(r) / len(x) for r in parts]
    loss = sum(w * res[0] for w, res in zip(weights, results))
    grads = []
    for layer in zip(*[[*res[1], *res[2]] for res in results]):
        gw = sum(w * g[0] for w, g in zip(weights, layer))
        gb = sum(w * g[1] for w, g in zip(weights, layer))
        grads.append((gw, gb))
    return loss, grads


def _standardised(samples: np.ndarray, offset: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """The encoder's inputs (P, 3N) of samples (P, N, 3)."""
    return ((samples - offset) * scale).reshape(samples.shape[0], -1)


def train_neural(samples: np.ndarray, directions: np.ndarray,
                 params: NeuralParameters | None = None, *, threads: int | None = None,
                 progress: Callable[[int], None] | None = None) -> NeuralModel:
    """Train a NeuralRTI autoencoder on pixels' RGB samples.

    Each step takes ``batch_size`` pixels, encodes their samples and decodes the codes at every
    light of ``directions``; the loss is the mean squared difference from the samples,
    minimised by Adam with a cosine-decaying step.

    Parameters
    ----------
    samples : ndarray, shape (P, N, 3)
        Display (sRGB-encoded) RGB values in 0–1 of the training pixels under each light;
        every pixel or a sample of them, ``training_pixels`` of which are used.
    directions : ndarray, shape (N, 3)
        The lights (normalised here).
    params : NeuralParameters, optional
    threads : int, optional
        Threads that share each batch; default: the number of CPUs.
    progress : callable, optional
        Called with 1 after each epoch.

    Returns
    -------
    NeuralModel
        Deterministic given ``params.seed``, up to rounding, which depends on the number of
        threads (how each batch is split) and on BLAS.

    Raises
    ------
    ValueError
        If the shapes disagree or a value is not finite.
    """
    params = params or NeuralParameters()
    samples = _check_samples(samples)
    dirs = _check_directions(directions, samples.shape[1])
    rng = np.random.default_rng(params.seed)
    if samples.shape[0] > params.training_pixels:
        pick = np.sort(rng.choice(samples.shape[0], params.training_pixels, replace=False))
        samples = samples[pick]
    offset = samples.mean(axis=0)
    scale = (1.0 / np.maximum(samples.std(axis=0), 1e-3)).astype(np.float32)
    inputs = _standardised(samples, offset, scale)
    lights = dirs[:, :2]

    encoder, decoder = _initial_layers(samples.shape[1], params, rng)
    layers = [*encoder, *decoder]
    moments = [(np.zeros_like(w), np.zeros_like(b), np.zeros_like(w), np.zeros_like(b)) for w, b in layers]
    n = samples.shape[0]
    batch = min(params.batch_size, n)
    # A pass is ceil(n / batch) steps; a small capture takes more per epoch, from as many
    # shuffles of its pixels as they need.
    per_epoch = max(math.ceil(n / batch), math.ceil(params.min_steps / params.epochs))
    shuffles = 1 if per_epoch == math.ceil(n / batch) else math.ceil(per_epoch * batch / n)
    steps = params.epochs * per_epoch
    losses = np.zeros(params.epochs, np.float32)
    step = 0
    workers = thread_count(threads)
    # BLAS kept to one thread: the batch's parts already occupy the cores.
    with ThreadPoolExecutor(max_workers=workers) as pool, threadpool_limits(1 if workers > 1 else None):
        for epoch in range(params.epochs):
            order = np.concatenate([rng.permutation(n) for _ in range(shuffles)])
            total = 0.0
            seen = 0
            for s in range(0, per_epoch * batch, batch):
                rows = order[s:s + batch]
                seen += len(rows)
                loss, grads = _batch_gradients(encoder, decoder, inputs[rows], samples[rows], lights, pool, workers)
                total += loss * len(rows)
                step += 1
                rate = params.learning_rate * (params.final_rate + (1 - params.final_rate)
                                               * 0.5 * (1 + math.cos(math.pi * (step - 1) / steps)))
                # Adam's bias corrections folded into the step size.
                alpha = rate * math.sqrt(1 - ADAM_BETA2 ** step) / (1 - ADAM_BETA1 ** step)
                for (w, b), (gw, gb), (mw, mb, vw, vb) in zip(layers, grads, moments):
                    for p, g, m, v in ((w, gw, mw, vw), (b, gb, mb, vb)):
                        m *= ADAM_BETA1
                        m += (1 - ADAM_BETA1) * g
                        v *= ADAM_BETA2
                        v += (1 - ADAM_BETA2) * (g * g)
                        p -= alpha * m / (np.sqrt(v) + ADAM_EPSILON)
            losses[epoch] = total / seen
            if progress is not None:
                progress(1)
    return NeuralModel(encoder, decoder, dirs, offset.astype(np.float32), scale, losses)


def encode(model: NeuralModel, samples: np.ndarray, *, threads: int | None = None) -> np.ndarray:
    """Codes of pixels from their samples.

    Parameters
    ----------
    model : NeuralModel
    samples : ndarray, shape (P, N, 3)
        Display RGB values in 0–1 under the model's lights, in its order; for a held-out test,
        those of the fitting lights only.
    threads : int, optional
        Chunks of pixels encoded at once; default: the number of CPUs.

    Returns
    -------
    ndarray, shape (P, k), float32
    """
    samples = _check_samples(samples)
    n = len(model.directions)
    if samples.shape[1] != n:
        raise ValueError(f"the model reads {n} samples per pixel, not {samples.shape[1]}")
    codes = np.empty((samples.shape[0], model.code_size), np.float32)

    def chunk(r0: int, r1: int) -> None:
        x = _standardised(samples[r0:r1], model.input_offset, model.input_scale)
        codes[r0:r1] = _encode_rows(model.encoder, x)[0]

    run_bands(samples.shape[0], CHUNK_PIXELS, chunk, threads=threads)
    return codes


def apply_decoder(network: list[Layer], codes: np.ndarray, light: np.ndarray, *,
                  threads: int | None = None) -> np.ndarray:
    """A decoder's RGB for every code under one light, in chunks of pixels (bounded memory).

    Parameters
    ----------
    network : list of (weights, bias)
        The three layers of :attr:`NeuralModel.decoder`.
    codes : ndarray, shape (..., k)
    light : ndarray, shape (3,)
        Light direction (normalised here); the decoder reads its x and y.
    threads : int, optional
        Chunks decoded at once; default: the number of CPUs.

    Returns
    -------
    ndarray, shape (..., 3), float32
        Display values, not clipped.
    """
    k = network[0][0].shape[0] - 2
    codes = np.asarray(codes, dtype=np.float32)
    if codes.ndim < 1 or codes.shape[-1] != k:
        raise ValueError(f"codes must end in an axis of {k}, not shape {codes.shape}")
    (w1, b1), (w2, b2), (w3, b3) = network
    bias1 = _light_input(light) @ w1[k:] + b1  # the light's part of the first layer, once
    flat = codes.reshape(-1, k)
    out = np.empty((flat.shape[0], 3), np.float32)

    def chunk(r0: int, r1: int) -> None:
        h = _elu(flat[r0:r1] @ w1[:k] + bias1)
        out[r0:r1] = _elu(h @ w2 + b2) @ w3 + b3

    run_bands(flat.shape[0], CHUNK_PIXELS, chunk, threads=threads)
    return out.reshape(codes.shape[:-1] + (3,))


def decode(model: NeuralModel, codes: np.ndarray, light: np.ndarray, *, threads: int | None = None) -> np.ndarray:
    """Every pixel's RGB under one light: :func:`apply_decoder` of the model's decoder.

    Parameters
    ----------
    model : NeuralModel
    codes : ndarray, shape (..., k)
        From :func:`encode` (or :func:`dequantize_codes`).
    light : ndarray, shape (3,)
    threads : int, optional

    Returns
    -------
    ndarray, shape (..., 3), float32
        Display values, not clipped.
    """
    return apply_decoder(model.decoder, codes, light, threads=threads)


def quantize_codes(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Codes as they are published: 8 bits per number, each code component over its range.

    Returns
    -------
    planes : ndarray of uint8, same shape as ``codes`` (..., k)
        ``rint((code - low) / (high - low) · 255)``; 0 where a component is constant.
    low, high : ndarray, shape (k,), float32
        Each component's minimum and maximum (OpenLIME's ``min`` and ``max``), so that
        ``code ≈ low + planes / 255 · (high - low)`` within half a step.
    """
    codes = np.asarray(codes, dtype=np.float32)
    flat = codes.reshape(-1, codes.shape[-1])
    low, high = flat.min(axis=0), flat.max(axis=0)
    span = high - low
    step = np.where(span > 0, np.float32(255.0) / np.where(span > 0, span, 1), 0).astype(np.float32)
    planes = np.clip(np.rint((codes - low) * step), 0, 255).astype(np.uint8)
    return planes, low, high


def dequantize_codes(planes: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Float codes from :func:`quantize_codes`' planes, as OpenLIME decodes them."""
    low = np.asarray(low, np.float32)
    return planes.astype(np.float32) / np.float32(255.0) * (np.asarray(high, np.float32) - low) + low


def held_out_error(samples: np.ndarray, directions: np.ndarray, held_out_indices: np.ndarray,
                   params: NeuralParameters | None = None, *, threads: int | None = None) -> float:
    """RMSE at lights the model never saw, in 8-bit sRGB levels of R, G and B.

    The model is trained on the other (fitting) lights: the encoder reads only their samples
    and the decoder is fitted only at them. The pixels' codes are then decoded at the held-out
    lights, clipped to 0–1 as a display shows them, and compared with the samples there. This
    is the measure to choose it by against the linear bases, whose own residuals at the fitting
    lights flatter them as the network's training loss flatters it.

    Parameters
    ----------
    samples : ndarray, shape (P, N, 3)
        Display RGB values in 0–1 of the pixels to measure (all of them are encoded; training
        uses ``params.training_pixels`` of them).
    directions : ndarray, shape (N, 3)
    held_out_indices : array of int
        Lights left out of training; at least one, and at least three must remain.
    params : NeuralParameters, optional
    threads : int, optional

    Returns
    -------
    float
    """
    samples = _check_samples(samples)
    dirs = _check_directions(directions, samples.shape[1])
    n = samples.shape[1]
    held = np.unique(np.asarray(held_out_indices, dtype=np.int64).ravel())
    if held.size == 0 or held.min() < 0 or held.max() >= n:
        raise ValueError(f"held-out indices must be at least one light index in 0..{n - 1}")
    keep = np.setdiff1d(np.arange(n), held)
    if keep.size < 3:
        raise ValueError(f"only {keep.size} fitting lights would remain; at least 3 are needed")
    model = train_neural(samples[:, keep], dirs[keep], params, threads=threads)
    codes = encode(model, samples[:, keep], threads=threads)
    err2 = 0.0
    for i in held:
        predicted = np.clip(decode(model, codes, dirs[i], threads=threads), 0, 1)
        err2 += float(np.mean((predicted - samples[:, i]) ** 2))
    return 255.0 * math.sqrt(err2 / held.size)
