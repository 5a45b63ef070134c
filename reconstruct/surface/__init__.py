"""Surfaces from normal maps: integration into heights for an orthographic camera (whole
rectangle or masked domain) or a perspective one, the integrator chosen by the normals,
flattening, segmentation of the object,
normal maps made elsewhere, and accuracy against ground truth.

The function :func:`integrate` shares its module's name: the package's attribute is the
function. The names are loaded on first use.
"""

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach(
    __name__,
    submod_attrs={
        "accuracy": ["GroundTruth", "height_rmse", "load_ground_truth", "normal_accuracy"],
        "flatten": ["flatten", "high_pass", "remove_plane", "remove_polynomial"],
        "fourier": ["frankot_chellappa", "poisson_dct"],
        "integrate": ["gradients_from_normals", "integrate"],
        "bilateral": ["discontinuity_preserving"],
        "choose": ["Integration", "integrate_auto", "integrate_with"],
        "masked": ["masked_poisson"],
        "multigrid": ["masked_laplacian"],
        "normalmaps": ["read_normal_map", "shaded"],
        "perspective": ["integrate_perspective", "perspective_gradients"],
        "segment": ["foreground_mask"],
    },
)
