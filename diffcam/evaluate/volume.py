"""Judging a reconstructed volume of a tilted planar target: its depth ridge.

A flat target tilted along x puts each column of the scene at one depth. In the x–z
maximum projection of a good volume the light of each column peaks at one plane, the
peaks lie on a line (the tilt), and the peak is thin along depth. Haze and speckle put
light outside the target. `ridge_measures` reports these numbers;
`target_box` finds the target in a max projection, so that several volumes of
one capture are judged on the same box.

All functions take NumPy-convertible arrays and return plain Python numbers (they
judge results; they are not differentiated).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from diffcam.core.errors import (DiffcamError, ShapeError, number_in, real_array,
                                 whole_number)

__all__ = ["Box", "Ridge", "target_box", "ridge_measures", "depth_map"]


class Box(NamedTuple):
    """A rectangle of pixels, ``rows = slice(top, bottom)``, ``cols = slice(left, right)``
    (ends excluded)."""

    top: int
    bottom: int
    left: int
    right: int

    def mask(self, shape) -> np.ndarray:
        """Boolean ``shape`` array, True inside the box."""
        m = np.zeros(shape, bool)
        m[self.top:self.bottom, self.left:self.right] = True
        return m


class Ridge(NamedTuple):
    """The depth ridge of a tilted target (`ridge_measures`).

    Attributes:
        slope: planes per column of the line through the per-column peak planes.
        rms: planes, root-mean-square distance of the peaks from that line.
        axial_width: planes, median over the columns of the number of planes at or
            above half the column's peak in the x–z projection.
        outside: share of the max projection's light outside the target box.
        peaks: the peak plane of each column of the box (``left`` … ``right - 1``).
        brightness: each column's x–z peak over the brightest column's (0–1); a dark
            column (the box's margin, a gap between bars) peaks wherever its faint
            light happens to be brightest.
    """

    slope: float
    rms: float
    axial_width: float
    outside: float
    peaks: np.ndarray
    brightness: np.ndarray

    def summary(self) -> dict:
        """The scalar measures as a dict (for JSON)."""
        return {"slope": self.slope, "rms": self.rms, "axial_width": self.axial_width,
                "outside": self.outside}


def _check_volume(volume) -> np.ndarray:
    v = np.asarray(real_array("volume", volume), np.float64)
    if v.ndim != 3:
        raise ShapeError(f"a volume is (nz, ny, nx); got shape {v.shape}.")
    if not np.isfinite(v).all():
        raise DiffcamError("the volume holds NaN/Inf values; judge a finite volume.")
    if v.max() <= 0:
        raise DiffcamError("the volume holds no light (max <= 0); nothing to judge.")
    return v


def target_box(max_projection, fraction: float = 0.3, sigma: float = 4.0,
               margin: int = 4) -> Box:
    """The bounding box of the target in a max projection: the largest connected region
    where the projection, smoothed by a Gaussian of ``sigma`` pixels, is at least
    ``fraction`` of its maximum, grown by ``margin`` pixels per side.

    Args:
        max_projection: ``(ny, nx)`` max projection over depth, any units.
        fraction: threshold, share of the smoothed maximum.
        sigma: pixels, Gaussian smoothing before the threshold (merges bars and digits).
        margin: pixels added on each side, clipped to the frame.
    """
    from scipy import ndimage

    fraction = number_in("fraction", fraction, 1e-6, 1, "a share of the peak in (0, 1]")
    sigma = number_in("sigma", sigma, 0, 1e4, "a width ≥ 0 in pixels")
    margin = whole_number("margin", margin, 0)
    mip = np.asarray(real_array("max_projection", max_projection), np.float64)
    if mip.ndim != 2 or not np.isfinite(mip).all() or mip.max() <= 0:
        raise DiffcamError(f"target_box needs a (ny, nx) max projection with some light; "
                           f"got shape {mip.shape}, max {mip.max() if mip.size else None}.")
    smooth = ndimage.gaussian_filter(mip, sigma)
    labels, n = ndimage.label(smooth >= fraction * smooth.max())
    sizes = ndimage.sum(np.ones_like(smooth), labels, index=np.arange(1, n + 1))
    rows, cols = ndimage.find_objects(labels)[int(np.argmax(sizes))]
    ny, nx = mip.shape
    return Box(max(rows.start - margin, 0), min(rows.stop + margin, ny),
               max(cols.start - margin, 0), min(cols.stop + margin, nx))


def ridge_measures(volume, box: Box | None = None) -> Ridge:
    """The depth ridge of a tilted target in ``volume``, inside ``box``.

    For each column of the box, the x–z projection (maximum over the box's rows) peaks
    at one plane; a least-squares line through the peaks gives the tilt (``slope``) and
    the scatter about it (``rms``); the planes at or above half the column's peak give
    its axial width. ``outside`` is the share of the max projection's light outside the
    box: haze and speckle.

    Args:
        volume: ``(nz, ny, nx)`` non-negative volume, plane 0 nearest.
        box: the target (`target_box`); default: found in this volume's max
            projection. Judge several volumes of one capture on one box.
    """
    v = _check_volume(volume)
    mip = v.max(axis=0)
    box = target_box(mip) if box is None else _box_in(box, mip.shape)
    xz = v[:, box.top:box.bottom, box.left:box.right].max(axis=1)     # (nz, columns)
    peaks = xz.argmax(axis=0)
    cols = np.arange(box.left, box.right)
    slope, offset = np.polyfit(cols, peaks, 1)
    rms = float(np.sqrt(np.mean((peaks - (offset + slope * cols)) ** 2)))
    width = float(np.median(np.sum(xz >= 0.5 * xz.max(axis=0), axis=0)))
    outside = float(mip[~box.mask(mip.shape)].sum() / mip.sum())
    brightness = xz.max(axis=0) / xz.max()
    return Ridge(float(slope), rms, width, outside, peaks, brightness)


def _box_in(box, shape) -> Box:
    """``box`` as a `Box` of whole pixels inside a frame of ``shape``, at least
    one row and two columns."""
    ny, nx = shape
    values = tuple(box) if isinstance(box, (tuple, list, np.ndarray)) else ()
    if len(values) != 4:
        raise DiffcamError(f"box must be (top, bottom, left, right) pixels, got "
                           f"{box!r:.60}.")
    top, bottom, left, right = (whole_number(f"box.{name} (frame {ny}×{nx})", v, 0, n)
                                for name, v, n in zip(Box._fields, values, (ny, ny, nx, nx)))
    if bottom <= top or right - left < 2:
        raise DiffcamError(f"the target box {tuple(box)} is empty or one column wide; "
                           f"give a box of at least 2 columns inside the frame.")
    return Box(top, bottom, left, right)


def depth_map(volume, fraction: float = 0.2) -> np.ma.MaskedArray:
    """Index of the brightest plane per pixel, masked where the max projection is below
    ``fraction`` of its 99.5th percentile (no object there; the percentile ignores a few
    hot pixels).

    Args:
        volume: ``(nz, ny, nx)`` volume, plane 0 nearest.
        fraction: share of the max projection's 99.5th percentile below which a pixel
            is masked.
    """
    fraction = number_in("fraction", fraction, 0, 1, "a share of the peak in 0 … 1")
    v = _check_volume(volume)
    mip = v.max(axis=0)
    return np.ma.masked_array(v.argmax(axis=0), mip < fraction * np.percentile(mip, 99.5))
