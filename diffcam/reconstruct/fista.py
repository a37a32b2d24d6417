"""Non-negative least squares by FISTA (Beck & Teboulle, SIAM J. Imaging Sci. 2, 183,
2009): the plain deconvolution, and the accelerated projected-gradient loop that fits
any linear model ``A x ≈ b`` with ``x >= 0``.

Each iteration takes a gradient step ``y - Aᵀ(A y - b) / L`` from the extrapolated point
``y``, projects it onto ``x >= 0`` and extrapolates with Nesterov's weights. With
``L >= ||A||²`` the objective ``½||A x - b||²`` falls as ``O(1/k²)``. No regulariser:
the iteration count is the only one (early stopping), which makes it the floor that
regularised solvers are measured against.
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike

from diffcam.core.progress import progress_bar
from diffcam.core.errors import DiffcamError, is_concrete
from diffcam.reconstruct.checks import (batch_shape, check_image, check_iterations,
                                        check_operator, check_psf, check_scale, check_tol,
                                        float_dtype)
from diffcam.reconstruct.loop import Reconstruction, iterate
from diffcam.reconstruct.operators import BOUNDARIES, convolution_model, operator_norm

__all__ = ["fista", "nonnegative_least_squares"]

_AXES = (-2, -1)


def nonnegative_least_squares(forward: Callable, adjoint: Callable, data, x0,
                              lipschitz, iterations: int, tol=None):
    """FISTA for ``min_x ½||forward(x) - data||²`` subject to ``x >= 0``.

    Args:
        forward, adjoint: the linear map ``A`` and its exact adjoint ``Aᵀ`` (pure, jit-able).
        data: ``b``, any shape ``forward`` returns.
        x0: start, the shape of ``x`` (non-negative).
        lipschitz: ``L >= ||A||²`` (the step is ``1/L``); a scalar or broadcasting with
            ``x`` when ``A`` is block-diagonal.
        iterations: iterations (static).
        tol: relative change of the objective that stops the loop, or ``None``.

    Returns:
        ``(x, residual, objective, iterations, converged)`` as `iterate` gives them;
        the residual is ``||A y - b|| / ||b||`` at the extrapolated point of each step.
    """
    def step(state):
        x, y, t = state
        misfit = forward(y) - data
        x_new = jnp.maximum(y - adjoint(misfit) / lipschitz, 0)
        t_new = (1 + jnp.sqrt(1 + 4 * t * t)) / 2
        y_new = x_new + ((t - 1) / t_new) * (x_new - x)
        residual = jnp.linalg.norm(misfit) / jnp.linalg.norm(data)
        return (x_new, y_new, t_new), (residual, 0.5 * jnp.sum(misfit ** 2))

    state = (x0, x0, jnp.asarray(1.0, x0.dtype))
    (x, _, _), res, obj, its, done = iterate(step, state, iterations, tol)
    return x, res, obj, its, done


def fista(image: ArrayLike, psf: ArrayLike, iterations: int = 200, *,
          boundary: str = "crop", tol: float | None = None,
          progress: bool = True) -> Reconstruction:
    """Non-negative least-squares deconvolution, ``min ½||A x - b||²`` with ``x >= 0``.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped.

    Args:
        image: ``(..., ny, nx)`` sensor image (background subtracted).
        psf: ``(..., my, mx)`` PSF, non-negative, at most the image size; leading axes
            broadcast with the image's (one PSF per colour channel, or one shared). Or a
            forward model (`FieldModel`, 2-D or
            3-D) for the image's sensor: it brings its own boundary, and its step is
            ``1 / (1.1 ||A||²)`` with ``||A||`` from 30 power iterations.
        iterations: iterations (static); the only regularisation.
        boundary: ``"crop"`` (DiffuserCam model; the estimate is on the larger object
            grid), ``"same"`` or ``"circular"`` (`diffcam.reconstruct.operators`).
        tol: stop early when the objective changes by less than ``tol`` (relative).
        progress: a progress bar for runs over 2 s.

    Returns:
        [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction], ``image`` in the units
        of ``image / psf`` (so ``A x ≈ b`` with the PSF as given).
    """
    if boundary not in BOUNDARIES:
        raise DiffcamError(f"boundary must be one of {BOUNDARIES}, got {boundary!r}.")
    iterations = check_iterations(iterations)
    check_tol(tol)
    check_image(image, nonnegative=False)
    if check_operator(psf, jnp.shape(image), solver="fista"):
        return _fista_model(image, psf, iterations, tol, progress)
    check_psf(psf, jnp.shape(image))
    batch = batch_shape(jnp.shape(image), jnp.shape(psf), 2)
    dtype = float_dtype(image, psf)
    if is_concrete(image, psf):
        check_scale(image, psf, dtype)
    image = jnp.broadcast_to(jnp.asarray(image, dtype), batch + jnp.shape(image)[-2:])
    psf = jnp.broadcast_to(jnp.asarray(psf, dtype), batch + jnp.shape(psf)[-2:])
    flat = lambda a: a.reshape((-1,) + a.shape[-2:])  # noqa: E731
    with progress_bar(iterations, "FISTA", progress):
        out = jax.block_until_ready(_fista_batched(
            flat(image), flat(psf), None if tol is None else jnp.asarray(tol, dtype),
            iterations=iterations, boundary=boundary))
    return jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), out)


_POWER_ITERATIONS = 30
_STEP_MARGIN = 1.1   # the power iteration's ||A||² approaches from below


def _fista_model(image, model, iterations, tol, progress) -> Reconstruction:
    """FISTA with a forward model in place of a PSF; leading image axes are a batch."""
    dtype = float_dtype(image)
    if is_concrete(image, model):
        check_scale(image, model.centre_psf(), dtype)
    image = jnp.asarray(image, dtype)
    flat = image.reshape((-1,) + image.shape[-2:])
    with progress_bar(iterations, "FISTA", progress):
        out = jax.block_until_ready(_fista_model_batched(
            flat, model, None if tol is None else jnp.asarray(tol, dtype),
            iterations=iterations))
    return jax.tree.map(lambda a: a.reshape(image.shape[:-2] + a.shape[1:]), out)


@partial(jax.jit, static_argnames=("iterations",))
def _fista_model_batched(image, model, tol, *, iterations):
    depth = model.weights.shape[1:2] if model.volume else ()
    x0 = jnp.zeros(depth + model.object_shape, image.dtype)
    lipschitz = _STEP_MARGIN * operator_norm(model, model.adjoint, x0 + 1,
                                             _POWER_ITERATIONS) ** 2

    def one(b):
        x, res, obj, its, done = nonnegative_least_squares(
            model, model.adjoint, b, x0, lipschitz, iterations, tol)
        return Reconstruction(image=x, residual=res, objective=obj, iterations=its,
                              converged=done)
    return jax.vmap(one)(image)


@partial(jax.jit, static_argnames=("iterations", "boundary"))
def _fista_batched(image, psf, tol, *, iterations, boundary):
    def one(b, h):
        model = convolution_model(h, b.shape, boundary)
        lipschitz = jnp.max(jnp.abs(model.otf) ** 2)
        x0 = jnp.zeros(model.object_shape, b.dtype)
        x, res, obj, its, done = nonnegative_least_squares(
            model, model.adjoint, b, x0, lipschitz, iterations, tol)
        return Reconstruction(image=x, residual=res, objective=obj, iterations=its,
                              converged=done)
    return jax.vmap(one)(image, psf)

