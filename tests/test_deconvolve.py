"""Tests of diffcam.reconstruct: Richardson–Lucy, ADMM-TV, Wiener and the forward models.

References: scikit-image's ``richardson_lucy`` (the skimage convention, bit for bit),
``scipy.signal.convolve`` (direct linear convolution), dense-matrix Tikhonov solves
(Wiener) and ``scipy.optimize.nnls`` (ADMM without TV).
"""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.signal
from jax.test_util import check_grads
from skimage.restoration import richardson_lucy as skimage_rl

from diffcam.core.backend import fft_size
from diffcam.core.errors import ConvergenceWarning, DiffcamError, ShapeError
from diffcam.reconstruct import (Reconstruction, admm_tv, admm_tv_3d, convolution_model,
                                 focus_sweep, richardson_lucy, richardson_lucy_3d,
                                 wiener)
from diffcam.reconstruct.operators import divergence, gradient

from conftest import assert_float32_gradient_matches_float64


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def _rel(a, b):
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(np.asarray(b)))


def _problem(shape=(30, 36), psf_shape=(7, 8), seed=0):
    rng = np.random.default_rng(seed)
    return rng.random(shape) + 0.1, rng.random(psf_shape) ** 2


def _dense(model, object_shape):
    """The matrix of a linear operator, column by column."""
    n = int(np.prod(object_shape))
    basis = np.eye(n).reshape((n,) + tuple(object_shape))
    return np.stack([np.asarray(model(e)).ravel() for e in basis], axis=1)


# --- forward model -----------------------------------------------------------------


@pytest.mark.parametrize("boundary", ["same", "circular", "crop"])
@pytest.mark.parametrize("psf_shape", [(5, 5), (6, 8)])
def test_adjoint_identity(x64, boundary, psf_shape):
    """<A x, y> = <x, Aᵀ y> to 1e-10 (relative) for every boundary, odd and even PSFs."""
    rng = np.random.default_rng(1)
    psf = rng.random(psf_shape)
    model = convolution_model(jnp.asarray(psf), (17, 20), boundary)
    x = rng.standard_normal(model.object_shape)
    y = rng.standard_normal((17, 20))
    lhs = float(jnp.vdot(model(x), y))
    rhs = float(jnp.vdot(x, model.adjoint(y)))
    assert abs(lhs - rhs) <= 1e-10 * abs(lhs)


def test_adjoint_identity_volume(x64):
    rng = np.random.default_rng(2)
    model = convolution_model(jnp.asarray(rng.random((3, 6, 7))), (12, 13), "crop", volume=True)
    x = rng.standard_normal((3,) + model.object_shape)
    y = rng.standard_normal((12, 13))
    lhs, rhs = float(jnp.vdot(model(x), y)), float(jnp.vdot(x, model.adjoint(y)))
    assert abs(lhs - rhs) <= 1e-10 * abs(lhs)


