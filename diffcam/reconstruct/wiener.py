"""Wiener (Tikhonov) deconvolution: one FFT division, the fast linear baseline."""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike

from diffcam.core.backend import irfft2, rfft2

from diffcam.core.errors import DiffcamError, is_concrete
from diffcam.core.grid import crop_to, pad_to
from diffcam.reconstruct.checks import batch_shape, check_image, check_psf, float_dtype
from diffcam.reconstruct.loop import Reconstruction, relative_residual
from diffcam.reconstruct.operators import BOUNDARIES, convolution_model

__all__ = ["wiener"]

_AXES = (-2, -1)


def wiener(image: ArrayLike, psf: ArrayLike, regularization: float = 1e-3, *,
           boundary: str = "circular") -> Reconstruction:
    """Tikhonov-regularised inverse filter ``X = conj(H) B / (|H|² + λ)``.

    **The PSF is normalised to unit sum** (each one, over its last two axes) before its
    transfer function ``H`` is built, so ``H(0) = 1``: the estimate is in the image's
    units (for ``"circular"`` its sum is about the image's), and multiplying the PSF by
    any positive constant leaves the result unchanged. A measured PSF in counts can be
    passed as it is.

    With ``λ = regularization · max|H|²`` (dimensionless ``regularization``), this is the
    exact minimiser of ``||h ⊛ x - b||² + λ||x||²``, ``h = psf / sum(psf)``, for
    ``boundary="circular"``. For ``"same"`` and ``"crop"`` the image is zero-padded to
    the model's FFT grid and the same division applied there: the circulant
    approximation of those models (fast, but it rings at the borders), cropped to the
    model's object grid.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image, finite.
        psf: ``(..., my, mx)`` PSF, finite, non-negative, not all zero, at most the
            image size; its scale does not matter.
        regularization: λ relative to ``max|H|²``, finite and > 0 (a noise-to-signal
            power ratio).
        boundary: ``"circular"``, ``"same"`` or ``"crop"``.

    Returns:
        [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction] with one-entry
        histories: the relative misfit of the estimate under the chosen model (with the
        normalised PSF), and the Tikhonov functional. The estimate is linear in the image
        and can be negative.

    Raises:
        DiffcamError: NaN/Inf in ``image``, ``psf`` or ``regularization`` (named), a
            negative or all-zero PSF, a bad ``boundary``; ``ShapeError`` for shapes.
    """
    if boundary not in BOUNDARIES:
        raise DiffcamError(f"boundary must be one of {BOUNDARIES}, got {boundary!r}.")
    check_image(image, nonnegative=False)
    psf = check_psf(psf, jnp.shape(image))
    if np.ndim(regularization) != 0:
        raise DiffcamError(f"regularization must be one number, got shape "
                           f"{np.shape(regularization)}.")
    if is_concrete(regularization):
        try:
            reg = float(regularization)
        except (TypeError, ValueError):
            reg = math.nan
        if not (math.isfinite(reg) and reg > 0):
            raise DiffcamError(f"regularization must be a finite number > 0 (e.g. 1e-3), "
                               f"got {regularization!r}.")
    batch = batch_shape(jnp.shape(image), jnp.shape(psf), 2)
    dtype = float_dtype(image, psf)
    image = jnp.broadcast_to(jnp.asarray(image, dtype), batch + jnp.shape(image)[-2:])
    psf = jnp.broadcast_to(jnp.asarray(psf, dtype), batch + jnp.shape(psf)[-2:])
    return _wiener(image, psf, jnp.asarray(regularization, dtype), boundary=boundary)


@partial(jax.jit, static_argnames=("boundary",))
def _wiener(b, psf, regularization, *, boundary):
    psf = psf / jnp.sum(psf, axis=_AXES, keepdims=True)  # H(0) = 1: the PSF's scale drops out
    model = convolution_model(psf, b.shape, boundary)
    power = jnp.real(model.otf * jnp.conj(model.otf))
    lam = regularization * jnp.max(power, axis=_AXES, keepdims=True)
    spectrum = rfft2(pad_to(b, model.fft_shape))
    estimate = irfft2(jnp.conj(model.otf) * spectrum / (power + lam), s=model.fft_shape)
    estimate = crop_to(estimate, model.object_shape)
    predicted = model(estimate)
    objective = (jnp.sum((predicted - b) ** 2, axis=_AXES)
                 + lam[..., 0, 0] * jnp.sum(estimate ** 2, axis=_AXES))
    batch = b.shape[:-2]
    return Reconstruction(image=estimate,
                          residual=relative_residual(predicted, b)[..., None],
                          objective=objective[..., None],
                          iterations=jnp.ones(batch, int), converged=jnp.ones(batch, bool))
