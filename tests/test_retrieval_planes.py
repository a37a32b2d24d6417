"""A captured PSF as a third intensity plane in the projection solvers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.model import Camera, psf, random_diffuser
from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.core.grid import crop_to
from diffcam.evaluate.metrics import pearson, phase_scores
from diffcam.optics.propagation import fresnel_tf
from diffcam.calibrate import DefocusedPlane, paper_simulation, psf_plane, raar

N, SIZE, Z1 = 256, 128, 22e-3


@pytest.fixture(scope="module")
def sim():
    """Paper Fig. 6 scaled down: a 1° random diffuser, 30 µm features, 128² in 256²."""
    phase = random_diffuser(jax.random.key(0), (SIZE, SIZE), 5e-6, 532e-9)
    return paper_simulation(N, SIZE, phase=phase)


@pytest.fixture(scope="module")
def camera():
    return Camera(wavelength=532e-9, z2=1e-3, dx=5e-6, aperture_radius=1.2e-3 * SIZE / 512,
                  shape=(N, N), crop=(152, 152))


def score(result, sim):
    return phase_scores(crop_to(result.phase, sim.truth.shape), sim.truth, mask=sim.mask)


@pytest.mark.slow
def test_psf_plane_is_the_plane_wave_intensity_at_z_eff(sim, camera):
    """Fresnel scaling theorem: the PSF of a point at z1 is the plane-wave intensity
    z1·z2/(z1 + z2) behind the diffuser, magnified by (z1 + z2)/z1."""
    plane = psf_plane(psf(sim.phase, camera, Z1), camera, Z1)
    z_eff = Z1 * 1e-3 / (Z1 + 1e-3)
    assert plane.distance == pytest.approx(z_eff)
    exact = jnp.abs(fresnel_tf(sim.aperture * jnp.exp(1j * sim.phase), 5e-6, 532e-9,
                               z_eff)) ** 2
    inside = np.asarray(plane.mask) > 0
    assert float(jnp.sum(exact * plane.mask) / jnp.sum(exact)) > 0.999  # the crop holds it
    assert np.corrcoef(np.asarray(plane.intensity)[inside], np.asarray(exact)[inside])[0, 1] > 0.99
    # the mask is the crop demagnified: 152 samples / M, less the edge
    width = int(inside[N // 2].sum())
    assert abs(width - (152 - 4) / ((Z1 + 1e-3) / Z1)) < 2


@pytest.mark.slow
def test_a_psf_plane_retrieves_a_random_diffuser_where_near_far_stall(sim, camera):
    """Near/far RAAR stalls on a phase spanning many 2π; with one PSF (at 22 mm) as a
    third plane it converges from a flat start, twin included (plain Pearson)."""
    alone = raar(sim.near, sim.far, sim.geometry, iterations=300, key=jax.random.key(0))
    assert float(score(alone, sim)["twin_resolved"]) < 0.8
    plane = psf_plane(psf(sim.phase, camera, Z1), camera, Z1)
    r = raar(sim.near, sim.far, sim.geometry, iterations=300, init="flat", planes=[plane])
    s = score(r, sim)
    assert float(s["pearson"]) > 0.995
    assert float(s["mse"]) < 0.02
    assert r.stats["planes"] == 1
    assert float(pearson(psf(r.phase, camera, 25e-3), psf(sim.phase, camera, 25e-3))) > 0.99


def test_bad_planes_are_refused(sim, camera):
    p = psf(sim.phase, camera, Z1)
    with pytest.raises(ShapeError, match="out_shape"):
        psf_plane(p[:-2], camera, Z1)
    with pytest.raises(DiffcamError, match="background"):
        psf_plane(p - 1.0, camera, Z1)
    with pytest.raises(DiffcamError, match="z1"):
        psf_plane(p, camera, -Z1)
    plane = psf_plane(p, camera, Z1)
    small = DefocusedPlane(plane.intensity[:-1], plane.distance, plane.mask[:-1])
    with pytest.raises(ShapeError, match="captures"):
        raar(sim.near, sim.far, sim.geometry, iterations=2, init="flat", planes=[small])
    with pytest.raises(DiffcamError, match="DefocusedPlane"):
        raar(sim.near, sim.far, sim.geometry, iterations=2, init="flat",
             planes=[plane.intensity])
