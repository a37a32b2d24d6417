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

A camera whose PSF changes across the field is [`FieldModel`][diffcam.reconstruct.operators.FieldModel], the low-rank model
of `diffcam.model.field` (Yanny et al. 2020): ``K`` kernels ``g_k`` and their
weights ``w_k`` on the object grid, ``b = crop(Σ_k g_k * (w_k · x))`` (per depth, summed,
in 3-D), on the same grids and with the same boundaries. The solvers take it in place
of a PSF.

Grids follow `diffcam.core.grid`: index ``n//2`` of every axis is the optical axis, so
the sensor's centre pixel sees the object's centre pixel through the PSF sample at
``m//2``. ``psf_centre`` moves that PSF sample (scikit-image's convention puts it at
``(m-1)//2``, see `diffcam.reconstruct.richardson_lucy`).
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import Array, lax
from jaxtyping import Complex, Float

from diffcam.core.backend import fft_size, irfft2, rfft2
from diffcam.core.errors import DiffcamError
from diffcam.core.grid import crop_to, pad_to
from diffcam.model.field import FieldPSF

__all__ = [
    "BOUNDARIES",
    "ConvolutionModel",
    "convolution_model",
    "FieldModel",
    "field_model",
    "operator_norm",
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


class FieldModel(eqx.Module):
    """The field-dependent linear map ``A``: object ``(..., [nz,] oy, ox)`` → sensor
    ``(..., ny, nx)``, ``A x = crop(Σ_k g_k * (w_k · x))`` (Σ over depths too in 3-D).

    Build it with `field_model`. ``model(x)`` is ``A x``, ``model.adjoint(y)`` is
    ``Aᵀ y = Σ_k w_k · (g_k ⋆ pad(y))`` (exact to rounding). The sum over ``k`` is a
    ``lax.scan`` accumulating into one spectrum (forward) or one object (adjoint), so
    the working memory does not grow with ``K``; an evaluation costs ``K + 1`` real
    FFTs of the object grid (one per kernel and one back).

    Attributes:
        otf: ``(K, [nz,] fy, fx//2+1)`` complex, real FFTs of the kernels on the FFT
            grid, their axis sample moved to index 0.
        weights: ``(K, [nz,] oy, ox)`` the kernels' weights on the object grid.
        sensor_shape, object_shape, fft_shape: as `ConvolutionModel`'s.
        boundary: ``"same"``, ``"circular"`` or ``"crop"``.
        volume: True if the model sums over a depth axis (-3).
    """

    otf: Complex[Array, "k *depth fy fxr"]
    weights: Float[Array, "k *depth oy ox"]
    sensor_shape: tuple[int, int] = eqx.field(static=True)
    object_shape: tuple[int, int] = eqx.field(static=True)
    fft_shape: tuple[int, int] = eqx.field(static=True)
    boundary: str = eqx.field(static=True)
    volume: bool = eqx.field(static=True)

    @property
    def rank(self) -> int:
        """``K``, the number of kernels."""
        return self.otf.shape[0]

    def __call__(self, obj: Float[Array, "*batch oy ox"]) -> Float[Array, "*batch ny nx"]:
        return crop_to(self.blur(obj), self.sensor_shape)

    def blur(self, obj: Float[Array, "*batch oy ox"]) -> Float[Array, "*batch fy fx"]:
        """``Σ_k g_k * (w_k · x)`` on the whole FFT grid (before the sensor's crop)."""
        def add(spectrum, kernel):
            otf, w = kernel
            term = rfft2(pad_to(w * obj, self.fft_shape)) * otf
            return spectrum + (term.sum(axis=-3) if self.volume else term), None
        core = 3 if self.volume else 2
        zero = jnp.zeros(jnp.shape(obj)[:jnp.ndim(obj) - core] + self.otf.shape[-2:],
                         jnp.result_type(obj, self.otf))
        spectrum, _ = lax.scan(add, zero, (self.otf, self.weights))
        return irfft2(spectrum, s=self.fft_shape)

    def adjoint(self, sensor: Float[Array, "*batch ny nx"]) -> Float[Array, "*batch oy ox"]:
        return self.blur_adjoint(pad_to(sensor, self.fft_shape))

    def blur_adjoint(self, image: Float[Array, "*batch fy fx"]) -> Float[Array, "*batch oy ox"]:
        """The adjoint of `blur`: ``Σ_k w_k · (g_k ⋆ image)``."""
        spectrum = rfft2(image)
        if self.volume:
            spectrum = spectrum[..., None, :, :]

        def add(obj, kernel):
            otf, w = kernel
            back = irfft2(spectrum * jnp.conj(otf), s=self.fft_shape)
            return obj + w * crop_to(back, self.object_shape), None
        shape = jnp.broadcast_shapes(spectrum.shape[:-2], self.weights.shape[1:-2])
        zero = jnp.zeros(shape + self.object_shape, jnp.result_type(image, self.weights))
        obj, _ = lax.scan(add, zero, (self.otf, self.weights))
        return obj

    def centre_psf(self) -> Float[Array, "*depth fy fx"]:
        """The PSF of a point at the object's centre, ``Σ_k w_k(0) g_k``, on the FFT
        grid with its axis sample at index 0 (one per depth)."""
        cy, cx = self.object_shape[0] // 2, self.object_shape[1] // 2
        w = self.weights[..., cy, cx]
        return irfft2(jnp.einsum("k...,k...yx->...yx", w.astype(self.otf.dtype), self.otf),
                      s=self.fft_shape)


def field_model(psf: FieldPSF, sensor_shape: Sequence[int], boundary: str = "crop"
                ) -> FieldModel:
    """The forward model of a camera whose PSF changes across the field.

    Args:
        psf: a `diffcam.model.field.FieldPSF` (from
            `diffcam.model.field.field_psf` or
            `diffcam.model.field.load_field_psf`); with a depth axis it gives a
            volume model.
        sensor_shape: ``(ny, nx)`` samples; the kernels ``(my, mx)`` fit inside it.
        boundary: ``"crop"`` (the DiffuserCam model), ``"same"`` or ``"circular"``
            (module docstring).

    Computes the OTFs and interpolates the weights onto the object grid once; the model
    is jit-friendly and differentiable in the kernels, coefficients and positions.
    """
    if not isinstance(psf, FieldPSF):
        raise DiffcamError(f"field_model takes a FieldPSF (diffcam.model.field.field_psf), "
                           f"got {type(psf).__name__}; for one PSF use convolution_model.")
    sensor_shape = tuple(int(v) for v in sensor_shape[-2:])
    if psf.kernels.shape[-2] > sensor_shape[0] or psf.kernels.shape[-1] > sensor_shape[1]:
        raise DiffcamError(f"the kernels {psf.kernels.shape[-2:]} are larger than the sensor "
                           f"{sensor_shape}; crop the PSFs to the sensor first.")
    return _field_model(psf, sensor_shape, boundary)


@partial(jax.jit, static_argnames=("sensor_shape", "boundary"))
def _field_model(psf: FieldPSF, sensor_shape, boundary) -> FieldModel:
    conv = convolution_model(psf.kernels, sensor_shape, boundary, volume=psf.volume)
    weights = psf.weights(conv.object_shape).astype(psf.kernels.dtype)
    return FieldModel(otf=conv.otf, weights=weights, sensor_shape=sensor_shape,
                      object_shape=conv.object_shape, fft_shape=conv.fft_shape,
                      boundary=boundary, volume=psf.volume)


def operator_norm(forward, adjoint, x0, iterations: int = 30) -> Array:
    """``||A||`` by power iteration on ``AᵀA`` from ``x0`` (a non-negative start, such as
    ones, converges fastest for a camera's non-negative PSFs); a lower bound that
    approaches the norm from below."""
    def step(_, x):
        y = adjoint(forward(x))
        return y / jnp.maximum(jnp.linalg.norm(y), jnp.finfo(y.dtype).tiny)
    x = lax.fori_loop(0, iterations, step, x0 / jnp.linalg.norm(x0))
    return jnp.linalg.norm(forward(x))


def gradient(x: Float[Array, "*batch ny nx"]) -> Float[Array, "2 *batch ny nx"]:
    """Circular forward differences ``(x[i+1] - x[i])`` along y and x, stacked first.

    Periodic like the DiffuserCam reference (``np.roll``), so ``gradientᵀ gradient`` is
    diagonal under the 2-D DFT with eigenvalues ``4 - 2cos(2πky/ny) - 2cos(2πkx/nx)``.
    """
    return jnp.stack([jnp.roll(x, -1, axis=-2) - x, jnp.roll(x, -1, axis=-1) - x])


def divergence(g: Float[Array, "2 *batch ny nx"]) -> Float[Array, "*batch ny nx"]:
    """Negative adjoint of `gradient`: ``div = -gradientᵀ``."""
    return (g[0] - jnp.roll(g[0], 1, axis=-2)) + (g[1] - jnp.roll(g[1], 1, axis=-1))


