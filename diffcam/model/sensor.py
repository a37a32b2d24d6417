"""The sensor as a chain of small steps: pixel integration, crop, noise, saturation, bits.

Compose them in the order light meets them, e.g. for a PSF simulated at 5 µm recorded
by a 3.45 µm sensor, cropped to 900×900 as the paper does::

    e = bin_pixels(psf, 5e-6, 3.45e-6) * photons            # electrons per pixel
    e = crop_to(e, (900, 900))                              # diffcam.core.grid.crop_to
    e = read_noise(k2, shot_noise(k1, e), sigma=2.0)
    counts = quantise(saturate(e, full_well), bit_depth=12, full_well=full_well)

Every step is pure and jit-able; randomness comes only from the explicit ``key``.
`bin_pixels` and `resample` are differentiable; shot noise and quantisation
are not (they are sampling and rounding).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from diffcam.core.backend import fft2, fft_size, ifft2

from diffcam.core.errors import (DiffcamError, check_field, check_positive, is_concrete,
                                 real_array)
from diffcam.model.spline import cubic_sample

__all__ = ["resample", "bin_pixels", "shot_noise", "read_noise", "saturate", "quantise"]


def bspline_prefilter(n):
    """1/B(f) on the FFT frequencies of ``n`` samples: turns samples into cubic B-spline
    coefficients when it multiplies their spectrum (B(f) = (4 + 2cos 2πf)/6)."""
    return 6 / (4 + 2 * jnp.cos(2 * jnp.pi * jnp.fft.fftfreq(n)))


def _area_rows(f, lo, hi, taps):
    """Integrate the piecewise-constant rows of ``f`` (pixel j spans [j − ½, j + ½], in
    index units) over the intervals ``[lo[i], hi[i]]``: output row i along axis −2.

    An interval reads at most the ``n`` rows there are, from row 0 on if it starts
    before the frame: the work is bounded by the frame, however wide the interval (a
    magnification of 10⁻⁵ asked for 10⁵ taps, each a pass over the image)."""
    n = f.shape[-2]
    taps = min(taps, n)
    j0 = jnp.maximum(jnp.floor(lo + 0.5).astype(jnp.int32), 0)
    out = 0
    for k in range(taps):
        j = j0 + k
        overlap = jnp.clip(jnp.minimum(hi, j + 0.5) - jnp.maximum(lo, j - 0.5), 0.0, None)
        w = jnp.where((j >= 0) & (j < n), overlap, 0.0).astype(f.dtype)
        out = out + jnp.take(f, jnp.clip(j, 0, n - 1), axis=-2, mode="clip") * w[:, None]
    return out


def _taps(width) -> int:
    """Input pixels an interval of ``width`` (input pixels) can touch."""
    return int(math.ceil(width)) + 1


def resample(intensity: Float[Array, "... ny nx"], dx, out_pitch, out_shape,
             magnification=1.0, centre=(0.0, 0.0), *, kind: str = "area",
             max_width: float | None = None) -> Float[Array, "... my mx"]:
    """Resample an image, optionally magnified about ``centre``, onto a new grid.

    The image is magnified by ``magnification`` about ``centre`` (that point stays,
    distances from it scale) and read on a centred grid of pitch ``out_pitch``. Both
    kinds return power per output pixel, so total power is kept where grids overlap:

    - ``"area"``: each input sample is a pixel of side ``dx`` holding a power; each
      output pixel collects the power of the magnified input pixels it overlaps. Right
      for pixel-integrated data (captures) and for binning to a coarser sensor.
    - ``"cubic"``: the image is taken as point samples of a smooth density,
      interpolated by a cubic B-spline (exact prefilter) at the output pixel centres,
      zero outside the frame (the frame is zero-extended before the periodic
      prefilter, so no edge wraps into the opposite one). Right for point-sampled simulations resampled at a similar pitch;
      it keeps speckle that area integration would blur.

    Args:
        intensity: power per pixel, last two axes space.
        dx: input pitch, metres.
        out_pitch: output pitch, metres.
        out_shape: ``(my, mx)`` of the output.
        magnification: unitless, > 0 (a traced value with ``kind="area"`` needs
            ``max_width``).
        centre: ``(y0, x0)`` of the fixed point, metres from the axis.
        kind: ``"area"`` or ``"cubic"``.
        max_width: ``"area"`` only: bound on out_pitch/(magnification·dx), an output
            pixel's width in input pixels, which fixes how many input pixels each output
            pixel reads; computed from the arguments when they are concrete.

    Returns:
        The resampled image (power per output pixel).
    """
    real_array("intensity", intensity)
    check_field(intensity, "intensity")
    check_positive("dx", dx, "m")
    check_positive("out_pitch", out_pitch, "m")
    check_positive("magnification", magnification, "")
    if kind not in ("area", "cubic"):
        raise DiffcamError(f"kind must be 'area' or 'cubic', got {kind!r}.")
    f = jnp.asarray(intensity)
    ny, nx = f.shape[-2:]
    my, mx = out_shape

    def centres(m_out, n_in, c):
        """Output pixel centres in input index units, and half an output pixel."""
        u = (jnp.arange(m_out) - m_out // 2) * out_pitch
        x = (u - c) / magnification + c
        return x / dx + n_in // 2, out_pitch / (2 * magnification * dx)

    if kind == "cubic":
        f = _zero_extend(f)
        ny, nx = f.shape[-2:]
        ty, hy = centres(my, ny, centre[0])
        tx, hx = centres(mx, nx, centre[1])
        coef = ifft2(fft2(f) * (bspline_prefilter(ny)[:, None]
                                                * bspline_prefilter(nx)[None, :])).real
        return cubic_sample(cubic_sample(coef, ty, -2), tx, -1) * (4 * hy * hx)
    if max_width is None:
        if not is_concrete(dx, out_pitch, magnification):
            raise DiffcamError("resample(kind='area') needs max_width (the largest "
                               "out_pitch/(magnification·dx)) when its arguments are traced.")
        max_width = float(np.max(np.asarray(out_pitch) / (np.asarray(magnification)
                                                          * np.asarray(dx))))
    taps = _taps(max_width)
    ty, hy = centres(my, ny, centre[0])
    tx, hx = centres(mx, nx, centre[1])
    f = _area_rows(f, ty - hy, ty + hy, taps)
    f = _area_rows(jnp.swapaxes(f, -1, -2), tx - hx, tx + hx, taps)
    return jnp.swapaxes(f, -1, -2)


_SPLINE_PAD = 16
"""Zeros added on each side before the periodic cubic-spline prefilter: its impulse
response decays as (2 − √3)^k, so light wrapped across 2·16 zeros is below 1e-18."""


def _zero_extend(ref):
    """``ref`` centred in a zero frame at least `_SPLINE_PAD` wider on every side,
    on an FFT-friendly length; index n//2 stays the centre, so does every coordinate."""
    widths = []
    for n in ref.shape[-2:]:
        size = fft_size(n + 2 * _SPLINE_PAD)
        before = size // 2 - n // 2
        widths.append((before, size - n - before))
    return jnp.pad(ref, [(0, 0)] * (ref.ndim - 2) + widths)


