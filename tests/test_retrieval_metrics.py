"""Phase metrics (docs/design.md, "Phase ambiguities and the phase metric")."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.evaluate.metrics import (pearson, phase_mse, phase_offset, phase_pearson, phase_scores,
                             twin_phase, wrap_phase)


@pytest.fixture
def truth():
    rng = np.random.default_rng(0)
    y, x = np.mgrid[-16:16, -16:16] / 16.0
    return jnp.asarray(np.pi * np.sin(3 * x + 2 * y * y) + 0.3 * rng.normal(size=x.shape),
                       jnp.float32).clip(-np.pi, np.pi)


def test_wrap_phase_range_and_identity():
    t = jnp.linspace(-20, 20, 1001)
    w = wrap_phase(t)
    assert float(w.min()) >= -np.pi and float(w.max()) < np.pi
    np.testing.assert_allclose(np.cos(w), np.cos(t), atol=1e-4)


def test_twin_is_an_involution_about_the_centre_index(truth):
    np.testing.assert_array_equal(twin_phase(twin_phase(truth)), truth)
    n = truth.shape[-1]
    # index N//2 maps to itself, i -> (N - i) mod N
    assert float(twin_phase(truth)[n // 2, n // 2]) == -float(truth[n // 2, n // 2])
    assert float(twin_phase(truth)[3, 5]) == -float(truth[n - 3, n - 5])


def test_piston_and_wrap_invariance(truth):
    shifted = wrap_phase(truth + 2.5)  # a piston that wraps part of the phase
    assert float(phase_offset(shifted, truth)) == pytest.approx(2.5, abs=1e-5)
    assert float(phase_pearson(shifted, truth)) == pytest.approx(1.0, abs=1e-5)
    assert float(phase_mse(shifted, truth)) == pytest.approx(0.0, abs=1e-9)
    # the raw figure is not piston invariant once the shift wraps
    assert float(pearson(shifted, truth)) < 0.9


def test_minus_pi_equals_plus_pi(truth):
    """A truth at −π and an estimate at +π are the same phase: P stays 1."""
    est = jnp.where(truth < -3.0, truth + 2 * np.pi, truth)
    assert float(phase_pearson(est, truth)) == pytest.approx(1.0, abs=1e-6)


def test_twin_resolved_figure(truth):
    tw = twin_phase(truth)
    mask = jnp.zeros_like(truth).at[4:-4, 4:-4].set(1.0)
    # the aligned figure is inflated by the wrap (an unrelated phase scores ≈ 0.7 against
    # a truth spanning [−π, π]), so the twin still scores well below 1 but not near 0
    assert float(phase_pearson(tw, truth, mask=mask)) < 0.95
    assert float(phase_mse(tw, truth, mask=mask)) > 0.5
    assert float(phase_pearson(tw, truth, mask=mask, twin=True)) == pytest.approx(1.0, abs=1e-5)


def test_unrelated_phase_scores_near_one_over_root_two():
    """For θtrue and θest independent and uniform on [−π, π), aligned = θtrue + uniform
    noise of the same variance, so P → 1/√2: the floor of the piston-aligned figure."""
    k1, k2 = jax.random.split(jax.random.key(2))
    t = jax.random.uniform(k1, (256, 256), minval=-np.pi, maxval=np.pi)
    e = jax.random.uniform(k2, (256, 256), minval=-np.pi, maxval=np.pi)
    assert float(phase_pearson(e, t)) == pytest.approx(2 ** -0.5, abs=0.01)
    assert abs(float(pearson(e, t))) < 0.02


def test_noise_lowers_the_score_and_mse_matches(truth):
    noise = 0.3 * jax.random.normal(jax.random.key(1), truth.shape)
    s = phase_scores(truth + noise, truth)
    assert 0.8 < float(s["pearson"]) < 0.999
    assert float(s["mse"]) == pytest.approx(float(jnp.mean((noise - noise.mean()) ** 2)),
                                            rel=0.05)


def test_jit_and_vmap(truth):
    batch = jnp.stack([truth, wrap_phase(truth + 1.0), twin_phase(truth)])
    f = jax.jit(jax.vmap(lambda e: phase_pearson(e, truth, twin=True)))
    np.testing.assert_allclose(f(batch), [1, 1, 1], atol=1e-5)
    # batched by broadcasting, too
    np.testing.assert_allclose(phase_pearson(batch[:2], truth), [1, 1], atol=1e-5)