@pytest.mark.parametrize("psf_shape", [(5, 7), (6, 6)])
def test_same_and_crop_equal_direct_convolution(x64, psf_shape):
    """'same' = scipy.signal.convolve(mode='same') with the PSF centred at m//2; 'crop' =
    the centre of the full linear convolution of the object grid."""
    rng = np.random.default_rng(3)
    psf = rng.random(psf_shape)
    x = rng.random((16, 19))
    my, mx = psf_shape
    full = scipy.signal.convolve(x, psf, mode="full")
    same = full[my // 2:my // 2 + 16, mx // 2:mx // 2 + 19]
    assert _rel(convolution_model(jnp.asarray(psf), x.shape, "same")(x), same) < 1e-12
    model = convolution_model(jnp.asarray(psf), (10, 11), "crop")
    obj = rng.random(model.object_shape)
    oy, ox = model.object_shape
    full = scipy.signal.convolve(obj, psf, mode="full")
    # sensor index i sees object index i + oy//2 - 10//2 through psf[m//2]
    y0, x0 = oy // 2 - 5 + my // 2, ox // 2 - 11 // 2 + mx // 2
    assert _rel(model(obj), full[y0:y0 + 10, x0:x0 + 11]) < 1e-12


def test_gradient_divergence_adjoint(x64):
    rng = np.random.default_rng(4)
    x, g = rng.standard_normal((9, 11)), rng.standard_normal((2, 9, 11))
    assert np.isclose(float(jnp.vdot(gradient(x), g)), -float(jnp.vdot(x, divergence(g))))


# --- Richardson–Lucy --------------------------------------------------------------


@pytest.mark.parametrize("psf_shape", [(5, 5), (6, 6), (4, 7), (8, 5)])
def test_skimage_convention_matches_scikit_image(x64, psf_shape):
    """Equals skimage.restoration.richardson_lucy(clip=False) to < 1e-6 relative L2."""
    image, psf = _problem(psf_shape=psf_shape)
    ref = skimage_rl(image, psf, 25, clip=False)
    out = richardson_lucy(image, psf, 25, convention="skimage")
    assert out.image.dtype == jnp.float64
    assert _rel(out.image, ref) < 1e-6


def test_skimage_convention_filter_epsilon(x64):
    image, psf = _problem()
    level = float(np.percentile(scipy.signal.convolve(np.full_like(image, 0.5), psf, "same"), 20))
    ref = skimage_rl(image, psf, 10, clip=False, filter_epsilon=level)
    out = richardson_lucy(image, psf, 10, convention="skimage", filter_epsilon=level)
    assert _rel(out.image, ref) < 1e-6


def test_skimage_even_psf_is_not_the_adjoint(x64):
    """For an even PSF scikit-image's back-projection is shifted by a pixel: the two
    conventions differ, while for an odd PSF (interior) they agree up to normalisation."""
    image, psf = _problem(psf_shape=(6, 6))
    a = richardson_lucy(image, psf, 10, convention="skimage").image
    b = richardson_lucy(image, psf, 10, init=0.5).image
    assert _rel(a / a.mean(), b / b.mean()) > 1e-2


def _rl_direct(image, psf, iterations, boundary):
    """The default update written with scipy.signal.convolve (no FFT), in float64."""
    my, mx = psf.shape
    ny, nx = image.shape
    if boundary == "same":
        oy, ox = ny, nx
        fwd = lambda x: scipy.signal.convolve(x, psf, "full", method="direct")[  # noqa
            my // 2:my // 2 + ny, mx // 2:mx // 2 + nx]
        adj = lambda r: scipy.signal.correlate(r, psf, "full", method="direct")[  # noqa
            my - 1 - my // 2:my - 1 - my // 2 + ny, mx - 1 - mx // 2:mx - 1 - mx // 2 + nx]
    else:  # crop
        oy, ox = convolution_model(jnp.asarray(psf), image.shape, "crop").object_shape
        y0, x0 = oy // 2 - ny // 2 + my // 2, ox // 2 - nx // 2 + mx // 2
        fwd = lambda x: scipy.signal.convolve(x, psf, "full", method="direct")[  # noqa
            y0:y0 + ny, x0:x0 + nx]

        def adj(r):
            big = np.zeros((oy + my - 1, ox + mx - 1))
            big[y0:y0 + ny, x0:x0 + nx] = r
            return scipy.signal.correlate(big, psf, "valid", method="direct")
    sens = adj(np.ones_like(image))
    seen = sens > 1e-5 * sens.max()
    x = np.where(seen, image.sum() / sens[seen].sum(), 0.0)
    for _ in range(iterations):
        x = np.where(seen, x * adj(image / (fwd(x) + 1e-12)) / np.where(seen, sens, 1), 0)
    return x


@pytest.mark.parametrize("boundary", ["same", "crop"])
@pytest.mark.parametrize("psf_shape", [(5, 5), (6, 4)])
def test_default_equals_direct_implementation(x64, boundary, psf_shape):
    image, psf = _problem(shape=(14, 17), psf_shape=psf_shape)
    ref = _rl_direct(image, psf, 15, boundary)
    out = richardson_lucy(image, psf, 15, boundary=boundary)
    assert out.image.shape == ref.shape
    assert _rel(out.image, ref) < 1e-10


def test_rl_keeps_flux_and_sign_and_lowers_idivergence():
    image, psf = _problem()
    out = richardson_lucy(image, psf, 40, boundary="circular")
    assert out.image.dtype == jnp.float32
    assert float(out.image.min()) >= 0
    model = convolution_model(jnp.asarray(psf, jnp.float32), image.shape, "circular")
    assert np.isclose(float(model(out.image).sum()), image.sum(), rtol=1e-4)
    assert np.all(np.diff(np.asarray(out.objective)) <= 1e-5 * float(out.objective[0]))
    assert out.residual.shape == (40,) and int(out.iterations) == 40 and not out.converged


def test_rl_recovers_sparse_scene(x64):
    """Noise-free data of a few points: RL's estimate concentrates on them."""
    rng = np.random.default_rng(5)
    psf = rng.random((15, 15)) ** 4
    scene = np.zeros((40, 40))
    scene[[10, 20, 31], [12, 25, 30]] = [1.0, 2.0, 1.5]
    image = np.asarray(convolution_model(jnp.asarray(psf), scene.shape, "same")(scene))
    out = richardson_lucy(image, psf, 500, accelerate=True)
    est = np.asarray(out.image)
    assert est[[10, 20, 31], [12, 25, 30]].sum() > 0.8 * est.sum()
    assert float(out.residual[-1]) < 1e-2


@pytest.mark.slow  # variants of the solver: its default is tested throughout
def test_acceleration_and_tv_variants():
    image, psf = _problem(seed=6)
    plain = richardson_lucy(image, psf, 30)
    fast = richardson_lucy(image, psf, 30, accelerate=True)
    assert float(fast.objective[-1]) < float(plain.objective[-1])
    tv = richardson_lucy(image, psf, 30, tv_weight=0.01)
    assert float(tv.image.min()) >= 0 and np.all(np.isfinite(np.asarray(tv.image)))
    tv_total = lambda x: float(jnp.abs(gradient(x)).sum())  # noqa: E731
    assert tv_total(tv.image) < tv_total(plain.image)


@pytest.mark.parametrize("scale", [1e-15, 1e15])
@pytest.mark.parametrize("variant", [{}, {"accelerate": True}, {"tv_weight": 0.01},
                                     {"volume": True}])
def test_rl_result_scales_with_the_image_and_the_psf(x64, scale, variant):
    """RL is homogeneous: A(s·x) = s·A(x), so an image in any units (irradiance in W,
    counts, a unit sum) gives the same estimate in those units, and a PSF s times larger
    an estimate s times smaller. Half of the scene is dark, where ``eps`` meets ``A x``."""
    rng = np.random.default_rng(11)
    scene = rng.random((24, 28)) * (np.arange(28) < 14)
    psf = rng.random((5, 5)) ** 2
    options = dict(variant)
    if options.pop("volume", False):
        psf = np.stack([psf, psf.T[::-1]])
        image = np.asarray(convolution_model(jnp.asarray(psf), scene.shape, "same",
                                             volume=True)(np.stack([scene, scene[::-1]])))
        solve = lambda b, h: richardson_lucy_3d(b, h, 20, boundary="same", **options)  # noqa: E731
    else:
        image = np.asarray(convolution_model(jnp.asarray(psf), scene.shape, "same")(scene))
        solve = lambda b, h: richardson_lucy(b, h, 20, **options)  # noqa: E731
    image = np.maximum(image, 0)
    reference = np.asarray(solve(image, psf).image)
    assert _rel(np.asarray(solve(image * scale, psf).image) / scale, reference) < 1e-10
    assert _rel(np.asarray(solve(image, psf * scale).image) * scale, reference) < 1e-10


@pytest.mark.parametrize("options, oscillates", [
    ({}, False), ({"accelerate": True}, False), ({"tv_weight": 1e-3}, False),
    ({"tv_weight": 0.05}, True)], ids=["plain", "accelerated", "tv-1e-3", "tv-0.05"])
def test_tv_rl_that_oscillates_says_so(options, oscillates):
    """Plain RL lowers its objective at every step (EM); TV-RL with a large weight does
    not settle, and the objective history that shows it comes with a warning."""
    rng = np.random.default_rng(1)
    image, psf = rng.random((48, 56)) + 0.1, rng.random((9, 9)) ** 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = richardson_lucy(image, psf, 200, progress=False, **options)
    objective = np.asarray(out.objective, np.float64)
    rise = np.max(np.diff(objective) / objective[1:])
    warned = [w for w in caught if issubclass(w.category, ConvergenceWarning)]
    assert (rise > 1e-3) == oscillates and bool(warned) == oscillates
    if oscillates:
        assert "tv_weight=0.05" in str(warned[0].message)


def test_early_stopping_inside_jit():
    image, psf = _problem(seed=7)
    out = richardson_lucy(image, psf, 500, tol=1e-3)
    k = int(out.iterations)
    assert bool(out.converged) and 1 < k < 500
    assert np.all(np.isfinite(np.asarray(out.objective[:k])))
    assert np.all(np.isnan(np.asarray(out.objective[k:])))
    f = np.asarray(out.objective)
    assert abs(f[k - 1] - f[k - 2]) <= 1e-3 * abs(f[k - 2])


def test_batched_psfs_and_vmap_agree():
    """Leading axes broadcast; the batched call equals per-PSF calls and jax.vmap."""
    rng = np.random.default_rng(8)
    image = rng.random((20, 24)) + 0.1
    psfs = rng.random((3, 5, 5))
    batched = richardson_lucy(image, psfs, 10)
    assert batched.image.shape == (3, 20, 24) and batched.residual.shape == (3, 10)
    for k in range(3):
        single = richardson_lucy(image, psfs[k], 10)
        assert _rel(batched.image[k], single.image) < 1e-5
    mapped = jax.vmap(lambda h: richardson_lucy(image, h, 10).image)(jnp.asarray(psfs))
    assert _rel(mapped, batched.image) < 1e-5


@pytest.mark.slow
@pytest.mark.parametrize("solver, options", [
    (richardson_lucy, {}), (richardson_lucy, {"accelerate": True}),
    (richardson_lucy, {"tv_weight": 1e-3}), (admm_tv, {}), (wiener, {})],
    ids=["rl", "rl-accelerated", "rl-tv", "admm", "wiener"])
def test_float32_gradient_through_a_solver_agrees_with_float64(solver, options):
    """The PSF gradient of a loss on the estimate, through 30 iterations, in float32
    equals the float64 one: nothing on the way leaves float32's range or amplifies its
    rounding."""
    image, psf = _problem(shape=(24, 28), psf_shape=(5, 5), seed=9)
    if solver is not wiener:
        options = {"iterations": 30, "progress": False, **options}

    def gradient(dtype):
        def loss(h):
            x = solver(jnp.asarray(image, dtype), h, **options).image
            return jnp.sum(x ** 2) / jnp.sum(x) ** 2
        return jax.grad(loss)(jnp.asarray(psf, dtype))
    assert_float32_gradient_matches_float64(gradient)


@pytest.mark.usefixtures("debug_nans")
def test_jit_wrapping_and_gradient(x64):
    """Works under a caller's jit, and grad through the scan matches finite differences."""
    image, psf = _problem(shape=(10, 12), psf_shape=(3, 3), seed=9)
    jitted = jax.jit(lambda b, h: richardson_lucy(b, h, 5).image)
    assert _rel(jitted(image, psf), richardson_lucy(image, psf, 5).image) < 1e-12
    loss = lambda h: jnp.sum(richardson_lucy(image, h, 5).image ** 2)  # noqa: E731
    check_grads(jax.jit(loss), (jnp.asarray(psf),), order=1, modes=["rev"], atol=1e-6,
                rtol=1e-5)


@pytest.mark.parametrize("method, measure", [pytest.param("admm", "misfit", marks=pytest.mark.slow),
                                             ("rl", "misfit"),
                                             ("rl", "sharpness")])
def test_focus_sweep_picks_the_true_depth(method, measure):
    """A scene blurred by any plane of a stack of dilated PSFs is found at that plane."""
    rng = np.random.default_rng(10)
    base = (rng.random((9, 9)) > 0.7).astype(float)
    planes = [np.kron(base, np.ones((k, k))) for k in (1, 2, 3)] + [np.kron(base.T, np.ones((2, 2)))]
    stack = np.stack([np.pad(p, ((27 - len(p)) // 2, (28 - len(p)) // 2)) for p in planes])
    scene = np.zeros((48, 48))
    scene[[12, 30, 24], [14, 20, 36]] = 1
    for true in range(4):
        image = np.asarray(convolution_model(jnp.asarray(stack[true]), scene.shape,
                                             "same")(scene))
        sweep = focus_sweep(image, stack, 100, method=method, measure=measure)
        assert sweep.misfit.shape == sweep.sharpness.shape == (4,)
        assert int(sweep.best) == true


def test_rl_3d_separates_planes(x64):
    """Two planes with different PSFs: a point in plane 1 is put back in plane 1."""
    rng = np.random.default_rng(11)
    stack = rng.random((2, 9, 9)) ** 6
    model = convolution_model(jnp.asarray(stack), (24, 24), "crop", volume=True)
    scene = np.zeros((2,) + model.object_shape)
    scene[1, 14, 17] = 1.0
    scene[1, 20, 12] = 0.5
    image = np.asarray(model(scene))
    out = richardson_lucy_3d(image, stack, 300)
    est = np.asarray(out.image)
    assert est.shape == scene.shape
    assert est[1].sum() > 0.9 * est.sum()
    assert float(out.residual[-1]) < 0.02


# --- Wiener -------------------------------------------------------------------------


def test_wiener_equals_dense_tikhonov(x64):
    """Circular Wiener = argmin ||h⊛x - b||² + λ||x||², solved with the dense matrix
    (h the PSF normalised to unit sum, as wiener normalises it)."""
    image, psf = _problem(shape=(8, 10), psf_shape=(3, 4), seed=12)
    psf = psf / psf.sum()
    model = convolution_model(jnp.asarray(psf), image.shape, "circular")
    a = _dense(model, image.shape)
    lam = 1e-2 * float(np.max(np.abs(np.asarray(model.otf)) ** 2))
    ref = np.linalg.solve(a.T @ a + lam * np.eye(a.shape[1]), a.T @ image.ravel())
    out = wiener(image, psf, 1e-2)
    assert _rel(np.asarray(out.image).ravel(), ref) < 1e-10
    assert out.residual.shape == (1,) and out.objective.shape == (1,)


# --- ADMM ---------------------------------------------------------------------------


def _nnls_problem():
    """A circular 8×8 deconvolution without TV: the image, the PSF, the dense model
    matrix and the non-negative least-squares solution (scipy.optimize.nnls)."""
    rng = np.random.default_rng(13)
    psf = rng.random((4, 4))
    scene = np.maximum(rng.standard_normal((8, 8)), 0)
    model = convolution_model(jnp.asarray(psf), scene.shape, "circular")
    image = np.asarray(model(scene)) + 0.01 * rng.standard_normal(scene.shape)
    a = _dense(model, scene.shape)
    return image, psf, a, scipy.optimize.nnls(a, image.ravel())[0]


@pytest.mark.parametrize("relaxation", [1.0, 1.7])
def test_admm_without_tv_reaches_nnls(x64, relaxation):
    """tau=0, circular: ADMM minimises ½||Ax-b||² over x >= 0 (scipy.optimize.nnls),
    plain or over-relaxed (the fixed point does not depend on the relaxation)."""
    image, psf, a, x_ref = _nnls_problem()
    f_ref = 0.5 * np.sum((a @ x_ref - image.ravel()) ** 2)
    out = admm_tv(image, psf, 3000, mu1=0.05, mu2=0.05, mu3=0.05, tau=0.0,
                  boundary="circular", relaxation=relaxation)
    est = np.asarray(out.image).ravel()
    assert est.min() >= 0
    f = 0.5 * np.sum((a @ est - image.ravel()) ** 2)
    assert f <= f_ref * (1 + 1e-3) + 1e-12
    assert _rel(est, x_ref) < 1e-6


def test_admm_over_relaxation_converges_in_fewer_iterations(x64):
    """Over-relaxation (Boyd et al. 2011, §3.4.3) with α = 1.7: after 300 iterations the
    estimate is at least ten times closer to the NNLS solution than plain ADMM's."""
    image, psf, _, x_ref = _nnls_problem()
    error = {alpha: _rel(admm_tv(image, psf, 300, mu1=0.05, mu2=0.05, mu3=0.05, tau=0.0,
                                 boundary="circular", relaxation=alpha,
                                 progress=False).image.ravel(), x_ref)
             for alpha in (1.0, 1.7)}
    assert error[1.7] < 0.1 * error[1.0]


def test_admm_decreases_its_objective(x64):
    rng = np.random.default_rng(14)
    psf = rng.random((12, 12)) ** 6
    model = convolution_model(jnp.asarray(psf), (20, 20), "crop")
    scene = np.zeros(model.object_shape)
    scene[12:22, 10:26] = 1.0
    image = np.asarray(model(scene))
    out = admm_tv(image, psf, 400, mu1=1e-2, mu2=1e-2, mu3=1e-2, tau=1e-3)
    f = np.asarray(out.objective)
    assert f[-1] < 0.05 * f[0] and f[-1] < f[10] < f[1]
    tail = f[200:]
    assert np.all(np.diff(tail) <= 1e-3 * tail[:-1])   # monotone once converging
    assert float(out.image.min()) >= 0
    assert float(out.residual[-1]) < 0.05


def test_admm_3d_and_2d_agree_for_one_plane(x64):
    image, psf = _problem(shape=(16, 18), psf_shape=(8, 9), seed=15)
    a = admm_tv(image, psf, 20, mu1=1e-2, mu2=1e-2, mu3=1e-2, tau=1e-3)
    b = admm_tv_3d(image, psf[None], 20, mu1=1e-2, mu2=1e-2, mu3=1e-2, tau=1e-3)
    assert b.image.shape == (1,) + a.image.shape
    assert _rel(b.image[0], a.image) < 1e-10


def test_admm_3d_axial_tv_runs_and_fits(x64):
    rng = np.random.default_rng(16)
    stack = rng.random((3, 8, 8)) ** 6
    model = convolution_model(jnp.asarray(stack), (16, 16), "crop", volume=True)
    scene = np.zeros((3,) + model.object_shape)
    scene[:, 10:14, 8:16] = 1.0
    image = np.asarray(model(scene))
    out = admm_tv_3d(image, stack, 200, mu1=1e-2, mu2=1e-2, mu3=1e-2, tau=1e-4)
    assert out.image.shape == scene.shape and float(out.image.min()) >= 0
    assert float(out.residual[-1]) < 0.05
    assert float(out.objective[-1]) < 0.01 * float(out.objective[0])


def test_result_is_a_pytree():
    image, psf = _problem()
    out = jax.jit(lambda b: admm_tv(b, psf, 3))(image)
    assert isinstance(out, Reconstruction) and out.image.shape == (
        fft_size(30 + 7 - 1), fft_size(36 + 8 - 1))


# --- validation ---------------------------------------------------------------------


@pytest.mark.parametrize("solver", [richardson_lucy, admm_tv, wiener])
def test_bad_inputs_raise_clear_errors(solver):
    image, psf = _problem()
    args = (lambda b, h: solver(b, h, 5)) if solver is not wiener else solver
    with pytest.raises(ShapeError, match="larger than the image"):
        args(image[:5, :5], psf)
    with pytest.raises(DiffcamError, match="negative"):
        args(image, psf - 0.5)
    with pytest.raises(DiffcamError, match="sums to zero"):
        args(image, np.zeros_like(psf))
    bad = image.copy()
    bad[3, 3] = np.nan
    with pytest.raises(DiffcamError, match="NaN/Inf"):
        args(bad, psf)
    bad_psf = psf.copy()
    bad_psf[0, 0] = np.inf
    with pytest.raises(DiffcamError, match="NaN/Inf"):
        args(image, bad_psf)
    with pytest.raises(ShapeError, match="at least 2 axes"):
        args(image[0], psf)
    with pytest.raises(ShapeError, match="do not broadcast"):
        args(np.stack([image] * 2), np.stack([psf] * 3))


@pytest.mark.parametrize("iterations", [0, -3, 2.5, True])
def test_bad_iterations(iterations):
    image, psf = _problem()
    with pytest.raises(DiffcamError, match="iterations"):
        richardson_lucy(image, psf, iterations)


def test_rl_specific_errors():
    image, psf = _problem()
    with pytest.raises(DiffcamError, match="non-negative counts"):
        richardson_lucy(image - 0.5, psf, 3)
    with pytest.raises(DiffcamError, match="boundary='same'"):
        richardson_lucy(image, psf, 3, convention="skimage", boundary="crop")
    with pytest.raises(DiffcamError, match="boundary must be"):
        richardson_lucy(image, psf, 3, boundary="reflect")
    with pytest.raises(ShapeError, match="one shape"):
        richardson_lucy_3d(image, [psf, psf[:-1]], 3)
    with pytest.raises(ShapeError, match="nz, my, mx"):
        richardson_lucy_3d(image, psf, 3)
    with pytest.raises(DiffcamError, match="tol"):
        richardson_lucy(image, psf, 3, tol=-1.0)
    with pytest.raises(ShapeError, match="object grid"):
        richardson_lucy(image, psf, 3, init=np.ones((4, 4)))


def test_admm_specific_errors():
    image, psf = _problem()
    with pytest.raises(DiffcamError, match="mu2 must be a finite number > 0"):
        admm_tv(image, psf, 3, mu2=0.0)
    with pytest.raises(DiffcamError, match="richardson_lucy"):
        admm_tv(image, psf, 3, boundary="same")
    with pytest.raises(DiffcamError, match="all zeros"):
        admm_tv(np.zeros_like(image), psf, 3)
    for alpha in (0.0, 2.0):
        with pytest.raises(DiffcamError, match="relaxation must be in"):
            admm_tv(image, psf, 3, relaxation=alpha)


def _volume_problem(seed=30, nz=4):
    rng = np.random.default_rng(seed)
    stack = rng.random((nz, 8, 8)) ** 6
    model = convolution_model(jnp.asarray(stack), (16, 16), "crop", volume=True)
    scene = np.zeros((nz,) + model.object_shape)
    scene[1, 10:14, 8:16] = 1.0
    scene[3, 6:9, 12:14] = 2.0
    return np.asarray(model(scene)), stack, model


def test_admm_reports_the_returned_volumes_residual(x64):
    """final_residual and split_gap describe the volume returned: the residual equals
    ||A x - b|| / ||b|| recomputed with the forward model, and the gap ||v - w|| / ||w||
    is what is left of the split (large when the penalties are far too small)."""
    from diffcam.reconstruct.loop import relative_residual

    image, stack, model = _volume_problem()
    for mu in (1e-6, 1e-2):
        out = admm_tv_3d(image, stack, 40, mu1=mu, mu2=mu, mu3=mu, tau=1e-4)
        recomputed = float(relative_residual(model(out.image), image))
        assert float(out.final_residual) == pytest.approx(recomputed, rel=1e-6)
        assert float(out.split_gap) >= 0
    assert float(out.final_residual) < 0.1


def test_admm_v_update_solves_its_linear_system(x64):
    """The v-update (DCT along depth as a matrix, axial TV scaled by tau_axial/tau)
    solves (mu1 HᵀH + mu2 ΨᵀΨ + mu3) v = Hᵀd + r: applying the operator, built from
    convolutions and differences directly, to the solution gives the right-hand side."""
    from diffcam.core.backend import irfft2, rfft2
    from diffcam.reconstruct.admm import _basis, _tv, _tv_adjoint, _v_update

    rng = np.random.default_rng(31)
    nz, grid = 5, (12, 10)
    otf = rfft2(jnp.asarray(rng.random((nz,) + grid)))
    d, r = jnp.asarray(rng.standard_normal(grid)), jnp.asarray(rng.standard_normal((nz,) + grid))
    mu = jnp.asarray([0.3, 0.7, 0.2])
    for a in (None, 0.4):
        basis = _basis(otf, grid, a, jnp.float64)
        v, hv = _v_update(basis, rfft2(d), r, mu)
        h = lambda x: irfft2(jnp.sum(otf * rfft2(x), axis=0), s=grid)       # noqa: E731
        ht = lambda y: irfft2(jnp.conj(otf) * rfft2(y)[None], s=grid)        # noqa: E731
        lhs = mu[0] * ht(h(v)) + mu[1] * _tv_adjoint(_tv(v, a), a) + mu[2] * v
        assert _rel(lhs, ht(d) + r) < 1e-10
        assert _rel(hv, h(v)) < 1e-10


def test_admm_balancing_closes_the_split(x64):
    """Penalties 1e-6 leave the split open after 60 iterations; residual balancing
    (Boyd et al. §3.4.1) closes it and the returned volume fits the data better."""
    image, stack, _ = _volume_problem()
    fixed = admm_tv_3d(image, stack, 60, mu1=1e-6, mu2=1e-6, mu3=1e-6, tau=1e-4)
    balanced = admm_tv_3d(image, stack, 60, mu1=1e-6, mu2=1e-6, mu3=1e-6, tau=1e-4,
                          balance=True)
    assert float(balanced.split_gap) < 0.1 * float(fixed.split_gap)
    assert float(balanced.final_residual) < 0.5 * float(fixed.final_residual)


def test_tiny_negative_psf_values_are_clipped_with_a_warning():
    """Rounding below zero (-3.8e-7 of a unit peak, as a background subtraction leaves)
    is clipped with a BackgroundWarning and gives the clipped PSF's result; a real
    negative lobe is refused."""
    from diffcam.io import BackgroundWarning

    image, stack, _ = _volume_problem()
    stack = (stack / stack.max()).astype(np.float32)
    dented = stack.copy()
    dented[2, 0, 0] = -3.8e-7
    with pytest.warns(BackgroundWarning, match="clipped"):
        out = admm_tv_3d(image, dented, 5, progress=False)
    clipped = admm_tv_3d(image, np.maximum(dented, 0), 5, progress=False)
    assert np.array_equal(np.asarray(out.image), np.asarray(clipped.image))
    dented[2, 0, 0] = -0.01
    with pytest.raises(DiffcamError, match="negative"):
        admm_tv_3d(image, dented, 5)


def _plane_background(shape, level, tilt_y, tilt_x):
    """``level + tilt_y·y + tilt_x·x`` over the sensor, ``y, x`` in [-1, 1]."""
    y, x = np.meshgrid(np.linspace(-1, 1, shape[0]), np.linspace(-1, 1, shape[1]),
                       indexing="ij")
    return level + tilt_y * y + tilt_x * x


def test_admm_background_basis_is_the_least_squares_polynomial(x64):
    """The background's fit equals numpy's least-squares fit of the monomials
    ``y^i x^j``, ``i + j <= degree`` (the same space as the Legendre products)."""
    from diffcam.reconstruct.sensor_terms import smooth_background

    rng = np.random.default_rng(32)
    shape, degree = (11, 14), 3
    r = rng.standard_normal(shape)
    y, x = np.meshgrid(np.linspace(-1, 1, shape[0]), np.linspace(-1, 1, shape[1]),
                       indexing="ij")
    a = np.stack([(y ** i * x ** j).ravel() for i in range(degree + 1)
                  for j in range(degree + 1 - i)], axis=1)
    expected = (a @ np.linalg.lstsq(a, r.ravel(), rcond=None)[0]).reshape(shape)
    fitted = np.asarray(smooth_background(shape, degree, jnp.float64).fit(jnp.asarray(r)))
    assert _rel(fitted, expected) < 1e-10


def test_admm_background_absorbs_a_smooth_background_exactly(x64):
    """The joint problem is invariant to adding a background of the term's degree to
    the image: the volume is unchanged and the fitted background moves by exactly that
    background; without the term the background's light goes into the volume."""
    image, stack, _ = _volume_problem()
    settings = dict(mu1=1e-2, mu2=1e-2, mu3=1e-2, tau=1e-4, sparsity=1e-2, balance=True)
    bg = _plane_background(image.shape, 0.3 * image.mean(), 0.1 * image.mean(),
                           -0.2 * image.mean())
    clean = admm_tv_3d(image, stack, 100, **settings, background=1, progress=False)
    joint = admm_tv_3d(image + bg, stack, 100, **settings, background=1, progress=False)
    plain = admm_tv_3d(image + bg, stack, 100, **settings, progress=False)
    assert _rel(joint.image, clean.image) < 1e-8
    assert _rel(joint.background - clean.background, bg) < 1e-8
    assert _rel(plain.image, clean.image) > 0.2 and plain.background is None


@pytest.mark.parametrize("relaxation", [1.0, 1.7])
def test_admm_background_reaches_bounded_least_squares(x64, relaxation):
    """tau=0, circular: ADMM with a background of degree 1 minimises
    ½||A x + B c - b||² over x >= 0 and free c (scipy.optimize.lsq_linear with bounds
    on the stacked matrix [A, B]), plain or over-relaxed."""
    rng = np.random.default_rng(33)
    psf = rng.random((4, 4))
    scene = np.maximum(rng.standard_normal((8, 8)), 0)
    model = convolution_model(jnp.asarray(psf), scene.shape, "circular")
    image = (np.asarray(model(scene)) + 0.1 * rng.standard_normal(scene.shape)
             + _plane_background(scene.shape, -0.5, 0.3, 0.2))
    y, x = np.meshgrid(np.linspace(-1, 1, 8), np.linspace(-1, 1, 8), indexing="ij")
    a = np.concatenate([_dense(model, scene.shape),
                        np.stack([np.ones(64), y.ravel(), x.ravel()], axis=1)], axis=1)
    lower = np.r_[np.zeros(64), -np.inf * np.ones(3)]
    ref = scipy.optimize.lsq_linear(a, image.ravel(), bounds=(lower, np.inf), tol=1e-12)
    f_ref = 0.5 * np.sum(ref.fun ** 2)
    out = admm_tv(image, psf, 3000, mu1=0.05, mu2=0.05, mu3=0.05, tau=0.0,
                  boundary="circular", background=1, relaxation=relaxation,
                  progress=False)
    predicted = np.asarray(model(out.image)) + np.asarray(out.background)
    f = 0.5 * np.sum((predicted - image) ** 2)
    assert float(out.image.min()) >= 0
    assert f <= f_ref * (1 + 1e-3) + 1e-12


@pytest.mark.parametrize("degree", [-1, 9, 1.5])
def test_admm_background_degree_errors(degree):
    image, psf = _problem()
    with pytest.raises(DiffcamError, match="background is a polynomial degree"):
        admm_tv(image, psf, 3, background=degree)
