"""A measured PSF stack: its wave model, fitted to a few planes, predicting the others.

Its modules (``diffcam.calibrate.stack.<name>``):

- `model` — [`StackModel`][diffcam.calibrate.stack.model.StackModel]: one band-limited
  diffuser-side field seen by every plane through the Fresnel scaling theorem
- `inputs` — the given planes, checked and prepared
- `fit` — [`fit_stack`][diffcam.calibrate.stack.fit.fit_stack]: the model fitted to the
  given planes
- `result` — [`StackFit`][diffcam.calibrate.stack.result.StackFit]: the fitted model's
  prediction of any plane, and its file
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
