"""Stage 1 — calibrate: the diffuser phase θd from near/far captures and captured PSFs.

Its modules (``diffcam.calibrate.<name>``):

- `near_far` — the near/far set-up
  ([`CalibrationGeometry`][diffcam.calibrate.near_far.CalibrationGeometry]), its forward
  model ([`NearFarModel`][diffcam.calibrate.near_far.NearFarModel],
  [`calibration_intensities`][diffcam.calibrate.near_far.calibration_intensities]) and
  input checks
- `projections` — Gerchberg–Saxton (paper Fig. 4), HIO, RAAR between the amplitudes
- `planes` — extra defocused intensity planes (a captured PSF) for them
- `lsq` — least squares through the differentiable forward model (optimistix)
- `psf_fit` — fitting θd (and geometry) to captured PSFs through paper Eq. 7
- `pipeline` — [`retrieve_phase`][diffcam.calibrate.pipeline.retrieve_phase], the default
  path: RAAR with restarts, then least squares
- `scene_psf` — the camera's PSF from raw captures of known scenes
  ([`fit_psf_from_scenes`][diffcam.calibrate.scene_psf.fit_psf_from_scenes]), no point
  source needed
- `captures` — preprocessing of captures, HDR merge, synthetic captures
- `simulation` — the paper's Fig. 3 simulation (the cameraman diffuser)
- `phase_io` — phase files
- `model_file` — the camera-model files (phase file, stack fit, field-dependent PSF)
  through one door
- `stack_model`, `stack_fit`, `stack_result`, `stack_inputs` — the wave model of a
  measured PSF stack, its fit to a few planes, the fitted result (prediction, file) and
  the given planes' checks and preparation
- `result` — [`RetrievalResult`][diffcam.calibrate.result.RetrievalResult], returned by
  every solver
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
