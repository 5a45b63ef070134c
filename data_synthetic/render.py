"""Rendering of a synthetic surface under directional lights, as a camera would record it."""

from __future__ import annotations

import numpy as np

from .shadows import cast_shadow_mask
from .surface import Surface

_VIEW = np.array([0.0, 0.0, 1.0])


def render(
    surface: Surface,
    lights: np.ndarray,
    *,
    specular: float = 0.0,
    shininess: float = 30.0,
    cast_shadows: bool = True,
    ambient: float = 0.0,
    noise: float = 0.005,
    seed: int = 0,
) -> np.ndarray:
    """Linear radiance of ``surface`` under each light (intensity 1, orthographic camera).

    Per light: ``albedo · max(0, n·l)`` plus, if ``specular > 0``, a white Blinn–Phong lobe
    ``specular · max(0, n·h)^shininess`` (view (0, 0, 1)) on surfaces facing the light; both
    are zero where the height field casts a shadow. Then ``ambient · albedo`` and Gaussian
    sensor noise are added. Values are not clipped: negative noise and over-bright
    highlights survive, for the writer to clip like a camera.

    Parameters
    ----------
    surface : Surface
        The scene.
    lights : np.ndarray
        (N, 3) directions towards the lights, above the plane (z > 0); normalised here.
    specular : float
        Peak of the specular lobe; 0 gives a purely Lambertian surface.
    shininess : float
        Blinn–Phong exponent; larger is a tighter highlight.
    cast_shadows : bool
        Whether the height field shadows itself.
    ambient : float
        Uniform light added to every image, as a fraction of the albedo.
    noise : float
        Standard deviation of the sensor noise, relative to full scale (1.0).
    seed : int
        Seeds the noise generator; images draw from it in light order.

    Returns
    -------
    np.ndarray
        (N, H, W, 3) float32 linear radiance.
    """
    lights = np.asarray(lights, dtype=np.float64).reshape(-1, 3)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    if np.any(lights[:, 2] <= 0):
        raise ValueError("every light must be above the object plane (z > 0)")
    if noise < 0 or specular < 0 or ambient < 0:
        raise ValueError("noise, specular and ambient must not be negative")
    h, w = surface.shape
    normals = surface.normals
    albedo = surface.albedo
    rng = np.random.default_rng(seed)
    out = np.empty((len(lights), h, w, 3), dtype=np.float32)
    for i, light in enumerate(lights):
        cosine = normals @ light.astype(np.float32)
        lit = cosine > 0
        if cast_shadows:
            lit &= ~cast_shadow_mask(surface.height, surface.pixel_size, light)
        shading = np.where(lit, cosine, np.float32(0))
        image = out[i]
        np.multiply(albedo, shading[..., None], out=image)
        if specular > 0:
            half = (light + _VIEW) / np.linalg.norm(light + _VIEW)
            lobe = np.clip(normals @ half.astype(np.float32), 0, None) ** np.float32(shininess)
            image += np.where(lit, np.float32(specular) * lobe, np.float32(0))[..., None]
        if ambient > 0:
            image += np.float32(ambient) * albedo
        if noise > 0:
            image += np.float32(noise) * rng.standard_normal((h, w, 3), dtype=np.float32)
    return out
