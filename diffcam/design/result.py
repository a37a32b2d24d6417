"""What a diffuser design is made of: its settings (`DesignOptions`) and its outcome
(`Design`: the surface, the camera and depths it was designed for, the objective's
history and the optimiser's state, so it can be continued)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from diffcam.core.errors import DiffcamError, real_number, whole_number
from diffcam.design.objective import DepthObjective
from diffcam.design.surfaces import Surface, height_map
from diffcam.model.camera import Camera, HeightMap

__all__ = ["DesignOptions", "Design", "HISTORY_COLUMNS"]

HISTORY_COLUMNS = ("loss", "smooth_max", "max_correlation", "spread")
"""The columns of `Design.history`, one row per step (the surface the step started
from)."""


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

    def __post_init__(self):
        whole_number("steps", self.steps, 1)
        whole_number("checkpoint_every", self.checkpoint_every, 1)
        for name in ("learning_rate", "temperature"):
            _positive(name, getattr(self, name))
        if not real_number("sparsity_weight", self.sparsity_weight, "a number ≥ 0") >= 0:
            raise DiffcamError(f"sparsity_weight must be ≥ 0, got {self.sparsity_weight!r}.")
        if self.time_budget is not None:
            _positive("time_budget", self.time_budget)

    def problem(self) -> dict:
        """The settings that define the objective and its optimiser (a continued design
        must keep them)."""
        return {"learning_rate": float(self.learning_rate),
                "temperature": float(self.temperature),
                "sparsity_weight": float(self.sparsity_weight)}


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

    @property
    def steps(self) -> int:
        """Steps taken so far."""
        return int(self.history.shape[0])

    def height_map(self) -> HeightMap:
        """The designed diffuser as a `HeightMap` (heights in metres): what
        `diffcam.model.point_spread.psf` and `diffcam.model.stack.psf_stack` take."""
        return height_map(self.surface, self.refractive_index)

    def objective(self) -> DepthObjective:
        """The objective the design minimised."""
        o = self.options
        return DepthObjective(self.camera, self.z1, self.refractive_index, o.temperature,
                              o.sparsity_weight)
