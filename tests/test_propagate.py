"""Propagators against closed-form optics (diffcam/propagate.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.special import j1

from diffcam.core import grid
from diffcam.core.errors import DiffcamError, SamplingError, ShapeError, UndersamplingWarning
from diffcam.optics.elements import circular_aperture, thin_lens
from diffcam.optics.lens import fourier_lens, inverse_fourier_lens
from diffcam.optics.propagation import (angular_spectrum, apply_transfer, choose_propagation,
                                        critical_distance, fresnel_ir, fresnel_tf,
                                        plan_propagation, propagate, transfer_function,
                                        transfer_pad)
from conftest import assert_float32_gradient_matches_float64, assert_grad_matches_fd

LAM = 0.5e-6


def _disc(n, dx, radius_px):
    aperture = circular_aperture((n, n), dx, radius_px * dx)
    a_eff = np.sqrt(float(aperture.sum()) / np.pi) * dx  # radius implied by the pixel count
    return aperture.astype(jnp.complex64), a_eff


# ------------------------------------------------------------------ on-axis intensity

N_ON, DX_ON, R_ON = 1024, 2e-6, 40


@pytest.mark.parametrize("fresnel_number", [1.8, 2.5, 3.3, 4.5, 5.0])
@pytest.mark.parametrize("method", ["fresnel_tf", "angular_spectrum"])
def test_on_axis_intensity_transfer_functions(method, fresnel_number):
    """Fresnel on-axis intensity behind a circular aperture, unit plane wave:
    I = 4 sin²(π a²/(2λz)) (Goodman, Introduction to Fourier Optics, §4.5).
    Within 1 % at N_F ≤ 5, a = radius implied by the pixel count."""
    u, a = _disc(N_ON, DX_ON, R_ON)
    z = a * a / (LAM * fresnel_number)
    out = propagate(u, DX_ON, LAM, z, method=method, pad=0)
    i_num = float(jnp.abs(out[N_ON // 2, N_ON // 2]) ** 2)
    i_ref = 4 * np.sin(np.pi * fresnel_number / 2) ** 2
    assert abs(i_num - i_ref) / i_ref < 0.01


@pytest.mark.parametrize("fresnel_number", [0.5, 1.0, 1.3])
def test_on_axis_intensity_impulse_response(fresnel_number):
    """Same closed form (Goodman §4.5) for the impulse-response method, where it is
    sampled (z ≥ N·dx²/λ); 1 %."""
    u, a = _disc(N_ON, DX_ON, R_ON)
    z = a * a / (LAM * fresnel_number)
    out = fresnel_ir(u, DX_ON, LAM, z)
    i_num = float(jnp.abs(out[N_ON // 2, N_ON // 2]) ** 2)
    i_ref = 4 * np.sin(np.pi * fresnel_number / 2) ** 2
    assert abs(i_num - i_ref) / i_ref < 0.01


@pytest.mark.parametrize("z_over_a", [3.0, 3.5, 4.0, 6.0, 10.0])
def test_on_axis_angular_spectrum_is_rayleigh_sommerfeld(z_over_a):
    """Exact on-axis intensity (Rayleigh–Sommerfeld, plane wave on a circular aperture):
    I = |1 − (z/ρ) e^{jk(ρ − z)}|², ρ = √(z² + a²) (Osterberg & Smith 1961). The angular
    spectrum matches within 1 % at z = 3a … 10a; at 3a … 6a Fresnel is off by 4–17 %."""
    n, dx, r_px = 1024, LAM / 4, 40
    u, a = _disc(n, dx, r_px)
    z = z_over_a * a
    out = angular_spectrum(u, dx, LAM, z)
    i_num = float(jnp.abs(out[n // 2, n // 2]) ** 2)
    k = 2 * np.pi / LAM
    rho = np.hypot(z, a)
    i_rs = abs(1 - z / rho * np.exp(1j * k * (rho - z))) ** 2
    i_fresnel = 4 * np.sin(np.pi * a * a / (2 * LAM * z)) ** 2
    assert abs(i_num - i_rs) / i_rs < 0.01
    if z_over_a <= 6:  # cases that tell the two apart
        assert abs(i_fresnel - i_rs) / i_rs > 0.02


# -------------------------------------------------------------------- Gaussian beams

W0, N_G, DX_G = 20e-6, 512, 2e-6
Z_R = np.pi * W0 ** 2 / LAM


def _gaussian_beam(n, dx):
    y, x = grid.yx((n, n), dx)
    return jnp.exp(-(x ** 2 + y ** 2) / W0 ** 2).astype(jnp.complex64)


def _second_moment_radius(field, dx, axis, window):
    """Beam radius w = 2·√⟨x²⟩ of |field|² within |x|, |y| ≤ window (m)."""
    i = np.abs(np.asarray(field)) ** 2
    cy, cx = (np.asarray(grid.coords(n, p), dtype=np.float64)
              for n, p in zip(i.shape, grid.pitch_yx(dx)))
    i = i[np.abs(cy) <= window][:, np.abs(cx) <= window]
    c = (cy, cx)[axis]
    c = c[np.abs(c) <= window]
    prof = i.sum(axis=1 - axis)
    return 2 * np.sqrt(np.sum(prof * c ** 2) / np.sum(prof))


@pytest.mark.parametrize("method,z", [("fresnel_tf", 2e-3), ("fresnel_tf", 4e-3),
                                      ("angular_spectrum", 2e-3), ("angular_spectrum", 4e-3),
                                      ("fresnel_ir", 6e-3), ("fresnel_ir", 10e-3)])
def test_gaussian_beam_radius_and_gouy_phase(method, z):
    """Gaussian beam: w(z) = w0·√(1 + (z/zR)²) within 0.5 %, on-axis phase kz − arctan(z/zR)
    within 0.01 rad (Siegman, Lasers, ch. 17), each method in its sampled regime. The
    radius is the second moment within ±3·w(z) (which holds all but e^{-18} of it)."""
    u = _gaussian_beam(N_G, DX_G)
    out = propagate(u, DX_G, LAM, z, method=method, pad=0)
    w_ref = W0 * np.sqrt(1 + (z / Z_R) ** 2)
    for axis in (0, 1):
        assert abs(_second_moment_radius(out, DX_G, axis, 3 * w_ref) / w_ref - 1) < 0.005
    k = 2 * np.pi / LAM
    centre = complex(out[N_G // 2, N_G // 2])
    gouy = np.angle(centre * np.exp(-1j * np.mod(k * z, 2 * np.pi)))
    assert abs(gouy + np.arctan(z / Z_R)) < 0.01
    assert abs(abs(centre) - W0 / w_ref) < 0.005


def test_gaussian_beam_non_square_grid():
    """A non-square grid (96 × 160) and rectangular pixels give the same beam radius
    on both axes (Siegman ch. 17), within 0.5 %."""
    shape, pitch, z = (160, 224), (2.5e-6, 2e-6), 1.5e-3
    y, x = grid.yx(shape, pitch)
    u = jnp.exp(-(x ** 2 + y ** 2) / W0 ** 2).astype(jnp.complex64)
    w_ref = W0 * np.sqrt(1 + (z / Z_R) ** 2)
    for method in ("fresnel_tf", "angular_spectrum"):
        out = propagate(u, pitch, LAM, z, method=method, pad=0)
        assert abs(_second_moment_radius(out, pitch, 0, 3 * w_ref) / w_ref - 1) < 0.005
        assert abs(_second_moment_radius(out, pitch, 1, 3 * w_ref) / w_ref - 1) < 0.005


# ------------------------------------------------------------------ Fourier lens / Airy

def _airy(v):
    v = np.where(v == 0, 1e-12, v)
    return (2 * j1(v) / v) ** 2


def test_fourier_lens_of_circular_aperture_is_airy():
    """Fourier lens of a circular aperture: I ∝ [2 J1(v)/v]², v = k·a·r/f (Goodman §4.4):
    profile RMS within 1 % of the peak out to the third ring, first dark ring at
    0.61 λf/a within one output pixel."""
    n, dx, f, r_px = 512, 10e-6, 0.1, 32
    u, a = _disc(n, dx, r_px)
    far, (du, dv) = fourier_lens(u, dx, LAM, f)
    assert np.isclose(du, LAM * f / (n * dx)) and np.isclose(dv, du)
    i = np.abs(np.asarray(far)) ** 2
    i /= i[n // 2, n // 2]
    yy, xx = np.asarray(grid.yx((n, n), du)[0]), np.asarray(grid.yx((n, n), du)[1])
    r = np.sqrt(yy ** 2 + xx ** 2)
    v = 2 * np.pi / LAM * a * r / f
    region = v < 10.2  # to the third dark ring
    rms = np.sqrt(np.mean((i[region] - _airy(v[region])) ** 2))
    assert rms < 0.01
    profile = i[n // 2, n // 2:]
    first_min = int(np.argmax(np.diff(profile) > 0))  # first index where it rises again
    r_ring = 0.61 * LAM * f / a
    assert abs(first_min * du - r_ring) <= du


def test_thin_lens_focuses_to_airy_spot():
    """A plane wave through an aperture and thin lens, propagated by f, focuses to the
    Airy spot (Goodman §5.2): peak on axis, FWHM = 1.029·λf/(2a) within 5 %; the lens
    chirp is oversampled 10× (a/(λf) vs 1/(2dx))."""
    n, dx, f, r_px = 1024, 1e-6, 2e-3, 50
    u, a = _disc(n, dx, r_px)
    u = u * thin_lens((n, n), dx, LAM, f)
    out = angular_spectrum(u, dx, LAM, f)
    i = np.abs(np.asarray(out)) ** 2
    assert np.unravel_index(np.argmax(i), i.shape) == (n // 2, n // 2)
    prof = i[n // 2, n // 2:] / i[n // 2, n // 2]
    k = int(np.argmax(prof < 0.5))
    half = (k - 1) + (prof[k - 1] - 0.5) / (prof[k - 1] - prof[k])  # linear interpolation
    fwhm = 2 * half * dx
    assert abs(fwhm / (1.029 * LAM * f / (2 * a)) - 1) < 0.05


# ------------------------------------------------------------- Parseval, round trips

def _smooth_field(shape, seed=0, band=0.2):
    """Random complex field band-limited to |f| < band/dx (so nothing is lost)."""
    rng = np.random.default_rng(seed)
    spec = rng.normal(size=shape) + 1j * rng.normal(size=shape)
    fy, fx = np.fft.fftfreq(shape[0])[:, None], np.fft.fftfreq(shape[1])[None, :]
    spec *= (fy ** 2 + fx ** 2) < band ** 2
    return jnp.asarray(np.fft.ifft2(spec), dtype=jnp.complex64)


@pytest.mark.parametrize("method", ["fresnel_tf", "angular_spectrum"])
def test_parseval_and_round_trip_transfer_functions(method):
    """Unitary kernels: Σ|U_z|² = Σ|U_0|², and propagating z then −z returns U_0,
    both to 1e-5 relative in float32 (Parseval's theorem)."""
    n, dx = 512, 2e-6
    u = _smooth_field((n, n + 64))
    z = 2e-3
    out = propagate(u, dx, LAM, z, method=method, pad=0)
    e0 = float(jnp.sum(jnp.abs(u) ** 2))
    assert abs(float(jnp.sum(jnp.abs(out) ** 2)) / e0 - 1) < 1e-5
    back = propagate(out, dx, LAM, -z, method=method, pad=0)
    assert float(jnp.linalg.norm(back - u) / jnp.linalg.norm(u)) < 1e-5


def test_parseval_and_inverse_fourier_lens():
    """Fourier lens: Σ|U'|² du² = Σ|U|² dx² (energy in physical units) and the inverse
    lens returns the input, to 1e-5 relative in float32; non-square grid."""
    dx, f = 5e-6, 0.05
    u = _smooth_field((256, 384))
    far, du = fourier_lens(u, dx, LAM, f)
    assert np.allclose(du, (LAM * f / (256 * dx), LAM * f / (384 * dx)))
    e_in = float(jnp.sum(jnp.abs(u) ** 2)) * dx * dx
    e_out = float(jnp.sum(jnp.abs(far) ** 2)) * du[0] * du[1]
    assert abs(e_out / e_in - 1) < 1e-5
    back, dx_back = inverse_fourier_lens(far, du, LAM, f)
    assert np.allclose(dx_back, (dx, dx))
    assert float(jnp.linalg.norm(back - u) / jnp.linalg.norm(u)) < 1e-5


def test_impulse_response_round_trip_error():
    """The sampled impulse response is not unitary, so no exactness is claimed: the
    round-trip error measured here (z = 2·N·dx²/λ, half-grid padding, a Gaussian well
    inside the grid) is about 2e-6 relative; the test bounds it at 1e-4."""
    n, dx = 256, 2e-6
    y, x = grid.yx((n, n), dx)
    u = jnp.exp(-(x ** 2 + y ** 2) / (30e-6) ** 2).astype(jnp.complex64)
    z = 2 * n * dx * dx / LAM
    back = fresnel_ir(fresnel_ir(u, dx, LAM, z, pad=n // 2), dx, LAM, -z, pad=n // 2)
    err = float(jnp.linalg.norm(back - u) / jnp.linalg.norm(u))
    print(f"impulse-response round-trip error: {err:.2e}")
    assert err < 1e-4


def test_piston_is_reduced_in_float64():
    """e^{jkz} at z = 0.1 m: kz ≈ 1.26e6 rad; the float32 step there is 0.125 rad, so
    the phase must be reduced modulo 2π in float64 first (compared with an exact
    float64 evaluation, within 1e-5 rad)."""
    z, lam = 0.1 + 3.3e-8, 532e-9
    H = transfer_function((8, 8), 2e-6, lam, z, method="fresnel_tf")
    expected = np.mod(2 * np.pi * z / lam, 2 * np.pi)
    got = np.mod(np.angle(complex(H[0, 0])), 2 * np.pi)
    assert abs(np.angle(np.exp(1j * (got - expected)))) < 1e-5


# ----------------------------------------------------------------------- the chooser

def test_auto_chooses_by_critical_distance_and_pads_spreading_fields():
    """propagate(method='auto') runs the angular spectrum for |z| ≤ N·dx²/λ and the
    impulse response beyond, and says so; pad='auto' pads a field that will spread
    past the grid edge and leaves a compact, slowly spreading one alone."""
    n, dx = 256, 2e-6
    zc = n * dx * dx / LAM
    u, _ = _disc(n, dx, 20)
    near = plan_propagation(u, dx, LAM, 0.5 * zc)
    assert near.method == "angular_spectrum" and "≤" in near.reason
    far = plan_propagation(u, dx, LAM, 20 * zc, pad=0)
    assert far.method == "fresnel_ir"
    padded = plan_propagation(u, dx, LAM, 4 * zc)
    assert padded.pad[0] > 0 and padded.pad[1] > 0
    g = _gaussian_beam(n, dx)
    compact = plan_propagation(g, dx, LAM, 0.1e-3)
    assert compact.pad == (0, 0)
    assert choose_propagation((n, n), dx, LAM, zc).method == "angular_spectrum"


def test_padding_removes_wrap_around():
    """Zero padding with crop-back matches propagation on a grid twice as large (the
    reference has no wrap-around within the window), to 1e-5; without padding the
    wrapped light makes a visible error."""
    n, dx, z = 128, 2e-6, 1.0e-3
    u, _ = _disc(n, dx, 40)
    big = grid.pad_to(u, (4 * n, 4 * n))
    ref = grid.crop_to(angular_spectrum(big, dx, LAM, z), (n, n))
    padded = angular_spectrum(u, dx, LAM, z, pad=3 * n // 2)
    circular = angular_spectrum(u, dx, LAM, z, pad=0)
    scale = float(jnp.linalg.norm(ref))
    assert float(jnp.linalg.norm(padded - ref)) / scale < 1e-5
    assert float(jnp.linalg.norm(circular - ref)) / scale > 1e-2


# -------------------------------------------------------------- jit, vmap, batching

def test_batched_vmap_and_jit_agree():
    """Leading batch axes broadcast; vmap over z and jit of the public function give the
    same fields as one-at-a-time calls (float32 round-off)."""
    n, dx = 128, 2e-6
    fields = jnp.stack([_smooth_field((n, n), seed=s) for s in range(3)])
    batch = fresnel_tf(fields, dx, LAM, 1e-3)
    for s in range(3):
        np.testing.assert_allclose(batch[s], fresnel_tf(fields[s], dx, LAM, 1e-3), atol=1e-6)
    zs = jnp.array([0.5e-3, 1e-3, 2e-3])
    swept = jax.vmap(lambda z: angular_spectrum(fields[0], dx, LAM, z))(zs)
    for i, z in enumerate(zs):
        np.testing.assert_allclose(swept[i], angular_spectrum(fields[0], dx, LAM, float(z)),
                                   atol=2e-5)
    jitted = jax.jit(lambda u, z: fresnel_tf(u, dx, LAM, z))(fields[1], 1e-3)
    np.testing.assert_allclose(jitted, batch[1], atol=2e-5)
    H = transfer_function((n, n), dx, LAM, 1e-3, method="fresnel_tf")
    np.testing.assert_allclose(apply_transfer(fields[2], H), batch[2], atol=1e-5)


# ---------------------------------------------------------------------- gradients

@pytest.mark.usefixtures("debug_nans")
@pytest.mark.parametrize("method", ["fresnel_tf", "fresnel_ir", "angular_spectrum"])
def test_gradients_match_finite_differences(x64, method):
    """Reverse and forward derivatives with respect to the field (check_grads) and to z,
    λ and dx (central differences with a relative step), float64."""
    n, dx = 64, 2e-6
    zc = n * dx * dx / LAM
    z = 0.5 * zc if method != "fresnel_ir" else 2 * zc
    u = _smooth_field((n, n)).astype(jnp.complex128)
    w = jnp.asarray(np.random.default_rng(1).random((n, n)))

    def loss(field=u, z=z, lam=LAM, pitch=dx):
        out = propagate(field, pitch, lam, z, method=method, pad=0)
        return jnp.sum(w * jnp.abs(out) ** 2)

    check_grads(jax.jit(lambda f: propagate(f, dx, LAM, z, method=method, pad=0)), (u,),
                order=1, modes=("fwd", "rev"), eps=1e-6)
    assert_grad_matches_fd(lambda z_: loss(z=z_), z)
    assert_grad_matches_fd(lambda l_: loss(lam=l_), LAM)
    assert_grad_matches_fd(lambda p_: loss(pitch=p_), dx)


@pytest.mark.parametrize("method", ["fresnel_tf", "fresnel_ir", "angular_spectrum",
                                    "fourier_lens"])
def test_float32_gradient_of_a_normalised_intensity_agrees_with_float64(method):
    """A phase gradient of Σ w·|u|²/Σ|u|² through each propagator in float32 equals the
    float64 one (1e-3 of its largest entry): the PSF's normalisation once lost a term in
    float32 to an overflowed sum (test_camera)."""
    n, dx, z = 64, 5e-6, {"fresnel_ir": 5e-3}.get(method, 1e-3)
    rng = np.random.default_rng(0)
    phase = rng.uniform(-np.pi, np.pi, (n, n))
    w = rng.random((n, n))
    aperture = np.asarray(circular_aperture((n, n), dx, 0.1e-3))

    def gradient(dtype):
        def loss(ph):
            u = aperture.astype(dtype) * jnp.exp(1j * ph)
            if method == "fourier_lens":
                u = fourier_lens(u, dtype(dx), dtype(LAM), dtype(0.05))[0]
            else:
                fn = {"fresnel_tf": fresnel_tf, "fresnel_ir": fresnel_ir,
                      "angular_spectrum": angular_spectrum}[method]
                u = fn(u, dtype(dx), dtype(LAM), dtype(z))
            i = jnp.abs(u) ** 2
            return jnp.sum(jnp.asarray(w, dtype) * i) / jnp.sum(i)
        return jax.grad(loss)(jnp.asarray(phase, dtype))

    assert_float32_gradient_matches_float64(gradient)


@pytest.mark.usefixtures("debug_nans")
def test_fourier_lens_gradients(x64):
    """Fourier lens derivatives w.r.t. the field (check_grads) and focal length (relative
    central difference), float64."""
    u = _smooth_field((32, 48)).astype(jnp.complex128)
    w = jnp.asarray(np.random.default_rng(2).random((32, 48)))
    check_grads(jax.jit(lambda f: fourier_lens(f, 5e-6, LAM, 0.05)[0]), (u,), order=1,
                modes=("fwd", "rev"), eps=1e-6)
    loss = lambda f: jnp.sum(w * jnp.real(fourier_lens(u, 5e-6, LAM, f)[0]))  # noqa: E731
    assert_grad_matches_fd(loss, 0.05, rel_step=1e-9, rtol=1e-4)  # e^{jkf} turns fast


@pytest.mark.usefixtures("debug_nans")
def test_gradient_is_finite_through_evanescent_cut(x64):
    """The angular spectrum's square root is guarded: gradients w.r.t. z and λ stay finite
    when the grid holds evanescent frequencies (dx < λ/2)."""
    u = _smooth_field((64, 64), band=0.45).astype(jnp.complex128)
    g = jax.grad(lambda lam: jnp.sum(jnp.abs(angular_spectrum(u, 0.2e-6, lam, 1e-6)) ** 2))
    assert np.isfinite(float(g(LAM)))


# ---------------------------------------------------------------------- bad input

def test_bad_input_errors_say_what_to_do():
    """ValueError subclasses with actionable messages for each kind of bad input."""
    u = _smooth_field((32, 32))
    with pytest.raises(ShapeError, match="at least 2 axes"):
        fresnel_tf(u[0], 1e-6, LAM, 1e-3)
    with pytest.raises(ShapeError, match="empty"):
        fresnel_tf(u[:0], 1e-6, LAM, 1e-3)
    with pytest.raises(DiffcamError, match="dx"):
        fresnel_tf(u, 0.0, LAM, 1e-3)
    with pytest.raises(DiffcamError, match="wavelength"):
        angular_spectrum(u, 1e-6, -LAM, 1e-3)
    with pytest.raises(DiffcamError, match="finite"):
        fresnel_tf(u, 1e-6, LAM, float("nan"))
    with pytest.raises(DiffcamError, match="NaN"):      # a device array: checked in the call
        fresnel_tf(u.at[3, 3].set(jnp.nan), 1e-6, LAM, 1e-5)
    with pytest.raises(DiffcamError, match="NaN"):      # a NumPy array: checked before
        fresnel_tf(np.asarray(u.at[3, 3].set(jnp.nan)), 1e-6, LAM, 1e-3)
    with pytest.raises(DiffcamError, match="metres"):
        fourier_lens(u, 1e-6, LAM, 0.0)
    with pytest.raises(SamplingError, match="fresnel_ir"):
        fresnel_tf(u, 1e-6, LAM, 1.0)
    with pytest.raises(SamplingError, match="accept_undersampling"):
        fresnel_ir(u, 1e-6, LAM, 1e-6)
    with pytest.warns(UndersamplingWarning):
        fresnel_tf(u, 1e-6, LAM, 1.0, accept_undersampling=True)
    with pytest.raises(DiffcamError, match="pad=<int>"):
        jax.jit(lambda f: propagate(f, 1e-6, LAM, 1e-5))(u)
    with pytest.raises(DiffcamError, match="method"):
        propagate(u, 1e-6, LAM, 1e-5, method="rayleigh")
    assert issubclass(SamplingError, ValueError)


def test_remembered_geometry_still_checks_what_changes():
    """An eager call remembers a geometry that passed its checks (plain numbers), not a
    field's values, a failure, or a warning: each of those comes back on every call."""
    u = _smooth_field((32, 32))
    first = fresnel_tf(u, 1e-6, LAM, 1e-5)
    np.testing.assert_array_equal(fresnel_tf(u, 1e-6, LAM, 1e-5), first)
    with pytest.raises(DiffcamError, match="NaN"):      # same geometry, a bad field
        fresnel_tf(u.at[3, 3].set(jnp.nan), 1e-6, LAM, 1e-5)
    for _ in range(2):
        with pytest.raises(SamplingError, match="fresnel_ir"):
            fresnel_tf(u, 1e-6, LAM, 1.0)
        with pytest.warns(UndersamplingWarning):
            fresnel_tf(u, 1e-6, LAM, 1.0, accept_undersampling=True)
    # the same numbers as NumPy or JAX scalars: checked, not remembered, equal results
    np.testing.assert_allclose(fresnel_tf(u, np.float32(1e-6), jnp.float32(LAM), 1e-5),
                               first, atol=1e-6)
    np.testing.assert_array_equal(fresnel_tf(u, 1e-6, LAM, 0.0), u)
    # a remembered geometry inside someone's ahead-of-time compiled program
    compiled = jax.jit(lambda f: fresnel_tf(f, 1e-6, LAM, 1e-5)).lower(u).compile()
    np.testing.assert_allclose(compiled(u), first, atol=1e-6)
    # ... and with the field a device array closed over (the vector kept on the device)
    closed = jax.jit(lambda: fresnel_tf(u, 1e-6, LAM, 1e-5)).lower().compile()
    np.testing.assert_allclose(closed(), first, atol=1e-6)


def test_zero_distance_is_identity():
    """z = 0 returns the input for every method (no kernel, no division by z)."""
    u = _smooth_field((32, 32))
    for fn in (fresnel_tf, fresnel_ir, angular_spectrum):
        np.testing.assert_array_equal(fn(u, 1e-6, LAM, 0.0), u)


@pytest.mark.parametrize("n, dx, z", [(128, 3e-6, 3e-3), (100, 2e-6, 5e-3), (257, 5e-6, 15e-3),
                                        (257, 5e-6, 1e-3)])
def test_transfer_pad_is_the_least_pad_whose_critical_distance_reaches_z(n, dx, z):
    """The padded axis samples the transfer function of z (N·dx²/λ ≥ z); one sample less
    a side does not (or the unpadded axis already does)."""
    lam = 532e-9
    pad = transfer_pad(n, dx, lam, z)
    assert critical_distance((1, n + 2 * pad), dx, lam)[1] >= z
    assert pad == 0 or critical_distance((1, n + 2 * pad - 2), dx, lam)[1] < z
