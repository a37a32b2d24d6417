"""Stage 4 — judging PSFs, phases and reconstructions.

- :mod:`.metrics` — Pearson (paper Eq. 14), SSIM, MSE/PSNR, the phase metric, PSF
  fidelity after registration;
- :mod:`.baseline` — the magnification baseline (Xie et al.): one measured PSF magnified
  to other depths, what the model must beat;
- :mod:`.volume` — the depth ridge of a tilted target in a reconstructed volume (tilt,
  scatter, axial width, light outside the target) and its depth map.
"""

from diffcam.evaluate.baseline import magnify_psf, relative_magnification
from diffcam.evaluate.metrics import (mse, pearson, phase_scores, psf_fidelity, psnr,
                                      ssim)
from diffcam.evaluate.registration import (Registration, magnification_from_light,
                                           magnify_about, register_magnification,
                                           scaling_baseline)

__all__ = ["magnify_psf", "relative_magnification", "mse", "pearson", "phase_scores",
           "psf_fidelity", "psnr", "ssim", "Registration", "register_magnification",
           "scaling_baseline", "magnify_about", "magnification_from_light"]
