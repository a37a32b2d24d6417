"""Stub of [`diffcam`][diffcam]: its public names and the modules they come from.

diffcam/__init__.py imports each on first use ([`diffcam.core.lazy`][diffcam.core.lazy])."""

from diffcam import calibrate, core, design, evaluate, model, optics, reconstruct
from diffcam.calibrate import retrieve_phase
from diffcam.core.errors import (ConvergenceWarning, DiffcamError, GeometryWarning,
                                 SamplingError, ShapeError, UndersamplingWarning)
from diffcam.evaluate import magnify_psf, pearson, psf_fidelity, psnr, ssim
from diffcam.model import (Camera, HeightMap, Spectrum, load_stack, psf, psf_loss, psf_map,
                           psf_stack, random_diffuser, save_stack)
from diffcam.optics import (angular_spectrum, apply_phase, circular_aperture, fourier_lens,
                            fresnel_ir, fresnel_tf, plan_sampling, point_source_field,
                            thin_lens)
from diffcam.reconstruct import admm_tv, richardson_lucy, wiener

__all__ = [
    "Camera", "HeightMap", "Spectrum", "psf", "psf_map", "psf_loss", "random_diffuser",
    "psf_stack", "save_stack",
    "load_stack", "magnify_psf", "retrieve_phase", "richardson_lucy", "admm_tv", "wiener",
    "fresnel_tf", "fresnel_ir", "angular_spectrum", "fourier_lens",
    "circular_aperture", "point_source_field", "thin_lens", "apply_phase", "plan_sampling",
    "pearson", "ssim", "psnr", "psf_fidelity", "DiffcamError", "SamplingError", "ShapeError",
    "UndersamplingWarning", "GeometryWarning", "ConvergenceWarning", "calibrate", "core", "design",
    "evaluate", "model", "optics", "reconstruct",
]

__version__: str
