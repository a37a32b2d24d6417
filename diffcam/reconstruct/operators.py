"""Linear operators of lensless reconstruction: the camera's convolution model and
finite differences for total variation.

The forward model of a diffuser camera maps a scene to a sensor image by convolving it
with the point spread function (PSF). Three boundaries are offered; each evaluates a
*linear* (non-periodic) or *circular* convolution with real FFTs on a grid chosen once:

``"circular"``
    Periodic convolution on the image grid: object, sensor and FFT grid are all
    ``(ny, nx)``. The PSF (at most the image size) is zero-padded to it.
``"same"``
    Zero-padded linear convolution, output the size of the input (like
    ``scipy.signal.convolve(..., mode="same")``): the object grid is the sensor grid
    ``(ny, nx)``; the FFT grid is ``fft_size(n + m//2)`` per axis, the least padding for
    which no wrap-around reaches the output.
``"crop"``
    The DiffuserCam model ``b = crop(h * x)``: the sensor sees the centre of the full
    linear convolution of a larger scene. The object grid is the FFT grid, at least
    ``n + m - 1`` per axis (one more for some parities), which holds every scene point
    that reaches the sensor; points near its border that no sensor pixel sees have zero
    sensitivity.

A volume model (``volume=True``) takes a PSF stack ``(..., nz, my, mx)``, one PSF per
depth, and an object ``(..., nz, oy, ox)``; the sensor image is the sum over depths,
``b = crop(sum_z h_z * x_z)``.

Grids follow `diffcam.core.grid`: index ``n//2`` of every axis is the optical axis, so
the sensor's centre pixel sees the object's centre pixel through the PSF sample at
``m//2``. ``psf_centre`` moves that PSF sample (scikit-image's convention puts it at
``(m-1)//2``, see `diffcam.reconstruct.richardson_lucy`).
"""

from __future__ import annotations

from typing import Sequence

import equinox as eqx
import jax.numpy as jnp
from jax import Array
from jaxtyping import Complex, Float

from diffcam.core.backend import fft_size, irfft2, rfft2
from diffcam.core.grid import crop_to, pad_to

__all__ = [
    "BOUNDARIES",
    "ConvolutionModel",
    "convolution_model",
    "grid_shapes",
    "gradient",
    "divergence",
]

BOUNDARIES = ("same", "circular", "crop")
_AXES = (-2, -1)


