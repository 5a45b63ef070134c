"""Where the lights were: the pinhole camera model (from numbers, the lens or EXIF), glossy
sphere detection, highlights, the reflection geometry, near-light triangulation from several
spheres, and checks of a light layout before any photograph is taken.

The functions :func:`calibrate` and :func:`triangulate` share their modules' names: the
package's attribute is the function (``from reconstruct.calibration.triangulate import …``
still reaches the module's other names). The names are loaded on first use.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "calibrate": ["Calibration", "calibrate", "calibrate_stack", "calibration_camera", "write_calibration_lp", "write_diagnostic"],
        "camera": ["Intrinsics", "intrinsics_from_exif", "parse_intrinsics"],
        "highlights": ["find_highlight", "find_highlights", "sphere_highlights"],
        "lightcheck": ["LightReport", "check_lights", "plot_positions", "polar_plot_png", "report_text",
                       "short_labels", "write_polar_plot"],
        "reflection": ["Sphere", "light_from_highlight"],
        "spheres": ["detect_spheres", "fit_circle", "refine_circle", "stack_statistics"],
        "triangulate": ["SphereLights", "Triangulation", "lights_are_near", "near_lights", "sphere_lights", "triangulate", "write_near_light_files"],
    },
)
