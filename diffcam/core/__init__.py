"""Foundations every stage shares: the centred grid convention (:mod:`.grid`), errors and
input checks (:mod:`.errors`), lengths with units at the command-line edge
(:mod:`.units`), the one seam between the physics and the FFT backend
(:mod:`.backend`), and e^{jθ} at the cost of a few products (:mod:`.phasor`)."""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__ = attach_stub(__name__, __file__)[:2]   # submodules on first access
