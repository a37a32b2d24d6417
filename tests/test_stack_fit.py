"""Stack fitting (diffcam.calibrate.stack.fit), registration and the scaling baseline
(diffcam.evaluate.registration), and the `diffcam fit/predict/compare-stack` commands."""

from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np
import pytest
import scipy.ndimage as ndi

from diffcam.apps.cli import main
from diffcam.calibrate import (StackFitOptions, StackFitWarning, fit_stack, load_model,
                               load_stack_fit, model_kind, prepare_planes)
from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.evaluate.metrics import pearson
from diffcam.evaluate.registration import (Registration, magnification_from_light,
                                           magnify_about, register_magnification,
                                           relative_magnification_at, scaling_baseline)

GIVEN = [2, 9]


@pytest.fixture(scope="module")
def synthetic_stack():
    """A 12-plane stack from diffcam's own PSF model, NOT the stack model
    (:func:`diffcam.calibrate.simulation.measured_stack_simulation`: 768² at 1 µm, three
    wavelengths, 4×4 binning to 96×96 pixels, Poisson noise)."""
    from diffcam.calibrate.simulation import measured_stack_simulation

    return measured_stack_simulation()[0]


@pytest.fixture(scope="module")
def synthetic_fit(synthetic_stack):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StackFitWarning)
        return fit_stack(synthetic_stack, GIVEN, progress=False, kappa=1.0, zetas=(64.0,),
                         max_steps=100, time_budget=math.inf)


@pytest.mark.slow   # the synthetic fit (fixture): 30 s of CPU
def test_fit_beats_scaling_baseline_on_held_out_planes(synthetic_stack, synthetic_fit):
    """On planes it never saw, the fitted model correlates better with the measured
    (noisy) planes than the scaling baseline does, on average over the held-out planes."""
    fit = synthetic_fit
    measured = prepare_planes(synthetic_stack)
    held = [t for t in range(len(measured)) if t not in GIVEN]
    pred = fit.predict(held)
    base = scaling_baseline({t: measured[t] for t in GIVEN}, held,
                            registration=fit.registration)
    r_model, r_base = (np.asarray(pearson(x, measured[held])) for x in (pred, base))
    assert pred.shape == (len(held), 96, 96) and np.isfinite(pred).all()
    assert r_model.mean() > r_base.mean() + 0.001, (r_model.mean(), r_base.mean())
    assert fit.validation_score > fit.baseline_validation and not fit.worse_than_baseline
    assert fit.stop_reason.startswith("no validation improvement")
    assert 0 <= fit.best_step < fit.steps == len(fit.validation) == len(fit.history)
    assert fit.planes == tuple(GIVEN) and fit.n_planes == 12
    # the true M(9)/M(2) of the simulation: (1 + z2/z1(9)) / (1 + z2/z1(2))
    z1 = 1e-3 / np.linspace(1 / 2, 1 / 10, 12)
    true = (1 + 0.6e-3 / z1[9]) / (1 + 0.6e-3 / z1[2])
    assert abs(fit.registration.magnification - true) < 0.01
    assert "zeta_reference_px2" in fit.identifiable and "z_eff_m" not in fit.identifiable


@pytest.mark.slow   # the synthetic fit (fixture): 30 s of CPU
def test_save_load_round_trip(synthetic_fit, tmp_path):
    """A saved fit predicts exactly what the original predicts; the file is one .npz."""
    path = tmp_path / "fit.npz"
    synthetic_fit.save(path)
    assert [p.name for p in tmp_path.iterdir()] == ["fit.npz"]  # no temp file left
    loaded = load_stack_fit(path)
    planes = [0, 5, 11]
    np.testing.assert_array_equal(loaded.predict(planes), synthetic_fit.predict(planes))
    assert loaded.summary() == synthetic_fit.summary()
    np.testing.assert_array_equal(loaded.validation, synthetic_fit.validation)
    # the one door for camera models reads it as a stack fit
    assert model_kind(path) == "stack-fit"
    assert load_model(path).summary() == synthetic_fit.summary()


