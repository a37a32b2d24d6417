"""The paper's simulated calibration (Section 3.1): the cameraman diffuser and its exact
near/far intensities (:func:`diffcam.calibrate.near_far.calibration_intensities`)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import ShapeError
from diffcam.calibrate.near_far import CalibrationGeometry, calibration_intensities

__all__ = ["cameraman_phase", "PaperSimulation",
           "paper_simulation"]


def cameraman_phase(size: int = 512) -> Float[Array, "size size"]:
    """The paper's simulated diffuser (Section 3.1): scikit-image's 512×512 "cameraman"
    scaled linearly to [−π, π] radians; other sizes are area-resampled first."""
    import skimage.data
    import skimage.transform
    img = skimage.data.camera().astype(np.float64)
    if size != img.shape[0]:
        img = skimage.transform.resize(img, (size, size), anti_aliasing=True)
    theta = (img - img.min()) / (img.max() - img.min()) * 2 * np.pi - np.pi
    return jnp.asarray(theta, jnp.float32)


# The paper's simulation (Section 3.1; docs/design.md, "The paper's simulation"), SI units
PAPER_DX = 5e-6
PAPER_WAVELENGTH = 532e-9
PAPER_FOCAL_LENGTH = 5e-2
PAPER_APERTURE_RADIUS = 1.2e-3


class PaperSimulation(NamedTuple):
    """The paper's Fig. 3 problem on an N×N grid (see :func:`paper_simulation`)."""

    phase: Float[Array, "n n"]      # θd on the grid (radians; 0 outside the diffuser)
    aperture: Float[Array, "n n"]   # circular aperture C
    geometry: CalibrationGeometry
    near: Float[Array, "n n"]       # exact near-field intensity (at the diffuser)
    far: Float[Array, "n n"]        # exact far-field intensity (Fourier-lens pitch)
    truth: Float[Array, "size size"]  # θd on the diffuser crop, for scoring
    mask: Float[Array, "size size"]   # the scored central square (300/512 of the side)


def paper_simulation(n: int = 1024, size: int = 512, phase=None) -> PaperSimulation:
    """Paper Section 3.1: a ``size``² cameraman diffuser at 5 µm, aperture radius 1.2 mm,
    f = 5 cm, λ = 532 nm, embedded in an ``n``² grid; ``size < 512`` shrinks the diffuser,
    the aperture and the scored square (300 px at 512) in proportion, for fast tests.
    ``phase`` (``size``², radians) replaces the cameraman, e.g. a random diffuser (Fig. 6)."""
    from diffcam.core.grid import pad_to
    from diffcam.optics.elements import circular_aperture
    dx = PAPER_DX
    geometry = CalibrationGeometry(dx=dx, wavelength=PAPER_WAVELENGTH,
                                   focal_length=PAPER_FOCAL_LENGTH)
    truth = cameraman_phase(size) if phase is None else jnp.asarray(phase, jnp.float32)
    if truth.shape != (size, size):
        raise ShapeError(f"phase must be {size}×{size}, got {truth.shape}.")
    aperture = circular_aperture((n, n), dx, PAPER_APERTURE_RADIUS * size / 512)
    phase = pad_to(truth, (n, n))
    near, far = calibration_intensities(phase, aperture, geometry)
    scored = round(300 * size / 512)
    lo = (size - scored) // 2
    mask = jnp.zeros((size, size), jnp.float32).at[lo:lo + scored, lo:lo + scored].set(1.0)
    return PaperSimulation(phase, aperture, geometry, near, far, truth, mask)
