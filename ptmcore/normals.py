"""Surface normals from a PTM's maximum and from Lambertian photometric stereo.

Both work in bands of rows, so memory stays bounded: the PTM maximum in a compiled kernel
(:mod:`ptmcore.maximum`), photometric stereo vectorised over the pixels of a band.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .bands import band_rows, run_bands
from .images import ImageStack
from .lp import as_directions
from .pixelfit import SINGULAR

#: A PTM is flat where |a0| + … + |a4| ≤ this × |a5|, a5 finite (an all-zero PTM too): the
#: pixel's samples carry no direction (all clipped, all black, or one value under every light),
#: and what shape the fit has is the float32 sums' rounding, about 1e-7 of the level, which
#: differs between CPUs and BLAS libraries. Real shading varies by more than 1e-2 of the level
#: over a dome's lights, and one 16-bit code of a bright pixel is 1.5e-5 of it. A flat PTM's
#: maximum is taken at (0, 0) (:func:`ptm_maximum`) and no normal is read from it
#: (:func:`normals_from_ptm`, :func:`ptmcore.robustptm.debiased_normals`, the robust PTM's
#: kernel): it is (0, 0, 1), flagged.
FLAT = 1e-4


def ptm_maximum(
    coefficients: np.ndarray, *, threads: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Light direction (lu0, lv0) of each PTM polynomial's maximum over the unit disk.

    Where the polynomial is strictly concave and its stationary point lies inside the disk,
    the closed form of Malzbender et al. is used::

        lu0 = (a2·a4 − 2·a1·a3) / (4·a0·a1 − a2²)
        lv0 = (a2·a3 − 2·a0·a4) / (4·a0·a1 − a2²)

    Elsewhere (not concave, or the stationary point outside the disk) the maximum over the
    disk is on its boundary and is found there, rather than by clamping the stationary point:
    L(θ) is sampled every 5° on the unit circle and the best sample refined by Newton's method
    on L'(θ). The arithmetic is float64 (compiled: :mod:`ptmcore.maximum`). A flat PTM
    (:data:`FLAT`) has no maximum but its rounding's: it is taken at (0, 0), not interior.

    Parameters
    ----------
    coefficients : ndarray, shape (..., 6)
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).

    Returns
    -------
    lu0, lv0 : ndarray, shape (...)
        float32.
    interior : ndarray, shape (...), bool
        Where the maximum is the interior closed-form one.
    """
    from .maximum import maximum_bands  # numba's import costs a second; `import ptmcore` does not need it

    a = np.asarray(coefficients)
    shape = a.shape[:-1]
    # Rows of pixels for the bands: (H, W, 6) as it is, a list of pixels as a column.
    a = a.reshape((math.prod(a.shape[:-2]), a.shape[-2], 6) if a.ndim >= 3 else (-1, 1, 6))
    lu = np.empty(a.shape[:2], dtype=np.float32)
    lv = np.empty(a.shape[:2], dtype=np.float32)
    interior = np.empty(a.shape[:2], dtype=bool)
    maximum_bands(a, lu, lv, interior=interior, threads=threads)
    return lu.reshape(shape), lv.reshape(shape), interior.reshape(shape)


def normals_from_ptm(coefficients: np.ndarray, *, threads: int | None = None,
                     valid: np.ndarray | None = None) -> np.ndarray:
    """Normals ``(lu0, lv0, √(1 − lu0² − lv0²))`` from each PTM's maximum (:func:`ptm_maximum`).

    A flat PTM (:data:`FLAT`: an all-zero one, or the fit of samples all clipped or all one
    value) has no maximum but its rounding's: its normal is (0, 0, 1), not read.

    Parameters
    ----------
    coefficients : ndarray, shape (H, W, 6)
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    valid : ndarray, shape (H, W), bool, optional
        Out: where a normal was read (False where the PTM is flat or its maximum not finite).

    Returns
    -------
    ndarray, shape (H, W, 3), float32
        Unit normals.

    Raises
    ------
    ValueError
        If ``coefficients`` is not (H, W, 6).
    """
    from .maximum import maximum_bands  # numba's import costs a second; `import ptmcore` does not need it

    coefficients = np.asarray(coefficients)
    out = np.empty(coefficients.shape[:-1] + (3,), dtype=np.float32)  # maximum_bands checks the shape
    maximum_bands(coefficients, out[..., 0], out[..., 1], out[..., 2], valid=valid, threads=threads)
    return out


