"""The scaling baseline (diffcam.evaluate.baseline) and PSF-fidelity metrics (diffcam.evaluate.metrics)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.registration import phase_cross_correlation

from diffcam.model.camera import Camera, random_diffuser
from diffcam.evaluate.metrics import fourier_shift, pearson, psf_fidelity, registration_shift
from diffcam.evaluate.baseline import magnify_psf, relative_magnification
from diffcam.model.stack import psf_stack

LAM = 532e-9
DEPTHS = np.array([22e-3, 24e-3, 26e-3, 28e-3, 30e-3])


def baseline_pearson(z2, feature, degrees, n=640, dx=5e-6):
    """Pearson of magnify_psf(PSF at 22 mm) against the modelled PSF at each depth."""
    cam = Camera(wavelength=LAM, z2=z2, dx=dx, aperture_radius=1.2e-3, shape=(n, n))
    phase = random_diffuser(jax.random.key(0), (n, n), dx, LAM, feature, np.deg2rad(degrees))
    stack = psf_stack(phase, cam, DEPTHS, batch_size=5)
    predicted = magnify_psf(stack[0], dx, DEPTHS[0], DEPTHS, z2)
    return np.asarray(pearson(predicted, stack))


@pytest.mark.slow
def test_baseline_near_exact_in_paper_geometry():
    """Paper's simulated geometry (z2 = 1 mm, aperture radius 1.2 mm, 5 µm pitch, a
    60 µm / 0.5° diffuser on 640²): an error-free reference at 22 mm, magnified, matches
    the model at 22–30 mm with Pearson > 0.999 (measured 0.9998–0.9999): z_eff moves by
    only 12 µm (docs/design.md)."""
    p = baseline_pearson(1e-3, 60e-6, 0.5)
    assert p[0] > 0.99999
    assert np.all(p > 0.999), p


@pytest.mark.slow
def test_baseline_degrades_with_depth_when_diffraction_dominates():
    """z2 = 5 mm, 30 µm / 1° diffuser: z_eff moves by 0.21 mm over 22→30 mm and the
    magnified reference departs from the model: Pearson falls monotonically, from
    > 0.95 at 24 mm to < 0.9 at 30 mm (measured 0.98, 0.94, 0.90, 0.87)."""
    p = baseline_pearson(5e-3, 30e-6, 1.0)
    assert np.all(np.diff(p) < 0), p
    assert p[1] > 0.95 and p[-1] < 0.9, p


def test_relative_magnification_and_identity():
    """m = 1 at z1_ref (the reference is returned unchanged, 1e-6); m > 1 for closer
    sources; a shape (nz,) of depths gives (nz, ny, nx)."""
    assert float(relative_magnification(22e-3, 22e-3, 1e-3)) == 1.0
    assert float(relative_magnification(22e-3, 20e-3, 1e-3)) > 1.0
    x = np.arange(64) - 32
    ref = np.exp(-(x[:, None] ** 2 + x[None, :] ** 2) / 40.0).astype(np.float32)
    out = magnify_psf(ref, 5e-6, 22e-3, np.array([22e-3, 30e-3]), 1e-3)
    assert out.shape == (2, 64, 64)
    np.testing.assert_allclose(out[0], ref, atol=1e-6)
    np.testing.assert_allclose(out.sum(axis=(-2, -1)), ref.sum(), rtol=1e-5)


@pytest.mark.slow  # 6 s of float64 compilation; magnify_psf's values by default
@pytest.mark.usefixtures("debug_nans")
def test_scale_psf_jit_grad_vmap(x64):
    """magnify_psf is differentiable in z1 (vs central difference of relative step 1e-6,
    rtol 1e-4) and vmaps over depths."""
    x = np.arange(64) - 32
    ref = jnp.asarray(np.exp(-((x[:, None] - 3) ** 2 + x[None, :] ** 2) / 40.0))
    w = jnp.asarray(np.random.default_rng(0).random((64, 64)))
    f = jax.jit(lambda z: jnp.sum(w * magnify_psf(ref, 5e-6, 22e-3, z, 5e-3)))
    g = jax.grad(f)(26e-3)
    h = 26e-9
    np.testing.assert_allclose(g, (f(26e-3 + h) - f(26e-3 - h)) / (2 * h), rtol=1e-4)
    v = jax.vmap(lambda z: magnify_psf(ref, 5e-6, 22e-3, z, 5e-3))(jnp.array([24e-3, 28e-3]))
    np.testing.assert_allclose(v[1], magnify_psf(ref, 5e-6, 22e-3, 28e-3, 5e-3), atol=1e-12)


# ------------------------------------------------------------------- fidelity metrics

@pytest.mark.parametrize("shift", [(3.37, -7.81), (-12.05, 0.5), (0.0, 0.0)])
def test_registration_matches_skimage(shift):
    """registration_shift equals skimage's phase_cross_correlation (same upsampling 20)
    and recovers a known Fourier shift to 1/20 pixel."""
    rng = np.random.default_rng(1)
    from scipy.ndimage import gaussian_filter
    ref = gaussian_filter(rng.random((96, 80)), 3).astype(np.float32)
    moved = np.asarray(fourier_shift(ref, jnp.asarray(shift)))
    ours = np.asarray(registration_shift(moved, ref, upsample=20))
    theirs = phase_cross_correlation(ref, moved, upsample_factor=20)[0]
    np.testing.assert_allclose(ours, theirs, atol=1e-6)
    np.testing.assert_allclose(ours, -np.asarray(shift), atol=0.05 + 1e-6)


@pytest.mark.slow
@pytest.mark.usefixtures("debug_nans")
def test_psf_fidelity_per_depth_and_transforms():
    """psf_fidelity registers, min–max normalises and scores each leading index: a
    shifted, rescaled copy scores Pearson and SSIM > 0.999; an unrelated PSF scores
    low. jit, vmap and grad (w.r.t. the model) work; the shift has zero gradient."""
    cam = Camera(wavelength=LAM, z2=1e-3, dx=4e-6, aperture_radius=0.15e-3, shape=(96, 96))
    ph = random_diffuser(jax.random.key(2), (96, 96), 4e-6, LAM, 40e-6)
    model = psf_stack(ph, cam, np.array([22e-3, 30e-3]))
    measured = 7.0 * np.asarray(fourier_shift(model, jnp.array([[2.3, -1.1], [0.4, 5.0]])))
    s = psf_fidelity(model, measured)
    assert s["pearson"].shape == (2,) and s["shift"].shape == (2, 2)
    assert np.all(np.asarray(s["pearson"]) > 0.999) and np.all(np.asarray(s["ssim"]) > 0.999)
    other = psf_stack(random_diffuser(jax.random.key(9), (96, 96), 4e-6, LAM, 40e-6),
                      cam, np.array([22e-3]))
    assert float(psf_fidelity(other[0], measured[0])["pearson"]) < 0.5
    jitted = jax.jit(psf_fidelity)(model, measured)
    np.testing.assert_allclose(jitted["pearson"], s["pearson"], rtol=1e-5)
    mapped = jax.vmap(psf_fidelity)(model, measured)
    np.testing.assert_allclose(mapped["ssim"], s["ssim"], rtol=1e-5)
    g = jax.grad(lambda m: psf_fidelity(m, measured[0])["pearson"])(jnp.asarray(model[0]))
    assert np.isfinite(np.asarray(g)).all() and float(jnp.abs(g).max()) > 0
