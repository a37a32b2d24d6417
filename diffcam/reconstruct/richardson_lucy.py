"""Richardson–Lucy deconvolution (paper Eq. 15), its accelerated and TV-regularised
variants, and 3-D (PSF-stack) reconstruction.

The update, for a sensor image ``b``, forward model ``A`` (`diffcam.reconstruct.operators`)
and estimate
``x``::

    x  <-  x · Aᵀ( b / (A x + eps) ) / Aᵀ1

``Aᵀ`` back-projects by ``conj(OTF)`` — correlation with the PSF, the flipped kernel
``H(-x)`` of Eq. 15 — and ``Aᵀ1`` (the sensitivity, ``sum(psf)`` inside a circular
model) keeps flux: ``sum(A x) = sum(b)`` after every step. It is the maximum-likelihood
(EM) iteration for Poisson data; it keeps ``x >= 0`` when ``b, psf, x0 >= 0`` and lowers
the I-divergence ``Σ b log(b / Ax) - b + Ax`` at every step. Scene points that no sensor
pixel sees (``Aᵀ1 <= 1e-5·max Aᵀ1``, the rim of the ``"crop"`` object grid) stay 0.
``eps`` is a fraction of ``max b``, so the estimate scales with the image whatever its
units: the solver runs on ``b / max b`` and ``psf / sum psf`` and scales the estimate
back (an absolute 1e-12 drove the estimate of an image of values ~1e-14 to zero).

``convention="skimage"`` reproduces ``skimage.restoration.richardson_lucy(image, psf,
num_iter, clip=False, filter_epsilon)``: start 0.5, no sensitivity division, the forward
convolution centred as scipy's ``"same"`` (PSF sample ``(m-1)//2`` on the axis), and
back-projection by convolution with the flipped PSF in the same centring — which for an
even-sized PSF is *not* the adjoint of the forward map but correlation about sample
``m//2``, a one-pixel shift per axis.

Variants:

* ``accelerate=True``: Biggs & Andrews (Appl. Opt. 36, 1766, 1997) vector extrapolation,
  ``y = x_k + α (x_k - x_{k-1})`` with ``α = <g_{k-1}, g_{k-2}> / <g_{k-2}, g_{k-2}>``
  clipped to ``[0, 1)``, ``g`` the change made by the last RL step; RL is applied at
  ``max(y, 0)``.
* ``tv_weight=λ > 0``: Dey et al. (Microsc. Res. Tech. 69, 260, 2006),
  ``x <- x · Aᵀ(b/Ax) / (Aᵀ1 - λ·S·div(∇x/|∇x|))`` with ``S = sum(psf)``: RL for
  I-divergence plus ``λ·S·TV(x)``. Keep ``λ`` small (1e-3 to 1e-2); the denominator is
  clamped at ``1e-3·Aᵀ1`` so ``x`` stays positive. Unlike plain RL this update is not
  guaranteed to lower its objective, and with a larger ``λ`` it does not settle: on
  random 48×56 problems the objective rose by up to 1.7e-4 of its value in one step at
  ``λ = 0.02`` and 1.5e-2 at 0.05 (never at 1e-3–1e-2), and at 0.05 float32 and float64
  runs of 100 iterations ended 7–19 % apart (24×28). A rise above 1e-4 issues a
  ``ConvergenceWarning`` (eager calls). Gradients through TV-RL are ill-conditioned from
  ``λ = 1e-2`` over tens of iterations (float32 and float64 ones disagree). A
  backtracking line search along the update (Lange, IEEE TMI 9, 439, 1990) would make
  the objective fall at every step, but at ``λ = 0.05`` it halves the step 6 times an
  iteration on average. For strong TV use `admm_tv`.
"""

from __future__ import annotations

import math
import warnings
from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.scipy.special import xlogy
from jaxtyping import ArrayLike

from diffcam.core.errors import (ConvergenceWarning, DiffcamError, ShapeError, check_finite,
                                 is_concrete, real_array, real_number)
