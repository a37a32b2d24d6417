"""PSFs many at a time inside JAX: ``jax.vmap`` of ``psf`` (diffcam.model.point_spread),
which runs a chunk at a time (diffcam.core.backend.in_chunks), and the differentiable
stacks ``psf_map`` and ``psf_loss`` (diffcam.model.stack_map). The reference is one ``psf`` call per depth; memory is XLA's own
figure for the compiled program (``memory_analysis``), which does not depend on load."""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.model import Camera, point_spread, psf, psf_loss, psf_map, random_diffuser

LAM = 532e-9
N = 64
DEPTHS = np.array([20e-3, 31e-3, 60e-3])


def _camera(method="scaling"):
    return Camera(wavelength=LAM, z2=1e-3, dx=5e-6, aperture_radius=0.1e-3, shape=(N, N),
                  crop=(56, 48), method=method)


PHASE = random_diffuser(jax.random.key(0), (N, N), 5e-6, LAM, 40e-6)
WEIGHTS = jax.random.normal(jax.random.key(1), (DEPTHS.size, 56, 48))


@pytest.mark.usefixtures("debug_nans")
@pytest.mark.parametrize("method", ["scaling", pytest.param("direct", marks=pytest.mark.slow)])
def test_vmap_and_psf_map_equal_one_psf_per_depth(method):
    """``jit(vmap(psf))`` over depths equals psf at each depth (float32 round-off), and
    the gradient of Σ w·PSF through psf_map (chunks of 2 of 3 depths: a remainder,
    recomputed in reverse mode) and through psf_loss (computed with the value) equals
    that of one psf call per depth."""
    cam = _camera(method)
    stacked = jax.jit(jax.vmap(lambda z: psf(PHASE, cam, z)))(jnp.asarray(DEPTHS))
    for z, got in zip(DEPTHS, stacked):
        want = psf(PHASE, cam, z)
        np.testing.assert_allclose(got, want, atol=1e-5 * want.max())

    def one_by_one(p):
        return sum(jnp.sum(psf(p, cam, z) * w) for z, w in zip(DEPTHS, WEIGHTS))
    reference = jax.jit(jax.grad(one_by_one))(PHASE)
    grad = jax.jit(jax.grad(lambda p: psf_map(lambda h, w: jnp.sum(h * w), p, cam, DEPTHS,
                                              WEIGHTS, batch_size=2).sum()))(PHASE)
    np.testing.assert_allclose(grad, reference, atol=1e-4 * np.abs(reference).max())
    value, grad = jax.jit(jax.value_and_grad(
        lambda p: psf_loss(lambda h, w: jnp.sum(h * w), p, cam, DEPTHS, WEIGHTS,
                           batch_size=2)))(PHASE)
    np.testing.assert_allclose(value, one_by_one(PHASE), rtol=1e-5)
    np.testing.assert_allclose(grad, reference, atol=1e-4 * np.abs(reference).max())


@pytest.mark.slow  # 7 s; psf_loss's phase gradient by default: the test above
def test_psf_loss_differentiates_everything_psf_map_does(x64):
    """psf_loss's gradient in the depths, a per-depth input, an array its fn closes over
    and the camera's z2 equals that of the sum of psf_map (direct path, float64; a
    chunk of 2 of 3 depths); a per-depth integer input rides along undifferentiated; a
    gradient in the depths alone is the same as with the rest."""
    cam = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), _camera("direct"))
    index = jnp.arange(DEPTHS.size)

    def through(stack):
        def loss(z, w, s, z2):
            c = dataclasses.replace(cam, z2=z2)
            return stack(lambda h, x: s * jnp.sum(h * x[0]) + x[1], PHASE, c, z,
                         (w, index), batch_size=2)
        return jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3)))
    args = (jnp.asarray(DEPTHS), jnp.asarray(WEIGHTS, jnp.float64), 1.5, 1e-3)
    v_map, g_map = through(lambda *a, **k: psf_map(*a, **k).sum())(*args)
    v_loss, g_loss = through(psf_loss)(*args)
    np.testing.assert_allclose(v_loss, v_map, rtol=1e-12)
    for got, want in zip(g_loss, g_map):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
    only_z = jax.jit(jax.grad(lambda z: psf_loss(lambda h, x: 1.5 * jnp.sum(h * x), PHASE,
                                                     cam, z, args[1])))(args[0])
    np.testing.assert_allclose(only_z, g_map[0], rtol=1e-9)


