"""The default calibration path: projections with restarts, then least squares.

RAAR from several random starts (batched) finds the basin that textbook GS misses;
the least-squares fit through the forward model then polishes the phase against the
measured intensities with a noise-aware loss and saturation masks. Either stage can be
switched off. This is what ``diffcam calibrate`` runs.
"""

from __future__ import annotations

import dataclasses
import time

import jax

from diffcam.calibrate.phase.near_far import CalibrationGeometry
from diffcam.calibrate.phase.lsq import FitOptions, retrieve_lsq
from diffcam.calibrate.phase.projections import ProjectionOptions, retrieve_projections
from diffcam.calibrate.phase.result import RetrievalResult

__all__ = ["retrieve_phase", "POLISH"]


POLISH = FitOptions(loss="intensity", iterations=100)


def retrieve_phase(near, far, geometry: CalibrationGeometry, aperture, *,
                   projections: ProjectionOptions | None = None,
                   refine: FitOptions | None = POLISH, masks=None,
                   **overrides) -> RetrievalResult:
    """Diffuser phase from near/far intensities: projections (RAAR, 300 iterations,
    ``restarts`` random starts), then a least-squares polish (``refine``; ``None`` skips
    it). The polish uses plain intensity residuals by default (`POLISH`, 100
    L-BFGS steps): after the projections it is already in the right basin, and on noisy
    synthetic captures it matched captured PSFs better than the weighted loss (registered
    Pearson 0.95 against 0.946 in the CLI test).

    Args:
        near, far: intensities on the calibration grid (see
            [`diffcam.calibrate.prepare_captures`][diffcam.calibrate.phase.captures.prepare_captures]).
        geometry: the set-up, SI units.
        aperture: diffuser-plane amplitude C (ny, nx).
        projections: [`ProjectionOptions`][diffcam.calibrate.phase.projections.ProjectionOptions]
            of the first stage (default: RAAR, 300 iterations, 4 random starts; with
            ``planes`` one flat start); ``**overrides`` replace its fields (``iterations=``,
            ``restarts=``, ``key=`` (default ``jax.random.key(0)``), ``far_pitch=``,
            ``planes=``: extra intensities,
            [`DefocusedPlane`][diffcam.calibrate.phase.planes.DefocusedPlane], e.g. a captured PSF
            through [`psf_plane`][diffcam.calibrate.phase.planes.psf_plane], that break the twin
            and let strongly scattering diffusers converge).
        refine: [`FitOptions`][diffcam.calibrate.phase.lsq.FitOptions] of the polish, or ``None``.
        masks: ``(near_mask, far_mask)``, 0 at saturated pixels (least-squares stage).

    Returns:
        [`RetrievalResult`][diffcam.calibrate.phase.result.RetrievalResult] of the last stage
        (``history`` its error history); ``stats["stages"]`` holds each stage's stats and
        history.
    """
    t0 = time.perf_counter()
    first_options = ProjectionOptions.of(projections, **overrides)
    if first_options.key is None:
        first_options = dataclasses.replace(first_options, key=jax.random.key(0))
    if first_options.restarts is None:
        first_options = dataclasses.replace(first_options,
                                            restarts=1 if first_options.planes else 4)
    first = retrieve_projections(near, far, geometry, options=first_options)
    stages = [dict(first.stats, history=first.history)]
    result = first
    if refine is not None:
        result = retrieve_lsq(near, far, geometry, aperture, init=first.phase, options=refine,
                              masks=masks)
        stages.append(dict(result.stats, history=result.history))
    stats = {"method": "+".join(s["method"] for s in stages), "stages": stages,
             "iterations": sum(int(s["iterations"]) for s in stages),
             "wall_time": time.perf_counter() - t0}
    return RetrievalResult(result.phase, result.field, result.history, stats)
