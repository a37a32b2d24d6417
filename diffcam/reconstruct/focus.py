"""Depth search: which plane of a PSF stack explains a sensor image best.

`focus_sweep` deconvolves the image once per PSF (one batched, jitted solver call)
and ranks the planes by a focus measure:

* ``"misfit"`` (default): the relative data misfit ``||A x − b|| / ||b||`` the solver
  reaches with that plane's PSF. The PSF of the scene's depth can explain the
  measurement; a PSF of another depth leaves the difference between the two caustics
  unexplained. On the shipped 3-D DiffuserCam capture (a tilted USAF target, 44 planes)
  the ADMM-TV misfit has one shallow minimum at plane 28 (0.0389 against 0.045 at
  plane 0), inside the depth range the 3-D reconstruction gives the target.
* ``"sharpness"``: `sharpness`, the ratio of the mean square to the squared mean
  of each reconstruction. It is right on synthetic stacks but depends on the solver on
  that capture: of Richardson–Lucy reconstructions (30 iterations) it falls steadily
  from plane 0 to plane 43 and picks plane 0, the end of the stack; of ADMM-TV ones it
  peaks at plane 32.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jax import Array
from jaxtyping import ArrayLike, Float

from diffcam.core.errors import DiffcamError, ShapeError, real_array
from diffcam.reconstruct.admm import admm_tv, safe_norm
from diffcam.reconstruct.checks import as_psf_stack
from diffcam.reconstruct.loop import Reconstruction
from diffcam.reconstruct.richardson_lucy import richardson_lucy

__all__ = ["focus_sweep", "FocusSweep", "sharpness", "MEASURES"]

MEASURES = ("misfit", "sharpness")


class FocusSweep(NamedTuple):
    """Result of [`focus_sweep`][diffcam.reconstruct.focus.focus_sweep].

    Attributes:
        reconstruction: [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction] with a
            depth axis before the two space axes, ``(..., nz, oy, ox)``.
        misfit: ``(..., nz)`` the relative data misfit reached with each plane's PSF.
        sharpness: ``(..., nz)`` [`sharpness`][diffcam.reconstruct.focus.sharpness] of each
            plane's reconstruction.
        best: ``(...)`` int, the plane the chosen measure ranks first (least misfit, or
            sharpest).
    """

    reconstruction: Reconstruction
    misfit: Array
    sharpness: Array
    best: Array


def sharpness(estimate: Float[Array, "... ny nx"]) -> Float[Array, "..."]:
    """Focus measure of an estimate: ``Σ x² · N / (Σ x)²`` over the last two axes.

    The ratio of the mean square to the squared mean (1 for a flat image, ``N`` for a
    single bright pixel). Scale-invariant. See the module docstring for where it fails.
    """
    n = estimate.shape[-1] * estimate.shape[-2]
    total = jnp.sum(estimate, axis=(-2, -1))
    return n * jnp.sum(estimate ** 2, axis=(-2, -1)) / jnp.where(total != 0, total, 1) ** 2


def focus_sweep(image: ArrayLike, psf_stack: ArrayLike, iterations: int = 100, *,
                method: str = "admm", measure: str = "misfit", **options) -> FocusSweep:
    """Deconvolve one sensor image with every PSF of a stack; pick the best plane.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image, dark level subtracted.
        psf_stack: ``(nz, my, mx)`` PSFs over depth (or a list of ``(my, mx)`` arrays).
        iterations: solver iterations per plane.
        method: ``"admm"`` ([`admm_tv`][diffcam.reconstruct.admm.admm_tv] on the image
            scaled to unit L2 norm, the scale its default ``tau`` is meant for; each PSF is
            normalised inside) or ``"rl"`` (`richardson_lucy`).
        measure: ``"misfit"`` or ``"sharpness"`` (module docstring).
        **options: passed to the solver (``tau=``, ``boundary=``, ``progress=``, ...).

    Returns:
        [`FocusSweep`][diffcam.reconstruct.focus.FocusSweep].

    Raises:
        DiffcamError: an unknown method or measure; the solver's own input errors.
        ShapeError: ``psf_stack`` is not a stack.
    """
    if method not in ("admm", "rl"):
        raise DiffcamError(f"method must be 'admm' or 'rl', got {method!r}.")
    if measure not in MEASURES:
        raise DiffcamError(f"measure must be one of {MEASURES}, got {measure!r}.")
    psf_stack = as_psf_stack(psf_stack)
    if jnp.ndim(psf_stack) < 3:
        raise ShapeError(f"psf_stack must be (nz, my, mx), got shape {jnp.shape(psf_stack)}; "
                         f"for one PSF call a solver directly.")
    image = jnp.asarray(real_array("image", image))[..., None, :, :]
    if method == "admm":
        norm = safe_norm(image, axis=(-2, -1), keepdims=True)
        rec = admm_tv(image / jnp.where(norm > 0, norm, 1), psf_stack, iterations, **options)
    else:
        rec = richardson_lucy(image, psf_stack, iterations, **options)
    misfit = jnp.nanmin(rec.residual, axis=-1)
    sharp = sharpness(rec.image)
    best = jnp.argmin(misfit, axis=-1) if measure == "misfit" else jnp.argmax(sharp, axis=-1)
    return FocusSweep(reconstruction=rec, misfit=misfit, sharpness=sharp, best=best)
