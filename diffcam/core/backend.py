"""The one seam between the physics and the FFT backend.

Every transform in diffcam goes through :func:`fft2`, :func:`ifft2`, :func:`rfft2` and
:func:`irfft2` (over the last two axes, batched over leading ones), and every
propagation step through :func:`transfer_step`. Today they are XLA's FFT (``jnp.fft``);
a faster CPU library can replace them here without touching a line of physics.

What is also here, and only here, are the scheduling aids that XLA's CPU backend needs.
None changes a result; each is differentiable and ``vmap``-able, and each is justified
by a benchmark (``benchmarks/RESULTS.md``); on other backends they reduce to the plain
expression.

**The FFT rule (CPU).** XLA splits a large elementwise fusion over its intra-op thread
pool and goes on with the program on whichever pool thread finishes last; an FFT that
then starts on a pool thread runs about as fast as on one core. Measured at 2048²: an
FFT pair with any product before or between the two FFTs costs 1.25–2× the pair alone,
while on one core (``taskset``) the same programs cost the same. So on CPU:

- :func:`transfer_step` writes the product between the two FFTs in place, in row
  blocks, which XLA never splits (a Fresnel step: 1.25–1.45× → 0.99–1.03× the pair);
- :func:`vector` computes the 1-D factors of separable kernels in a loop, which XLA
  neither splits nor fuses into the N² product that consumes them;
- :func:`staged` runs a computation whose FFT follows a large product as two jitted
  calls, so the FFT starts a call of its own;
- :func:`materialise` computes a value once instead of once per consumer (XLA's
  fusion copied the gathers of a sampled PSF into each consumer: 23× an FFT pair per
  PSF at 1024² instead of 1.4×).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
from jax import Array, lax

__all__ = ["fft2", "ifft2", "rfft2", "irfft2", "fft_size", "transfer_step",
           "transfer_step_with_spectrum", "vector",
           "staged", "materialise", "on_cpu"]

_AXES = (-2, -1)


def on_cpu() -> bool:
    """True when JAX's default backend is the CPU (the scheduling aids apply)."""
    return jax.default_backend() == "cpu"


def fft2(u: Array, norm: str | None = None) -> Array:
    """2-D DFT over the last two axes (``numpy.fft.fft2`` conventions)."""
    return jnp.fft.fft2(u, axes=_AXES, norm=norm)


def ifft2(u: Array, norm: str | None = None) -> Array:
    """Inverse of :func:`fft2` (``1/(ny·nx)`` unless ``norm`` says otherwise)."""
    return jnp.fft.ifft2(u, axes=_AXES, norm=norm)


def rfft2(u: Array, s=None) -> Array:
    """2-D DFT of a real array over the last two axes, half spectrum along the last."""
    return jnp.fft.rfft2(u, s=s, axes=_AXES)


def irfft2(u: Array, s=None) -> Array:
    """Inverse of :func:`rfft2` onto the real shape ``s``."""
    return jnp.fft.irfft2(u, s=s, axes=_AXES)


def fft_size(n: int) -> int:
    """Smallest even length ``>= n`` whose factors are 2, 3 and at most one 5: the one
    rule for every padded FFT grid in diffcam.

    XLA's CPU FFT is fast on 2^a·3^b and 2^a·3^b·5 lengths; lengths with 5² or larger
    primes measured up to 2x slower here (1600 and 2000 against 1536 and 2048).
    """
    m = max(2, int(n) + (int(n) % 2))
    while True:
        k = m
        for p in (2, 3):
            while k % p == 0:
                k //= p
        if k in (1, 5):
            return m
        m += 2


def transfer_step(u: Array, H: Array) -> Array:
    """``ifft2(fft2(u) · H)``: one propagation step with a transfer function ``H`` that
    broadcasts against the spectrum (prebuilt, or the outer product of two 1-D factors).

    On CPU the product is written over the spectrum in two row blocks as in-place
    dynamic-update-slices, which keeps the inverse FFT multi-threaded (module docstring).
    """
    return transfer_step_with_spectrum(u, H)[0]


def transfer_step_with_spectrum(u: Array, H: Array) -> tuple[Array, Array]:
    """:func:`transfer_step` and the spectrum ``fft2(u) · H`` it went through: for a
    caller that donates both field-sized arrays back as the next call's buffers, so
    that no fresh, page-faulted buffer is allocated per call (:mod:`diffcam.model.stack`)."""
    u_hat = fft2(u)
    if not on_cpu():
        spectrum = u_hat * H
        return ifft2(spectrum), spectrum
    u_hat = jnp.broadcast_to(u_hat, jnp.broadcast_shapes(u_hat.shape, H.shape))
    ny = u_hat.shape[-2]
    start = (0,) * (u_hat.ndim - 2)
    for a, b in ((0, ny // 2), (ny // 2, ny)):
        block = u_hat[..., a:b, :] * H[..., a:b, :]
        u_hat = lax.dynamic_update_slice(u_hat, block.astype(u_hat.dtype), start + (a, 0))
    return ifft2(u_hat), u_hat


def vector(f: Callable[[Array], Array], n: int, block: int = 512) -> Array:
    """``f(i)`` for the int32 indices ``i = 0 … n − 1``, ``f`` elementwise: shape ``(n,)``.

    For the 1-D factors of separable kernels (chirps). On CPU they are computed block by
    block inside a loop, which XLA neither fuses into the N² product that consumes them
    (it would evaluate the sin/cos once per sample: a Fresnel step 1.3× an FFT pair
    instead of 1.03×) nor splits over threads (module docstring).
    """
    if not on_cpu():
        return f(lax.iota(jnp.int32, n))

    def one_block(b):
        return f(b * block + lax.iota(jnp.int32, block))
    return lax.map(one_block, jnp.arange(-(-n // block), dtype=jnp.int32)).reshape(-1)[:n]


def materialise(x: Array, token: Array) -> Array:
    """``x``, computed once rather than once per consumer.

    On CPU, a conditional on a runtime-true ``token > 0`` (a pixel pitch, say: a traced
    value XLA cannot fold) is a boundary XLA's fusion cannot cross. Its never-taken
    branch returns ``-x`` only because XLA deletes a conditional whose branches are the
    same; ``lax.optimization_barrier`` is removed before fusion too. Measured on the
    scaling-theorem PSF stack at 1024²: 35–37 ms per PSF with this conditional, 46–51 ms
    with identical branches, with the optimisation barrier, or with nothing.
    Elsewhere ``x`` itself.
    """
    if not on_cpu():
        return x
    return lax.cond(token > 0, lambda a: a, lambda a: -a, x)


def staged(first: Callable, second: Callable, static_argnames=()) -> Callable:
    """``second(first(*args), *args)`` as one callable that is jitted once per shape.

    On CPU the two halves run as two jitted calls, so that ``second``'s FFTs start a
    program of their own (the FFT rule); elsewhere as one. ``static_argnames`` name
    keyword arguments of ``second`` that fix shapes or code paths.
    """
    if not on_cpu():
        return jax.jit(lambda *a, **k: second(first(*a), *a, **k),
                       static_argnames=static_argnames)
    first_j = jax.jit(first)
    second_j = jax.jit(second, static_argnames=static_argnames)
    return lambda *a, **k: second_j(first_j(*a), *a, **k)
