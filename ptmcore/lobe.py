"""A reflectance lobe shared by the whole object, fitted alongside the normals.

Real glazes, varnishes, stone and metal are not Lambertian, and most of their departure is not a
sharp highlight that a robust fit can leave out as an outlier: it is a broad, low-frequency lobe
that brightens every sample whose half vector is near the normal. On DiLiGenT's ceramic cat the
brightness of a sample, relative to ``ρ n·l`` under the laser-scanned normal, rises smoothly
from 0.9 at 35° between half vector and normal to 1.16 at 0°. Every photograph is slightly
"wrong" in the same smooth way, and the Lambertian fit tilts each normal towards the lights on
the brighter side of its lobe.

The model is that of the low-frequency, isotropic reflectance methods of photometric stereo
(Alldrin, Zickler and Kriegman, CVPR 2008; Shi, Tan, Matsushita and Ikeuchi, "Bi-polynomial
modeling of low-frequency reflectances", TPAMI 2014), whose reflectance depends on the normal
through the angle between normal and half vector (the microfacet distribution of a glossy
surface). Here

    I_i = ρ · (n·l_i) · f(n·h_i),    f(c) = Σ_{k=0..4} a_k (1 − c)^k,

with ``ρ`` and ``n`` per pixel and the five coefficients of ``f`` shared by the object (most
objects photographed are of one material; sharp highlights, shadows and inter-reflections stay
the robust fit's outliers). A term in ``n·l`` as well was tried: it trades off against the tilt
of the normals (the residual stayed the same while the normals drifted) and was left out.

``f`` is estimated by alternation on a sample of pixels (:func:`estimate_lobe`): ``f`` by least
squares given the normals, then robust Lambertian normals (:func:`ptmcore.robust.robust_lambertian`)
of the samples divided by ``f``, until the normals move less than :data:`CONVERGED_DEG` in a
round. The alternation converges slowly (each round undoes part of the lobe's pull) but steadily;
a joint Gauss–Newton solve of normals and coefficients was tried and settled on worse normals.
The normals of the whole image are then fitted to the photographs divided by ``f`` at a prior
normal (:mod:`ptmcore.robustkernel`, three passes, :func:`ptmcore.robust.robust_photometric_stereo`).

A lobe is used only where it explains the data: when it lowers the robust residual of the
sample by less than :data:`MIN_GAIN`, the object is taken as Lambertian and nothing changes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .images import ImageStack

__all__ = ["MIN_GAIN", "Lobe", "estimate_lobe", "fit_lobe", "lobe_factors"]

#: Highest power of (1 − n·h) in ``f``.
DEGREE = 4
#: ``f`` is kept within these bounds: a polynomial must not blow up outside the range of
#: angles it was fitted on, nor divide a sample by (almost) zero.
FACTOR_RANGE = (0.3, 3.0)
#: The lobe is used when it lowers the sample's robust residual RMS by at least this fraction.
MIN_GAIN = 0.1
#: Pixels sampled on a grid, and of those at most FIT_PIXELS lit ones (evenly spread) that the
#: lobe is estimated on. A thousand pixels of 48 or more photographs determine five coefficients
#: well; the cost of a round grows with them.
SAMPLE_PIXELS = 12_000
FIT_PIXELS = 2_000
#: The alternation stops when the normals move less than this on average in a round, or after
#: MAX_ROUNDS rounds.
CONVERGED_DEG = 0.02
MAX_ROUNDS = 60
#: Sample pixels darker than this fraction of the 90th percentile albedo are left out: their
#: ratios are mostly noise.
MIN_RELATIVE_ALBEDO = 0.2


@dataclass(frozen=True)
class Lobe:
    """A fitted lobe ``f`` (module docstring).

    Attributes
    ----------
    coefficients : ndarray, shape (DEGREE + 1,), float64
        ``a_0 … a_4``.
    gain : float
        Fraction by which the lobe lowered the sample's robust residual RMS.
    pixels : int
        Pixels it was estimated on.
    rounds : int
        Rounds of the alternation.
    """

    coefficients: np.ndarray
    gain: float
    pixels: int
    rounds: int

    def summary(self) -> dict:
        """For report.json."""
        return {"coefficients": [round(float(c), 5) for c in self.coefficients],
                "residual_reduction": round(self.gain, 4), "pixels": self.pixels, "rounds": self.rounds}


def lobe_factors(coefficients: np.ndarray, halves: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """``f`` of every light at every normal: (N, P) float32, within :data:`FACTOR_RANGE`.

    Parameters
    ----------
    coefficients : ndarray
        :attr:`Lobe.coefficients`.
    halves : ndarray, shape (N, 3)
        The lights' half vectors with the view (0, 0, 1).
    unit : ndarray, shape (3, P)
        Unit normals.
    """
    x = np.float32(1.0) - halves.astype(np.float32) @ unit.astype(np.float32)
    f = np.full_like(x, coefficients[-1])
    for a in coefficients[-2::-1].astype(np.float32):
        f *= x
        f += a
    return np.clip(f, *FACTOR_RANGE, out=f)


def fit_lobe(v: np.ndarray, dirs: np.ndarray, halves: np.ndarray, unit: np.ndarray, rho: np.ndarray,
             weights: np.ndarray, min_shading: float) -> np.ndarray:
    """Least-squares coefficients of ``f`` given normals and albedos.

    Minimises ``Σ (v − ρ (n·l) f)²`` over the samples with robust weight above 0.5 and
    ``n·l`` above ``min_shading``: residuals in the photographs' own units, so that dark pixels,
    whose ratios are mostly noise, count little.

    Parameters
    ----------
    v : ndarray, shape (N, P)
        Linear luminance samples.
    dirs, halves : ndarray, shape (N, 3)
        Light directions and half vectors.
    unit : ndarray, shape (3, P)
        Unit normals.
    rho : ndarray, shape (P,)
        Albedos.
    weights : ndarray, shape (N, P)
        The robust fit's weights.
    min_shading : float

    Returns
    -------
    ndarray, shape (DEGREE + 1,), float64
    """
    unit = unit.astype(np.float64)
    shading = dirs.astype(np.float64) @ unit
    use = (weights > 0.5) & (shading > min_shading)
    x = 1.0 - (halves.astype(np.float64) @ unit)[use]
    design = np.stack([x ** k for k in range(DEGREE + 1)], axis=1)
    design *= (rho[None, :] * shading)[use][:, None]
    # Normal equations: five unknowns, and lstsq's SVD of the tall matrix took 20× longer.
    return np.linalg.solve(design.T @ design, design.T @ v[use].astype(np.float64))


def _sample(stack: ImageStack, max_pixels: int) -> tuple[np.ndarray, np.ndarray]:
    """Samples (N, P) float32 and their usability of up to ``max_pixels`` pixels on a grid."""
    h, w = stack.shape
    step = max(1, int(np.ceil(np.sqrt(h * w / max_pixels))))
    codes = stack.grid(step).reshape(len(stack), -1)
    return stack.table[codes], codes != stack.saturated_code


def _relative_rms(v: np.ndarray, pred: np.ndarray, weights: np.ndarray) -> float:
    """RMS residual under the robust weights, relative to the samples' weighted mean."""
    total = weights.sum()
    return float(np.sqrt((weights * (v - pred) ** 2).sum() / total) / ((weights * v).sum() / total))


