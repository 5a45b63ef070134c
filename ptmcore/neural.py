"""A learned compact relighting basis: NeuralRTI trained on the CPU with NumPy.

Dulecha, Fanni, Ponchio, Pellacini and Giachetti, "Neural reflectance transformation imaging",
The Visual Computer 36 (2020) 2161–2174, replace the fixed bases of PTM and HSH by an
autoencoder trained on the capture's own pixels: an encoder MLP maps a pixel's N samples to a
code of k = 9 numbers, a decoder MLP maps (code, lu, lv) to the pixel under that light. What is
published is the per-pixel codes (8-bit planes, one scale and bias for all of them) and the small
decoder, which a viewer evaluates per pixel (OpenLIME's ``ShaderNeural``).

Here, as in the rest of the project, the model is luminance only ("LRGB"): the encoder reads a
pixel's N luminances and the decoder returns one luminance; colour is the stack's per-pixel
chroma times it. Inside the network, luminance is sRGB-encoded (NeuralRTI trains on the
photographs' 8-bit values): the squared loss then weighs errors as the 8-bit sRGB measure of
:func:`held_out_error` and the eye do, instead of letting the bright highlights dominate.

The architecture is NeuralRTI's: ELU hidden layers, a linear code and a linear output, Glorot
uniform initial weights, zero biases, Adam. Its widths are not: NeuralRTI uses three hidden
layers of 3N units on both sides (216 for 72 RGB photographs), whose decoder costs ten times the
default's per (pixel, light) on two CPU cores, so the defaults are narrower and train on a sample of the pixels
(:class:`NeuralParameters`). Forward and backward passes are written out here as batched matrix
products, so BLAS does the work: the decoder's first layer is split into a code part, computed
once per pixel, and a light part, computed once per light, and only their sums are formed for
every (pixel, light) pair. Each batch is split among threads (data parallel), because at these
widths the element-wise work, which NumPy does on one core, costs more than the products.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from threadpoolctl import threadpool_limits

from .bands import run_bands
from .images import ImageStack, linear_to_srgb, srgb_to_linear
from .resources import thread_count

#: Pixels per chunk when encoding or relighting (a few megabytes of activations per thread).
CHUNK_PIXELS = 16384
#: Adam's constants (Kingma and Ba 2015; ε as Keras, which NeuralRTI used).
ADAM_BETA1, ADAM_BETA2, ADAM_EPSILON = 0.9, 0.999, 1e-7

#: One dense layer: weights (inputs, outputs) and bias (outputs,).
Layer = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class NeuralParameters:
    """How a :class:`NeuralModel` is built and trained.

    With the defaults, training on a 400 × 400 capture of 72 photographs takes about 45 s on
    two cores of an AMD EPYC (OpenBLAS), 35 s with 54 of them and 26 s with 36
    (``benchmarks/neural.py``). The time grows with ``training_pixels`` × ``epochs`` × the
    number of lights and does not depend on the image size; encoding every pixel takes a
    fraction of a second.

    Attributes
    ----------
    code_size : int
        Numbers per pixel (NeuralRTI: 9).
    encoder_widths : tuple of int
        Hidden layers of the encoder (NeuralRTI: three of 3N). It runs once per pixel, so it
        costs little next to the decoder, which runs once per pixel and light.
    decoder_widths : tuple of int
        Hidden layers of the decoder (NeuralRTI: three of 3N). The decoder is what a viewer
        evaluates per pixel, and what dominates training time, so it is kept small.
    epochs : int
        Passes over the training pixels.
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
    seed : int
        Seeds the pixel sample, the initial weights and the order of the batches.
    """

    code_size: int = 9
    encoder_widths: tuple[int, ...] = (96, 96, 96)
    decoder_widths: tuple[int, ...] = (64, 64, 64)
    epochs: int = 16
    batch_size: int = 64
    learning_rate: float = 3e-3
    final_rate: float = 0.02
    training_pixels: int = 65536
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("code_size", "epochs", "batch_size", "training_pixels"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"NeuralParameters.{name} must be at least 1, not {getattr(self, name)}")
        for name in ("encoder_widths", "decoder_widths"):
            widths = getattr(self, name)
            if len(widths) < 1 or min(int(w) for w in widths) < 1:
                raise ValueError(f"NeuralParameters.{name} needs at least one hidden layer of at "
                                 f"least one unit, not {widths}")
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
        The first layer's weights have ``code_size + 2`` rows: the code's, then lu's and lv's;
        ELU hidden layers, then a linear output (sRGB-encoded luminance).
    directions : ndarray, shape (N, 3)
        The lights of the encoder's inputs, in their order (unit vectors).
    input_offset, input_scale : ndarray, shape (N,)
        The encoder reads ``(sRGB(luminance) - offset) * scale``: each light's samples
        standardised over the training pixels, so that Glorot's initial weights suit every
        input whatever its light's brightness.
    loss : ndarray, shape (epochs,)
        Mean squared error of each epoch's steps, in sRGB units (multiply the root by 255 for
        8-bit levels).
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


def _light_inputs(directions: np.ndarray) -> np.ndarray:
    """(lu, lv) of unit light vectors, (L, 2)."""
    return directions[:, :2]


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


def _check_samples(samples: np.ndarray) -> np.ndarray:
    s = np.asarray(samples)
    if s.ndim != 2 or s.shape[0] < 1 or s.shape[1] < 1:
        raise ValueError(f"samples must be a (pixels, lights) array, not shape {s.shape}")
    s = s.astype(np.float32, copy=False)
    if not np.all(np.isfinite(s)):
        raise ValueError("samples contain NaN or infinite values")
    return s


def _encode_rows(encoder: list[Layer], x: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Codes of standardised inputs ``x`` (B, N), and the activations backpropagation needs."""
    acts = [x]
    for w, b in encoder[:-1]:
        acts.append(_elu(acts[-1] @ w + b))
    w, b = encoder[-1]
    return acts[-1] @ w + b, acts


