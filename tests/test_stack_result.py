"""A fitted stack's prediction (diffcam.calibrate.stack.result.StackFit.predict) against
its formula evaluated with SciPy's splines, and the NumPy spline magnification it
carries residuals with (diffcam.evaluate.registration) against scipy.ndimage."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

from diffcam.calibrate.stack.model import StackModel, coefficient_shape, render_planes
from diffcam.calibrate.stack.result import StackFit
from diffcam.evaluate.registration import (Registration, bracket_weights, magnify_about,
                                           relative_magnification_at, spline_coefficients)


def _scipy_magnify(coef, magnification, centre):
    h, w = coef.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    coords = np.stack([centre[0] + (yy - centre[0]) / magnification,
                       centre[1] + (xx - centre[1]) / magnification])
    return ndi.map_coordinates(coef, coords, order=3, mode="constant", cval=0.0,
                               prefilter=False)


@pytest.mark.parametrize("shape", [(270, 320), (64, 48), (5, 7), (2, 3)])
def test_spline_magnification_is_scipys(shape):
    """spline_coefficients is scipy.ndimage.spline_filter(order=3) and magnify_about is
    map_coordinates(order=3, mode="constant"), to 1e-12 of the image's scale: centres
    inside, on the edge and far outside the frame, magnifications above and below 1."""
    rng = np.random.default_rng(sum(shape))
    img = rng.normal(size=shape)
    coef = spline_coefficients(img)
    np.testing.assert_allclose(coef, ndi.spline_filter(img, order=3), rtol=0, atol=1e-12)
    h, w = shape
    for m, centre in [(0.9, (h / 2, w / 2)), (1.13, (1.2, w - 0.3)), (0.85, (-20.0, 400.0)),
                      (1.0, (0.0, 0.0)), (1.5, (h / 3, w / 4))]:
        expected = _scipy_magnify(ndi.spline_filter(img, order=3), m, centre)
        np.testing.assert_allclose(magnify_about(coef, m, centre, prefiltered=True),
                                   expected, rtol=0, atol=1e-12)
        np.testing.assert_allclose(magnify_about(img, m, centre), expected, rtol=0,
                                   atol=1e-12)


@pytest.fixture(scope="module")
def small_fit():
    """A StackFit of a 24×32 frame: a random band-limited field (not a fit), given planes
    2 and 9 measured as the rendering plus a smooth pattern it does not reproduce."""
    frame, pad, stride = (24, 32), 8, 2
    grid = (2 * frame[0] + 2 * pad, 2 * frame[1] + 2 * pad)
    rng = np.random.default_rng(3)
    coarse = coefficient_shape(grid, stride)
    model = StackModel(
        jnp.asarray(rng.normal(size=coarse), jnp.float32),
        jnp.asarray(rng.normal(size=coarse), jnp.float32), jnp.log(jnp.float32(12.0)),
        jnp.log(jnp.float32(0.9)), jnp.array([11.0, 17.5], jnp.float32),
        jnp.log(jnp.float32(0.6)), jnp.float32(1.0), frame=frame, pad=pad, grid=grid,
        stride=stride, reference=2, anchor=9)
    planes = (2, 9)
    yy, xx = np.mgrid[0:frame[0], 0:frame[1]]
    measured = np.stack([r / r.mean() + 0.3 * np.sin(xx / 3.0 + k) * np.cos(yy / 4.0)
                         for k, r in enumerate(render_planes(model, planes))])
    return StackFit(model=model, planes=planes, n_planes=12,
                    registration=Registration(0.9, (11.0, 17.5), 1.0),
                    history=np.zeros(1), validation=np.zeros(1), stop_reason="test",
                    best_step=0, validation_score=1.0, baseline_validation=1.0,
                    worse_than_baseline=False, zeta_scan={}, identifiable={}, physical={},
                    options={}, seconds=0.0, measured=measured.astype(np.float32))


def _formula(fit, ts):
    """The module docstring's prediction, step by step with SciPy's splines."""
    m, planes = fit.model, list(fit.planes)
    rendered = render_planes(m, planes + ts)
    given, rendered = rendered[:len(planes)], rendered[len(planes):]
    gain, coef = {}, {}
    for k, y, p in zip(planes, fit.measured.astype(np.float64), given):
        a, b = np.polyfit(p.ravel(), y.ravel(), 1)
        gain[k], coef[k] = a, ndi.spline_filter(y - a * p - b, order=3)
    law = lambda t: relative_magnification_at(  # noqa: E731
        t, np.exp(float(m.log_s)), m.reference, m.anchor)
    centre = tuple(float(c) for c in np.asarray(m.centre))
    out = []
    for n, t in enumerate(ts):
        w = bracket_weights(t, planes)
        plane = sum(v * gain[k] for k, v in w.items()) * rendered[n]
        plane += sum(v * _scipy_magnify(coef[k], law(t) / law(k), centre)
                     for k, v in w.items())
        out.append(plane / plane.mean())
    return np.asarray(out)


def test_prediction_is_the_formula_with_scipy_splines(small_fit):
    """Every plane of the stack, planes outside the given range and a repeated plane:
    equal to the formula to 1e-6 of the stack's scale."""
    ts = list(range(12)) + [15, -3, 5, 5]
    predicted = small_fit.predict(ts)
    expected = _formula(small_fit, ts)
    assert np.abs(predicted - expected).max() <= 1e-6 * np.abs(expected).max()
    rendered = small_fit.predict([4], residual=False)[0]
    assert np.abs(rendered - predicted[4]).max() > 1e-2  # the residual is carried
