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
           "paper_simulation", "measured_stack_simulation"]


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


def measured_stack_simulation(n_planes: int = 12, *, grid: int = 768, dx: float = 1e-6,
                              binning: int = 4, photons: float = 150.0, dark: float = 5.0,
                              seed: int = 3, noise: bool = True
                              ) -> tuple[np.ndarray, np.ndarray]:
    """A PSF stack as a camera would measure it, made by a higher-fidelity model than
    the stack model that fits it (:func:`diffcam.calibrate.fit_stack`: monochromatic,
    thin phase, 2× oversampled): a ``grid``² field at ``dx`` (m) behind a random 30 µm
    diffuser (1.5° deflection, aperture radius 0.2·grid·dx), z2 = 0.6 mm, three
    wavelengths (515/532/549 nm, weights ½/1/½), z1 from 2 to 10 mm equally spaced in
    1/z1, integrated over ``binning``×``binning`` pixels, Poisson noise at a peak of
    ``photons`` and a dark level of ``dark`` counts (``noise=False``: the expected counts,
    the truth the noisy planes scatter about).

    Returns:
        (float32 counts (n_planes, grid/(2·binning), grid/(2·binning)), z1 in m).
    """
    import jax

    from diffcam.model import Camera
    from diffcam.model.camera import random_diffuser
    from diffcam.model.sensor import bin_pixels
    from diffcam.model.stack import psf_stack

    camera = Camera(wavelength=532e-9, z2=0.6e-3, dx=dx, aperture_radius=0.2 * grid * dx,
                    shape=(grid, grid), pad=26, crop=(grid // 2, grid // 2))
    phase = random_diffuser(jax.random.key(seed), (grid, grid), dx, 532e-9,
                            feature_size=30e-6, deflection=np.deg2rad(1.5))
    z1 = 1e-3 / np.linspace(1 / 2, 1 / 10, n_planes)
    spectrum = (np.array([515e-9, 532e-9, 549e-9]), np.array([0.5, 1.0, 0.5]))
    stack = psf_stack(phase, camera, z1, spectrum=spectrum, progress=False)
    pixels = np.asarray(bin_pixels(stack, dx, binning * dx))
    pixels = pixels / pixels.max() * photons
    if noise:
        pixels = np.random.default_rng(0).poisson(pixels)
    counts = pixels.astype(np.float32) + dark
    return counts, z1
