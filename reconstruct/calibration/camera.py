"""The pinhole camera model: intrinsics in pixels, from numbers, the lens and sensor, or EXIF.

Frame of ``docs/CONVENTIONS.md``: x right, y up, z towards the camera. The camera's centre is
the origin and it looks along −z; pixel centres lie at integer (col, row), and pixel (col, row)
sees the ray ((col − cx)/fx, −(row − cy)/fy, −1) (the minus: rows go down, y goes up). Used by
the sphere calibration (:mod:`reconstruct.calibration`) and the perspective integration
(:mod:`reconstruct.surface.perspective`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FOCAL_RANGE", "MAX_PRINCIPAL", "Intrinsics", "intrinsics_from_exif", "parse_intrinsics"]

#: Focal lengths accepted, in pixels: 1 sees 179.5° across a 400-pixel photograph, wider than
#: any pinhole lens; 1e8 is a 10 m lens on 0.1 µm pixels. Beyond them the sphere's position
#: and the rays lose their precision (1e12 and 1e-308 failed inside SciPy's solver).
FOCAL_RANGE = (1.0, 1e8)
#: The farthest the principal point may lie from the first pixel, in pixels: a shifted lens
#: moves it by a fraction of the photograph, and none is 1e5 pixels across.
MAX_PRINCIPAL = 1e6


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera intrinsics, in pixels.

    Attributes
    ----------
    fx, fy : float
        Focal length in pixels along the columns and the rows (focal length in mm divided
        by the pixel pitch in mm).
    cx, cy : float
        Principal point in column and row pixel coordinates, pixel centres at integers (the
        centre of a W × H image is ((W − 1)/2, (H − 1)/2)).

    Raises
    ------
    ValueError
        For a value that is not finite, a focal length outside :data:`FOCAL_RANGE`, or a
        principal point farther than :data:`MAX_PRINCIPAL`.
    """

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.floating, np.integer)) or not math.isfinite(
                value
            ):
                raise ValueError(f"intrinsic {name} must be a finite number, not {value!r}")
        low, high = FOCAL_RANGE
        if not (low <= self.fx <= high and low <= self.fy <= high):
            raise ValueError(
                f"focal lengths must be positive, {low:g} to {high:g} pixels, not fx={self.fx:g}, fy={self.fy:g}"
            )
        if max(abs(self.cx), abs(self.cy)) > MAX_PRINCIPAL:
            raise ValueError(
                f"the principal point must lie within {MAX_PRINCIPAL:g} pixels of the image, "
                f"not cx={self.cx:g}, cy={self.cy:g}"
            )

    def rays(self, x_img, y_img) -> np.ndarray:
        """Unit rays from the camera centre through image points.

        Parameters
        ----------
        x_img, y_img : float or ndarray
            Column and row in pixels (pixel centres at integers); broadcast together.

        Returns
        -------
        numpy.ndarray
            ``(..., 3)`` float64 unit vectors along ((col − cx)/fx, −(row − cy)/fy, −1) in
            the project frame (the camera looks along −z).
        """
        x = np.asarray(x_img, dtype=np.float64)
        y = np.asarray(y_img, dtype=np.float64)
        rays = np.stack(np.broadcast_arrays((x - self.cx) / self.fx, -(y - self.cy) / self.fy,
                                            -np.ones_like(x)), axis=-1)
        return rays / np.linalg.norm(rays, axis=-1, keepdims=True)

    @classmethod
    def from_focal(
        cls,
        focal_mm: float,
        sensor_width_mm: float,
        image_width_px: int,
        image_height_px: int,
    ) -> Intrinsics:
        """Intrinsics from the lens focal length and the sensor width.

        Assumes square pixels (pitch = sensor width / image width) and the principal point
        at the image centre.

        Parameters
        ----------
        focal_mm : float
            Focal length of the lens in mm (the real one, not the 35 mm equivalent, unless
            `sensor_width_mm` is 36).
        sensor_width_mm : float
            Width of the sensor area that the image covers, in mm.
        image_width_px, image_height_px : int
            Image size in pixels.

        Returns
        -------
        Intrinsics
            fx = fy = focal_mm · image_width_px / sensor_width_mm,
            cx = (image_width_px − 1)/2, cy = (image_height_px − 1)/2.

        Raises
        ------
        ValueError
            If a length or a size is not positive, or the focal length in pixels is outside
            :data:`FOCAL_RANGE`.
        """
        values = (focal_mm, sensor_width_mm, image_width_px, image_height_px)
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(
                "focal length, sensor width and image size must be positive, not "
                f"{focal_mm}, {sensor_width_mm}, {image_width_px}×{image_height_px}"
            )
        f = float(focal_mm) * float(image_width_px) / float(sensor_width_mm)
        return cls(f, f, (image_width_px - 1) / 2.0, (image_height_px - 1) / 2.0)