def _float64_loss(method):
    """``(stack, phase, z1) → Σ_z Σ w·PSF(z)`` on a float64 camera, chunks of 2 of 3
    depths, for ``stack`` psf_loss or the sum of psf_map."""
    cam = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), _camera(method))
    w = jnp.asarray(WEIGHTS, jnp.float64)
    return lambda stack, p, z: stack(lambda h, x: jnp.sum(h * x), p, cam, z, w,
                                     batch_size=2)


@pytest.mark.slow  # 5 s of float64 compilation
def test_psf_loss_in_depths_both_modes_match_finite_differences(x64):
    """Along a move of the depths (direct path, float64), psf_loss's jvp and its
    reverse-mode derivative equal a central difference of the loss."""
    loss = _float64_loss("direct")
    phase, z = jnp.asarray(PHASE, jnp.float64), jnp.asarray(DEPTHS)
    move = jnp.array([1.0, -0.5, 2.0]) * 1e-3
    along = jax.jit(lambda s: loss(psf_loss, phase, z + s * move))
    step = 1e-4
    fd = (along(step) - along(-step)) / (2 * step)
    value, forward = jax.jvp(along, (0.0,), (1.0,))
    np.testing.assert_allclose(value, along(0.0), rtol=1e-12)
    np.testing.assert_allclose(forward, fd, rtol=1e-6)
    np.testing.assert_allclose(jax.jit(jax.grad(along))(0.0), forward, rtol=1e-10)


@pytest.mark.slow  # 60 s of compilation on a loaded machine
def test_psf_loss_equals_psf_map_on_the_scaling_path(x64):
    """Scaling path, float64, a chunk of 2 of 3 depths: psf_loss's value and phase
    gradient equal those of the sum of psf_map to 1e-10."""
    loss, phase, z = _float64_loss("scaling"), jnp.asarray(PHASE, jnp.float64), DEPTHS
    by_map = lambda *a, **k: psf_map(*a, **k).sum()  # noqa: E731
    v_map, g_map = jax.jit(jax.value_and_grad(partial(loss, by_map)))(phase, z)
    v_loss, g_loss = jax.jit(jax.value_and_grad(partial(loss, psf_loss)))(phase, z)
    np.testing.assert_allclose(v_loss, v_map, rtol=1e-10)
    np.testing.assert_allclose(g_loss, g_map, rtol=0, atol=1e-10 * np.abs(g_map).max())


@pytest.mark.slow  # 50 s of compilation: a chunk rule per batched argument
def test_vmap_over_positions_wavelengths_and_cameras():
    """A batch of lateral positions, of wavelengths or of z2 gives each item's PSF; the
    jvp of a vmap over depths is each depth's jvp."""
    cam = _camera()
    ys = jnp.array([-40e-6, 30e-6])
    batched = jax.vmap(lambda y: psf(PHASE, cam, 30e-3, y1=y, x1=-y / 2))(ys)
    want = psf(PHASE, cam, 30e-3, y1=30e-6, x1=-15e-6)
    np.testing.assert_allclose(batched[1], want, atol=1e-5 * want.max())
    z2s = jnp.array([0.9e-3, 1.1e-3])
    batched = jax.vmap(lambda z2: psf(PHASE, dataclasses.replace(cam, z2=z2), 30e-3))(z2s)
    want = psf(PHASE, dataclasses.replace(cam, z2=1.1e-3), 30e-3)
    np.testing.assert_allclose(batched[1], want, atol=1e-5 * want.max())
    lams = jnp.array([500e-9, 600e-9])
    batched = jax.vmap(lambda lam: psf(PHASE, cam, 30e-3, spectrum=(lam[None],
                                                                    jnp.ones(1))))(lams)
    want = psf(PHASE, cam, 30e-3, spectrum=([600e-9], [1.0]))
    np.testing.assert_allclose(batched[1], want, atol=1e-5 * want.max())
    tangent = jax.random.normal(jax.random.key(2), PHASE.shape)
    jvp = jax.jvp(lambda p: jax.vmap(lambda z: psf(p, cam, z))(jnp.asarray(DEPTHS)),
                  (PHASE,), (tangent,))[1]
    one = jax.jvp(lambda p: psf(p, cam, DEPTHS[1]), (PHASE,), (tangent,))[1]
    np.testing.assert_allclose(jvp[1], one, atol=1e-4 * np.abs(one).max())


