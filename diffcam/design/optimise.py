"""Designing a diffuser: Adam (optax) on a surface's parameters, through the PSFs of a
depth range, against `diffcam.design.objective.depth_objective` or, with
``DesignOptions(objective="end_to_end")``,
`diffcam.design.end_to_end.end_to_end_objective` (the solver's TV weight is learnt
beside the surface).

    surface = SmoothSurface.random(key, (256, 256), 3e-6, feature_size=30e-6,
                                   height_max=2e-6)
    result = design(surface, camera, z1, refractive_index=1.5)
    save_design(result, "diffuser.npz")          # and diffuser.tif, the height map

A design stops after ``steps`` steps (the same on any machine) or, if set, after
``time_budget`` seconds. With ``checkpoint`` set it writes its file every
``checkpoint_every`` steps and continues from that file when started again: the
optimiser's state and the step are in it, so a continued design ends where an
uninterrupted one would.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import optax

from diffcam.core.errors import (DiffcamError, SamplingError, UndersamplingWarning,
                                 check_positive)
from diffcam.core.progress import new_bar
from diffcam.design.design_file import load_design, save_design
from diffcam.design.end_to_end import EndToEndObjective, end_to_end_objective
from diffcam.design.objective import DepthObjective, Terms, depth_objective
from diffcam.design.result import HISTORY_COLUMNS, Design, DesignOptions
from diffcam.design.surfaces import LensletArray, SmoothSurface, Surface, height_map
from diffcam.model.camera import Camera, finer_diffuser, oversampled
from diffcam.model.point_spread import check_inputs, depth_list

__all__ = ["design", "evaluate_design", "depth_range"]


def depth_range(near: float, far: float, count: int) -> np.ndarray:
    """``count`` depths from ``near`` to ``far`` (metres), evenly spaced in 1/z1 (the
    PSF's magnification M = 1 + z2/z1 and the scaling theorem's z_eff change linearly
    in 1/z1, so neighbouring depths are equally alike)."""
    check_positive("near", near, "m")
    check_positive("far", far, "m")
    if not (isinstance(count, (int, np.integer)) and count >= 2) or not near < far:
        raise DiffcamError(f"a depth range needs near < far and at least 2 depths, got "
                           f"{near!r} … {far!r}, {count!r} depths.")
    return 1 / np.linspace(1 / near, 1 / far, count)


def _loss(parameters, objective):
    """``(loss, Terms)``: ``parameters`` is the surface (depth objective) or
    ``(surface, log_tau)`` (end to end)."""
    if isinstance(objective, EndToEndObjective):
        return end_to_end_objective(parameters, objective)
    return depth_objective(parameters, objective)


@eqx.filter_jit
def _step(parameters, state, objective, learning_rate):
    """One Adam step: the parameters and state after it, and the loss and terms before."""
    (loss, terms), grad = eqx.filter_value_and_grad(_loss, has_aux=True)(parameters,
                                                                         objective)
    updates, state = optax.adam(learning_rate).update(grad, state)
    return eqx.apply_updates(parameters, updates), state, loss, terms


_terms = eqx.filter_jit(_loss)


def evaluate_design(parameters, objective: DepthObjective | EndToEndObjective) -> dict:
    """The objective's terms at ``parameters`` as floats: ``loss``, ``smooth_max``,
    ``max_correlation``, ``spread``. ``parameters``: a surface for the depth objective,
    ``(surface, log_tau)`` end to end (`diffcam.design.result.Design.parameters`).
    Evaluate a design on depths it was not optimised for with
    ``objective._replace(z1=finer_depths)`` (depth objective)."""
    loss, terms = _terms(parameters, objective)
    return _row(loss, terms)


def _row(loss, terms: Terms) -> dict:
    values = (loss, terms.smooth, terms.max_correlation, terms.spread)
    return dict(zip(HISTORY_COLUMNS, (float(v) for v in values)))


MAX_RELATIVE_BANDWIDTH = 0.25
"""Largest ``bandwidth`` as a share of the camera's wavelength: the shortest line's
phase, 2π(n − 1)h/λ, is steeper by 1/(1 − share) than the one the surface's limits are
set for, and the thin, dispersion-free element holds over a narrow band only."""
MAX_SOURCE_IMAGE = 1 / 8
"""Largest radius of the source's image on the sensor (source_radius·z2/z1 at the
nearest depth) as a share of the frame's smaller side: the PSF is blurred by moving it
circularly (`source_blurred`), which wraps light across the frame beyond that."""


def _check_light(camera, options: DesignOptions, z_min: float) -> None:
    """The light and source of ``options`` within what the design's PSFs can model."""
    wavelength = float(camera.wavelength)
    if not options.bandwidth <= MAX_RELATIVE_BANDWIDTH * wavelength:
        raise DiffcamError(f"bandwidth ({options.bandwidth:g} m) must be at most "
                           f"{MAX_RELATIVE_BANDWIDTH:g} of the camera's wavelength "
                           f"({wavelength:g} m): it is the light's half-width about it, "
                           f"and the surface's phase is modelled dispersion-free.")
    image = options.source_radius * float(camera.z2) / z_min / float(camera.dx)
    frame = min(camera.out_shape)
    if image > MAX_SOURCE_IMAGE * frame:
        raise DiffcamError(f"a source of radius {options.source_radius:g} m has an image "
                           f"of radius {image:.3g} pixels at z1 = {z_min:g} m, more than "
                           f"{MAX_SOURCE_IMAGE:g} of the {frame}-pixel frame: its blur would "
                           f"wrap around it; give the source's real radius (a pinhole or an "
                           f"LED: tens of µm) or a farther nearest depth.")


