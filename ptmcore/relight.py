"""Relighting an LRGB PTM as RTIViewer does: default, diffuse gain and specular enhancement.

An LRGB PTM here is ``coefficients (H, W, 6)`` float32, the luminance polynomial
``L = a0·lu² + a1·lv² + a2·lu·lv + a3·lu + a4·lv + a5`` in 0–255 luminance units, plus
``rgb (H, W, 3)`` uint8, the colour. (lu, lv) are the x and y components of the unit vector
towards the light, in the project frame (x right, y up, z towards the camera).

The formulas follow RTIViewer 1.1 (Visual Computing Lab ISTI-CNR and Cultural Heritage
Imaging), read in its sources ``ptm.h`` (``DefaultRenderingPtm``), ``diffusegain.cpp``,
``specularenhanc.cpp`` and ``util.h`` (``tobyte``):

* default rendering: ``out = tobyte(rgb · L / 255)``;
* diffuse gain (Malzbender, Gelb, Wolters, "Polynomial Texture Maps", SIGGRAPH 2001, §5.2):
  the polynomial is rewritten about the light of its maximum with its quadratic part scaled
  by a gain g (RTIViewer's default g = 2, slider range 1–10), then rendered as default;
* specular enhancement: ``out = tobyte((kd · rgb + 255 · ks · (n·h)ⁿ) · L / 255)`` with n the
  normal at the PTM's maximum, h the half-way vector between the light and the view direction
  (0, 0, 1), and RTIViewer's defaults kd = 0.4, ks = 0.7, n = 75;

where ``tobyte`` clips to 0–255 and truncates (it does not round). Everything is vectorised
over pixels and done in bands of rows, so temporaries stay small for large captures.
"""

from __future__ import annotations

import math

import numpy as np

from .fit import evaluate_at, light_matrix
from .images import LUMA_WEIGHTS
from .normals import ptm_maximum

__all__ = ["as_lrgb", "check_parameters", "diffuse_gain", "display_srgb", "light_angles", "light_direction", "relight",
           "specular_enhancement"]

#: RTIViewer's default diffuse gain (``DiffuseGain`` constructor; the slider spans 1–10).
DEFAULT_GAIN = 2.0
#: RTIViewer's defaults of specular enhancement (``SpecularEnhancement`` constructor):
#: diffuse weight, specular weight and Phong exponent.
DEFAULT_KD = 0.4
DEFAULT_KS = 0.7
DEFAULT_EXPONENT = 75.0

# Pixels per band: a band's float64 copy of the coefficients and its temporaries stay around 100 MB.
_BAND_PIXELS = 1 << 21

_VIEW = np.array([0.0, 0.0, 1.0])


