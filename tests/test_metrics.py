"""Metrics against scikit-image and numpy (diffcam/metrics.py)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from diffcam.core.errors import ShapeError, DiffcamError
from diffcam.evaluate.metrics import align_to, mse, pearson, psnr, ssim

RNG = np.random.default_rng(0)
A = RNG.random((48, 70))
B = 0.7 * A + 0.3 * RNG.random((48, 70))


@pytest.mark.parametrize("scale", [1e-25, 1e-12, 1e10, 1e16, 1e18])
def test_metrics_in_float32_at_any_scale(scale):
    """Pearson (against numpy.corrcoef in float64), SSIM and PSNR (against scikit-image
    in float64) and the least-squares alignment hold in float32 for images of any
    scale: a PSF in W/m² is ~1e16, whose products' sums overflowed (Pearson read 0,
    SSIM NaN), and tiny values underflowed (NaN)."""
    rng = np.random.default_rng(0)
    a = rng.random((64, 64))
    b = a + 0.5 * rng.random((64, 64))
    truth = np.corrcoef(a.ravel(), b.ravel())[0, 1]
    sa, sb = (np.asarray(x * scale, np.float32) for x in (a, b))
    assert abs(float(pearson(sa, sb)) - truth) < 1e-5
    assert abs(float(pearson(sa, b.astype(np.float32))) - truth) < 1e-5
    data_range = float(b.max() - b.min())
    assert abs(float(ssim(sa, sb)) - structural_similarity(a, b, data_range=data_range)) < 1e-4
    assert abs(float(psnr(sa, sb)) - peak_signal_noise_ratio(b, a, data_range=data_range)) < 1e-3
    for mode, offset in (("scale", 0.0), ("affine", 1.0)):
        fitted = np.asarray(align_to(3 * sa + offset * scale, sb, mode), np.float64)
        unit = np.asarray(align_to(np.float32(3) * a.astype(np.float32) + offset,
                                   b.astype(np.float32), mode), np.float64)
        np.testing.assert_allclose(fitted / scale, unit, rtol=1e-5, atol=1e-6)


def test_pearson_equals_numpy_corrcoef(x64):
    """Paper Eq. 14 equals numpy.corrcoef to 1e-12; batched over a leading axis; masked
    version equals corrcoef of the masked samples."""
    assert abs(float(pearson(A, B)) - np.corrcoef(A.ravel(), B.ravel())[0, 1]) < 1e-12
    batch = pearson(np.stack([A, B]), np.stack([B, A]))
    assert batch.shape == (2,) and np.allclose(batch[0], batch[1])
    mask = RNG.random(A.shape) > 0.5
    ref = np.corrcoef(A[mask], B[mask])[0, 1]
    assert abs(float(pearson(A, B, mask=mask)) - ref) < 1e-12


@pytest.mark.parametrize("kw", [{}, {"gaussian_weights": True, "use_sample_covariance": False},
                                {"win_size": 11}])
def test_ssim_equals_scikit_image(x64, kw):
    """SSIM equals skimage.metrics.structural_similarity for the same data range, to 1e-6."""
    ours = float(ssim(B, A, data_range=1.0, **kw))
    ref = structural_similarity(B, A, data_range=1.0, **kw)
    assert abs(ours - ref) < 1e-6


def test_mse_psnr_and_alignment(x64):
    """MSE and PSNR equal scikit-image's; after affine alignment an affinely distorted
    copy scores perfectly (MSE 0, Pearson unchanged)."""
    assert np.isclose(float(mse(B, A)), np.mean((B - A) ** 2))
    assert np.isclose(float(psnr(B, A, data_range=1.0)),
                      peak_signal_noise_ratio(A, B, data_range=1.0))
    distorted = 3.0 * A + 0.2
    assert float(mse(distorted, A, align="affine")) < 1e-20
    assert float(mse(2.0 * A, A, align="scale")) < 1e-20
    assert np.isclose(float(pearson(distorted, A)), 1.0)
    assert np.allclose(align_to(distorted, A), A)


@pytest.mark.slow  # 6 s of float64 compilation; the metrics' values by default
@pytest.mark.usefixtures("debug_nans")
def test_metric_gradients(x64):
    """Pearson and SSIM are differentiable (check_grads, reverse and forward mode)."""
    a, b = jnp.asarray(A[:16, :16]), jnp.asarray(B[:16, :16])
    check_grads(jax.jit(lambda x: pearson(x, b)), (a,), order=1, modes=("fwd", "rev"))
    check_grads(jax.jit(lambda x: ssim(x, b, data_range=1.0)), (a,), order=1, modes=("fwd", "rev"))
    assert np.isfinite(float(jax.jit(lambda x: ssim(x, b, data_range=1.0))(a)))


def test_metric_bad_input():
    """Mismatched shapes, NaN and too-small images raise with a clear message."""
    with pytest.raises(ShapeError, match="spatial shape"):
        pearson(A, B[:10])
    with pytest.raises(DiffcamError, match="NaN"):
        mse(np.full_like(A, np.nan), A)
    with pytest.raises(ShapeError, match="window"):
        ssim(A[:5, :5], B[:5, :5], data_range=1.0)
    with pytest.raises(DiffcamError, match="align"):
        mse(A, B, align="rotate")


def test_ssim_options_object_equals_keywords():
    """SsimOptions given as an object or as keywords: the same score; its fields are
    validated (an even window, a zero sigma, an unknown field)."""
    from diffcam.evaluate.metrics import SsimOptions

    options = SsimOptions(win_size=11, K2=0.05)
    assert float(ssim(B, A, options, data_range=1.0)) == \
        float(ssim(B, A, data_range=1.0, win_size=11, K2=0.05))
    for bad in ({"win_size": 4}, {"win_size": 7.0}, {"sigma": 0.0}, {"K1": float("nan")},
                {"window": 7}):
        with pytest.raises(DiffcamError):
            ssim(B, A, data_range=1.0, **bad)