def estimate_lobe(stack: ImageStack, directions: np.ndarray, opt) -> Lobe | None:
    """The object's lobe, estimated on a sample of its pixels; None when it is Lambertian.

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    opt : ptmcore.robust.RobustOptions
        The robust fit's settings.

    Returns
    -------
    Lobe or None
        None when the lights lie in a plane, fewer than 100 sampled pixels are lit, or the lobe
        lowers the robust residual by less than :data:`MIN_GAIN`.
    """
    from .robust import Lights, robust_lambertian

    lights = Lights.of(directions)
    if lights.lambertian.rank < 3:
        return None
    v, usable = _sample(stack, SAMPLE_PIXELS)
    unit, rho, ok, weights = robust_lambertian(lights, opt, v, usable)
    if np.count_nonzero(ok) < 100:
        return None
    lit = np.flatnonzero(ok & (rho >= MIN_RELATIVE_ALBEDO * np.percentile(rho[ok], 90)))
    if len(lit) < 100:
        return None
    lit = lit[:: -(-len(lit) // FIT_PIXELS)]
    v, usable, unit, rho, weights = v[:, lit], usable[:, lit], unit[:, lit], rho[lit], weights[:, lit]
    dirs, halves = lights.dirs, lights.halves
    lambertian_rms = _relative_rms(v, (dirs @ unit) * rho.astype(np.float32), weights)
    rounds = 0
    while rounds < MAX_ROUNDS:
        rounds += 1
        coefficients = fit_lobe(v, dirs, halves, unit, rho, weights, opt.min_shading)
        fitted, rho, _, weights = robust_lambertian(lights, opt, v / lobe_factors(coefficients, halves, unit), usable)
        moved = np.degrees(np.arccos(np.clip(np.einsum("ip,ip->p", fitted, unit), -1.0, 1.0))).mean()
        unit = fitted
        if moved < CONVERGED_DEG:
            break
    pred = (dirs @ unit) * rho.astype(np.float32) * lobe_factors(coefficients, halves, unit)
    gain = 1.0 - _relative_rms(v, pred, weights) / lambertian_rms
    if not np.isfinite(gain) or gain < MIN_GAIN:
        return None
    return Lobe(coefficients, float(gain), len(lit), rounds)
