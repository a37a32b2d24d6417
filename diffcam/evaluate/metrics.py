"""Image and PSF quality metrics: Pearson correlation (paper Eq. 14), SSIM, MSE, PSNR.

All are pure JAX, jit-able and differentiable; they reduce over the last two (space)
axes and broadcast over leading batch axes, so a stack of PSFs is scored in one call.
``align="scale"`` or ``"affine"`` first fits ``a·estimate (+ b)`` to the reference by
least squares: use it when the two images carry arbitrary exposure or normalisation.

The composite scores (`ssim`, `registration_shift`, `psf_fidelity`,
`phase_scores`) check their inputs, then run as one compiled program: called
eagerly, op by op, they cost 10–30 ms a call and up to 2 s for the first, against
1.5–4 ms and one compilation (256², and 96² stacks for ``psf_fidelity``).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.backend import fft2, ifft2

from diffcam.core.errors import (DiffcamError, ShapeError, check_finite, is_concrete,
                                 real_array)
from diffcam.core.options import Options

__all__ = ["pearson", "ssim", "SsimOptions", "mse", "psnr", "align_to", "wrap_phase", "twin_phase",
           "phase_offset", "phase_pearson", "phase_mse", "phase_scores"]

_SPACE = (-2, -1)


def _check_pair(a, b, name_a="estimate", name_b="reference"):
    """``a`` and ``b`` as real float arrays (`real_array`:
    integers converted, complex refused), checked: image axes of one shape, finite."""
    a, b = real_array(name_a, a), real_array(name_b, b)
    sa, sb = np.shape(a), np.shape(b)
    if len(sa) < 2 or len(sb) < 2:
        raise ShapeError(f"metrics take images (..., ny, nx); got shapes {sa} and {sb}.")
    if sa[-2:] != sb[-2:]:
        raise ShapeError(f"{name_a} {sa} and {name_b} {sb} differ in their spatial shape; "
                         f"crop or resample one onto the other's grid first.")
    if 0 in sa[-2:]:
        raise ShapeError(f"{name_a} and {name_b} have no pixels (spatial shape {sa[-2:]}); "
                         f"a metric needs at least one.")
    check_finite(name_a, a)
    check_finite(name_b, b)
    return a, b


def _mean(x, mask):
    if mask is None:
        return jnp.mean(x, axis=_SPACE, keepdims=True)
    return jnp.sum(x * mask, axis=_SPACE, keepdims=True) / jnp.sum(mask)


def _peak(x):
    """The largest magnitude of ``x`` on the space axes (1 where it is 0), a constant to
    derivatives: the scale by which Pearson and the least-squares fits below divide
    each image before summing products.

    Those are ratios of sums of products, in which the scale cancels. In float32 the
    sums overflow for values above ~10⁹ (a PSF in W/m², ``normalise=False``, is ~10¹⁶)
    and underflow below ~10⁻¹⁰, and Pearson read 0 or NaN. Divided by its peak, an
    image's products sum to at most its sample count. The results do not depend on the
    peak, so it holds no derivative."""
    peak = jnp.max(jnp.abs(x), axis=_SPACE, keepdims=True)
    return jax.lax.stop_gradient(jnp.where(peak > 0, peak, 1.0))


def align_to(estimate: Float[Array, "... ny nx"], reference: Float[Array, "... ny nx"],
             mode: str = "affine", mask=None) -> Float[Array, "... ny nx"]:
    """``a·estimate + b`` (``mode="affine"``) or ``a·estimate`` (``"scale"``) fitted to
    ``reference`` by least squares over the image (or ``mask``), per batch element.

    The fit is undefined when the estimate is constant (``"scale"``: all zero) over the
    image: every ``a`` fits equally well. Called eagerly that is a DiffcamError; under a
    caller's ``jit`` such an element gets a = 0 (the least-norm solution)."""
    estimate, reference = _check_pair(estimate, reference)
    return _aligned(estimate, reference, mode, mask)


