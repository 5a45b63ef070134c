"""Surfaces from normal maps: integration into heights for an orthographic camera (whole
rectangle or masked domain) or a perspective one, flattening, segmentation of the object,
normal maps made elsewhere, and accuracy against ground truth.

The function :func:`integrate` hides its module as an attribute of this package; use
``importlib.import_module("reconstruct.surface.integrate")`` for the module.
"""

from reconstruct.surface.accuracy import GroundTruth, height_rmse, load_ground_truth, normal_accuracy
from reconstruct.surface.flatten import flatten, high_pass, remove_plane, remove_polynomial
from reconstruct.surface.fourier import frankot_chellappa, poisson_dct
from reconstruct.surface.integrate import gradients_from_normals, integrate
from reconstruct.surface.masked import discontinuity_preserving, masked_poisson
from reconstruct.surface.multigrid import masked_laplacian
from reconstruct.surface.normalmaps import read_normal_map, shaded
from reconstruct.surface.perspective import integrate_perspective, perspective_gradients
from reconstruct.surface.segment import foreground_mask

__all__ = [
    "GroundTruth",
    "discontinuity_preserving",
    "flatten",
    "foreground_mask",
    "frankot_chellappa",
    "gradients_from_normals",
    "height_rmse",
    "high_pass",
    "integrate",
    "integrate_perspective",
    "load_ground_truth",
    "masked_laplacian",
    "masked_poisson",
    "normal_accuracy",
    "perspective_gradients",
    "poisson_dct",
    "read_normal_map",
    "remove_plane",
    "remove_polynomial",
    "shaded",
]
