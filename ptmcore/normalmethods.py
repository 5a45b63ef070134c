"""Every normal method and per-pixel fit, each declared once.

A normal method (``--normals``) says what model the normals come from; a fit (``--fit``) how
each pixel's samples are weighed. The command line's choices and help (``cli/parser.py``,
through ``reconstruct.pipeline.options.NormalMethod`` and ``Fit``), the report's sentence on
how the normals were made (``reconstruct.report.summary``) and
``reconstruct.pipeline.stages.estimate_normals`` all read :data:`NORMAL_METHODS` and
:data:`FITS`: adding a method is one entry here (its functions for distant and, if it has
one, near lights) and its tests.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .fit import fit_ptm
from .images import ImageStack
from .nearlight import fit_ptm_near, near_lambertian_albedo, near_photometric_stereo
from .normals import normals_from_ptm, photometric_stereo
from .robust import robust_photometric_stereo
from .robustptm import debiased_normals, hemisphere_coefficients, robust_ptm

__all__ = ["FITS", "NORMAL_METHODS", "Estimate", "Fit", "NormalMethod"]

#: ``progress(rows)`` as bands of rows are done.
Advance = Callable[[int], None]


@dataclass(frozen=True)
class Fit:
    """A per-pixel fit: how the samples of a pixel are weighed.

    Attributes
    ----------
    name : str
        ``--fit``'s value.
    help : str
        What the command line's help says of it.
    words : str
        What the report says (after "by photometric stereo, ").
    robust : str or None
        The robust weighting of :func:`~ptmcore.robust.robust_photometric_stereo` and
        :func:`~ptmcore.robustptm.robust_ptm` (None: plain least squares).
    lobe : bool
        Whether the object's glossy reflectance lobe is fitted too (:mod:`ptmcore.lobe`).
    """

    name: str
    help: str
    words: str
    robust: str | None
    lobe: bool = False


#: The fits, the default first.
FITS: dict[str, Fit] = {f.name: f for f in (
    Fit("lobe", "default: irls with a glossy reflectance lobe shared by the object, estimated from the "
        "photographs and used only where it explains them",
        "robust fit with the object's glossy reflectance lobe", "irls", lobe=True),
    Fit("irls", "robust, down-weights shadowed, clipped and specular samples",
        "robust Lambertian fit (shadows, clipped samples and highlights left out)", "irls"),
    Fit("trimmed", "robust, leaves them out", "trimmed least squares", "trimmed"),
    Fit("plain", "least squares", "least squares", None),
)}


@dataclass(frozen=True)
class Estimate:
    """What a normal method gives: unit normals ``(H, W, 3)``, the luminance albedo ``(H, W)``
    (None: Lambertian, from the normals, :func:`ptmcore.normals.lambertian_albedo`), which
    pixels have a normal, and the reflectance lobe's summary, if one was fitted."""

    normals: np.ndarray
    albedo: np.ndarray | None
    valid: np.ndarray
    lobe: dict | None = None


@dataclass(frozen=True)
class NormalMethod:
    """A normal method.

    Attributes
    ----------
    name : str
        ``--normals``' value.
    help : str
        What the command line's help says of it.
    words : str
        What the report says (after "Normals "), for the fit ``{fit}``'s words where it has one.
    reference : str
        Where the method comes from.
    distant : callable
        ``distant(stack, directions, fit, solver, threads, progress) -> Estimate`` for one
        light direction per photograph.
    near : callable or None
        ``near(stack, positions, threads, progress) -> Estimate`` for point lights at
        ``positions`` (pixels, :mod:`ptmcore.nearlight`; no choice of fit), None when the method
        assumes distant lights.
    near_words : str
        What the report says of the method with near lights.
    """

    name: str
    help: str
    words: str
    reference: str
    distant: Callable[..., Estimate]
    near: Callable[..., Estimate] | None = None
    near_words: str = ""


def _ps(stack: ImageStack, directions: np.ndarray, fit: Fit, solver: str, threads: int | None,
        progress: Advance | None) -> Estimate:
    if fit.robust is None:
        ps = photometric_stereo(stack, directions, threads=threads, progress=progress)
    else:
        ps = robust_photometric_stereo(stack, directions, method=fit.robust, lobe=fit.lobe, threads=threads,
                                       progress=progress)
    return Estimate(ps.normals, ps.albedo, ps.valid, ps.lobe.summary() if ps.lobe else None)


def _ptm_maximum(stack: ImageStack, directions: np.ndarray, fit: Fit, solver: str, threads: int | None,
                 progress: Advance | None) -> Estimate:
    if fit.robust is None:
        coefficients = fit_ptm(stack, directions, solver=solver, threads=threads, progress=progress).coefficients
    else:
        coefficients = robust_ptm(stack, directions, method=fit.robust, threads=threads,
                                  progress=progress).ptm.coefficients
    valid = np.empty(stack.shape, bool)
    return Estimate(normals_from_ptm(coefficients, threads=threads, valid=valid), None, valid)


def _ptm_debiased(stack: ImageStack, directions: np.ndarray, fit: Fit, solver: str, threads: int | None,
                  progress: Advance | None) -> Estimate:
    if fit.robust is None:
        coefficients = fit_ptm(stack, directions, solver=solver, threads=threads, progress=progress).coefficients
        valid = np.empty(stack.shape, bool)
        return Estimate(debiased_normals(coefficients, hemisphere_coefficients(directions), valid=valid), None, valid)
    fitted = robust_ptm(stack, directions, method=fit.robust, threads=threads, progress=progress)
    return Estimate(fitted.normals, None, fitted.valid)


def _ps_near(stack: ImageStack, positions: np.ndarray, threads: int | None, progress: Advance | None) -> Estimate:
    ps = near_photometric_stereo(stack, positions, threads=threads, progress=progress)
    return Estimate(ps.normals, ps.albedo, ps.valid)


def _ptm_near(stack: ImageStack, positions: np.ndarray, threads: int | None, progress: Advance | None) -> Estimate:
    coefficients = fit_ptm_near(stack, positions, threads=threads, progress=progress).coefficients
    valid = np.empty(stack.shape, bool)
    normals = normals_from_ptm(coefficients, threads=threads, valid=valid)
    return Estimate(normals, near_lambertian_albedo(stack, positions, normals, threads=threads), valid)


#: The normal methods, the default first.
NORMAL_METHODS: dict[str, NormalMethod] = {m.name: m for m in (
    NormalMethod("ps", "photometric stereo (default, the most accurate)", "by photometric stereo, {fit}",
                 "Woodham 1980; robust fits and the lobe: ptmcore.robust, ptmcore.lobe", _ps, _ps_near,
                 "photometric stereo, plain fit"),
    NormalMethod("ptm", "maximum of each pixel's PTM", "from the maximum of each pixel's PTM polynomial",
                 "Malzbender, Gelb and Wolters 2001 (the maximum in closed form)", _ptm_maximum, _ptm_near,
                 "PTM maximum of a per-pixel fit"),
    NormalMethod("ptm-debiased", "that maximum corrected for the PTM's bias towards the view direction",
                 "from the maximum of each pixel's PTM polynomial, corrected for its bias",
                 "ptmcore.robustptm: the maximum read through the fit's own model of the hemisphere",
                 _ptm_debiased),
)}