def _fit(estimate, reference, mode, mask):
    """`align_to` after its checks (the traced path: a = 0 where undefined)."""
    w = 1.0 if mask is None else mask
    unit = _peak(reference)       # the means below are sums: of unit-peak values
    reference = reference / unit
    rm = 0.0 if mode == "scale" else _mean(reference, mask)
    dr = reference - rm
    scale = _peak(dr)
    r = dr / scale
    de, flat = _flat(estimate, mode, mask)
    e = jnp.where(flat, 0, de / _peak(de))
    ee = jnp.sum(w * e * e, axis=_SPACE, keepdims=True)
    a = jnp.sum(w * e * r, axis=_SPACE, keepdims=True) / jnp.where(ee > 0, ee, 1)
    return unit * (scale * a * e + rm)


def _flat(estimate, mode, mask):
    """The estimate's part that a fits (minus its mean for ``"affine"``), and where it
    is nothing but rounding (a few ulps of the estimate's mean, which `_peak`
    would blow up to ±1): there every a fits equally well."""
    estimate = estimate / _peak(estimate)     # a absorbs the scale; the mean is a sum
    de = estimate if mode == "scale" else estimate - _mean(estimate, mask)
    top = lambda x: jnp.max(jnp.abs(x), axis=_SPACE, keepdims=True)  # noqa: E731
    return de, top(de) <= 64 * jnp.finfo(de.dtype).eps * top(estimate)


@partial(jax.jit, static_argnames="mode")
def _flat_mask(estimate, mode, mask):
    """Where `_flat` finds nothing to fit, as one program (eagerly, op by op, the
    check takes seconds of dispatch and compilation on a loaded machine)."""
    return _flat(estimate, mode, mask)[1]


def _check_alignable(estimate, mode, mask) -> None:
    """A DiffcamError if the fit of `align_to` is undefined for any element of a
    concrete ``estimate``."""
    if not is_concrete(estimate, mask):
        return
    flat = np.asarray(_flat_mask(jnp.asarray(estimate), mode, mask))
    if flat.any():
        what = "all zero" if mode == "scale" else "constant"
        raise DiffcamError(
            f"align={mode!r} is undefined: the estimate is {what} over "
            f"{'the image' if mask is None else 'the mask'} ({int(flat.sum())} image(s)), "
            f"so every gain a fits it equally well; compare without align, or check "
            f"that the estimate holds any signal.")


def _aligned(estimate, reference, align, mask=None):
    """``estimate`` aligned to ``reference`` (checked arrays) by ``align`` (None: as it
    is), the fit checked first when the estimate is concrete."""
    estimate, reference = jnp.asarray(estimate), jnp.asarray(reference)
    if align is None:
        return estimate
    if align not in ("affine", "scale"):
        raise DiffcamError(f"align must be None, 'scale' or 'affine', got {align!r}.")
    _check_alignable(estimate, align, mask)
    return _fit(estimate, reference, align, mask)


def pearson(a: Float[Array, "... ny nx"], b: Float[Array, "... ny nx"], *, mask=None
            ) -> Float[Array, "..."]:
    """Pearson correlation coefficient over the last two axes (paper Eq. 14):

        P(A, B) = Σ(A − Ā)(B − B̄) / √(Σ(A − Ā)² · Σ(B − B̄)²),

    optionally over the samples where ``mask`` is nonzero (``mask`` broadcasts).
    Equals ``numpy.corrcoef(a.ravel(), b.ravel())[0, 1]`` for 2-D inputs.

    It is undefined (0/0) when ``a`` or ``b`` is constant over the mask, or the mask
    selects nothing: called eagerly, that is a DiffcamError saying which; under a
    caller's ``jit`` the result is NaN or meaningless.
    """
    a, b = _check_pair(a, b, "a", "b")
    a, b = jnp.asarray(a), jnp.asarray(b)
    if mask is not None:
        mask = jnp.asarray(real_array("mask", mask), dtype=a.dtype)
    if is_concrete(a, b, mask):
        _check_variance(a, b, mask)
    w = 1.0 if mask is None else mask
    a, b = a / _peak(a), b / _peak(b)     # the means are sums: of unit-peak values
    da, db = a - _mean(a, mask), b - _mean(b, mask)
    da, db = da / _peak(da), db / _peak(db)
    num = jnp.sum(w * da * db, axis=_SPACE)
    den = jnp.sqrt(jnp.sum(w * da * da, axis=_SPACE) * jnp.sum(w * db * db, axis=_SPACE))
    return num / den


