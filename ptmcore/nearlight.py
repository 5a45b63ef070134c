"""Near (point) lights: per-pixel light directions, fitting and normals, light-position files.

A hand-held flash one or two image widths from the object lights each pixel from a different
direction and with a different strength. Given the flash's 3D position P in each photograph
(for example triangulated from the highlights on two glossy spheres, see
``reconstruct.calibration.triangulate``), every pixel X sees the direction ``(P − X)/|P − X|`` and an
irradiance falling off as ``1/|P − X|²``; the fit and the photometric stereo here use those
per-pixel lights instead of one direction per photograph.

Coordinates are the project frame in **pixel units**: pixel (row, col) lies at
``x = col``, ``y = −row`` (row 0 at the top, y up) on the base plane ``z = 0``, z towards the
camera; light positions use the same frame and units (a camera pixel size only changes the
unit, not the geometry). Surface points are taken on the base plane unless their heights are
given: the relief is assumed small compared with the light's distance (a 5-pixel bump under a
flash 500 pixels away turns the direction by under 0.6°).

Light-position files are small CSV files, one photograph per line::

    name,x,y,z
    img_000.png,1510.25,-230.5,612.0

with x, y, z in pixels in the frame above. Everything works in bands of rows, so memory
stays bounded: the per-pixel light field of one band only.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable

import numpy as np

from .atomic import atomic_write
from .bands import band_rows, run_bands
from .errors import InputError, read_input_text
from .fit import PTM, ptm_terms
from .images import ImageStack
from .lp import MAX_TEXT_BYTES, decimal_number
from .normals import (
    PhotometricStereo,
    albedo_fit,
    empty_result,
    shadow_refined_solve,
    store_normals,
)
from .pixelfit import SINGULAR

#: Header of a light-position file.
POSITION_HEADER = ("name", "x", "y", "z")


# --------------------------------------------------------------------------- files


def write_light_positions(path: str | os.PathLike, names: list[str], positions: np.ndarray) -> None:
    """Write a light-position CSV file (``name,x,y,z`` in pixels, project frame), atomically.

    Parameters
    ----------
    path : str or PathLike
        Destination.
    names : list of str
        Photograph file names (relative to the file's folder).
    positions : ndarray, shape (N, 3)
        Light positions: x = column, y = −row, z above the base plane, in pixels.

    Raises
    ------
    ValueError
        If the shapes disagree or a position is not finite (leave such photographs out).
    """
    positions = np.asarray(positions, dtype=np.float64)
    if positions.shape != (len(names), 3):
        raise ValueError("positions must have shape (len(names), 3)")
    if not np.isfinite(positions).all():
        raise ValueError("light positions must be finite; leave unusable photographs out")
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(POSITION_HEADER)
    for name, (x, y, z) in zip(names, positions):
        writer.writerow([name, f"{x:.4f}", f"{y:.4f}", f"{z:.4f}"])
    with atomic_write(path, "w") as f:
        f.write(buf.getvalue())


def read_light_positions(path: str | os.PathLike) -> tuple[list[str], np.ndarray]:
    """Read a light-position CSV file written by :func:`write_light_positions`.

    Returns
    -------
    names : list of str
    positions : ndarray, shape (N, 3), float64
        Pixels, project frame (x = column, y = −row, z above the base plane).

    Raises
    ------
    InputError
        Missing or unreadable file, wrong header, a line without four fields, a value that
        is not a finite plain decimal number (:func:`ptmcore.lp.decimal_number`), a light
        below the base plane, or no lines at all.
    """
    text = read_input_text(path, "light-position file", max_bytes=MAX_TEXT_BYTES)
    reader = csv.reader(io.StringIO(text))
    try:
        # Numbered as the file's lines, blank ones included.
        rows = [(reader.line_num, r) for r in reader if any(field.strip() for field in r)]
    except csv.Error as exc:  # a field longer than csv's limit (128 KiB)
        raise InputError(f"line {reader.line_num}: {exc}", path) from None
    if not rows or tuple(f.strip().lower() for f in rows[0][1]) != POSITION_HEADER:
        raise InputError("light-position file must start with the header 'name,x,y,z'", path)
    names: list[str] = []
    values: list[tuple[float, float, float]] = []
    for line, row in rows[1:]:
        if len(row) != 4 or not row[0].strip():
            raise InputError(f"line {line}: expected 'name,x,y,z', got {','.join(row)!r}", path)
        try:
            xyz = tuple(decimal_number(v.strip()) for v in row[1:])
        except ValueError:
            raise InputError(f"line {line}: x, y, z must be numbers, got {row[1:]!r}", path) from None
        if not np.isfinite(xyz).all():
            raise InputError(f"line {line}: position is not finite", path)
        if xyz[2] <= 0:
            raise InputError(f"line {line}: the light is not above the base plane (z ≤ 0)", path)
        names.append(row[0].strip())
        values.append(xyz)
    if not names:
        raise InputError("light-position file lists no photographs", path)
    return names, np.array(values, dtype=np.float64)


# --------------------------------------------------------------------------- light field


def image_centre(shape: tuple[int, int]) -> np.ndarray:
    """The image centre on the base plane, (x, y, z) = ((W − 1)/2, −(H − 1)/2, 0) pixels."""
    h, w = shape
    return np.array([(w - 1) / 2.0, -(h - 1) / 2.0, 0.0])


def typical_distance(positions: np.ndarray, shape: tuple[int, int]) -> float:
    """Median distance (pixels) of the lights from the image centre on the base plane.

    A convenient ``reference_distance`` for :func:`light_field`: the falloff is then about 1
    at the centre, so albedos keep the scale of a distant-light fit.
    """
    d = np.asarray(positions, np.float64) - image_centre(shape)
    return float(np.median(np.linalg.norm(d, axis=1)))


def centre_directions(positions: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Unit directions from the image centre (on the base plane) towards each light.

    The one direction per photograph that tools assuming distant lights (an ``.lp`` file,
    RTIViewer, the light-layout check) take for a near light.

    Returns
    -------
    ndarray, shape (N, 3), float64
    """
    d = np.asarray(positions, np.float64) - image_centre(shape)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _check_positions(positions: np.ndarray, count: int | None = None) -> np.ndarray:
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or (count is not None and len(p) != count):
        want = f"({count}, 3)" if count is not None else "(N, 3)"
        raise ValueError(f"expected light positions of shape {want}, got {p.shape}")
    if not np.isfinite(p).all():
        raise InputError("light positions must be finite (leave out photographs without one)")
    if (p[:, 2] <= 0).any():
        raise InputError("every light must be above the base plane (z > 0)")
    return p


def _checked_lights(stack: ImageStack, positions: np.ndarray, reference_distance: float | None,
                    heights: np.ndarray | None) -> tuple[np.ndarray, float]:
    """Validated positions of a stack's lights and the reference distance (default typical)."""
    p = _check_positions(positions, len(stack))
    if heights is not None and np.shape(heights) != stack.shape:
        raise ValueError(f"heights must have shape {stack.shape}, got {np.shape(heights)}")
    d0 = typical_distance(p, stack.shape) if reference_distance is None else float(reference_distance)
    return p, d0


def light_field(
    positions: np.ndarray,
    rows: slice,
    width: int,
    *,
    reference_distance: float = 1.0,
    heights: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel unit directions towards point lights and their inverse-square falloff.

    For pixel (row, col) the surface point is X = (col, −row, z) with z = 0 (or ``heights``);
    for light P the direction is (P − X)/|P − X| and the falloff (d₀/|P − X|)², d₀ being
    ``reference_distance``.

    Parameters
    ----------
    positions : ndarray, shape (N, 3)
        Light positions in pixels, project frame (x = column, y = −row, z above the base).
    rows : slice
        The band of rows (``slice(r0, r1)``, step 1).
    width : int
        Image width W.
    reference_distance : float
        Distance d₀ at which the falloff is 1 (e.g. :func:`typical_distance`).
    heights : ndarray, shape (r1 − r0, W), optional
        Heights of the band above the base plane, in pixels.

    Returns
    -------
    directions : ndarray, shape (N, r1 − r0, W, 3), float32
    falloff : ndarray, shape (N, r1 − r0, W), float32
    """
    p = _check_positions(positions)
    r0, r1 = rows.start or 0, rows.stop
    if rows.step not in (None, 1) or r1 is None or r1 <= r0:
        raise ValueError(f"rows must be a slice(r0, r1) with r1 > r0, got {rows!r}")
    if heights is not None and np.shape(heights) != (r1 - r0, width):
        raise ValueError(f"heights must have shape {(r1 - r0, width)}, got {np.shape(heights)}")
    return _light_field(p, r0, r1, width, reference_distance, heights)


def _light_field(p: np.ndarray, r0: int, r1: int, width: int, reference_distance: float,
                 heights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`light_field` of checked positions (:func:`_checked_lights`), for one band."""
    h = r1 - r0
    # Differences in float64, relative to the band's first pixel, keep precision for large
    # coordinates; the results are stored as float32.
    dx = (p[:, 0, None] - np.arange(width, dtype=np.float64)).astype(np.float32)  # (N, W)
    dy = (p[:, 1, None] + np.arange(r0, r1, dtype=np.float64)).astype(np.float32)  # (N, h)
    directions = np.empty((len(p), h, width, 3), dtype=np.float32)
    directions[..., 0] = dx[:, None, :]
    directions[..., 1] = dy[:, :, None]
    if heights is None:
        directions[..., 2] = p[:, 2, None, None].astype(np.float32)
    else:
        z = np.asarray(heights, dtype=np.float32)
        directions[..., 2] = p[:, 2, None, None].astype(np.float32) - z
    dist2 = np.einsum("nhwc,nhwc->nhw", directions, directions)
    directions /= np.sqrt(dist2)[..., None]
    falloff = np.float32(reference_distance) ** 2 / dist2
    return directions, falloff.astype(np.float32, copy=False)


# --------------------------------------------------------------------------- normals


def _solve_normal_equations(l: np.ndarray, values: np.ndarray, weights: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel weighted least squares ``(Σ w l lᵀ) g = Σ w I l`` with per-pixel ``l``.

    ``l`` is (N, P, 3), ``values`` and ``weights`` (N, P). Returns g (3, P), where the system
    is well posed (P,), and the number of samples used (P,).
    """
    lw = l * weights[..., None]
    m = np.einsum("npi,npj->pij", lw, l, dtype=np.float64)  # (P, 3, 3)
    b = np.einsum("npi,np->pi", lw, values, dtype=np.float64)  # (P, 3)
    count = weights.sum(axis=0, dtype=np.float64)
    det = np.linalg.det(m)
    # As in ptmcore.normals: relative to the cube of the mean eigenvalue, a small determinant
    # means the used lights are (nearly) coplanar at this pixel.
    well_posed = det > SINGULAR * np.maximum((np.trace(m, axis1=1, axis2=2) / 3.0) ** 3, 1e-30)
    m[~well_posed] = np.eye(3)
    g = np.linalg.solve(m, b[..., None])[..., 0].T  # (3, P)
    g[:, ~well_posed] = 0.0
    return g, well_posed, count


def near_photometric_stereo(
    stack: ImageStack,
    positions: np.ndarray,
    *,
    reference_distance: float | None = None,
    heights: np.ndarray | None = None,
    dark_fraction: float = 0.05,
    min_shading: float = 0.05,
    cast_shadow_ratio: float = 0.4,
    iterations: int = 1,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> PhotometricStereo:
    """Lambertian photometric stereo under point lights, one light direction per pixel.

    Each sample is divided by its inverse-square falloff, then each pixel solves
    ``I_i / f_i = ρ n·l_i(x)`` by weighted least squares with the same exclusions as
    :func:`ptmcore.normals.photometric_stereo`: saturated samples always; in the first pass
    samples darker than ``dark_fraction`` × the pixel's brightest (compensated) sample; in
    each refinement pass those predicted in attached shadow (``n·l < min_shading``) or much
    darker than predicted (below ``cast_shadow_ratio`` × the prediction).

    Parameters
    ----------
    stack : ImageStack
    positions : ndarray, shape (N, 3)
        Light positions in pixels, project frame (see the module docstring).
    reference_distance : float, optional
        Distance at which the falloff is 1; default :func:`typical_distance`, so the albedo
        is that of a light at the lights' median distance from the image centre.
    heights : ndarray, shape (H, W), optional
        Surface heights in pixels (e.g. from a first reconstruction); default the base plane.
    dark_fraction, min_shading, cast_shadow_ratio, iterations, threads, progress
        As in :func:`ptmcore.normals.photometric_stereo`.

    Returns
    -------
    PhotometricStereo
    """
    n = len(stack)
    h, w = stack.shape
    p, d0 = _checked_lights(stack, positions, reference_distance, heights)
    result = empty_result((h, w))

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        dirs, falloff = _light_field(p, r0, r1, w, d0, None if heights is None else heights[r0:r1])
        l = dirs.reshape(n, -1, 3)
        v = (values / falloff).reshape(n, -1)
        del dirs, falloff, values
        usable = ~saturated.reshape(n, -1)
        wts = (v > np.maximum(dark_fraction * np.where(usable, v, 0).max(axis=0), 1e-4)) & usable
        g, ok, count = shadow_refined_solve(
            lambda weights: _solve_normal_equations(l, v, weights),
            lambda unit: np.einsum("npc,cp->np", l, unit),
            v, wts, usable, iterations=iterations, min_shading=min_shading, cast_shadow_ratio=cast_shadow_ratio)
        store_normals(result, slice(r0, r1), g, ok, count)

    # Per sample: values, light vector, falloff, weights and einsum temporaries, in float32.
    run_bands(h, band_rows(n, w, 4 * 14), work, threads=threads, progress=progress)
    return result


def near_lambertian_albedo(
    stack: ImageStack,
    positions: np.ndarray,
    normals: np.ndarray,
    *,
    reference_distance: float | None = None,
    heights: np.ndarray | None = None,
    min_shading: float = 0.05,
    threads: int | None = None,
) -> np.ndarray:
    """Luminance albedo ρ that best explains the stack given the normals, point lights.

    :func:`ptmcore.normals.lambertian_albedo` with each pixel's own light directions: least
    squares of ``I_i / f_i = ρ n·l_i(x)`` over the unsaturated samples with
    ``n·l_i ≥ min_shading``; the same albedo scale as :func:`near_photometric_stereo`.

    Parameters
    ----------
    stack : ImageStack
    positions : ndarray, shape (N, 3)
        Light positions in pixels, project frame.
    normals : ndarray, shape (H, W, 3)
        Unit normals (e.g. of :func:`fit_ptm_near`'s PTM).
    reference_distance, heights
        As in :func:`near_photometric_stereo`.
    min_shading : float
        Samples with a smaller n·l are left out (attached shadow, grazing light).
    threads : int, optional

    Returns
    -------
    ndarray, shape (H, W), float32
    """
    n = len(stack)
    h, w = stack.shape
    p, d0 = _checked_lights(stack, positions, reference_distance, heights)
    if np.shape(normals) != (h, w, 3):
        raise ValueError(f"normals must have shape {(h, w, 3)}, got {np.shape(normals)}")
    out = np.empty((h, w), dtype=np.float32)

    def work(r0: int, r1: int) -> None:
        values, saturated = stack.band(r0, r1)
        dirs, falloff = _light_field(p, r0, r1, w, d0, None if heights is None else heights[r0:r1])
        shading = np.einsum("nhwc,hwc->nhw", dirs, normals[r0:r1].astype(np.float32, copy=False))
        del dirs
        out[r0:r1] = albedo_fit((values / falloff).reshape(n, -1), shading.reshape(n, -1),
                                saturated.reshape(n, -1), min_shading).reshape(r1 - r0, w)

    # Per sample: values, light vector, falloff, shading and temporaries, in float32.
    run_bands(h, band_rows(n, w, 4 * 10), work, threads=threads)
    return out


# --------------------------------------------------------------------------- PTM


def fit_ptm_near(
    stack: ImageStack,
    positions: np.ndarray,
    *,
    reference_distance: float | None = None,
    heights: np.ndarray | None = None,
    threads: int | None = None,
    progress: Callable[[int], None] | None = None,
) -> PTM:
    """Fit an LRGB PTM with each pixel's own light directions (point lights).

    Per pixel, the luminances divided by their falloff are fitted by least squares with the
    rows ``[lu², lv², lu·lv, lu, lv, 1]`` of that pixel's directions: a 6×6 system per pixel,
    solved for a whole band at once. The result is the PTM of the object under distant lights
    of the reference strength, comparable with :func:`ptmcore.fit.fit_ptm`. Where a pixel's
    system is rank deficient (a ring of lights at one elevation) a ridge of 1e-9 of its trace
    picks the solution of nearly minimum norm, like the pseudoinverse of ``fit_ptm``.

    Parameters
    ----------
    stack : ImageStack
    positions : ndarray, shape (N, 3)
        Light positions in pixels, project frame.
    reference_distance : float, optional
        Distance at which the falloff is 1; default :func:`typical_distance`.
    heights : ndarray, shape (H, W), optional
        Surface heights in pixels; default the base plane.
    threads, progress
        As in :func:`ptmcore.fit.fit_ptm`.

    Returns
    -------
    PTM
    """
    n = len(stack)
    h, w = stack.shape
    p, d0 = _checked_lights(stack, positions, reference_distance, heights)
    coef = np.empty((h, w, 6), dtype=np.float32)
    ridge = 1e-9 * np.eye(6)

    def work(r0: int, r1: int) -> None:
        values, _ = stack.band(r0, r1)
        dirs, falloff = _light_field(p, r0, r1, w, d0, None if heights is None else heights[r0:r1])
        lu, lv = dirs[..., 0].reshape(n, -1), dirs[..., 1].reshape(n, -1)
        y = (values / falloff).reshape(n, -1)
        del dirs, falloff, values
        basis = ptm_terms(lu, lv)  # (N, P, 6)
        a = np.einsum("npi,npj->pij", basis, basis, dtype=np.float64)
        b = np.einsum("npi,np->pi", basis, y, dtype=np.float64)
        a += ridge * np.trace(a, axis1=1, axis2=2)[:, None, None]
        coef[r0:r1] = np.linalg.solve(a, b[..., None])[..., 0].reshape(r1 - r0, w, 6)

    # Per sample: the 6 basis values, direction, falloff and luminance in float32.
    run_bands(h, band_rows(n, w, 4 * 14), work, threads=threads, progress=progress)
    return PTM(coef, stack.chroma)


__all__ = [
    "POSITION_HEADER",
    "centre_directions",
    "fit_ptm_near",
    "image_centre",
    "light_field",
    "near_lambertian_albedo",
    "near_photometric_stereo",
    "read_light_positions",
    "typical_distance",
    "write_light_positions",
]
