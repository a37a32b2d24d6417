"""What a diffuser design is made of: its settings (`DesignOptions`) and its outcome
(`Design`: the surface, the camera and depths it was designed for, the objective's
history and the optimiser's state, so it can be continued)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import numpy as np
import optax

from diffcam.core.errors import DiffcamError, real_number, whole_number
from diffcam.design.end_to_end import EndToEndObjective, training_volumes
from diffcam.design.objective import DepthObjective
from diffcam.design.surfaces import Surface, height_map
from diffcam.model.camera import Camera, HeightMap

__all__ = ["DesignOptions", "Design", "HISTORY_COLUMNS", "OBJECTIVES"]

HISTORY_COLUMNS = ("loss", "smooth_max", "max_correlation", "spread")
"""The columns of `Design.history`, one row per step (the surface the step started
from): the objective's loss, and the depth terms of the same PSFs."""

OBJECTIVES = ("depth", "end_to_end")
"""`DesignOptions.objective`: depth discrimination (`diffcam.design.objective`) or the
reconstruction of training volumes (`diffcam.design.end_to_end`)."""


@dataclasses.dataclass(frozen=True)
class DesignOptions:
    """How `diffcam.design.optimise.design` optimises.

    Attributes:
        steps: Adam steps in all (a resumed design runs the ones its file lacks).
        learning_rate: Adam's step size, in the surface's unconstrained units.
        temperature: τ of the smooth maximum of the correlations (correlation units).
        sparsity_weight: weight w of the PSFs' spread ‖h‖₁/(√N‖h‖₂), unitless.
        time_budget: also stop after this many seconds (``None``: the steps alone).
        checkpoint: a design file (``.npz``) written every ``checkpoint_every`` steps
            and at the end.
        checkpoint_every: steps between checkpoints.
        resume: if the checkpoint file exists when the design starts, continue from it
            (``False``: start afresh; the file is replaced at the first checkpoint).
        progress: show a progress bar over the steps.
        objective: one of `OBJECTIVES`; ``scenes`` … ``seed`` apply to ``"end_to_end"``
            alone, the light, source and pixels (``bandwidth`` …) to both.
        scenes: training volumes (`diffcam.design.end_to_end.training_volumes`).
        solver_iterations: unrolled ADMM-TV iterations.
        photons: the captures' mean per sensor pixel, photo-electrons (shot noise).
        tau: the lateral TV weight the solver starts from, for a capture of unit L2
            norm (`diffcam.reconstruct.admm.VOLUME`'s; learnt with the surface).
        seed: the training volumes' and the noise's random seed.
        bandwidth: the light's half-width about ``camera.wavelength``, metres: three
            lines at λ − bandwidth, λ, λ + bandwidth (weights ½, 1, ½); 0 for one line.
        source_radius: radius of the disc source the PSFs are of, metres (0: a point;
            `diffcam.design.objective.source_blurred`).
        oversample: field samples per sensor pixel, per side: 1, the irradiance at each
            pixel's centre; k > 1, the field on a k× finer grid and its irradiance
            integrated over each pixel (pixel integration).
    """

    steps: int = 300
    learning_rate: float = 0.2
    temperature: float = 0.01
    sparsity_weight: float = 0.1
    time_budget: float | None = None
    checkpoint: str | None = None
    checkpoint_every: int = 50
    resume: bool = True
    progress: bool = True
    objective: str = "depth"
    scenes: int = 4
    solver_iterations: int = 30
    photons: float = 100.0
    tau: float = 1e-5
    seed: int = 0
    bandwidth: float = 0.0
    source_radius: float = 0.0
    oversample: int = 1

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise DiffcamError(f"objective must be one of {', '.join(OBJECTIVES)}, got "
                               f"{self.objective!r}.")
        for name in ("steps", "checkpoint_every", "scenes", "solver_iterations",
                     "oversample"):
            whole_number(name, getattr(self, name), 1)
        whole_number("seed", self.seed, 0)
        for name in ("learning_rate", "temperature", "photons", "tau"):
            _positive(name, getattr(self, name))
        for name in ("sparsity_weight", "bandwidth", "source_radius"):
            if not real_number(name, getattr(self, name), "a number ≥ 0") >= 0:
                raise DiffcamError(f"{name} must be ≥ 0, got {getattr(self, name)!r}.")
        if self.time_budget is not None:
            _positive("time_budget", self.time_budget)

    def problem(self) -> dict:
        """The settings that define the objective and its optimiser (a continued design
        must keep them)."""
        problem = {"objective": self.objective, "learning_rate": float(self.learning_rate),
                   "temperature": float(self.temperature),
                   "bandwidth": float(self.bandwidth),
                   "source_radius": float(self.source_radius),
                   "oversample": int(self.oversample)}
        if self.objective == "depth":
            return {**problem, "sparsity_weight": float(self.sparsity_weight)}
        return {**problem, "scenes": int(self.scenes), "photons": float(self.photons),
                "solver_iterations": int(self.solver_iterations), "tau": float(self.tau),
                "seed": int(self.seed)}