from diffcam.core.options import Options
from diffcam.core.progress import progress_bar
from diffcam.reconstruct.checks import (as_psf_stack, batch_shape, check_image,
                                        check_iterations, check_operator, check_psf,
                                        check_tol, float_dtype)
from diffcam.reconstruct.loop import Reconstruction, iterate, relative_residual
from diffcam.reconstruct.operators import (BOUNDARIES, FieldModel, convolution_model,
                                           divergence, gradient, grid_shapes)

__all__ = ["richardson_lucy", "richardson_lucy_3d", "RichardsonLucyOptions"]

CONVENTIONS = ("adjoint", "skimage")
_SEEN = 1e-5      # sensitivity below this fraction of its maximum: the pixel is unseen
_TV_FLOOR = 1e-3  # the TV-RL denominator is clamped at this fraction of the sensitivity
_TV_SMOOTH = 1e-3  # |∇x| is smoothed by this fraction of the mean initial estimate
_RISE = 1e-4  # a TV-RL objective rising by more than this fraction in one step oscillates


class RichardsonLucyOptions(Options):
    """How [`richardson_lucy`][diffcam.reconstruct.richardson_lucy.richardson_lucy] and
    [`richardson_lucy_3d`][diffcam.reconstruct.richardson_lucy.richardson_lucy_3d] iterate.

    Attributes:
        boundary: ``"same"`` (zero-padded linear convolution), ``"circular"`` or
            ``"crop"`` (the DiffuserCam model; the estimate is on the larger object grid).
        convention: ``"adjoint"`` (true adjoint, flux-normalised) or ``"skimage"`` (bit
            for bit the scikit-image iteration; ``boundary="same"`` only).
        accelerate: Biggs–Andrews extrapolation (module docstring).
        tv_weight: λ of the Dey et al. TV-regularised update; 0 for plain RL.
        tol: stop when the objective changes by less than ``tol`` (relative) in one
            iteration; None runs all iterations and is the only setting that supports
            reverse-mode ``grad``.
        eps: added to ``A x`` before dividing, as a fraction of the image's largest
            value, so the result does not depend on the image's units (an absolute
            value, as scikit-image's, with ``convention="skimage"``).
        filter_epsilon: where ``A x + eps < filter_epsilon`` the ratio is set to 0
            (scikit-image's argument, relative like ``eps``); None or 0 disables it.
        progress: a progress bar for runs over 2 s
            ([`diffcam.core.progress`][diffcam.core.progress]).
    """

    boundary: str = "same"
    convention: str = "adjoint"
    accelerate: bool = False
    tv_weight: Any = 0.0
    tol: float | None = None
    eps: Any = 1e-12
    filter_epsilon: float | None = None
    progress: bool = True


def richardson_lucy(image: ArrayLike, psf: ArrayLike, iterations: int = 150, *,
                    init: ArrayLike | None = None,
                    options: RichardsonLucyOptions | None = None,
                    **overrides) -> Reconstruction:
    """Richardson–Lucy deconvolution of a sensor image by one PSF (paper Eq. 15).

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image, non-negative (counts, any scale;
            rounding-level negatives, ``>= -1e-5·max``, are clipped to 0).
        psf: ``(..., my, mx)`` PSF at the sensor pitch, non-negative, optical axis at
            ``(my//2, mx//2)``; ``my <= ny``, ``mx <= nx``. Leading axes of ``image`` and
            ``psf`` broadcast: one call deconvolves one image by a stack of PSFs (see
            [`focus_sweep`][diffcam.reconstruct.focus.focus_sweep]) or a stack of images by
            one PSF. Or a 2-D forward model
            ([`FieldModel`][diffcam.reconstruct.operators.FieldModel]) for the image's
            sensor: it brings its own boundary and units (the estimate is in the units
            of ``image`` over the model's), with ``convention="adjoint"``.
        iterations: iterations (static: it fixes the history length).
        init: initial estimate (object-grid shape, non-negative), default the constant
            that matches the image's flux (0.5 for ``convention="skimage"``).
        options:
            [`RichardsonLucyOptions`][diffcam.reconstruct.richardson_lucy.RichardsonLucyOptions];
            keywords named after its fields (``boundary``, ``convention``, ``accelerate``,
            ``tv_weight``, ``tol``, ``eps``, ``filter_epsilon``, ``progress``) replace them.

    Returns:
        [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction] with ``image`` of shape
        ``(..., oy, ox)``: ``(ny, nx)`` for ``"same"``/``"circular"``, the object grid of
        `diffcam.reconstruct.operators.grid_shapes` for ``"crop"``. Its values are in the
        units of ``image / sum(psf)``.

    Raises:
        DiffcamError: negative, NaN/Inf, non-numeric or all-zero inputs, inputs or an
            estimate outside the float range it computes in, ``iterations`` outside
            1 … `MAX_ITERATIONS`, or a
            convention/boundary combination that does not exist.
        ShapeError: a PSF larger than the image, or batch axes that do not broadcast.
    """
    opts = RichardsonLucyOptions.of(options, **overrides)
    return _richardson_lucy(image, psf, iterations, init, opts, volume=False)


