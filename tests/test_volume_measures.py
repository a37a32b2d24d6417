"""diffcam.evaluate.volume: the ridge measures of a tilted target, on volumes built with
known tilt, axial profile and stray light."""

import numpy as np
import pytest

from diffcam.core.errors import DiffcamError
from diffcam.evaluate.volume import Box, depth_map, ridge_measures, target_box

BOX = Box(10, 20, 5, 35)


def tilted(slope=0.4, sigma=1.5, nz=24, shape=(30, 40), start=2.0):
    """A target filling BOX whose column c lies at depth start + slope·(c - left), with a
    Gaussian axial profile of ``sigma`` planes."""
    v = np.zeros((nz,) + shape)
    z = np.arange(nz)[:, None]
    cols = np.arange(BOX.left, BOX.right)
    centre = start + slope * (cols - BOX.left)
    profile = np.exp(-(z - np.round(centre)) ** 2 / (2 * sigma ** 2))      # (nz, cols)
    v[:, BOX.top:BOX.bottom, BOX.left:BOX.right] = profile[:, None, :]
    return v, np.round(centre)


def test_slope_rms_and_width_of_a_known_ridge():
    """The peaks are the rounded line: slope 0.4 to rounding, rms below 0.5 plane (the
    rounding), and the planes at or above half the peak are those within σ·√(2 ln 2)."""
    v, peaks = tilted(slope=0.4, sigma=1.5)
    r = ridge_measures(v, BOX)
    assert np.array_equal(r.peaks, peaks)
    fit = np.polyfit(np.arange(BOX.left, BOX.right), peaks, 1)
    assert r.slope == pytest.approx(fit[0]) and abs(r.slope - 0.4) < 0.02
    assert r.rms < 0.5
    assert r.axial_width == 2 * np.floor(1.5 * np.sqrt(2 * np.log(2))) + 1   # 3 planes
    assert r.outside == pytest.approx(0.0)


def test_stray_light_share_and_a_haze_column():
    """Light outside the box is counted by its share of the max projection; a column
    whose brightest plane is haze moves the rms."""
    v, _ = tilted()
    mip_in = v.max(axis=0).sum()
    v[:, 0:5, 0:5] = 0.5                         # 25 pixels of stray light at 0.5
    assert ridge_measures(v, BOX).outside == pytest.approx(12.5 / (mip_in + 12.5))
    clean = ridge_measures(v, BOX).rms
    v[-1, BOX.top:BOX.bottom, BOX.left + 3] = 2.0          # far-plane haze in one column
    hazy = ridge_measures(v, BOX)
    assert hazy.peaks[3] == v.shape[0] - 1 and hazy.rms > clean + 1
    assert hazy.brightness[3] == 1.0 and np.allclose(np.delete(hazy.brightness, 3), 0.5)


def test_target_box_finds_the_target():
    v, _ = tilted()
    assert target_box(v.max(axis=0), sigma=0.5, margin=0) == BOX
    box = target_box(v.max(axis=0))          # smoothing and margin widen it by < 2σ + 4
    assert box.top <= BOX.top and box.bottom >= BOX.bottom and box.top >= BOX.top - 12
    assert box.left <= BOX.left and box.right >= BOX.right and box.right <= BOX.right + 12
    assert ridge_measures(v).summary() == ridge_measures(v, target_box(v.max(axis=0))).summary()


def test_depth_map_masks_empty_pixels():
    v, peaks = tilted()
    d = depth_map(v)
    assert d.mask[0, 0] and not d.mask[BOX.top, BOX.left]
    assert np.array_equal(d[BOX.top, BOX.left:BOX.right], peaks)


@pytest.mark.parametrize("volume", [np.zeros((3, 8, 8)), np.ones((8, 8)),
                                    np.full((3, 8, 8), np.nan)])
def test_bad_volumes_raise(volume):
    with pytest.raises(DiffcamError):
        ridge_measures(volume, BOX)