def _positive(name, value):
    v = real_number(name, value, "a finite number > 0")
    if not (math.isfinite(v) and v > 0):
        raise DiffcamError(f"{name} must be a finite number > 0, got {value!r}.")


@dataclasses.dataclass
class Design:
    """A diffuser design and how it was reached.

    Attributes:
        surface: the `diffcam.design.surfaces.SmoothSurface` or `LensletArray`.
        camera: the camera it was designed for (wavelength, z2, pitch, aperture).
        z1: the depths it was designed over, metres, (nz,).
        refractive_index: n of the diffuser material, unitless.
        options: the `DesignOptions` it ran with.
        history: (steps, 4) float64, columns `HISTORY_COLUMNS`.
        final: the objective's terms at the returned surface (``max_correlation``,
            ``smooth_max``, ``spread``, ``loss``).
        optimiser_state: the optimiser's state after the last step (a pytree).
        stop_reason: why the steps ended.
        seconds: wall-clock time of the steps run in this process and before, s.
        log_tau: end to end: log of the solver's learnt TV weight (``None`` for the
            depth objective).
    """

    surface: Surface
    camera: Camera
    z1: np.ndarray
    refractive_index: float
    options: DesignOptions
    history: np.ndarray
    final: dict
    optimiser_state: Any
    stop_reason: str
    seconds: float
    log_tau: Any = None

    @property
    def steps(self) -> int:
        """Steps taken so far."""
        return int(self.history.shape[0])

    def height_map(self) -> HeightMap:
        """The designed diffuser as a `HeightMap` (heights in metres): what
        `diffcam.model.point_spread.psf` and `diffcam.model.stack.psf_stack` take."""
        return height_map(self.surface, self.refractive_index)

    @property
    def parameters(self):
        """What the optimiser moves: the surface, or ``(surface, log_tau)`` end to end."""
        return self.surface if self.log_tau is None else (self.surface, self.log_tau)

    def with_parameters(self, parameters) -> "Design":
        """This design at other `parameters` (the structure `parameters` has)."""
        surface, log_tau = (parameters, None) if self.log_tau is None else parameters
        return dataclasses.replace(self, surface=surface, log_tau=log_tau)

    def initial_optimiser_state(self):
        """Adam's state before a first step from `parameters` (optax)."""
        return optax.adam(self.options.learning_rate).init(
            eqx.filter(self.parameters, eqx.is_array))

    def objective(self) -> DepthObjective | EndToEndObjective:
        """The objective the design minimises (its training volumes drawn from
        ``options.seed``)."""
        o = self.options
        lines = self.camera.wavelength + o.bandwidth * np.array([-1.0, 0.0, 1.0])
        spectrum = (lines, np.array([0.5, 1.0, 0.5])) if o.bandwidth > 0 else None
        if o.objective == "depth":
            return DepthObjective(self.camera, self.z1, self.refractive_index,
                                  o.temperature, o.sparsity_weight, spectrum,
                                  float(o.source_radius), int(o.oversample))
        key = jax.random.key(o.seed)
        volumes = training_volumes(key, o.scenes, self.z1, self.camera)
        noise = jax.random.normal(jax.random.fold_in(key, 1),
                                  (o.scenes, *self.camera.out_shape))
        return EndToEndObjective(self.camera, self.z1, self.refractive_index, volumes,
                                 noise, float(o.photons), int(o.solver_iterations),
                                 o.temperature, spectrum, float(o.source_radius),
                                 int(o.oversample))
