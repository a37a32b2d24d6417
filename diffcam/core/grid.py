"""Sampling grids in the centred convention: the one home of coordinates and shifts.

A grid is ``ny × nx`` samples of pitch ``dx`` (metres; a scalar, or a ``(dy, dx)``
pair for rectangular pixels). The coordinate of index ``i`` along an axis of ``n``
samples is ``(i - n//2) * dx``, so index ``n//2`` is the optical axis, for even and
odd ``n`` alike. Spatial axes are always the last two; leading axes are batch.

Frequency grids come in two orders: [`fft_freqs`][diffcam.core.grid.fft_freqs] is the
natural order of ``jnp.fft.fft`` (used to build transfer functions that multiply
``fft2(field)`` with no shift at all: a convolution kernel is translation invariant, so a
centred field stays centred), and [`centred_freqs`][diffcam.core.grid.centred_freqs] is the
order of [`fft2c`][diffcam.core.grid.fft2c] outputs.
"""

from __future__ import annotations

import numbers
from typing import Any, Sequence

import jax.numpy as jnp

from diffcam.core.backend import fft2, ifft2
from diffcam.core.errors import DiffcamError
from jax import Array

__all__ = [
    "pitch_yx",
    "coords",
    "yx",
    "radius2",
    "fft_freqs",
    "coord_at",
    "fft_freq_at",
    "centred_freqs",
    "fft2c",
    "ifft2c",
    "pad_to",
    "crop_to",
    "pad_by",
    "int_pair",
    "check_grid_size",
    "MAX_GRID_SAMPLES",
]

MAX_GRID_SAMPLES = 2 ** 28
"""Largest propagation grid (samples, padding included) that a
[`Camera`][diffcam.model.camera.Camera] or a propagator accepts: 16384², 2 GiB per complex64
field. A mistyped pad or shape is refused before anything is allocated; raise it for the
session by assigning to ``diffcam.core.grid.MAX_GRID_SAMPLES``."""

_AXES = (-2, -1)


def pitch_yx(dx) -> tuple:
    """``(dy, dx)`` from a scalar pitch or a pair, metres per sample."""
    if isinstance(dx, (tuple, list)):
        if len(dx) != 2:
            raise DiffcamError(f"the pitch dx must be one number or a (dy, dx) pair in "
                               f"metres, got {dx!r}.")
        return dx[0], dx[1]
    return dx, dx


def coords(n: int, dx) -> Array:
    """Centred sample coordinates ``(i - n//2) * dx`` of an axis of ``n`` samples (m)."""
    return coord_at(jnp.arange(n), n, dx)


