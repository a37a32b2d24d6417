"""The cubic B-spline sampling primitive (diffcam.model.spline): values of the B-spline,
its transpose (a primitive of gathers) against JAX's own derivatives of the plain
gathers, and the NaN it returns when its promise on the sample points is broken."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.model import Camera, psf
from diffcam.model.spline import bspline, cubic_sample, spline_sample

RNG = np.random.default_rng(0)


def _complex(shape):
    return jnp.asarray(RNG.standard_normal(shape) + 1j * RNG.standard_normal(shape))


def test_bspline_is_the_cubic_b_spline():
    """At the knots β₃ is 0, 1/6, 4/6, 1/6, 0; shifted copies sum to 1 and their
    derivatives to 0 at any offset; the slope at ±1 is ∓1/2; the pieces meet with two
    continuous derivatives; the 4th derivative is 0; the derivatives are JAX's own."""
    np.testing.assert_allclose(bspline(jnp.arange(-2.0, 3.0)), [0, 1 / 6, 4 / 6, 1 / 6, 0],
                               atol=1e-7)
    u = jnp.linspace(0, 0.999, 17)[:, None] + 1 - jnp.arange(4)
    np.testing.assert_allclose(jnp.sum(bspline(u), -1), 1, rtol=1e-6)
    for order in (1, 2, 3):
        np.testing.assert_allclose(jnp.sum(bspline(u, order), -1), 0, atol=1e-5)
    np.testing.assert_allclose(bspline(jnp.array([-1.0, 1.0]), 1), [0.5, -0.5], atol=1e-7)
    for order in (0, 1, 2):
        for knot in (1.0, 2.0):
            below, above = bspline(jnp.array([knot - 1e-4, knot + 1e-4]), order)
            assert abs(below - above) < 1e-3
    assert not np.any(bspline(u, 4))
    x = jnp.linspace(-2.5, 2.5, 41) + 0.01
    np.testing.assert_allclose(jax.vmap(jax.grad(bspline))(x), bspline(x, 1), atol=1e-6)


@pytest.mark.parametrize("m", [57, 40], ids=["more points than samples", "as many"])
@pytest.mark.parametrize("axis", [-2, -1])
def test_transpose_is_the_adjoint(axis, m, x64):
    """⟨S f, g⟩ = ⟨f, Sᵀ g⟩ for the written-out transpose, batched, points partly off
    the grid and stepping by less than one sample; along −1 with as many points as
    samples the rows are sampled (and spread) in place, in blocks that leave two rows
    over (42 rows in 4 blocks)."""
    n = 40
    f = _complex((3, 42, n))
    t = jnp.asarray((np.arange(m) - m // 2) / 1.3 + n / 2 - 5.2)
    s, pullback = jax.vjp(lambda f: spline_sample(f, t, axis), f)
    g = _complex(s.shape)
    (st_g,) = pullback(g)
    np.testing.assert_allclose(jnp.sum(s * g), jnp.sum(f * st_g), rtol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("m", [61, 50], ids=["more points than samples", "as many"])
def test_derivatives_equal_jax_on_the_plain_gathers(m, x64):
    """Gradients in f and t, forward mode, a Hessian in t and vmap over the points of
    a 2-D magnification equal JAX's own derivatives of the same gathers (each compiled:
    op by op they took 25 s a case)."""
    n = 50
    f = _complex((2, n, n))
    g = _complex((2, m, m))
    t = jnp.asarray((np.arange(m) - m // 2) / 1.3 + n / 2 + 0.37)

    def loss(sample):
        return jax.jit(lambda f, t: jnp.sum(jnp.abs(sample(sample(f, t, -2), t, -1) * g) ** 2))
    new, old = loss(spline_sample), loss(cubic_sample)
    both = lambda transform, *args: [jax.jit(transform(h))(*args) for h in (new, old)]  # noqa: E731
    np.testing.assert_allclose(new(f, t), old(f, t), rtol=1e-13)
    for a, b in zip(*both(lambda h: jax.grad(h, (0, 1)), f, t)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(b))))
    tangents = (0.3 * f, jnp.ones_like(t))
    np.testing.assert_allclose(*both(lambda h: lambda *a: jax.jvp(h, a, tangents)[1], f, t),
                               rtol=1e-10)
    h_new, h_old = both(lambda h: jax.hessian(lambda t: h(f, t)), t)
    np.testing.assert_allclose(h_new, h_old, atol=1e-10 * float(jnp.max(jnp.abs(h_old))))
    ts = jnp.stack([t, t + 0.2])
    np.testing.assert_allclose(*both(lambda h: jax.vmap(jax.grad(h), (None, 0)), f, ts),
                               rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("t", [np.arange(30) * 1.5, np.arange(30) * 0.05 + 3.3,
                               np.arange(30)[::-1] * 0.5],
                         ids=["sparse points", "crowded points", "decreasing"])
def test_any_increasing_points_differentiate_and_decreasing_ones_give_nan(t):
    """Points 1.5 samples apart, or 0.05 (80 points within a B-spline's support: several
    passes of the transpose), differentiate as JAX's own gathers; decreasing points give
    NaN, not a wrong gradient."""
    f = _complex((40, 40)).astype(jnp.complex64)

    def grad(sample):
        return jax.grad(lambda f: jnp.sum(jnp.abs(sample(f, jnp.asarray(t), -2)) ** 2))(f)
    if np.all(np.diff(t) > 0):
        plain = grad(cubic_sample)
        np.testing.assert_allclose(grad(spline_sample), plain, rtol=1e-5,
                                   atol=1e-5 * float(jnp.max(jnp.abs(plain))))
    else:
        assert np.isnan(np.asarray(grad(spline_sample))).any()


def test_scaling_psf_in_a_users_jit_equals_the_call():
    """A camera closed over by the user's jit (every geometry a constant): the same PSF
    to float32 rounding. XLA folds the constant geometry with its own rounding, so the
    sample points may differ in their last bit (4e-6 samples at 40 samples: a few 1e-6
    of the PSF's peak); a point given the wrong taps was off by 5% of the peak (before
    the taps came from a search: spline._taps)."""
    cam = Camera(wavelength=532e-9, z2=1e-3, dx=5e-6, aperture_radius=0.1e-3, shape=(64, 64))
    phase = jnp.asarray(RNG.uniform(-3, 3, (64, 64)), jnp.float32)
    expected = psf(phase, cam, 25e-3)
    np.testing.assert_allclose(jax.jit(lambda p: psf(p, cam, 25e-3))(phase), expected,
                               rtol=0, atol=2e-5 * float(expected.max()))