def _decode_rows(decoder: list[Layer], code: np.ndarray, lights: np.ndarray
                 ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Decoder outputs (B, L) for codes (B, k) at lights (L, 2), and its activations."""
    w1, b1 = decoder[0]
    k = code.shape[1]
    # The first layer of [code, lu, lv] is code @ W_code + light @ W_light: each part once.
    z = (code @ w1[:k])[:, None, :] + (lights @ w1[k:] + b1)[None, :, :]
    acts = [_elu(z.reshape(-1, z.shape[2]))]
    for w, b in decoder[1:-1]:
        acts.append(_elu(acts[-1] @ w + b))
    w, b = decoder[-1]
    return (acts[-1] @ w + b).reshape(code.shape[0], lights.shape[0]), acts


def _loss_and_gradients(encoder: list[Layer], decoder: list[Layer], x: np.ndarray,
                        target: np.ndarray, lights: np.ndarray) -> tuple[float, list[Layer], list[Layer]]:
    """Mean squared error of the autoencoder on one batch and its gradients.

    Parameters
    ----------
    x : ndarray, shape (B, N)
        Standardised encoder inputs.
    target : ndarray, shape (B, L)
        What the decoder should give at ``lights`` (L, 2).

    Returns
    -------
    loss : float
    encoder_grads, decoder_grads : list of (weights, bias)
        Shaped as the layers.
    """
    code, enc_acts = _encode_rows(encoder, x)
    y, dec_acts = _decode_rows(decoder, code, lights)
    residual = y - target
    loss = float(np.mean(residual * residual))
    bsz, nl = target.shape

    dec_grads: list[Layer] = []
    g = (residual * (2.0 / residual.size)).reshape(-1, 1).astype(y.dtype, copy=False)
    w, _ = decoder[-1]
    dec_grads.append((dec_acts[-1].T @ g, g.sum(axis=0)))
    g = g @ w.T
    for i in range(len(decoder) - 2, 0, -1):
        g = _elu_backward(g, dec_acts[i])
        w, _ = decoder[i]
        dec_grads.append((dec_acts[i - 1].T @ g, g.sum(axis=0)))
        g = g @ w.T
    g = _elu_backward(g, dec_acts[0]).reshape(bsz, nl, -1)
    k = code.shape[1]
    g_code = g.sum(axis=1)       # (B, h): each pixel's code meets every light
    g_light = g.sum(axis=0)      # (L, h): each light meets every pixel
    w1, _ = decoder[0]
    dec_grads.append((np.vstack([code.T @ g_code, lights.T @ g_light]), g_light.sum(axis=0)))
    dec_grads.reverse()

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
    return loss, enc_grads, dec_grads


def _glorot(rng: np.random.Generator, n_in: int, n_out: int) -> Layer:
    """Glorot-uniform weights and zero bias (Keras' defaults, which NeuralRTI kept)."""
    limit = math.sqrt(6.0 / (n_in + n_out))
    return rng.uniform(-limit, limit, (n_in, n_out)).astype(np.float32), np.zeros(n_out, np.float32)


def _initial_layers(n_lights: int, params: NeuralParameters, rng: np.random.Generator
                    ) -> tuple[list[Layer], list[Layer]]:
    widths = [n_lights, *params.encoder_widths, params.code_size]
    encoder = [_glorot(rng, a, b) for a, b in zip(widths[:-1], widths[1:])]
    widths = [params.code_size + 2, *params.decoder_widths, 1]
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


def train_neural(samples: np.ndarray, directions: np.ndarray,
                 params: NeuralParameters | None = None, *, threads: int | None = None) -> NeuralModel:
    """Train a NeuralRTI autoencoder on pixels' samples.

    Each step takes ``batch_size`` pixels, encodes their samples and decodes the codes at every
    light of ``directions``; the loss is the mean squared difference from the samples in sRGB
    units, minimised by Adam with a cosine-decaying step.

    Parameters
    ----------
    samples : ndarray, shape (P, N)
        Linear luminance of the training pixels under each light (e.g. rows of
        ``ImageStack.band`` reshaped); every pixel or a sample of them, ``training_pixels`` of
        which are used.
    directions : ndarray, shape (N, 3)
        The lights (normalised here).
    params : NeuralParameters, optional
    threads : int, optional
        Threads that share each batch; default: the number of CPUs.

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
    target = linear_to_srgb(samples)
    offset = target.mean(axis=0)
    scale = (1.0 / np.maximum(target.std(axis=0), 1e-3)).astype(np.float32)
    inputs = (target - offset) * scale
    lights = _light_inputs(dirs)

    encoder, decoder = _initial_layers(samples.shape[1], params, rng)
    layers = [*encoder, *decoder]
    moments = [(np.zeros_like(w), np.zeros_like(b), np.zeros_like(w), np.zeros_like(b)) for w, b in layers]
    n = samples.shape[0]
    batch = min(params.batch_size, n)
    steps = params.epochs * math.ceil(n / batch)
    losses = np.zeros(params.epochs, np.float32)
    step = 0
    workers = thread_count(threads)
    # BLAS kept to one thread: the batch's parts already occupy the cores.
    with ThreadPoolExecutor(max_workers=workers) as pool, threadpool_limits(1 if workers > 1 else None):
        for epoch in range(params.epochs):
            order = rng.permutation(n)
            total = 0.0
            for s in range(0, n, batch):
                rows = order[s:s + batch]
                loss, grads = _batch_gradients(encoder, decoder, inputs[rows], target[rows], lights, pool, workers)
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
            losses[epoch] = total / n
    return NeuralModel(encoder, decoder, dirs, offset.astype(np.float32), scale, losses)


def _encode_samples(model: NeuralModel, samples: np.ndarray) -> np.ndarray:
    x = (linear_to_srgb(samples) - model.input_offset) * model.input_scale
    return _encode_rows(model.encoder, x)[0]


def encode(model: NeuralModel, data: ImageStack | np.ndarray, *, threads: int | None = None) -> np.ndarray:
    """Codes of a stack's pixels, or of samples.

    Parameters
    ----------
    model : NeuralModel
    data : ImageStack or ndarray, shape (P, N)
        The photographs (or samples) under the model's lights, in its order; for a held-out
        test, the stack of the fitting photographs only (``stack.select``).
    threads : int, optional
        Bands of rows encoded at once; default: the number of CPUs.

    Returns
    -------
    ndarray, float32
        ``(H, W, k)`` for a stack, ``(P, k)`` for samples.
    """
    n = len(model.directions)
    if isinstance(data, ImageStack):
        if len(data) != n:
            raise ValueError(f"the model reads {n} photographs, the stack has {len(data)}")
        h, w = data.shape
        codes = np.empty((h, w, model.code_size), np.float32)

        def work(r0: int, r1: int) -> None:
            values, _ = data.band(r0, r1)
            codes[r0:r1] = _encode_samples(model, values.reshape(n, -1).T).reshape(r1 - r0, w, -1)

        run_bands(h, max(1, CHUNK_PIXELS // w), work, threads=threads)
        return codes
    samples = _check_samples(data)
    if samples.shape[1] != n:
        raise ValueError(f"the model reads {n} samples per pixel, not {samples.shape[1]}")
    codes = np.empty((samples.shape[0], model.code_size), np.float32)

    def chunk(r0: int, r1: int) -> None:
        codes[r0:r1] = _encode_samples(model, samples[r0:r1])

    run_bands(samples.shape[0], CHUNK_PIXELS, chunk, threads=threads)
    return codes


def relight(model: NeuralModel, codes: np.ndarray, light: np.ndarray, *,
            threads: int | None = None) -> np.ndarray:
    """Linear luminance of every pixel under one light.

    Parameters
    ----------
    model : NeuralModel
    codes : ndarray, shape (..., k)
        From :func:`encode` (or :func:`dequantize_codes`).
    light : ndarray, shape (3,)
        Light direction (normalised here).
    threads : int, optional
        Chunks decoded at once; default: the number of CPUs.

    Returns
    -------
    ndarray, shape (...), float32
        Luminance in [0, 1] (the decoder's sRGB output clipped, then decoded).
    """
    codes = np.asarray(codes, dtype=np.float32)
    if codes.ndim < 1 or codes.shape[-1] != model.code_size:
        raise ValueError(f"codes must end in an axis of {model.code_size}, not shape {codes.shape}")
    lights = _light_inputs(_check_directions(np.reshape(light, (1, -1))))
    flat = codes.reshape(-1, model.code_size)
    out = np.empty(flat.shape[0], np.float32)

    def chunk(r0: int, r1: int) -> None:
        out[r0:r1] = srgb_to_linear(np.clip(_decode_rows(model.decoder, flat[r0:r1], lights)[0][:, 0], 0, 1))

    run_bands(flat.shape[0], CHUNK_PIXELS, chunk, threads=threads)
    return out.reshape(codes.shape[:-1])


def quantize_codes(codes: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Codes as NeuralRTI publishes them: 8-bit planes with one bias and scale for all.

    Returns
    -------
    planes : ndarray of uint8, same shape as ``codes``
        ``round((code - bias) / scale)``.
    bias, scale : float
        The codes' minimum and (maximum - minimum) / 255.
    """
    codes = np.asarray(codes, dtype=np.float32)
    lo, hi = float(codes.min()), float(codes.max())
    scale = max(hi - lo, 1e-12) / 255.0
    planes = np.rint((codes - lo) / scale).clip(0, 255).astype(np.uint8)
    return planes, lo, scale


def dequantize_codes(planes: np.ndarray, bias: float, scale: float) -> np.ndarray:
    """Float codes from :func:`quantize_codes`' planes."""
    return (planes.astype(np.float32) * np.float32(scale) + np.float32(bias))


def held_out_error(samples: np.ndarray, directions: np.ndarray, held_out_indices: np.ndarray,
                   params: NeuralParameters | None = None) -> float:
    """RMSE at lights the model never saw, in 8-bit sRGB levels.

    The model is trained on the other (fitting) lights: the encoder reads only their samples
    and the decoder is fitted only at them. The pixels' codes are then decoded at the held-out
    lights and compared with the samples there, as ``255 · sRGB(luminance)``. This is the
    measure to choose it by against the linear bases, whose own residuals at the fitting
    lights flatter them as the network's training loss flatters it.

    Parameters
    ----------
    samples : ndarray, shape (P, N)
        Linear luminance of the pixels to measure (all of them are encoded; training uses
        ``params.training_pixels`` of them).
    directions : ndarray, shape (N, 3)
    held_out_indices : array of int
        Lights left out of training; at least one, and at least three must remain.
    params : NeuralParameters, optional

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
    model = train_neural(samples[:, keep], dirs[keep], params)
    codes = encode(model, samples[:, keep])
    err2 = 0.0
    for i in held:
        predicted = linear_to_srgb(relight(model, codes, dirs[i]))
        err2 += float(np.mean((predicted - linear_to_srgb(samples[:, i])) ** 2))
    return 255.0 * math.sqrt(err2 / held.size)
