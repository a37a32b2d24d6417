"""expj(θ) = e^{jθ}: against numpy's float64 exponential, its derivative exact, under
jit and vmap, NaN and Inf as jnp.exp's."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffcam.core.phasor import expj


def _error(theta):
    theta = np.asarray(theta, np.float32)
    got = np.asarray(jax.jit(expj)(theta))
    assert got.dtype == np.complex64
    return np.abs(got - np.exp(1j * theta.astype(np.float64))).max()


@pytest.mark.parametrize("reach", [1.0, 100.0, 12868.0, 1e6])
def test_expj_float32_within_1_3e7_of_the_exponential(reach):
    theta = np.random.default_rng(0).uniform(-reach, reach, 200_000)
    assert _error(theta) < 1.3e-7


def test_expj_at_the_quadrant_boundaries_and_tiny_angles():
    k = np.arange(-2000, 2000)[:, None] * (np.pi / 4)
    assert _error(k + np.array([-1e-4, -1e-6, 0, 1e-6, 1e-4])) < 1.3e-7
    tiny = np.array([0, 1e-30, -1e-20, 1e-8, np.pi, -np.pi], np.float32)
    got = np.asarray(expj(tiny))
    np.testing.assert_allclose(got.imag[:4], tiny[:4], rtol=1e-6, atol=0)  # sin θ ≈ θ
    assert _error(tiny) < 1.3e-7


def test_expj_stays_bounded_where_float32_phases_carry_no_phase():
    theta = np.random.default_rng(1).uniform(-1e9, 1e9, 100_000).astype(np.float32)
    modulus = np.abs(np.asarray(expj(theta)))
    assert modulus.max() < 1.001 and modulus.min() > 0.999


def test_expj_float64_is_the_exponential(x64):
    theta = np.random.default_rng(2).uniform(-50, 50, 1000)
    got = np.asarray(expj(theta))
    assert got.dtype == np.complex128
    np.testing.assert_allclose(got, np.exp(1j * theta), rtol=0, atol=1e-15)


def test_expj_other_dtypes_become_complex64():
    assert expj(jnp.arange(4)).dtype == jnp.complex64
    assert expj(jnp.ones(3, jnp.float16)).dtype == jnp.complex64
    np.testing.assert_allclose(np.asarray(expj(jnp.arange(4))), np.exp(1j * np.arange(4)),
                               atol=1.3e-7)
    # an integer phase is a constant to differentiation: d/da Σ Re(a·e^{jk}) = Σ cos k
    grad = jax.grad(lambda a: jnp.sum((a * expj(jnp.arange(4))).real))(1.0)
    np.testing.assert_allclose(float(grad), np.cos(np.arange(4)).sum(), rtol=1e-6)


def test_expj_propagates_nan_and_inf_like_the_exponential():
    got = np.asarray(expj(np.array([np.nan, np.inf, -np.inf, 1.0], np.float32)))
    assert np.isnan(got[:3].real).all() and np.isnan(got[:3].imag).all()
    assert np.isfinite(got[3])


def test_expj_derivative_is_j_times_the_value():
    theta = jnp.asarray(np.random.default_rng(3).uniform(-20, 20, (8, 8)), jnp.float32)
    dtheta = jnp.asarray(np.random.default_rng(4).normal(size=(8, 8)), jnp.float32)
    value, tangent = jax.jvp(expj, (theta,), (dtheta,))
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(1j * value * dtheta), atol=1e-6)
    # reverse mode: d/dθ Σ Re(w·e^{jθ}) = −Re(w)·sin θ − Im(w)·cos θ
    w = jnp.asarray(np.random.default_rng(5).normal(size=(8, 8, 2)) @ [1, 1j], jnp.complex64)
    grad = jax.grad(lambda t: jnp.sum((w * expj(t)).real))(theta)
    t = np.asarray(theta, np.float64)
    want = -np.asarray(w).real * np.sin(t) - np.asarray(w).imag * np.cos(t)
    np.testing.assert_allclose(np.asarray(grad), want, atol=2e-6)


def test_expj_gradients_to_second_order(x64):
    theta = jnp.asarray(np.random.default_rng(6).uniform(-3, 3, 5))
    check_grads(jax.jit(lambda t: expj(t) * (1 + 2j)), (theta,), order=2, modes=("fwd", "rev"))


def test_expj_under_jit_vmap_and_a_loop():
    theta = jnp.asarray(np.random.default_rng(7).uniform(-9, 9, (3, 16)), jnp.float32)
    mapped = jax.jit(jax.vmap(expj))(theta)
    looped = jax.lax.fori_loop(0, 3, lambda i, acc: acc.at[i].set(expj(theta[i])),
                               jnp.zeros(theta.shape, jnp.complex64))
    np.testing.assert_array_equal(np.asarray(mapped), np.asarray(looped))
    assert _error(theta) < 1.3e-7
