"""The field-dependent (low-rank) PSF model: diffcam.model.field and its operator
diffcam.reconstruct.operators.field_model, in every solver."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.model import Camera, psf_stack, random_diffuser
from diffcam.model.field import (FieldPSF, chief_rays, field_psf, load_field_psf,
                                 register, save_field_psf)
from diffcam.reconstruct import (admm_tv, admm_tv_3d, fista, richardson_lucy,
                                 richardson_lucy_3d)
from diffcam.reconstruct.operators import convolution_model, field_model

SENSOR = (20, 24)
POSITIONS = np.array([[-4.0, -5.0], [-4.0, 5.0], [0.0, 0.0], [4.0, -5.0], [4.0, 5.0],
                      [1.0, 3.0]])


def _kernels(rng, k, shape=(9, 11)):
    """``k`` non-negative kernels with the axis sample at the centre."""
    return rng.random((k,) + shape) ** 3


def _shift(h, position):
    """``h`` moved by an integer ``position`` (pixels) on its own grid."""
    return np.roll(h, tuple(int(round(p)) for p in position), axis=(-2, -1))


def _affine(positions):
    """Weights that vary across the field as planes (a thin-plate spline reproduces
    them everywhere): ``(2, npos)``."""
    y, x = positions[..., 0], positions[..., 1]
    return np.stack([1 + 0.02 * y - 0.01 * x, 0.3 + 0.04 * x])


def _low_rank_field(rng, positions=POSITIONS):
    """PSFs that ARE rank 2 after registration: ``h_p = shift(Σ_k a_k(c_p) g_k, c_p)``."""
    g = _kernels(rng, 2)
    a = _affine(positions)
    psfs = np.stack([_shift(np.tensordot(a[:, p], g, 1), c) for p, c in enumerate(positions)])
    return psfs, g, a


def _one_kernel(h, volume=False):
    """K = 1 with constant weights: every position has the PSF ``h``."""
    depth = h.shape[:-2]
    return FieldPSF(kernels=jnp.asarray(h)[None],
                    coefficients=jnp.ones((1,) + depth + (1,), h.dtype),
                    positions=jnp.zeros(depth + (1, 2), h.dtype),
                    singular_values=jnp.ones(depth + (1,), h.dtype))


@pytest.mark.parametrize("boundary, volume", [("crop", False), ("circular", False),
                                              ("crop", True), ("same", True)])
def test_rank_one_constant_field_is_the_convolution_model(boundary, volume):
    """K = 1 with weights 1 everywhere is the shift-invariant model, forward and
    adjoint, to float32 rounding."""
    rng = np.random.default_rng(0)
    h = _kernels(rng, 3 if volume else 1).astype(np.float32)
    h = h if volume else h[0]
    model = field_model(_one_kernel(h), SENSOR, boundary)
    conv = convolution_model(jnp.asarray(h), SENSOR, boundary, volume=volume)
    assert model.object_shape == conv.object_shape and model.fft_shape == conv.fft_shape
    np.testing.assert_allclose(model.weights, 1, rtol=1e-6)
    x = rng.random(h.shape[:-2] + model.object_shape).astype(np.float32)
    y = rng.random(SENSOR).astype(np.float32)
    np.testing.assert_allclose(model(x), conv(x), atol=1e-6 * np.abs(conv(x)).max())
    np.testing.assert_allclose(model.adjoint(y), conv.adjoint(y),
                               atol=1e-6 * np.abs(conv.adjoint(y)).max())


@pytest.mark.parametrize("boundary, volume", [("crop", False), ("same", False),
                                              ("crop", True), ("circular", True)])
def test_adjoint_identity(boundary, volume, x64):
    """<A x, y> = <x, Aᵀ y> for a rank-3 model with weights varying across the field."""
    rng = np.random.default_rng(1)
    depth = (2,) if volume else ()
    psfs = rng.random(depth + (len(POSITIONS), 9, 11))
    model = field_model(field_psf(psfs, POSITIONS, rank=3), SENSOR, boundary)
    assert model.rank == 3 and float(jnp.std(model.weights[1])) > 0
    x = rng.standard_normal(depth + model.object_shape)
    y = rng.standard_normal(SENSOR)
    lhs, rhs = jnp.vdot(model(x), y), jnp.vdot(x, model.adjoint(y))
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12)


def test_a_low_rank_field_is_recovered(x64):
    """PSFs of rank 2 by construction: the tolerance picks rank 2 with no error, the
    model reproduces every measured PSF, and a point between the positions gets the
    PSF of its own (interpolated) weights."""
    psfs, g, a = _low_rank_field(np.random.default_rng(2))
    fp = field_psf(psfs, POSITIONS, tolerance=1e-6)
    assert fp.rank == 2 and float(fp.error()) < 1e-7 and float(fp.error(1)) > 1e-2
    np.testing.assert_allclose(fp.at(jnp.asarray(POSITIONS)),
                               register(psfs, POSITIONS), atol=1e-10)
    model = field_model(fp, SENSOR, "crop")
    oy, ox = model.object_shape
    point = np.array([2.0, -3.0])                # not one of the positions
    x = np.zeros(model.object_shape)
    x[oy // 2 + 2, ox // 2 - 3] = 1
    truth = np.tensordot(_affine(point), g, 1)   # centred on the axis, (my, mx)
    expected = convolution_model(jnp.asarray(truth), SENSOR, "crop")(x)
    np.testing.assert_allclose(model(x), expected, atol=1e-9 * float(np.max(expected)))


def test_the_rank_is_the_smallest_within_the_tolerance():
    """The rank chosen is the least whose error is within the tolerance."""
    rng = np.random.default_rng(3)
    psfs = rng.random((len(POSITIONS), 9, 11))
    for tol in (0.5, 0.2, 0.05):
        fp = field_psf(psfs, POSITIONS, tolerance=tol)
        assert float(fp.error()) <= tol < float(fp.error(fp.rank - 1))


@pytest.fixture(scope="module")
def engine_stack():
    """Off-axis PSFs from the engine on a 3 × 3 grid of sources at z1 = 25 mm."""
    n, lam, z1 = 64, 532e-9, 25e-3
    cam = Camera(wavelength=lam, z2=1e-3, dx=4e-6, aperture_radius=0.1e-3, shape=(n, n),
                 crop=(56, 56))
    phase = np.asarray(random_diffuser(jax.random.key(0), (n, n), 4e-6, lam, 40e-6))
    grid = np.linspace(-0.4e-3, 0.4e-3, 3)
    offsets = np.array([[y, x] for y in grid for x in grid])
    stack = psf_stack(phase, cam, [z1], offsets=offsets)[0]
    return stack, chief_rays(offsets, z1, 1e-3, 4e-6)


def test_engine_stack_decomposes_with_the_stated_error(engine_stack):
    """Registered at the chief rays ``−(y1, x1)·z2/z1``, the engine's off-axis PSFs are
    closer to one PSF than unregistered or registered at the opposite sign; the
    decomposition's model error is what the singular values say and is within the
    tolerance, one rank fewer is not; the registered PSFs it rebuilds are off by
    exactly that error."""
    stack, rays = engine_stack
    one = {sign: float(field_psf(stack, sign * rays, rank=1).error()) for sign in (1, 0, -1)}
    assert one[1] < 0.5 * min(one[0], one[-1])
    fp = field_psf(stack, rays, tolerance=1e-2)
    assert 1 < fp.rank < len(stack)
    assert float(fp.error()) <= 1e-2 < float(fp.error(fp.rank - 1))
    registered = register(jnp.asarray(stack), rays)
    rebuilt = fp.at(rays)
    measured = float(jnp.linalg.norm(rebuilt - registered) / jnp.linalg.norm(registered))
    np.testing.assert_allclose(measured, float(fp.error()), rtol=2e-2)


def _problem(volume):
    """A small rank-2 field model and the sensor image of a block scene."""
    rng = np.random.default_rng(4)
    psfs, _, _ = _low_rank_field(rng)
    psfs = np.stack([psfs, 0.6 * psfs[:, ::-1]]) if volume else psfs
    model = field_model(field_psf(psfs.astype(np.float32), POSITIONS, rank=2), SENSOR)
    x = np.zeros((2,) * volume + model.object_shape, np.float32)
    x[..., 9:17, 10:20] = 1
    return model, x, np.asarray(model(x))


SOLVERS_2D = [(fista, {}), (richardson_lucy, {}), (admm_tv, {"tau": 1e-6})]
SOLVERS_3D = [(fista, {}), (richardson_lucy_3d, {}), (admm_tv_3d, {"tau": 1e-6})]


@pytest.mark.parametrize("volume", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_every_solver_takes_the_model(volume):
    """FISTA, Richardson–Lucy and ADMM-TV, 2-D and 3-D, take the model in place of the
    PSF, with leading image axes as a batch: the estimates are on the model's object
    grid and each image's data misfit falls well below its start."""
    model, x, b = _problem(volume)
    other = 0.5 * b + 0.1 * np.asarray(model(x[..., ::-1, :]))
    for solver, kw in SOLVERS_3D if volume else SOLVERS_2D:
        out = solver(np.stack([b, other]), model, 150, progress=False, **kw)
        assert out.image.shape == (2,) + x.shape, solver.__name__
        assert np.all(np.asarray(out.residual[:, -1]) < 0.05 * np.asarray(out.residual[:, 0])), \
            solver.__name__


