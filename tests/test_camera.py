"""The diffuser-camera PSF (diffcam.model.camera): physics, bad input, jit/grad/vmap."""

import dataclasses
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.model import Camera, HeightMap, psf, random_diffuser, with_method
from diffcam.core.errors import DiffcamError, SamplingError, ShapeError, UndersamplingWarning
from diffcam.core.grid import pad_to
from diffcam.evaluate.metrics import pearson
from diffcam.model.point_spread import check_inputs
from diffcam.model.stack import psf_stack

from conftest import assert_float32_gradient_matches_float64

LAM = 532e-9


def small_camera(n=256, dx=2e-6, z2=2e-3, radius=0.15e-3, pad=32, **kw):
    return Camera(wavelength=LAM, z2=z2, dx=dx, aperture_radius=radius, shape=(n, n),
                  pad=pad, **kw)


def smooth_phase(n, seed=0, feature=40e-6, dx=2e-6, degrees=0.5):
    return np.asarray(random_diffuser(jax.random.key(seed), (n, n), dx, LAM, feature,
                                      np.deg2rad(degrees)))


def centroid_x(img, dx):
    img = np.asarray(img, np.float64)
    x = (np.arange(img.shape[-1]) - img.shape[-1] // 2) * dx
    return float((img.sum(axis=0) * x).sum() / img.sum())


# ------------------------------------------------------------------------------ physics

@pytest.mark.parametrize("method", ["scaling", "direct"])
def test_prism_moves_centroid_by_z2_tan_alpha(method, x64):
    """A linear phase k·x·sin(α) (a prism deflecting by α) moves the PSF centroid by
    z2·tan(α) towards +x. Reference: geometric optics; the Fresnel model is paraxial
    (it shifts by z2·sin α), so the tolerance is the sin/tan difference at 1°
    (1.5e-4 relative) plus 1 % for the centroid of a finite grid: rtol 1.2e-2."""
    n, dx, z2 = 256, 2e-6, 2e-3
    cam = small_camera(n, dx, z2, radius=0.1e-3, method=method)
    alpha = np.deg2rad(1.0)
    x = (np.arange(n) - n // 2) * dx
    ramp = np.broadcast_to(2 * np.pi / LAM * np.sin(alpha) * x, (n, n))
    base = psf(np.zeros((n, n)), cam, 50e-3)
    tilted = psf(ramp, cam, 50e-3)
    assert abs(centroid_x(base, dx)) < 0.01 * dx
    np.testing.assert_allclose(centroid_x(tilted, dx), z2 * np.tan(alpha), rtol=1.2e-2)


@pytest.mark.parametrize("method", ["scaling", "direct"])
def test_lateral_source_shifts_psf_by_minus_d_z2_over_z1(method):
    """psf(x1 = d) equals psf(0) moved by −d·z2/z1 (12 pixels here; 1 − Pearson < 1e-3
    over the region both cover). Reference: the shift theorem of Fresnel propagation
    (paraxial memory effect), exact in this model."""
    n, dx, z1, z2 = 256, 2e-6, 20e-3, 2e-3
    cam = small_camera(n, dx, z2, method=method)
    phase = smooth_phase(n)
    shift_px = 12
    d = shift_px * dx * z1 / z2
    p0 = np.asarray(psf(phase, cam, z1))
    px = np.asarray(psf(phase, cam, z1, x1=d))
    py = np.asarray(psf(phase, cam, z1, y1=-d))
    assert 1 - float(pearson(px[:, 20:-20], p0[:, 20 + shift_px:n - 20 + shift_px])) < 1e-3
    assert 1 - float(pearson(py[20:-20], p0[20 - shift_px:n - 20 - shift_px])) < 1e-3


def test_lens_diffuser_is_sharpest_at_imaging_depth():
    """A lens phase −k r²/(2 fd) focuses best where 1/z1 + 1/z2 = 1/fd (thin-lens law).
    dx 2 µm, aperture radius 0.3 mm (lens chirp 135 cycles/mm < Nyquist 250), z2 5 mm,
    fd chosen for z1 = 25 mm. The sharpness Σ PSF² is fitted by a parabola in 1/z1;
    its peak is within 1 % of 25 mm (the depth of field is about ±2 mm)."""
    n, dx, z2, z1_focus = 512, 2e-6, 5e-3, 25e-3
    fd = 1 / (1 / z1_focus + 1 / z2)
    cam = small_camera(n, dx, z2, radius=0.3e-3, pad=64)
    x = (np.arange(n) - n // 2) * dx
    phase = -np.pi * (x[:, None] ** 2 + x[None, :] ** 2) / (LAM * fd)
    inv = np.linspace(1 / 40e-3, 1 / 15e-3, 21)
    sharp = (psf_stack(phase, cam, 1 / inv, batch_size=4) ** 2).sum(axis=(-2, -1))
    i = int(np.argmax(sharp))
    c = np.polyfit(inv[i - 2:i + 3], sharp[i - 2:i + 3], 2)
    np.testing.assert_allclose(-2 * c[0] / c[1], z1_focus, rtol=0.01)


@pytest.mark.parametrize("z1", [20e-3, 60e-3])
def test_scaling_theorem_matches_direct_where_both_sampled(z1, x64):
    """Scaling theorem vs direct propagation (paper Eq. 7 literally), where the source
    chirp (≤ 14 cycles/mm) and both transfer functions are sampled; soft-edged aperture
    and a smooth diffuser, padded grid. Reference: the Fresnel scaling theorem is exact
    for the continuous fields; the grids differ by interpolation and by how each path
    aliases the aperture edge: 1 − Pearson < 1e-4, max difference < 2 % of the peak,
    physical irradiance sums within 1 %."""
    n = 256
    cam = small_camera(n, z2=1e-3, pad=64, edge="soft")
    phase = smooth_phase(n, seed=1)
    a = np.asarray(psf(phase, cam, z1, x1=30e-6, normalise=False))
    b = np.asarray(psf(phase, with_method(cam, "direct"), z1, x1=30e-6, normalise=False))
    assert 1 - float(pearson(a, b)) < 1e-4
    assert np.abs(a - b).max() < 0.02 * b.max()
    np.testing.assert_allclose(a.sum(), b.sum(), rtol=0.01)


@pytest.mark.parametrize("method, rtol", [("direct", 1e-6), ("scaling", 3e-3)])
def test_physical_irradiance_conserves_power(method, rtol, x64):
    """normalise=False: Σ PSF·dx² equals the power through the aperture from a unit
    point source, (area of C)/(λz1)². Reference: Parseval; the circular Fresnel TF is
    unitary, so the direct path matches to round-off (1e-6); the scaling path's sum is a
    Riemann sum of the interpolated field at pitch dx/M and drops the hard edge's
    diffraction that lands outside the magnified sensor: 3e-3 (measured 1.3e-3)."""
    n, dx, z1 = 256, 2e-6, 30e-3
    cam = small_camera(n, dx, z2=1e-3, edge="hard", pad=0, method=method)
    p = np.asarray(psf(smooth_phase(n), cam, z1, normalise=False))
    area = float(np.sum(np.asarray(cam.aperture()))) * dx * dx
    np.testing.assert_allclose(p.sum() * dx * dx, area / (LAM * z1) ** 2, rtol=rtol)
    q = np.asarray(psf(smooth_phase(n), cam, z1))
    np.testing.assert_allclose(q.sum(), 1.0, rtol=1e-6)


def test_broadband_single_wavelength_equals_monochromatic_and_smooths():
    """A one-line spectrum at the camera wavelength reproduces the monochromatic PSF (to
    float32 round-off, 1e-6 of the peak); a ±10 % band of 9 lines lowers the caustic's
    contrast (std/mean over the lit region) by more than 10 % (measured: 0.68 → 0.60)
    for a 4° diffuser of 60 µm features (height rms 2 µm, n = 1.5)."""
    n = 256
    cam = small_camera(n, z2=2e-3)
    height = smooth_phase(n, feature=60e-6, degrees=4.0) * LAM / (2 * np.pi * 0.5)
    diffuser = HeightMap(height, 1.5)
    mono = np.asarray(psf(diffuser, cam, 30e-3))
    one = np.asarray(psf(diffuser, cam, 30e-3, spectrum=([LAM], [2.0])))
    np.testing.assert_allclose(one, mono, atol=1e-6 * mono.max())
    wl = LAM * np.linspace(0.9, 1.1, 9)
    broad = np.asarray(psf(diffuser, cam, 30e-3, spectrum=(wl, np.ones(9))))
    lit = mono > 0.05 * mono.max()

    def contrast(p):
        return p[lit].std() / p[lit].mean()

    assert contrast(broad) < 0.9 * contrast(mono)


def test_height_map_equals_phase_at_reference_wavelength():
    """HeightMap(h, n) at λ is the phase 2π(n − 1)h/λ (to float32 round-off)."""
    n = 128
    cam = small_camera(n, z2=1e-3, radius=0.1e-3)
    theta = smooth_phase(n)
    h = theta * LAM / (2 * np.pi * 0.46)
    a = psf(HeightMap(h, 1.46), cam, 25e-3)
    b = psf(theta, cam, 25e-3)
    np.testing.assert_allclose(a, b, atol=1e-5 * float(b.max()))


def test_paper_simulation_grid_runs():
    """The paper's simulation (Section 3.1): 4000×4000 at 5 µm, a 512×512 cameraman
    phase embedded at the centre, aperture radius 1.2 mm, z1 = 25 mm, z2 = 1 mm. The
    PSF is finite, sums to one, and its light stays within the aperture's image plus
    the diffuser's spread (99 % inside radius 1.2 mm·M + 0.2 mm). About 5 s here with
    compilation, so it runs by default."""
    from diffcam.calibrate.simulation import cameraman_phase

    n, dx = 4000, 5e-6
    phase = pad_to(jnp.asarray(cameraman_phase(512), jnp.float32), (n, n))
    cam = Camera(wavelength=LAM, z2=1e-3, dx=dx, aperture_radius=1.2e-3, shape=(n, n))
    t = time.perf_counter()
    p = np.asarray(psf(phase, cam, 25e-3))
    elapsed = time.perf_counter() - t
    assert np.isfinite(p).all()
    np.testing.assert_allclose(p.sum(), 1.0, rtol=1e-4)
    x = (np.arange(n) - n // 2) * dx
    r = np.hypot(x[:, None], x[None, :])
    assert p[r < 1.2e-3 * 1.04 + 0.2e-3].sum() > 0.99
    print(f"4000² PSF in {elapsed:.1f} s (including compilation)")


# ---------------------------------------------------------------------------- bad input

def test_phase_shape_must_match_camera():
    cam = small_camera(128, radius=0.1e-3)
    with pytest.raises(ShapeError, match="camera grid"):
        psf(np.zeros((64, 64)), cam, 25e-3)


@pytest.mark.parametrize("z1", [0.0, -25e-3, np.nan])
def test_z1_must_be_positive(z1):
    cam = small_camera(128, radius=0.1e-3)
    with pytest.raises(DiffcamError, match="z1"):
        psf(np.zeros((128, 128)), cam, z1)


@pytest.mark.parametrize("z2", [0.0, -1e-3])
def test_z2_must_be_positive(z2):
    with pytest.raises(DiffcamError, match="z2"):
        small_camera(128, z2=z2, radius=0.1e-3)


def test_nan_in_phase_is_rejected():
    cam = small_camera(128, radius=0.1e-3)
    phase = np.zeros((128, 128))
    phase[3, 4] = np.nan
    with pytest.raises(DiffcamError, match="NaN"):
        psf(phase, cam, 25e-3)


def test_aperture_larger_than_grid():
    with pytest.raises(DiffcamError, match="half-width"):
        small_camera(128, dx=2e-6, radius=0.2e-3)


def test_mask_shape_and_exactly_one_aperture():
    with pytest.raises(ShapeError):
        Camera(wavelength=LAM, z2=1e-3, dx=2e-6, aperture_mask=np.ones((4, 4)), shape=(8, 8))
    with pytest.raises(DiffcamError, match="exactly one"):
        Camera(wavelength=LAM, z2=1e-3, dx=2e-6, shape=(8, 8))


def test_direct_path_at_paper_real_camera_is_undersampled():
    """Aperture radius 2.3 mm, pixel 3.45 µm, λ 532 nm: every z1 < 29.8 mm aliases the
    source chirp on the direct path; the scaling path has no such limit."""
    n = 2048
    cam = Camera(wavelength=LAM, z2=2e-3, dx=3.45e-6, aperture_radius=2.3e-3, shape=(n, n),
                 method="direct")
    phase = np.zeros((n, n), np.float32)
    with pytest.raises(SamplingError, match="scaling"):
        psf(phase, cam, 29e-3)
    with pytest.warns(UndersamplingWarning):
        from diffcam.model.point_spread import check_inputs
        check_inputs(phase, cam, 22e-3, 0.0, [LAM], accept_undersampling=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_inputs(phase, cam, 30e-3, 0.0, [LAM], accept_undersampling=False)
        check_inputs(phase, with_method(cam, "scaling"), 5e-3, 0.0, [LAM], False)


def test_psf_remembers_a_source_that_passed_and_nothing_else():
    """An eager psf remembers a camera and a source (plain numbers) that passed its
    checks; a closer source, a source off the frame, an accepted undersampling (its
    warning every time), a bad diffuser and another camera with the same numbers are
    all checked afresh, every time."""
    n, dx = 256, 10e-6
    # the source's chirp is sampled at the aperture edge (0.785 mm) from z1 ≈ 29.5 mm on
    # (a radius between lattice points: on one, rounding decides which pixels are in)
    cam = Camera(wavelength=LAM, z2=2e-3, dx=dx, aperture_radius=0.785e-3, shape=(n, n),
                 method="direct")
    phase = jnp.zeros((n, n), jnp.float32)
    first = psf(phase, cam, 30e-3)
    np.testing.assert_array_equal(psf(phase, cam, 30e-3), first)     # remembered
    compiled = jax.jit(lambda p: psf(p, cam, 30e-3)).lower(phase).compile()   # in AOT
    np.testing.assert_allclose(compiled(phase), first, rtol=1e-5, atol=1e-7)
    for _ in range(2):
        with pytest.raises(SamplingError):
            psf(phase, cam, 29e-3)
        with pytest.raises(DiffcamError, match="outside"):
            psf(phase, cam, 30e-3, x1=0.2)
        with pytest.warns(UndersamplingWarning):
            psf(phase, cam, 22e-3, accept_undersampling=True)
        with pytest.raises(DiffcamError, match="NaN"):
            psf(phase.at[3, 3].set(jnp.nan), cam, 30e-3)
        with pytest.raises(ShapeError, match="shape"):
            psf(phase[1:], cam, 30e-3)
    wider = Camera(wavelength=LAM, z2=2e-3, dx=dx, aperture_radius=1.0e-3, shape=(n, n),
                   method="direct")                 # the same numbers alias at its edge
    with pytest.raises(SamplingError):
        psf(phase, wider, 30e-3)


def test_check_inputs_transfer_function_sampling():
    """The Fresnel transfer function's own sampling is checked for the padded grid."""
    small = Camera(wavelength=LAM, z2=1e-3, dx=3.45e-6, aperture_radius=0.1e-3,
                   shape=(64, 64), method="direct", pad=0)
    check_inputs(np.zeros((64, 64)), small, 30e-3, 0.0, [LAM], False)
    tight = Camera(wavelength=LAM, z2=2e-3, dx=3.45e-6, aperture_radius=0.1e-3,
                   shape=(64, 64), method="direct", pad=0)   # its transfer function aliases
    with pytest.raises(SamplingError, match="aliases"):
        check_inputs(np.zeros((64, 64)), tight, 30e-3, 0.0, [LAM], False)


@pytest.mark.parametrize("weights, match", [([1.0, -0.5], ">= 0"), ([0.0, 0.0], "sum to zero")])
def test_spectrum_weights(weights, match):
    cam = small_camera(64, radius=0.05e-3)
    with pytest.raises(DiffcamError, match=match):
        psf(np.zeros((64, 64)), cam, 25e-3, spectrum=([500e-9, 560e-9], weights))


def test_bad_static_fields():
    with pytest.raises(DiffcamError, match="method"):
        small_camera(64, radius=0.05e-3, method="fast")
    with pytest.raises(ShapeError, match="crop"):
        small_camera(64, radius=0.05e-3, crop=(128, 128))


# -------------------------------------------------------------------- jit, grad, vmap

@pytest.mark.slow  # 9 s; jit(vmap(psf)) against psf by default: test_batched
def test_jit_vmap_and_no_recompile_for_new_numbers():
    """Traced camera numbers: vmap over z2 and new values reuse the compiled core."""
    n = 64
    cam = small_camera(n, dx=4e-6, radius=0.08e-3)
    phase = smooth_phase(n, dx=4e-6)
    f = jax.jit(lambda ph, c, z: psf(ph, c, z))
    a = f(phase, cam, 25e-3)
    b = f(phase, dataclasses.replace(cam, z2=3e-3), 26e-3)
    assert a.shape == b.shape == (n, n)
    assert f._cache_size() == 1
    z2s = jnp.array([1e-3, 2e-3, 3e-3])
    stacked = jax.vmap(lambda z2: psf(phase, eqx.tree_at(lambda c: c.z2, cam, z2), 25e-3))(z2s)
    np.testing.assert_allclose(stacked[1], psf(phase, dataclasses.replace(cam, z2=2e-3), 25e-3),
                               rtol=1e-4, atol=1e-7)
    zs = jnp.array([22e-3, 30e-3])
    np.testing.assert_allclose(jax.vmap(lambda z: psf(phase, cam, z))(zs)[1],
                               psf(phase, cam, 30e-3), rtol=1e-4, atol=1e-7)


@pytest.mark.usefixtures("debug_nans")
@pytest.mark.parametrize("method", [pytest.param("scaling", marks=pytest.mark.slow), "direct"])
def test_gradients_match_finite_differences(method, x64):  # scaling: 16 s of compilation
    """d/dz1, d/dz2 and a directional derivative in the phase of Σ w·PSF agree with
    central differences of relative step 1e-6 in float64 (rtol 1e-4)."""
    n = 64
    cam = small_camera(n, dx=4e-6, z2=1e-3, radius=0.08e-3, method=method, edge="soft")
    phase = jnp.asarray(smooth_phase(n, dx=4e-6))
    w = jnp.asarray(np.random.default_rng(0).random((n, n)))

    def loss(ph, z1, z2):
        return jnp.sum(w * psf(ph, eqx.tree_at(lambda c: c.z2, cam, z2), z1, x1=20e-6))

    z1, z2 = 30e-3, 1e-3
    g_ph, g_z1, g_z2 = jax.grad(loss, argnums=(0, 1, 2))(phase, z1, z2)
    for g, f, x in ((g_z1, lambda t: loss(phase, t, z2), z1),
                    (g_z2, lambda t: loss(phase, z1, t), z2)):
        h = 1e-6 * x
        fd = (f(x + h) - f(x - h)) / (2 * h)
        np.testing.assert_allclose(g, fd, rtol=1e-4)
    v = jnp.asarray(np.random.default_rng(1).standard_normal((n, n)))
    h = 1e-6
    fd = (loss(phase + h * v, z1, z2) - loss(phase - h * v, z1, z2)) / (2 * h)
    np.testing.assert_allclose(jnp.sum(g_ph * v), fd, rtol=1e-4)
    assert np.isfinite(np.asarray(g_ph)).all()


@pytest.mark.slow  # 11–18 s of compilation a path; float32 against float64 by default:
@pytest.mark.parametrize("method", ["scaling", "direct"])  # test_retrieval_lsq's model
def test_float32_gradient_agrees_with_float64(method):
    """The phase gradient of Σ w·PSF in float32 equals the float64 one (1e-3 of its
    largest entry) for a close source (z1 = 25 mm, 5 µm pitch). The unnormalised
    irradiance sums to ~10²² here, and its square overflows float32: a quotient rule
    that divides by it dropped the normalisation's term and was 60 % off."""
    n = 128
    rng = np.random.default_rng(0)
    phase = rng.uniform(-np.pi, np.pi, (n, n))
    w = rng.random((n, n))

    def gradient(dtype):
        cam = Camera(wavelength=dtype(LAM), z2=dtype(1e-3), dx=dtype(5e-6),
                     aperture_radius=dtype(0.2e-3), shape=(n, n), method=method)
        loss = lambda ph: jnp.sum(jnp.asarray(w, dtype) * psf(ph, cam, 25e-3,
                                                                accept_undersampling=True))
        return jax.grad(loss)(jnp.asarray(phase, dtype))

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UndersamplingWarning)
        assert_float32_gradient_matches_float64(gradient)


@pytest.mark.slow  # 6 s; the soft edge's radius gradient by default: test_optics
@pytest.mark.usefixtures("debug_nans")
def test_gradient_in_aperture_radius_with_soft_edge():
    """edge='soft' makes the PSF differentiable in the aperture radius (finite, nonzero)."""
    n = 64
    cam = small_camera(n, dx=4e-6, radius=0.08e-3, edge="soft")
    phase = smooth_phase(n, dx=4e-6)
    w = jnp.asarray(np.random.default_rng(0).random((n, n)))
    g = jax.grad(lambda r: jnp.sum(w * psf(phase, eqx.tree_at(
        lambda c: c.aperture_radius, cam, r), 25e-3)))(jnp.asarray(0.08e-3))
    assert np.isfinite(float(g)) and float(g) != 0.0


def test_random_diffuser_deflection():
    """random_diffuser scales the r.m.s. phase slope to 2π·sin(deflection)/λ (1e-5)."""
    dx = 5e-6
    th = np.asarray(random_diffuser(jax.random.key(3), (128, 128), dx, LAM, 30e-6,
                                    np.deg2rad(1.0)), np.float64)
    gy, gx = np.gradient(th, dx)
    np.testing.assert_allclose(np.sqrt(np.mean(gy ** 2 + gx ** 2)) * LAM / (2 * np.pi),
                               np.sin(np.deg2rad(1.0)), rtol=1e-4)
