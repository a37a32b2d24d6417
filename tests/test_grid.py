"""Centred-grid conventions (diffcam/grid.py)."""

import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core import grid


@pytest.mark.parametrize("n", [7, 8])
def test_axis_sample_is_n_over_2(n):
    """Index n//2 has coordinate 0 for even and odd n; the pitch is dx."""
    c = np.asarray(grid.coords(n, 2.0))
    assert c[n // 2] == 0 and np.allclose(np.diff(c), 2.0)


@pytest.mark.parametrize("shape", [(6, 9), (7, 8)])
def test_fft2c_keeps_the_centre(shape):
    """A delta at the centre has a flat centred spectrum (zero phase), and a flat field
    transforms to a delta at the centre; ifft2c inverts fft2c."""
    delta = jnp.zeros(shape).at[shape[0] // 2, shape[1] // 2].set(1.0)
    np.testing.assert_allclose(grid.fft2c(delta), np.ones(shape), atol=1e-6)
    flat = grid.fft2c(jnp.ones(shape))
    assert np.unravel_index(np.argmax(np.abs(flat)), shape) == (shape[0] // 2, shape[1] // 2)
    x = jnp.asarray(np.random.default_rng(0).normal(size=shape))
    np.testing.assert_allclose(grid.ifft2c(grid.fft2c(x)), x, atol=1e-5)


def test_centred_freqs_match_fft2c_order():
    """centred_freqs are the frequencies of fft2c's output: a plane wave of frequency f
    peaks where centred_freqs == f."""
    n, dx = 32, 1e-6
    f0 = 5 / (n * dx)
    _, x = grid.yx((n, n), dx)
    wave = jnp.exp(2j * jnp.pi * f0 * x) * jnp.ones((n, 1))
    peak = np.unravel_index(np.argmax(np.abs(grid.fft2c(wave))), (n, n))
    _, fx = grid.centred_freqs((n, n), dx)
    assert np.isclose(float(fx[0, peak[1]]), f0)


@pytest.mark.parametrize("small,big", [((5, 6), (11, 16)), ((8, 8), (9, 9))])
def test_pad_and_crop_keep_the_axis_sample(small, big):
    """pad_to puts index n//2 at m//2, crop_to inverts it."""
    x = jnp.zeros(small).at[small[0] // 2, small[1] // 2].set(1.0)
    p = grid.pad_to(x, big)
    assert p.shape == big and p[big[0] // 2, big[1] // 2] == 1.0
    np.testing.assert_array_equal(grid.crop_to(p, small), x)
    assert grid.pad_by(x, (1, 2)).shape == (small[0] + 2, small[1] + 4)