def richardson_lucy_3d(image: ArrayLike, psf_stack: ArrayLike, iterations: int = 150, *,
                       init: ArrayLike | None = None,
                       options: RichardsonLucyOptions | None = None,
                       **overrides) -> Reconstruction:
    """Richardson–Lucy reconstruction of a volume from one sensor image.

    The model is ``b = crop(Σ_z h_z * x_z)``: every depth plane of the object is blurred
    by the PSF of its depth and the sensor sees the sum. The update is the one of
    [`richardson_lucy`][diffcam.reconstruct.richardson_lucy.richardson_lucy] with ``A`` this
    sum and ``Aᵀ`` back-projecting into every plane, so all planes are solved together.

    Input checks run when called eagerly; under ``jax.jit`` they see tracers and are skipped
    (shapes are still checked) — call once eagerly (``iterations=1`` is enough) to validate.

    Args:
        image: ``(..., ny, nx)`` sensor image, non-negative.
        psf_stack: ``(..., nz, my, mx)`` PSFs, one per depth, on one common scale (their
            relative intensities matter), or a list of ``(my, mx)`` arrays; or a 3-D
            forward model ([`FieldModel`][diffcam.reconstruct.operators.FieldModel]).
        iterations, init: as for
            [`richardson_lucy`][diffcam.reconstruct.richardson_lucy.richardson_lucy].
        options:
            [`RichardsonLucyOptions`][diffcam.reconstruct.richardson_lucy.RichardsonLucyOptions]
            (default ``boundary="crop"``, the DiffuserCam model; ``convention`` must be
            ``"adjoint"`` and ``filter_epsilon`` is not used); keywords named after its
            fields replace them.

    Returns:
        [`Reconstruction`][diffcam.reconstruct.loop.Reconstruction] whose ``image`` is the
        volume ``(..., nz, oy, ox)``.
    """
    opts = RichardsonLucyOptions.of(options or RichardsonLucyOptions(boundary="crop"),
                                    **overrides)
    if opts.convention != "adjoint" or opts.filter_epsilon:
        raise DiffcamError("richardson_lucy_3d uses the adjoint convention without a "
                           "filter_epsilon; leave both at their defaults.")
    return _richardson_lucy(image, as_psf_stack(psf_stack), iterations, init, opts,
                            volume=True)