def _check_variance(a, b, mask):
    """Raise a DiffcamError if the mask selects nothing or ``a`` or ``b`` is constant
    over it (in the dtype it is computed in: its mean's rounding would otherwise
    normalise to a meaningless ±1 pattern, or 0/0)."""
    shape = np.broadcast_shapes(np.shape(a), np.shape(b), np.shape(mask) if mask is not
                                None else ())
    sel = True if mask is None else np.broadcast_to(np.asarray(mask) != 0, shape)
    if mask is not None and not np.any(sel):
        raise DiffcamError("pearson: the mask selects no sample; give a mask with nonzero "
                           "entries where the images should be compared.")
    for name, x in (("a", a), ("b", b)):
        x = np.broadcast_to(np.asarray(x), shape)
        hi = np.max(x, axis=_SPACE, where=sel, initial=-np.inf)
        lo = np.min(x, axis=_SPACE, where=sel, initial=np.inf)
        if np.any(hi == lo):
            raise DiffcamError(
                f"pearson is undefined: {name} is constant over "
                f"{'the image' if mask is None else 'the mask'} ({int(np.sum(hi == lo))} "
                f"image(s)), so its variance is 0; compare constant images with mse, or "
                f"check that the image holds any signal.")


def mse(estimate, reference, *, align: str | None = None) -> Float[Array, "..."]:
    """Mean squared error over the last two axes (after optional alignment)."""
    estimate, reference = _check_pair(estimate, reference)
    e = _aligned(estimate, reference, align)
    return jnp.mean((e - jnp.asarray(reference)) ** 2, axis=_SPACE)


def _data_range(reference, data_range):
    """``data_range``, checked finite and > 0, or the reference's max − min (which must
    be > 0: SSIM and PSNR are measured in units of it)."""
    if data_range is not None:
        if is_concrete(data_range):
            dr = np.asarray(real_array("data_range", data_range), np.float64)
            if dr.size == 0 or not (np.all(np.isfinite(dr)) and np.all(dr > 0)):
                raise DiffcamError(
                    f"data_range must be a finite number > 0 (the span of the images' "
                    f"scale, e.g. 1 for [0, 1] or 255 for 8 bits), got {data_range!r}; "
                    f"SSIM and PSNR are undefined in units of 0, NaN or a negative span.")
        return data_range
    if not is_concrete(reference):
        raise DiffcamError("data_range is needed under jit/grad (the reference is traced); "
                           "pass data_range=<max − min of the reference's scale>.")
    r = np.asarray(reference)
    span = float(r.max() - r.min())
    if not span > 0:
        raise DiffcamError(
            f"the reference is constant (every value {float(r.max()):.4g}), so its data "
            f"range max − min is 0 and SSIM/PSNR in units of it are undefined; pass "
            f"data_range= (e.g. 1 for images in [0, 1]).")
    return span


def psnr(estimate, reference, *, data_range=None, align: str | None = None
         ) -> Float[Array, "..."]:
    """Peak signal-to-noise ratio, dB: 10·log10(data_range² / MSE).

    ``data_range`` defaults to the reference's max − min (as
    ``skimage.metrics.peak_signal_noise_ratio`` does for float images only when told).
    """
    estimate, reference = _check_pair(estimate, reference)
    dr = _data_range(reference, data_range)    # in units of it: see ssim
    return -10 * jnp.log10(mse(jnp.asarray(estimate) / dr, jnp.asarray(reference) / dr,
                               align=align))


