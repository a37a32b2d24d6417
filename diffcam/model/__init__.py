"""Stage 2 — the camera model: the PSF at any depth (paper Eqs. 7–8) and its sensor.

- `diffcam.model.camera` — [`Camera`][diffcam.model.camera.Camera] (fixed geometry and
  traced physical numbers), [`HeightMap`][diffcam.model.camera.HeightMap],
  [`Spectrum`][diffcam.model.camera.Spectrum], random diffusers;
- `diffcam.model.point_spread` — the PSF of a point source (direct, or by the Fresnel
  scaling theorem);
- `diffcam.model.off_axis` — what changes across the field: the stop's shadow, the
  sensor's angular response, vignetting;
- `diffcam.model.stack` — PSF stacks over depths and positions: chunked, sharded, streamed,
  saved and loaded;
- `diffcam.model.sensor` — pixel integration, resampling, noise, saturation, quantisation.
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
