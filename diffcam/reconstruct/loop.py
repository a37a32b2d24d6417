"""The result every solver returns, and the jitted iteration driver they share."""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jax import Array, lax

from diffcam.core.progress import tick

__all__ = ["Reconstruction", "iterate", "relative_residual"]


class Reconstruction(NamedTuple):
    """What a solver returns (a pytree: it passes through ``jit`` and ``vmap``).

    Attributes:
        image: ``(..., [nz,] oy, ox)`` estimated object on the model's object grid, in
            the units of ``image / sum(psf)``.
        residual: ``(..., iterations)`` relative data misfit ``||A x_k - b|| / ||b||`` of
            the estimate entering iteration ``k``; NaN after an early stop.
        objective: ``(..., iterations)`` the quantity the solver minimises, at the same
            estimates (Richardson–Lucy: the I-divergence ``Σ b log(b/Ax) - b + Ax``
            plus its regulariser; ADMM: ``½||A x - b||² + tau·TV``; Wiener: the
            Tikhonov functional); NaN after an early stop.
        iterations: ``(...)`` int, iterations run.
        converged: ``(...)`` bool, True if the tolerance stopped the loop.
        final_residual: ``(...)`` relative data misfit of ``image`` itself (the
            estimate returned), or ``None`` where the solver returns the last iterate
            of ``residual``'s history.
        final_objective: ``(...)`` the objective of ``image``, or ``None`` likewise.
        split_gap: ``(...)`` ADMM: ``||v - w|| / ||w||`` between the iterate and the
            returned non-negative split variable (0 when the split has closed);
            ``None`` for other solvers.
        background: ``(..., ny, nx)`` ADMM with a background term: the smooth
            background fitted on the sensor, in the image's units; ``None`` otherwise.
    """

    image: Array
    residual: Array
    objective: Array
    iterations: Array
    converged: Array
    final_residual: Array | None = None
    final_objective: Array | None = None
    split_gap: Array | None = None
    background: Array | None = None


def relative_residual(predicted: Array, data: Array) -> Array:
    """``||predicted - data|| / ||data||`` over the last two axes (0/0 gives 0)."""
    num = jnp.sqrt(jnp.sum((predicted - data) ** 2, axis=(-2, -1)))
    den = jnp.sqrt(jnp.sum(data ** 2, axis=(-2, -1)))
    return jnp.where(den > 0, num / jnp.where(den > 0, den, 1), num)


def iterate(step: Callable, state, iterations: int, tol: Array | None):
    """Run ``state, (residual, objective) = step(state)`` up to ``iterations`` times.

    With ``tol=None`` this is a ``lax.scan`` (reverse-mode differentiable); otherwise a
    ``lax.while_loop`` that stops once ``|f_k - f_{k-1}| <= tol·|f_{k-1}|`` for the
    objective ``f`` (forward-mode only). Returns ``(state, residual, objective,
    iterations, converged)`` with NaN-filled histories of length ``iterations``. Each
    iteration ticks the open progress bar (`diffcam.core.progress`).
    """
    if tol is None:
        def scan_step(s, k):
            tick(k)
            return step(s)
        state, (res, obj) = lax.scan(scan_step, state, jnp.arange(iterations))
        return state, res, obj, jnp.asarray(iterations), jnp.asarray(False)

    def body(carry):
        state, k, res, obj, _ = carry
        tick(k)
        state, (r, f) = step(state)
        f_prev = obj[jnp.maximum(k - 1, 0)]
        done = (k > 0) & (jnp.abs(f - f_prev) <= tol * jnp.abs(f_prev))
        return state, k + 1, res.at[k].set(r), obj.at[k].set(f), done

    def cond(carry):
        _, k, _, _, done = carry
        return (k < iterations) & ~done

    _, (r0, f0) = jax.eval_shape(step, state)
    nan = jnp.full((iterations,), jnp.nan, dtype=f0.dtype)
    carry = (state, jnp.asarray(0), nan.astype(r0.dtype), nan, jnp.asarray(False))
    state, k, res, obj, done = lax.while_loop(cond, body, carry)
    return state, res, obj, k, done
