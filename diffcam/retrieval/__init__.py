"""Diffuser phase retrieval (issue #4): θd from near/far captures and captured PSFs.

- :mod:`.geometry`    — the near/far set-up (:class:`CalibrationGeometry`) and input checks
- :mod:`.forward`     — θd → near/far intensities; the paper's Fig. 3 simulation
- :mod:`.projections` — Gerchberg–Saxton, HIO, RAAR between near and far amplitudes
- :mod:`.planes`      — extra defocused intensity planes (a captured PSF) for them
- :mod:`.lsq`         — least squares through the differentiable forward model (optimistix)
- :mod:`.psf_fit`     — fitting θd (and geometry) to captured PSFs through paper Eq. 7
- :mod:`.calibrate`   — the default path: RAAR with restarts, then least squares
- :mod:`.captures`    — preprocessing of captures, HDR merge, synthetic captures
- :mod:`.result`      — :class:`RetrievalResult`, returned by every solver
"""

from .calibrate import calibrate
from .captures import (PreparedCaptures, centre_on_axis, centroid, merge_exposures,
                       normalise_min_max,
                       prepare_captures, resample_capture, resample_far_field,
                       synthetic_captures)
from .forward import (PaperSimulation, calibration_intensities, cameraman_phase,
                      paper_simulation)
from .geometry import CalibrationGeometry, check_far_pitch, glass_equivalent_distance
from .lsq import PhaseGrid, fit_phase, near_far_model, retrieve_lsq
from .projections import gerchberg_saxton, hio, initial_phase, raar, retrieve_projections
from .phase_io import PhaseFile, load_phase, save_phase
from .planes import DefocusedPlane, psf_plane
from .psf_fit import fit_to_psfs, predict_psfs, resolve_twin
from .result import RetrievalResult

__all__ = [
    # geometry, forward model, result
    "CalibrationGeometry", "glass_equivalent_distance", "check_far_pitch",
    "calibration_intensities", "cameraman_phase", "paper_simulation", "PaperSimulation",
    "RetrievalResult",
    # solvers
    "calibrate", "retrieve_projections", "gerchberg_saxton", "hio", "raar",
    "initial_phase", "DefocusedPlane", "psf_plane",
    "retrieve_lsq", "fit_phase", "near_far_model", "PhaseGrid",
    "fit_to_psfs", "predict_psfs", "resolve_twin", "PhaseFile", "save_phase", "load_phase",
    # captures
    "prepare_captures", "PreparedCaptures", "synthetic_captures", "merge_exposures",
    "normalise_min_max",
    "centroid", "centre_on_axis", "resample_capture", "resample_far_field",
]
