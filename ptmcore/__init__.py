"""RTI maths and file formats: light files, image stacks, PTM fitting and normals.

Needs only NumPy and SciPy (plus the image decoders when photographs are read); it imports
none of the 3D libraries.
"""

from .errors import InputError
from .fit import PTM, fit_matrix, fit_ptm, light_matrix
from .images import ImageStack, linear_to_srgb, load_stack, read_image, srgb_to_linear
from .lp import LightSet, read_lp, write_lp
from .normals import (
    PhotometricStereo,
    angular_error,
    lambertian_albedo,
    normals_from_ptm,
    photometric_stereo,
    ptm_maximum,
)

__version__ = "0.1.0"

__all__ = [
    "InputError",
    "ImageStack",
    "LightSet",
    "PTM",
    "PhotometricStereo",
    "angular_error",
    "fit_matrix",
    "fit_ptm",
    "lambertian_albedo",
    "light_matrix",
    "linear_to_srgb",
    "load_stack",
    "normals_from_ptm",
    "photometric_stereo",
    "ptm_maximum",
    "read_image",
    "read_lp",
    "srgb_to_linear",
    "write_lp",
]
