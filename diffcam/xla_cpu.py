"""Scheduling aids for XLA on CPU: where the compiler's defaults cost FFT-sized time.

Each function returns the value its arguments describe; what changes is how XLA fuses
and threads the work. None changes a result, each is differentiable and ``vmap``-able,
and each was measured (``benchmarks/RESULTS.md``).

**The FFT rule.** XLA splits a large elementwise fusion over its intra-op thread pool
and goes on with the program on whichever pool thread finishes last; an FFT that then
starts on a pool thread runs about as fast as on one core. Measured at 2048²: an FFT
pair with any product before or between the two FFTs costs 1.25–2× the pair alone,
while on one core (``taskset``) the same programs cost the same, and the three pieces
as three jitted calls cost 1.08×. So in a jitted program every FFT must come before
the first large elementwise fusion, which is what these do:

- :func:`update_rows_for_fft`: a product written in place, which XLA never splits;
- :func:`vector`: the 1-D factors of separable kernels, computed in a loop, which XLA
  neither splits nor fuses into the N² product that consumes them;
- where a product must come first (the field a PSF's FFT starts from), the caller runs
  it as a jitted call of its own (:func:`diffcam.camera.depth_inputs`).

:func:`fusion_barrier` is about fusion alone: a value computed once, not once per
consumer.
"""

from __future__ import annotations

from typing import Callable

import jax.numpy as jnp
from jax import Array, lax

__all__ = ["update_rows_for_fft", "vector", "fusion_barrier"]


def update_rows_for_fft(x: Array, f: Callable[[Array, slice], Array]) -> Array:
    """``x`` with its rows ``a:b`` (axis −2) replaced by ``f(x[..., a:b, :], slice(a, b))``.

    For the product between the two FFTs of a propagation step:
    ``ifft2(update_rows_for_fft(fft2(u), lambda b, s: b * H[s]))``. Written as
    ``ifft2(fft2(u) * H)``, the inverse FFT loses its threads (the module's FFT rule): a
    Fresnel step cost 1.25–1.45× the bare FFT pair at 2048² and 4096². Written in two
    row blocks as in-place dynamic-update-slices, which XLA never splits over threads, it
    costs 0.99–1.03×. ``f`` must keep the block's shape and dtype; ``x`` must not be
    needed afterwards (XLA would copy it first).
    """
    ny = x.shape[-2]
    edges = [0, ny // 2, ny]
    start = (0,) * (x.ndim - 2)
    for a, b in zip(edges[:-1], edges[1:]):
        x = lax.dynamic_update_slice(x, f(x[..., a:b, :], slice(a, b)).astype(x.dtype),
                                     start + (a, 0))
    return x


def vector(f: Callable[[Array], Array], n: int, block: int = 512) -> Array:
    """``f(i)`` for the int32 indices ``i = 0 … n − 1``, ``f`` elementwise: shape ``(n,)``.

    For the 1-D factors of separable kernels (chirps), computed block by block inside a
    loop. XLA cannot fuse through a loop, so the sin/cos are evaluated n times and not
    once per sample of the N² product that consumes them (left to fusion, a Fresnel
    step cost 1.3× an FFT pair instead of 1.03×). And XLA does not split loop bodies over
    threads, as it does with 1-D fusions from about 2048 samples on, so an FFT after them
    keeps its threads (the module's FFT rule).
    """
    def one_block(b):
        return f(b * block + lax.iota(jnp.int32, block))
    return lax.map(one_block, jnp.arange(-(-n // block), dtype=jnp.int32)).reshape(-1)[:n]


def fusion_barrier(x: Array, token: Array) -> Array:
    """``x`` unchanged, but materialised. XLA's CPU fusion otherwise copies the gathers
    that produce a sampled PSF into each of its consumers (the normalising sum, the
    divide, the spectrum's running sum) and evaluates them once per consumer: 23× an FFT
    pair per PSF at 1024² instead of 1.4×. A conditional on a runtime-true ``token > 0``
    (for example a pixel pitch) is a boundary fusion cannot cross."""
    return lax.cond(token > 0, lambda a: a, lambda a: -a, x)
