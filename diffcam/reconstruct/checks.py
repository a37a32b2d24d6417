"""Checks that every solver runs on its concrete arguments before tracing."""

from __future__ import annotations

import numbers
import warnings
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from diffcam.core.errors import (DiffcamError, ShapeError, check_field, is_concrete,
                                 real_array)
from diffcam.io import BackgroundWarning
from diffcam.reconstruct.operators import FieldModel

_ROUNDING = 1e-5  # negatives this small (relative to max|image|) are rounding, not data

MAX_ITERATIONS = 100_000
"""Most iterations a solver accepts (Richardson–Lucy settles in 50–300, ADMM in
100–1000): a mistyped count (``10**9``) is refused before its history, which holds
two numbers per iteration and image, is allocated. Raise it for the session by
assigning to ``diffcam.reconstruct.checks.MAX_ITERATIONS``."""

__all__ = ["as_psf_stack", "check_operator", "check_psf", "check_image", "check_scale",
           "check_iterations",
           "check_tol",
           "batch_shape", "float_dtype", "MAX_ITERATIONS"]


def as_psf_stack(psfs: Any) -> Any:
    """A PSF stack ``(nz, my, mx)`` from an array or a sequence of ``(my, mx)`` arrays."""
    if isinstance(psfs, (list, tuple)):
        if len(psfs) == 0:
            raise ShapeError("the PSF stack is empty; give one (my, mx) PSF per depth.")
        shapes = {np.shape(p) for p in psfs}
        if len(shapes) != 1:
            raise ShapeError(
                f"the PSFs of a stack must all have one shape, got {sorted(shapes)}; "
                f"crop or pad them to a common (my, mx) first (diffcam.core.grid.crop_to).")
        return jnp.stack([jnp.asarray(p) for p in psfs])
    return psfs


def check_operator(model: Any, image_shape: Sequence[int], *, volume: bool | None = None,
                   boundaries: Sequence[str] | None = None, solver: str = "the solver") -> bool:
    """True if ``model`` is a forward model (`
    FieldModel`) given in place of a PSF, after checking it against the sensor image
    (and, if given, its dimensionality and boundary); False for a PSF array."""
    if not isinstance(model, FieldModel):
        return False
    if tuple(image_shape[-2:]) != model.sensor_shape:
        raise ShapeError(f"the image {tuple(image_shape[-2:])} is not the model's sensor "
                         f"{model.sensor_shape}; build the model with "
                         f"field_model(psf, image.shape[-2:]).")
    if volume is not None and model.volume != volume:
        raise DiffcamError(f"{solver} needs a {'3-D' if volume else '2-D'} model, got a "
                           f"{'3-D' if model.volume else '2-D'} one; use the "
                           f"{'2-D' if model.volume else '3-D'} solver.")
    if boundaries is not None and model.boundary not in boundaries:
        raise DiffcamError(f"{solver} supports models with boundary in {tuple(boundaries)}, "
                           f"got {model.boundary!r}; build the model with one of them.")
    return True


def check_psf(psf: Any, image_shape: Sequence[int], *, min_ndim: int = 2) -> Any:
    """Shape, finiteness, sign and sum of a PSF (or stack) against the sensor image.

    Returns the PSF, with negatives down to ``-1e-5·max(psf)`` (the rounding left by a
    background subtraction or an FFT) clipped to 0 and reported by one
    `diffcam.io.BackgroundWarning`; deeper negatives raise.
    """
    real_array("psf", psf)
    check_field(psf, "psf")
    shape = np.shape(psf)
    if len(shape) < min_ndim:
        raise ShapeError(
            f"psf must have at least {min_ndim} axes "
            f"({'(..., nz, my, mx): one PSF per depth' if min_ndim == 3 else '(..., my, mx)'}), "
            f"got shape {shape}.")
    if shape[-2] > image_shape[-2] or shape[-1] > image_shape[-1]:
        raise ShapeError(
            f"psf {shape[-2:]} is larger than the image {tuple(image_shape[-2:])}; crop the "
            f"PSF to at most the image size around its centre "
            f"(diffcam.core.grid.crop_to(psf, image.shape)) or capture a larger image.")
    if not is_concrete(psf):
        return psf
    p = np.asarray(psf, dtype=np.float64)
    _check_range("psf", p, float_dtype(psf))
    if p.min() < -_ROUNDING * p.max():
        raise DiffcamError(
            f"psf has {int((p < 0).sum())} negative value(s) (min {p.min():.3g}, max "
            f"{p.max():.3g}); a PSF is an intensity: subtract the background with "
            f"diffcam.io.subtract_background (which clips small negatives) or "
            f"np.clip(psf, 0, None).")
    sums = p.sum(axis=(-2, -1))
    if np.any(sums <= 0):
        raise DiffcamError(
            f"psf sums to zero in {int((sums <= 0).sum())} slice(s); every PSF needs some "
            f"light: check the file and the background subtraction.")
    if p.min() >= 0:
        return psf
    warnings.warn(f"psf: {int((p < 0).sum())} negative value(s) down to {p.min():.3g} "
                  f"(rounding: at most {_ROUNDING:g} of the peak) clipped to 0.",
                  BackgroundWarning, stacklevel=4)
    return jnp.maximum(jnp.asarray(psf), 0)