def _separable_filter(x, weights):
    """Correlate the last two axes with a 1-D kernel, scipy ``mode='reflect'`` edges."""
    r = (len(weights) - 1) // 2
    widths = [(0, 0)] * (x.ndim - 2)
    xp = jnp.pad(x, widths + [(r, r), (0, 0)], mode="symmetric")
    ny = x.shape[-2]
    x = sum(w * xp[..., i:i + ny, :] for i, w in enumerate(weights))
    xp = jnp.pad(x, widths + [(0, 0), (r, r)], mode="symmetric")
    nx = x.shape[-1]
    return sum(w * xp[..., :, i:i + nx] for i, w in enumerate(weights))


class SsimOptions(Options):
    """Settings of `ssim`, scikit-image's ``structural_similarity`` defaults.

    Attributes:
        win_size: side of the uniform window, samples (odd, ≥ 3).
        gaussian_weights: a Gaussian window of width ``sigma`` instead (truncated at
            3.5 σ, as scikit-image does; ``win_size`` is then unused).
        sigma: the Gaussian window's standard deviation, samples.
        K1, K2: the constants of the luminance and contrast terms
            (``c = (K·data_range)²``).
        use_sample_covariance: normalise the window's covariances by ``n − 1``
            (scikit-image's default) instead of ``n`` (Wang et al.'s definition).
    """

    win_size: int = 7
    gaussian_weights: bool = False
    sigma: float = 1.5
    K1: float = 0.01
    K2: float = 0.03
    use_sample_covariance: bool = True

    def __check_init__(self):
        win = self.win_size
        if isinstance(win, bool) or not isinstance(win, (int, np.integer)) or win % 2 != 1 \
                or win < 3:
            raise DiffcamError(f"win_size must be an odd integer ≥ 3, got {win!r}.")
        for name in ("sigma", "K1", "K2"):
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.number)) or isinstance(value, bool) \
                    or not 0 < float(value) < np.inf:
                raise DiffcamError(f"{name} must be a finite number > 0, got {value!r}.")

    def window(self) -> np.ndarray:
        """The 1-D weights of the separable window, summing to 1."""
        if not self.gaussian_weights:
            return np.full(int(self.win_size), 1.0 / int(self.win_size))
        r = int(3.5 * float(self.sigma) + 0.5)  # the truncation scikit-image uses
        t = np.arange(-r, r + 1, dtype=np.float64)
        w = np.exp(-0.5 * (t / float(self.sigma)) ** 2)
        return w / w.sum()


def ssim(estimate: Float[Array, "... ny nx"], reference: Float[Array, "... ny nx"],
         options: SsimOptions | None = None, *, data_range=None, align: str | None = None,
         **overrides) -> Float[Array, "..."]:
    """Mean structural similarity (Wang et al. 2004) over the last two axes.

    Matches ``skimage.metrics.structural_similarity`` for the same ``data_range`` and
    options (uniform 7×7 window, sample covariance, reflected edges, the border of
    half a window excluded from the mean). ``data_range`` defaults to the reference's
    max − min. ``options``: `SsimOptions`, whose fields may also be given as
    keywords (``win_size=11``); ``gaussian_weights=True, use_sample_covariance=False``
    gives Wang et al.'s original definition.
    """
    options = SsimOptions.of(options, **overrides)
    estimate, reference = _check_pair(estimate, reference)
    weights = options.window()
    ny, nx = np.shape(reference)[-2:]
    win = len(weights)
    if ny < win or nx < win:
        raise ShapeError(f"images of {ny}×{nx} are smaller than the {win}×{win} SSIM window.")
    dr = _data_range(reference, data_range)
    if align is not None:
        _check_alignable(jnp.asarray(estimate), align, None)
    return _ssim(jnp.asarray(estimate), jnp.asarray(reference), dr,
                 tuple(float(w) for w in weights), float(options.K1), float(options.K2),
                 bool(options.use_sample_covariance), align)