@pytest.mark.slow
def test_solvers_with_a_rank_one_model_match_the_psf_path():
    """Richardson–Lucy is the same iteration with the model as with its PSF (its
    update does not depend on the operator's scale); FISTA and the linearised ADMM
    reach the same fit as with the PSF."""
    rng = np.random.default_rng(5)
    h = _kernels(rng, 1)[0].astype(np.float32)
    model = field_model(_one_kernel(h), SENSOR, "crop")
    x = np.zeros(model.object_shape, np.float32)
    x[8:18, 12:22] = 1
    b = np.asarray(model(x))
    a, m = (richardson_lucy(b, p, 50, boundary="crop", progress=False) for p in (h, model))
    assert float(jnp.linalg.norm(m.image - a.image) / jnp.linalg.norm(a.image)) < 1e-4
    for solver in (fista, admm_tv):
        a, m = (solver(b, p, 300, progress=False) for p in (h, model))
        assert abs(float(m.residual[-1]) - float(a.residual[-1])) < 0.02, solver.__name__


@pytest.mark.slow  # float64 finite differences in both modes: 25 s
def test_gradients_through_the_model_match_finite_differences(x64):
    """Reverse and forward mode through the decomposition (fixed rank) and the operator,
    with respect to the PSFs and their positions, against finite differences."""
    rng = np.random.default_rng(6)
    psfs, _, _ = _low_rank_field(rng)
    scene = rng.random((2,) + convolution_model(jnp.ones((9, 11)), SENSOR, "crop").object_shape)

    def loss(psfs, positions):
        model = field_model(field_psf(psfs, positions, rank=2), SENSOR)
        return (jnp.sum(model(scene[0]) * model(scene[1]))
                + jnp.sum(model.adjoint(scene[0, :20, :24])))
    check_grads(loss, (jnp.asarray(psfs), jnp.asarray(POSITIONS + 0.3)), order=1,
                modes=("rev", "fwd"), eps=1e-5)


