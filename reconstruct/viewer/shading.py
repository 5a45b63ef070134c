"""A relief shading for shallow surfaces, a live mode of the preview window.

(RTIViewer's specular enhancement is :func:`ptmcore.relight.specular_enhancement`, given the
normals at the polynomials' maxima once, ``maximum=``, so that it follows the light as fast as
the default rendering.)

* :func:`relief_shading` shows the shape alone, as MeshLab's radiance scaling does (Vergne et
  al., "Radiance Scaling for Versatile Surface Enhancement", I3D 2010): a grey Lambertian
  surface whose normals are steepened by the vertical exaggeration, its brightness scaled up on
  convex and down on concave places by the surface's curvature (:func:`convexity`), so a relief
  of a few tenths of a millimetre on a flat tablet reads at once.

Images are ``(h, w, 3)`` uint8, display-encoded (sRGB); computations are in linear light.
"""

from __future__ import annotations

import numpy as np

from reconstruct.report.figures import encode_srgb8
from ptmcore.relight import light_direction

__all__ = ["convexity", "exaggerated_normals", "relief_shading"]

#: Grey albedo and ambient light of the relief shading (linear): the ambient term keeps
#: shadowed slopes readable.
RELIEF_ALBEDO = 0.8
RELIEF_AMBIENT = 0.12
#: How far radiance scaling brightens convex and darkens concave places (0: plain shading).
RELIEF_STRENGTH = 0.6


def exaggerated_normals(normals: np.ndarray, factor: float) -> np.ndarray:
    """Normals of the surface whose heights are multiplied by `factor`: the slopes
    (−nx/nz, −ny/nz) scale by it, so (nx, ny) do before renormalising."""
    n = np.asarray(normals, dtype=np.float32) * np.array([factor, factor, 1.0], np.float32)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), np.float32(1e-6))


def convexity(normals: np.ndarray) -> np.ndarray:
    """How convex the surface is at each texel, scaled to −1…1.

    The negative Laplacian of the height, −(∂p/∂x + ∂q/∂y) with (p, q) = (−nx/nz, −ny/nz) the
    slopes (y up, so ∂/∂y = −∂/∂row), smoothed over a texel and divided by its 95th percentile
    of magnitude (the scale of the object's own detail), then squashed by tanh.

    Parameters
    ----------
    normals : numpy.ndarray
        ``(h, w, 3)`` unit normals, (0, 0, 1) where unknown.

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` float32: > 0 on ridges and domes, < 0 in grooves.
    """
    from scipy.ndimage import gaussian_filter

    from reconstruct.surface.divergence import divergence_from_normals

    # The DCT integrator's right-hand side Dᵀg is −∇²z (its slope limit keeps steep walls finite).
    c = gaussian_filter(divergence_from_normals(normals, None)[0], 1.0)
    scale = float(np.percentile(np.abs(c), 95)) or 1.0
    return np.tanh(c / np.float32(scale)).astype(np.float32)


def relief_shading(
    normals: np.ndarray,
    convex: np.ndarray,
    light: np.ndarray,
) -> np.ndarray:
    """A grey rendering of the shape: Lambertian shading of the exaggerated normals with
    radiance scaling by the convexity.

    Parameters
    ----------
    normals : numpy.ndarray
        ``(h, w, 3)`` unit normals, exaggerated as the view shows them
        (:func:`exaggerated_normals`).
    convex : numpy.ndarray
        ``(h, w)`` convexity from :func:`convexity` (of the unexaggerated normals: it is
        scale-free).
    light : array_like, shape (3,)
        Direction towards the light.

    Returns
    -------
    numpy.ndarray
        ``(h, w, 3)`` uint8 sRGB grey image.
    """
    l_vec = light_direction(light=light).astype(np.float32)
    lambert = np.maximum(np.asarray(normals, np.float32) @ l_vec, np.float32(0.0))
    linear = RELIEF_ALBEDO * (RELIEF_AMBIENT + (1 - RELIEF_AMBIENT) * lambert) * (1 + RELIEF_STRENGTH * convex)
    grey = encode_srgb8(linear)
    return np.repeat(grey[..., None], 3, axis=2)
