"""Comparison of a reconstruction with a laser scan, in millimetres.

The subpackage owns reading meshes and point clouds (:mod:`.geometry`), aligning the scan
to the reconstruction (:mod:`.registration`), their signed distances and statistics
(:mod:`.signed_distance`), and the coloured PLY, histogram and overlay (:mod:`.figures`).
open3d and pyvista are imported only by the functions that use them.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "figures": ["DEFAULT_SIGN_CONVENTION", "NAN_COLOR", "default_limit", "distance_lookup_table", "diverging_colors", "write_distance_ply", "write_histogram", "write_overlay"],
        "geometry": ["Geometry", "UNITS", "load_geometry"],
        "registration": ["Alignment", "align"],
        "signed_distance": ["DistanceResult", "distances", "within_tolerance"],
    },
)