def bin_pixels(intensity: Float[Array, "... ny nx"], dx, sensor_pitch, shape=None
               ) -> Float[Array, "... my mx"]:
    """Sensor pixels of pitch ``sensor_pitch`` (m) integrating a simulation at ``dx`` (m).

    ``shape`` defaults to the sensor pixels that fit in the simulated field,
    ``floor(n·dx/sensor_pitch)`` per axis. Power is conserved.
    """
    if shape is None:
        if not is_concrete(dx, sensor_pitch):
            raise DiffcamError("bin_pixels needs an explicit shape when dx or sensor_pitch "
                               "is traced.")
        ny, nx = np.shape(intensity)[-2:]
        ratio = float(dx) / float(sensor_pitch)
        shape = (int(ny * ratio), int(nx * ratio))
    return resample(intensity, dx, sensor_pitch, shape)


def shot_noise(key: Array, electrons: Float[Array, "..."]) -> Float[Array, "..."]:
    """Poisson photon noise on a mean count of ``electrons`` (≥ 0) per pixel."""
    lam = jnp.maximum(jnp.asarray(electrons), 0.0)
    return jax.random.poisson(key, lam, lam.shape).astype(lam.dtype)


def read_noise(key: Array, electrons: Float[Array, "..."], sigma) -> Float[Array, "..."]:
    """Gaussian read noise of ``sigma`` electrons r.m.s. added to every pixel."""
    check_positive("sigma (read noise)", sigma, "electrons", allow_zero=True)
    e = jnp.asarray(electrons)
    return e + sigma * jax.random.normal(key, e.shape, e.dtype)


def saturate(electrons: Float[Array, "..."], full_well) -> Float[Array, "..."]:
    """Clip to ``[0, full_well]`` electrons (the pixel's capacity)."""
    check_positive("full_well", full_well, "electrons")
    return jnp.clip(electrons, 0.0, full_well)


def quantise(electrons: Float[Array, "..."], bit_depth: int, full_well) -> Float[Array, "..."]:
    """Digital numbers 0 … 2**bit_depth − 1, with ``full_well`` electrons at the top."""
    if not isinstance(bit_depth, int) or not 1 <= bit_depth <= 32:
        raise DiffcamError(f"bit_depth must be an int in 1…32, got {bit_depth!r}.")
    check_positive("full_well", full_well, "electrons")
    top = 2 ** bit_depth - 1
    return jnp.clip(jnp.round(jnp.asarray(electrons) / full_well * top), 0, top)
