"""The end-to-end objective: a diffuser is as good as the volumes reconstructed through it.

Training volumes ``v`` (a few point-like sources at random depths and positions) are
imaged through the diffuser's PSFs ``h_z`` (`diffcam.design.objective.recorded`: of a
point source in one line unless the objective gives a spectrum, a source disc or pixel
integration, as the depth objective does) by the 3-D model the solver assumes, with
shot noise at a stated mean photon count per sensor pixel, and reconstructed as
``diffcam reconstruct --3d`` does — the capture scaled to unit L2 norm, ``iterations``
unrolled iterations of ADMM-TV with the `VOLUME` settings
(`diffcam.reconstruct.admm.admm_tv_3d`, a ``lax.scan``, differentiable in the PSFs and
in its TV weights). The loss is the reconstruction's relative squared error after its
least-squares scale (the capture's scale is gone), one minus the squared cosine:

    b = s·A_h v + √max(s·A_h v, 1)·ε,    s = photons·N_pixels / Σv,
    x̂ = ADMM_K(b/‖b‖; h, τ),    loss = mean_scenes (1 − ⟨x̂, v⟩² / (‖x̂‖²‖v‖²)),

with ``ε`` standard normal draws fixed for the whole design (Poisson noise in its
Gaussian limit, at least one count's, so the loss is a smooth function of the
surface). The lateral TV weight ``τ = exp(log τ)`` is optimised beside the surface, the
axial one in `VOLUME`'s proportion to it: the solver's penalty is learnt with the
optics. An empty or unrelated reconstruction scores 1.

The depth-discrimination terms of the same PSFs (`diffcam.design.objective`) are
reported beside the loss, so the two objectives' designs can be compared on one scale.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.errors import DiffcamError
from diffcam.design.objective import Terms, depth_terms, recorded, spread, standardised
from diffcam.design.surfaces import Surface
from diffcam.model.camera import Camera
from diffcam.reconstruct.admm import VOLUME, admm_tv_3d
from diffcam.reconstruct.operators import convolution_model, grid_shapes

__all__ = ["EndToEndObjective", "training_volumes", "end_to_end_objective"]

SOURCE_SIGMA = 1.0
"""Gaussian radius of a training source, object-grid samples."""


class EndToEndObjective(NamedTuple):
    """What the end-to-end loss needs besides the surface and log τ.

    Attributes:
        camera: the camera the diffuser sits in (its grid is the surface's).
        z1: the depths of the training volumes' planes, metres, (nz,).
        refractive_index: n of the diffuser material, unitless.
        volumes: training volumes on the solver's object grid, (nscenes, nz, oy, ox),
            peak 1 (`training_volumes`).
        noise: the fixed standard normal draws ε, (nscenes, ny, nx) on the sensor.
        photons: the captures' mean per sensor pixel, photo-electrons (shot noise).
        iterations: unrolled ADMM-TV iterations.
        temperature: τ of the reported smooth maximum of the correlations.
        spectrum, source_radius, oversample: the light, source and pixels the PSFs are
            recorded with, as in `diffcam.design.objective.DepthObjective` (the
            captures and the solver both use these PSFs).
    """

    camera: Camera
    z1: np.ndarray
    refractive_index: float
    volumes: Array
    noise: Array
    photons: float
    iterations: int
    temperature: float = 0.01
    spectrum: tuple | None = None
    source_radius: float = 0.0
    oversample: int = 1


def training_volumes(key: Array, count: int, z1, camera: Camera,
                     sources: int = 8) -> Float[Array, "count nz oy ox"]:
    """``count`` volumes of ``sources`` point-like sources each (Gaussians of radius
    `SOURCE_SIGMA` samples, peak 1, random brightness in [0.5, 1]) at random planes of
    ``z1`` (metres, (nz,)) and random positions inside the sensor's field, on the object
    grid of the 3-D solver for ``camera`` (its ``out_shape`` sensor)."""
    if not (isinstance(count, (int, np.integer)) and count >= 1
            and isinstance(sources, (int, np.integer)) and sources >= 1):
        raise DiffcamError(f"count and sources must be whole numbers ≥ 1, got {count!r} "
                           f"and {sources!r}.")
    nz = np.shape(z1)[0]
    sensor = camera.out_shape
    (oy, ox), _ = grid_shapes(sensor, sensor, "crop")
    ky, kx, kz, kb = jax.random.split(key, 4)
    shape = (count, sources)
    y = (oy - sensor[0]) / 2 + jax.random.uniform(ky, shape) * sensor[0]
    x = (ox - sensor[1]) / 2 + jax.random.uniform(kx, shape) * sensor[1]
    plane = jax.random.randint(kz, shape, 0, nz)
    brightness = jax.random.uniform(kb, shape, minval=0.5, maxval=1.0)
    gy = jnp.exp(-(jnp.arange(oy) - y[..., None]) ** 2 / (2 * SOURCE_SIGMA ** 2))
    gx = jnp.exp(-(jnp.arange(ox) - x[..., None]) ** 2 / (2 * SOURCE_SIGMA ** 2))
    on_plane = jax.nn.one_hot(plane, nz) * brightness[..., None]
    volumes = jnp.einsum("csz,csy,csx->czyx", on_plane, gy, gx)
    return volumes / jnp.max(volumes, axis=(1, 2, 3), keepdims=True)


def end_to_end_objective(parameters: tuple[Surface, Array],
                         objective: EndToEndObjective) -> tuple[Array, Terms]:
    """``(loss, Terms)`` at ``parameters = (surface, log_tau)``: the reconstruction's
    relative squared error after its least-squares scale (module docstring), and the
    depth terms of the same PSFs
    (``Terms.smooth``, ``max_correlation``, ``spread``). Differentiable in the surface's
    array leaves and in ``log_tau``."""
    surface, log_tau = parameters
    h = recorded(lambda p: p, surface, objective)
    model = convolution_model(h, objective.camera.out_shape, "crop", volume=True)
    clean = jax.vmap(model)(objective.volumes)
    pixels = np.prod(objective.camera.out_shape)
    axes = (1, 2, 3)
    counts = clean * (objective.photons * pixels
                      / jnp.sum(objective.volumes, axis=axes))[:, None, None]
    captures = counts + jnp.sqrt(jnp.maximum(counts, 1)) * objective.noise
    unit = captures / jnp.linalg.norm(captures, axis=(-2, -1), keepdims=True)
    tau = jnp.exp(log_tau)
    recon = admm_tv_3d(unit, h, objective.iterations, VOLUME, progress=False, tau=tau,
                       tau_axial=tau * (VOLUME.tau_axial / VOLUME.tau)).image
    overlap = jnp.sum(recon * objective.volumes, axis=axes)
    cosine2 = overlap ** 2 / (jnp.sum(recon ** 2, axis=axes)
                              * jnp.sum(objective.volumes ** 2, axis=axes) + 1e-30)
    return jnp.mean(1 - cosine2), depth_terms(standardised(h), spread(h),
                                              objective.temperature)