def _richardson_lucy(image, psf, iterations, init, opts: RichardsonLucyOptions, *,
                     volume: bool) -> Reconstruction:
    """Validate, broadcast the batch axes, run the jitted solver, restore the axes."""
    boundary, convention, accelerate = opts.boundary, opts.convention, opts.accelerate
    tv_weight, tol, eps, filter_epsilon = opts.tv_weight, opts.tol, opts.eps, opts.filter_epsilon
    progress = opts.progress
    if boundary not in BOUNDARIES:
        raise DiffcamError(f"boundary must be one of {BOUNDARIES}, got {boundary!r}.")
    if convention not in CONVENTIONS:
        raise DiffcamError(f"convention must be one of {CONVENTIONS}, got {convention!r}.")
    if convention == "skimage" and boundary != "same":
        raise DiffcamError("convention='skimage' reproduces scikit-image's 'same'-size "
                           "convolution; use boundary='same' with it.")
    iterations = check_iterations(iterations)
    check_tol(tol)
    check_image(image, nonnegative=True)
    core = 3 if volume else 2
    for name, value in (("tv_weight", tv_weight), ("eps", eps)):
        if is_concrete(value) and not 0 <= real_number(name, value, "a number >= 0") \
                < math.inf:
            raise DiffcamError(f"{name} must be a finite number >= 0, got {value!r}.")
    model = check_operator(psf, jnp.shape(image), volume=volume, solver="richardson_lucy"
                           + ("_3d" if volume else ""))
    image, psf, batch, object_shape = (_model_inputs if model else _psf_inputs)(
        image, psf, opts, volume)
    dtype = image.dtype
    if init is not None:
        init = real_array("init", init)
        check_finite("init", init)
        if is_concrete(init) and float(jnp.min(init)) < 0:
            raise DiffcamError("init must be non-negative: RL keeps the sign of its start.")
        try:
            init = jnp.broadcast_to(jnp.asarray(init, dtype), batch + object_shape)
        except ValueError:
            raise ShapeError(f"init of shape {jnp.shape(init)} does not broadcast to the "
                             f"object grid {batch + object_shape}.") from None
        init = init.reshape((-1,) + object_shape)
    use_tv = not is_concrete(tv_weight) or float(tv_weight) != 0
    use_filter = filter_epsilon is not None and (not is_concrete(filter_epsilon)
                                                 or float(filter_epsilon) != 0)
    flat = lambda a, k: a.reshape((-1,) + a.shape[a.ndim - k:])  # noqa: E731
    weights = _Weights(jnp.asarray(tv_weight, dtype), jnp.asarray(eps, dtype),
                       jnp.asarray(filter_epsilon if use_filter else 0, dtype),
                       None if tol is None else jnp.asarray(tol, dtype))
    config = _Config(iterations, boundary, convention, bool(accelerate), use_tv, use_filter,
                     volume)
    with progress_bar(iterations, "Richardson–Lucy", progress):
        out = jax.block_until_ready(_rl_batched(flat(image, 2),
                                                psf if model else flat(psf, core), init,
                                                weights, config))
    if use_tv and is_concrete(out.objective):
        _warn_if_oscillating(np.asarray(out.objective, np.float64), tv_weight)
    return jax.tree.map(lambda a: a.reshape(batch + a.shape[1:]), out)


def _model_inputs(image, model, opts, volume):
    """``(image, model, batch shape, object shape)`` of a run with a forward model."""
    if opts.convention != "adjoint":
        raise DiffcamError("a forward model runs with convention='adjoint'; "
                           "convention='skimage' takes a PSF.")
    depth = model.weights.shape[1:2] if volume else ()
    image = jnp.asarray(image, float_dtype(image))
    return image, model, tuple(image.shape[:-2]), depth + model.object_shape


def _psf_inputs(image, psf, opts, volume):
    """``(image, psf, batch shape, object shape)`` of a run with a PSF (stack), checked
    and broadcast to their common batch axes."""
    core = 3 if volume else 2
    psf = check_psf(psf, jnp.shape(image), min_ndim=core)
    batch = batch_shape(jnp.shape(image), jnp.shape(psf), core)
    dtype = float_dtype(image, psf)
    if is_concrete(image, psf) and opts.convention == "adjoint":
        _check_estimate_range(image, psf, dtype)
    psf = jnp.broadcast_to(jnp.asarray(psf, dtype), batch + jnp.shape(psf)[-core:])
    image = jnp.broadcast_to(jnp.asarray(image, dtype), batch + jnp.shape(image)[-2:])
    depth = jnp.shape(psf)[-3:-2] if volume else ()
    return image, psf, batch, depth + grid_shapes(image.shape, psf.shape, opts.boundary)[0]


