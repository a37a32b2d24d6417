"""The sensor as a chain of small steps: pixel integration, crop, noise, saturation, bits.

Compose them in the order light meets them, e.g. for a PSF simulated at 5 µm recorded
by a 3.45 µm sensor, cropped to 900×900 as the paper does::

    e = bin_pixels(psf, 5e-6, 3.45e-6) * photons            # electrons per pixel
    e = crop_to(e, (900, 900))                              # diffcam.grid.crop_to
    e = read_noise(k2, shot_noise(k1, e), sigma=2.0)
    counts = quantise(saturate(e, full_well), bit_depth=12, full_well=full_well)

Every step is pure and jit-able; randomness comes only from the explicit ``key``.
:func:`bin_pixels` and :func:`resample` are differentiable; shot noise and quantisation
are not (they are sampling and rounding).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array
from jaxtyping import Float

from .errors import DiffcamError, check_field, check_positive, is_concrete

__all__ = ["resample", "bin_pixels", "shot_noise", "read_noise", "saturate", "quantise"]


def _area_rows(f, lo, hi, taps):
    """Integrate the piecewise-constant rows of ``f`` (pixel j spans [j − ½, j + ½], in
    index units) over the intervals ``[lo[i], hi[i]]``: output row i along axis −2."""
    n = f.shape[-2]
    j0 = jnp.floor(lo + 0.5).astype(jnp.int32)
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
             magnification=1.0, centre=(0.0, 0.0), *, max_width: float | None = None
             ) -> Float[Array, "... my mx"]:
    """Area-integrate an image, optionally magnified about ``centre``, onto a new grid.

    Each input sample is a pixel of side ``dx`` holding a power; the image is magnified
    by ``magnification`` about ``centre`` (the point stays fixed, distances from it
    scale), and each output pixel of side ``out_pitch`` collects the power of the
    magnified input pixels it overlaps (so total power is kept where the grids overlap).
    Both grids are centred (index n//2 on the axis).

    Args:
        intensity: power per pixel, last two axes space.
        dx: input pitch, metres.
        out_pitch: output pitch, metres.
        out_shape: ``(my, mx)`` of the output.
        magnification: unitless, > 0 (a traced value needs ``max_width``).
        centre: ``(y0, x0)`` of the fixed point, metres from the axis.
        max_width: bound on out_pitch/(magnification·dx), the output pixel's width in
            input pixels; fixes how many input pixels each output pixel reads. Computed
            from the arguments when they are concrete.

    Returns:
        The resampled image (power per output pixel).
    """
    check_field(intensity, "intensity")
    check_positive("dx", dx, "m")
    check_positive("out_pitch", out_pitch, "m")
    check_positive("magnification", magnification, "")
    if max_width is None:
        if not is_concrete(dx, out_pitch, magnification):
            raise DiffcamError("resample needs max_width (the largest out_pitch/"
                               "(magnification·dx)) when its arguments are traced.")
        max_width = float(np.max(np.asarray(out_pitch) / (np.asarray(magnification)
                                                          * np.asarray(dx))))
    taps = _taps(max_width)
    f = jnp.asarray(intensity)
    ny, nx = f.shape[-2:]
    my, mx = out_shape

    def bounds(m_out, n_in, c):
        u = (jnp.arange(m_out) - m_out // 2) * out_pitch
        x = (u - c) / magnification + c  # output pixel centre in input coordinates (m)
        half = out_pitch / (2 * magnification)
        return (x - half) / dx + n_in // 2, (x + half) / dx + n_in // 2

    f = _area_rows(f, *bounds(my, ny, centre[0]), taps)
    f = _area_rows(jnp.swapaxes(f, -1, -2), *bounds(mx, nx, centre[1]), taps)
    return jnp.swapaxes(f, -1, -2)


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