def check_image(image: Any, *, nonnegative: bool) -> None:
    """Shape and finiteness of the sensor image; its sign if the solver needs it.

    With ``nonnegative``, negatives down to ``-1e-5·max|image|`` pass (the rounding of an
    FFT-simulated image; the solver clips them); deeper ones raise, and so does an image
    (or a slice of a batch) without light.
    """
    real_array("image", image)
    check_field(image, "image")
    if is_concrete(image):
        _check_range("image", np.asarray(image), float_dtype(image))
    if nonnegative and is_concrete(image):
        a = np.asarray(image)
        lo = float(np.min(a))
        if lo < -_ROUNDING * float(np.max(np.abs(a))):
            raise DiffcamError(
                f"image has negative values (min {lo:.3g}); Richardson–Lucy needs "
                f"non-negative counts: subtract the background with "
                f"diffcam.io.subtract_background (clips small negatives) or use admm_tv.")
        dark = int(np.sum(np.max(a.reshape((-1,) + a.shape[-2:]), axis=(-2, -1)) <= 0))
        if dark:
            raise DiffcamError(
                f"image has no light ({dark} of its {a.size // (a.shape[-2] * a.shape[-1])} "
                f"image(s) are all zeros after clipping rounding-level negatives): there is "
                f"nothing to deconvolve; check the capture and the background subtraction.")


def _check_range(name: str, a: np.ndarray, dtype) -> None:
    """The peak of ``a`` is a normal number of the solver's ``dtype`` (float32 unless
    x64 is on): a smaller one is flushed to zero on the CPU, a larger one is Inf."""
    info = np.finfo(dtype)
    peak = float(np.max(np.abs(a), initial=0.0))
    if 0 < peak < info.tiny or peak > info.max:
        raise DiffcamError(
            f"{name} peaks at {peak:.3g}, outside the range of {np.dtype(dtype).name} "
            f"({info.tiny:.2g} to {info.max:.2g}), in which the solver computes; divide it "
            f"by a constant first (the solvers' results scale with the image and "
            f"inversely with the PSF), or enable jax_enable_x64.")


def check_scale(image, psf, dtype) -> None:
    """Every image (of a batch) holds light, and the estimate's scale
    ``||image|| / ||psf||`` (norms in float64) is a normal number of the solver's
    ``dtype``."""
    a = np.asarray(image, np.float64)
    norms = np.linalg.norm(a.reshape((-1, a.shape[-2] * a.shape[-1])), axis=1)
    if not norms.all():
        raise DiffcamError(f"image is all zeros ({int(np.sum(norms == 0))} of its "
                           f"{norms.size} image(s)): there is nothing to reconstruct; check "
                           f"the capture and the background subtraction.")
    image_norm = float(np.linalg.norm(norms))
    ratio = image_norm / float(np.linalg.norm(np.asarray(psf, np.float64)))
    info = np.finfo(dtype)
    if not float(info.tiny) < ratio < float(info.max):
        raise DiffcamError(
            f"the estimate's scale ||image|| / ||psf|| = {ratio:.3g} is outside the range "
            f"of {np.dtype(dtype).name} ({info.tiny:.2g} to {info.max:.2g}); divide the "
            f"image or multiply the PSF by a constant first (the estimate scales with "
            f"image / psf).")


def check_iterations(iterations: Any, name: str = "iterations") -> int:
    """``iterations`` (or the count called ``name``) as a positive Python int, at most
    `MAX_ITERATIONS` (it fixes the history length: static); a bool is no count."""
    if isinstance(iterations, jax.core.Tracer) or not isinstance(iterations, numbers.Integral) \
            or isinstance(iterations, (bool, np.bool_)):
        raise DiffcamError(
            f"{name} must be a Python int (it is static under jit), got {iterations!r}.")
    if iterations <= 0:
        raise DiffcamError(f"{name} must be >= 1, got {iterations}; 50–300 is typical.")
    if iterations > MAX_ITERATIONS:
        raise DiffcamError(
            f"{name} = {iterations} is above the limit of {MAX_ITERATIONS} "
            f"(diffcam.reconstruct.checks.MAX_ITERATIONS); 50–300 is typical: pass tol= to "
            f"stop early, or raise the limit.")
    return int(iterations)


def check_tol(tol: Any) -> None:
    """``tol`` is None or a finite number >= 0."""
    if tol is None or not is_concrete(tol):
        return
    t = float(tol)
    if not np.isfinite(t) or t < 0:
        raise DiffcamError(f"tol must be None or a number >= 0 (e.g. 1e-4), got {tol!r}.")


def batch_shape(image_shape: Sequence[int], psf_shape: Sequence[int],
                psf_core_ndim: int) -> tuple[int, ...]:
    """Broadcast leading (batch) axes of image ``(..., ny, nx)`` and PSF."""
    a, b = tuple(image_shape[:-2]), tuple(psf_shape[:len(psf_shape) - psf_core_ndim])
    try:
        return tuple(np.broadcast_shapes(a, b))
    except ValueError:
        raise ShapeError(
            f"the leading (batch) axes of image {tuple(image_shape)} and psf "
            f"{tuple(psf_shape)} do not broadcast ({a} vs {b}); give one PSF per image, "
            f"or one PSF for all.") from None


def float_dtype(*arrays: Any):
    """The float dtype of a computation: float32 unless x64 is on and inputs are float64."""
    dtypes = [np.asarray(a).dtype if not hasattr(a, "dtype") else a.dtype for a in arrays]
    return jax.dtypes.canonicalize_dtype(np.result_type(*dtypes, np.float32))
