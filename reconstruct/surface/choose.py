"""The integrator chosen by the normals themselves: bilateral where they show depth steps,
least squares where the surface is continuous.

Bilateral normal integration (:mod:`reconstruct.surface.bilateral`) keeps depth steps and
occluding contours that least squares smears over millimetres (DiLiGenT's cat: 2.24 → 0.08
mm), but where the surface is continuous it is less accurate (its nz² weights, and sigmoid
weights that stray from ½ wherever the slope changes: the module's docstring): on a smooth
clay tablet's true normals 1.6 times the error of masked least squares, on a sphere 3.4 times
(``benchmarks/integration.py``). Whether a mask exists says nothing about steps; what the
bilateral fit did does. So
:func:`integrate_auto` runs it and keeps its result only when it cut edges
(:data:`~reconstruct.surface.bilateral.CUT_WEIGHT`): at least :data:`MIN_CUT_EDGES` of them,
the length of a short step. Otherwise the surface is continuous as far as the normals can
tell, and masked least squares (:func:`~reconstruct.surface.masked.masked_poisson`, a
fraction of the bilateral fit's time) integrates it, each pixel's equations weighed by nz² as
the bilateral fit weighs them (``steep_weights``: a normal's error δ moves its gradient by
about δ/nz², so the steepest are the least sure).

On the scenes of ``benchmarks/integration.py`` no edge was cut on any smooth relief (tablet,
coin, sphere caps; true normals and photometric stereo with 0.5–2 % noise), and 38–1031 were
on every scene with a step or occluding contour (a scissor step, DiLiGenT's cat and harvest)
and on wedges cut at 75°; the choice came within 10 % of the better of masked and bilateral
integration on every scene (the weights: better than both on noisy steep normals, up to 9 %
worse on gradients whose noise does not grow with the slope).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from reconstruct.calibration.camera import Intrinsics
from reconstruct.surface.integrate import integrate
from reconstruct.surface.perspective import integrate_perspective

__all__ = ["BILATERAL_PIXELS", "MIN_CUT_EDGES", "Integration", "integrate_auto", "integrate_with"]

#: Masks of at most this many pixels are tried with bilateral integration; larger ones are
#: integrated by masked least squares: bilateral took 0.65 s on DiLiGenT's cat (45,200 pixels)
#: but 52 s and 5 GB on 14 million (BENCHMARKS.md, "Normal integration").
BILATERAL_PIXELS = 1 << 20
#: Fewest edges the bilateral fit must cut for its result to be kept: a pixel cut off all
#: round is four, a step worth keeping longer than a couple of them.
MIN_CUT_EDGES = 8


@dataclass(frozen=True)
class Integration:
    """A height map and how it was integrated.

    Attributes
    ----------
    height : numpy.ndarray
        ``(H, W)`` float32, NaN outside the object (:func:`integrate` or
        :func:`integrate_perspective`'s units).
    method : str
        The integrator whose result this is: ``"dct"``, ``"masked"`` or ``"bilateral"``.
    reason : str
        Why, in a sentence for the report.
    cut_edges : int or None
        Edges the bilateral fit cut (None when it was not run).
    """

    height: np.ndarray
    method: str
    reason: str
    cut_edges: int | None = None


def _integrate(normals: np.ndarray, method: str, mask: np.ndarray | None, pixel_size: float,
               intrinsics: Intrinsics | None, distance: float | None, workers: int | None,
               steep_weights: bool = False) -> tuple[np.ndarray, dict]:
    if intrinsics is None:
        return integrate(normals, method, mask=mask, pixel_size=pixel_size, workers=workers, return_info=True,
                         steep_weights=steep_weights)
    return integrate_perspective(normals, intrinsics, mask=mask, method=method, distance=distance,
                                 workers=workers, return_info=True, steep_weights=steep_weights)


def integrate_auto(
    normals: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    pixel_size: float = 1.0,
    intrinsics: Intrinsics | None = None,
    distance: float | None = None,
    workers: int | None = -1,
    bilateral_pixels: int = BILATERAL_PIXELS,
) -> Integration:
    """Integrate normals with the integrator their object calls for.

    Without a mask, least squares on the whole frame (``dct``; with a camera, its
    perspective form). With a mask of at most `bilateral_pixels` pixels, bilateral
    integration, kept when it cut at least :data:`MIN_CUT_EDGES` edges (depth steps or
    occluding contours in the normals), else masked least squares weighed by nz². A larger
    mask: masked least squares (bilateral integration takes about a minute at 14 million
    pixels).

    Parameters
    ----------
    normals : numpy.ndarray
        ``(H, W, 3)`` normals in the project frame.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool, the object.
    pixel_size : float
        Orthographic pixel size (heights in its unit); ignored with `intrinsics`.
    intrinsics : Intrinsics, optional
        A pinhole camera: :func:`integrate_perspective` with `distance`.
    distance : float, optional
        The object's median depth in mm (perspective only).
    workers : int or None
        Threads for scipy.fft.
    bilateral_pixels : int
        Largest mask tried with bilateral integration.

    Returns
    -------
    Integration
    """
    if mask is None:
        height, _ = _integrate(normals, "dct", None, pixel_size, intrinsics, distance, workers)
        return Integration(height, "dct", "no mask: least squares on the whole frame with a free boundary")
    pixels = int(np.count_nonzero(mask))
    if pixels > bilateral_pixels:
        height, _ = _integrate(normals, "masked", mask, pixel_size, intrinsics, distance, workers)
        return Integration(height, "masked", (
            f"a mask is known: least squares on the object only ({pixels / 1e6:.1f} million pixels; bilateral "
            f"integration, which keeps depth steps, is tried up to {bilateral_pixels / 1e6:.1f} million, and takes "
            "about a minute beyond: --integrator bilateral)"))
    height, info = _integrate(normals, "bilateral", mask, pixel_size, intrinsics, distance, workers)
    cut = int(info["cut_edges"])
    if cut >= MIN_CUT_EDGES:
        return Integration(height, "bilateral", (
            f"bilateral normal integration found depth steps or occluding contours ({cut} edges cut) and keeps "
            "them instead of smoothing across them"), cut)
    height, _ = _integrate(normals, "masked", mask, pixel_size, intrinsics, distance, workers, steep_weights=True)
    return Integration(height, "masked", (
        f"bilateral normal integration found no depth step ({cut} edges cut, fewer than {MIN_CUT_EDGES}): the "
        "surface is continuous, integrated by least squares on the object, which is more accurate there, each "
        "pixel's equations weighed by nz² as bilateral integration weighs them (steep normals' gradients are "
        "the least sure)"), cut)


def integrate_with(
    normals: np.ndarray,
    method: str,
    mask: np.ndarray | None = None,
    *,
    pixel_size: float = 1.0,
    intrinsics: Intrinsics | None = None,
    distance: float | None = None,
    workers: int | None = -1,
) -> Integration:
    """Integrate normals with ``method`` (``"auto"``: :func:`integrate_auto`; else the
    integrator named, orthographic or, with ``intrinsics``, perspective), as ``reconstruct``'s
    ``--integrator`` does. The parameters are :func:`integrate_auto`'s."""
    if method == "auto":
        return integrate_auto(normals, mask, pixel_size=pixel_size, intrinsics=intrinsics, distance=distance,
                              workers=workers)
    height, _ = _integrate(normals, method, mask, pixel_size, intrinsics, distance, workers)
    return Integration(height, method, "chosen")
