"""The sensor response in the ADMM data term (diffcam.reconstruct.sensor_terms,
diffcam.reconstruct.admm): ``b = S ⊙ C H v``."""

import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.core.grid import pad_to
from diffcam.reconstruct import admm_tv_3d, convolution_model
from diffcam.reconstruct.loop import relative_residual
from diffcam.reconstruct.sensor_terms import sensor_split, smooth_background

SENSOR, GRID = (4, 5), (6, 8)


def _crop_matrix():
    """``C``: the sensor pixels of the centred ``SENSOR`` window of ``GRID``, as a
    selection matrix (rows: sensor pixels, columns: grid pixels)."""
    index = np.asarray(pad_to(np.arange(1, 21, dtype=np.float32).reshape(SENSOR), GRID))
    rows = np.argsort(index.ravel())[-20:]
    return np.eye(index.size)[rows]


def test_sensor_split_solves_the_small_linear_system(x64):
    """The x update against a direct solve of ``(CᵀS²C + μ1) x = CᵀS r + μ1 Hv + ξ``
    with the crop ``C`` and ``diag(S)`` as dense matrices (S with a zero pixel)."""
    rng = np.random.default_rng(0)
    s, r = rng.random(SENSOR), rng.normal(size=SENSOR)
    s[1, 2] = 0.0
    hv, xi, mu1 = rng.normal(size=GRID), rng.normal(size=GRID), 0.7
    c, big_s = _crop_matrix(), np.diag(s.ravel())
    lhs = c.T @ big_s @ big_s @ c + mu1 * np.eye(c.shape[1])
    rhs = c.T @ big_s @ r.ravel() + mu1 * hv.ravel() + xi.ravel()
    direct = np.linalg.solve(lhs, rhs).reshape(GRID)
    x = sensor_split(pad_to(s, GRID), pad_to(r, GRID), hv, xi, mu1)
    np.testing.assert_allclose(np.asarray(x), direct, rtol=1e-12, atol=1e-12)


def test_joint_background_is_the_joint_least_squares_solution(x64):
    """``fit_joint``: the background of ``min_{x, c} ½||S x + B c - b||² + μ1/2||x - z||²``
    against the dense least-squares solution over ``(x, c)`` together."""
    rng = np.random.default_rng(1)
    s, b, z, mu1 = rng.random(SENSOR) + 0.1, rng.normal(size=SENSOR), rng.normal(size=SENSOR), 0.3
    smooth = smooth_background(SENSOR, 1, np.float64)
    basis = np.asarray(smooth.basis).reshape(len(smooth.basis), -1).T       # (20, 3)
    n = s.size
    system = np.block([[np.diag(s.ravel()), basis],
                       [np.sqrt(mu1) * np.eye(n), np.zeros_like(basis)]])
    target = np.concatenate([b.ravel(), np.sqrt(mu1) * z.ravel()])
    c = np.linalg.lstsq(system, target, rcond=None)[0][n:]
    fitted = smooth.fit_joint(b - s * z, s, mu1)
    np.testing.assert_allclose(np.asarray(fitted), (basis @ c).reshape(SENSOR), atol=1e-10)


ITERATIONS = 150


@pytest.fixture(scope="module")
def problem():
    """A two-plane volume, its PSFs, a sensor response falling off along y, and the
    solves the tests compare (two compilations: without and with a response)."""
    rng = np.random.default_rng(2)
    psfs = rng.random((2, 6, 7)).astype(np.float32)
    volume = np.zeros((2, 17, 19), np.float32)
    volume[0, 5:9, 6:12], volume[1, 9:13, 4:9] = 1.0, 0.5
    model = convolution_model(psfs, (12, 13), "crop", volume=True)
    s = np.exp(-0.5 * ((np.arange(12) - 5.0) / 3.0) ** 2)[:, None].astype(np.float32)
    clean, masked = np.asarray(model(volume)), s * np.asarray(model(volume))

    def solve(image, response=None):
        return admm_tv_3d(image, psfs, ITERATIONS, tau=1e-6, balance=True, progress=False,
                          sensor_response=response)
    solves = {"plain": solve(clean), "ones": solve(clean, np.ones((12, 1))),
              "masked": solve(masked, s), "masked, no response": solve(masked)}
    return psfs, model, volume, s, masked, solves


@pytest.mark.slow        # the fixture compiles the 3-D solver twice
def test_unit_response_is_todays_solve_exactly(problem):
    solves = problem[-1]
    for field in ("image", "residual", "objective"):
        np.testing.assert_array_equal(np.asarray(getattr(solves["plain"], field)),
                                      np.asarray(getattr(solves["ones"], field)))


@pytest.mark.slow
def test_masked_solve_explains_masked_data_and_reports_its_residual(problem):
    """Data made by ``S ⊙ A v``: with ``S`` the solve fits it (residual < 2 %, and the
    residual it reports is that of ``S ⊙ A x`` recomputed); without ``S`` it cannot
    (residual > 5 times larger)."""
    _, model, _, s, image, solves = problem
    masked = solves["masked"]
    recomputed = relative_residual(s * model(masked.image), image)
    assert float(masked.final_residual) < 0.02
    np.testing.assert_allclose(float(masked.final_residual), float(recomputed), rtol=1e-3)
    assert float(solves["masked, no response"].final_residual) > 5 * float(
        masked.final_residual)


@pytest.mark.parametrize("response", [-np.ones((12, 1)), np.full((12, 13), np.nan),
                                      np.zeros((12, 13)), np.ones((13, 1)),
                                      np.ones((2, 12, 13))])
def test_bad_sensor_response_is_refused(response):
    image, psfs = np.ones((12, 13), np.float32), np.ones((2, 6, 7), np.float32)
    with pytest.raises(DiffcamError, match="sensor_response"):
        admm_tv_3d(image, psfs, 1, sensor_response=response, progress=False)