def coord_at(i, n: int, dx):
    """The centred coordinate of sample index ``i`` (any int array) on an axis of ``n``
    samples: ``coords(n, dx)[i]`` without building the axis (m)."""
    return (i - n // 2) * dx


def fft_freq_at(i, n: int, dx):
    """The FFT-order frequency of index ``i``: ``jnp.fft.fftfreq(n, dx)[i]`` (cycles/m)."""
    return jnp.where(i < (n + 1) // 2, i, i - n) / (n * dx)


def yx(shape: Sequence[int], dx) -> tuple[Array, Array]:
    """Broadcastable coordinates ``y[:, None]`` and ``x[None, :]`` of a grid (m).

    ``shape`` is ``(..., ny, nx)``; only the last two entries are used. Separable, so
    nothing of size ``ny*nx`` is materialised until the caller combines them.
    """
    ny, nx = shape[-2], shape[-1]
    dy, dxx = pitch_yx(dx)
    return coords(ny, dy)[:, None], coords(nx, dxx)[None, :]


def radius2(shape: Sequence[int], dx, centre=(0.0, 0.0)) -> Array:
    """Squared distance from ``centre = (y0, x0)`` (m) of every grid sample (m²)."""
    y, x = yx(shape, dx)
    return (y - centre[0]) ** 2 + (x - centre[1]) ** 2


def fft_freqs(shape: Sequence[int], dx) -> tuple[Array, Array]:
    """Spatial frequencies ``(fy[:, None], fx[None, :])`` in FFT order (cycles/m)."""
    ny, nx = shape[-2], shape[-1]
    dy, dxx = pitch_yx(dx)
    return (fft_freq_at(jnp.arange(ny), ny, dy)[:, None],
            fft_freq_at(jnp.arange(nx), nx, dxx)[None, :])


def centred_freqs(shape: Sequence[int], dx) -> tuple[Array, Array]:
    """Spatial frequencies ``(fy[:, None], fx[None, :])`` in centred order (cycles/m)."""
    ny, nx = shape[-2], shape[-1]
    dy, dxx = pitch_yx(dx)
    return coords(ny, 1.0 / (ny * dy))[:, None], coords(nx, 1.0 / (nx * dxx))[None, :]


def fft2c(field: Array) -> Array:
    """Centred 2-D DFT over the last two axes: index ``n//2`` in and out is zero.

    ``fftshift(fft2(ifftshift(u)))``; no normalisation (like ``jnp.fft.fft2``).
    """
    return jnp.fft.fftshift(fft2(jnp.fft.ifftshift(field, axes=_AXES)),
                            axes=_AXES)


def ifft2c(spectrum: Array) -> Array:
    """Inverse of [`fft2c`][diffcam.core.grid.fft2c] (``ifft2`` normalisation,
    ``1/(ny*nx)``)."""
    return jnp.fft.fftshift(ifft2(jnp.fft.ifftshift(spectrum, axes=_AXES)),
                            axes=_AXES)


def _centred_slices(big: int, small: int) -> slice:
    start = big // 2 - small // 2
    return slice(start, start + small)


def pad_to(field: Array, shape: Sequence[int]) -> Array:
    """Zero-pad the last two axes to ``shape[-2:]``, keeping the axis sample centred."""
    ny, nx = field.shape[-2:]
    my, mx = shape[-2], shape[-1]
    if my < ny or mx < nx:
        raise ValueError(f"cannot pad {field.shape[-2:]} to smaller {(my, mx)}")
    by, bx = my // 2 - ny // 2, mx // 2 - nx // 2
    widths = [(0, 0)] * (field.ndim - 2) + [(by, my - ny - by), (bx, mx - nx - bx)]
    return jnp.pad(field, widths)


def int_pair(value: Any, name: str) -> tuple[int, int]:
    """``(a, b)`` from an int or a pair of ints (NumPy integers too, not bools), or a
    DiffcamError naming ``name``."""
    def whole(v):
        return isinstance(v, numbers.Integral) and not isinstance(v, bool)
    if whole(value):
        return int(value), int(value)
    if isinstance(value, (tuple, list)) and len(value) == 2 and all(map(whole, value)):
        return int(value[0]), int(value[1])
    raise DiffcamError(f"{name} must be an int or a pair of ints (samples), got {value!r:.80}.")


def check_grid_size(shape: Sequence[int], pad: Any = 0, what: str = "the propagation grid"
                    ) -> tuple[int, int]:
    """The padded ``(ny, nx)`` of a grid of ``shape[-2:]`` plus ``pad`` per side, after
    checking that ``pad`` is whole and ≥ 0 and that the grid holds at most
    [`MAX_GRID_SAMPLES`][diffcam.core.grid.MAX_GRID_SAMPLES] samples (before anything of
    that size is allocated)."""
    py, px = int_pair(pad, "pad")
    if py < 0 or px < 0:
        raise DiffcamError(f"pad must be ≥ 0 samples per side, got {pad!r}.")
    ny, nx = shape[-2] + 2 * py, shape[-1] + 2 * px
    if ny * nx > MAX_GRID_SAMPLES:
        raise DiffcamError(
            f"{what} {ny}×{nx} (shape {tuple(shape[-2:])} plus pad {(py, px)} per side) is "
            f"{ny * nx / 2**20:.0f} Mi samples, {ny * nx * 8 / 2**30:.1f} GiB per complex64 "
            f"field, above the limit of {MAX_GRID_SAMPLES / 2**20:.0f} Mi samples "
            f"(diffcam.core.grid.MAX_GRID_SAMPLES; the paper's 4000² grid is 15 Mi); check "
            f"pad and shape (samples, not metres).")
    return ny, nx


def pad_by(field: Array, pad) -> Array:
    """Zero-pad ``pad`` samples (an int, or a ``(py, px)`` pair) on each side."""
    py, px = int_pair(pad, "pad")
    ny, nx = field.shape[-2:]
    return pad_to(field, (ny + 2 * py, nx + 2 * px))


def crop_to(field: Array, shape: Sequence[int]) -> Array:
    """Centred crop of the last two axes to ``shape[-2:]`` (inverse of
    [`pad_to`][diffcam.core.grid.pad_to])."""
    ny, nx = field.shape[-2:]
    my, mx = shape[-2], shape[-1]
    if my > ny or mx > nx:
        raise ValueError(f"cannot crop {field.shape[-2:]} to larger {(my, mx)}")
    return field[..., _centred_slices(ny, my), _centred_slices(nx, mx)]
