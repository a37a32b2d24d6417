"""The higher-fidelity simulator that makes the demo's data (calibrate.simulation): it
reduces to diffcam's model in the model's own limit, keeps power, and differs from the
model otherwise (so the demo's scores cannot be 1 by construction)."""

import numpy as np
import pytest

import diffcam as dc
from diffcam.calibrate.simulation import (high_fidelity_captures, high_fidelity_psfs,
                                          paper_simulation)

MONO = (np.array([532e-9]), np.array([1.0]))


@pytest.fixture(scope="module")
def sim():
    return paper_simulation(256, 128)          # the paper's set-up, scaled down


@pytest.fixture(scope="module")
def camera():
    return dc.Camera(wavelength=532e-9, z2=1e-3, dx=5e-6, aperture_radius=1.2e-3 / 4,
                     shape=(256, 256), crop=(192, 192))


def _pearson(a, b):
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def test_model_limit_is_diffcams_psf(sim, camera):
    """No oversampling, one wavelength, a point source, no noise: diffcam's own PSF."""
    hf = high_fidelity_psfs(sim.phase, camera, [25e-3], oversample=1, spectrum=MONO,
                            source_radius=0.0)[0]
    model = np.asarray(dc.psf(sim.phase, camera, 25e-3))
    assert np.abs(hf - model).max() < 1e-4 * model.max()


def test_psfs_differ_from_the_model_but_not_wildly(sim, camera):
    """The full simulation (2× grid, 3 wavelengths, 50 µm source, pixels) against the
    true phase through diffcam's model: close, never equal (0.970 measured)."""
    hf = high_fidelity_psfs(sim.phase, camera, [25e-3])[0]
    model = np.asarray(dc.psf(sim.phase, camera, 25e-3))
    assert np.isclose(hf.sum(), 1, atol=1e-4)
    assert 0.9 < _pearson(hf, model) < 0.995


def test_noise_is_poisson_at_the_stated_peak(sim, camera):
    """With photons=100 the PSF is integer counts (scaled to unit sum): in units of the
    smallest non-zero count (one photon) every value is an integer, the peak near 100."""
    hf = high_fidelity_psfs(sim.phase, camera, [25e-3], photons=100.0, seed=1)[0]
    counts = hf / hf[hf > 0].min()
    assert np.allclose(counts, np.round(counts), atol=1e-3)
    assert 60 < counts.max() < 160
    assert np.isclose(hf.sum(), 1, atol=1e-5)


@pytest.mark.slow
def test_captures_keep_power_and_shape(sim):
    """One wavelength, no noise: the 2×-finer captures binned to the grid carry the
    model's power (near 1.002, far 0.992 measured) and pattern (Pearson > 0.99)."""
    near, far = high_fidelity_captures(sim.phase, 1.2e-3 / 4, sim.geometry, spectrum=MONO,
                                       photons=None)
    for got, want in ((near, sim.near), (far, sim.far)):
        want = np.asarray(want)
        assert got.shape == want.shape
        assert abs(got.sum() / want.sum() - 1) < 0.02
        assert _pearson(got, want) > 0.99
