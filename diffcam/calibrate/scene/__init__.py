"""The camera's PSF from raw captures of known scenes: calibration without a point source.

Its modules (``diffcam.calibrate.scene.<name>``):

- `pairs` — the raws and their ground-truth scenes, checked, flipped and scaled
- `fit` — [`fit_psf_from_scenes`][diffcam.calibrate.scene.fit.fit_psf_from_scenes], its
  field-dependent form
  [`fit_field_psf_from_scenes`][diffcam.calibrate.scene.fit.fit_field_psf_from_scenes],
  and [`predict_raw`][diffcam.calibrate.scene.fit.predict_raw]
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
