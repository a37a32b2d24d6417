"""Stage 2 — the camera model: the PSF at any depth (paper Eqs. 7–8) and its sensor.

- :mod:`.camera` — :class:`Camera` (fixed geometry and traced physical numbers),
  :class:`HeightMap`, :class:`Spectrum`, random diffusers;
- :mod:`.point_spread` — the PSF of a point source (direct, or by the Fresnel scaling theorem);
- :mod:`.stack` — PSF stacks over depths and positions: chunked, sharded, streamed,
  saved and loaded;
- :mod:`.sensor` — pixel integration, resampling, noise, saturation, quantisation.
"""

from diffcam.model.camera import Camera, HeightMap, Spectrum, random_diffuser, with_method
from diffcam.model.point_spread import psf
from diffcam.model.stack import (PsfStackOptions, iter_psf_stack, load_stack, psf_stack,
                                 save_stack)

__all__ = ["Camera", "HeightMap", "Spectrum", "random_diffuser", "psf", "psf_stack",
           "iter_psf_stack", "PsfStackOptions", "save_stack", "load_stack", "with_method"]
