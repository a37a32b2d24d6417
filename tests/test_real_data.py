"""Reconstruction of the built-in measured captures (Waller Lab DiffuserCam data).

There is no ground truth for these captures, so the tests assert what can be measured:
the data misfit, the sign, how concentrated the light is, and — for the tilted USAF
target — that the in-focus depth moves steadily across the target. The pictures are
made by ``scripts/reconstruct_real.py``.
"""

from pathlib import Path

import numpy as np
import pytest
from scipy.stats import spearmanr

from diffcam.data import load_psf_stack_3d, load_raw_3d, load_tutorial_pair
from diffcam.core.grid import crop_to
from diffcam.io import normalise_l2, read_psf_stack
from diffcam.reconstruct import (admm_tv, admm_tv_3d, focus_sweep, richardson_lucy,
                                 richardson_lucy_3d, wiener)

SHARED_3D = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "diffusercam_3d"


def _concentration(x, fraction=0.02):
    """Share of the total held by the brightest ``fraction`` of pixels."""
    v = np.sort(np.asarray(x).ravel())[::-1]
    return v[:max(1, int(fraction * v.size))].sum() / v.sum()


@pytest.fixture(scope="module")
def tutorial():
    pair = load_tutorial_pair(downsample_by=2)   # 150x200, background subtracted
    return normalise_l2(pair.psf), normalise_l2(pair.image)


@pytest.fixture(scope="module")
def volume_data():
    stack = load_psf_stack_3d(downsample_by=2)   # (44, 135, 160)
    return stack, load_raw_3d(downsample_by=2)


def test_loaders():
    pair = load_tutorial_pair()
    assert pair.psf.shape == pair.image.shape == (300, 400)
    assert pair.psf.dtype == np.float32 and pair.psf.min() >= 0
    assert abs(pair.dark_level - 34.1) < 0.1
    stack = load_psf_stack_3d()
    assert stack.shape == (44, 270, 320) and stack.dtype == np.float32
    assert stack.min() == 0 and stack.max() == 1 and stack[8].max() == 1  # LCAV min-max
    sums = stack.sum(axis=(1, 2))
    assert sums[0] > 2.5 * sums[-1]          # energy falls from plane 0 to plane 43
    raw = load_raw_3d()
    assert raw.shape == (270, 320) and raw.min() == 0


@pytest.mark.slow
@pytest.mark.skipif(not SHARED_3D.is_dir(), reason="needs shared/data/real beside the repo")
def test_stored_stack_matches_the_original_slices():
    """16-bit storage of the normalised slices changes a reconstruction by < 1e-3."""
    original = read_psf_stack(sorted((SHARED_3D / "psf").glob("psf*.tiff")))
    stored = load_psf_stack_3d()
    assert np.abs(stored - original).max() <= 0.5 / 65535 + 1e-7
    raw = load_raw_3d()
    a = richardson_lucy_3d(raw, stored[::4], 20).image
    b = richardson_lucy_3d(raw, original[::4], 20).image
    assert np.linalg.norm(a - b) / np.linalg.norm(b) < 1e-3


def test_tutorial_hand_richardson_lucy(tutorial):
    psf, image = tutorial
    out = richardson_lucy(image, psf, 100, boundary="crop")
    est = np.asarray(out.image)
    assert est.min() >= 0
    assert float(out.residual[-1]) < 0.04          # 0.030 measured
    assert float(out.residual[-1]) < 0.1 * float(out.residual[0])
    # the hand is compact: 2 % of the pixels hold most of the light (0.85 measured) ...
    assert _concentration(est) > 0.6
    # ... and it lies inside the sensor's field of view (the object grid is larger; a
    # few barely-seen rim pixels of it collect light, as RL does on a crop model)
    bright = est > 0.2 * np.percentile(est, 99.9)
    assert crop_to(bright, image.shape).sum() > 0.9 * bright.sum()   # 0.97 measured


def test_tutorial_hand_admm(tutorial):
    psf, image = tutorial
    out = admm_tv(image, psf, 50)          # DiffuserCam tutorial penalties
    est = np.asarray(out.image)
    assert est.min() >= 0
    assert float(out.residual[-1]) < 0.02          # 0.0095 measured
    assert _concentration(est) > 0.5               # 0.75 measured
    baseline = wiener(image, psf, 1e-2, boundary="crop")
    assert _concentration(np.maximum(np.asarray(baseline.image), 0)) < _concentration(est)


def _best_depth_per_column(volume, stack, sensor_shape):
    """In-focus depth of each column of the target: the plane holding most of the
    column's light on the sensor (each plane weighted by its PSF's total)."""
    v = crop_to(np.asarray(volume), sensor_shape) * stack.sum(axis=(1, 2))[:, None, None]
    columns = v.sum(axis=1)                               # (nz, nx)
    energy = columns.sum(axis=0)
    target = np.where(energy > 0.3 * energy.max())[0]
    return target, columns[:, target].argmax(axis=0)


@pytest.fixture(scope="module")
def admm_volume(volume_data):
    stack, raw = volume_data
    return admm_tv_3d(raw, stack, 40)                      # the defaults are these settings


def test_tilted_usaf_target_admm_3d(volume_data, admm_volume):
    stack, raw = volume_data
    out = admm_volume
    assert out.image.shape == (44,) + out.image.shape[1:]
    assert float(out.image.min()) >= 0
    assert float(out.residual[-1]) < 0.01                 # 0.005 measured
    target, best = _best_depth_per_column(out.image, stack, raw.shape)
    assert target.size > 20                                # the target spans ~30 columns
    assert best.max() - best.min() > 15                    # depth changes across it ...
    assert spearmanr(target, best)[0] < -0.75              # ... steadily (-0.88 measured)


@pytest.mark.slow
def test_tilted_usaf_target_richardson_lucy_3d(volume_data):
    stack, raw = volume_data
    out = richardson_lucy_3d(raw, stack, 100)
    assert float(out.image.min()) >= 0
    assert float(out.residual[-1]) < 0.12                 # 0.089 measured
    target, best = _best_depth_per_column(out.image, stack, raw.shape)
    assert spearmanr(target, best)[0] < -0.4               # -0.64 measured: RL is blurrier


@pytest.mark.slow
def test_focus_sweep_finds_the_target_depth(volume_data, admm_volume):
    """The plane a 2-D focus sweep picks lies within the depths the 3-D reconstruction
    gives the tilted target; the sharpness of Richardson–Lucy reconstructions picks the
    stack's first plane."""
    stack, raw = volume_data
    _, best_3d = _best_depth_per_column(admm_volume.image, stack, raw.shape)
    sweep = focus_sweep(raw, stack[::2], 60)
    plane = 2 * int(sweep.best)
    assert best_3d.min() <= plane <= best_3d.max()
    assert 4 <= plane <= 40                                # 28 measured, not an end
    rl = focus_sweep(raw, stack[::2], 30, method="rl", measure="sharpness")
    assert int(rl.best) == 0
