"""Stage 4 — judging PSFs, phases and reconstructions.

- `diffcam.evaluate.metrics` — Pearson (paper Eq. 14), SSIM, MSE/PSNR, the phase metric, PSF
  fidelity after registration;
- `diffcam.evaluate.baseline` — the magnification baseline (Xie et al.): one measured PSF
  magnified to other depths, what the model must beat;
- `diffcam.evaluate.volume` — the depth ridge of a tilted target in a reconstructed volume
  (tilt, scatter, axial width, light outside the target) and its depth map.
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