def grid_shapes(sensor_shape: Sequence[int], psf_shape: Sequence[int],
                boundary: str) -> tuple[tuple[int, int], tuple[int, int]]:
    """``(object_shape, fft_shape)`` of a model; ``sensor_shape`` and ``psf_shape`` are
    ``(..., ny, nx)`` and ``(..., my, mx)`` (only the last two entries are used)."""
    if boundary not in BOUNDARIES:
        raise ValueError(f"boundary must be one of {BOUNDARIES}, got {boundary!r}")
    n = tuple(int(v) for v in sensor_shape[-2:])
    m = tuple(int(v) for v in psf_shape[-2:])
    if boundary == "circular":
        return n, n
    if boundary == "same":
        return n, tuple(fft_size(ni + mi // 2) for ni, mi in zip(n, m))
    full = tuple(_crop_grid(ni, mi) for ni, mi in zip(n, m))
    return full, full


def _crop_grid(n: int, m: int) -> int:
    """Smallest fast length ``p >= n + m - 1`` whose centred sensor window leaves room on
    both sides for every scene point that reaches it: ``m - 1 - m//2`` samples before
    the window and ``m//2`` after (so the circular convolution never wraps into it)."""
    p = fft_size(n + m - 1)
    while True:
        before = p // 2 - n // 2
        if before >= m - 1 - m // 2 and p - n - before >= m // 2:
            return p
        p = fft_size(p + 1)


class ConvolutionModel(eqx.Module):
    """The linear map ``A``: object ``(..., [nz,] oy, ox)`` → sensor ``(..., ny, nx)``.

    Build it with [`convolution_model`][diffcam.reconstruct.operators.convolution_model].
    ``model(x)`` is ``A x``; ``model.adjoint(y)`` is ``Aᵀ y`` (exact:
    ``<A x, y> = <x, Aᵀ y>`` to rounding). Leading axes of the OTF and of the arguments
    broadcast.

    Attributes:
        otf: ``(..., [nz,] fy, fx//2+1)`` complex, real FFT of the PSF on the FFT grid,
            its ``psf_centre`` sample moved to index 0.
        sensor_shape: ``(ny, nx)`` samples.
        object_shape: ``(oy, ox)`` samples (centred on the FFT grid).
        fft_shape: ``(fy, fx)`` samples of the FFT grid.
        volume: True if the model sums over a depth axis (-3).
    """

    otf: Complex[Array, "*batch fy fxr"]
    sensor_shape: tuple[int, int] = eqx.field(static=True)
    object_shape: tuple[int, int] = eqx.field(static=True)
    fft_shape: tuple[int, int] = eqx.field(static=True)
    volume: bool = eqx.field(static=True)

    def __call__(self, obj: Float[Array, "*batch oy ox"]) -> Float[Array, "*batch ny nx"]:
        spectrum = rfft2(pad_to(obj, self.fft_shape)) * self.otf
        if self.volume:
            spectrum = spectrum.sum(axis=-3)
        return crop_to(irfft2(spectrum, s=self.fft_shape),
                       self.sensor_shape)

    def adjoint(self, sensor: Float[Array, "*batch ny nx"]) -> Float[Array, "*batch oy ox"]:
        spectrum = rfft2(pad_to(sensor, self.fft_shape))
        if self.volume:
            spectrum = spectrum[..., None, :, :]
        back = irfft2(spectrum * jnp.conj(self.otf), s=self.fft_shape)
        return crop_to(back, self.object_shape)


def convolution_model(psf: Float[Array, "*batch my mx"], sensor_shape: Sequence[int],
                      boundary: str = "same", *, volume: bool = False,
                      psf_centre: tuple[int, int] | None = None) -> ConvolutionModel:
    """The forward model of a camera with PSF ``psf`` and a sensor of ``sensor_shape``.

    Args:
        psf: ``(..., my, mx)`` PSF (or ``(..., nz, my, mx)`` stack with ``volume=True``),
            sampled at the sensor pitch, optical axis at index ``(my//2, mx//2)``.
            Not normalised here: ``A`` carries the PSF's units (sensor counts per unit of
            object).
        sensor_shape: ``(ny, nx)`` samples; ``my <= ny`` and ``mx <= nx``.
        boundary: ``"same"``, ``"circular"`` or ``"crop"`` (see the module docstring).
        volume: sum over the depth axis -3 of the PSF stack.
        psf_centre: index of the PSF sample that maps object (0, 0) to sensor (0, 0);
            default ``(my//2, mx//2)``. Static (it fixes a shift).

    Computes the OTF once; the returned model is jit-friendly and differentiable in
    ``psf``. Shapes are static: a new ``sensor_shape`` or PSF size compiles anew.
    """
    object_shape, fft_shape = grid_shapes(sensor_shape, psf.shape, boundary)
    my, mx = psf.shape[-2:]
    cy, cx = (my // 2, mx // 2) if psf_centre is None else psf_centre
    kernel = jnp.fft.ifftshift(pad_to(psf, fft_shape), axes=_AXES)
    if (cy, cx) != (my // 2, mx // 2):
        kernel = jnp.roll(kernel, (my // 2 - cy, mx // 2 - cx), axis=_AXES)
    otf = rfft2(kernel)
    return ConvolutionModel(otf=otf, sensor_shape=tuple(int(v) for v in sensor_shape[-2:]),
                            object_shape=object_shape, fft_shape=fft_shape, volume=volume)


def gradient(x: Float[Array, "*batch ny nx"]) -> Float[Array, "2 *batch ny nx"]:
    """Circular forward differences ``(x[i+1] - x[i])`` along y and x, stacked first.

    Periodic like the DiffuserCam reference (``np.roll``), so ``gradientᵀ gradient`` is
    diagonal under the 2-D DFT with eigenvalues ``4 - 2cos(2πky/ny) - 2cos(2πkx/nx)``.
    """
    return jnp.stack([jnp.roll(x, -1, axis=-2) - x, jnp.roll(x, -1, axis=-1) - x])


def divergence(g: Float[Array, "2 *batch ny nx"]) -> Float[Array, "*batch ny nx"]:
    """Negative adjoint of `gradient`: ``div = -gradientᵀ``."""
    return (g[0] - jnp.roll(g[0], 1, axis=-2)) + (g[1] - jnp.roll(g[1], 1, axis=-1))