@pytest.mark.slow
def test_psf_map_gradient_in_depth_matches_finite_differences(x64):
    """d/dz of Σ w·PSF through psf_map against a central difference (float64)."""
    cam = jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), _camera())
    phase, w = jnp.asarray(PHASE, jnp.float64), jnp.asarray(WEIGHTS[0], jnp.float64)
    loss = jax.jit(lambda z: psf_map(lambda h: jnp.sum(h * w), phase, cam,
                                     jnp.stack([z, z + 5e-3]))[0])
    z, h = 30e-3, 1e-7
    fd = (loss(z + h) - loss(z - h)) / (2 * h)
    np.testing.assert_allclose(jax.grad(loss)(z), fd, rtol=1e-5)


def _temporaries(fn, *args):
    return jax.jit(fn).lower(*args).compile().memory_analysis().temp_size_in_bytes


@pytest.mark.slow
def test_working_memory_is_flat_in_the_number_of_depths(monkeypatch):
    """XLA's temporaries of ``jit(vmap(psf))`` (both paths) and of psf_map's gradient
    are those of a chunk (here one depth): 4 and 32 depths need the same (within 10 %),
    where a vmap of every depth at once adds each depth's fields."""
    monkeypatch.setattr(point_spread, "FIELD_SAMPLES_PER_CHUNK", N * N)
    few, many = jnp.linspace(20e-3, 60e-3, 4), jnp.linspace(20e-3, 60e-3, 32)
    for method in ("scaling", "direct"):
        cam = _camera(method)
        stack = lambda zs: jax.vmap(lambda z: psf(PHASE, cam, z))(zs)  # noqa: E731
        assert _temporaries(stack, many) < 1.1 * _temporaries(stack, few)

    def gradient(zs):
        return jax.grad(lambda p: psf_map(lambda h: jnp.sum(h ** 2), p, cam, zs).sum())(PHASE)
    assert _temporaries(gradient, many) < 1.1 * _temporaries(gradient, few)

    def summed(zs):
        return jax.grad(lambda p: psf_loss(lambda h: jnp.sum(h ** 2), p, cam, zs))(PHASE)
    assert _temporaries(summed, many) < 1.1 * _temporaries(summed, few)


def test_psf_map_refuses_bad_input():
    cam = _camera()
    with pytest.raises(ShapeError, match="1-D"):
        psf_map(lambda h: h, PHASE, cam, np.ones((2, 2)) * 0.03)
    with pytest.raises(DiffcamError, match="batch_size"):
        psf_map(lambda h: h, PHASE, cam, DEPTHS, batch_size=0)
    with pytest.raises(DiffcamError, match="fn must be"):
        psf_map("sum", PHASE, cam, DEPTHS)
    with pytest.raises(DiffcamError, match="z1"):
        psf_map(lambda h: h, PHASE, cam, -DEPTHS)
    with pytest.raises(DiffcamError, match="real number per depth"):
        psf_loss(lambda h: h, PHASE, cam, DEPTHS)
    with pytest.raises(DiffcamError, match="batch_size"):
        psf_loss(jnp.sum, PHASE, cam, DEPTHS, batch_size=-1)
