"""The preprocessing steps that make a capture fit to reconstruct, each a separate
function: background subtraction, saturation mask, box downsampling, L2 normalisation."""

from __future__ import annotations

import warnings

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, check_field, check_finite
from diffcam.io.reading import Capture

__all__ = ["BackgroundWarning", "border_dark_level", "dark_level", "subtract_background",
           "saturation_mask", "downsample", "normalise_l2"]

_SATURATION = 0.999  # of full scale: at or above it a pixel counts as saturated


class BackgroundWarning(UserWarning):
    """Small negative values after background subtraction were clipped to zero."""


def border_dark_level(images, ring: int = 6) -> np.ndarray:
    """Median of a ``ring``-pixel band at the frame border, per frame (input units, shape
    ``images.shape[:-2]``): the dark level of a PSF or capture whose light rarely reaches
    the border (the median ignores a few bright pixels there).

    Raises:
        ShapeError: a frame too small for the band (2·ring ≥ its shorter side).
    """
    a = np.asarray(images, np.float64)
    h, w = a.shape[-2:]
    if ring < 1 or 2 * ring >= min(h, w):
        raise ShapeError(f"frame {h}×{w} is too small for a {ring}-pixel border ring (or "
                         f"ring < 1); give the dark level in counts instead.")
    band = np.zeros((h, w), bool)
    band[:ring] = band[-ring:] = band[:, :ring] = band[:, -ring:] = True
    return np.median(a[..., band], axis=-1)


def dark_level(image: np.ndarray, region: tuple[slice, slice]) -> np.ndarray:
    """Mean of ``image[..., region]`` over space: a background level per channel.

    The DiffuserCam tutorial takes ``region = (slice(5, 15), slice(5, 15))`` of the PSF
    capture (a dark corner) and subtracts it from both PSF and image.
    """
    patch = np.asarray(image)[(Ellipsis,) + tuple(region)]
    if patch.size == 0:
        raise ShapeError(f"the dark region {region} selects no pixels of an image of shape "
                         f"{np.shape(image)}.")
    return patch.mean(axis=(-2, -1))


def subtract_background(image: np.ndarray, background, *,
                        tolerance: float = 0.05) -> np.ndarray:
    """``image - background``, with the negative values that noise leaves clipped to 0.

    Args:
        image: ``(..., ny, nx)`` counts.
        background: a scalar (a sensor bias, e.g. DiffuserCam's ``image_bias = 100``), a
            per-channel level from :func:`dark_level` of shape ``(...)``, or a dark frame
            of the image's shape.
        tolerance: negatives down to ``-tolerance · max(result)`` are noise: they are
            clipped with a :class:`BackgroundWarning`. Deeper ones mean the background
            is wrong and raise.

    Returns:
        float32 array, non-negative.
    """
    image = np.asarray(image, dtype=np.float32)
    background = np.asarray(background, dtype=np.float32)
    check_finite("image", image)
    check_finite("background", background)
    if background.ndim and background.shape == image.shape[:-2]:
        background = background[..., None, None]
    elif background.ndim and background.shape != image.shape:
        raise ShapeError(f"background of shape {background.shape} does not match the "
                         f"image {image.shape}; give a scalar, one level per channel "
                         f"{image.shape[:-2]}, or a dark frame of the image's shape.")
    out = image - background
    check_finite("image - background", out)
    lo, hi = float(out.min()), float(out.max())
    if lo < 0:
        if hi <= 0 or -lo > tolerance * hi:
            raise DiffcamError(
                f"background subtraction leaves values down to {lo:.4g} against a maximum "
                f"of {hi:.4g}: the background is too large for this image (wrong dark "
                f"frame, bias or region?). Check it, or raise tolerance (now {tolerance}).")
        n = int((out < 0).sum())
        warnings.warn(f"clipped {n} negative value(s) (down to {lo:.3g}, "
                      f"{-lo / hi:.2%} of the maximum) left by background subtraction",
                      BackgroundWarning, stacklevel=2)
        out = np.maximum(out, 0)
    return out


def saturation_mask(capture: Capture, level: float | None = None) -> np.ndarray:
    """Boolean mask of saturated pixels (True where a pixel reached the sensor's ceiling).

    Args:
        capture: a :class:`Capture` (its ``full_scale`` sets the default level).
        level: counts at or above which a pixel is saturated; default
            ``0.999 · full_scale`` (65470 for 16-bit files, so a 12-bit sensor's
            ``4095·16 = 65520`` counts as saturated). Required for float data.
    """
    if level is None:
        if capture.full_scale is None:
            raise DiffcamError(f"{capture.path}: float data has no full scale; pass the "
                               f"saturation level in counts (level=...).")
        level = _SATURATION * capture.full_scale
    return np.asarray(capture.image) >= level


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Box-average the last two axes by an integer ``factor`` (``factor²`` pixels → 1).

    Rows/columns that do not fill a whole box are dropped, split evenly between the two
    ends so the centre stays the centre. Returns float32.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise DiffcamError(f"factor must be a positive integer, got {factor!r}.")
    image = np.asarray(image, dtype=np.float32)
    check_field(image, "image")
    ny, nx = image.shape[-2:]
    my, mx = ny // factor, nx // factor
    if my == 0 or mx == 0:
        raise ShapeError(f"image {image.shape[-2:]} is smaller than one {factor}x{factor} box.")
    y0, x0 = (ny - my * factor) // 2, (nx - mx * factor) // 2
    core = image[..., y0:y0 + my * factor, x0:x0 + mx * factor]
    boxes = core.reshape(image.shape[:-2] + (my, factor, mx, factor))
    return boxes.mean(axis=(-3, -1), dtype=np.float64).astype(np.float32)


def normalise_l2(image: np.ndarray) -> np.ndarray:
    """``image / ||image||₂`` over the last two axes (per channel / per plane)."""
    image = np.asarray(image, dtype=np.float32)
    check_field(image, "image")
    norm = np.sqrt(np.sum(image.astype(np.float64) ** 2, axis=(-2, -1), keepdims=True))
    if np.any(norm == 0):
        raise DiffcamError("cannot L2-normalise an all-zero image (or channel).")
    return (image / norm).astype(np.float32)
