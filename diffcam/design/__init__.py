"""Designing a diffuser: a manufacturable surface optimised through the model's PSFs.

- `diffcam.design.surfaces` — [`SmoothSurface`][diffcam.design.surfaces.SmoothSurface] (a
  smooth random surface of bounded height and minimum feature size) and
  [`LensletArray`][diffcam.design.surfaces.LensletArray] (a microlens array), height maps
  in metres;
- `diffcam.design.objective` — depth discrimination: the largest Pearson correlation
  between the PSFs of two depths (a smooth maximum for the gradient), with the PSFs'
  spread;
- `diffcam.design.end_to_end` — end to end: training volumes imaged through the PSFs
  with shot noise and reconstructed by unrolled ADMM-TV, whose TV weight is learnt
  beside the surface;
- `diffcam.design.optimise` — [`design`][diffcam.design.optimise.design]: Adam through
  [`psf_map`][diffcam.model.stack_map.psf_map], resumable;
- `diffcam.design.design_file` — the design file (``.npz``) and its TIFF height map.
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