@partial(jax.jit, static_argnames=("weights", "K1", "K2", "use_sample_covariance", "align"))
def _ssim(estimate, reference, dr, weights, K1, K2, use_sample_covariance, align):
    """`ssim` after its checks, one program (eagerly, op by op, it took 14 ms a
    call at 256², against about 1 ms)."""
    win = len(weights)
    ny, nx = reference.shape[-2:]
    x = _aligned(estimate, reference, align)
    y = jnp.asarray(reference)
    dtype = jnp.result_type(x.dtype, y.dtype, jnp.float32)
    # in units of the data range, which leaves SSIM unchanged (c1, c2 scale with it):
    # the window's products of raw images leave float32's range (NaN above ~1e10)
    x, y = x.astype(dtype) / dr, y.astype(dtype) / dr
    filt = lambda im: _separable_filter(im, weights)  # noqa: E731
    n_window = win ** 2
    cov_norm = n_window / (n_window - 1) if use_sample_covariance else 1.0
    ux, uy = filt(x), filt(y)
    vx = cov_norm * (filt(x * x) - ux * ux)
    vy = cov_norm * (filt(y * y) - uy * uy)
    vxy = cov_norm * (filt(x * y) - ux * uy)
    c1, c2 = K1 ** 2, K2 ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux ** 2 + uy ** 2 + c1) * (vx + vy + c2))
    r = (win - 1) // 2
    return jnp.mean(s[..., r:ny - r, r:nx - r], axis=_SPACE)


# ------------------------------------------------------------------- phase metrics
# docs/design.md, "Phase ambiguities and the phase metric": near/far intensities fix the
# diffuser phase only up to a piston and the conjugate twin θ'(x) = −θ(−x).

def wrap_phase(phase: Float[Array, "..."]) -> Float[Array, "..."]:
    """Phase wrapped into [−π, π) (radians)."""
    return jnp.mod(jnp.asarray(phase) + jnp.pi, 2 * jnp.pi) - jnp.pi


def twin_phase(phase: Float[Array, "... ny nx"]) -> Float[Array, "... ny nx"]:
    """The conjugate twin θ'(x) = −θ(−x), reflected about index N//2 (i → (N − i) mod N).

    A field C·e^{jθ} with a centro-symmetric aperture C and its twin C·e^{jθ'} have the
    same Fourier-lens intensity (the twin's far field is the complex conjugate).
    """
    flipped = jnp.flip(jnp.asarray(phase), axis=_SPACE)
    return -jnp.roll(flipped, 1, axis=_SPACE)


def phase_offset(estimate: Float[Array, "... ny nx"], truth: Float[Array, "... ny nx"], *,
                 mask=None) -> Float[Array, "..."]:
    """The piston d = arg Σ_mask e^{j(θest − θtrue)} that best aligns two phases (rad)."""
    estimate, truth = _check_pair(estimate, truth, "estimate", "truth")
    w = 1.0 if mask is None else jnp.asarray(mask)
    z = jnp.sum(w * jnp.exp(1j * (jnp.asarray(estimate) - jnp.asarray(truth))), axis=_SPACE)
    return jnp.angle(z)


def _phase_residual(estimate, truth, mask):
    d = phase_offset(estimate, truth, mask=mask)[..., None, None]
    return wrap_phase(jnp.asarray(estimate) - jnp.asarray(truth) - d)


def phase_pearson(estimate: Float[Array, "... ny nx"], truth: Float[Array, "... ny nx"], *,
                  mask=None, twin: bool = False) -> Float[Array, "..."]:
    """Piston-aligned phase Pearson: P(θtrue + wrap(θest − θtrue − d), θtrue) over ``mask``.

    With ``twin=True`` the twin-resolved figure max(P(θest), P(twin(θest))): the twin is
    taken on the full grid given (index N//2 is the axis), then masked.
    """
    truth = jnp.asarray(truth)
    aligned = truth + _phase_residual(estimate, truth, mask)
    p = pearson(aligned, truth, mask=mask)
    if not twin:
        return p
    return jnp.maximum(p, phase_pearson(twin_phase(estimate), truth, mask=mask))


def phase_mse(estimate: Float[Array, "... ny nx"], truth: Float[Array, "... ny nx"], *,
              mask=None) -> Float[Array, "..."]:
    """Mean of wrap(θest − θtrue − d)² over ``mask`` (rad²), d from `phase_offset`."""
    r2 = _phase_residual(estimate, truth, mask) ** 2
    if mask is None:
        return jnp.mean(r2, axis=_SPACE)
    m = jnp.asarray(mask, dtype=r2.dtype)
    return jnp.sum(m * r2, axis=_SPACE) / jnp.sum(m)


