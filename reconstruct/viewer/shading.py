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

from ptmcore.images import linear_to_srgb
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

    n = np.asarray(normals, dtype=np.float32)
    nz = np.maximum(n[..., 2], np.float32(0.05))
    p, q = -n[..., 0] / nz, -n[..., 1] / nz
    laplacian = np.gradient(p, axis=1) - np.gradient(q, axis=0)
    c = -gaussian_filter(laplacian, 1.0)
    scale = float(np.percentile(np.abs(c), 95)) or 1.0
    return np.tanh(c / np.float32(scale)).astype(np.float32)


def relief_shading(
    normals: np.ndarray,
    convex: np.ndarray,
    light: np.ndarray,
    *,
    strength: float = RELIEF_STRENGTH,
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
    strength : float
        Radiance scaling's weight, 0 to 1.

    Returns
    -------
    numpy.ndarray
        ``(h, w, 3)`` uint8 sRGB grey image.
    """
    l_vec = light_direction(light=light).astype(np.float32)
    lambert = np.maximum(np.asarray(normals, np.float32) @ l_vec, np.float32(0.0))
    linear = RELIEF_ALBEDO * (RELIEF_AMBIENT + (1 - RELIEF_AMBIENT) * lambert) * (1 + np.float32(strength) * convex)
    grey = np.round(linear_to_srgb(np.clip(linear, 0.0, 1.0)) * 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=2)
