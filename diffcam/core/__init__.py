"""Foundations every stage shares: the centred grid convention
([`diffcam.core.grid`][diffcam.core.grid]), errors and input checks
([`diffcam.core.errors`][diffcam.core.errors]), lengths with units at the command-line edge
([`diffcam.core.units`][diffcam.core.units]), the one seam between the physics and the FFT
backend ([`diffcam.core.backend`][diffcam.core.backend]), and e^{jθ} at the cost of a few
products ([`diffcam.core.phasor`][diffcam.core.phasor])."""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__ = attach_stub(__name__, __file__)[:2]   # submodules on first access