def phase_scores(estimate: Float[Array, "... ny nx"], truth: Float[Array, "... ny nx"], *,
                 mask=None) -> dict:
    """All phase figures of docs/design.md, "Phase ambiguities and the phase metric":
    ``pearson`` (piston-aligned), ``twin_resolved`` (the better of the estimate and its
    twin), ``raw`` (plain Pearson of θest and θtrue),
    ``mse`` (rad², piston-aligned) and ``mse_twin_resolved`` (the smaller of the MSEs of
    the estimate and its twin)."""
    estimate, truth = _check_pair(estimate, truth, "estimate", "truth")
    mask = None if mask is None else jnp.asarray(mask)
    return _phase_scores(jnp.asarray(estimate), jnp.asarray(truth), mask)


@jax.jit
def _phase_scores(estimate, truth, mask):
    """`phase_scores` after its checks, one program (eagerly, 12 ms a call at
    256²)."""
    mse_twin = phase_mse(twin_phase(estimate), truth, mask=mask)
    mse_est = phase_mse(estimate, truth, mask=mask)
    return {
        "pearson": phase_pearson(estimate, truth, mask=mask),
        "twin_resolved": phase_pearson(estimate, truth, mask=mask, twin=True),
        "raw": pearson(estimate, truth, mask=mask),
        "mse": mse_est,
        "mse_twin_resolved": jnp.minimum(mse_est, mse_twin),
    }


# --------------------------------------------------------------------- PSF fidelity
# Paper Fig. 9: a modelled PSF against a measured one, per depth, after sub-pixel
# registration and intensity normalisation.

