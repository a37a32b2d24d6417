"""The camera's off-axis terms (diffcam.model.off_axis): the stop's shadow, the sensor's
angular response and vignetting, against closed forms, the other PSF path, finite
differences and the transformations."""

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core.errors import DiffcamError, SamplingError
from diffcam.model import Camera, psf, psf_stack, random_diffuser
from diffcam.model.off_axis import acceptance, response_amplitude
from diffcam.model.stack import camera_record

LAM, DX, Z2 = 532e-9, 4e-6, 1e-3


def _camera(n=64, method="scaling", **terms):
    return Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_radius=0.06e-3, shape=(n, n),
                  pad=16, method=method, edge="soft", **terms)


@functools.cache
def _phase(n=64, key=0):
    return np.asarray(random_diffuser(jax.random.key(key), (n, n), DX, LAM, 30e-6))


def _centroid_x(image):
    x = np.arange(image.shape[1]) - image.shape[1] // 2
    return float((image.sum(axis=0) * x).sum() / image.sum())


def test_plane_wave_loses_the_acceptance_exactly():
    """A plane wave at incidence θ (on an FFT frequency, sin θ = λf) through the response
    keeps exactly A(θ) = cos^p θ of its power."""
    n, p = 64, 12.0
    for k in (3, 9, 20):
        f = k / (n * DX)
        x = (np.arange(n) - n // 2) * DX
        wave = np.exp(2j * np.pi * f * x)[None, :] * np.ones((n, 1))
        amp = response_amplitude((n, n), DX, LAM, p)
        out = np.fft.ifft2(np.fft.fft2(wave) * np.asarray(amp))
        cos_theta = np.cos(np.arcsin(LAM * f))
        np.testing.assert_allclose(np.sum(np.abs(out) ** 2) / np.sum(np.abs(wave) ** 2),
                                   cos_theta ** p, rtol=1e-5)


@pytest.mark.parametrize("method", ["scaling", "direct"])
def test_distant_source_through_a_clear_diffuser_loses_the_acceptance(method):
    """A source far away (z1 = 1 m) through a clear diffuser arrives as one plane wave
    at the field angle: the unnormalised PSF keeps (1 − (ρ1/z1)²)^(p/2) of its power
    (cos^p of the paraxial source's angle, λf_c = ρ1/z1). On the scaling path the tilt
    is applied analytically, so 5° works there; the direct path samples it (2°)."""
    p, z1 = 40.0, 1.0
    offset = 0.06 if method == "scaling" else 0.025
    on, off = _camera(method=method, acceptance_exponent=p), _camera(method=method)
    a, b = (np.asarray(psf(np.zeros((64, 64)), c, z1, y1=offset, x1=offset,
                           normalise=False)).sum() for c in (on, off))
    expected = float(acceptance(2 * (offset / z1) ** 2, p))
    assert expected < 0.98
    np.testing.assert_allclose(a / b, expected, rtol=2e-3)


def test_stop_shadow_moves_with_the_source():
    """Through a clear diffuser the PSF is the stop's shadow cast from the source onto the
    sensor: its centroid is at −x1·(z2 + d)/(z1 − d) (d = 0: the chief ray −x1·z2/z1)."""
    z1, x1 = 20e-3, 0.3e-3
    for d in (0.0, 1e-3, 3e-3):
        cam = _camera(96, aperture_distance=d)
        image = np.asarray(psf(np.zeros((96, 96)), cam, z1, x1=x1))
        np.testing.assert_allclose(_centroid_x(image) * DX, -x1 * (Z2 + d) / (z1 - d),
                                   atol=0.05 * DX)


def test_vignetting_follows_cos_n():
    """The unnormalised PSF falls as cos^n of the field angle."""
    z1, y1, x1, n_exp = 20e-3, 0.3e-3, -0.5e-3, 4.0
    phase = _phase()
    on, off = _camera(vignetting_exponent=n_exp), _camera()
    a, b = (np.asarray(psf(phase, c, z1, y1=y1, x1=x1, normalise=False)) for c in (on, off))
    cos = z1 / np.sqrt(z1 ** 2 + y1 ** 2 + x1 ** 2)
    np.testing.assert_allclose(a, b * cos ** n_exp, rtol=1e-5, atol=1e-6 * b.max())


@pytest.mark.parametrize("method", ["scaling", "direct"])
def test_zero_strength_terms_are_todays_psf(method):
    """d = 0, p = 0 and n = 0 give the PSF of a camera without the terms."""
    phase = _phase()
    off = _camera(method=method)
    zero = _camera(method=method, aperture_distance=0.0, acceptance_exponent=0.0,
                   vignetting_exponent=0.0)
    a, b = (np.asarray(psf(phase, c, 25e-3, y1=0.2e-3, x1=-0.3e-3, normalise=False))
            for c in (zero, off))
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * b.max())