def light_direction(
    *,
    light: np.ndarray | tuple[float, ...] | None = None,
    azimuth_deg: float | None = None,
    elevation_deg: float | None = None,
) -> np.ndarray:
    """The unit vector towards a light, from a vector or from azimuth and elevation.

    Parameters
    ----------
    light : array_like, shape (3,) or (2,), optional
        A direction (x, y, z), normalised here, or the projection (lu, lv) of a unit vector
        on the image plane (``lu² + lv² ≤ 1``; z is then ``√(1 − lu² − lv²)``).
    azimuth_deg : float, optional
        Angle in the image plane, counter-clockwise from +x: 0° is light from the right,
        90° from the top, 180° from the left.
    elevation_deg : float, optional
        Angle above the object plane, 0° (grazing) to 90° (from the camera).

    Returns
    -------
    ndarray, shape (3,), float64
        Unit vector (x right, y up, z towards the camera), z ≥ 0.

    Raises
    ------
    ValueError
        If neither or both of `light` and the angles are given, only one angle is given, a
        value is not finite, the vector is zero, or the light is below the horizon.
    """
    if light is not None:
        if azimuth_deg is not None or elevation_deg is not None:
            raise ValueError("give either light or azimuth_deg and elevation_deg, not both")
        v = np.asarray(light, dtype=np.float64).reshape(-1)
        if v.shape not in ((2,), (3,)):
            raise ValueError(f"light must have 2 (lu, lv) or 3 (x, y, z) components, not {v.size}")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"light direction {v.tolist()} is not finite")
        if v.size == 2:
            r2 = float(v @ v)
            # A little slack so that (cos a, sin a) computed in float passes.
            if r2 > 1.0 + 1e-9:
                raise ValueError(
                    f"light (lu, lv) = {v.tolist()} lies outside the unit disk "
                    "(it is not the projection of a unit vector)"
                )
            return np.array([v[0], v[1], math.sqrt(max(0.0, 1.0 - r2))])
        norm = float(np.linalg.norm(v))
        if norm == 0.0:
            raise ValueError("light direction is the zero vector")
        if v[2] < 0.0:
            raise ValueError(f"light direction {v.tolist()} is below the horizon (z < 0)")
        return v / norm
    if azimuth_deg is None or elevation_deg is None:
        raise ValueError("give light, or both azimuth_deg and elevation_deg")
    az, el = float(azimuth_deg), float(elevation_deg)
    if not (math.isfinite(az) and math.isfinite(el)):
        raise ValueError(f"azimuth {az} and elevation {el} must be finite")
    if el < 0.0:
        raise ValueError(f"elevation {el}° is below the horizon (it must be 0° to 90°)")
    if el > 90.0:
        raise ValueError(f"elevation {el}° is past the zenith (it must be 0° to 90°)")
    a, e = math.radians(az), math.radians(el)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


