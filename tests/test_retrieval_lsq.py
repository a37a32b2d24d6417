"""Least squares through the forward model (optimistix; jaxopt as optional backend)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.core.grid import crop_to
from diffcam.evaluate.metrics import phase_scores
from diffcam.calibrate import (FitOptions, PhaseGrid, retrieve_phase, near_far_model, paper_simulation, raar,
                               retrieve_lsq)
from diffcam.calibrate.phase.lsq import ConvergenceWarning, _linear_fit, _residual

from conftest import assert_float32_gradient_matches_float64


@pytest.fixture(scope="module")
def sim():
    return paper_simulation(128, 64)


@pytest.fixture(scope="module")
def warm(sim):
    """A RAAR start that is close but not converged."""
    return raar(sim.near, sim.far, sim.geometry, iterations=60, key=jax.random.key(0)).phase


def twin_resolved(result, sim):
    return float(phase_scores(crop_to(result.phase, sim.truth.shape), sim.truth,
                              mask=sim.mask)["twin_resolved"])


def test_model_conserves_energy_for_any_phase(sim):
    model = near_far_model(sim.aperture, sim.geometry)
    for phase in (sim.phase, jnp.zeros_like(sim.phase), 3 * sim.phase):
        near, far = model(phase)
        np.testing.assert_allclose(float(near.sum()), float(sim.aperture.sum()), rtol=1e-4)
        np.testing.assert_allclose(float(far.sum()), float(sim.aperture.sum()), rtol=1e-4)


def test_model_float32_gradient_agrees_with_float64(sim):
    """The phase gradient of Σ w·(near + far) through the near/far model in float32
    equals the float64 one (1e-3 of its largest entry): no sum of the model leaves
    float32's range (the PSF's normalisation once did, test_camera)."""
    w = np.random.default_rng(0).random(np.shape(sim.phase))

    def gradient(dtype):
        model = near_far_model(jnp.asarray(sim.aperture, dtype), sim.geometry)
        weight = jnp.asarray(w, dtype)
        loss = lambda ph: sum(jnp.sum(weight * m) for m in model(ph))  # noqa: E731
        return jax.grad(loss)(jnp.asarray(sim.phase, dtype))

    assert_float32_gradient_matches_float64(gradient)


def test_model_far_field_matches_the_fourier_lens_up_to_scale(sim):
    _, far = near_far_model(sim.aperture, sim.geometry)(sim.phase)
    ratio = np.asarray(sim.far) / np.maximum(np.asarray(far), 1e-30)
    bright = np.asarray(far) > 1e-3 * float(far.max())
    assert np.std(ratio[bright]) / np.mean(ratio[bright]) < 1e-3


@pytest.mark.slow  # 6 s a solver; the default solver's fit by default (the tests below)
@pytest.mark.parametrize("solver", ["lbfgs", "ncg", "gauss_newton"])
def test_solvers_polish_a_warm_start(sim, warm, solver):
    r = retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, init=warm, solver=solver,
                     iterations=40)
    h = np.asarray(r.history)
    assert h[-1] < (0.7 if solver == "ncg" else 0.1) * h[0]  # NCG is the slowest here
    assert twin_resolved(r, sim) > 0.995
    assert r.stats["method"] == f"lsq/{solver}/weighted_intensity"


@pytest.mark.slow  # the optional backend (jaxopt is unmaintained upstream)
def test_jaxopt_backend(sim, warm):
    r = retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, init=warm,
                     solver="jaxopt_lbfgs", iterations=40)
    assert np.asarray(r.history)[-1] < 0.1 * np.asarray(r.history)[0]
    assert twin_resolved(r, sim) > 0.995


@pytest.mark.parametrize("loss", ["amplitude", pytest.param("poisson", marks=pytest.mark.slow)])
def test_other_losses(sim, warm, loss):
    r = retrieve_lsq(sim.near * 1e3, sim.far * 1e3, sim.geometry, sim.aperture, init=warm,
                     loss=loss, iterations=40)
    assert twin_resolved(r, sim) > 0.99


def test_scale_and_background_are_fitted(sim, warm):
    near, far = 5.0 * sim.near + 0.2, 0.01 * sim.far + 3e-4 * float(sim.far.max())
    r = retrieve_lsq(near, far, sim.geometry, sim.aperture, init=warm, iterations=40)
    bg = np.asarray(r.stats["background"])
    np.testing.assert_allclose(bg, [0.2, 3e-4 * float(sim.far.max())], rtol=0.05)
    assert twin_resolved(r, sim) > 0.995


def test_masks_ignore_saturated_pixels(sim, warm):
    """Clip the far field's bright core as a saturated sensor would: unmasked, the clipped
    pixels pull the fit away; masked, they are ignored."""
    level = 0.05 * float(sim.far.max())
    far = jnp.minimum(sim.far, level)
    far_mask = (sim.far < level).astype(jnp.float32)
    masked = retrieve_lsq(sim.near, far, sim.geometry, sim.aperture, init=warm, iterations=60,
                          masks=(jnp.ones_like(far), far_mask))
    plain = retrieve_lsq(sim.near, far, sim.geometry, sim.aperture, init=warm, iterations=60)
    assert twin_resolved(masked, sim) > 0.995
    assert twin_resolved(masked, sim) > twin_resolved(plain, sim)


@pytest.mark.slow
def test_coarse_phase_grid_and_regularisers(sim):
    grid = PhaseGrid.for_aperture(sim.aperture, 2)
    assert grid.box % 2 == 0 and grid.param_shape == (grid.box // 2,) * 2
    smooth = raar(sim.near, sim.far, sim.geometry, iterations=300, key=jax.random.key(0)).phase
    r = retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, init=smooth, coarse=2,
                     smoothness=1e-3, tv=1e-3, iterations=20)
    assert np.all(np.isfinite(np.asarray(r.history)))
    assert r.phase.shape == sim.phase.shape


@pytest.mark.usefixtures("debug_nans")
def test_residuals_have_finite_gradients(sim, x64):
    """Gradient of each loss against finite differences, including where the prediction
    or the measurement is zero (the safe sqrt / log)."""
    y = jnp.array([0.0, 0.5, 2.0, 1e-3])
    for loss in ("intensity", "weighted_intensity", "amplitude", "poisson"):
        f = lambda p: jnp.sum(_residual(p, y, 1.0, loss) ** 2)  # noqa: E731
        check_grads(jax.jit(f), (jnp.array([0.3, 0.7, 1.5, 0.2]),), order=1, modes=["rev"])
        g = jax.grad(f)(jnp.array([0.0, 0.7, 1.5, 0.0]))
        assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.usefixtures("debug_nans")
@pytest.mark.parametrize("fit_background", [True, False])
def test_weighted_loss_needs_no_derivative_through_scale_and_background(x64, fit_background):
    """Variable projection: (s, b) minimise the weighted loss Σ(s·p + b − y)²/(y + 1), so
    the derivative of the projected loss equals its partial derivative at fixed (s, b)
    (envelope theorem), which is what the fit differentiates."""
    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.uniform(0.1, 2.0, 64))
    y = jnp.asarray(rng.uniform(0.0, 3.0, 64))

    def projected(p, stop):
        s, b = _linear_fit(p, y, 1.0 / (y + 1.0), fit_background)
        if stop:
            s, b = jax.lax.stop_gradient((s, b))
        return jnp.sum(_residual(s * p + b, y, 1.0, "weighted_intensity") ** 2)

    exact = jax.grad(projected)(p, False)
    assert float(jnp.linalg.norm(exact)) > 1e-3  # the check is not vacuous
    np.testing.assert_allclose(jax.grad(projected)(p, True), exact, rtol=1e-9, atol=1e-12)


@pytest.mark.usefixtures("debug_nans")
def test_model_is_jittable_and_vmappable(sim):
    model = near_far_model(sim.aperture, sim.geometry)
    batch = jnp.stack([sim.phase, 0.5 * sim.phase])
    near, far = jax.jit(jax.vmap(model))(batch)
    assert near.shape == far.shape == (2, 128, 128)
    g = jax.grad(lambda p: jnp.sum(model(p)[1] * sim.far))(sim.phase)
    assert np.all(np.isfinite(np.asarray(g)))


@pytest.mark.slow  # 6 s; retrieval's default path by default: the test below
def test_calibrate_default_path(sim):
    r = retrieve_phase(sim.near, sim.far, sim.geometry, sim.aperture, key=jax.random.key(0),
                       iterations=200, restarts=2, refine=FitOptions(loss="intensity",
                                                                      iterations=20))
    assert twin_resolved(r, sim) > 0.999
    assert [s["method"] for s in r.stats["stages"]] == ["raar", "lsq/lbfgs/intensity"]


def test_bad_options(sim):
    with pytest.raises(DiffcamError, match="loss"):
        retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, loss="l1")
    with pytest.raises(DiffcamError, match="solver"):
        retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, solver="adam")
    with pytest.raises(ShapeError):
        retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture[:64])
    with pytest.raises(DiffcamError, match="coarse factor"):
        retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, coarse=0)


def test_default_reaches_the_phase_from_a_flat_start(sim):
    """The default retrieve_lsq (weighted residuals after a 30-iteration RAAR warm start
    from a flat phase) retrieves the 128² problem: phase Pearson ≥ 0.99 (plain intensity
    residuals from a flat start stall at 0.80 there, and are reported as stalled)."""
    r = retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture)
    assert twin_resolved(r, sim) >= 0.99 and r.stats["status"] == "converged"
    with pytest.warns(ConvergenceWarning, match="stalled"):
        cold = retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, init="flat",
                            loss="intensity", iterations=200)
    assert cold.stats["status"] == "stalled" and twin_resolved(cold, sim) < 0.95


def test_a_second_fit_does_not_compile_again(sim, warm):
    """New data, a new start and new regularisation weights of the same structure reuse
    the compiled fit (a counter of XLA compilations stays put)."""
    from jax._src import dispatch  # noqa: F401  (jax.monitoring event names)
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda name, *a, **k: compiles.append(name)
        if name == "/jax/core/compile/backend_compile_duration" else None)
    options = dict(init=warm, iterations=5, smoothness=1e-3)
    retrieve_lsq(sim.near, sim.far, sim.geometry, sim.aperture, **options)
    before = len(compiles)
    retrieve_lsq(sim.near * 1.5, sim.far * 0.7, sim.geometry, sim.aperture,
                 init=warm + 0.1, iterations=5, smoothness=2e-3)
    assert before > 0 and len(compiles) == before


@pytest.mark.slow  # float64 end to end: the float32 gradient is checked against it by default
def test_fits_run_in_float64(sim, warm, x64):
    """Under jax_enable_x64 float64 captures fit in float64 end to end (the solver's
    carry keeps one dtype), to the same phase as float32."""
    near64, far64 = (jnp.asarray(a, jnp.float64) for a in (sim.near, sim.far))
    r = retrieve_lsq(near64, far64, sim.geometry, sim.aperture, init=warm, iterations=40)
    assert r.phase.dtype == jnp.float64 and r.history.dtype == jnp.float64
    assert twin_resolved(r, sim) > 0.995
