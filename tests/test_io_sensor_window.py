"""The sensor window fitted to a capture (diffcam.io.preprocessing: SensorWindow,
fit_sensor_window)."""

import numpy as np
import pytest
from scipy.signal import fftconvolve

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.io import SensorWindow, fit_sensor_window

NY, NX, M = 120, 90, 80
AXIS = 36.0      # the PSF row the planes magnify about (PSF row 40 is sensor row 60)


def _stack(nz=4):
    """Footprints magnified about PSF row ``AXIS``: plane ``z`` covers rows 4 … 70 at
    plane 0, 4 % less per plane (edge rows partly: the row centroids are exact), each
    row the same random texture along x."""
    rng = np.random.default_rng(4)
    rows, texture = np.arange(M), rng.uniform(0.2, 1.0, M) * (np.abs(np.arange(M) - 40) < 30)
    psfs = np.zeros((nz, M, M))
    for z in range(nz):
        top, bottom = (AXIS + (1 - 0.04 * z) * (edge - AXIS) for edge in (4, 70))
        cover = np.clip(np.minimum(rows + 0.5, bottom) - np.maximum(rows - 0.5, top), 0, 1)
        psfs[z] = cover[:, None] * texture[None]
    return psfs


def _capture(psfs, window=None):
    """The crop-model capture of a compact scene (dots within 8 rows of the axis on
    every plane), times the sensor window's response (if any): without a window its
    row profile is as tall as the footprints, which no non-negative scene narrows."""
    rng = np.random.default_rng(5)
    shape = (len(psfs), NY + M - 1, NX + M - 1)
    scene = (rng.random(shape) > 0.9) * rng.uniform(1, 3, shape)
    rows = np.arange(shape[1])[:, None]
    scene *= np.abs(rows - (NY // 2 + M - 1 - M // 2)) < 8      # on-axis points
    capture = sum(fftconvolve(scene[z], psfs[z], mode="valid") for z in range(len(psfs)))
    return capture if window is None else capture * window.response(capture.shape)


def test_response_is_the_gaussian_about_the_centre_row():
    s = SensorWindow(centre_row=10.0, sigma=4.0).response((30, 7))
    assert s.shape == (30, 1) and s.dtype == np.float32
    np.testing.assert_allclose(s[10, 0], 1.0)
    np.testing.assert_allclose(s[14, 0], np.exp(-0.5), rtol=1e-6)


@pytest.mark.parametrize("sigma", [15.0, 20.0])
def test_fit_recovers_a_known_window(sigma):
    """A capture made with a known window narrower than the footprints (half-height
    33 px): the centre is the planes' magnification row (to 0.5 px); σ within 25 %
    (the L1 term biases it wide: 16.8 and 23.9 px here)."""
    psfs = _stack()
    truth = SensorWindow(AXIS + NY // 2 - M // 2, sigma)
    fitted = fit_sensor_window(_capture(psfs, truth), psfs)
    assert abs(fitted.centre_row - truth.centre_row) < 0.5
    assert 0.95 < fitted.sigma / sigma < 1.25


def test_capture_without_a_window_fits_a_wide_one():
    """The PSFs as they are explain the capture: σ far wider than the footprints."""
    psfs = _stack()
    assert fit_sensor_window(_capture(psfs), psfs).sigma > 3 * M


def test_bad_input_is_refused():
    psfs = _stack()
    with pytest.raises(ShapeError):
        fit_sensor_window(np.ones((10, 80)), psfs)
    with pytest.raises(DiffcamError, match="light"):
        fit_sensor_window(np.zeros((NY, NX)), psfs)
    with pytest.raises(DiffcamError, match="light_weight"):
        fit_sensor_window(_capture(psfs), psfs, light_weight=1.5)
