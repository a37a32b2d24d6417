"""Optical elements (diffcam/optics.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core.errors import DiffcamError, SamplingError
from diffcam.core.grid import radius2
from diffcam.optics.elements import (apply_phase, circular_aperture, point_source_field,
                            rectangular_aperture, thin_lens)
from conftest import assert_grad_matches_fd


def test_circular_aperture_area_and_offset():
    """Sample count ≈ πR²/dx² (within the perimeter's pixel count), the soft edge is closer
    to the exact area, and an offset centre moves the centroid by the offset."""
    n, dx, radius = 256, 1e-6, 40.3e-6
    exact = np.pi * (radius / dx) ** 2
    hard = float(circular_aperture((n, n), dx, radius).sum())
    soft = float(circular_aperture((n, n), dx, radius, edge="soft").sum())
    assert abs(hard - exact) < 2 * np.pi * radius / dx
    assert abs(soft - exact) < 0.002 * exact
    shifted = np.asarray(circular_aperture((n, n), dx, radius, centre=(10e-6, -20e-6)))
    ys, xs = np.nonzero(shifted)
    assert np.isclose((ys.mean() - n // 2) * dx, 10e-6, atol=0.1e-6)
    assert np.isclose((xs.mean() - n // 2) * dx, -20e-6, atol=0.1e-6)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_hard_aperture_is_the_square_root_rule_on_the_rim(precision):
    """The hard edge, decided on r² without a square root, keeps exactly the samples
    with sqrt(r²) ≤ radius rounded in the working precision (its definition), including
    samples on the rim (radii 5, 13, 25, 65 pitches pass through grid points: 3-4-5,
    5-12-13, 7-24-25, 16-63-65) and radii a rounding away from them."""
    n, dx = 160, 5e-6
    with jax.enable_x64(precision == "float64"):
        r2 = np.asarray(radius2((n, n), jnp.asarray(dx, precision)))
        for k in (5, 13, 25, 65, 40.3, 77.77):
            for radius in (k * dx, np.nextafter(k * dx, 0), np.nextafter(k * dx, 1)):
                r = np.asarray(radius, precision)
                rule = (r - np.sqrt(r2)) >= 0          # what the edge means, in numpy
                mask = np.asarray(circular_aperture((n, n), jnp.asarray(dx, precision),
                                                    radius)) > 0
                assert np.array_equal(mask, rule), (precision, k, radius)
    # a step in the radius: derivative 0, as before (no error from the rule's search)
    area = lambda r: jnp.sum(circular_aperture((n, n), dx, r))  # noqa: E731
    assert float(jax.grad(area)(40.3 * dx)) == 0.0


def test_rectangular_aperture_counts_samples():
    """A 21 × 41 µm rectangle at 1 µm pitch passes 21 × 41 samples (hard edge)."""
    a = rectangular_aperture((64, 96), 1e-6, 21e-6, 41e-6)
    assert float(a.sum()) == 21 * 41


@pytest.mark.usefixtures("debug_nans")
def test_soft_aperture_radius_gradient(x64):
    """The soft edge makes the transmitted area differentiable in the radius: d(area)/dR
    averaged over a pixel's worth of radii is 2πR/dx² (the circumference) within 1 %,
    and it matches a central difference."""
    n, dx = 128, 1e-6
    area = lambda r: jnp.sum(circular_aperture((n, n), dx, r, edge="soft"))  # noqa: E731
    radii = jnp.linspace(30e-6, 31e-6, 21)
    g = float(jnp.mean(jax.vmap(jax.grad(area))(radii)))
    assert abs(g / (2 * np.pi * 30.5e-6 / dx ** 2) - 1) < 0.01
    assert_grad_matches_fd(area, 30e-6, rel_step=1e-4, rtol=1e-3)


def test_point_source_field_is_paraxial_spherical_wave(x64):
    """Eq. 2: amplitude 1/(λz1) everywhere, phase k r²/(2 z1) about (x1, y1) plus kz1."""
    n, dx, lam, z1 = 64, 5e-6, 532e-9, 25e-3
    u = np.asarray(point_source_field((n, n), dx, lam, z1, x1=20e-6, y1=-10e-6))
    assert np.allclose(np.abs(u), 1 / (lam * z1))
    k = 2 * np.pi / lam
    y, x = (np.arange(n) - n // 2) * dx, (np.arange(n) - n // 2) * dx
    ref = np.exp(1j * k * z1) / (1j * lam * z1) * np.exp(
        1j * k * ((x[None, :] - 20e-6) ** 2 + (y[:, None] + 10e-6) ** 2) / (2 * z1))
    assert np.max(np.abs(u - ref)) * lam * z1 < 1e-6


def test_point_source_chirp_sampling_check():
    """The paper's simulation (R = 1.2 mm, λ = 532 nm, dx = 5 µm): the on-axis chirp reaches
    Nyquist at z1 = 22.56 mm (docs/design.md), so 22 mm is an error and 23 mm is fine; the
    message gives the pitch that would work."""
    kw = dict(aperture_radius=1.2e-3)
    with pytest.raises(SamplingError, match=r"dx ≤ 4\.8"):
        point_source_field((64, 64), 5e-6, 532e-9, 22e-3, **kw)
    point_source_field((64, 64), 5e-6, 532e-9, 23e-3, **kw)
    with pytest.warns(UserWarning):
        point_source_field((64, 64), 5e-6, 532e-9, 22e-3, accept_undersampling=True, **kw)


def test_thin_lens_and_phase_screen():
    """Thin lens: unit modulus, phase −k r²/(2f); apply_phase multiplies by e^{jθ}."""
    n, dx, lam, f = 32, 2e-6, 0.5e-6, 5e-3
    t = np.asarray(thin_lens((n, n), dx, lam, f))
    assert np.allclose(np.abs(t), 1, atol=1e-6)
    r2 = (3 * dx) ** 2
    assert np.isclose(np.angle(t[n // 2, n // 2 + 3]), -2 * np.pi / lam * r2 / (2 * f), atol=1e-5)
    theta = jnp.full((n, n), 0.3)
    np.testing.assert_allclose(apply_phase(jnp.ones((n, n)), theta), np.exp(0.3j) * np.ones((n, n)),
                               rtol=1e-6)


def test_optics_bad_input():
    """Aperture larger than the grid, non-positive radius, mismatched phase, f = 0."""
    with pytest.raises(DiffcamError, match="beyond the grid"):
        circular_aperture((64, 64), 1e-6, 40e-6)
    with pytest.raises(DiffcamError, match="radius"):
        circular_aperture((64, 64), 1e-6, -1e-6)
    with pytest.raises(DiffcamError, match="does not match"):
        apply_phase(jnp.ones((8, 8)), jnp.ones((9, 9)))
    with pytest.raises(DiffcamError, match="non-zero"):
        thin_lens((8, 8), 1e-6, 0.5e-6, 0.0)
    with pytest.raises(DiffcamError, match="edge"):
        circular_aperture((64, 64), 1e-6, 10e-6, edge="fuzzy")


@pytest.mark.usefixtures("debug_nans")
def test_element_gradients_match_finite_differences(x64):
    """Point-source field w.r.t. z1 and x1, thin lens w.r.t. f, phase screen w.r.t. θ:
    reverse-mode derivatives equal relative-step central differences (float64)."""
    from jax.test_util import check_grads

    n, dx, lam = 32, 5e-6, 532e-9
    w = jnp.asarray(np.random.default_rng(3).random((n, n)))
    src = lambda z1=25e-3, x1=20e-6: jnp.sum(  # noqa: E731
        w * jnp.real(point_source_field((n, n), dx, lam, z1, x1=x1) * lam * z1))
    assert_grad_matches_fd(lambda z: src(z1=z), 25e-3, rel_step=1e-9, rtol=1e-4)
    assert_grad_matches_fd(lambda x: src(x1=x), 20e-6, rel_step=1e-6, rtol=1e-4)
    lens = lambda f: jnp.sum(w * jnp.imag(thin_lens((n, n), dx, lam, f)))  # noqa: E731
    assert_grad_matches_fd(lens, 5e-3, rel_step=1e-7, rtol=1e-4)
    check_grads(jax.jit(lambda t: apply_phase(jnp.ones((n, n)), t)),
                (w,), order=1, modes=("fwd", "rev"))