@pytest.mark.slow
def test_both_paths_lose_the_same_power_off_axis():
    """With the stop away from the diffuser and an angular response, the scaling path
    (tilt applied analytically) and the direct path (tilt sampled) keep the same
    fraction of an off-axis source's power (within 1 %), and that fraction is below the
    on-axis one (the response takes more of the oblique light)."""
    phase = _phase(n=96)
    terms = dict(aperture_distance=1e-3, acceptance_exponent=150.0)
    z1, x1 = 20e-3, -0.4e-3
    kept = {}
    for m in ("scaling", "direct"):
        on, off = _camera(96, m, **terms), _camera(96, m)
        kept[m] = [float(np.sum(psf(phase, on, z1, x1=x, normalise=False))
                         / np.sum(psf(phase, off, z1, x1=x, normalise=False))) for x in (0, x1)]
    np.testing.assert_allclose(kept["scaling"], kept["direct"], rtol=1e-2)
    assert kept["scaling"][1] < 0.99 * kept["scaling"][0]


@pytest.mark.slow
@pytest.mark.usefixtures("debug_nans")
@pytest.mark.parametrize("name, value", [("aperture_distance", 2e-3),
                                         ("acceptance_exponent", 30.0),
                                         ("vignetting_exponent", 4.0)])
def test_gradients_in_the_terms_match_finite_differences(name, value, x64):
    """d/d(term) of Σ w·PSF (unnormalised, off axis) agrees with a central difference."""
    phase = jnp.asarray(_phase())
    cam = _camera(**{name: value})
    w = jnp.asarray(np.random.default_rng(0).random((64, 64)))

    def loss(t):
        c = eqx.tree_at(lambda c: getattr(c, name), cam, t)
        return jnp.sum(w * psf(phase, c, 20e-3, y1=0.2e-3, x1=-0.5e-3, normalise=False)) * 1e-12
    g = float(jax.grad(loss)(jnp.float64(value)))
    h = 1e-5 * value
    fd = (float(loss(value + h)) - float(loss(value - h))) / (2 * h)
    assert abs(g) > 0
    np.testing.assert_allclose(g, fd, rtol=1e-4)


@pytest.mark.slow
def test_jit_and_vmap_over_a_term_match_a_loop():
    """A vmap over the acceptance exponent (one compiled function) equals PSFs one by one."""
    phase = jnp.asarray(_phase())
    cam = _camera(acceptance_exponent=1.0)
    ps = jnp.array([0.0, 20.0, 80.0])
    batched = jax.jit(jax.vmap(lambda p: psf(
        phase, eqx.tree_at(lambda c: c.acceptance_exponent, cam, p), 20e-3, x1=-0.6e-3)))(ps)
    for p, b in zip(ps, batched):
        one = psf(phase, dataclasses.replace(cam, acceptance_exponent=p), 20e-3, x1=-0.6e-3)
        np.testing.assert_allclose(b, one, rtol=1e-4, atol=1e-6 * float(one.max()))


@pytest.mark.slow
def test_psf_stack_equals_psf_with_a_moving_stop():
    """psf_stack over positions (one shadow each) gives psf's PSFs; the stack's camera
    record carries the terms."""
    phase = _phase()
    cam = _camera(aperture_distance=2e-3, acceptance_exponent=10.0, vignetting_exponent=3.0)
    offsets = np.array([[0.0, 0.0], [0.3e-3, -0.4e-3]])
    stack = psf_stack(phase, cam, [20e-3, 30e-3], offsets=offsets, normalise=False)
    for i, z1 in enumerate((20e-3, 30e-3)):
        for j, (y1, x1) in enumerate(offsets):
            one = np.asarray(psf(phase, cam, z1, y1=y1, x1=x1, normalise=False))
            np.testing.assert_allclose(stack[i, j], one, rtol=1e-4, atol=1e-5 * one.max())
    rec = camera_record(cam)
    np.testing.assert_allclose([rec["aperture_distance"], rec["acceptance_exponent"],
                                rec["vignetting_exponent"]], [2e-3, 10.0, 3.0], rtol=1e-6)


def test_bad_terms_are_clear_errors():
    with pytest.raises(DiffcamError, match="aperture_distance must be >= 0"):
        _camera(aperture_distance=-1e-3)
    with pytest.raises(DiffcamError, match="acceptance_exponent must be finite"):
        _camera(acceptance_exponent=np.nan)
    with pytest.raises(DiffcamError, match="one number"):
        _camera(vignetting_exponent=[1.0, 2.0])
    with pytest.raises(DiffcamError, match="metres"):
        _camera(aperture_distance="2mm")
    with pytest.raises(DiffcamError, match="instead of a mask"):
        Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_mask=np.ones((64, 64)), shape=(64, 64),
               aperture_distance=1e-3)
    with pytest.raises(DiffcamError, match="not in front of the stop"):
        psf(_phase(), _camera(aperture_distance=5e-3), 4e-3)
    with pytest.raises(DiffcamError, match="shadow"):
        psf(_phase(), _camera(aperture_distance=5e-3), 10e-3, x1=0.5e-3)


def test_response_needs_a_sampled_chirp_on_the_scaling_path():
    """A sensor so wide that the source's wave tilts past Nyquist about the PSF centre
    is a SamplingError, not a silently aliased filter."""
    cam = Camera(wavelength=LAM, z2=5e-3, dx=8e-6, aperture_radius=0.1e-3, shape=(256, 256),
                 method="scaling", acceptance_exponent=5.0)
    with pytest.raises(SamplingError, match="Nyquist angle"):
        psf(np.zeros((256, 256)), cam, 6e-3)
