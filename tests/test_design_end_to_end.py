"""The end-to-end design objective: its training volumes, a loss that an empty
reconstruction scores 1 and the solver's TV weight moves, gradients in that weight
equal to finite differences, and a short design that lowers the loss, saved and
continued with its learnt weight."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.design import (DepthObjective, Design, DesignOptions, SmoothSurface, depth_range, design,
                            end_to_end_objective, evaluate_design, load_design,
                            training_volumes)
from diffcam.model import Camera

N, DX = 64, 3e-6
Z1 = depth_range(10e-3, 60e-3, 4)
OPTIONS = DesignOptions(objective="end_to_end", steps=6, scenes=2, solver_iterations=8,
                        learning_rate=0.3, progress=False)


def _camera():
    return Camera(wavelength=532e-9, z2=1e-3, dx=DX, aperture_radius=60e-6, shape=(N, N))


def _surface():
    return SmoothSurface.random(0, (N, N), DX, 15e-6, 1e-6)


def test_training_volumes_are_sparse_sources_inside_the_field():
    camera = _camera()
    v = np.asarray(training_volumes(jax.random.key(0), 3, Z1, camera, sources=5))
    assert v.shape == (3, 4, 2 * N, 2 * N)            # the solver's object grid ("crop")
    assert np.allclose(v.max(axis=(1, 2, 3)), 1)
    lit = np.argwhere(v > 0.5)
    assert lit[:, 2:].min() >= N // 2 - 3 and lit[:, 2:].max() <= 3 * N // 2 + 3
    assert 2 <= len({tuple(p) for p in lit[:, :2]}) <= 3 * 4   # on a few planes
    with pytest.raises(DiffcamError, match="whole numbers"):
        training_volumes(jax.random.key(0), 0, Z1, camera)


def _loss():
    start = Design(_surface(), _camera(), Z1, 1.5, OPTIONS, np.zeros((0, 4)), {}, None, "",
                   0.0, jnp.log(1e-5))
    objective = start.objective()
    return jax.jit(lambda log_tau: end_to_end_objective((start.surface, log_tau),
                                                        objective)[0])


@pytest.mark.slow  # 8 s of compilation (the unrolled solver's gradient)
def test_loss_is_below_an_empty_estimates_and_rises_with_too_much_tv():
    loss = _loss()
    values = [float(loss(jnp.float32(t))) for t in (np.log(1e-5), np.log(1e-2))]
    assert 0 < values[0] < values[1] < 1      # too much TV blurs the sources away


@pytest.mark.slow
def test_loss_gradient_in_the_solver_weight_is_finite_differences(x64):
    loss = _loss()
    at = np.log(1e-4)
    grad = float(jax.grad(loss)(jnp.float64(at)))
    step = 1e-4
    fd = (float(loss(jnp.float64(at + step))) - float(loss(jnp.float64(at - step)))) / (2 * step)
    assert grad == pytest.approx(fd, rel=1e-3, abs=1e-7)


@pytest.mark.slow  # two designs' compilation: 30 s of CPU
def test_short_design_lowers_the_loss_and_continues_from_its_file(tmp_path):
    path = tmp_path / "e2e.npz"
    options = dataclasses.replace(OPTIONS, checkpoint=str(path))
    result = design(_surface(), _camera(), Z1, options=options)
    assert result.history[-1, 0] < result.history[0, 0]
    assert result.final["loss"] < result.history[0, 0]
    assert result.log_tau is not None and float(result.log_tau) != pytest.approx(np.log(1e-5))
    loaded = load_design(path)
    assert float(loaded.log_tau) == pytest.approx(float(result.log_tau))
    assert evaluate_design(loaded.parameters, loaded.objective())["loss"] == pytest.approx(
        result.final["loss"], rel=1e-5)
    more = design(_surface(), _camera(), Z1,
                  options=dataclasses.replace(options, steps=8))
    assert more.steps == 8
    np.testing.assert_array_equal(more.history[:6], result.history)


def _broadband_disc_start():
    options = dataclasses.replace(OPTIONS, bandwidth=6e-9, source_radius=20e-6)
    return Design(_surface(), _camera(), Z1, 1.5, options, np.zeros((0, 4)), {}, None,
                  "", 0.0, jnp.log(1e-5))


def test_end_to_end_objective_takes_the_light_and_source_of_its_options():
    objective = _broadband_disc_start().objective()
    assert objective.source_radius == 20e-6 and objective.oversample == 1
    np.testing.assert_allclose(objective.spectrum[0],
                               532e-9 + 6e-9 * np.array([-1.0, 0.0, 1.0]))
    np.testing.assert_array_equal(objective.spectrum[1], [0.5, 1.0, 0.5])


@pytest.mark.slow  # the unrolled solver's compilation: 13 s
def test_end_to_end_psfs_are_the_depth_objectives_through_a_broadband_disc_source():
    """With a spectrum and a source disc the end-to-end objective images through the
    PSFs the depth objective scores (their correlations and spread agree), not the
    point source's."""
    start = _broadband_disc_start()
    objective = start.objective()
    e2e = evaluate_design(start.parameters, objective)
    depth = DepthObjective(_camera(), Z1, 1.5, spectrum=objective.spectrum,
                           source_radius=20e-6)
    want = evaluate_design(start.surface, depth)
    for term in ("max_correlation", "spread"):
        assert e2e[term] == pytest.approx(want[term], abs=1e-6)
    point = evaluate_design(start.surface, DepthObjective(_camera(), Z1, 1.5))
    assert abs(point["max_correlation"] - want["max_correlation"]) > 1e-4


def test_options_refuse_an_unknown_objective():
    with pytest.raises(DiffcamError, match="objective must be one of"):
        DesignOptions(objective="sharpness")
    with pytest.raises(DiffcamError, match="photons"):
        DesignOptions(objective="end_to_end", photons=0)
