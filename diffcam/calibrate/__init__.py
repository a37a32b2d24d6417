"""Stage 1 — calibrate: the diffuser phase θd from near/far captures and captured PSFs.

- `diffcam.calibrate.near_far` — the near/far set-up
  ([`CalibrationGeometry`][diffcam.calibrate.near_far.CalibrationGeometry]), its forward
  model ([`NearFarModel`][diffcam.calibrate.near_far.NearFarModel],
  [`calibration_intensities`][diffcam.calibrate.near_far.calibration_intensities]) and input
  checks
- `diffcam.calibrate.projections` — Gerchberg–Saxton (paper Fig. 4), HIO, RAAR between the
  amplitudes
- `diffcam.calibrate.planes`      — extra defocused intensity planes (a captured PSF) for them
- `diffcam.calibrate.lsq` — least squares through the differentiable forward model
  (optimistix)
- `diffcam.calibrate.psf_fit` — fitting θd (and geometry) to captured PSFs through paper Eq.
  7
- `diffcam.calibrate.pipeline` —
  [`retrieve_phase`][diffcam.calibrate.pipeline.retrieve_phase], the default path: RAAR with
  restarts, then least squares
- `diffcam.calibrate.scene_psf`   — the camera's PSF from raw captures of known scenes
  ([`fit_psf_from_scenes`][diffcam.calibrate.scene_psf.fit_psf_from_scenes]), no point
  source needed
- `diffcam.calibrate.captures`    — preprocessing of captures, HDR merge, synthetic captures
- `diffcam.calibrate.simulation`  — the paper's Fig. 3 simulation (the cameraman diffuser)
- `diffcam.calibrate.phase_io`    — phase files
- `diffcam.calibrate.model_file` — the camera-model files (phase file or stack fit) through
  one door
- `diffcam.calibrate.stack_model`, `diffcam.calibrate.stack_fit`,
  `diffcam.calibrate.stack_result`, `diffcam.calibrate.stack_inputs` — the wave model of a
  measured PSF stack, its fit to a few planes, the fitted result (prediction, file) and the
  given planes' checks and preparation
- `diffcam.calibrate.result` —
  [`RetrievalResult`][diffcam.calibrate.result.RetrievalResult], returned by every solver
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