@pytest.mark.slow   # the synthetic fit (fixture): 30 s of CPU
def test_prediction_reproduces_given_planes_and_carries_residuals(synthetic_stack,
                                                                 synthetic_fit):
    """At a given plane the prediction is that measured plane (up to gain and offset);
    halfway between the given planes it is the rendered model plus both residuals
    magnified by the model's law, each with weight ½ — computed here independently with
    scipy (the module's law, not its code)."""
    fit = synthetic_fit
    measured = prepare_planes(synthetic_stack)
    for t in GIVEN:
        assert float(pearson(fit.predict([t])[0], measured[t])) > 0.99999
    m = fit.model
    s = lambda t: float(np.asarray(m.magnification(t)))  # noqa: E731
    t_mid = 5.5
    planes = GIVEN + [t_mid]
    raw = np.asarray(m.render(np.asarray(planes)), np.float64)
    expect = 0.0
    for n, k in enumerate(GIVEN):
        a, b = np.polyfit(raw[n].ravel(), measured[k].ravel(), 1)
        res = measured[k] - a * raw[n] - b
        yy, xx = np.mgrid[0:96, 0:96].astype(float)
        c = np.asarray(m.centre, float)
        q = s(t_mid) / s(k)
        moved = ndi.map_coordinates(res, [c[0] + (yy - c[0]) / q, c[1] + (xx - c[1]) / q],
                                    order=3, mode="constant")
        expect = expect + 0.5 * (a * raw[2] + moved)
    # weights at 5.5: (9 − 5.5)/7 = (5.5 − 2)/7 = ½
    got = fit._with_residuals(m, [t_mid])[0]
    np.testing.assert_allclose(got, expect, rtol=0, atol=2e-3 * np.abs(expect).max())
    # rendering alone differs from the carried prediction (the residual is not empty)
    alone = fit.predict([6], residual=False)[0]
    assert float(pearson(alone, fit.predict([6])[0])) < 0.9999


@pytest.mark.parametrize("planes, match", [
    (2.7, "count or a sequence"), ("12", "count or a sequence"), (True, "count or a sequence"),
    ([1.5], "integers"), ([3, True], "integers"), (0, "no planes"), ([], "no planes"),
    (10 ** 7, "at most 4096"), ([5000], "magnification law reaches zero"),
])
@pytest.mark.slow   # the synthetic fit (fixture): 30 s of CPU
def test_predict_refuses_bad_planes(synthetic_fit, planes, match):
    """Fractions, strings and bools are not planes; a count is bounded before any work; a
    plane where the fitted linear magnification law is ≤ 0 would render nonsense."""
    with pytest.raises(DiffcamError, match=match):
        synthetic_fit.predict(planes)


