"""Stage 3 — reconstruct a scene from a sensor image and the PSF of its depth(s).

* `richardson_lucy` — paper Eq. 15, jitted; ``convention="skimage"`` reproduces
  scikit-image; Biggs–Andrews acceleration; Dey et al. TV regularisation.
* [`richardson_lucy_3d`][diffcam.reconstruct.richardson_lucy.richardson_lucy_3d],
  [`admm_tv_3d`][diffcam.reconstruct.admm.admm_tv_3d] — a volume from one image and a PSF
  stack.
* [`focus_sweep`][diffcam.reconstruct.focus.focus_sweep] — deconvolve at every depth of a
  stack, pick the plane that explains the image best.
* [`admm_tv`][diffcam.reconstruct.admm.admm_tv] — the DiffuserCam ADMM-TV solver for the
  crop model; its settings (axial TV weight, L1 weight, residual balancing) in
  [`AdmmOptions`][diffcam.reconstruct.admm.AdmmOptions].
* `fista` — non-negative least squares (FISTA), the unregularised floor.
* `wiener` — Tikhonov inverse filter, the fast linear baseline.
* [`convolution_model`][diffcam.reconstruct.operators.convolution_model] — the forward model
  ``A`` and its adjoint; [`field_model`][diffcam.reconstruct.operators.field_model] — the
  field-dependent (low-rank) one, which every solver takes in place of a PSF.

Every solver returns a [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction].
"""

from diffcam.reconstruct.admm import AdmmOptions, admm_tv, admm_tv_3d
from diffcam.reconstruct.fista import fista, nonnegative_least_squares
from diffcam.reconstruct.focus import FocusSweep, focus_sweep, sharpness
from diffcam.reconstruct.loop import Reconstruction
from diffcam.reconstruct.operators import (ConvolutionModel, FieldModel, convolution_model,
                                           field_model)
from diffcam.reconstruct.richardson_lucy import (RichardsonLucyOptions, richardson_lucy,
                                                richardson_lucy_3d)
from diffcam.reconstruct.wiener import wiener

__all__ = [
    "Reconstruction",
    "ConvolutionModel",
    "convolution_model",
    "FieldModel",
    "field_model",
    "richardson_lucy",
    "richardson_lucy_3d",
    "RichardsonLucyOptions",
    "focus_sweep",
    "FocusSweep",
    "sharpness",
    "AdmmOptions",
    "admm_tv",
    "admm_tv_3d",
    "wiener",
    "fista",
    "nonnegative_least_squares",
]