def _check(surface, camera, z1, refractive_index, options: DesignOptions) -> np.ndarray:
    """The concrete checks before anything is traced (sampling at the longest
    wavelength, ``camera.wavelength`` + ``options.bandwidth``, on the grid
    ``options.oversample``× finer); the depths as float64 (nz,)."""
    if not isinstance(surface, (SmoothSurface, LensletArray)):
        raise DiffcamError(f"surface must be a SmoothSurface or a LensletArray, got "
                           f"{type(surface).__name__}.")
    if tuple(surface.shape) != tuple(camera.shape) \
            or not np.isclose(surface.dx, float(camera.dx), rtol=1e-6, atol=0):
        raise DiffcamError(f"the surface's grid ({surface.shape} at {surface.dx:.3g} m) is "
                           f"not the camera's ({camera.shape} at {float(camera.dx):.3g} m); "
                           f"build them on one grid.")
    if not float(refractive_index) > 1:
        raise DiffcamError(f"refractive_index must be > 1 (a material denser than air), "
                           f"got {refractive_index!r}.")
    z1 = depth_list(z1)
    if z1.size < 2 or np.unique(z1).size != z1.size:
        raise DiffcamError(f"a depth range needs at least 2 different depths, got "
                           f"{z1.size} ({np.unique(z1).size} different).")
    _check_light(camera, options, float(z1.min()))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UndersamplingWarning)
        try:
            k = options.oversample
            check_inputs(finer_diffuser(height_map(surface, refractive_index), k),
                         oversampled(camera, k), z1, 0.0,
                         float(camera.wavelength) + options.bandwidth, True)
        except UndersamplingWarning as problem:
            raise SamplingError(f"{problem}. A design cannot accept undersampling (it would "
                                f"optimise the aliasing): change the camera or the depth "
                                f"range as said.") from None
    return z1


