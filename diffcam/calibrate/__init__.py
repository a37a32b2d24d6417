"""Stage 1 — calibrate: the camera's model from its captures, one subpackage per job.

- `diffcam.calibrate.phase` — the diffuser phase θd from a
  near-field and a far-field capture, and from captured PSFs (the paper's calibration:
  Gerchberg–Saxton, RAAR, least squares through the forward model)
- `diffcam.calibrate.stack` — a measured PSF stack's wave
  model, fitted to a few planes, predicting every other depth
- `diffcam.calibrate.scene` — the PSF (one, or field-dependent)
  from raw captures of known scenes, no point source needed

Beside them, serving all three:

- `model_file` — the camera-model files (phase file, stack fit, field-dependent PSF)
  through one door ([`load_model`][diffcam.calibrate.model_file.load_model])
- `simulation` — the paper's Fig. 3 simulation (the cameraman diffuser), simulated
  measured stacks, and the higher-fidelity PSFs of a height map that the benchmarks
  judge against

The public names of all of them are here (``diffcam.calibrate.fit_stack``, …).
"""

from diffcam.core.deprecation import moved_modules
from diffcam.core.lazy import attach_stub

__getattr__, __dir__, __all__ = attach_stub(__name__, __file__)
moved_modules(__name__, {
    **{m: f"phase.{m}" for m in ("near_far", "projections", "planes", "lsq", "psf_fit",
                                 "pipeline", "captures", "result")},
    "phase_io": "phase.file", "scene_psf": "scene.fit",
    **{f"stack_{m}": f"stack.{m}" for m in ("fit", "model", "inputs", "result")}})