def _check_estimate_range(image, psf, dtype) -> None:
    """The estimate is in units of ``image / sum(psf)``: refuse a pair whose ratio
    leaves ``dtype`` (each may be within it: an image ×1e30 and a PSF ×1e-30)."""
    top = float(np.max(np.asarray(image), initial=0.0))
    psf_sum = float(np.min(np.sum(np.asarray(psf, np.float64), axis=(-2, -1))))
    info = np.finfo(dtype)
    if top / psf_sum > info.max / 1e3 or top / psf_sum < info.tiny * 1e3:
        raise DiffcamError(
            f"the estimate would be about max(image)/sum(psf) = {top / psf_sum:.3g}, "
            f"outside the range of {np.dtype(dtype).name} in which it is computed; divide "
            f"the image or the PSF by a constant first (the estimate scales with both).")


def _warn_if_oscillating(objective, tv_weight) -> None:
    """A `ConvergenceWarning` when the TV-RL objective (``(batch, iterations)``,
    NaN after an early stop) rose between two iterations by more than
    `_RISE` of its value. Plain RL lowers it at every step; TV-RL with a large
    weight oscillates and its estimate keeps changing (module docstring)."""
    with np.errstate(divide="ignore", invalid="ignore"):  # an objective of exactly 0
        rise = np.nanmax(np.diff(objective, axis=-1) / np.abs(objective[..., 1:]), initial=0)
    if rise > _RISE:
        warnings.warn(
            f"TV-regularised Richardson–Lucy did not settle: its objective rose by "
            f"{rise:.1e} of its value between two iterations, so the estimate oscillates "
            f"(tv_weight={float(tv_weight):g}). Use a smaller tv_weight (1e-3 to 1e-2), or "
            f"admm_tv for strong TV.", ConvergenceWarning, stacklevel=3)


class _Weights(NamedTuple):
    """The traced numbers of a run (arrays; ``tol`` may be None)."""

    tv_weight: Array
    eps: Array
    filter_epsilon: Array
    tol: Array | None


class _Config(NamedTuple):
    """The static settings of a run (hashable: one compilation per distinct value)."""

    iterations: int
    boundary: str
    convention: str
    accelerate: bool
    use_tv: bool
    use_filter: bool
    volume: bool


@partial(jax.jit, static_argnames=("config",))
def _rl_batched(image, psf, init, weights: _Weights, config: _Config):
    """One problem per image; ``psf`` is a batch of PSFs or one forward model."""
    axes = (0, None if isinstance(psf, FieldModel) else 0, 0)
    return jax.vmap(lambda b, h, x0: _rl_solve(b, h, x0, weights, config),
                    in_axes=axes)(image, psf, init)