def light_angles(directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth and elevation of light directions, the angles of :func:`light_direction`.

    Parameters
    ----------
    directions : array_like, shape (N, 3) or (3,)
        Unit vectors towards the lights (x right, y up, z towards the camera).

    Returns
    -------
    azimuth_deg : ndarray, shape (N,) or ()
        Counter-clockwise from +x, in [0, 360): 0° is light from the right, 90° from the top.
    elevation_deg : ndarray, shape (N,) or ()
        Above the object plane, −90° to 90° (negative below the horizon).
    """
    d = np.asarray(directions, dtype=np.float64)
    azimuth = np.degrees(np.arctan2(d[..., 1], d[..., 0])) % 360.0
    elevation = np.degrees(np.arcsin(np.clip(d[..., 2], -1.0, 1.0)))
    return azimuth, elevation


def _check_ptm(coefficients: np.ndarray, rgb: np.ndarray | None = None) -> np.ndarray:
    """Validate the shapes of an LRGB PTM; return the coefficients as an array."""
    coef = np.asarray(coefficients)
    if coef.ndim != 3 or coef.shape[2] != 6:
        raise ValueError(f"coefficients must be (H, W, 6), not {coef.shape}")
    if rgb is not None:
        if rgb.shape != coef.shape[:2] + (3,):
            raise ValueError(f"rgb must be {coef.shape[:2] + (3,)} to match the coefficients, not {rgb.shape}")
        if rgb.dtype != np.uint8:
            raise ValueError(f"rgb must be uint8, not {rgb.dtype}")
    return coef


def _bands(height: int, width: int) -> list[tuple[int, int]]:
    """Consecutive row ranges of about ``_BAND_PIXELS`` pixels covering the image."""
    step = max(1, _BAND_PIXELS // max(1, width))
    return [(r0, min(height, r0 + step)) for r0 in range(0, height, step)]


def _basis(light: np.ndarray) -> np.ndarray:
    """Row ``[lu², lv², lu·lv, lu, lv, 1]`` of one unit light, float32."""
    return light_matrix(light[None, :2]).astype(np.float32)[0]


def _shade(rgb: np.ndarray, lum: np.ndarray, kd: float | None, specular: np.ndarray | None) -> np.ndarray:
    """``tobyte((kd · rgb + specular) · L / 255)`` for one band.

    RTIViewer's ``tobyte`` clips to 0–255 and truncates. With ``kd=None`` and no specular term
    this is exactly the default rendering, so specular enhancement with kd = 1, ks = 0 gives
    the same bytes.
    """
    out = rgb.astype(np.float32)
    if kd is not None:
        out *= np.float32(kd)
    if specular is not None:
        out += specular[..., None]
    out *= (lum / np.float32(255.0))[..., None]
    np.nan_to_num(out, copy=False, nan=0.0)
    np.clip(out, 0.0, 255.0, out=out)
    return out.astype(np.uint8)


def relight(coefficients: np.ndarray, rgb: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Render an LRGB PTM under one light, as RTIViewer's default mode.

    ``out = tobyte(rgb · L(lu, lv) / 255)`` per pixel and channel, where ``tobyte`` clips to
    0–255 and truncates (RTIViewer ``DefaultRenderingPtm::applyPtmLRGB``).

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6)
        a0..a5 in 0–255 luminance units.
    rgb : ndarray, shape (H, W, 3), uint8
        Colour of each pixel.
    light : array_like, shape (3,) or (2,)
        Light direction, as accepted by :func:`light_direction`.

    Returns
    -------
    ndarray, shape (H, W, 3), uint8

    Examples
    --------
    Diffuse gain is a change of coefficients rendered the default way::

        image = relight(diffuse_gain(coefficients), rgb, light_direction(azimuth_deg=30, elevation_deg=40))
    """
    rgb = np.asarray(rgb)
    coef = _check_ptm(coefficients, rgb)
    row = _basis(light_direction(light=light))
    h, w = coef.shape[:2]
    out = np.empty((h, w, 3), dtype=np.uint8)
    for r0, r1 in _bands(h, w):
        lum = coef[r0:r1].astype(np.float32, copy=False) @ row
        out[r0:r1] = _shade(rgb[r0:r1], lum, None, None)
    return out


def display_srgb(image: np.ndarray) -> np.ndarray:
    """Encode an 8-bit rendering of a linear-light PTM as sRGB for display.

    A PTM fitted to linear photographs (16-bit captures) holds linear light scaled to 0-255;
    shown as it is (as RTIViewer shows it) it looks dark and contrasty. This applies the sRGB
    transfer function byte by byte, through a 256-entry table.
    """
    from .images import linear_to_srgb

    table = np.round(linear_to_srgb(np.arange(256, dtype=np.float32) / 255.0) * 255.0).astype(np.uint8)
    return table[np.asarray(image, dtype=np.uint8)]


#: The largest value of each relighting parameter: far past RTIViewer's sliders (kd, ks up to
#: 1, exponent 150, gain 10), where the image is already white or one highlight.
PARAMETER_BOUNDS = {"kd": 100.0, "ks": 100.0, "exponent": 10_000.0, "gain": 1000.0}


def check_parameters(*, kd: float | None = None, ks: float | None = None, exponent: float | None = None,
                     gain: float | None = None) -> None:
    """Check the parameters of :func:`specular_enhancement` and :func:`diffuse_gain` given.

    They check their own; a caller about to do long work before calling them (read a large
    PTM, find its maxima) checks first, so a typo is refused at once.

    Raises
    ------
    ValueError
        For the first one that is not a number from 0 to its bound (:data:`PARAMETER_BOUNDS`;
        ``gain`` above 0): beyond them every pixel saturates, or the arithmetic overflows.
    """
    for name, value in (("kd", kd), ("ks", ks), ("exponent", exponent), ("gain", gain)):
        if value is None:
            continue
        top = PARAMETER_BOUNDS[name]
        value = float(value)
        low_ok = value > 0.0 if name == "gain" else value >= 0.0
        if not (math.isfinite(value) and low_ok and value <= top):
            within = f"above 0, at most {top:g}" if name == "gain" else f"from 0 to {top:g}"
            raise ValueError(f"{name} must be a number {within}, not {value:g}")


def diffuse_gain(coefficients: np.ndarray, gain: float = DEFAULT_GAIN, *,
                 maximum: np.ndarray | None = None) -> np.ndarray:
    """Coefficients with the diffuse gain of Malzbender et al. (2001) applied.

    With (nu, nv) the light of each polynomial's maximum (:func:`ptmcore.normals.ptm_maximum`)
    and g the gain, the polynomial is rewritten about (nu, nv) with its quadratic part scaled
    by g (RTIViewer ``DiffuseGain::applyModel``)::

        a0' = g·a0      a1' = g·a1      a2' = g·a2
        a3' = (1 − g)·(2·a0·nu + a2·nv) + a3
        a4' = (1 − g)·(2·a1·nv + a2·nu) + a4
        a5' = (1 − g)·(a0·nu² + a1·nv² + a2·nu·nv) + (a3 − a3')·nu + (a4 − a4')·nv + a5

    so that ``L'(l) − L(n) = g·(L(l) − L(n))``: the value and the gradient at (nu, nv) are
    kept and every other light departs g times as much from it. Where the maximum is the
    interior stationary point of a concave polynomial (the usual case), it therefore stays at
    the same (nu, nv) with the same value for any g > 0; g > 1 exaggerates the surface's
    curvature (its shading), g < 1 flattens it. Where the maximum lies on the rim of the disk
    it is not stationary and may move.

    Render the result with :func:`relight`. (RTIViewer divides the gained luminance by 256
    rather than the 255 of its default mode; here both use 255, so g = 1 renders exactly as
    the default.)

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6)
        a0..a5 (any luminance units: the transform is linear in them).
    gain : float
        g > 0. RTIViewer's default is 2.
    maximum : ndarray, shape (H, W, 3), optional
        The normals (nu, nv, nz) at the polynomials' maxima, when already known (as for
        :func:`specular_enhancement`): finding them is most of the cost, so a viewer that
        changes the gain computes them once.

    Returns
    -------
    ndarray, shape (H, W, 6)
        float32 (float64 if the input was float64).

    Raises
    ------
    ValueError
        If the gain is not a positive finite number.
    """
    check_parameters(gain=gain)
    g = float(gain)
    coef = _check_ptm(coefficients)
    dtype = np.result_type(coef.dtype, np.float32)
    h, w = coef.shape[:2]
    out = np.empty((h, w, 6), dtype=dtype)
    for r0, r1 in _bands(h, w):
        a = coef[r0:r1].astype(np.float64)
        if maximum is None:
            nu, nv, _ = ptm_maximum(a)
        else:
            nu, nv = maximum[r0:r1, :, 0], maximum[r0:r1, :, 1]
        nu = nu.astype(np.float64)
        nv = nv.astype(np.float64)
        a0, a1, a2, a3, a4, a5 = (a[..., k] for k in range(6))
        # With g = 1 every (1 − g) term is 0 and the result is bit-identical to the input.
        a3g = (1.0 - g) * (2.0 * a0 * nu + a2 * nv) + a3
        a4g = (1.0 - g) * (2.0 * a1 * nv + a2 * nu) + a4
        a5g = (1.0 - g) * (a0 * nu * nu + a1 * nv * nv + a2 * nu * nv) + (a3 - a3g) * nu + (a4 - a4g) * nv + a5
        out[r0:r1] = np.stack([g * a0, g * a1, g * a2, a3g, a4g, a5g], axis=-1)
    return out


def specular_enhancement(
    coefficients: np.ndarray,
    rgb: np.ndarray,
    light: np.ndarray,
    *,
    kd: float = DEFAULT_KD,
    ks: float = DEFAULT_KS,
    exponent: float = DEFAULT_EXPONENT,
    maximum: np.ndarray | None = None,
) -> np.ndarray:
    """Render an LRGB PTM with RTIViewer's "specular enhancement".

    A Blinn–Phong lobe on the normal at the PTM's maximum is added to a scaled-down colour,
    and the sum is shaded by the PTM's luminance (RTIViewer
    ``SpecularEnhancement::applyPtmLRGB``)::

        out = tobyte((kd · rgb + 255 · ks · clip(n·h, 0, 1)^exponent) · L(lu, lv) / 255)

    where n = (nu, nv, √(1 − nu² − nv²)) is the normal from the maximum of the polynomial
    (:func:`ptmcore.normals.ptm_maximum`), h = (l + v)/|l + v| is the half-way vector between
    the light l and the view direction v = (0, 0, 1), and ``tobyte`` clips to 0–255 and
    truncates. The defaults are RTIViewer's (kd = 0.4, ks = 0.7, n = 75; its sliders span
    kd, ks in 0–1 and n in 1–150). With ks = 0 the result is the default rendering with the
    colour scaled by kd (identical bytes to :func:`relight` when kd = 1).

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6)
        a0..a5 in 0–255 luminance units.
    rgb : ndarray, shape (H, W, 3), uint8
        Colour of each pixel.
    light : array_like, shape (3,) or (2,)
        Light direction, as accepted by :func:`light_direction`.
    kd : float
        Weight of the diffuse colour, ≥ 0.
    ks : float
        Weight of the specular lobe, ≥ 0.
    exponent : float
        Specular exponent (highlight sharpness), ≥ 0.
    maximum : ndarray, shape (H, W, 3), optional
        The normals (nu, nv, nz) at the polynomials' maxima, when already known: finding them
        costs about twice a relight, so a viewer that moves the light computes them once.

    Returns
    -------
    ndarray, shape (H, W, 3), uint8

    Raises
    ------
    ValueError
        If a parameter is negative or not finite.
    """
    check_parameters(kd=kd, ks=ks, exponent=exponent)
    rgb = np.asarray(rgb)
    coef = _check_ptm(coefficients, rgb)
    l_vec = light_direction(light=light)
    row = _basis(l_vec)
    half = l_vec + _VIEW  # never zero: the light is not below the horizon
    half = (half / np.linalg.norm(half)).astype(np.float32)
    h, w = coef.shape[:2]
    out = np.empty((h, w, 3), dtype=np.uint8)
    for r0, r1 in _bands(h, w):
        band = coef[r0:r1].astype(np.float32, copy=False)
        lum = band @ row
        if maximum is None:
            nu, nv, _ = ptm_maximum(band)
            nz = np.sqrt(np.clip(1.0 - nu * nu - nv * nv, 0.0, 1.0))
        else:
            nu, nv, nz = (maximum[r0:r1, :, k] for k in range(3))
        n_dot_h = np.clip(nu * half[0] + nv * half[1] + nz * half[2], 0.0, 1.0)
        lobe = np.float32(255.0 * float(ks)) * n_dot_h ** np.float32(exponent)
        out[r0:r1] = _shade(rgb[r0:r1], lum, float(kd), lobe)
    return out


def as_lrgb(ptm) -> tuple[np.ndarray, np.ndarray]:
    """LRGB coefficients and colour of a PTM (:class:`ptmcore.ptmfile.PTMFile`); RGB-format
    PTMs are converted.

    The luminance polynomial of an RGB-format PTM is the weighted sum of its channels'
    (luminance is linear in them); the colour is each channel's share of it at the
    luminance maximum, where it is best determined.
    """
    if ptm.is_lrgb:
        return ptm.coefficients, ptm.rgb
    coef = np.einsum("hwck,c->hwk", ptm.coefficients, LUMA_WEIGHTS)
    lu, lv, _ = ptm_maximum(coef)
    channels = evaluate_at(ptm.coefficients, lu, lv)
    lum = evaluate_at(coef, lu, lv)[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(lum > 0, channels / lum, 1.0)
    # Channels brighter than the luminance (saturated colours) move into the coefficients.
    k = np.maximum(share.max(axis=-1), 1.0)
    rgb = np.clip(np.round(share / k[..., None] * 255), 0, 255).astype(np.uint8)
    return (coef * k[..., None]).astype(np.float32), rgb
