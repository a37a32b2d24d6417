"""Non-negative least squares by FISTA (diffcam.reconstruct.fista), checked against
scipy.optimize.nnls on the explicit matrix of a small convolution model."""

import jax
import numpy as np
import pytest
from scipy.optimize import nnls

from diffcam.core.errors import DiffcamError
from diffcam.reconstruct import convolution_model, fista, nonnegative_least_squares


def _matrix(model, shape):
    """The model's matrix, column by column (unit objects)."""
    n = int(np.prod(shape))
    basis = np.eye(n, dtype=np.float64).reshape((n,) + shape)
    return np.asarray(jax.vmap(model)(basis)).reshape(n, -1).T


@pytest.mark.parametrize("boundary", ["same", "circular"])
def test_fista_matches_scipy_nnls(boundary, x64):
    """A 6×7 sensor, 3×4 PSF (non-square, even and odd): FISTA's estimate is scipy's
    non-negative least-squares solution (Lawson–Hanson) of the same matrix problem."""
    rng = np.random.default_rng(0)
    psf = rng.uniform(0, 1, (3, 4))
    model = convolution_model(psf, (6, 7), boundary)
    a = _matrix(model, model.object_shape)
    b = rng.normal(1.0, 0.5, (6, 7))        # inconsistent data: some constraints active
    x_ref, _ = nnls(a, b.ravel(), maxiter=10_000)
    rec = fista(b, psf, 1500, boundary=boundary, progress=False)
    x = np.asarray(rec.image).ravel()
    assert (x >= 0).all()
    objective = lambda v: 0.5 * np.sum((a @ v - b.ravel()) ** 2)  # noqa: E731
    assert objective(x) == pytest.approx(objective(x_ref), rel=1e-6)
    assert objective(x) >= objective(x_ref) * (1 - 1e-9)   # nnls is the minimum
    # the objective falls (FISTA is not monotone step by step, but overall it is)
    assert rec.objective[-1] < rec.objective[10] < rec.objective[0]


def test_fista_fits_consistent_crop_data():
    """Data made by the crop model from a non-negative scene are fitted to a small
    fraction of their energy (the crop grid's border pixels, seen by few sensor pixels,
    need not be recovered)."""
    rng = np.random.default_rng(2)
    psf = rng.uniform(0, 1, (5, 6))
    model = convolution_model(psf, (16, 18), "crop")
    b = np.asarray(model(rng.uniform(0, 1, model.object_shape)))
    rec = fista(b, psf, 500, progress=False)
    assert float(rec.residual[-1]) < 0.01 * float(rec.residual[0])


def test_fista_broadcasts_over_colour_channels():
    """Three channels with one PSF each give the three single-channel results."""
    rng = np.random.default_rng(1)
    psfs, images = rng.uniform(0, 1, (3, 5, 5)), rng.uniform(0, 1, (3, 12, 10))
    joint = fista(images, psfs, 50, progress=False).image
    for c in range(3):
        alone = fista(images[c], psfs[c], 50, progress=False).image
        np.testing.assert_allclose(joint[c], alone, rtol=1e-4, atol=1e-6)


def test_nonnegative_least_squares_on_a_diagonal_problem():
    """``min ½||d x - b||², x >= 0`` with diagonal ``d``: the answer is max(b/d, 0)."""
    d = np.array([1.0, 2.0, 0.5, 3.0], np.float32)
    b = np.array([1.0, -2.0, 0.25, 6.0], np.float32)
    x, res, obj, its, done = nonnegative_least_squares(
        lambda v: d * v, lambda r: d * r, b, np.zeros(4, np.float32), float(d.max() ** 2), 3000)
    np.testing.assert_allclose(x, np.maximum(b / d, 0), atol=1e-5)
    assert int(its) == 3000 and obj[-1] == pytest.approx(0.5 * 2.0 ** 2, rel=1e-5)


def test_fista_rejects_bad_input():
    with pytest.raises(DiffcamError, match="boundary"):
        fista(np.ones((8, 8)), np.ones((3, 3)), boundary="wrap")
    with pytest.raises(DiffcamError):
        fista(np.ones((8, 8)), np.ones((3, 3)), 0)
    with pytest.raises(DiffcamError):
        fista(np.full((8, 8), np.nan), np.ones((3, 3)))
