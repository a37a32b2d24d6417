"""diffcam: differentiable JAX optics for lensless diffuser cameras.

The four stages of the method (Optics Express 2019), each a subpackage or module:

1. calibrate — :mod:`diffcam.retrieval` (``calibrate``, GS/HIO/RAAR, least squares,
   fitting to captured PSFs);
2. model — :mod:`diffcam.camera` (``Camera``, ``psf``), :mod:`diffcam.stack`
   (``psf_stack``), built on :mod:`diffcam.propagate` and :mod:`diffcam.optics`;
3. reconstruct — :mod:`diffcam.reconstruct` (Richardson–Lucy, ADMM-TV, Wiener);
4. evaluate — :mod:`diffcam.metrics`, :mod:`diffcam.scaling` (the scaling baseline).

Units are SI everywhere (metres, radians); grids are centred (index N//2 is the axis).
"""

from . import grid, metrics, optics, propagate, reconstruct, retrieval, sampling
from .camera import Camera, HeightMap, Spectrum, psf, random_diffuser
from .errors import DiffcamError, SamplingError, ShapeError, UndersamplingWarning
from .metrics import pearson, psf_fidelity, psnr, ssim
from .optics import apply_phase, circular_aperture, point_source_field, thin_lens
from .propagate import angular_spectrum, fourier_lens, fresnel_ir, fresnel_tf
from .reconstruct import admm_tv, richardson_lucy, wiener
from .retrieval import calibrate
from .sampling import plan_sampling
from .scaling import scale_psf
from .stack import load_stack, psf_stack, save_stack

__version__ = "0.1.0"

__all__ = [
    "Camera", "HeightMap", "Spectrum", "psf", "random_diffuser", "psf_stack", "save_stack",
    "load_stack", "scale_psf", "calibrate", "richardson_lucy", "admm_tv", "wiener",
    "fresnel_tf", "fresnel_ir", "angular_spectrum", "fourier_lens",
    "circular_aperture", "point_source_field", "thin_lens", "apply_phase", "plan_sampling",
    "pearson", "ssim", "psnr", "psf_fidelity", "DiffcamError", "SamplingError", "ShapeError",
    "UndersamplingWarning", "grid", "metrics", "optics", "propagate", "reconstruct",
    "retrieval", "sampling",
]
