"""RTI maths and file formats: light files, image stacks, PTM fitting (plain, robust, and HP's
own in the photographs' encoding), normals, and HP's ``.ptm`` files.

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
from .ptmencoded import fit_ptm_encoded, fit_ptm_rgb_encoded
from .ptmfile import PTMFile, read_ptm, write_ptm
from .robust import robust_photometric_stereo
from .robustptm import RobustPTM, debiased_normals, hemisphere_coefficients, robust_fit_ptm, robust_ptm

__version__ = "0.1.0"

__all__ = [
    "InputError",
    "ImageStack",
    "LightSet",
    "PTM",
    "PTMFile",
    "PhotometricStereo",
    "RobustPTM",
    "angular_error",
    "debiased_normals",
    "fit_matrix",
    "fit_ptm",
    "fit_ptm_encoded",
    "fit_ptm_rgb_encoded",
    "hemisphere_coefficients",
    "lambertian_albedo",
    "light_matrix",
    "linear_to_srgb",
    "load_stack",
    "normals_from_ptm",
    "photometric_stereo",
    "ptm_maximum",
    "read_image",
    "read_lp",
    "read_ptm",
    "robust_fit_ptm",
    "robust_photometric_stereo",
    "robust_ptm",
    "srgb_to_linear",
    "write_lp",
    "write_ptm",
]
