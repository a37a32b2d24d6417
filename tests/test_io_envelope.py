"""The PSF stack's vertical envelope matched to a capture (diffcam.io.preprocessing:
envelope_widths, apply_envelope)."""

import numpy as np
import pytest
from scipy.signal import fftconvolve

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.io import apply_envelope, envelope_widths

NY, NX, M = 96, 80, 64


def _footprints(nz=4):
    """Flat-topped footprints, taller for nearer planes, rows 8 … 56 at plane 0."""
    rng = np.random.default_rng(3)
    psfs = np.zeros((nz, M, M), np.float32)
    for z in range(nz):
        half = 24 - 2 * z
        psfs[z, 32 - half:32 + half, 12:52] = rng.uniform(0.5, 1.5, (2 * half, 40))
    return psfs


def _capture(psfs):
    """A crop-model capture (valid part of the full convolution) of a small scene: two
    bars on plane 1, a dot on plane 2."""
    scene = np.zeros((len(psfs), NY + M - 1, NX + M - 1))
    scene[1, 70:74, 60:90] = 1
    scene[2, 90, 70] = 5
    return sum(fftconvolve(scene[z], psfs[z], mode="valid") for z in range(len(psfs)))


def test_apply_envelope_is_the_gaussian_about_each_planes_centre():
    """Closed form: a plane's centre row keeps its values, the rows σ away carry
    exp(-1/2) of them."""
    psfs = np.ones((2, 41, 5), np.float32)
    out = apply_envelope(psfs, [4.0, 10.0])
    np.testing.assert_allclose(out[:, 20], 1, rtol=1e-6)
    np.testing.assert_allclose(out[0, [16, 24]], np.exp(-0.5), rtol=1e-5)
    np.testing.assert_allclose(out[1, [10, 30]], np.exp(-0.5), rtol=1e-5)


def _heights(psfs):
    """rms height of each plane's light, pixels."""
    profile = psfs.sum(axis=2)
    rows = np.arange(psfs.shape[1])
    centre = profile @ rows / profile.sum(axis=1)
    return np.sqrt(profile @ rows ** 2 / profile.sum(axis=1) - centre ** 2)


def test_widths_recover_the_envelope_a_capture_was_made_with():
    """A capture made with footprints apodised by σ_z = 14 px · (plane's rms height /
    the tallest plane's) gives back these widths within 5 % (all planes fitted)."""
    psfs = _footprints()
    truth = 14.0 * _heights(psfs) / _heights(psfs).max()
    widths = envelope_widths(_capture(apply_envelope(psfs, truth)), psfs, samples=4)
    np.testing.assert_allclose(widths, truth, rtol=0.05)


def test_a_capture_of_the_psfs_as_measured_asks_for_no_envelope():
    """Made with the footprints as they are, the capture's profile is explained best by
    envelopes so wide that they change no PSF value by more than 2 %."""
    psfs = _footprints()
    out = apply_envelope(psfs, envelope_widths(_capture(psfs), psfs))
    assert np.all(out >= 0.98 * psfs)


def test_bad_inputs_are_refused():
    psfs = _footprints()
    with pytest.raises(ShapeError, match="my <= ny"):
        envelope_widths(np.ones((10, 80)), psfs)
    with pytest.raises(DiffcamError, match="light"):
        envelope_widths(np.zeros((NY, NX)), psfs)
    with pytest.raises(DiffcamError, match="widths > 0"):
        apply_envelope(psfs, [1.0, 2.0])
    with pytest.raises(DiffcamError, match="widths > 0"):
        apply_envelope(psfs, [1.0, 0.0, 1.0, 1.0])


def test_widths_scale_with_the_pixel_grid_on_the_shipped_capture():
    """The shipped 3-D capture: the widths (σ ≈ 100 px on plane 0, decreasing with the
    planes' height) double when every row is repeated twice (the fit then bins the
    540-row profiles to 90 rows as it bins the 270-row ones to 90): within 2 %."""
    from diffcam.data import load_psf_stack_3d, load_raw_3d

    raw, psfs = load_raw_3d(), np.clip(load_psf_stack_3d() - 2 / 65535, 0, None)
    widths = envelope_widths(raw, psfs)
    assert 90 < widths[0] < 110 and np.all(np.diff(widths) < 0)
    doubled = envelope_widths(np.repeat(raw, 2, axis=0), np.repeat(psfs, 2, axis=1))
    np.testing.assert_allclose(doubled, 2 * widths, rtol=0.02)