def test_save_and_load_round_trip_and_refuse_bad_files(tmp_path):
    psfs, _, _ = _low_rank_field(np.random.default_rng(7))
    fp = field_psf(psfs.astype(np.float32), POSITIONS, tolerance=1e-3)
    path = tmp_path / "field.npz"
    save_field_psf(path, fp, z1=25e-3)
    back, meta = load_field_psf(path)
    assert meta["rank"] == fp.rank and meta["z1"] == 25e-3 and meta["error"] <= 1e-3
    for a, b in zip(jax.tree.leaves(fp), jax.tree.leaves(back)):
        np.testing.assert_array_equal(a, b)
    np.savez(tmp_path / "other.npz", stack=np.ones(3))
    with pytest.raises(DiffcamError, match="other.npz"):
        load_field_psf(tmp_path / "other.npz")
    arrays = dict(np.load(path))
    arrays["positions"] = arrays["positions"][:2]
    np.savez(tmp_path / "cut.npz", **arrays)
    with pytest.raises(DiffcamError, match="do not fit together"):
        load_field_psf(tmp_path / "cut.npz")


def test_colour_file_round_trip_and_version_1(tmp_path):
    """A colour file holds one model per channel, in the channels' order, exactly; a
    version 1 file (one model, no channels) still reads; mismatched channels and
    damaged channel axes are refused."""
    rng = np.random.default_rng(9)
    models = [field_psf(_low_rank_field(rng)[0].astype(np.float32), POSITIONS, rank=2)
              for _ in range(3)]
    path = tmp_path / "colour.npz"
    save_field_psf(path, models, channels="RGB", grid=[2, 3], offset=[0.1, 0.2, 0.3])
    back, meta = load_field_psf(path)
    assert meta["channels"] == "RGB" and meta["grid"] == [2, 3] and len(back) == 3
    assert meta["error"] == max(float(m.error()) for m in models)
    for m, b in zip(models, back):
        for x, y in zip(jax.tree.leaves(m), jax.tree.leaves(b)):
            np.testing.assert_array_equal(x, y)
    arrays = dict(np.load(path))
    one = {k: v[0] for k, v in arrays.items() if k != "meta"}
    meta_1 = {k: v for k, v in meta.items() if k != "channels"}
    np.savez(tmp_path / "v1.npz", **one, meta=np.array(json.dumps({**meta_1, "version": 1})))
    single, _ = load_field_psf(tmp_path / "v1.npz")
    np.testing.assert_array_equal(single.kernels, models[0].kernels)
    with pytest.raises(DiffcamError, match="one channel per FieldPSF"):
        save_field_psf(tmp_path / "x.npz", models[:2], channels="RGB")
    with pytest.raises(DiffcamError, match="one FieldPSF"):
        save_field_psf(tmp_path / "x.npz", models)
    arrays["kernels"] = arrays["kernels"][:2]
    np.savez(tmp_path / "cut.npz", **arrays)
    with pytest.raises(DiffcamError, match="do not match its arrays"):
        load_field_psf(tmp_path / "cut.npz")


def test_bad_inputs_get_one_clear_error():
    rng = np.random.default_rng(8)
    psfs = rng.random((len(POSITIONS), 9, 11))
    with pytest.raises(ShapeError, match="positions"):
        field_psf(psfs, POSITIONS[:3])
    with pytest.raises(DiffcamError, match="tolerance"):
        field_psf(psfs, POSITIONS, tolerance=2.0)
    with pytest.raises(DiffcamError, match="rank"):
        field_psf(psfs, POSITIONS, rank=len(POSITIONS) + 1)
    with pytest.raises(DiffcamError, match="FieldPSF"):
        field_model(psfs[0], SENSOR)
    model = field_model(field_psf(psfs, POSITIONS, rank=2), SENSOR, "same")
    with pytest.raises(ShapeError, match="sensor"):
        fista(np.ones((10, 12)), model, 5, progress=False)
    with pytest.raises(DiffcamError, match="boundary"):
        admm_tv(np.ones(SENSOR), model, 5, progress=False)
    with pytest.raises(DiffcamError, match="3-D"):
        admm_tv_3d(np.ones(SENSOR), model, 5, progress=False)
