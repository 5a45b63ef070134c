"""Where the lights were: the pinhole camera model (from numbers, the lens or EXIF), glossy
sphere detection, highlights, the reflection geometry, near-light triangulation from several
spheres, and checks of a light layout before any photograph is taken.

The functions :func:`calibrate` and :func:`triangulate` hide their modules as attributes of this
package; use ``importlib.import_module("reconstruct.calibration.calibrate")`` for a module.
"""

from reconstruct.calibration.calibrate import (
    Calibration,
    calibrate,
    calibrate_stack,
    calibration_camera,
    write_calibration_lp,
    write_diagnostic,
)
from reconstruct.calibration.camera import Intrinsics, intrinsics_from_exif, parse_intrinsics
from reconstruct.calibration.highlights import find_highlight, find_highlights
from reconstruct.calibration.lightcheck import (
    LightReport,
    check_lights,
    plot_positions,
    report_text,
    write_polar_plot,
)
from reconstruct.calibration.reflection import Sphere, light_from_highlight
from reconstruct.calibration.spheres import detect_spheres, fit_circle, refine_circle, stack_statistics
from reconstruct.calibration.triangulate import (
    SphereLights,
    Triangulation,
    lights_are_near,
    near_lights,
    sphere_lights,
    triangulate,
    write_near_light_files,
)

__all__ = [
    "Calibration",
    "Intrinsics",
    "LightReport",
    "Sphere",
    "SphereLights",
    "Triangulation",
    "calibrate",
    "calibrate_stack",
    "calibration_camera",
    "check_lights",
    "detect_spheres",
    "find_highlight",
    "find_highlights",
    "fit_circle",
    "intrinsics_from_exif",
    "light_from_highlight",
    "lights_are_near",
    "near_lights",
    "parse_intrinsics",
    "plot_positions",
    "refine_circle",
    "report_text",
    "sphere_lights",
    "stack_statistics",
    "triangulate",
    "write_calibration_lp",
    "write_diagnostic",
    "write_near_light_files",
    "write_polar_plot",
]
