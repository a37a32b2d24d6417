"""Sensor steps (diffcam.model.sensor): pixel integration, resampling, noise, saturation, bits."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.model.sensor import (bin_pixels, quantise, read_noise, resample, saturate,
                            shot_noise)


def test_bin_pixels_integer_ratio_on_centred_grids():
    """Pitch ratio 2 with both grids centred (index n//2 on the axis): the sensor pixel
    on the axis spans input pixels −1…1 with weights ½, 1, ½ per axis (exact to float32
    round-off)."""
    rng = np.random.default_rng(0)
    img = rng.random((8, 12)).astype(np.float32)
    out = np.asarray(bin_pixels(img, 1e-6, 2e-6))
    assert out.shape == (4, 6)
    w = np.array([0.5, 1.0, 0.5])
    np.testing.assert_allclose(out[2, 3], w @ img[3:6, 5:8] @ w, rtol=1e-6)


def test_bin_pixels_non_integer_ratio_conserves_power():
    """5 µm → 3.45 µm (the paper's sensor) and back: power inside the common area is
    kept (rtol 1e-5)."""
    x = np.arange(200) - 100
    img = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * 15.0 ** 2)).astype(np.float32)
    fine = bin_pixels(img, 5e-6, 3.45e-6, shape=(280, 280))
    np.testing.assert_allclose(float(fine.sum()), img.sum(), rtol=1e-5)
    coarse = bin_pixels(img, 5e-6, 7.3e-6)
    np.testing.assert_allclose(float(coarse.sum()), img.sum(), rtol=1e-5)


@pytest.mark.parametrize("kind", ["area", "cubic"])
def test_resample_identity_and_magnified_gaussian(kind):
    """Magnification 1 at the same pitch is the identity (1e-6). A Gaussian of σ = 6 px
    magnified by 1.2 about the centre is a Gaussian of σ = 7.2 px: second moment within
    1 % (area adds the pixel's 1/12 px² variance, inside that)."""
    x = np.arange(128) - 64
    g = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / (2 * 6.0 ** 2)).astype(np.float32)
    same = resample(g, 1.0, 1.0, g.shape, kind=kind)
    np.testing.assert_allclose(same, g, atol=1e-6)
    big = np.asarray(resample(g, 1.0, 1.0, g.shape, 1.2, kind=kind), np.float64)
    var = (big.sum(axis=0) * x ** 2).sum() / big.sum()
    np.testing.assert_allclose(np.sqrt(var), 7.2, rtol=0.01)
    np.testing.assert_allclose(big.sum(), g.sum(), rtol=1e-4)


@pytest.mark.slow  # 6 s of float64 compilation; resample's values by default
@pytest.mark.usefixtures("debug_nans")
def test_resample_jit_grad_vmap(x64):
    """resample is differentiable in the magnification (vs a central difference of step
    1e-5 in float64, rtol 1e-4) and maps over a batch of magnifications."""
    x = np.arange(64) - 32
    g = jnp.asarray(np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / 50.0))
    w = jnp.asarray(np.random.default_rng(0).random((64, 64)))
    for kind in ("area", "cubic"):
        f = jax.jit(lambda m: jnp.sum(w * resample(g, 1.0, 1.0, (64, 64), m, kind=kind,
                                                   max_width=2.0)))
        gm = jax.grad(f)(1.1)
        fd = (f(1.1 + 1e-5) - f(1.1 - 1e-5)) / 2e-5
        np.testing.assert_allclose(gm, fd, rtol=1e-4)
        batch = jax.jit(jax.vmap(lambda m: resample(g, 1.0, 1.0, (64, 64), m, kind=kind,
                                                    max_width=2.0)))(jnp.array([1.0, 1.2]))
        assert batch.shape == (2, 64, 64)
    with pytest.raises(DiffcamError, match="max_width"):
        jax.jit(lambda m: resample(g, 1.0, 1.0, (64, 64), m))(1.1)


def test_noise_saturation_and_bits():
    """Shot noise: mean and variance of a Poisson count (5 σ of the estimator); same key,
    same noise. Read noise adds σ r.m.s.; saturation clips; 8-bit quantisation gives
    integers in 0…255."""
    key = jax.random.key(0)
    e = jnp.full((200, 200), 50.0)
    s = shot_noise(key, e)
    assert abs(float(s.mean()) - 50) < 5 * np.sqrt(50 / s.size)
    assert abs(float(s.var()) - 50) < 5 * 50 * np.sqrt(2 / s.size)
    np.testing.assert_array_equal(s, shot_noise(key, e))
    r = read_noise(jax.random.key(1), jnp.zeros((200, 200)), 3.0)
    np.testing.assert_allclose(float(r.std()), 3.0, rtol=0.02)
    np.testing.assert_array_equal(saturate(jnp.array([-1.0, 5.0, 20.0]), 10.0), [0, 5, 10])
    q = np.asarray(quantise(jnp.array([0.0, 5.0, 10.0, 30.0]), 8, 10.0))
    np.testing.assert_array_equal(q, [0, 128, 255, 255])
    with pytest.raises(DiffcamError, match="bit_depth"):
        quantise(e, 0, 10.0)
    with pytest.raises(DiffcamError, match="full_well"):
        saturate(e, -1.0)
    chain = jax.jit(lambda k, x: quantise(saturate(read_noise(k, shot_noise(k, x), 2.0),
                                                   100.0), 12, 100.0))
    assert chain(key, e).shape == e.shape