@pytest.mark.parametrize("level", ["abc", "nan", "inf", "1e400"])
def test_cli_fit_refuses_a_saturation_that_is_not_a_level(tmp_path, capsys, level):
    """One usage error (exit 2, no traceback) before the stack is read."""
    with pytest.raises(SystemExit) as exit_:
        main(["fit", str(tmp_path / "missing.npy"), "--planes", "4,12", "--saturation", level,
              "-o", str(tmp_path / "m.npz")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "is not a pixel level" in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow   # the synthetic fit (fixture): 30 s of CPU
@pytest.mark.parametrize("kappa", [math.nan, math.inf, 1e6, "1", True])
def test_predict_refuses_bad_kappa(synthetic_fit, kappa):
    with pytest.raises(DiffcamError, match="kappa must be a number"):
        synthetic_fit.predict([3], kappa=kappa)


def test_blend_baseline_mixes_bracketing_planes():
    """``blend=True``: at a given plane that plane; between two given planes the weighted
    mean of both magnified to t; outside the given range the nearest plane alone."""
    from diffcam.evaluate.registration import bracket_weights

    assert bracket_weights(3, [2, 9]) == pytest.approx({2: 6 / 7, 9: 1 / 7})
    assert bracket_weights(2, [9, 2]) == {2: 1.0}
    assert bracket_weights(0, [2, 9]) == {2: 1.0} and bracket_weights(20, [2, 9]) == {9: 1.0}
    assert bracket_weights(6, [2, 5, 9]) == pytest.approx({5: 0.75, 9: 0.25})
    a, b = _blobs(seed=1), _blobs(seed=2)
    reg = Registration(1.10, (45.0, 60.0), 1.0)
    blend = scaling_baseline({0: a, 10: b}, [0, 4, 10, 12], registration=reg, blend=True)
    near = scaling_baseline({0: a, 10: b}, [4, 12], registration=reg)
    np.testing.assert_array_equal(blend[0], a)
    np.testing.assert_array_equal(blend[2], b)
    np.testing.assert_allclose(blend[3], near[1])
    only_b = scaling_baseline({0: np.zeros_like(a), 10: b}, [4], registration=reg,
                              blend=True)[0]
    only_a = scaling_baseline({0: a, 10: np.zeros_like(b)}, [4], registration=reg,
                              blend=True)[0]
    np.testing.assert_allclose(blend[1], only_a + only_b, atol=1e-12)
    np.testing.assert_allclose(only_a, 0.6 * near[0], atol=1e-12)


def test_load_refuses_bad_files(tmp_path):
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip archive at all")
    with pytest.raises(DiffcamError, match="not a diffcam stack-fit file"):
        load_stack_fit(garbage)
    other = tmp_path / "other.npz"
    np.savez(other, stack=np.zeros((2, 3, 3)))
    with pytest.raises(DiffcamError, match="no array"):
        load_stack_fit(other)
    with pytest.raises(DiffcamError, match="no such file"):
        load_stack_fit(tmp_path / "missing.npz")


@pytest.mark.slow   # the synthetic fit (fixture): 30 s of CPU
def test_load_refuses_older_format_with_what_to_do(synthetic_fit, tmp_path):
    """A file of an earlier model format (per-sample phase) fails with one line that
    says to fit again, not with a missing-array error."""
    import json as _json
    import zipfile

    path = tmp_path / "fit.npz"
    synthetic_fit.save(path)
    with np.load(path) as f:
        arrays = {k: f[k] for k in f.files}
    meta = _json.loads(str(arrays["metadata"][()]))
    meta["version"] = 2
    arrays["metadata"] = np.array(_json.dumps(meta))
    old = tmp_path / "old.npz"
    np.savez(old, **{k: v for k, v in arrays.items() if not k.startswith("field_")})
    assert zipfile.is_zipfile(old)
    with pytest.raises(DiffcamError, match="fit the stack again") as err:
        load_stack_fit(old)
    assert "\n" not in str(err.value)
    with pytest.raises(DiffcamError, match="fit the stack again"):
        load_model(old)


def test_z2_and_magnification_are_one_unknown():
    """The Fresnel scaling theorem's family: a diffuser magnified by a, seen from a·z2 by
    sources whose magnification is M/a, gives the same PSF as the original at every
    depth — computed with the engine's own PSF (paper Eq. 7, direct path). So a stack
    fixes z2·M(t), never z2 and z1 apart (what :func:`fit_stack` reports)."""
    import jax.numpy as jnp

    import diffcam as dc

    n, dx, lam, z2, a = 256, 4e-6, 532e-9, 1e-3, 0.8
    yy, xx = (np.mgrid[0:n, 0:n] - n // 2) * dx

    def phase(scale):   # a smooth diffuser, magnified by ``scale``
        y, x = yy / scale, xx / scale
        return (3 * np.sin(2 * np.pi * x / 90e-6) * np.cos(2 * np.pi * y / 70e-6)
                + 2 * np.cos(2 * np.pi * (x + y) / 130e-6))

    for z1 in (6e-3, 15e-3):
        m = 1 + z2 / z1
        z1_scaled = a * z2 / (m / a - 1)        # magnification M/a at distance a·z2
        cam = dc.Camera(wavelength=lam, z2=z2, dx=dx, aperture_radius=0.3e-3,
                        shape=(n, n), pad=n // 2, edge="soft")
        big = dc.Camera(wavelength=lam, z2=a * z2, dx=dx, aperture_radius=a * 0.3e-3,
                        shape=(n, n), pad=n // 2, edge="soft")
        h = np.asarray(dc.psf(jnp.asarray(phase(1.0), jnp.float32), cam, z1))
        g = np.asarray(dc.psf(jnp.asarray(phase(a), jnp.float32), big, z1_scaled))
        assert float(pearson(h, g)) > 0.999, z1
        assert abs(z2 * m - a * z2 * (1 + a * z2 / z1_scaled)) < 1e-12   # z2·M kept


def test_stack_model_renders_the_engines_psf():
    """One camera model: the stack model, given the diffuser field C·e^{jθ} and the
    geometry in its pixel units (ζ = λ·z2/(M·dx²), magnification M(t) linear through
    two planes), renders the engine's own PSF (paper Eq. 7, :func:`diffcam.psf`) at
    those two depths and at one between them, with no blur and one sample per pixel."""
    import jax.numpy as jnp

    import diffcam as dc
    from diffcam.calibrate.stack.model import StackModel, coefficients_of, render_planes
    from diffcam.core.grid import pad_to

    n, pad, dx, lam, z2 = 64, 32, 4e-6, 532e-9, 0.5e-3
    yy, xx = (np.mgrid[0:n, 0:n] - n // 2) * dx
    theta = (3 * np.sin(2 * np.pi * xx / 90e-6) * np.cos(2 * np.pi * yy / 70e-6)
             + 2 * np.cos(2 * np.pi * (xx + yy) / 130e-6))
    cam = dc.Camera(wavelength=lam, z2=z2, dx=dx, aperture_radius=0.1e-3, shape=(n, n),
                    pad=pad, edge="soft")
    grid = cam.padded_shape
    g = pad_to(cam.aperture() * jnp.exp(1j * jnp.asarray(theta, jnp.float32)), grid)
    c = coefficients_of(g.astype(jnp.complex64), grid, 1, 80)
    m_a, m_b = 1 + z2 / 3e-3, 1 + z2 / 15e-3
    model = StackModel(
        c.real, c.imag, jnp.log(jnp.float32(lam * z2 / (m_a * dx ** 2))),
        jnp.log(jnp.float32(m_b / m_a)), jnp.array([n // 2, n // 2], jnp.float32),
        jnp.log(jnp.float32(1e-3)), jnp.float32(1.0), frame=(n, n), pad=pad, grid=grid,
        stride=1, reference=0, anchor=1, oversample=1, grid_magnification=1 / m_a)
    rendered = render_planes(model, [0.0, 1.0, 0.5])
    m_mid = (m_a + m_b) / 2
    for k, z1 in enumerate((3e-3, 15e-3, z2 / (m_mid - 1))):
        engine = np.asarray(dc.psf(jnp.asarray(theta, jnp.float32), cam, z1))
        assert float(pearson(rendered[k], engine)) > 0.99999, z1
    # the frozen ablation renders the middle plane from the reference's distance: visibly
    # another PSF, so the check above could fail
    frozen = render_planes(dataclasses.replace(model, frozen=True), [1.0])[0]
    engine = np.asarray(dc.psf(jnp.asarray(theta, jnp.float32), cam, 15e-3))
    assert float(pearson(frozen, engine)) < 0.999


def _blobs(shape=(96, 128), seed=1):
    rng = np.random.default_rng(seed)
    img = ndi.gaussian_filter(rng.random(shape), 2.0) ** 4
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return img * np.exp(-((yy - 50) ** 2 + (xx - 60) ** 2) / (2 * 35.0 ** 2))


def test_registration_recovers_magnification_and_fixed_point():
    """A pair made by magnifying an image by 1.07 about an off-centre point (40.3, 70.8):
    the registration recovers both (the frame centre is (47.5, 63.5))."""
    a = _blobs()
    b = magnify_about(a, 1.07, (40.3, 70.8))
    reg = register_magnification(a, b)
    assert abs(reg.magnification - 1.07) < 1e-3
    assert np.hypot(reg.centre[0] - 40.3, reg.centre[1] - 70.8) < 0.3
    assert reg.pearson > 0.999


def test_light_fixes_the_magnification_on_the_shipped_stack():
    """The inverse-square law on measured data: the light of planes 10 and 39 of the
    built-in stack and their registered relative magnification fix M(10) = 1 + z2/z1;
    with it every other plane's light, ∝ (M(t) − 1)², is predicted to 2.5 % (mean 1 %)."""
    from diffcam.data import load_psf_stack_3d
    from diffcam.io.preprocessing import plane_light
    stack = np.asarray(load_psf_stack_3d(), np.float64)
    light = plane_light(stack)
    prepared = prepare_planes(stack[[10, 39]])
    reg = register_magnification(prepared[0], prepared[1])
    m10 = magnification_from_light(light[10], light[39], reg.magnification)
    s = relative_magnification_at(np.arange(44), reg.magnification, 10, 39)
    law = light[10] * ((s * m10 - 1) / (m10 - 1)) ** 2
    error = np.abs(law / light - 1)
    assert 1.3 < m10 < 2.0
    assert error.mean() < 0.01 and error.max() < 0.025


@pytest.mark.slow
def test_predicted_planes_carry_the_light_of_the_measured_ones():
    """``predict(light=True)`` on a fit of planes 10 and 39 of the built-in stack: each
    held-out plane's light relative to plane 10 is its measured light's to 2.5 %, where
    unit-mean planes are off by up to 20 %."""
    from diffcam.data import load_psf_stack_3d
    from diffcam.io.preprocessing import plane_light
    stack = np.asarray(load_psf_stack_3d(), np.float64)
    fit = fit_stack(stack, [10, 39], progress=False, max_steps=1)
    light = plane_light(stack)
    predicted = fit.predict(light=True).astype(np.float64).sum(axis=(1, 2))
    ratio = (predicted / predicted[10]) / (light / light[10])
    assert np.abs(ratio - 1).max() < 0.025
    assert np.abs(light / light[10] - 1).max() > 0.2


def test_light_that_no_point_source_gives_is_refused():
    """A light ratio of 1/m² is a source at infinity (M = ∞), and a brighter far plane
    no source in front of the aperture gives: both a DiffcamError naming the law."""
    with pytest.raises(DiffcamError, match="inverse-square"):
        magnification_from_light(1.0 / 0.9 ** 2, 1.0, 0.9)
    with pytest.raises(DiffcamError, match="inverse-square"):
        magnification_from_light(1.0, 2.0, 0.9)


def test_scaling_baseline_law_and_given_planes():
    """Given planes come back unchanged; a plane between them is the nearest given plane
    magnified by M(t)/M(k) with M linear in the plane index."""
    a = _blobs()
    reg = Registration(1.10, (45.0, 60.0), 1.0)
    b = magnify_about(a, 1.10, reg.centre)
    out = scaling_baseline({0: a, 10: b}, [0, 3, 10], registration=reg)
    np.testing.assert_allclose(out[0], a)
    np.testing.assert_allclose(out[2], b)
    c = (1.10 - 1) / 10  # M(t) ∝ 1 + c·t
    np.testing.assert_allclose(out[1], magnify_about(a, 1 + 3 * c, reg.centre), atol=1e-12)
    with pytest.raises(DiffcamError, match="at least two"):
        scaling_baseline({0: a}, 5)


def _stack(n=6, shape=(32, 40), dtype=np.float32):
    rng = np.random.default_rng(0)
    return (rng.random((n,) + shape) * 100 + 10).astype(dtype)


@pytest.mark.parametrize("planes, error, match", [
    ([0, 6], DiffcamError, "out of range"),
    ([-1, 3], DiffcamError, "out of range"),
    ([3], DiffcamError, "at least 2"),
    ([2, 2], DiffcamError, "more than once"),
    ([1.5, 3], DiffcamError, "integers"),
])
def test_bad_planes(planes, error, match):
    with pytest.raises(error, match=match):
        fit_stack(_stack(), planes, progress=False)


def test_bad_frames():
    frames = [np.ones((32, 40)) + np.eye(32, 40), np.ones((32, 48)) + np.eye(32, 48)]
    with pytest.raises(ShapeError, match="differ in shape"):
        fit_stack(frames, [0, 1], progress=False)
    with pytest.raises(ShapeError, match="differ in shape"):
        fit_stack({0: frames[0], 4: frames[1]}, [0, 4], progress=False)
    stack = _stack()
    stack[3, 5, 7] = np.nan
    stack[3, 6, 7] = np.inf
    with pytest.raises(DiffcamError, match="plane 3 holds 2 NaN/Inf"):
        fit_stack(stack, [1, 3], progress=False)
    stack = _stack()
    stack[4] = 0.0
    with pytest.raises(DiffcamError, match="plane 4 is constant"):
        fit_stack(stack, [1, 4], progress=False)
    with pytest.raises(ShapeError, match=r"\(n_planes, ny, nx\)"):
        fit_stack(_stack()[0], [0, 1], progress=False)


def test_saturated_pixels_are_counted():
    stack = _stack(dtype=np.uint16)
    stack[2, :3, :2] = 65535
    with pytest.raises(DiffcamError, match=r"6 saturated pixel\(s\).*plane 2: 6"):
        fit_stack(stack, [2, 5], progress=False)
    with pytest.raises(DiffcamError, match="saturated"):
        fit_stack(_stack(), [2, 5], saturation=100.0, progress=False)
    for level in (float("nan"), float("inf"), "abc", True):
        with pytest.raises(DiffcamError, match="saturation must be"):
            fit_stack(_stack(), [2, 5], saturation=level, progress=False)


def test_options_validate():
    with pytest.raises(DiffcamError, match="unknown option.*StackFitOptions"):
        StackFitOptions.of(steps=3)
    with pytest.raises(DiffcamError, match="validation_fraction"):
        StackFitOptions(validation_fraction=0.7)
    with pytest.raises(DiffcamError, match="max_steps"):
        StackFitOptions(max_steps=0)
    assert StackFitOptions.of(zetas=64).zetas == (64.0,)
    for bad in (math.inf, math.nan, -1.0):
        with pytest.raises(DiffcamError, match="step_field must be a finite step"):
            StackFitOptions(step_field=bad)
    with pytest.raises(DiffcamError, match="optimiser must be one of"):
        StackFitOptions(optimiser="sgd")


@pytest.mark.slow
@pytest.mark.parametrize("optimiser", ["lbfgs", "nonlinear_cg"])
def test_optimistix_minimisers_descend_the_same_loss(synthetic_stack, optimiser):
    """The optimistix alternatives to Adam run the same loss, start and validation
    stopping: the training Pearson rises, and no parameter outside the fitted groups
    (κ, not fitted by default) moves."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StackFitWarning)
        fit = fit_stack(synthetic_stack, GIVEN, progress=False, zetas=(64.0,), max_steps=15,
                        time_budget=math.inf, optimiser=optimiser)
    assert fit.history[-1] > fit.history[0]
    assert len(fit.validation) == fit.steps
    assert float(fit.model.kappa) == 1.0


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::diffcam.calibrate.stack.fit.StackFitWarning")
def test_cli_fit_predict_compare_round_trip(tmp_path, capsys):
    """`diffcam fit` on a crop of the built-in stack, then `predict` and `compare-stack`."""
    from diffcam.data import load_psf_stack_3d

    import tifffile

    stack = load_psf_stack_3d()[:16, 100:164, 120:200]
    src = tmp_path / "crop.npy"
    np.save(src, stack)
    model = tmp_path / "model.npz"
    assert main(["fit", str(src), "--planes", "4,12", "--max-steps", "4", "--no-progress",
                 "--time-budget", "900", "--pixel", "3.45um", "-o", str(model)]) == 0
    out = capsys.readouterr().out
    assert "stopped: max_steps (4)" in out and "scaling baseline" in out
    assert "from a start at 4 px² (the default" in out     # where ζ_ref started, and why
    fit = load_stack_fit(model)
    assert fit.planes == (4, 12) and fit.steps == 4
    assert fit.identifiable["lambda_z2_M_reference_m2"] > 0 and "z2_M_reference_m" not in fit.identifiable
    pred = tmp_path / "pred.tif"
    assert main(["predict", str(model), "--planes", "0:10", "-o", str(pred)]) == 0
    images = tifffile.imread(pred)
    assert images.shape == (11, 64, 80) and np.isfinite(images).all()
    np.testing.assert_allclose(images, fit.predict(range(11)), rtol=1e-6)
    # `diffcam psf` takes the model too (plane indices, not depths)
    via_psf = tmp_path / "via_psf.tif"
    assert main(["psf", str(model), "--planes", "0:10", "-o", str(via_psf)]) == 0
    np.testing.assert_array_equal(tifffile.imread(via_psf), images)
    alone, alone_psf = tmp_path / "alone.tif", tmp_path / "alone_psf.tif"   # the alias
    assert main(["predict", str(model), "--planes", "2,7", "--kappa", "0", "--rendered-only",
                 "-o", str(alone)]) == 0
    assert main(["psf", str(model), "--planes", "2,7", "--kappa", "0", "--rendered-only",
                 "-o", str(alone_psf)]) == 0
    np.testing.assert_array_equal(tifffile.imread(alone_psf), tifffile.imread(alone))
    np.testing.assert_allclose(tifffile.imread(alone),
                               fit.predict([2, 7], kappa=0, residual=False), rtol=1e-6)
    capsys.readouterr()
    assert main(["psf", str(model), "--z1", "25mm", "--z2", "1mm", "-o", str(via_psf)]) == 2
    assert "stack-fit model" in capsys.readouterr().err
    np.testing.assert_array_equal(tifffile.imread(via_psf), images)   # left as it was
    fig, js = tmp_path / "cmp.png", tmp_path / "cmp.json"
    assert main(["compare-stack", str(src), "--model", str(model), "-o", str(fig),
                 "--json", str(js)]) == 0
    result = json.loads(js.read_text())
    assert len(result["per_plane"]) == 16 and fig.stat().st_size > 0
    js2 = tmp_path / "cmp2.json"        # `diffcam compare --model` is the same comparison
    assert main(["compare", str(src), "--model", str(model), "-o", str(fig),
                 "--json", str(js2)]) == 0
    assert json.loads(js2.read_text()) == result
    assert result["mean_held_out"]["held_out"] == 14
    # a bad planes argument is a usage error; a plane out of range is a DiffcamError
    assert main(["fit", str(src), "--planes", "4,40", "-o", str(model)]) == 2
    assert "out of range" in capsys.readouterr().err


def _fit_file(path) -> tuple[dict, dict]:
    """A model file's arrays, and its metadata without the wall times."""
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files if k != "metadata"}
        meta = json.loads(str(data["metadata"][()]))
    del meta["seconds"], meta["registration"]["seconds"]
    return arrays, meta


def _same_fit_files(a, b) -> None:
    (arrays_a, meta_a), (arrays_b, meta_b) = _fit_file(a), _fit_file(b)
    assert sorted(arrays_a) == sorted(arrays_b)
    for key in arrays_a:
        np.testing.assert_array_equal(arrays_a[key], arrays_b[key], err_msg=key)
    assert meta_a == meta_b


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::diffcam.calibrate.stack.fit.StackFitWarning")
def test_cli_fit_stops_on_steps_and_repeats_exactly(tmp_path, capsys):
    """By default `diffcam fit` has no wall-clock limit: it stops on its step budget,
    which the file records with the seed, and a second run writes the same arrays and
    metadata (wall times aside). `--time-budget` still stops it on the clock."""
    from diffcam.data import load_psf_stack_3d

    src = tmp_path / "crop.npy"
    np.save(src, load_psf_stack_3d()[:16, 100:164, 120:200])
    runs = [tmp_path / "a.npz", tmp_path / "b.npz"]
    for out in runs:
        assert main(["fit", str(src), "--planes", "4,12", "--max-steps", "6",
                     "--no-progress", "-o", str(out)]) == 0
    assert "stopped: max_steps (6)" in capsys.readouterr().out
    _same_fit_files(*runs)
    options = _fit_file(runs[0])[1]["options"]
    assert (options["seed"], options["max_steps"], options["time_budget"]) == (0, 6, None)
    assert main(["fit", str(src), "--planes", "4,12", "--time-budget", "1e-3",
                 "--no-progress", "-o", str(tmp_path / "c.npz")]) == 0
    assert "stopped: time budget (0.001 s); best step 0 of 1" in capsys.readouterr().out


@pytest.mark.slow   # two fits of the README's planes: 9.4 min on 2 cores at load 12–15
def test_readme_fit_is_the_same_on_a_busy_machine(tmp_path):
    """The README's `diffcam fit captures/psfs --planes 5,27`, run twice in fresh
    processes, the second with both cores kept busy by two spinning processes: the
    model files hold identical arrays and metadata (wall times aside)."""
    import subprocess
    import sys

    env = dict(os.environ, DIFFCAM_PROGRESS="0")
    diffcam = [sys.executable, "-m", "diffcam"]
    subprocess.run([*diffcam, "data", "usaf3d", "-o", str(tmp_path / "captures")],
                   check=True, env=env, capture_output=True)
    runs = [tmp_path / "idle.npz", tmp_path / "busy.npz"]
    spin = [sys.executable, "-c", "while 1: pass"]
    for k, out in enumerate(runs):
        spinners = [subprocess.Popen(spin) for _ in range(2 * k)]
        try:
            subprocess.run([*diffcam, "fit", str(tmp_path / "captures" / "psfs"),
                            "--planes", "5,27", "-o", str(out)],
                           check=True, env=env, capture_output=True, timeout=1800)
        finally:
            for p in spinners:
                p.kill()
                p.wait()
    _same_fit_files(*runs)


@pytest.mark.slow   # two fits' compilation: 18 s
def test_distance_starts_from_the_physical_inputs(synthetic_stack):
    """With pixel pitch, wavelength and z2 the ζ start is the far-source value
    o²·λ·z2/pitch² (fine samples²); a scan keeps the candidate with the best validation
    after its short descent, and records every candidate's."""
    pitch, lam, z2 = 4e-6, 532e-9, 0.6e-3
    fit = fit_stack(synthetic_stack, [2, 9], progress=False, max_steps=1,
                    pixel_pitch=pitch, wavelength=lam, z2=z2)
    assert list(fit.zeta_scan) == [pytest.approx(4 * lam * z2 / pitch ** 2)]
    scan = fit_stack(synthetic_stack, [2, 9], progress=False, max_steps=1, scan_steps=3,
                     zetas=(4.0, 64.0))
    assert sorted(scan.zeta_scan) == [4.0, 64.0]
    best = max(scan.zeta_scan, key=scan.zeta_scan.get)
    assert scan.model.zeta_pixels * 4 == pytest.approx(best, rel=0.05)


@pytest.mark.parametrize("oversample", [2, 3])
def test_default_distance_start_is_in_pixels(oversample):
    """Without physical inputs ζ_ref starts at ZETA_START pixel² whatever the
    oversampling (o² fine samples per pixel²), not at a fixed number of fine samples."""
    from diffcam.calibrate.stack.fit import ZETA_START, _zetas
    opts = StackFitOptions(oversample=oversample, field_stride=oversample)
    none = dict(pixel_pitch=None, wavelength=None, z2=None)
    assert _zetas(opts, none) == (ZETA_START * oversample ** 2,)