def _peak_shift(image_product, upsample):
    """Sub-pixel location of the inverse-DFT peak of one cross-power spectrum (pixels).

    The integer peak of ``ifft2`` is refined on a window of ±0.75 pixel sampled every
    1/``upsample`` pixel, where the inverse DFT is evaluated directly as two small
    matrix products (the matrix-multiply DFT of Guizar-Sicairos et al., Opt. Lett. 2008).
    """
    ny, nx = image_product.shape
    cc = jnp.abs(ifft2(image_product))
    flat = jnp.argmax(cc)
    coarse = jnp.stack([flat // nx, flat % nx]).astype(jnp.float32)
    n = jnp.array([ny, nx], jnp.float32)
    coarse = jnp.where(coarse > n // 2, coarse - n, coarse)
    if upsample <= 1:
        return coarse
    k = int(np.ceil(1.5 * upsample))
    offsets = (jnp.arange(k) - k // 2) / upsample
    sy, sx = coarse[0] + offsets, coarse[1] + offsets
    ey = jnp.exp(2j * jnp.pi * sy[:, None] * jnp.fft.fftfreq(ny)[None, :])
    ex = jnp.exp(2j * jnp.pi * sx[:, None] * jnp.fft.fftfreq(nx)[None, :])
    fine = jnp.abs(ey @ image_product.astype(ey.dtype) @ ex.T)
    best = jnp.argmax(fine)
    return jnp.stack([sy[best // k], sx[best % k]])


def registration_shift(moving: Float[Array, "... ny nx"], reference: Float[Array, "... ny nx"],
                       *, upsample: int = 20) -> Float[Array, "... 2"]:
    """Shift ``(dy, dx)`` in pixels that moves ``moving`` onto ``reference``.

    Phase correlation (the normalised cross-power spectrum) with its peak refined to
    1/``upsample`` pixel; the same convention as
    ``skimage.registration.phase_cross_correlation(reference, moving)``. Shifts are
    piecewise constant in the images, so their gradient is zero.
    """
    moving, reference = _check_pair(moving, reference, "moving", "reference")
    if not isinstance(upsample, int) or upsample < 1:
        raise DiffcamError(f"upsample must be a positive int, got {upsample!r}.")
    return _registration_shift(jnp.asarray(moving), jnp.asarray(reference), upsample)


@partial(jax.jit, static_argnames="upsample")
def _registration_shift(moving, reference, upsample):
    """`registration_shift` after its checks, one program (eagerly it took 15 ms a
    call at 256², and 1.5 s for the first)."""
    a = fft2(reference)
    b = fft2(moving)
    a, b = jnp.broadcast_arrays(a, b)
    product = a * jnp.conj(b)
    product = product / jnp.maximum(jnp.abs(product), jnp.finfo(product.real.dtype).tiny)
    lead = product.shape[:-2]
    flat = product.reshape((-1,) + product.shape[-2:])
    shifts = jax.vmap(lambda p: _peak_shift(p, upsample))(flat)
    return jax.lax.stop_gradient(shifts.reshape(lead + (2,)))


def fourier_shift(image: Float[Array, "... ny nx"], shift: Float[Array, "... 2"]
                  ) -> Float[Array, "... ny nx"]:
    """``image`` moved by ``shift = (dy, dx)`` pixels (sub-pixel, circular, via the FFT)."""
    image = jnp.asarray(image)
    shift = jnp.asarray(shift, image.dtype)
    ny, nx = image.shape[-2:]
    fy = jnp.fft.fftfreq(ny)[:, None]
    fx = jnp.fft.fftfreq(nx)[None, :]
    ramp = jnp.exp(-2j * jnp.pi * (fy * shift[..., 0, None, None] + fx * shift[..., 1, None, None]))
    return ifft2(fft2(image) * ramp).real.astype(image.dtype)


def _min_max(x):
    lo = jnp.min(x, axis=_SPACE, keepdims=True)
    hi = jnp.max(x, axis=_SPACE, keepdims=True)
    return (x - lo) / (hi - lo)


def psf_fidelity(model: Float[Array, "... ny nx"], measured: Float[Array, "... ny nx"], *,
                 register: bool = True, upsample: int = 20) -> dict:
    """Pearson and SSIM of a modelled PSF against a measured one, per leading index.

    The model is moved onto the measurement by `registration_shift` (if
    ``register``), both are min–max normalised to [0, 1] (as the paper normalises its
    captures), then scored with [`pearson`][diffcam.evaluate.metrics.pearson] and
    [`ssim`][diffcam.evaluate.metrics.ssim] (``data_range=1``).

    Returns:
        ``{"pearson": (...), "ssim": (...), "shift": (..., 2)}``; ``shift`` in pixels
        (zero when ``register=False``).
    """
    model, measured = _check_pair(model, measured, "model", "measured")
    for name, x in (("model", model), ("measured", measured)):
        if is_concrete(x):
            x = np.asarray(x)
            flat = x.reshape((-1,) + x.shape[-2:])
            flat_range = np.ptp(flat, axis=(-2, -1))
            if np.any(flat_range == 0):
                raise DiffcamError(
                    f"psf_fidelity: {name} is constant in {int(np.sum(flat_range == 0))} of "
                    f"its {flat.shape[0]} PSF(s), so its min–max normalisation (0/0) and "
                    f"the scores are undefined; check that every PSF holds light.")
    return _fidelity(jnp.asarray(model), jnp.asarray(measured), register, upsample)


@partial(jax.jit, static_argnames=("register", "upsample"))
def _fidelity(model, measured, register, upsample):
    """`psf_fidelity` after its checks, as one program: called eagerly, its
    registration, shift and scores ran op by op (2.2 s for the first call on a pair
    of 96² stacks, 28 ms for each call after it, against 1.5 ms compiled)."""
    model, measured = jnp.broadcast_arrays(model, measured)
    if register:
        shift = registration_shift(model, measured, upsample=upsample)
        model = fourier_shift(model, shift)
    else:
        shift = jnp.zeros(model.shape[:-2] + (2,), model.dtype)
    a, b = _min_max(model), _min_max(measured)
    return {"pearson": pearson(a, b), "ssim": ssim(a, b, data_range=1.0), "shift": shift}
