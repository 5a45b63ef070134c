"""Synthetic RTI captures with known ground truth, deterministic from a seed.

Build a scene (:data:`SCENES`, :func:`clay_tablet`, :func:`sphere_cap`), light it
(:func:`dome_lights`, :func:`ring_lights`), render it (:func:`render`) or write a complete
capture folder with images, ``.lp`` file, ground truth and a laser scan
(:func:`write_capture`, also ``python -m data_synthetic``).
"""

from .capture import CaptureInfo, write_capture
from .lights import dome_lights, ring_lights
from .render import render
from .scan import sample_scan
from .shadows import cast_shadow_mask
from .surfaces import SCENES, Surface, clay_tablet, normals_from_height, sphere_cap

__all__ = [
    "SCENES",
    "CaptureInfo",
    "Surface",
    "cast_shadow_mask",
    "clay_tablet",
    "dome_lights",
    "normals_from_height",
    "render",
    "ring_lights",
    "sample_scan",
    "sphere_cap",
    "write_capture",
]
