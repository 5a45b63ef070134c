"""Height map from a normal map: gradients and the choice of integrator.

Frame (see ``docs/CONVENTIONS.md``): x to the right, y **up**, z towards the camera. A
surface z(x, y) has the normal n ∝ (−p, −q, 1) with p = ∂z/∂x and q = ∂z/∂y.
:func:`gradients_from_normals` turns normals into (p, q), and :func:`integrate` passes them to
one of four integrators:

* on the whole rectangle (:mod:`reconstruct.surface.fourier`): :func:`poisson_dct`, least
  squares with the Neumann boundary solved by the DCT (the default), and
  :func:`frankot_chellappa`;
* on the mask only (:mod:`reconstruct.surface.masked`): :func:`masked_poisson`, least squares
  with a free boundary, and (:mod:`reconstruct.surface.bilateral`)
  :func:`discontinuity_preserving`, bilateral normal integration (BiNI) that keeps creases and
  steps.
"""

from __future__ import annotations

import math

import numpy as np

from reconstruct.surface.fourier import checked_normals, frankot_chellappa, poisson_dct, solve_neumann
from reconstruct.surface.bilateral import discontinuity_preserving
from reconstruct.surface.masked import masked_poisson

__all__ = ["gradients_from_normals", "integrate"]


def gradients_from_normals(
    normals: np.ndarray, *, max_slope_deg: float = 85.0
) -> tuple[np.ndarray, np.ndarray]:
    """Surface gradients from a normal map.

    Parameters
    ----------
    normals : numpy.ndarray
        ``(H, W, 3)`` normals in the project frame (x right, y up, z towards the camera).
        They need not be unit length. Non-finite normals (outside a mask) are allowed.
    max_slope_deg : float
        Largest slope, in degrees from the image plane, that a normal may imply. Normals
        closer to the horizon (or pointing away from the camera) are tilted back to this
        slope, keeping their azimuth, so the gradients stay finite.

    Returns
    -------
    p, q : numpy.ndarray
        ``(H, W)`` float32 gradients p = ∂z/∂x = −nx/nz and q = ∂z/∂y = −ny/nz (y up), in
        height units per horizontal unit. 0 where a normal is not finite.

    Raises
    ------
    ValueError
        If `normals` is not ``(H, W, 3)`` or `max_slope_deg` is not in (0, 90).
    """
    normals = checked_normals(normals, max_slope_deg)
    nx, ny, nz = normals[..., 0], normals[..., 1], normals[..., 2]
    # |∇z| = hypot(nx, ny) / nz, so nz >= hypot / tan(max) bounds the slope; this also gives
    # normals facing away from the camera (nz <= 0) the maximum slope instead of a sign flip.
    tan_max = np.float32(math.tan(math.radians(max_slope_deg)))
    denom = np.hypot(nx, ny)
    denom /= tan_max
    np.maximum(denom, nz, out=denom)
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.negative(nx) / denom
        q = np.negative(ny) / denom
    # 0/0 happens only for nx = ny = 0 with nz <= 0, where the flat answer is the sane one.
    p[~np.isfinite(p)] = 0.0
    q[~np.isfinite(q)] = 0.0
    return p, q


_METHODS = {
    "dct": poisson_dct,
    "fc": frankot_chellappa,
    "masked": masked_poisson,
    "bilateral": discontinuity_preserving,
}
# Integrators on the mask only, which get the whole image when there is no mask.
_MASKED_METHODS = ("masked", "bilateral")


def integrate(
    normals: np.ndarray,
    method: str = "dct",
    *,
    mask: np.ndarray | None = None,
    pixel_size: float = 1.0,
    max_slope_deg: float = 85.0,
    workers: int | None = -1,
    return_info: bool = False,
    steep_weights: bool = False,
) -> np.ndarray | tuple[np.ndarray, dict]:
    """Height map from a normal map.

    Parameters
    ----------
    normals : numpy.ndarray
        ``(H, W, 3)`` normals in the project frame (x right, y up, z towards the camera).
    method : {"dct", "fc", "masked", "bilateral"}
        ``"dct"``: least squares with Neumann boundary (:func:`poisson_dct`), the default.
        ``"fc"``: Frankot–Chellappa with mirrored borders (:func:`frankot_chellappa`).
        ``"masked"``: least squares on the mask only, free boundary
        (:func:`masked_poisson`). ``"bilateral"``: bilateral normal integration on the
        mask, keeping steps (:func:`discontinuity_preserving`, Cao et al. 2022). Both use
        the whole image (minus non-finite normals) when there is no mask.
    mask : numpy.ndarray, optional
        ``(H, W)`` bool, True for pixels of the object. Without a mask, pixels whose normal
        is not finite are treated as outside the object.
    pixel_size : float
        Pixel size; heights come out in its unit (mm for mm/pixel, pixels for 1).
    max_slope_deg : float
        Slope limit passed to :func:`gradients_from_normals`.
    workers : int or None
        Threads for scipy.fft (−1: all CPUs).
    return_info : bool
        Also return the solver's info dict (``masked`` and ``bilateral``: iterations and
        more, ``bilateral`` the edges it cut; an empty dict for ``dct`` and ``fc``).
    steep_weights : bool
        ``masked`` only: weigh each pixel's equations by nz² (of its normal after the slope
        limit), as bilateral integration does: a normal's error δ moves its gradient by about
        δ/nz², so the steepest normals' gradients are the least sure.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 heights, mean 0 over the object, NaN outside it. With
        `return_info`, a ``(height, info)`` tuple.

    Raises
    ------
    ValueError
        For an unknown `method` or mismatched inputs.
    """
    try:
        integrator = _METHODS[method]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown integration method {method!r}; use one of {list(_METHODS)}"
        ) from None
    if steep_weights and method != "masked":
        raise ValueError(f"steep_weights applies to the masked integrator, not {method!r}")
    normals = np.asarray(normals)
    if method == "dct":
        # The same arithmetic as below in two compiled passes instead of a dozen NumPy ones.
        from reconstruct.surface.divergence import divergence_from_normals  # numba: imported when used

        mask = None if mask is None else np.asarray(mask, dtype=bool)
        f, nonfinite = divergence_from_normals(normals, mask, max_slope_deg=max_slope_deg, workers=workers)
        if mask is None and nonfinite:
            mask = np.isfinite(normals).all(axis=-1)
        height = solve_neumann(f, mask, pixel_size, workers=workers)
        return (height, {}) if return_info else height
    if mask is None:
        finite = np.isfinite(normals).all(axis=-1) if normals.ndim == 3 else None
        if finite is not None and not finite.all():
            mask = finite
    p, q = gradients_from_normals(normals, max_slope_deg=max_slope_deg)
    if method in _MASKED_METHODS and mask is None:
        mask = np.ones(p.shape, dtype=bool)  # the whole image is the domain
    if method in _MASKED_METHODS:
        extra = {"weights": 1.0 / (1.0 + p * p + q * q)} if steep_weights else {}
        return integrator(p, q, mask=mask, pixel_size=pixel_size, workers=workers, return_info=return_info, **extra)
    height = integrator(p, q, mask=mask, pixel_size=pixel_size, workers=workers)
    return (height, {}) if return_info else height
