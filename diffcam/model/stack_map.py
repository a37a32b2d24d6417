"""PSF stacks inside a traced program: a function of every depth's PSF, a chunk of
depths at a time, differentiable with working memory flat in the number of depths.

- `psf_map` — ``fn(PSF(z), x)`` for every depth, stacked: any transformation
  (``jit``, ``vmap``, forward and reverse mode); in reverse mode each chunk's PSFs are
  recomputed (``jax.checkpoint``), so a gradient costs about three forward passes.
- `psf_loss` — the sum over depths of a scalar ``fn(PSF(z), x)``, differentiated by
  computing each chunk's gradient beside its value in one pass (the loss is a sum, so
  its cotangent is one number for every depth), about two forward passes.

Both compute the diffuser's field (its FFT on the scaling path) once for all depths;
`diffcam.model.stack.psf_stack` is the host-side stack (sharded, streamed, saved).
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array, lax
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Float

from diffcam.core.errors import DiffcamError
from diffcam.model.camera import Camera, real_dtype
from diffcam.model.point_spread import (depth_list, diffuser_fields, items_per_chunk,
                                        on_axis_arguments, source_psfs)

__all__ = ["psf_map", "psf_loss"]


def _stack_inputs(fn, phase, camera, z1, spectrum, batch_size):
    """Checks, then ``(prepared, wavelengths, weights, z1, positions, batch_size)``: the
    diffuser's fields and what every depth's PSF is computed from."""
    z1 = depth_list(z1)
    if z1.size == 0:
        raise DiffcamError("the depth list z1 is empty; give at least one depth in metres.")
    if not callable(fn):
        raise DiffcamError(f"fn must be a function of a PSF (and an x of xs), got {fn!r:.60}.")
    wavelengths, weights, z1, positions = on_axis_arguments(phase, camera, z1, spectrum)
    if batch_size is None:
        batch_size = items_per_chunk(camera, wavelengths.shape[0])
    if isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer)) \
            or batch_size < 1:
        raise DiffcamError(f"batch_size must be a positive int, got {batch_size!r}.")
    prepared = diffuser_fields(phase, camera, wavelengths)
    return prepared, wavelengths, weights, z1, positions, min(int(batch_size), z1.shape[0])


def psf_map(fn: Callable, phase, camera: Camera, z1, xs=None, *, spectrum=None,
            normalise: bool = True, batch_size: int | None = None):
    """``fn(PSF(z), x)`` for every depth ``z`` of ``z1`` (and ``x`` of ``xs``), a chunk of
    depths at a time: the differentiable PSF stack.

    Pure and traceable (``jax.jit``, ``jax.grad``, ``jax.jvp``, ``jax.vmap``), unlike
    `diffcam.model.stack.psf_stack`, which runs on the host. The depths go
    through a ``lax.map`` of ``batch_size`` depths a step, the diffuser's field (its
    FFT on the scaling path) computed once for all of them; in reverse mode each chunk's
    PSFs are recomputed (``jax.checkpoint``) rather than kept, so a gradient's working
    memory is one chunk's whatever the number of depths (``python -m
    benchmarks.bench_peers``: 32 and 256 depths at 1024²). Reduce inside ``fn`` (a
    per-depth loss, a correlation with a measured plane): what ``fn`` returns is kept
    for every depth. For a loss summed over depths, `psf_loss` computes the same
    gradient in about two thirds of the time.

    Args:
        fn: ``fn(psf)`` (``xs`` is ``None``) or ``fn(psf, x)``; ``psf`` is the
            ``camera.out_shape`` PSF of one depth; returns a pytree of arrays.
        phase, camera, spectrum, normalise: as in `diffcam.model.point_spread.psf`; the
            source is on the axis (an off-axis or knowingly undersampled source:
            ``jax.lax.map`` over ``psf`` with its keywords).
        z1: depths, metres, shape (nz,) (> 0).
        xs: a pytree of arrays with leading axis nz (a measured plane per depth, a
            weight), or ``None``.
        batch_size: depths per chunk; default about 2**20 field samples (one depth at
            1024²), as `psf_stack`.

    Returns:
        ``fn``'s outputs stacked over depth (leading axis nz).
    """
    prepared, wavelengths, weights, z1, positions, batch = _stack_inputs(
        fn, phase, camera, z1, spectrum, batch_size)

    @jax.checkpoint
    def step(item):
        z, x = item
        h = source_psfs(prepared, camera, wavelengths, weights, z, positions, normalise)[0]
        return fn(h) if xs is None else fn(h, x)
    return lax.map(step, (z1, xs), batch_size=batch)


def psf_loss(fn: Callable, phase, camera: Camera, z1, xs=None, *, spectrum=None,
             normalise: bool = True, batch_size: int | None = None) -> Float[Array, ""]:
    """``Σ_z fn(PSF(z), x)`` over the depths ``z`` of ``z1`` (and ``x`` of ``xs``): a
    scalar loss over a PSF stack whose gradient costs about two forward passes, in one
    chunk's working memory whatever the number of depths.

    Differentiated, each chunk's contribution to the gradient is computed right after
    its value, in the same pass, and summed as the chunks go: the loss is a sum, so
    every depth's cotangent is the loss's own, one number. Nothing per depth is kept or
    recomputed (`psf_map`'s gradient recomputes every chunk: three passes). Evaluated
    without differentiation it is one pass. The derivative is a ``jax.custom_jvp``
    whose rule computes that gradient: reverse mode (``jax.grad``) multiplies it by the
    loss's cotangent, forward mode (``jax.jvp``) returns its product with the tangent,
    at the cost of the gradient with respect to whatever the tangent moves.

    Args:
        fn: ``fn(psf)`` (``xs`` is ``None``) or ``fn(psf, x)`` returning a real scalar;
            ``psf`` is the ``camera.out_shape`` PSF of one depth. Arrays it closes
            over are differentiated too (``jax.closure_convert``).
        phase, camera, spectrum, normalise: as in `diffcam.model.point_spread.psf`
            (on-axis source).
        z1: depths, metres, shape (nz,) (> 0).
        xs: a pytree of arrays with leading axis nz, or ``None``.
        batch_size: depths per chunk, as in `psf_map`.

    Returns:
        The loss, a real scalar; differentiable (both modes) in ``phase``, the camera's
        traced fields, ``z1``, the spectrum, ``xs`` and what ``fn`` closes over.

    Raises:
        DiffcamError: as `psf_map`, and ``fn`` not returning one real number.
    """
    prepared, wavelengths, weights, z1, positions, batch = _stack_inputs(
        fn, phase, camera, z1, spectrum, batch_size)
    x0 = None if xs is None else jax.tree_util.tree_map(lambda a: a[0], xs)
    h0 = jnp.zeros(camera.out_shape, real_dtype(camera))
    out = jax.eval_shape(lambda h, x: fn(h) if xs is None else fn(h, x), h0, x0)
    if not (isinstance(out, jax.ShapeDtypeStruct) and out.shape == ()
            and jnp.issubdtype(out.dtype, jnp.floating)):
        raise DiffcamError(f"psf_loss sums a real number per depth: fn returned {out}; "
                           f"reduce inside fn (e.g. jnp.sum), or use psf_map for "
                           f"per-depth arrays.")
    per_depth, consts = jax.closure_convert(
        lambda h, x: fn(h) if xs is None else fn(h, x), h0, x0)
    shared, fixed = eqx.partition((prepared, camera, wavelengths, weights, consts),
                                  eqx.is_inexact_array)
    xs_free, xs_fixed = eqx.partition(xs, eqx.is_inexact_array)
    return _summed((per_depth, normalise, batch, out.dtype), shared, z1, xs_free,
                   (fixed, positions), xs_fixed)


def _depth_loss(per_depth, normalise, shared, z, x, fixed):
    """One depth's term of `psf_loss` (``fixed``: the non-differentiable parts and the
    source's position)."""
    fixed, positions = fixed
    prepared, camera, wavelengths, weights, consts = eqx.combine(shared, fixed)
    h = source_psfs(prepared, camera, wavelengths, weights, z, positions, normalise)[0]
    return per_depth(h, x, *consts)


def _chunk_loss(per_depth, normalise, shared, zs, xs_free, fixed, xs_fixed):
    """The loss of a chunk of depths (leading axis of ``zs`` and the ``xs`` parts)."""
    x = eqx.combine(xs_free, xs_fixed)
    terms = jax.vmap(lambda z, xi: _depth_loss(per_depth, normalise, shared, z, xi, fixed))
    return jnp.sum(terms(zs, x))


def _chunks(tree, start, stop, size):
    """Depths ``start:stop`` of every leaf, as ``(chunks, size, ...)``."""
    return jax.tree_util.tree_map(
        lambda a: a[start:stop].reshape((-1, size) + a.shape[1:]), tree)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def _summed(how, shared, z1, xs_free, fixed, xs_fixed):
    """`psf_loss`'s value: the chunks' losses, summed. ``how``: ``(per_depth,
    normalise, batch, dtype)``."""
    per_depth, normalise, batch, _ = how

    def step(item):
        zs, xf, xx = item
        return _chunk_loss(per_depth, normalise, shared, zs, xf, fixed, xx)
    nz = z1.shape[0]
    full = nz - nz % batch
    items = (z1, xs_free, xs_fixed)
    total = jnp.sum(lax.map(step, _chunks(items, 0, full, batch)))
    if full < nz:
        total = total + step(jax.tree_util.tree_map(lambda a: a[full:], items))
    return total


def _value_and_gradients(how, perturbed, shared, per_item, fixed, xs_fixed):
    """The loss and, chunk by chunk in the same pass, its gradient with respect to the
    ``perturbed`` leaves of ``shared`` and of ``per_item = (z1, xs_free)`` (the others:
    ``None``): summed over the chunks for what every depth shares, per depth for ``z1``
    and ``xs``."""
    per_depth, normalise, batch, dtype = how
    shared_live, shared_dead = eqx.partition(shared, perturbed[0])
    items_live, items_dead = eqx.partition(per_item, perturbed[1])

    def chunk_loss(shared_live, chunk_live, chunk_dead, xx):
        zs, xf = eqx.combine(chunk_live, chunk_dead)
        return _chunk_loss(per_depth, normalise, eqx.combine(shared_live, shared_dead), zs,
                           xf, fixed, xx)
    grad = jax.value_and_grad(chunk_loss, argnums=(0, 1))

    def step(carry, item):
        total, g_shared = carry
        value, (gs, g_items) = grad(shared_live, *item)
        return (total + value, jax.tree_util.tree_map(jnp.add, g_shared, gs)), g_items

    nz = per_item[0].shape[0]
    full = nz - nz % batch
    items = (items_live, items_dead, xs_fixed)
    start = (jnp.zeros((), dtype), jax.tree_util.tree_map(jnp.zeros_like, shared_live))
    carry, g_items = lax.scan(step, start, _chunks(items, 0, full, batch))
    g_items = jax.tree_util.tree_map(lambda a: a.reshape((full,) + a.shape[2:]), g_items)
    if full < nz:
        carry, tail = step(carry, jax.tree_util.tree_map(lambda a: a[full:], items))
        g_items = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), g_items, tail)
    total, g_shared = carry
    return total, (g_shared, g_items)


def _summed_jvp(how, primals, tangents):
    """The loss and its directional derivative ``Σ Re(Σ g·u̇)`` over the inputs ``u``
    whose tangent ``u̇`` is not a symbolic zero, ``g`` JAX's gradient in ``u`` (for a
    complex ``u``, ∂/∂Re u − i ∂/∂Im u). The gradient comes from
    `_value_and_gradients`, whose scan holds no tangent: reverse mode keeps the
    gradient alone and multiplies it by the loss's cotangent."""
    shared, z1, xs_free, fixed, xs_fixed = primals
    moving = (tangents[0], tangents[1:3])
    perturbed = jax.tree_util.tree_map(lambda t: not isinstance(t, SymbolicZero), moving)
    value, gradients = _value_and_gradients(how, perturbed, shared, (z1, xs_free), fixed,
                                            xs_fixed)
    pairs = zip(jax.tree_util.tree_leaves(gradients),
                jax.tree_util.tree_leaves(eqx.filter(moving, perturbed)))
    tangent = sum((jnp.real(jnp.sum(g * t)).astype(value.dtype) for g, t in pairs),
                  jnp.zeros((), value.dtype))
    return value, tangent


_summed.defjvp(_summed_jvp, symbolic_zeros=True)