@dataclass
class PhotometricStereo:
    """Result of Lambertian photometric stereo.

    Attributes
    ----------
    normals : ndarray, shape (H, W, 3), float32
        Unit normals; (0, 0, 1) where they could not be determined.
    albedo : ndarray, shape (H, W), float32
        Linear luminance albedo (reflectance × light intensity).
    samples : ndarray, shape (H, W), uint16
        How many photographs were used at each pixel.
    valid : ndarray, shape (H, W), bool
        Where at least three well-spread samples determined the normal.
    lobe : ptmcore.lobe.Lobe or None
        The reflectance lobe the normals were fitted with (robust fits with ``lobe``).
    """

    normals: np.ndarray
    albedo: np.ndarray
    samples: np.ndarray
    valid: np.ndarray
    lobe: object | None = None


def _weighted_normal_solve(
    dirs: np.ndarray, outer: np.ndarray, values: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve the per-pixel 3×3 weighted normal equations ``(Σ w l lᵀ) g = Σ w I l``.

    Returns ``g`` (3, P), where the system is well posed (P,), and the number of samples used
    (P,), which is the trace of the normal matrix since the light directions are unit vectors.
    """
    m = (outer.T @ weights).astype(np.float64)  # (6, P): xx, yy, zz, xy, xz, yz
    weights *= values  # the weights are not needed again: reuse their memory
    b = (dirs.T @ weights).astype(np.float64)  # (3, P)
    m0, m1, m2, m3, m4, m5 = m
    c00 = m1 * m2 - m5 * m5
    c01 = m4 * m5 - m3 * m2
    c02 = m3 * m5 - m4 * m1
    c11 = m0 * m2 - m4 * m4
    c12 = m3 * m4 - m0 * m5
    c22 = m0 * m1 - m3 * m3
    det = m0 * c00 + m3 * c01 + m4 * c02
    count = m0 + m1 + m2
    # Relative to the cube of the mean eigenvalue, a small determinant means the used lights
    # are (nearly) coplanar: the normal along their plane's normal is undetermined.
    well_posed = det > SINGULAR * np.maximum((count / 3.0) ** 3, 1e-30)
    safe = np.where(well_posed, det, 1.0)
    g = np.stack(
        [
            c00 * b[0] + c01 * b[1] + c02 * b[2],
            c01 * b[0] + c11 * b[1] + c12 * b[2],
            c02 * b[0] + c12 * b[1] + c22 * b[2],
        ]
    ) / safe
    return g, well_posed, count


def shadow_refined_solve(
    solve: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]],
    shading: Callable[[np.ndarray], np.ndarray],
    values: np.ndarray,
    weights: np.ndarray,
    usable: np.ndarray | None,
    *,
    iterations: int,
    min_shading: float,
    cast_shadow_ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Lambertian solve, then passes that leave out the samples its estimate calls shadowed.

    ``solve(weights)`` returns (g (3, P), well posed (P,), samples used (P,)) for (N, P)
    float32 weights; ``shading(unit)`` gives the (N, P) shading n·l of unit normals (3, P).
    Each pass keeps the samples predicted lit (``n·l > min_shading``), not clipped (``usable``)
    and not much darker than predicted (``cast_shadow_ratio`` × ρ n·l: a cast shadow).
    """
    g, ok, count = solve(weights.astype(np.float32))
    for _ in range(iterations):
        rho = np.linalg.norm(g, axis=0)
        unit = (g / np.where(rho > 0, rho, 1.0)).astype(np.float32)
        shade = shading(unit)
        wts = shade > min_shading
        if usable is not None:
            wts &= usable
        shade *= (cast_shadow_ratio * rho).astype(np.float32)  # now the darkest plausible value
        wts &= values >= shade
        g_new, ok_new, count_new = solve(wts.astype(np.float32))
        # Keep the previous estimate where the refined selection left too little.
        g = np.where(ok_new, g_new, g)
        count = np.where(ok_new, count_new, count)
        ok |= ok_new
    return g, ok, count


def store_normals(result: PhotometricStereo, rows: slice, g: np.ndarray, ok: np.ndarray,
                  count: np.ndarray) -> None:
    """Write a band's solution g = ρ n (3, P) into ``result``; (0, 0, 1) where undetermined."""
    h, w = result.albedo[rows].shape
    rho = np.linalg.norm(g, axis=0)
    good = ok & (rho > 0) & np.isfinite(rho)
    nrm = np.where(good, g / np.where(good, rho, 1.0), np.array([[0.0], [0.0], [1.0]]))
    result.normals[rows] = nrm.T.reshape(h, w, 3)
    result.albedo[rows] = np.where(good, rho, 0.0).reshape(h, w)
    result.samples[rows] = np.round(count).reshape(h, w)
    result.valid[rows] = good.reshape(h, w)


def empty_result(shape: tuple[int, int]) -> PhotometricStereo:
    """Uninitialised arrays of a photometric-stereo result, filled band by band."""
    h, w = shape
    return PhotometricStereo(np.empty((h, w, 3), np.float32), np.empty((h, w), np.float32),
                             np.empty((h, w), np.uint16), np.empty((h, w), bool))


def photometric_stereo(
    stack: ImageStack,
    directions: np.ndarray,
    *,
    dark_fraction: float = 0.05,
    min_shading: float = 0.05,
    cast_shadow_ratio: float = 0.4,
    iterations: int = 1,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> PhotometricStereo:
    """Lambertian photometric stereo, excluding shadowed and saturated samples per pixel.

    Each pixel's normal and albedo solve ``I_i = ρ n·l_i`` by weighted least squares over the
    samples that the Lambertian model explains. Saturated samples are always left out. A first
    pass leaves out samples darker than ``dark_fraction`` × the pixel's brightest unsaturated
    sample (shadows); each further pass leaves out the samples the current estimate predicts
    in attached shadow (``n·l < min_shading``) and those much darker than predicted (cast
    shadow: below ``cast_shadow_ratio`` × the prediction).

    Parameters
    ----------
    stack : ImageStack
    directions : ndarray, shape (N, 3)
        Unit light directions.
    dark_fraction, min_shading, cast_shadow_ratio : float
        Thresholds described above.
    iterations : int
        Refinement passes after the first.
    threads : int, optional
        Threads working on bands of rows (default: all CPUs).
    progress : callable, optional
        Called with the number of rows done after each band.

    Returns
    -------
    PhotometricStereo
    """
    n = len(stack)
    h, w = stack.shape
    dirs = as_directions(directions, n, np.float32)
    x, y, z = dirs.T
    outer = np.stack([x * x, y * y, z * z, x * y, x * z, y * z], axis=1)  # (N, 6)
    result = empty_result((h, w))

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        v = values.reshape(n, -1)
        # Most bands have no clipped sample; skip the masking there.
        usable = ~saturated.reshape(n, -1) if saturated.any() else None
        # Clipped samples read as 1; counting them in the maximum only raises the first
        # threshold where the refinement pass re-decides anyway.
        wts = v > np.maximum(dark_fraction * v.max(axis=0), 1e-4)
        if usable is not None:
            wts &= usable
        g, ok, count = shadow_refined_solve(
            lambda weights: _weighted_normal_solve(dirs, outer, v, weights), lambda unit: dirs @ unit,
            v, wts, usable, iterations=iterations, min_shading=min_shading, cast_shadow_ratio=cast_shadow_ratio)
        store_normals(result, slice(r0, r1), g, ok, count)

    run_bands(h, band_rows(n, w, 4 * 4), work, threads=threads, progress=progress)
    return result


def lambertian_albedo(
    stack: ImageStack,
    directions: np.ndarray,
    normals: np.ndarray,
    *,
    min_shading: float = 0.05,
    threads: int | None = None,
) -> np.ndarray:
    """Luminance albedo ρ that best explains the stack given the normals.

    Least squares of ``I_i = ρ n·l_i`` over the unsaturated samples with ``n·l_i ≥ min_shading``.

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    n = len(stack)
    h, w = stack.shape
    dirs = as_directions(directions, n, np.float32)
    out = np.empty((h, w), dtype=np.float32)

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        shading = dirs @ normals[r0:r1].reshape(-1, 3).T  # (N, P)
        out[r0:r1] = albedo_fit(values.reshape(n, -1), shading, saturated.reshape(n, -1),
                                min_shading).reshape(r1 - r0, w)

    run_bands(h, band_rows(n, w, 4 * 4), work, threads=threads)
    return out


def albedo_fit(values: np.ndarray, shading: np.ndarray, saturated: np.ndarray,
               min_shading: float) -> np.ndarray:
    """Per-pixel least-squares ρ of ``values = ρ · shading`` over the usable samples.

    ``values``, ``shading`` (n·l, overwritten) and ``saturated`` are (N, P); samples that
    clipped or have ``shading < min_shading`` are left out. Pixels with none left get 0.
    """
    shading[(shading < min_shading) | saturated] = 0.0
    num = (shading * values).sum(axis=0)
    den = (shading * shading).sum(axis=0)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


def angular_error(normals: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Angle in degrees between two normal maps.

    Parameters
    ----------
    normals, reference : ndarray, shape (H, W, 3)
    mask : ndarray, shape (H, W), bool, optional
        If given, only the errors inside it are returned (as a flat array).

    Returns
    -------
    ndarray
        ``(H, W)`` float32 degrees, or the masked values.
    """
    if mask is not None:
        # Reference maps often hold zero vectors outside the object: compare inside only.
        normals, reference = normals[mask], reference[mask]
    a = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    b = reference / np.linalg.norm(reference, axis=-1, keepdims=True)
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=-1), -1.0, 1.0))).astype(np.float32)
