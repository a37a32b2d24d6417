"""The given planes of a PSF-stack fit: validated before any compute, and prepared
(dark-subtracted, mean-normalised) the same way for the fit and the benchmarks."""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, check_positive, real_array
from diffcam.io import border_dark_level

__all__ = ["prepare_planes", "given_planes", "check_saturation", "saturation_level",
           "check_physical"]


def prepare_planes(images, ring: int = 6, *, labels: Sequence[int] | None = None
                   ) -> np.ndarray:
    """Dark-subtract and mean-normalise PSF planes (the fit's and the benchmark's
    preprocessing, applied to each plane on its own frame).

    The dark level of a plane is the median of a ``ring``-pixel band at the frame border
    (the caustic rarely reaches the border; the median ignores a few bright pixels);
    the plane is then divided by its mean, so every plane has unit mean.

    Args:
        images: (..., ny, nx) planes.
        ring: band width, pixels (0: no dark subtraction).
        labels: plane numbers used in error messages (default 0, 1, ...).

    Returns:
        float64 array of the same shape.
    """
    a = np.asarray(real_array("images", images), np.float64)
    h, w = a.shape[-2:]
    if ring:
        a = a - border_dark_level(a, ring)[..., None, None]
    out = np.empty_like(a)
    flat_in, flat_out = a.reshape(-1, h, w), out.reshape(-1, h, w)
    for k, f in enumerate(flat_in):
        mean = f.mean()
        if not mean > 0:
            name = k if labels is None else labels[k]
            raise DiffcamError(f"plane {name} has no signal above its dark level (mean "
                               f"{mean:.3g} after subtracting the border median): an "
                               f"empty or dark plane cannot be fitted.")
        flat_out[k] = f / mean
    return out


def given_planes(stack, planes):
    """Validate (stack, planes) before any compute → (list of float64 frames, planes,
    n_planes or None, input dtype)."""
    planes = _plane_list(planes)
    frames, n_planes = _frames_of(stack, planes)
    for t, f in zip(planes, frames):   # refused if complex; the input dtype is kept: it
        real_array(f"plane {t}", f)    # sets the saturation level
    dtype = _check_frames(frames, planes)
    return [f.astype(np.float64) for f in frames], planes, n_planes, dtype


def _plane_list(planes) -> list[int]:
    """Two or more distinct integer plane indices."""
    if isinstance(planes, (int, np.integer)) or isinstance(planes, (str, bytes)):
        raise DiffcamError(f"planes must be a sequence of at least 2 plane indices, got "
                           f"{planes!r}.")
    try:
        planes = list(planes)
    except TypeError:
        raise DiffcamError(f"planes must be a sequence of plane indices, got {planes!r}.") \
            from None
    for t in planes:
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)):
            raise DiffcamError(f"plane indices must be integers, got {t!r}.")
    planes = [int(t) for t in planes]
    if len(planes) < 2:
        raise DiffcamError(f"give at least 2 planes to fit (the magnification law needs "
                           f"two), got {planes}.")
    repeated = sorted({t for t in planes if planes.count(t) > 1})
    if repeated:
        raise DiffcamError(f"plane(s) {repeated} given more than once in {planes}.")
    return planes


def _frames_of(stack, planes):
    """The given planes' frames of a ``{plane: frame}`` mapping or an (n, ny, nx) stack
    → (frames, n_planes or None)."""
    if isinstance(stack, Mapping):
        missing = [t for t in planes if t not in stack]
        if missing:
            raise DiffcamError(f"plane(s) {missing} are not in the given frames (planes "
                               f"{sorted(stack)}).")
        return [np.asarray(stack[t]) for t in planes], None
    if isinstance(stack, (list, tuple)):
        shapes = {np.shape(f) for f in stack}
        if len(shapes) > 1:
            raise ShapeError(f"the stack's frames differ in shape: {sorted(shapes)}; "
                             f"crop them to one size first.")
    arr = np.asarray(stack) if not hasattr(stack, "shape") else stack
    if np.ndim(arr) != 3 or 0 in np.shape(arr):
        raise ShapeError(f"the stack must be (n_planes, ny, nx), got shape "
                         f"{np.shape(arr)}.")
    n_planes = int(np.shape(arr)[0])
    bad = [t for t in planes if not 0 <= t < n_planes]
    if bad:
        raise DiffcamError(f"plane(s) {bad} out of range: the stack has {n_planes} "
                           f"planes (0 … {n_planes - 1}).")
    return [np.asarray(arr[t]) for t in planes], n_planes


def _check_frames(frames, planes):
    """One shape of ≥ 16 pixels a side, a numeric dtype, finite, not constant → the
    dtype."""
    shapes = {f.shape for f in frames}
    if len(shapes) > 1:
        raise ShapeError(f"the given frames differ in shape: {sorted(shapes)}; crop them "
                         f"to one size first.")
    if frames[0].ndim != 2 or 0 in frames[0].shape:
        raise ShapeError(f"each plane must be a non-empty 2-D image, got {frames[0].shape}.")
    if min(frames[0].shape) < 16:
        raise ShapeError(f"frames of {frames[0].shape} pixels are too small to fit (≥ 16 "
                         f"per side).")
    for t, f in zip(planes, frames):
        if not (np.issubdtype(f.dtype, np.integer) or np.issubdtype(f.dtype, np.floating)):
            raise DiffcamError(f"plane {t}: unsupported data type {f.dtype}.")
        finite = np.isfinite(f)
        if not finite.all():
            raise DiffcamError(f"plane {t} holds {int(f.size - finite.sum())} NaN/Inf "
                               f"pixel(s); clean or crop them first.")
        if float(np.ptp(f)) == 0:
            raise DiffcamError(f"plane {t} is constant ({float(f.flat[0]):g} everywhere): "
                               f"an empty or dark plane cannot be fitted.")
    return frames[0].dtype


def check_saturation(frames, planes, level):
    if level is None:
        return
    counts = {t: int((f >= level).sum()) for t, f in zip(planes, frames)}
    bad = {t: n for t, n in counts.items() if n}
    if bad:
        total = sum(bad.values())
        listing = ", ".join(f"plane {t}: {n}" for t, n in bad.items())
        raise DiffcamError(f"{total} saturated pixel(s) (≥ {level:g}) in the given planes "
                           f"({listing}); their true values are unknown. Retake or crop "
                           f"them, or pass saturation=None to fit them as they are.")


def check_physical(pixel_pitch, wavelength, z2) -> dict:
    """The physical inputs given (metres or ``None``), checked."""
    phys = {"pixel_pitch": pixel_pitch, "wavelength": wavelength, "z2": z2}
    for name, v in phys.items():
        if v is not None:
            check_positive(name, v, "m")
            phys[name] = float(v)
    return phys


def saturation_level(saturation, dtype) -> float | None:
    """The pixel level at or above which a given plane counts as saturated (input
    units), from ``saturation`` (a level, ``"auto"`` or ``None``, see
    `diffcam.calibrate.stack.fit.fit_stack`) and the input dtype."""
    if isinstance(saturation, str):
        if saturation != "auto":
            raise DiffcamError(f"saturation must be a level, 'auto' or None, got "
                               f"{saturation!r}.")
        return 0.999 * float(np.iinfo(dtype).max) \
            if np.issubdtype(dtype, np.integer) else None
    if saturation is not None:
        if isinstance(saturation, bool) or not isinstance(saturation, (int, float, np.number)) \
                or not np.isfinite(saturation):
            raise DiffcamError(f"saturation must be a finite pixel level, 'auto' or None, "
                               f"got {saturation!r}.")
        return float(saturation)
    return saturation
