"""Stage 1 — calibrate: the diffuser phase θd from near/far captures and captured PSFs.

- :mod:`.near_far`    — the near/far set-up (:class:`CalibrationGeometry`), its forward
  model (:class:`NearFarModel`, :func:`calibration_intensities`) and input checks
- :mod:`.projections` — Gerchberg–Saxton (paper Fig. 4), HIO, RAAR between the amplitudes
- :mod:`.planes`      — extra defocused intensity planes (a captured PSF) for them
- :mod:`.lsq`         — least squares through the differentiable forward model (optimistix)
- :mod:`.psf_fit`     — fitting θd (and geometry) to captured PSFs through paper Eq. 7
- :mod:`.pipeline`    — :func:`retrieve_phase`, the default path: RAAR with restarts, then
  least squares
- :mod:`.scene_psf`   — the camera's PSF from raw captures of known scenes
  (:func:`fit_psf_from_scenes`), no point source needed
- :mod:`.captures`    — preprocessing of captures, HDR merge, synthetic captures
- :mod:`.simulation`  — the paper's Fig. 3 simulation (the cameraman diffuser)
- :mod:`.phase_io`    — phase files
- :mod:`.model_file`  — the camera-model files (phase file or stack fit) through one door
- :mod:`.stack_model`, :mod:`.stack_fit`, :mod:`.stack_result`, :mod:`.stack_inputs`
  — the wave model of a measured PSF stack, its fit to a few planes, the fitted result
  (prediction, file) and the given planes' checks and preparation
- :mod:`.result`      — :class:`RetrievalResult`, returned by every solver
"""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
