"""Every relighting basis fitted from a stack, scored on the capture itself, and the best chosen.

A capture can be published for relighting in several bases (:data:`NAMES`), none best
everywhere: HSH on most objects, interpolation of the photographs over the light hemisphere
on glossy ones, RBF on coins' fine structure. This module fits any of them from an
:class:`~ptmcore.images.ImageStack` into the form viewers read,
:class:`~ptmcore.published.PublishedBasis`, and chooses among them by measuring each on the
capture: how well it predicts a photograph left out of its fit (:func:`score_bases`,
:func:`choose_basis`).

The bases, each in the encoding it is fitted in (``"srgb"``: the photographs display-encoded,
as RTIBuilder and relight fit them; ``"linear"``: linear light, which a viewer encodes for
display):

* ``ptm`` — the biquadratic of Malzbender et al. 2001, and ``hsh2``, ``hsh3``, ``hsh4`` —
  hemispherical harmonics (:mod:`ptmcore.hsh`): LRGB, a least-squares luminance fit times a
  per-pixel colour, PTMfitter's way (:mod:`ptmcore.ptmencoded`): each pixel's luminance
  normalised by its brightest photograph, the colour the least-squares colour of the samples.
* ``rbf`` and ``bilinear`` — relight's interpolating bases (:mod:`ptmcore.interpolation`): the
  RGB samples of all lights (``bilinear``: resampled onto a grid over the hemisphere) compressed
  by principal components shared by all pixels (:data:`PCA_PLANES` per-pixel coefficients;
  relight's "mrgb"), relit by interpolating the components between the lights.
* ``neural`` — NeuralRTI's learned basis (:mod:`ptmcore.neural`): a 9-number code per pixel and
  a small decoder shared by all pixels, trained on a grid of the stack's pixels; sRGB only.

The samples are display-encoded (and split into LRGB) by compiled kernels,
:mod:`ptmcore.displaykernel`, band by band.

**Scoring.** On a grid of about :data:`SAMPLE_PIXELS` lit pixels, each photograph is predicted
by the basis fitted without it, and compared with it in 8-bit sRGB levels, as a screen would
show the difference: for the least-squares bases exactly, by the PRESS identity
(:mod:`ptmcore.loo`); for the interpolating ones by interpolating the other lights'
compressed samples (the principal components are those of all lights: a left-out light
contributes one of N samples to them; for ``bilinear`` they are taken at the lights, where the
published ones are those of the grid's values). A global fit's leave-one-out error estimates its
error at a new light; an interpolation's does not: its error grows with the distance to the
nearest photographed light, a whole spacing for a left-out light and about half that for a
viewer's. So for ``rbf`` and ``bilinear`` the per-light square errors at the light itself
(relit from all lights) and left out are combined as a square error growing with the squared
distance, averaged over a viewer's lights spread over the hemisphere the capture covers
(:func:`viewer_distance_weights`). To that is added the error of storing the planes in
8 bits (each plane quantised over its range, and the colour plane of LRGB bases, uniform
error of a twelfth of a step squared, carried through the basis to the display: in linear encoding it is multiplied by the slope of
the sRGB curve, steep in the shadows). The viewers' JPEG compression is not counted; it is
alike for all bases. ``neural`` cannot be refitted per light: :func:`score_neural` trains it
once without every sixth light and scores it on those.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from .bands import BAND_BYTES, band_rows, run_bands
from .hsh import RCOND, hsh_basis
from .images import LUMA_WEIGHTS, ImageStack, linear_to_srgb
from .interpolation import (
    DEFAULT_PLANES,
    DEFAULT_RESOLUTION,
    bilinear_loo_matrix,
    bilinear_weights,
    default_sigma,
    pca,
    rbf_loo_matrix,
    rbf_weights,
    resample_matrix,
)
from .loo import loo_residuals
from .lp import as_directions
from .neural import NeuralParameters
from .published import PublishedBasis, ptm_weights

__all__ = ["AUTO", "CANDIDATES", "ENCODINGS", "NAMES", "BasisChoice", "BasisScore", "choose_basis", "fit_published",
           "sample_stack", "score_bases", "score_neural", "viewer_distance_weights"]

#: Every basis by the name the command line gives it.
NAMES = ("ptm", "hsh2", "hsh3", "hsh4", "rbf", "bilinear", "neural")
#: The bases ``--basis auto`` chooses among by default: every one fitted in seconds. ``hsh4``
#: is among them although only this project's page shows it (OpenLIME's HSH has 9 terms): it
#: was the most faithful on five of the eight captures of ``benchmarks/relight_bases.py``.
AUTO = ("ptm", "hsh2", "hsh3", "hsh4", "rbf", "bilinear")
#: The sets of candidates ``--basis-candidates`` names: ``standard`` (:data:`AUTO`),
#: ``openlime`` (those OpenLIME shows too, for a site built on it) and ``all`` (with the
#: learned basis, whose training takes tens of seconds: :mod:`ptmcore.neural`).
CANDIDATES = {
    "standard": AUTO,
    "openlime": ("ptm", "hsh2", "hsh3", "rbf", "bilinear"),
    "all": NAMES,
}
#: What a basis may be fitted to.
ENCODINGS = ("srgb", "linear")
#: Per-pixel coefficient planes of the interpolating bases: twice relight's default of 9
#: (:data:`~ptmcore.interpolation.DEFAULT_PLANES`, which relight-cli's ``-p`` raises up to 27,
#: as here), so that they are stored in as many channels as ``hsh4`` (16 planes and a colour)
#: and the choice among bases compares them at equal size. Nine components lose what sets
#: these bases apart: on lights held out of nine captures, 9 → 18 planes gained 0.3–1.3 dB
#: for RBF and 0.4–2.6 dB for bilinear (``benchmarks/relight_bases.py``, BENCHMARKS.md).
PCA_PLANES = 2 * DEFAULT_PLANES
#: Side of the bilinear basis's grid of light directions (relight's default).
BILINEAR_RESOLUTION = DEFAULT_RESOLUTION
#: Pixels scored (and from which the principal components are found).
SAMPLE_PIXELS = 20_000
#: Directions standing for a viewer's lights over the hemisphere
#: (:func:`viewer_distance_weights`).
VIEWER_LIGHTS = 4096
#: ``neural`` is scored by training it once without every this-many-th light (NeuralRTI's
#: own validation split is a sixth) and predicting those.
NEURAL_HOLD_OUT = 6
#: Fewest lights ``neural`` is scored with: a sixth of them left out must still leave the
#: network a hemisphere to learn from.
NEURAL_MIN_LIGHTS = 18
#: Pixels darker than this fraction of the brightest pixel's mean are left out of the score:
#: a black background is predicted perfectly by every basis and would only dilute it.
DARK_FRACTION = 0.02


@dataclass(frozen=True)
class BasisScore:
    """How faithfully one basis, in one encoding, relights a capture under lights it was not
    fitted to.

    Attributes
    ----------
    name, encoding : str
        The basis (:data:`NAMES`) and what it is fitted to (:data:`ENCODINGS`).
    planes : int
        Coefficient planes per pixel (the colour plane of LRGB bases not counted).
    prediction : float
        RMS difference between each left-out photograph and its prediction, 8-bit sRGB levels
        of R, G and B.
    storage : float
        RMS error of storing the planes in 8 bits, the same levels.
    rms : float
        The two together, √(prediction² + storage²).
    psnr : float
        20·log10(255 / rms), dB.
    measured_by : str
        ``"leave-one-out"``, or for ``neural`` ``"held-out lights"`` (every
        :data:`NEURAL_HOLD_OUT`-th light left out of one training).
    """

    name: str
    encoding: str
    planes: int
    prediction: float
    storage: float
    rms: float
    psnr: float
    measured_by: str = "leave-one-out"


@dataclass(frozen=True)
class BasisChoice:
    """The basis a capture is published in, and the scores it was chosen by.

    Attributes
    ----------
    name, encoding : str
        The chosen basis and encoding.
    scores : tuple of BasisScore
        Every candidate's score, best first.
    pixels : int
        Pixels the scores were measured on.
    chosen_by : str
        ``"leave-one-out"`` when chosen by the scores, ``"asked"`` when named by the user.
    """

    name: str
    encoding: str
    scores: tuple[BasisScore, ...]
    pixels: int
    chosen_by: str = "leave-one-out"

    @property
    def best(self) -> BasisScore | None:
        """The score of the chosen basis, if it was scored."""
        return next((s for s in self.scores if (s.name, s.encoding) == (self.name, self.encoding)), None)

    def to_dict(self) -> dict:
        """JSON-ready summary (report.json's ``relighting.basis``)."""
        best = self.best
        runner = next((s for s in self.scores if s is not best), None)
        out = {"name": self.name, "encoding": self.encoding, "chosen_by": self.chosen_by, "pixels": self.pixels,
               "unit": "8-bit sRGB levels",
               "scores": [{k: (round(v, 3) if isinstance(v, float) else v) for k, v in asdict(s).items()}
                          for s in self.scores]}
        if best is not None and runner is not None:
            out["margin_db"] = round(best.psnr - runner.psnr, 2)
            out["runner_up"] = f"{runner.name} ({runner.encoding})"
        return out


def _check_name(name: str) -> str:
    if name not in NAMES:
        raise ValueError(f"unknown relighting basis {name!r}; one of {', '.join(NAMES)}")
    return name


def _check_encoding(encoding: str) -> str:
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding must be one of {ENCODINGS}, not {encoding!r}")
    return encoding


def _hsh_order(name: str) -> int:
    return int(name[3:])


def least_squares_matrix(name: str, directions: np.ndarray) -> np.ndarray:
    """The ``(N, K)`` basis functions of ``ptm`` or ``hshN`` at each light, in the order of
    the published planes (the PTM's in OpenLIME's order 1, x, y, x², x·y, y²)."""
    if name == "ptm":
        return ptm_weights(directions)
    if name.startswith("hsh"):
        return hsh_basis(directions, _hsh_order(name))
    raise ValueError(f"{name!r} is not a least-squares basis")


def _display(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """Linear RGB in [0, 1] as the values a basis of ``encoding`` is fitted to."""
    rgb = np.clip(rgb, 0.0, 1.0)
    return linear_to_srgb(rgb) if encoding == "srgb" else rgb


def _lrgb(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PTMfitter's split of RGB samples ``(N, P, 3)`` into a luminance ``(N, P)`` and a colour
    ``(P, 3)`` in [0, 1] with ``samples ≈ colour · luminance``.

    Luminance is normalised by each pixel's brightest sample, the colour the least-squares
    colour of the samples; where that colour would exceed 1 (a saturated colour), it is scaled
    down and the luminance up by the same factor, so nothing is clipped.
    """
    y = samples @ LUMA_WEIGHTS.astype(samples.dtype)
    peak = y.max(axis=0)
    energy = np.einsum("np,np->p", y, y)
    colour = np.einsum("npc,np->pc", samples, y) * (peak / np.where(energy > 0, energy, 1.0))[:, None]
    over = np.maximum(colour.max(axis=1), 1.0)
    colour /= over[:, None]
    scale = over / np.where(peak > 0, peak, 1.0)
    return y * scale[None, :], colour


def sample_stack(stack: ImageStack, count: int = SAMPLE_PIXELS, mask: np.ndarray | None = None,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Linear luminance ``(N, P)`` and chroma ``(P, 3)`` of the lit pixels of a grid over the stack.

    The grid has about ``count`` pixels (every s-th row and column); pixels outside ``mask``
    or darker than :data:`DARK_FRACTION` of the brightest are dropped.
    """
    h, w = stack.shape
    step = max(1, int(np.ceil(np.sqrt(h * w / max(1, count)))))
    codes = stack.grid(step)
    luminance = stack.table[codes].reshape(len(stack), -1).astype(np.float32)
    chroma = stack.chroma[step // 2::step, step // 2::step].reshape(-1, 3).astype(np.float32)
    keep = np.ones(luminance.shape[1], bool)
    if mask is not None:
        keep &= np.asarray(mask, bool)[step // 2::step, step // 2::step].reshape(-1)
    mean = luminance.mean(axis=0)
    if keep.any():
        keep &= mean >= DARK_FRACTION * mean[keep].max()
    if not keep.any():
        keep = mean >= mean.max()
    return luminance[:, keep], chroma[keep]


def _loo_predictor(name: str, directions: np.ndarray) -> np.ndarray:
    """``(N, N)``: row i predicts light i from the others, as ``name`` interpolates."""
    sigma = default_sigma(directions)
    if name == "rbf":
        return rbf_loo_matrix(directions, sigma)
    return bilinear_loo_matrix(directions, BILINEAR_RESOLUTION, sigma)


def _relit_at_lights(name: str, directions: np.ndarray) -> np.ndarray:
    """``(N, N)``: row i is what ``name``, built from all the lights, shows at light i."""
    sigma = default_sigma(directions)
    if name == "rbf":
        return rbf_weights(directions, directions, sigma)
    return bilinear_weights(directions, BILINEAR_RESOLUTION) @ resample_matrix(directions, BILINEAR_RESOLUTION, sigma)


def viewer_distance_weights(directions: np.ndarray, count: int = VIEWER_LIGHTS) -> tuple[np.ndarray, np.ndarray]:
    """How a viewer's lights fall among the capture's: per light, the share of viewer lights
    nearest to it, and their mean squared distance to it relative to its nearest neighbour's.

    The viewer's lights are ``count`` directions spread evenly over the upper hemisphere (a
    Fibonacci lattice), those no farther from the nearest light than the widest gap between
    neighbouring lights (the part of the sky the capture covers).

    Parameters
    ----------
    directions : ndarray, shape (N, 3)
        Unit light directions, N ≥ 2.
    count : int
        Directions of the lattice.

    Returns
    -------
    share : ndarray, shape (N,)
        Fraction of the covered viewer lights whose nearest light is light i (sums to 1).
    spread : ndarray, shape (N,)
        Σ over those viewer lights of (distance to light i / light i's distance to its nearest
        other light)², divided by the number of covered viewer lights.
    """
    d = np.asarray(directions, np.float64)
    i = np.arange(count) + 0.5
    z = i / count  # uniform in z is uniform in area on the sphere
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    viewer = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    between = np.linalg.norm(d[:, None] - d[None], axis=2)
    np.fill_diagonal(between, np.inf)
    spacing = np.maximum(between.min(axis=1), 1e-9)
    to_lights = np.linalg.norm(viewer[:, None] - d[None], axis=2)
    nearest, distance = to_lights.argmin(axis=1), to_lights.min(axis=1)
    covered = distance <= spacing.max()
    if not covered.any():  # every light in one spot: the viewer's lights are the lights
        return np.full(len(d), 1.0 / len(d)), np.zeros(len(d))
    nearest, distance = nearest[covered], distance[covered]
    share = np.bincount(nearest, minlength=len(d)) / len(nearest)
    spread = np.bincount(nearest, weights=(distance / spacing[nearest]) ** 2, minlength=len(d)) / len(nearest)
    return share, spread


def _storage_var(planes: np.ndarray) -> np.ndarray:
    """Variance ``(K,)`` of quantising each plane ``(P, K)`` to 8 bits over its range."""
    step = (planes.max(axis=0) - planes.min(axis=0)) / 255.0
    return step.astype(np.float64) ** 2 / 12.0


def _compress(fitted: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples ``(N, P, 3)`` through :data:`PCA_PLANES` principal components (at most
    3·N), as the interpolating bases store them: the compressed samples, the components at the
    lights ``(K, N, 3)`` and the per-pixel coefficients ``(P, K)``."""
    n, p, _ = fitted.shape
    vectors = fitted.transpose(1, 0, 2).reshape(p, -1)  # (P, N·3)
    mean, components = pca(vectors, _pca_planes(PCA_PLANES, n))
    coefficients = (vectors - mean) @ components.T
    compressed = (mean + coefficients @ components).reshape(p, n, 3).transpose(1, 0, 2)
    return compressed, components.reshape(len(components), n, 3), coefficients


def _score(name: str, encoding: str, fitted: np.ndarray, observed: np.ndarray, directions: np.ndarray,
           compression: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
           interpolation: tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]] | None) -> BasisScore:
    """One basis's score; ``fitted`` the samples in ``encoding``, ``observed`` in 8-bit sRGB
    levels; for ``rbf`` and ``bilinear``, ``compression`` :func:`_compress` of ``fitted`` and
    ``interpolation`` the basis's :func:`_loo_predictor`, :func:`_relit_at_lights` and the
    lights' :func:`viewer_distance_weights` (the same for every encoding)."""
    relit = None
    if name in ("rbf", "bilinear"):
        compressed, at_lights, coefficients = compression
        loo_matrix, relit_matrix, (share, spread) = interpolation
        flat = compressed.reshape(len(compressed), -1)
        predicted = (loo_matrix @ flat).reshape(compressed.shape)
        relit = (relit_matrix @ flat).reshape(compressed.shape)
        used = np.arange(len(directions))
        variance = np.einsum("knc,k->nc", at_lights ** 2, _storage_var(coefficients))[:, None, :]
        planes = len(at_lights)
    else:
        matrix = least_squares_matrix(name, directions)
        values, colour = _lrgb(fitted)
        residuals, used = loo_residuals(values, matrix, rcond=RCOND, warn=False)
        predicted = colour[None] * (values[used] - residuals)[..., None]
        fit = np.linalg.pinv(matrix, rcond=RCOND)
        coefficients = (fit @ values).T  # (P, K)
        w2 = matrix[used] ** 2  # (M, K)
        # The planes' quantisation through the basis, and the 8-bit colour plane's through the
        # luminance (a dark object's brightness is in its colour: few levels in linear light).
        variance = ((w2 @ _storage_var(coefficients))[:, None, None] * colour[None] ** 2
                    + (values[used] ** 2)[..., None] / (12.0 * 255.0 ** 2))
        planes = matrix.shape[1]
    def shown(values: np.ndarray) -> np.ndarray:
        return 255.0 * (np.clip(values, 0.0, 1.0) if encoding == "srgb" else linear_to_srgb(values))

    slope = 255.0 if encoding == "srgb" else 255.0 * _srgb_slope(np.clip(predicted, 0.0, 1.0))
    left_out = np.mean((shown(predicted) - observed[used]) ** 2, axis=(1, 2))  # per light
    if relit is None:
        prediction = float(np.sqrt(np.mean(left_out)))
    else:
        # An interpolating basis's error grows with the distance from the light to the nearest
        # photographed one: nothing at a light but its compression's, and at a left-out light
        # what a gap of a whole spacing costs. A viewer's light is closer than that to some
        # photograph (half a spacing on average), so leave-one-out alone underrates these
        # bases: by 3–6 dB against lights held out of rendered domes, against 0.5–2.7 dB for
        # HSH, whose global fit's leave-one-out error already estimates its error at a new
        # light. Modelled as the square error growing with the squared distance, weighed over
        # the viewer's lights of the hemisphere the capture covers.
        at_light = np.mean((shown(relit) - observed[used]) ** 2, axis=(1, 2))
        prediction = float(np.sqrt(np.sum(share * at_light + spread * np.maximum(left_out - at_light, 0.0))))
    storage = float(np.sqrt(np.mean(variance * slope ** 2)))
    rms = float(np.hypot(prediction, storage))
    return BasisScore(name, encoding, int(planes), prediction, storage, rms,
                      float(20 * np.log10(255.0 / max(rms, 1e-9))))


def _srgb_slope(v: np.ndarray) -> np.ndarray:
    """d sRGB / d linear, finite at 0 (the curve's linear toe)."""
    return np.where(v <= 0.0031308, 12.92, 1.055 / 2.4 * np.maximum(v, 0.0031308) ** (1 / 2.4 - 1))


def score_bases(luminance: np.ndarray, chroma: np.ndarray, directions: np.ndarray,
                names: Sequence[str] = AUTO, encodings: Sequence[str] = ENCODINGS) -> list[BasisScore]:
    """Score relighting bases on samples of a capture, best first.

    Parameters
    ----------
    luminance : ndarray, shape (N, P)
        Linear luminance of P pixels under each of the N lights (:func:`sample_stack`).
    chroma : ndarray, shape (P, 3)
        The pixels' colour of unit luminance.
    directions : ndarray, shape (N, 3)
        Unit light directions.
    names, encodings : sequence of str
        The bases (:data:`NAMES`) and encodings (:data:`ENCODINGS`) to score, every pair.

    Returns
    -------
    list of BasisScore
        Sorted by ``rms``, lowest first. A basis with no more lights than terms cannot be
        scored (every light is needed to fit it) and is left out.
    """
    luminance = np.asarray(luminance, np.float32)
    chroma = np.asarray(chroma, np.float32)
    directions = as_directions(directions, luminance.shape[0])
    if chroma.shape != (luminance.shape[1], 3):
        raise ValueError(f"chroma must be ({luminance.shape[1]}, 3) to match the samples, not {chroma.shape}")
    scorable = []
    for name in names:
        if _check_name(name) == "neural":  # trained, not fitted: :func:`score_neural`
            continue
        # A fitted basis needs more lights than terms; an interpolating one more lights than
        # relight's nine planes and a mean (fewer leave the hemisphere too coarsely sampled to
        # interpolate; the PTM's six terms are the fallback).
        terms = DEFAULT_PLANES + 1 if name in ("rbf", "bilinear") else least_squares_matrix(name, directions[:1]).shape[1]
        if len(directions) > terms:
            scorable.append(name)
    observed_linear = chroma[None] * luminance[..., None]  # (N, P, 3)
    observed = 255.0 * linear_to_srgb(observed_linear)
    interpolating = [name for name in scorable if name in ("rbf", "bilinear")]
    viewer = viewer_distance_weights(directions) if interpolating else None
    interpolation = {name: (_loo_predictor(name, directions), _relit_at_lights(name, directions), viewer)
                     for name in interpolating}
    scores = []
    for encoding in encodings:
        fitted = _display(observed_linear, _check_encoding(encoding)).astype(np.float64)
        # One compression of the samples serves both interpolating bases.
        compression = _compress(fitted) if interpolating else None
        scores += [_score(name, encoding, fitted, observed, directions, compression, interpolation.get(name))
                   for name in scorable]
    return sorted(scores, key=lambda s: s.rms)


def _rgb_samples(luminance: np.ndarray, chroma: np.ndarray) -> np.ndarray:
    """Display-encoded RGB ``(P, N, 3)`` of linear luminance ``(N, P)`` and chroma ``(P, 3)``:
    what NeuralRTI trains on (the photographs' 8-bit values)."""
    from .displaykernel import display_samples

    return np.ascontiguousarray(display_samples(luminance, chroma, "srgb").transpose(1, 0, 2))


def score_neural(luminance: np.ndarray, chroma: np.ndarray, directions: np.ndarray, *,
                 params: NeuralParameters | None = None, threads: int | None = None,
                 progress: Callable[[int], None] | None = None) -> BasisScore | None:
    """Score the learned basis (:mod:`ptmcore.neural`) on samples of a capture.

    A network cannot be refitted once per left-out light, so it is trained once without every
    :data:`NEURAL_HOLD_OUT`-th light and scored on predicting those, in the levels of
    :func:`score_bases`. That leaves it fewer lights than the others' leave-one-out, so the
    comparison, if anything, favours the fitted bases. The storage error is measured, not
    modelled: the codes quantised to 8 bits as they are published, decoded again.

    ``progress`` is called with 1 after each epoch of the training.

    Returns
    -------
    BasisScore or None
        None with fewer than :data:`NEURAL_MIN_LIGHTS` lights.
    """
    from .neural import decode, dequantize_codes, encode, quantize_codes, train_neural

    luminance = np.asarray(luminance, np.float32)
    directions = as_directions(directions, luminance.shape[0])
    n = len(directions)
    if n < NEURAL_MIN_LIGHTS:
        return None
    held = np.arange(n) % NEURAL_HOLD_OUT == NEURAL_HOLD_OUT // 2
    kept = _rgb_samples(luminance[~held], np.asarray(chroma, np.float32))
    model = train_neural(kept, directions[~held], params, threads=threads, progress=progress)
    codes = encode(model, kept)
    stored = dequantize_codes(*quantize_codes(codes))
    observed = 255.0 * np.asarray(linear_to_srgb(np.asarray(chroma, np.float32)[None]
                                                 * luminance[held][..., None]), np.float64)
    prediction = storage = 0.0
    for light, seen in zip(directions[held], observed):
        exact = 255.0 * np.clip(decode(model, codes, light), 0.0, 1.0).astype(np.float64)
        quantised = 255.0 * np.clip(decode(model, stored, light), 0.0, 1.0).astype(np.float64)
        prediction += float(np.mean((exact - seen) ** 2))
        storage += float(np.mean((quantised - exact) ** 2))
    prediction, storage = np.sqrt(prediction / held.sum()), np.sqrt(storage / held.sum())
    rms = float(np.hypot(prediction, storage))
    return BasisScore("neural", "srgb", int(codes.shape[1]), float(prediction), float(storage), rms,
                      float(20 * np.log10(255.0 / max(rms, 1e-9))), "held-out lights")


def choose_basis(stack: ImageStack, directions: np.ndarray, *, candidates: Sequence[str] = AUTO,
                 encodings: Sequence[str] = ENCODINGS, mask: np.ndarray | None = None,
                 pixels: int = SAMPLE_PIXELS, threads: int | None = None,
                 neural: NeuralParameters | None = None, progress: Callable[[int], None] | None = None,
                 ) -> BasisChoice:
    """The basis and encoding that relight this capture most faithfully (:func:`score_bases`,
    and :func:`score_neural` when ``neural`` is a candidate).

    With one candidate and one encoding the choice is that one, still scored (``neural`` asked
    for alone is not: scoring it is a second training). Falls back to the PTM in sRGB when no
    candidate can be scored (as few lights as terms). ``neural`` is fitted to sRGB values only,
    with the parameters ``neural`` (:class:`~ptmcore.neural.NeuralParameters`'s defaults);
    its training calls ``progress`` with rows of the image, ``stack.shape[0]`` in all, as
    :func:`fit_published` reports (nothing else here takes long enough to report).
    """
    luminance, chroma = sample_stack(stack, pixels, mask)
    scores = score_bases(luminance, chroma, directions, candidates, encodings)
    if "neural" in candidates and len(candidates) > 1 and "srgb" in encodings:
        learned = score_neural(luminance, chroma, directions, params=neural, threads=threads,
                               progress=_epochs_as_rows(stack.shape[0], neural, progress))
        scores = sorted(scores + ([learned] if learned is not None else []), key=lambda s: s.rms)
    if list(candidates) == ["neural"]:
        return BasisChoice("neural", "srgb", (), luminance.shape[1], "asked")
    chosen_by = scores[0].measured_by if scores and len(candidates) * len(encodings) > 1 else "asked"
    if not scores:
        return BasisChoice(candidates[0] if len(candidates) == 1 else "ptm", encodings[0], (), luminance.shape[1],
                           "asked" if len(candidates) == 1 else "fewest terms")
    return BasisChoice(scores[0].name, scores[0].encoding, tuple(scores), luminance.shape[1], chosen_by)


def fit_published(stack: ImageStack, directions: np.ndarray, name: str, encoding: str = "srgb", *,
                  threads: int | None = None, progress: Callable[[int], None] | None = None,
                  pixels: int = SAMPLE_PIXELS, neural: NeuralParameters | None = None,
                  planes: int = PCA_PLANES) -> PublishedBasis:
    """Fit one basis to a whole stack, in the form viewers read.

    Parameters
    ----------
    stack : ImageStack
        The photographs' linear luminance and colour.
    directions : ndarray, shape (N, 3)
        Unit light directions.
    name : str
        One of :data:`NAMES`.
    encoding : {"srgb", "linear"}
        What the basis is fitted to.
    threads : int, optional
        Threads working on bands of rows.
    progress : callable, optional
        Called with the number of rows done after each band.
    pixels : int
        Pixels of the grid the principal components of ``rbf`` and ``bilinear`` are found on.
    planes : int
        Principal components (per-pixel planes) of ``rbf`` and ``bilinear``, at most three per
        basis direction (relight: 9).
    neural : NeuralParameters, optional
        How ``neural`` is trained (default: :class:`~ptmcore.neural.NeuralParameters`). Its
        training reports to ``progress`` as many rows again as the image has, before its
        encoding reports the rows themselves.

    Returns
    -------
    PublishedBasis
    """
    from .displaykernel import display_by_pixel, lrgb_samples

    _check_name(name)
    _check_encoding(encoding)
    directions = as_directions(directions, len(stack))
    if name == "neural":
        if encoding != "srgb":
            raise ValueError("the neural basis is fitted to sRGB values only, as NeuralRTI is")
        return _fit_neural(stack, directions, params=neural, threads=threads, progress=progress)
    n = len(stack)
    h, w = stack.shape
    if name in ("rbf", "bilinear"):
        sigma = default_sigma(directions)
        grid = resample_matrix(directions, BILINEAR_RESOLUTION, sigma) if name == "bilinear" else None
        grid_t = None if grid is None else np.ascontiguousarray(grid.T, dtype=np.float32)
        luminance, chroma = sample_stack(stack, pixels)

        def vectors_of(lum: np.ndarray, chr_: np.ndarray) -> np.ndarray:
            # Each pixel's vector channel by channel, (P, 3·D): no copy for the bilinear
            # resampling's product; the components are put back in relight's order, D × 3, below.
            rgb = display_by_pixel(lum, chr_, encoding)  # (P, 3, N)
            if grid is not None:
                rgb = rgb.reshape(-1, n) @ grid_t
            return rgb.reshape(lum.shape[1], -1)

        dims = len(directions) if grid is None else BILINEAR_RESOLUTION ** 2
        k = _pca_planes(planes, dims)
        mean, components = pca(vectors_of(luminance, chroma).astype(np.float64), k)
        mean32, comp32 = mean.astype(np.float32), components.T.astype(np.float32)
        coefficients = np.empty((h, w, k), np.float32)

        def work(r0: int, r1: int) -> None:
            lum, _ = stack.band(r0, r1)
            vectors = vectors_of(lum.reshape(n, -1), stack.chroma[r0:r1].reshape(-1, 3))
            coefficients[r0:r1] = ((vectors - mean32) @ comp32).reshape(r1 - r0, w, k)

        rows = band_rows(n, w, bytes_per_sample=40, budget=BAND_BYTES)
        run_bands(h, rows, work, threads=threads, progress=progress)
        basis = np.concatenate([mean[None], components]).reshape(k + 1, 3, dims).transpose(0, 2, 1)
        basis = np.ascontiguousarray(basis, dtype=np.float32)
        if grid is None:
            return PublishedBasis("rbf", "mrgb", coefficients, encoding, lights=directions.copy(), sigma=sigma,
                                  basis=basis, name=name)
        return PublishedBasis("bln", "mrgb", coefficients, encoding, resolution=BILINEAR_RESOLUTION, basis=basis,
                              name=name)

    matrix = least_squares_matrix(name, directions)
    fit = np.linalg.pinv(matrix, rcond=RCOND).astype(np.float32)  # (K, N)
    k = fit.shape[0]
    planes = np.empty((h, w, k), np.float32)
    colour = np.empty((h, w, 3), np.uint8)

    def work(r0: int, r1: int) -> None:
        lum, _ = stack.band(r0, r1)
        values, col = lrgb_samples(lum.reshape(n, -1), stack.chroma[r0:r1].reshape(-1, 3), encoding)
        planes[r0:r1] = (fit @ values).T.reshape(r1 - r0, w, k)
        colour[r0:r1] = np.rint(255.0 * col).reshape(r1 - r0, w, 3).astype(np.uint8)

    rows = band_rows(n, w, bytes_per_sample=40, budget=BAND_BYTES)
    run_bands(h, rows, work, threads=threads, progress=progress)
    kind = "ptm" if name == "ptm" else "hsh"
    return PublishedBasis(kind, "lrgb", planes, encoding, colour=colour,
                          order=_hsh_order(name) if kind == "hsh" else None, name=name)


def _pca_planes(planes: int, dims: int) -> int:
    """``planes`` checked, and at most the 3 · ``dims`` numbers a pixel's samples have (a
    capture of few lights keeps them all)."""
    if isinstance(planes, bool) or int(planes) != planes or int(planes) < 1:
        raise ValueError(f"planes must be a positive integer, got {planes!r}")
    return min(int(planes), 3 * dims)


def _epochs_as_rows(rows: int, params: NeuralParameters | None,
                   progress: Callable[[int], None] | None) -> Callable[[int], None] | None:
    """A training's epochs reported as ``rows`` rows in all, for a progress counted in rows."""
    if progress is None:
        return None
    epochs = (params or NeuralParameters()).epochs
    done = [0]

    def epoch(_: int) -> None:
        done[0] += 1
        progress(rows * done[0] // epochs - rows * (done[0] - 1) // epochs)

    return epoch


def _fit_neural(stack: ImageStack, directions: np.ndarray, *, params: NeuralParameters | None = None,
                threads: int | None = None, progress: Callable[[int], None] | None = None) -> PublishedBasis:
    """Train the learned basis on a grid of the stack's lit pixels, then encode every pixel,
    band by band."""
    from .neural import encode, train_neural
    from .published import neural_basis

    params = params or NeuralParameters()
    luminance, chroma = sample_stack(stack, params.training_pixels)
    model = train_neural(_rgb_samples(luminance, chroma), directions, params, threads=threads,
                         progress=_epochs_as_rows(stack.shape[0], params, progress))
    n = len(stack)
    h, w = stack.shape
    codes = np.empty((h, w, model.code_size), np.float32)

    def work(r0: int, r1: int) -> None:
        lum, _ = stack.band(r0, r1)
        rgb = _rgb_samples(lum.reshape(n, -1), stack.chroma[r0:r1].reshape(-1, 3))
        codes[r0:r1] = encode(model, rgb, threads=1).reshape(r1 - r0, w, -1)

    rows = band_rows(n, w, bytes_per_sample=60, budget=BAND_BYTES)
    run_bands(h, rows, work, threads=threads, progress=progress)
    return neural_basis(model, codes, name="neural")