def _operators(b, psf, x0, config: _Config):
    """(forward, back, sensitivity Aᵀ1, seen mask, start) of one problem."""
    sensor_shape = b.shape
    if config.convention == "skimage":
        my, mx = psf.shape[-2:]
        forward = convolution_model(psf, sensor_shape, "same",
                                    psf_centre=((my - 1) // 2, (mx - 1) // 2))
        back = convolution_model(psf, sensor_shape, "same")
        sensitivity = jnp.ones((), b.dtype)
        seen = jnp.ones((), bool)
        if x0 is None:
            x0 = jnp.full(sensor_shape, 0.5, b.dtype)
        return forward, back, sensitivity, seen, x0
    forward = psf if isinstance(psf, FieldModel) else convolution_model(
        psf, sensor_shape, config.boundary, volume=config.volume)
    sensitivity = forward.adjoint(jnp.ones(sensor_shape, b.dtype))
    seen = sensitivity > _SEEN * jnp.max(sensitivity)
    if x0 is None:
        flux = jnp.sum(b) / jnp.sum(jnp.where(seen, sensitivity, 0))
        x0 = jnp.where(seen, flux, 0).astype(b.dtype)
    return forward, forward, sensitivity, seen, x0


def _rl_solve(b, psf, x0, weights: _Weights, config: _Config) -> Reconstruction:
    """One problem: ``b (ny, nx)``, ``psf ([nz,] my, mx)``.

    With the adjoint convention it runs on ``b / max b`` and ``psf / sum psf`` and
    scales the estimate (and the objective) back: the iteration is homogeneous in both,
    and float32 products of raw values leave its range (NaN for an image ×1e30 with
    acceleration or TV, or a PSF ×1e-30). ``eps`` is then the fraction of the peak it
    is documented to be."""
    b = jnp.maximum(b, 0)  # rounding-level negatives passed validation
    b_scale = h_scale = jnp.ones((), b.dtype)
    if config.convention != "skimage":  # skimage's iteration is kept bit for bit
        b_scale = _positive(jnp.max(b))
        if not isinstance(psf, FieldModel):   # a model keeps its units
            h_scale = _positive(jnp.sum(psf))
            psf = psf / h_scale
        b = b / b_scale
        x0 = None if x0 is None else x0 * (h_scale / b_scale)
    solution = _rl_normalised(b, psf, x0, weights, config)
    return solution._replace(image=solution.image * (b_scale / h_scale),
                             objective=solution.objective * b_scale)


def _positive(scale):
    return jnp.where(scale > 0, scale, 1)


def _rl_normalised(b, psf, x0, weights: _Weights, config: _Config) -> Reconstruction:
    """`_rl_solve` on the normalised problem (``max b = 1`` unless skimage's)."""
    forward, back, sensitivity, seen, x0 = _operators(b, psf, x0, config)
    eps, filter_epsilon = weights.eps, weights.filter_epsilon
    use_tv, use_filter, accelerate = config.use_tv, config.use_filter, config.accelerate
    inv_sensitivity = jnp.where(seen, 1 / jnp.where(seen, sensitivity, 1), 0)
    if use_tv:
        psf_sum = (jnp.max(sensitivity, axis=(-2, -1), keepdims=True)
                   if isinstance(psf, FieldModel)
                   else jnp.sum(psf, axis=(-2, -1), keepdims=True))
        tv_scale = weights.tv_weight * psf_sum
        smooth = _TV_SMOOTH * jnp.mean(x0)

    def rl_step(y):
        """One multiplicative update at ``y``; returns it, the misfit and objective."""
        predicted = forward(y) + eps
        ratio = b / predicted
        if use_filter:
            ratio = jnp.where(predicted < filter_epsilon, 0, ratio)
        correction = back.adjoint(ratio)
        objective = jnp.sum(xlogy(b, b) - xlogy(b, predicted) - b + predicted)
        if use_tv:
            g = gradient(y)
            norm = jnp.sqrt(jnp.sum(g ** 2, axis=0) + smooth ** 2)
            denominator = sensitivity - tv_scale * divergence(g / norm)
            denominator = jnp.maximum(denominator, _TV_FLOOR * sensitivity)
            update = jnp.where(seen, y * correction / denominator, 0)
            objective = objective + jnp.sum(tv_scale * norm)
        else:
            update = y * correction * inv_sensitivity
        # exact RL cannot go negative; FFT rounding of a near-zero correction can
        update = jnp.maximum(update, 0)
        return update, relative_residual(predicted - eps, b), objective

    if not accelerate:
        def step(x):
            x_new, r, f = rl_step(x)
            return x_new, (r, f)
        state = x0
    else:
        def step(state):
            x, x_prev, g1, g2, k = state
            alpha = jnp.sum(g1 * g2) / jnp.maximum(jnp.sum(g2 * g2), jnp.finfo(x.dtype).tiny)
            alpha = jnp.where(k >= 2, jnp.clip(alpha, 0.0, 1.0 - 1e-6), 0.0)
            y = jnp.maximum(x + alpha * (x - x_prev), 0)
            x_new, r, f = rl_step(y)
            return (x_new, x, x_new - y, g1, k + 1), (r, f)
        zeros = jnp.zeros_like(x0)
        state = (x0, x0, zeros, zeros, jnp.asarray(0))

    state, res, obj, its, done = iterate(step, state, config.iterations, weights.tol)
    x = state if not accelerate else state[0]
    return Reconstruction(image=x, residual=res, objective=obj, iterations=its,
                          converged=done)
