"""Shared test fixtures: float64 mode, NaN checking, finite-difference gradient checks."""

import jax
import numpy as np
import pytest


@pytest.fixture
def x64():
    """Run a test with JAX float64 enabled (closed-form comparisons, gradient checks)."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def debug_nans():
    """Run a test with ``jax_debug_nans`` on (any NaN a JAX op produces raises
    FloatingPointError), restored after: the gradient tests use it through
    ``@pytest.mark.usefixtures("debug_nans")``, so a NaN in a derivative fails loudly."""
    before = jax.config.jax_debug_nans
    jax.config.update("jax_debug_nans", True)
    try:
        yield
    finally:
        jax.config.update("jax_debug_nans", before)


def fd_gradient(f, x, rel_step=1e-6):
    """Central finite difference of scalar f at scalar x with a step relative to |x|."""
    h = rel_step * max(abs(float(x)), 1e-30)
    return (float(f(x + h)) - float(f(x - h))) / (2 * h)


def assert_grad_matches_fd(f, x, rel_step=1e-6, rtol=1e-5):
    """jax.grad of scalar f at scalar x agrees with a relative-step central difference."""
    g = float(jax.grad(f)(x))
    fd = fd_gradient(f, x, rel_step)
    np.testing.assert_allclose(g, fd, rtol=rtol, atol=1e-12 * max(abs(fd), 1.0))