#: EXIF tags (in the Exif sub-IFD, 0x8769) used by :func:`intrinsics_from_exif`.
_EXIF_IFD = 0x8769
_FOCAL_LENGTH = 0x920A
_PIXEL_X_DIMENSION = 0xA002
_FOCAL_PLANE_X_RES = 0xA20E
_FOCAL_PLANE_Y_RES = 0xA20F
_FOCAL_PLANE_UNIT = 0xA210
_FOCAL_35MM = 0xA405
#: FocalPlaneResolutionUnit → millimetres per unit (2 inch, 3 cm, 4 mm, 5 µm).
_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}
#: Diagonal of a 36 × 24 mm frame, the reference of 35 mm-equivalent focal lengths.
_FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def _positive_tag(ifd, tag: int) -> float | None:
    """A tag's value as a positive finite float, or None (missing, zero, garbage)."""
    value = ifd.get(tag)
    try:
        value = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def intrinsics_from_exif(path) -> Intrinsics | None:
    """Pinhole intrinsics from a photograph's EXIF focal length and sensor size.

    The principal point is taken at the image centre. The focal length in pixels comes
    from, in this order of preference:

    1. FocalLength (mm) and FocalPlaneXResolution / FocalPlaneResolutionUnit (pixels per
       unit length on the sensor): fx = FocalLength · pixels per mm (fy likewise from
       FocalPlaneYResolution when present, else fx). When the photograph is narrower or
       wider than the EXIF PixelXDimension (resized after the camera wrote the tags), the
       pixel density is scaled by the ratio.
    2. FocalLengthIn35mmFilm: the focal length that gives the same field of view on a
       36 × 24 mm frame, compared along the diagonal (the usual crop-factor convention):
       fx = fy = f35 · image diagonal in pixels / 43.27 mm. For a 3:2 image this is
       f35 / 36 mm · image width.

    Parameters
    ----------
    path : str or PathLike
        A photograph (JPEG or TIFF with EXIF).

    Returns
    -------
    Intrinsics or None
        None when the EXIF lacks the tags (or they are zero or unreadable).

    Raises
    ------
    InputError
        If the file cannot be opened as an image, or its tags give a camera out of range.
    """
    from ptmcore.decoders import pillow_image
    from ptmcore.errors import InputError

    try:
        with pillow_image(path) as img:
            width, height = img.size
            exif = img.getexif()
    except (OSError, SyntaxError, ValueError) as exc:  # a damaged EXIF block
        raise InputError(f"cannot read the photograph's EXIF: {exc}", path) from None
    sub = exif.get_ifd(_EXIF_IFD)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    focal = _positive_tag(sub, _FOCAL_LENGTH)
    x_res = _positive_tag(sub, _FOCAL_PLANE_X_RES)
    try:
        unit = _UNIT_MM.get(int(sub.get(_FOCAL_PLANE_UNIT, 2)))  # EXIF's default: the inch
    except (TypeError, ValueError):
        unit = None
    try:
        if focal is not None and x_res is not None and unit is not None:
            y_res = _positive_tag(sub, _FOCAL_PLANE_Y_RES) or x_res
            native_width = _positive_tag(sub, _PIXEL_X_DIMENSION)
            resized = width / native_width if native_width else 1.0
            return Intrinsics(focal * x_res / unit * resized, focal * y_res / unit * resized, cx, cy)
        f35 = _positive_tag(sub, _FOCAL_35MM)
        if f35 is not None:
            f = f35 * math.hypot(width, height) / _FULL_FRAME_DIAGONAL_MM
            return Intrinsics(f, f, cx, cy)
    except ValueError as exc:
        raise InputError(f"the EXIF's focal length gives no usable camera: {exc}", path) from None
    return None


def parse_intrinsics(text: str) -> Intrinsics:
    """Parse ``"fx,fy,cx,cy"`` (pixels) into :class:`Intrinsics`.

    Parameters
    ----------
    text : str
        Four comma-separated numbers; spaces around them are allowed.

    Returns
    -------
    Intrinsics

    Raises
    ------
    ValueError
        If there are not exactly four numbers, one does not parse or is not finite, or the
        camera is out of range (:class:`Intrinsics`).
    """
    parts = [s.strip() for s in str(text).split(",")]
    if len(parts) != 4:
        raise ValueError(
            f"intrinsics must be four comma-separated numbers 'fx,fy,cx,cy' (pixels), "
            f"got {len(parts)} field(s) in {text!r}"
        )
    values = []
    for name, part in zip(("fx", "fy", "cx", "cy"), parts):
        try:
            value = float(part)
        except ValueError:
            raise ValueError(
                f"intrinsic {name} in {text!r} is not a number: {part!r}"
            ) from None
        if not math.isfinite(value):
            raise ValueError(f"intrinsic {name} in {text!r} must be finite, not {part!r}")
        values.append(value)
    return Intrinsics(*values)