def design(surface: Surface, camera: Camera, z1, refractive_index: float = 1.5,
           options: DesignOptions | None = None) -> Design:
    """Optimise ``surface`` so the PSFs of the depths ``z1`` are unlike each other.

    Args:
        surface: the start, a `diffcam.design.surfaces.SmoothSurface` or
            `diffcam.design.surfaces.LensletArray` on the camera's grid.
        camera: the camera (wavelength, z2, pitch, aperture), metres.
        z1: the depths of the range, metres, (nz,), at least 2 (see `depth_range`).
        refractive_index: n of the diffuser material, unitless (> 1).
        options: `diffcam.design.result.DesignOptions` (objective, steps, step size,
            τ, sparsity weight, time budget, checkpoint, progress; end to end: training
            volumes, solver iterations, photons, the solver's first TV weight).

    Returns:
        A `diffcam.design.result.Design`; write it with
        `diffcam.design.design_file.save_design`.

    Raises:
        DiffcamError: a surface off the camera's grid, n ≤ 1, fewer than two depths, a
            geometry the PSF cannot sample, a bandwidth over `MAX_RELATIVE_BANDWIDTH` of
            the wavelength or a source imaged wider than `MAX_SOURCE_IMAGE` of the
            frame, or a checkpoint of another problem.
    """
    options = DesignOptions() if options is None else options
    z1 = _check(surface, camera, z1, refractive_index, options)
    log_tau = None if options.objective == "depth" else jnp.log(jnp.float32(options.tau))
    start = Design(surface, camera, z1, float(refractive_index), options,
                   np.zeros((0, len(HISTORY_COLUMNS))), {}, None, "not started", 0.0,
                   log_tau)
    start = dataclasses.replace(start, optimiser_state=start.initial_optimiser_state())
    if options.resume and options.checkpoint is not None \
            and Path(options.checkpoint).exists():
        start = _continued(start, load_design(options.checkpoint))
    return _run(start, start.objective())


def _continued(start: Design, saved: Design) -> Design:
    """The saved design, if it is the same problem as ``start``, with ``start``'s
    options (more steps, another budget)."""
    same = (type(saved.surface) is type(start.surface)
            and _fields(saved.surface) == _fields(start.surface)
            and np.array_equal(saved.z1, start.z1)
            and saved.refractive_index == start.refractive_index
            and saved.options.problem() == start.options.problem()
            and _fields(saved.camera) == _fields(start.camera))
    if not same:
        raise DiffcamError(f"{start.options.checkpoint}: a design of another problem "
                           f"(surface, camera, depths or settings differ); remove it or "
                           f"choose another checkpoint file.")
    return dataclasses.replace(saved, options=start.options)


def _fields(module) -> list:
    """A module's fields as plain values, to compare two problems."""
    return [np.asarray(v).tolist() if v is not None else None
            for f in dataclasses.fields(module) if not _is_parameter(f.name)
            for v in (getattr(module, f.name),)]


def _is_parameter(name: str) -> bool:
    return name in ("coefficients", "params")


def _run(current: Design, objective: DepthObjective | EndToEndObjective) -> Design:
    """Steps from ``current`` to ``options.steps``, with checkpoints and progress."""
    options = current.options
    parameters, state = current.parameters, current.optimiser_state
    rows, reason = list(current.history), f"{options.steps} steps"
    lr = jnp.asarray(options.learning_rate, jnp.float32)
    t0, seconds = time.perf_counter(), current.seconds
    with new_bar(options.steps, "design", unit="step", progress=options.progress) as bar:
        bar.update(len(rows))
        while len(rows) < options.steps:
            parameters, state, loss, terms = _step(parameters, state, objective, lr)
            rows.append(list(_row(loss, terms).values()))
            bar.update(1)
            bar.set_postfix(loss=f"{rows[-1][0]:.4f}", max_correlation=f"{rows[-1][2]:.4f}")
            elapsed = time.perf_counter() - t0
            current = dataclasses.replace(current.with_parameters(parameters),
                                          optimiser_state=state,
                                          history=np.asarray(rows, np.float64),
                                          seconds=seconds + elapsed)
            if options.checkpoint is not None and len(rows) % options.checkpoint_every == 0:
                save_design(_finished(current, objective, "checkpoint"), options.checkpoint)
            if options.time_budget is not None and elapsed > options.time_budget:
                reason = f"time budget ({options.time_budget:g} s)"
                break
    current = _finished(current, objective, reason)
    if options.checkpoint is not None:
        save_design(current, options.checkpoint)
    return current


def _finished(current: Design, objective: DepthObjective | EndToEndObjective,
              reason: str) -> Design:
    """``current`` with the objective's terms at its parameters and why it stopped."""
    return dataclasses.replace(current, final=evaluate_design(current.parameters, objective),
                               stop_reason=reason)
