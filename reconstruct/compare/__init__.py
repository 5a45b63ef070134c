"""Comparison of a reconstruction with a laser scan, in millimetres.

The subpackage owns reading meshes and point clouds (:mod:`.geometry`), aligning the scan
to the reconstruction (:mod:`.registration`), their signed distances and statistics
(:mod:`.signed_distance`), and the coloured PLY, histogram and overlay (:mod:`.figures`).
open3d and pyvista are imported only by the functions that use them.
"""

from reconstruct.compare.figures import (
    DEFAULT_SIGN_CONVENTION,
    NAN_COLOR,
    default_limit,
    distance_lookup_table,
    diverging_colors,
    write_distance_ply,
    write_histogram,
    write_overlay,
)
from reconstruct.compare.geometry import UNITS, Geometry, load_geometry
from reconstruct.compare.registration import Alignment, align
from reconstruct.compare.signed_distance import DistanceResult, distances, within_tolerance

__all__ = [
    "DEFAULT_SIGN_CONVENTION",
    "NAN_COLOR",
    "UNITS",
    "Alignment",
    "DistanceResult",
    "Geometry",
    "align",
    "default_limit",
    "distance_lookup_table",
    "distances",
    "diverging_colors",
    "load_geometry",
    "within_tolerance",
    "write_distance_ply",
    "write_histogram",
    "write_overlay",
]
