"""The backend seam (``diffcam.core.backend``): its transforms are ``jnp.fft``'s, and its
scheduling aids change how XLA runs a computation, never its value: each is compared
with the plain expression it stands for, jitted, vmapped and differentiated."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core.backend import (fft2, fft_size, ifft2, irfft2, rfft2, staged,
                                  transfer_step, transfer_step_with_spectrum,
                                  separable_factor)


def _complex(rng, shape):
    return jnp.asarray(rng.normal(size=shape) + 1j * rng.normal(size=shape), jnp.complex64)


@pytest.mark.parametrize("shape", [(4, 6), (3, 5, 7), (2, 3, 8, 4)])
def test_transforms_are_numpys(shape):
    """fft2/ifft2/rfft2/irfft2 over the last two axes, batched: numpy's to float32 precision."""
    rng = np.random.default_rng(0)
    u = _complex(rng, shape)
    np.testing.assert_allclose(fft2(u), np.fft.fft2(np.asarray(u)), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(ifft2(u), np.fft.ifft2(np.asarray(u)), rtol=1e-5, atol=1e-5)
    r = jnp.real(u)
    np.testing.assert_allclose(rfft2(r), np.fft.rfft2(np.asarray(r)), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(irfft2(rfft2(r), s=shape[-2:]), r, atol=1e-5)


@pytest.mark.parametrize("shape", [(1, 8), (5, 7), (3, 4, 6), (2, 3, 9, 4)])
def test_transfer_step_is_the_plain_step(shape):
    """Odd row counts, a single row and leading batch axes: ifft2(fft2(u)·H), and the
    spectrum it reports is fft2(u)·H."""
    rng = np.random.default_rng(0)
    u, h = _complex(rng, shape), _complex(rng, shape[-2:])
    field, spectrum = jax.jit(transfer_step_with_spectrum)(u, h)
    np.testing.assert_allclose(np.asarray(spectrum), np.asarray(jnp.fft.fft2(u) * h),
                               rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(jax.jit(transfer_step)(u, h)),
                               np.asarray(jnp.fft.ifft2(jnp.fft.fft2(u) * h)), rtol=1e-5,
                               atol=1e-5)
    np.testing.assert_allclose(np.asarray(field), np.asarray(transfer_step(u, h)), atol=1e-6)


@pytest.mark.usefixtures("debug_nans")
def test_transfer_step_vmaps_and_differentiates():
    """Under vmap and grad it is the plain step too (gradient with respect to H)."""
    rng = np.random.default_rng(1)
    u, h = _complex(rng, (3, 6, 5)), _complex(rng, (6, 5))

    def loss(h, seam):
        step = transfer_step if seam else (lambda a, k: jnp.fft.ifft2(jnp.fft.fft2(a) * k))
        return jnp.sum(jnp.abs(jax.vmap(step, (0, None))(u, h)) ** 3)
    np.testing.assert_allclose(jax.grad(loss)(h, True), jax.grad(loss)(h, False), rtol=1e-4)


def test_transfer_step_derivatives_in_both_modes():
    """The row-block step's own reverse rule (the adjoint through the same row-block
    program) and forward rule, against finite differences to second order (float64)
    and against JAX's derivatives of the plain expression, in u and H, with the
    spectrum's cotangent too, batched with vmap over either argument."""
    from jax.test_util import check_grads

    rng = np.random.default_rng(2)
    with jax.enable_x64(True):
        u = jnp.asarray(rng.normal(size=(2, 5, 4)) + 1j * rng.normal(size=(2, 5, 4)))
        h = jnp.asarray(rng.normal(size=(5, 4)) + 1j * rng.normal(size=(5, 4)))
        check_grads(jax.jit(transfer_step), (u, h), order=2, modes=("fwd", "rev"))
        plain = lambda a, k: (jnp.fft.ifft2(jnp.fft.fft2(a) * k), jnp.fft.fft2(a) * k)  # noqa: E731
        cts = (jnp.conj(u) * 0.5, u + 1j)
        for got, want in zip(jax.vjp(transfer_step_with_spectrum, u, h)[1](cts),
                             jax.vjp(plain, u, h)[1](cts)):
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        tangents = (u * 1j, h * 0.3)
        for got, want in zip(jax.jvp(transfer_step_with_spectrum, (u, h), tangents)[1],
                             jax.jvp(plain, (u, h), tangents)[1]):
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
        hs = jnp.stack([h, 2 * h])
        np.testing.assert_allclose(jax.vmap(transfer_step, (None, 0))(u[0], hs),
                                   jax.vmap(plain, (None, 0))(u[0], hs)[0], rtol=1e-12,
                                   atol=1e-12)


@pytest.mark.usefixtures("debug_nans")
@pytest.mark.parametrize("n", [1, 511, 512, 513, 2000])
def test_separable_factor_equals_the_elementwise_function(n):
    """Any length, whole blocks or not: a complex chirp exp(j·z·k²), k = i − n//2, with a
    traced z (phases up to 1 rad, so float32 holds 1e-6), and its derivative in z,
    Σ k² cos(z k²) for the imaginary part."""
    def chirp(z):
        return separable_factor(lambda i: jnp.exp(1j * z * (i - n // 2) ** 2), n)
    k2 = (np.arange(n) - n // 2) ** 2.0
    z = 1e-6
    np.testing.assert_allclose(np.asarray(jax.jit(chirp)(jnp.float32(z))),
                               np.exp(1j * z * k2), atol=1e-6)
    grad = jax.grad(lambda z: jnp.sum(jnp.imag(chirp(z))))(jnp.float32(z))
    np.testing.assert_allclose(float(grad), np.sum(k2 * np.cos(z * k2)), rtol=1e-5)


@pytest.mark.usefixtures("debug_nans")
def test_staged_is_the_composition():
    x = jnp.arange(12.0).reshape(3, 4)
    f = staged(lambda a, b: a * b, lambda ab, a, b, *, power: ab ** power + a,
               static_argnames=("power",))
    np.testing.assert_allclose(f(x, 2.0, power=2), (2 * x) ** 2 + x)


def test_fft_size():
    """Even, 2^a·3^b (·5) and the least such length ≥ n."""
    assert fft_size(1536) == 1536 and fft_size(1537) == 1620 and fft_size(2047) == 2048
    assert fft_size(599) == 640
    for n in range(1, 300):
        m = fft_size(n)
        assert m >= n and m % 2 == 0
        k = m
        for p in (2, 3):
            while k % p == 0:
                k //= p
        assert k in (1, 5)
