"""Light directions from the highlights on black glossy spheres ("highlight RTI").

A hand-held flash lights the object from a different direction in each photograph; one or more
black glossy spheres beside the object show a mirror highlight (small on a polished sphere,
broad on a glossy one) centred where the sphere normal bisects the light and the viewing
direction. With an orthographic camera (a distant lens, view v = (0, 0, 1)) the light follows
from the highlight position alone; with a pinhole camera
(:class:`reconstruct.calibration.camera.Intrinsics`, e.g. from EXIF) the view is each
highlight's own ray and the sphere's position comes from its outline
(:func:`reconstruct.calibration.reflection.sphere_centre_3d`).

Coordinates: image positions are (x_img, y_img) = (column, row) with pixel centres at integers;
spheres are (cx, cy, r) in those units. Directions use the project frame: x right, y up,
z towards the camera (so y = (cy − hy)/r, rows go down).

The spheres are found by :mod:`reconstruct.calibration.spheres`, their highlights by
:mod:`reconstruct.calibration.highlights`, and the geometry of the reflection is in
:mod:`reconstruct.calibration.reflection`. Near lights (a
flash close to the object) are triangulated from two or more spheres by
:mod:`reconstruct.calibration.triangulate`; here every sphere gives a distant direction, and their
disagreement lowers the confidence.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.colourtags import srgb_save_options
from ptmcore.errors import InputError
from ptmcore.images import ImageStack, linear_to_srgb, load_stack
from ptmcore.lp import write_lp
from reconstruct.calibration.camera import Intrinsics
from reconstruct.calibration.highlights import PINHOLE_REACH, sphere_highlights
from reconstruct.calibration.reflection import Sphere, light_from_highlight
from reconstruct.calibration.spheres import check_sphere, detect_spheres, stack_statistics

__all__ = [
    "Calibration",
    "calibrate",
    "calibrate_stack",
    "calibration_camera",
    "write_calibration_lp",
    "write_diagnostic",
]


@dataclass
class Calibration:
    """Light directions read from sphere highlights.

    Attributes
    ----------
    directions : np.ndarray
        (N, 3) unit vectors towards the lights; rows of NaN for unusable photographs.
    confidence : np.ndarray
        (N,) in [0, 1]; 0 for unusable photographs. Lowered when spheres disagree.
    sphere_directions : np.ndarray
        (S, N, 3) the direction each sphere gives (NaN where it has no usable highlight).
    sphere_confidence : np.ndarray
        (S, N) confidence of each sphere's highlight (0 where none).
    highlights : np.ndarray
        (S, N, 2) highlight positions (x_img, y_img) in pixels, NaN where none.
    disagreement_deg : np.ndarray
        (N,) largest angle between any sphere's direction and the combined one (0 for a
        single usable sphere, NaN for unusable photographs).
    spheres : list of (cx, cy, r)
        The spheres used.
    names : list of str
        File names of the photographs, in order.
    flagged : list of str
        Names of the photographs whose direction could not be read (NaN rows).
    intrinsics : Intrinsics or None
        The pinhole camera used for the reflection; None for the orthographic view.
    shape : (H, W) or None
        Size of the photographs in pixels.
    lobe_cosine : float
        The exponent q of the factor (n·l)^q on the spheres' specular lobe the highlights
        were placed with: 0 for a lobe that is the radiance, 1 for a BRDF lit by a light;
        estimated from the highlights
        (:func:`reconstruct.calibration.highlights.sphere_highlights`).
    """

    directions: np.ndarray
    confidence: np.ndarray
    sphere_directions: np.ndarray
    sphere_confidence: np.ndarray
    highlights: np.ndarray
    disagreement_deg: np.ndarray
    spheres: list[Sphere]
    names: list[str] = field(default_factory=list)
    flagged: list[str] = field(default_factory=list)
    intrinsics: Intrinsics | None = None
    shape: tuple[int, int] | None = None
    lobe_cosine: float = 0.0

    @property
    def view_model(self) -> str:
        """``"orthographic"`` or ``"perspective (fx=…, fy=…, cx=…, cy=… px)"``."""
        k = self.intrinsics
        if k is None:
            return "orthographic"
        return f"perspective (fx={k.fx:.1f}, fy={k.fy:.1f}, cx={k.cx:.1f}, cy={k.cy:.1f} px)"

    @property
    def usable(self) -> np.ndarray:
        """(N,) bool: photographs with a direction."""
        return np.isfinite(self.directions).all(axis=1)


def _sphere_crops(stack: ImageStack, sphere: Sphere, reach: float = 1.0
                  ) -> tuple[np.ndarray, int, int]:
    """Every photograph's linear luminance in the sphere's bounding box, and the box's corner.

    Only these few thousand pixels per photograph are needed to find highlights, so the
    whole stack is never converted to float. ``reach`` scales the radius (a pinhole's
    outline is an ellipse longer than its mean radius).
    """
    h, w = stack.shape
    cx, cy, r = sphere
    r = reach * r
    x0, x1 = max(0, int(cx - r) - 2), min(w, int(np.ceil(cx + r)) + 3)
    y0, y1 = max(0, int(cy - r) - 2), min(h, int(np.ceil(cy + r)) + 3)
    values, _ = stack.band(y0, y1, x0, x1)
    return values, x0, y0


def _crops_per_sphere(stack: ImageStack, spheres: list[Sphere], intrinsics: Intrinsics | None
                      ) -> tuple[list[np.ndarray], list[tuple[int, int]], list[Sphere],
                                 list[Intrinsics | None]]:
    """Every sphere's crops (:func:`_sphere_crops`; 10 % wider through a pinhole), as the
    highlights are looked for in them.

    Returns
    -------
    crops : list of ndarray
        Per sphere, (N, h, w) linear luminance of every photograph.
    corners : list of (x0, y0)
        Per sphere, the crop's corner in the photographs.
    local : list of (cx, cy, r)
        Per sphere, its outline in the crop's pixels.
    cameras : list of Intrinsics or None
        Per sphere, the pinhole camera with its principal point in the crop's pixels; None
        when orthographic.
    """
    crops, corners, local, cameras = [], [], [], []
    for sph in spheres:
        crop, x0, y0 = _sphere_crops(stack, sph, 1.0 if intrinsics is None else PINHOLE_REACH)
        crops.append(crop)
        corners.append((x0, y0))
        local.append((sph[0] - x0, sph[1] - y0, sph[2]))
        cameras.append(None if intrinsics is None else replace(
            intrinsics, cx=intrinsics.cx - x0, cy=intrinsics.cy - y0))
    return crops, corners, local, cameras


def calibration_camera(
    photograph: str | os.PathLike,
    shape: tuple[int, int],
    *,
    intrinsics: str | Intrinsics | None = None,
    focal_mm: float | None = None,
    sensor_width_mm: float | None = None,
    exif: bool = False,
) -> Intrinsics | None:
    """The camera model for :func:`calibrate` from whichever description the user gave.

    At most one of: ``intrinsics`` (an :class:`Intrinsics` or ``"fx,fy,cx,cy"`` in
    pixels), ``focal_mm`` with ``sensor_width_mm`` (square pixels, principal point at the
    image centre; :meth:`Intrinsics.from_focal`), or ``exif`` (read from ``photograph``'s
    EXIF by :func:`reconstruct.calibration.camera.intrinsics_from_exif`). None of them: None, the
    orthographic view.

    Parameters
    ----------
    photograph : str or PathLike
        One photograph of the capture, whose EXIF is read with ``exif``.
    shape : (H, W)
        Size of the photographs in pixels (e.g. ``ImageStack.shape``).
    intrinsics, focal_mm, sensor_width_mm, exif
        See above.

    Returns
    -------
    Intrinsics or None

    Raises
    ------
    InputError
        Two descriptions at once, a focal length without a sensor width (or the reverse),
        non-positive or non-numeric values, or ``exif`` on a photograph without the tags.
    """
    from reconstruct.calibration.camera import intrinsics_from_exif, parse_intrinsics

    lens = focal_mm is not None or sensor_width_mm is not None
    if sum([intrinsics is not None, lens, bool(exif)]) > 1:
        raise InputError("give the camera one way only: intrinsics, focal length with sensor "
                         "width, or EXIF")
    if isinstance(intrinsics, str):
        try:
            return parse_intrinsics(intrinsics)
        except ValueError as exc:
            raise InputError(f"--intrinsics: {exc}") from None
    if intrinsics is not None:
        return intrinsics
    if exif:
        camera = intrinsics_from_exif(photograph)
        if camera is None:
            raise InputError("the EXIF has no focal length with sensor resolution or 35 mm "
                             "equivalent; give the focal length and sensor width instead",
                             photograph)
        return camera
    if not lens:
        return None
    if focal_mm is None or sensor_width_mm is None:
        raise InputError("a focal length needs the sensor width too (and the reverse)")
    height, width = shape
    try:
        return Intrinsics.from_focal(float(focal_mm), float(sensor_width_mm), width, height)
    except (TypeError, ValueError) as exc:
        raise InputError(f"bad focal length or sensor width: {exc}") from None


#: How a user gives the spheres by hand (``reconstruct calibrate``'s option, cli/parser.py).
_SPHERE_HINT = "give each sphere with `reconstruct calibrate --sphere X,Y,R` (centre column, row and radius in pixels)"


def _detect(stack: ImageStack, expected: int | None) -> list[Sphere]:
    """The spheres found in ``stack``, or an :class:`InputError` naming the photographs' folder
    and saying how to give the spheres by hand."""
    folders = {p.parent for p in stack.paths}
    folder = folders.pop() if len(folders) == 1 else None
    if len(stack) < 3:
        raise InputError(f"{len(stack)} photograph(s): at least 3 are needed to detect the spheres; "
                         f"for fewer, {_SPHERE_HINT}", folder)
    try:
        return detect_spheres(*stack_statistics(stack), expected=expected)
    except InputError as exc:
        raise InputError(f"{exc.problem}; if the spheres are in view, {_SPHERE_HINT}", folder) from None


def calibrate_stack(
    stack: ImageStack,
    *,
    spheres: list[Sphere] | None = None,
    expected: int | None = None,
    names: list[str] | None = None,
    min_confidence: float = 0.2,
    disagreement_tol_deg: float = 5.0,
    intrinsics: Intrinsics | None = None,
) -> Calibration:
    """Calibrate from a decoded capture (:func:`ptmcore.load_stack`); see :func:`calibrate`."""
    n = len(stack)
    names = [p.name for p in stack.paths] if names is None else list(names)
    if spheres is None:
        spheres = _detect(stack, expected)
    else:
        spheres = [check_sphere(s, stack.shape) for s in spheres]
        if not spheres:
            raise InputError("the list of spheres is empty")
    m = len(spheres)
    sdirs = np.full((m, n, 3), np.nan)
    sconf = np.zeros((m, n))
    hl = np.full((m, n, 2), np.nan)
    crops, corners, local, cameras = _crops_per_sphere(stack, spheres, intrinsics)
    # The spheres share the lights: the lobe's factor (n·l)^q is estimated from them all.
    found, lobe_cosine = sphere_highlights(crops, local, intrinsics=cameras)
    del crops
    for i, sph in enumerate(spheres):
        x0, y0 = corners[i]
        for k, one in enumerate(found[i]):
            if one is not None:
                hl[i, k] = one[0] + x0, one[1] + y0
                sconf[i, k] = one[2]
        seen = np.isfinite(hl[i, :, 0])
        if seen.any():
            sdirs[i, seen] = light_from_highlight(hl[i, seen, 0], hl[i, seen, 1], sph,
                                                  intrinsics)

    # Combine spheres per photograph: confidence-weighted mean of unit vectors.
    wts = np.where(np.isfinite(sdirs).all(-1), sconf, 0.0)  # (M, N)
    summed = np.einsum("mn,mnc->nc", wts, np.nan_to_num(sdirs))
    norm = np.linalg.norm(summed, axis=1)
    has = wts.sum(0) > 0
    combined = np.full((n, 3), np.nan)
    combined[has] = summed[has] / norm[has, None]
    cosang = np.einsum("mnc,nc->mn", np.nan_to_num(sdirs), np.nan_to_num(combined))
    ang = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    ang = np.where(wts > 0, ang, 0.0)
    # With one sphere there is nothing to disagree with (and arccos near 1 is only rounding).
    disagree = np.where(has, np.where((wts > 0).sum(0) >= 2, ang.max(0), 0.0), np.nan)
    mean_conf = np.where(has, wts.sum(0) / np.maximum((wts > 0).sum(0), 1), 0.0)
    # Spheres that disagree mean a bad highlight or a near light; either way trust it less.
    conf = mean_conf * np.clip(1.0 - np.nan_to_num(disagree) / disagreement_tol_deg, 0, 1)
    bad = ~has | (conf < min_confidence)
    combined[bad] = np.nan
    conf = np.where(bad, 0.0, conf)
    flagged = [names[k] for k in np.flatnonzero(bad)]
    return Calibration(directions=combined, confidence=conf, sphere_directions=sdirs,
                       sphere_confidence=sconf, highlights=hl, disagreement_deg=disagree,
                       spheres=[tuple(s) for s in spheres], names=names, flagged=flagged,
                       intrinsics=intrinsics, shape=stack.shape, lobe_cosine=lobe_cosine)


def calibrate(
    paths: list[str | os.PathLike],
    *,
    spheres: list[Sphere] | None = None,
    expected: int | None = None,
    min_confidence: float = 0.2,
    disagreement_tol_deg: float = 5.0,
    intrinsics: Intrinsics | None = None,
) -> Calibration:
    """Light directions of a highlight-RTI capture from its glossy spheres.

    Parameters
    ----------
    paths : list of str or PathLike
        The photographs (JPEG, PNG, TIFF; 8-bit is decoded from sRGB).
    spheres : list of (cx, cy, r), optional
        Known spheres in pixels (cx = column, cy = row); detected when omitted.
    expected : int, optional
        Number of spheres to detect.
    min_confidence : float
        Photographs whose combined confidence is lower are flagged (NaN direction).
    disagreement_tol_deg : float
        Angle between spheres' directions at which the confidence drops to 0.
    intrinsics : Intrinsics, optional
        Pinhole camera (see :func:`reconstruct.calibration.camera.intrinsics_from_exif` and
        :meth:`~reconstruct.calibration.camera.Intrinsics.from_focal`): the reflection then uses
        each highlight's own view ray (:func:`light_from_highlight`). None: orthographic
        view, right for long lenses.

    Returns
    -------
    Calibration

    Raises
    ------
    InputError
        Missing or unreadable photographs, mismatched sizes, no spheres found.
    """
    paths = [Path(p) for p in paths]
    stack = load_stack(paths, min_photographs=1)
    return calibrate_stack(stack, spheres=spheres, expected=expected,
                           min_confidence=min_confidence,
                           disagreement_tol_deg=disagreement_tol_deg, intrinsics=intrinsics)


def write_calibration_lp(path: str | os.PathLike, calibration: Calibration,
                         names: list[str] | None = None) -> int:
    """Write an ``.lp`` file of the usable photographs only.

    Parameters
    ----------
    path : str or PathLike
        Destination.
    calibration : Calibration
        Result of :func:`calibrate`.
    names : list of str, optional
        Names to write (relative to the ``.lp`` file's folder); default the calibration's.

    Returns
    -------
    int
        Number of photographs written.

    Raises
    ------
    InputError
        When no photograph has a usable highlight (nothing is written), naming the spheres.
    """
    names = calibration.names if names is None else list(names)
    if len(names) != len(calibration.directions):
        raise InputError(f"{len(names)} names for {len(calibration.directions)} photographs")
    ok = calibration.usable
    if not ok.any():
        spheres = ", ".join(f"({cx:g}, {cy:g}, {r:g})" for cx, cy, r in calibration.spheres)
        raise InputError(f"none of the {len(names)} photographs has a usable highlight on the sphere(s) {spheres}; "
                         "check where they are and their radius in pixels")
    write_lp(path, [nm for nm, u in zip(names, ok) if u], calibration.directions[ok])
    return int(ok.sum())


def write_diagnostic(path: str | os.PathLike, image: np.ndarray, calibration: Calibration,
                     k: int) -> None:
    """A PNG of photograph ``k`` with the sphere outlines and the highlights found.

    Outlines are green; a found highlight is a red cross; a sphere without a usable
    highlight in this photograph gets a yellow outline instead. The view model used
    (:attr:`Calibration.view_model`) is written in the top-left corner.
    """
    from PIL import Image, ImageDraw

    img = np.asarray(image)
    if img.dtype == np.uint8:
        rgb = img
    else:
        # 16-bit and float photographs are linear (ptmcore.images.read_image): encode them
        # as sRGB, as a viewer would show them, or they look far too dark.
        v = img.astype(np.float32)
        if img.dtype == np.uint16:
            v = v / 65535.0
        rgb = (linear_to_srgb(v) * 255 + 0.5).astype(np.uint8)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    pil = Image.fromarray(np.ascontiguousarray(rgb[..., :3]))
    draw = ImageDraw.Draw(pil)
    draw.text((3, 2), f"{calibration.view_model} view", fill=(255, 255, 255))
    for i, (cx, cy, r) in enumerate(calibration.spheres):
        hx, hy = calibration.highlights[i, k]
        colour = (0, 255, 0) if np.isfinite(hx) else (255, 255, 0)
        draw.ellipse([cx - r, cy - r, cx + r, cy + r], outline=colour, width=1)
        draw.line([cx - 3, cy, cx + 3, cy], fill=colour)
        draw.line([cx, cy - 3, cx, cy + 3], fill=colour)
        if np.isfinite(hx):
            a = max(4.0, 0.08 * r)
            draw.line([hx - a, hy, hx + a, hy], fill=(255, 0, 0), width=1)
            draw.line([hx, hy - a, hx, hy + a], fill=(255, 0, 0), width=1)
    with atomic_write(path, "wb") as f:
        pil.save(f, format="PNG", **srgb_save_options("PNG"))
