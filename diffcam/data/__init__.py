"""Built-in measured data (Waller Lab, BSD-3-Clause; see PROVENANCE.md beside this file).

* :func:`load_tutorial_pair` — DiffuserCam tutorial PSF and raw capture of a hand,
  300x400 (box-averaged by 4 from 1200x1600).
* :func:`load_psf_stack_3d` — the 44-plane DiffuserCam 3-D PSF stack, 270x320, values
  as LCAV normalised them (one global min-max over the stack, so 0 … 1).
* :func:`load_raw_3d` — the raw 3-D capture (a tilted USAF target) that goes with it.

The arrays are NumPy float32 in sensor counts unless said otherwise.
"""

from __future__ import annotations

import warnings
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from diffcam.io import BackgroundWarning, downsample
from diffcam.io import subtract_background as _subtract

__all__ = ["DATA_DIR", "TutorialPair", "load_tutorial_pair", "load_psf_stack_3d",
           "load_raw_3d", "IMAGE_BIAS_3D"]

DATA_DIR = Path(__file__).resolve().parent
IMAGE_BIAS_3D = 100.0
"""Sensor bias of the 3-D raw capture in counts (DiffuserCam_settings.m: image_bias)."""


class TutorialPair(NamedTuple):
    """The DiffuserCam tutorial PSF and capture (same camera, same downsampling).

    Attributes:
        psf: float32 ``(ny, nx)`` PSF, counts.
        image: float32 ``(ny, nx)`` raw capture of a hand, counts.
        dark_level: the background both had, counts: the mean of the full-resolution
            PSF's corner ``[5:15, 5:15]`` (34.1), already subtracted unless
            ``subtract_background=False``.
    """

    psf: np.ndarray
    image: np.ndarray
    dark_level: float


@lru_cache(maxsize=None)
def _npz(name: str) -> dict:
    with np.load(DATA_DIR / name) as f:
        return {k: f[k] for k in f.files}


def load_tutorial_pair(*, subtract_background: bool = True,
                       downsample_by: int = 1) -> TutorialPair:
    """The DiffuserCam tutorial pair (``psf_sample.tif``, ``rawdata_hand_sample.tif``).

    Args:
        subtract_background: subtract the dark level from both (the tutorial's
            preprocessing); the few noise negatives this leaves in the PSF are clipped.
        downsample_by: further box averaging on top of the stored factor 4
            (2 gives 150x200, the tutorial's ADMM size is 300x400 = 1).

    Returns:
        :class:`TutorialPair`; 300x400 at ``downsample_by=1``.
    """
    d = _npz("tutorial.npz")
    psf, image, level = d["psf"], d["image"], float(d["dark_level"])
    if subtract_background:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BackgroundWarning)
            psf, image = _subtract(psf, level), _subtract(image, level)
    if downsample_by != 1:
        psf, image = downsample(psf, downsample_by), downsample(image, downsample_by)
    return TutorialPair(psf=psf.copy(), image=image.copy(), dark_level=level)


def load_psf_stack_3d(*, downsample_by: int = 1) -> np.ndarray:
    """The 44-plane DiffuserCam PSF stack, float32 ``(44, 270, 320)`` in ``[0, 1]``.

    Plane 0 is the source position closest to the camera, plane 43 the farthest; the
    axial spacing and pixel pitch were not published. Values are LCAV's global min-max
    normalisation of Waller Lab's ``example_psfs.mat``, stored to 16 bits (absolute error
    <= 7.7e-6, below the data's noise).

    Args:
        downsample_by: lateral box averaging (2 gives ``(44, 135, 160)``).
    """
    stack = _npz("diffusercam_3d.npz")["psf_stack"].astype(np.float32) / np.float32(65535)
    return downsample(stack, downsample_by) if downsample_by != 1 else stack


def load_raw_3d(*, subtract_bias: bool = True, downsample_by: int = 1) -> np.ndarray:
    """The raw 3-D capture ``example_raw.png`` (a tilted USAF target), float32 counts.

    Args:
        subtract_bias: subtract :data:`IMAGE_BIAS_3D` (100 counts); the pixels one
            count below it are clipped to 0.
        downsample_by: lateral box averaging.

    Returns:
        ``(270, 320)`` at ``downsample_by=1``; one pixel is saturated (65535 counts).
    """
    image = _npz("diffusercam_3d.npz")["image"].astype(np.float32)
    if subtract_bias:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BackgroundWarning)
            image = _subtract(image, IMAGE_BIAS_3D)
    return downsample(image, downsample_by) if downsample_by != 1 else image
