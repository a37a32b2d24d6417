"""Stub of [`diffcam.calibrate`][diffcam.calibrate]: its public names and the modules they
come from.

diffcam/calibrate/__init__.py imports each on first use
([`diffcam.core.lazy`][diffcam.core.lazy])."""

from diffcam.calibrate.phase.captures import (CaptureOptions, PreparedCaptures, SyntheticSensor,
                                        centre_on_axis, centroid,
                                        merge_exposures, normalise_min_max, prepare_captures,
                                        resample_capture, resample_far_field,
                                        synthetic_captures)
from diffcam.calibrate.phase.lsq import (ConvergenceWarning, FitOptions, PhaseGrid, fit_phase,
                                   near_far_model,
                                   retrieve_lsq)
from diffcam.calibrate.model_file import load_model, model_kind
from diffcam.calibrate.phase.near_far import (CalibrationGeometry, NearFarModel,
                                        calibration_intensities, check_far_pitch,
                                        glass_equivalent_distance)
from diffcam.calibrate.phase.file import PhaseFile, load_phase, save_phase
from diffcam.calibrate.phase.pipeline import retrieve_phase
from diffcam.calibrate.phase.planes import DefocusedPlane, psf_plane
from diffcam.calibrate.phase.projections import (ProjectionOptions, gerchberg_saxton, hio, initial_phase, raar,
                                           retrieve_projections)
from diffcam.calibrate.phase.psf_fit import (DepthLaw, PsfFitOptions, fit_to_psfs, predict_psfs,
                                      resolve_twin)
from diffcam.calibrate.phase.result import RetrievalResult
from diffcam.calibrate.scene.fit import (SceneFieldPsf, ScenePsf, ScenePsfOptions,
                                         fit_field_psf_from_scenes, fit_psf_from_scenes,
                                         predict_raw)
from diffcam.calibrate.simulation import PaperSimulation, cameraman_phase, paper_simulation
from diffcam.calibrate.stack.fit import StackFitOptions, StackFitWarning, fit_stack
from diffcam.calibrate.stack.inputs import prepare_planes
from diffcam.calibrate.stack.model import StackModel
from diffcam.calibrate.stack.result import StackFit, load_stack_fit

__all__ = [
    # geometry, forward model, result
    "CalibrationGeometry", "NearFarModel", "glass_equivalent_distance", "check_far_pitch",
    "calibration_intensities", "cameraman_phase", "paper_simulation", "PaperSimulation",
    "RetrievalResult", "ConvergenceWarning",
    # solvers
    "retrieve_phase", "retrieve_projections", "gerchberg_saxton", "hio", "raar",
    "initial_phase", "ProjectionOptions", "DefocusedPlane", "psf_plane",
    "retrieve_lsq", "fit_phase", "FitOptions", "near_far_model", "PhaseGrid",
    "fit_to_psfs", "PsfFitOptions", "DepthLaw", "predict_psfs", "resolve_twin", "PhaseFile", "save_phase", "load_phase",
    "load_model", "model_kind",
    # captures
    "prepare_captures", "PreparedCaptures", "CaptureOptions", "synthetic_captures",
    "SyntheticSensor", "merge_exposures",
    "normalise_min_max", "centroid", "centre_on_axis", "resample_capture",
    "resample_far_field",
    # measured PSF stacks
    "StackModel", "StackFitOptions", "StackFit", "StackFitWarning", "fit_stack",
    "load_stack_fit", "prepare_planes",
    # the PSF from scenes
    "ScenePsf", "ScenePsfOptions", "fit_psf_from_scenes", "predict_raw",
    "SceneFieldPsf", "fit_field_psf_from_scenes",
]
