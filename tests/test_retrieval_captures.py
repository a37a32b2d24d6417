"""Captures in: preprocessing, resampling to the Fourier-lens pitch, synthetic captures."""

import jax
import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.core.grid import crop_to, yx
from diffcam.evaluate.metrics import phase_scores
from diffcam.calibrate import (CalibrationGeometry, centre_on_axis, centroid, merge_exposures,
                               normalise_min_max, paper_simulation, prepare_captures, raar,
                               resample_far_field, synthetic_captures)

N, SENSOR = 128, 3.45e-6
# f = 6 mm puts the Fourier-lens pitch of the scaled-down 128² problem at 4.99 µm, so a
# 3.45 µm sensor of 184² pixels covers both captures (as f = 5 cm does at 1024²)
GEOMETRY = CalibrationGeometry(dx=5e-6, wavelength=532e-9, focal_length=6e-3)
SENSOR_SHAPE = (184, 184)


@pytest.fixture(scope="module")
def sim():
    return paper_simulation(N, 64)


def retrieve_from_raw(sim, near_raw, far_raw, exposure, pitch_error):
    kw = dict(background=(82, 82), exposure=exposure, saturation=4095, centre=False)
    near = prepare_captures(near_raw, far_raw, GEOMETRY, (N, N), sensor_pitch=SENSOR, **kw).near
    far = prepare_captures(near_raw, far_raw, GEOMETRY, (N, N),
                           sensor_pitch=SENSOR * (1 + pitch_error), **kw).far
    r = raar(near, far, GEOMETRY, iterations=300, key=jax.random.key(0), restarts=2)
    return phase_scores(crop_to(r.phase, sim.truth.shape), sim.truth, mask=sim.mask)


@pytest.mark.slow
def test_noisy_synthetic_captures(sim):
    """Poisson 1e4 photons at peak, 12 bits, 2 % background, pixel integration at 3.45 µm,
    far pitch 1 % wrong: one exposure still gives twin-resolved P > 0.9; an exposure
    series (1, 30, 1000) recovers the faint speckle halo and P > 0.98."""
    key = jax.random.key(5)
    near_raw, far_raw = synthetic_captures(sim.phase, sim.aperture, GEOMETRY, key,
                                           sensor_pitch=SENSOR, sensor_shape=SENSOR_SHAPE)
    assert near_raw.max() <= 4095 and np.all(near_raw == np.round(near_raw))
    single = retrieve_from_raw(sim, near_raw, far_raw, (1.0, 1.0), 0.01)
    times = (1.0, 30.0, 1000.0)
    near_raw, far_series = synthetic_captures(sim.phase, sim.aperture, GEOMETRY, key,
                                              sensor_pitch=SENSOR, sensor_shape=SENSOR_SHAPE,
                                              far_exposures=times)
    assert far_series.shape == (3,) + SENSOR_SHAPE and far_series[2].max() == 4095
    hdr = retrieve_from_raw(sim, near_raw, far_series, (1.0, times), 0.01)
    assert float(single["twin_resolved"]) > 0.9
    assert float(hdr["twin_resolved"]) > 0.98
    assert float(hdr["mse_twin_resolved"]) < float(single["mse_twin_resolved"])


def test_resample_far_field_matches_a_gaussian():
    """A Gaussian of 40 µm waist recorded at 3.45 µm reads as the same Gaussian on the
    Fourier-lens grid (closed form at the new sample positions)."""
    w = 40e-6
    y, x = yx(SENSOR_SHAPE, SENSOR)
    img = np.exp(-(x ** 2 + y ** 2) / w ** 2)
    out = resample_far_field(img, SENSOR, GEOMETRY, (N, N))
    fy, fx = yx((N, N), GEOMETRY.far_pitch((N, N))[0])
    np.testing.assert_allclose(out, np.exp(-(fx ** 2 + fy ** 2) / w ** 2), atol=2e-3)


def test_centring_and_normalisation():
    img = np.zeros((64, 64), np.float32)
    img[40:43, 10:13] = 1.0
    assert centroid(img) == pytest.approx((41 - 32, 11 - 32))
    centred, shift = centre_on_axis(img)
    assert shift == (-9, 21) and centroid(centred) == pytest.approx((0.0, 0.0))
    n = normalise_min_max(img * 7 + 3)
    assert n.min() == 0 and n.max() == 1


def test_merge_exposures_closed_form():
    """Pixel values s per unit time; exposure t reads bg + s·t, clipped at 4095."""
    s = np.array([[0.5, 3.0], [40.0, 400.0]], np.float32)
    t = np.array([1.0, 10.0, 100.0])
    raws = np.minimum(10 + s[None] * t[:, None, None], 4095)
    merged, usable = merge_exposures(raws, t, background=10, saturation=4095)
    np.testing.assert_allclose(merged, s, rtol=1e-5)
    assert usable.all()


@pytest.mark.parametrize("near, far, background, error", [
    (np.full((50, 50), 4095.0), None, 0, "saturated everywhere"),
    (np.full((50, 50), 100.0), None, 500, "background"),
    (np.full((50, 50), 100.0), None, 100, "all zero"),
    (np.where(np.eye(50) > 0, np.nan, 100.0), None, 0, "NaN"),
    (np.ones((3, 50, 50, 2)), None, 0, "2-D"),
])
def test_bad_captures(near, far, background, error):
    far = np.random.default_rng(0).uniform(100, 200, (50, 50)) if far is None else far
    with pytest.raises(DiffcamError, match=error):
        prepare_captures(near, far, GEOMETRY, (N, N), sensor_pitch=SENSOR,
                         background=(background, 0), saturation=4095)
