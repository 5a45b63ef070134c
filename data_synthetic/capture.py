"""Write a complete synthetic RTI capture folder: images, ``.lp`` file, ground truth, scan."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptmcore.atomic import atomic_write
from ptmcore.errors import InputError
from ptmcore.lp import write_lp

from .encoding import write_jpeg8, write_mask_png, write_npy, write_tiff16
from .lights import dome_lights
from .render import render
from .scan import sample_scan, write_ply
from .surfaces import SCENES

#: Image writer and file extension for each encoding.
ENCODINGS = {"tiff16": (write_tiff16, ".tif"), "jpeg8": (write_jpeg8, ".jpg")}

FRAME = ("x right, y up, z towards the camera; pixel (row, col) lies at "
         "(col*pixel_size, -row*pixel_size, height) in mm")

#: The most lights a capture is rendered under: more than any dome has (a few hundred at most).
MAX_LIGHTS = 1000
#: The longest side of a photograph, in pixels (JPEG's own limit is 65535).
MAX_SIDE = 16384
#: What rendering holds per pixel besides the images: the scene's height, normals, albedo
#: and mask, the shadow march's scratch arrays (measured: 175 bytes at 1 and 4 megapixels).
SCENE_BYTES_PER_PIXEL = 176
#: The images are rendered into one float32 RGB array before any is written.
IMAGE_BYTES_PER_PIXEL = 12
#: The most memory a capture may take to render: a synthetic capture larger than this is a
#: slip (``--lights 100000000``), not a test anyone needs, and would fail deep inside NumPy.
MAX_RENDER_BYTES = 4 * 2**30
#: The largest rendering parameter (specular peak and exponent, ambient, noise, scan noise):
#: 1e308 overflowed the float32 radiance to infinity.
MAX_PARAMETER = 1e6


def render_bytes(shape: tuple[int, int], n_lights: int) -> int:
    """Memory, in bytes, that rendering ``n_lights`` images of ``shape`` (H, W) takes."""
    h, w = shape
    return h * w * (SCENE_BYTES_PER_PIXEL + IMAGE_BYTES_PER_PIXEL * n_lights)


def check_capture_size(shape: tuple[int, int], n_lights: int) -> None:
    """Refuse a capture too large to render: more than :data:`MAX_LIGHTS` lights, a side
    beyond :data:`MAX_SIDE`, or more than :data:`MAX_RENDER_BYTES` of memory.

    Parameters
    ----------
    shape : tuple of int
        (H, W) of the photographs, each at least 8.
    n_lights : int
        Number of photographs.

    Raises
    ------
    InputError
        Naming the size asked for and the bound it passes.
    """
    h, w = shape
    if n_lights > MAX_LIGHTS:
        raise InputError(f"{n_lights} lights asked for; a synthetic capture has at most {MAX_LIGHTS}")
    if max(h, w) > MAX_SIDE:
        raise InputError(f"images of {w}×{h} pixels asked for; each side is at most {MAX_SIDE}")
    need = render_bytes((h, w), n_lights)
    if need > MAX_RENDER_BYTES:
        raise InputError(f"{n_lights} images of {w}×{h} pixels would take {need / 2**30:.1f} GiB to render "
                         f"(at most {MAX_RENDER_BYTES / 2**30:g} GiB); choose a smaller size or fewer lights")


@dataclass(frozen=True)
class CaptureInfo:
    """Where a written capture lives and what it is.

    Attributes
    ----------
    folder : Path
        The capture folder.
    lp_path : Path
        The light-position file, ``folder/lights.lp`` (``folder/ground_truth/lights.lp`` for a
        capture with spheres, which has to be calibrated from them).
    ground_truth_dir : Path
        ``folder/ground_truth``.
    scan_path : Path or None
        ``folder/scan.ply``, or None if no scan was written.
    image_paths : tuple of Path
        The images, in light order.
    pixel_size : float
        Millimetres per pixel.
    shape : tuple of int
        (H, W) of the images.
    spheres : tuple of (float, float, float)
        The glossy spheres in the frame, (cx, cy, r) in pixels (cx = column, cy = row).
    """

    folder: Path
    lp_path: Path
    ground_truth_dir: Path
    scan_path: Path | None
    image_paths: tuple[Path, ...]
    pixel_size: float
    shape: tuple[int, int]
    spheres: tuple[tuple[float, float, float], ...] = ()


def _finite(value: float) -> bool:
    """Whether ``value`` is a finite number; an integer too large for a float is not."""
    try:
        return math.isfinite(value)
    except (OverflowError, TypeError):
        return False


def _validate(scene: str, shape: tuple[int, int], n_lights: int, encoding: str, seed: int,
              lights: np.ndarray | None, numbers: dict[str, float | None],
              ) -> tuple[tuple[int, int], np.ndarray | None]:
    """Turn bad arguments into InputError; return the checked shape and lights."""
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose from {', '.join(SCENES)}")
    if encoding not in ENCODINGS:
        raise InputError(f"unknown encoding {encoding!r}; choose from {', '.join(ENCODINGS)}")
    try:
        h, w = (int(v) for v in shape)
    except (TypeError, ValueError):
        raise InputError(f"shape must be (height, width), got {shape!r}") from None
    if h < 8 or w < 8:
        raise InputError(f"images must be at least 8×8 pixels, got {h}×{w}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    for name, value in numbers.items():
        if value is not None and not (_finite(value) and value >= 0):
            raise InputError(f"{name} must be a non-negative number, got {value!r}")
        if name not in ("pixel_size", "scan_points") and value is not None and value > MAX_PARAMETER:
            raise InputError(f"{name} must be at most {MAX_PARAMETER:g}, got {value!r}")
    if numbers["pixel_size"] == 0 or numbers["shininess"] == 0:
        raise InputError("pixel_size and shininess must be positive")
    # Imported here: rendering needs nothing else of the reconstruction.
    from reconstruct.pipeline.options import BOUNDS

    low, high = BOUNDS["pixel_size"]
    if numbers["pixel_size"] is not None and not low <= numbers["pixel_size"] <= high:
        # The range a reconstruction takes; 1e300 made the heights NaN.
        raise InputError(f"pixel_size must be {low:g} to {high:g} mm, got {numbers['pixel_size']!r}")
    if numbers["scan_points"] is not None and numbers["scan_points"] > h * w:
        # Points are drawn on the height field: more than one per pixel adds no detail.
        raise InputError(f"{numbers['scan_points']} scan points asked for; at most one per pixel ({h * w})")
    if lights is not None:
        lights = np.asarray(lights, dtype=np.float64)
        if lights.ndim != 2 or lights.shape[1] != 3 or len(lights) < 1:
            raise InputError(f"lights must be an (N, 3) array, got shape {lights.shape}")
        if np.any(lights[:, 2] <= 0):
            raise InputError("every light must be above the object plane (z > 0)")
        check_capture_size((h, w), len(lights))
        return (h, w), lights
    if n_lights < 3:
        raise InputError(f"need at least 3 lights, got {n_lights}")
    check_capture_size((h, w), n_lights)
    low, high = numbers["min_elevation_deg"], numbers["max_elevation_deg"]
    if not 0 < low <= high <= 90:
        raise InputError(f"dome elevations need 0 < min ≤ max ≤ 90 degrees, got {low}, {high}")
    return (h, w), None


def _prepare_folder(out_dir: Path) -> Path:
    """Create the capture and ground-truth folders, reporting problems as InputError."""
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError("exists and is not a folder", out_dir)
    gt_dir = out_dir / "ground_truth"
    try:
        gt_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the capture folder: {exc.strerror}", out_dir) from None
    if not os.access(out_dir, os.W_OK) or not os.access(gt_dir, os.W_OK):
        raise InputError("folder is not writable", out_dir)
    return gt_dir


def write_capture(
    out_dir: str | os.PathLike,
    scene: str = "tablet",
    shape: tuple[int, int] = (384, 512),
    n_lights: int = 48,
    encoding: str = "tiff16",
    seed: int = 0,
    *,
    pixel_size: float | None = None,
    specular: float = 0.0,
    shininess: float = 30.0,
    cast_shadows: bool = True,
    ambient: float = 0.0,
    noise: float = 0.005,
    min_elevation_deg: float = 15.0,
    max_elevation_deg: float = 75.0,
    lights: np.ndarray | None = None,
    scan_points: int | None = None,
    scan_noise_mm: float = 0.02,
    spheres: int = 0,
) -> CaptureInfo:
    """Render a synthetic scene and write a complete capture folder.

    Layout of ``out_dir``::

        img_000.tif …         one image per light (img_000.jpg … for jpeg8)
        lights.lp             N, then "filename x y z" per image (x right, y up, z to camera)
        scan.ply              synthetic laser scan, mm, moved by the scan transform
        ground_truth/
            normals.npy       (H, W, 3) float32 unit normals
            height.npy        (H, W) float32, mm
            albedo.npy        (H, W, 3) float32 linear RGB
            mask.png          8-bit, 255 on the object
            scan_transform.txt  4×4 matrix mapping the ground-truth frame onto scan.ply
            scene.json        everything needed to reproduce the capture

    With ``spheres``, black glossy spheres lie in the frame's corners (highlight RTI) and
    ``lights.lp`` goes into ``ground_truth/``: the capture folder has no light file, so
    ``reconstruct calibrate`` and ``reconstruct run`` read the lights from the spheres.

    The surface is ``SCENES[scene](shape, pixel_size=pixel_size, seed=seed)`` and the images
    are ``render(surface, lights, ..., seed=seed)`` clipped to [0, 1], like a camera.

    Parameters
    ----------
    out_dir : str or os.PathLike
        The capture folder; created if missing. Existing files of the same names are replaced.
    scene : str
        A key of ``SCENES``: "tablet" or "sphere".
    shape : tuple of int
        (H, W) of the images.
    n_lights : int
        Number of dome lights (ignored when ``lights`` is given).
    encoding : str
        "tiff16": 16-bit linear RGB TIFF; "jpeg8": 8-bit sRGB JPEG, quality 95.
    seed : int
        Drives the scene, the sensor noise and the scan; same arguments, same files.
    pixel_size : float, optional
        Millimetres per pixel; default 80 mm across the longer side.
    specular, shininess, cast_shadows, ambient, noise
        Passed to :func:`data_synthetic.render.render`.
    min_elevation_deg, max_elevation_deg : float
        Elevation range of the dome's rings.
    lights : np.ndarray, optional
        (N, 3) directions to use instead of a dome, e.g. ``ring_lights(...)``.
    scan_points : int, optional
        Number of scan points; default one per four pixels; 0 writes no scan.
    scan_noise_mm : float
        Depth noise of the scan.
    spheres : int
        Number of glossy spheres, 0 to 4, each in a corner of the frame beside the object
        (:func:`data_synthetic.spheres.corner_spheres`), as large as the corner allows.

    Returns
    -------
    CaptureInfo

    Raises
    ------
    InputError
        For an unknown scene or encoding, a bad shape, seed, option value or light set, or an
        output folder that cannot be created or written, or spheres that do not fit.
    """
    numbers = {"pixel_size": pixel_size, "specular": specular, "shininess": shininess,
               "ambient": ambient, "noise": noise, "min_elevation_deg": min_elevation_deg,
               "max_elevation_deg": max_elevation_deg, "scan_points": scan_points,
               "scan_noise_mm": scan_noise_mm}
    shape, custom_lights = _validate(scene, shape, n_lights, encoding, seed, lights, numbers)
    if not isinstance(spheres, (int, np.integer)) or not 0 <= spheres <= 4:
        raise InputError(f"spheres must be 0 to 4 (one per corner of the frame), got {spheres!r}")
    folder = Path(out_dir)
    gt_dir = _prepare_folder(folder)
    surface = SCENES[scene](shape, pixel_size=pixel_size, seed=seed)
    light_dirs = (custom_lights if custom_lights is not None
                  else dome_lights(n_lights, min_elevation_deg, max_elevation_deg))
    light_dirs = light_dirs / np.linalg.norm(light_dirs, axis=1, keepdims=True)
    # Plain Python types, so scene.json can record exactly what was rendered.
    options = {"specular": float(specular), "shininess": float(shininess),
               "cast_shadows": bool(cast_shadows), "ambient": float(ambient),
               "noise": float(noise)}
    placed: tuple[tuple[float, float, float], ...] = ()
    if spheres:
        # Imported here: it needs the calibration's geometry, which a plain capture does not.
        from .spheres import corner_spheres, paint_spheres

        placed = corner_spheres(surface.mask, spheres)
    radiance = render(surface, light_dirs, **options, seed=seed)
    if placed:
        paint_spheres(radiance, light_dirs, placed, seed=seed)

    writer, ext = ENCODINGS[encoding]
    digits = max(3, len(str(len(light_dirs) - 1)))
    names = [f"img_{i:0{digits}d}{ext}" for i in range(len(light_dirs))]
    for name, image in zip(names, radiance):
        writer(folder / name, image)
    del radiance
    lp_path = (gt_dir if placed else folder) / "lights.lp"
    # Relative to the .lp's own folder, as the format wants.
    write_lp(lp_path, [os.path.relpath(folder / n, lp_path.parent) for n in names], light_dirs)

    write_npy(gt_dir / "normals.npy", surface.normals)
    write_npy(gt_dir / "height.npy", surface.height)
    write_npy(gt_dir / "albedo.npy", surface.albedo)
    write_mask_png(gt_dir / "mask.png", surface.mask)

    scan_path = None
    transform = np.eye(4)
    n_scan = 0
    if scan_points is None or scan_points > 0:
        points, transform = sample_scan(surface, scan_points, noise_mm=scan_noise_mm, seed=seed)
        n_scan = len(points)
        scan_path = folder / "scan.ply"
        write_ply(scan_path, points, "ptm-reconstruct synthetic laser scan, units mm")
    matrix_text = "\n".join(" ".join(repr(float(v)) for v in row) for row in transform)
    with atomic_write(gt_dir / "scan_transform.txt", "w") as f:
        f.write(matrix_text + "\n")

    description = {
        "scene": scene,
        "shape": list(shape),
        "pixel_size_mm": surface.pixel_size,
        "height_units": "mm",
        "frame": FRAME,
        "seed": int(seed),
        "lights": {
            "count": len(light_dirs),
            "layout": "custom" if custom_lights is not None else "dome",
            "min_elevation_deg": None if custom_lights is not None else float(min_elevation_deg),
            "max_elevation_deg": None if custom_lights is not None else float(max_elevation_deg),
            "file": lp_path.relative_to(folder).as_posix(),
        },
        "spheres": [{"cx": cx, "cy": cy, "r": r, "view": "orthographic"} for cx, cy, r in placed],
        "encoding": encoding,
        "render": {**options, "light_intensity": 1.0, "view": [0.0, 0.0, 1.0],
                   "clipped_to": [0.0, 1.0]},
        "scan": {"file": scan_path.name if scan_path else None, "points": n_scan,
                 "noise_mm": float(scan_noise_mm),
                 "transform_maps": "ground-truth frame -> scan.ply coordinates"},
        "scan_transform": transform.tolist(),
    }
    with atomic_write(gt_dir / "scene.json", "w") as f:
        f.write(json.dumps(description, indent=2) + "\n")
    return CaptureInfo(
        folder=folder,
        lp_path=lp_path,
        ground_truth_dir=gt_dir,
        scan_path=scan_path,
        image_paths=tuple(folder / n for n in names),
        pixel_size=surface.pixel_size,
        shape=shape,
        spheres=placed,
    )
