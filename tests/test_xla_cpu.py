"""The scheduling aids of ``diffcam.xla_cpu`` change how XLA runs a computation, never its
value: each is compared with the plain expression it stands for, jitted, vmapped and
differentiated."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.xla_cpu import fusion_barrier, update_rows_for_fft, vector


@pytest.mark.parametrize("shape", [(1, 8), (5, 7), (3, 4, 6), (2, 3, 9, 4)])
def test_update_rows_equals_the_product(shape):
    """Odd row counts, a single row and leading batch axes: the blocks cover every row
    once."""
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.normal(size=shape) + 1j * rng.normal(size=shape), jnp.complex64)
    h = jnp.asarray(rng.normal(size=shape[-2:]) + 1j * rng.normal(size=shape[-2:]),
                    jnp.complex64)
    got = jax.jit(lambda x: update_rows_for_fft(x, lambda b, s: b * h[s]))(x)
    np.testing.assert_allclose(np.asarray(got), np.asarray(x * h), rtol=1e-6)


def test_update_rows_vmaps_and_differentiates():
    """Under vmap and grad it is the product too (gradient with respect to the kernel)."""
    rng = np.random.default_rng(1)
    x = jnp.asarray(rng.normal(size=(3, 6, 5)), jnp.float32)
    h = jnp.asarray(rng.normal(size=(6, 5)), jnp.float32)
    def loss(h, rows):
        f = (lambda u: update_rows_for_fft(u, lambda b, s: b * h[s])) if rows else (
            lambda u: u * h)
        return jnp.sum(jax.vmap(f)(x) ** 3)
    np.testing.assert_allclose(jax.grad(loss)(h, True), jax.grad(loss)(h, False),
                               rtol=1e-5)


@pytest.mark.parametrize("n", [1, 511, 512, 513, 2000])
def test_vector_equals_the_elementwise_function(n):
    """Any length, whole blocks or not: a complex chirp exp(j·z·k²), k = i − n//2, with a
    traced z (phases up to 1 rad, so float32 holds 1e-6), and its derivative in z,
    Σ k² cos(z k²) for the imaginary part."""
    def chirp(z):
        return vector(lambda i: jnp.exp(1j * z * (i - n // 2) ** 2), n)
    k2 = (np.arange(n) - n // 2) ** 2.0
    z = 1e-6
    np.testing.assert_allclose(np.asarray(jax.jit(chirp)(jnp.float32(z))),
                               np.exp(1j * z * k2), atol=1e-6)
    grad = jax.grad(lambda z: jnp.sum(jnp.imag(chirp(z))))(jnp.float32(z))
    np.testing.assert_allclose(float(grad), np.sum(k2 * np.cos(z * k2)), rtol=1e-5)


def test_fusion_barrier_is_the_identity():
    x = jnp.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(jax.jit(fusion_barrier)(x, jnp.float32(5e-6)), x)
