"""Scene pairs: raw captures and the ground-truth scenes they record, checked, flipped
into the sensor frame and scaled before a fit (`diffcam.calibrate.scene.fit`)."""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike, Float

from diffcam.core.errors import DiffcamError, ShapeError, real_array

__all__ = ["FLIPS", "as_pairs", "check_scene_pairs", "flip_scene", "border_window",
           "scaled_pairs", "channel_peaks"]

FLIPS = ("none", "y", "x", "yx")
"""Flips of the scene frame relative to the sensor frame: none, up-down, left-right,
both (a 180° rotation)."""


def as_pairs(images, what: str) -> np.ndarray:
    """``(k, c, ny, nx)`` float32 from a sequence of ``(c, ny, nx)`` or ``(ny, nx)`` real
    images, finite and within float32's range."""
    if isinstance(images, np.ndarray) and images.ndim in (2, 3):
        raise ShapeError(f"{what}: give a sequence of images (one per pair), got one "
                         f"array of shape {images.shape}; wrap it in a list.")
    try:
        arrays = [np.asarray(real_array(f"{what}[{k}]", a)) for k, a in enumerate(images)]
    except TypeError:
        raise DiffcamError(f"{what}: give a sequence of images (one per pair), got "
                           f"{images!r:.60}.") from None
    if not arrays:
        raise DiffcamError(f"{what}: no images given; give at least one pair.")
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1 or arrays[0].ndim not in (2, 3):
        raise ShapeError(f"{what}: the images must share one shape (ny, nx) or "
                         f"(channels, ny, nx), got {sorted(shapes)}.")
    stack = np.stack(arrays)
    if not np.isfinite(stack).all():
        raise DiffcamError(f"{what}: NaN/Inf values; clean the data first.")
    top = float(np.max(np.abs(stack)))
    if top > float(np.finfo(np.float32).max):
        raise DiffcamError(f"{what}: values up to {top:.3g}, beyond float32's range "
                           f"(3.4e+38), in which the fit runs; divide them by a constant "
                           f"first (the PSF scales with the raws).")
    stack = stack.astype(np.float32)
    return stack[:, None] if stack.ndim == 3 else stack


def check_scene_pairs(raws, truths) -> tuple[np.ndarray, np.ndarray]:
    """Raws and scenes as ``(k, c, ny, nx)`` float32 arrays, checked before any fit.

    Raises:
        DiffcamError: different numbers of raws and scenes, of channels or of pixels; a
            scene that is dark everywhere (it does not overlap the sensor frame) or has
            negative values; a raw that is constant; complex, NaN/Inf or beyond
            float32's range.
    """
    raws, truths = as_pairs(raws, "raws"), as_pairs(truths, "truths")
    if len(raws) != len(truths):
        raise DiffcamError(f"{len(raws)} raw(s) but {len(truths)} truth(s); give one "
                           f"ground-truth scene per raw capture, in the same order.")
    if raws.shape[1] != truths.shape[1]:
        raise ShapeError(f"the raws have {raws.shape[1]} channel(s), the truths "
                         f"{truths.shape[1]}; read both in colour (or both in grayscale).")
    if raws.shape[2:] != truths.shape[2:]:
        raise ShapeError(f"raws are {raws.shape[2]}×{raws.shape[3]} pixels, truths "
                         f"{truths.shape[2]}×{truths.shape[3]}; resample the truths to the "
                         f"sensor's pixels (the scene on the sensor grid) first.")
    if (truths < 0).any():
        k, ch = np.argwhere((truths < 0).any(axis=(-2, -1)))[0]
        raise DiffcamError(f"truth {k} (channel {ch}) has negative values (min "
                           f"{float(truths[k, ch].min()):.3g}); a scene is an intensity: "
                           f"subtract its dark level with clipping "
                           f"(diffcam.io.subtract_background) or np.clip(truth, 0, None).")
    lit = np.max(truths, axis=(-2, -1)) > 0
    if not lit.all():
        k, ch = np.argwhere(~lit)[0]
        raise DiffcamError(f"truth {k} (channel {ch}) is dark everywhere: it does not "
                           f"overlap the sensor frame; check its registration.")
    flat = np.ptp(raws, axis=(-2, -1)) == 0
    if flat.any():
        k, ch = np.argwhere(flat)[0]
        raise DiffcamError(f"raw {k} (channel {ch}) is constant: it holds no image.")
    return raws, truths


def flip_scene(scene: Float[ArrayLike, "... ny nx"], flip: str) -> np.ndarray:
    """``scene`` flipped into the sensor frame (``flip`` one of `FLIPS`)."""
    scene = np.asarray(scene)
    if "y" in flip:
        scene = scene[..., ::-1, :]
    if "x" in flip:
        scene = scene[..., :, ::-1]
    return scene


def border_window(shape: tuple[int, int], taper: float) -> np.ndarray:
    """``(ny, nx)`` separable Tukey window: 1 inside, a raised cosine over ``taper`` of
    each side at each border."""
    def side(n):
        w, m = np.ones(n, np.float32), int(round(taper * n))
        w[:m] = 0.5 - 0.5 * np.cos(np.pi * (np.arange(m) + 0.5) / m)
        w[n - m:] = w[:m][::-1]
        return w
    return np.outer(side(shape[0]), side(shape[1]))


def scaled_pairs(raws, truths):
    """Each channel of the raws and the truths scaled to unit peak (the fit's float32
    sums of products of raw values overflow from ~1e19: a raw of 1e30 would give an
    all-NaN PSF), and the two scales ``(raw_peak, gain)`` per channel."""
    raw_peak, truth_peak = channel_peaks(raws), channel_peaks(truths)
    gain = raw_peak / truth_peak
    if not np.finfo(np.float32).tiny < gain.min() <= gain.max() < np.finfo(np.float32).max:
        raise DiffcamError(f"the PSF's scale max(raw)/max(truth) reaches {gain.min():.3g}…"
                           f"{gain.max():.3g}, outside float32's range; divide the raws or "
                           f"the truths by a constant first (the PSF scales with raw/truth).")
    return (raws / raw_peak[:, None, None].astype(np.float32),
            truths / truth_peak[:, None, None].astype(np.float32), raw_peak, gain)


def channel_peaks(images: np.ndarray) -> np.ndarray:
    """max |images| per channel of a ``(k, c, ny, nx)`` stack, float64 (1 where 0)."""
    peak = np.max(np.abs(images), axis=(0, 2, 3)).astype(np.float64)
    return np.where(peak > 0, peak, 1.0)
