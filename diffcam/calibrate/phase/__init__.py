"""The diffuser phase θd from near/far captures and captured PSFs (the paper's
calibration).

Its modules (``diffcam.calibrate.phase.<name>``):

- `near_far` — the near/far set-up
  ([`CalibrationGeometry`][diffcam.calibrate.phase.near_far.CalibrationGeometry]), its
  forward model ([`NearFarModel`][diffcam.calibrate.phase.near_far.NearFarModel],
  [`calibration_intensities`][diffcam.calibrate.phase.near_far.calibration_intensities])
  and input checks
- `projections` — Gerchberg–Saxton (paper Fig. 4), HIO, RAAR between the amplitudes
- `planes` — extra defocused intensity planes (a captured PSF) for them
- `lsq` — least squares through the differentiable forward model (optimistix)
- `psf_fit` — fitting θd (and geometry) to captured PSFs through paper Eq. 7
- `pipeline` — [`retrieve_phase`][diffcam.calibrate.phase.pipeline.retrieve_phase], the
  default path: RAAR with restarts, then least squares
- `captures` — preprocessing of captures, HDR merge, synthetic captures
- `file` — phase files
- `result` — [`RetrievalResult`][diffcam.calibrate.phase.result.RetrievalResult], returned
  by every solver
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
