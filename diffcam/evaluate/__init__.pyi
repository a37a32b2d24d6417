"""Stub of [`diffcam.evaluate`][diffcam.evaluate]: its public names and the modules they
come from.

diffcam/evaluate/__init__.py imports each on first use
([`diffcam.core.lazy`][diffcam.core.lazy])."""

from diffcam.evaluate.baseline import magnify_psf, relative_magnification
from diffcam.evaluate.metrics import (mse, pearson, phase_scores, psf_fidelity, psnr,
                                      ssim)
from diffcam.evaluate.registration import (Registration, magnification_from_light,
                                           magnify_about, register_magnification,
                                           scaling_baseline)

__all__ = ["magnify_psf", "relative_magnification", "mse", "pearson", "phase_scores",
           "psf_fidelity", "psnr", "ssim", "Registration", "register_magnification",
           "scaling_baseline", "magnify_about", "magnification_from_light"]
