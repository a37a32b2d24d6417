"""Built-in measured data (Waller Lab, BSD-3-Clause; see PROVENANCE.md beside this file).

* [`load_tutorial_pair`][diffcam.data.load_tutorial_pair] — DiffuserCam tutorial PSF and raw
  capture of a hand, 300x400 (box-averaged by 4 from 1200x1600).
* [`load_psf_stack_3d`][diffcam.data.load_psf_stack_3d] — the 44-plane DiffuserCam 3-D PSF
  stack, 270x320, values as LCAV normalised them (one global min-max over the stack, so 0 …
  1).
* [`load_raw_3d`][diffcam.data.load_raw_3d] — the raw 3-D capture (a tilted USAF target)
  that goes with it.
* [`load_scene_pairs`][diffcam.data.load_scene_pairs] — seven colour DiffuserCam captures
  with the lensed photograph of each scene (Lensless Learning), 135x240 RGB (box-averaged by
  2).
* [`export_captures`][diffcam.data.export_captures] — write either set as the image files a
  camera gives (``diffcam data``), for the command line's real-data walkthrough
  (docs/real_data.md).

The arrays are NumPy float32 in sensor counts unless said otherwise.
"""

from __future__ import annotations

import warnings
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam.io import BackgroundWarning, atomic_output, downsample, make_output_folder
from diffcam.io import subtract_background as _subtract

__all__ = ["DATA_DIR", "TutorialPair", "load_tutorial_pair", "ScenePairs",
           "load_scene_pairs", "load_psf_stack_3d",
           "load_raw_3d", "IMAGE_BIAS_3D", "CAPTURES", "export_captures"]

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
        [`TutorialPair`][diffcam.data.TutorialPair]; 300x400 at ``downsample_by=1``.
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
        subtract_bias: subtract [`IMAGE_BIAS_3D`][diffcam.data.IMAGE_BIAS_3D] (100 counts);
            the pixels one count below it are clipped to 0.
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


class ScenePairs(NamedTuple):
    """Raw colour captures and the ground-truth scene of each.

    Attributes:
        raws: float32 ``(7, 3, ny, nx)`` raw captures, channels R, G, B; the source's
            units (12-bit counts / 4095, background 0.00827 already subtracted, so a
            few values are slightly negative).
        truths: float32 ``(7, 3, ny, nx)`` lensed photographs registered to the sensor
            grid, R, G, B, in ``[0, 1]``.
        names: the source's name of each pair (``"im43"`` …).
    """

    raws: np.ndarray
    truths: np.ndarray
    names: tuple[str, ...]


def load_scene_pairs(*, downsample_by: int = 1) -> ScenePairs:
    """The seven Lensless Learning pairs (a DiffuserCam capture of a picture on a
    monitor, and a lensed photograph of it), 135x240 at ``downsample_by=1``.

    The source arrays (270x480, BGR, float32) are box-averaged by 2, reordered to RGB
    with channels first, and stored as 16 bits: raws with a step of 5.4e-6 (the
    source's 12-bit step averaged over 64 pixels is 3.8e-6), truths with 1/65535.

    Args:
        downsample_by: further box averaging (2 gives 67x120).
    """
    d = _npz("lensless_learning.npz")
    raws = (d["raw"].astype(np.float64) * float(d["raw_step"])
            + float(d["raw_low"])).astype(np.float32)
    truths = d["truth"].astype(np.float32) / np.float32(65535)
    if downsample_by != 1:
        raws, truths = downsample(raws, downsample_by), downsample(truths, downsample_by)
    return ScenePairs(raws=raws, truths=truths, names=tuple(str(n) for n in d["names"]))


CAPTURES = ("hand", "usaf3d", "scenes")
"""The built-in capture sets [`export_captures`][diffcam.data.export_captures] writes."""


def _capture_files(name: str) -> dict[str, np.ndarray]:
    """File name (relative) → array, as a camera would have written them."""
    if name == "hand":
        pair = load_tutorial_pair(subtract_background=False)
        return {"hand_raw.tif": pair.image, "hand_psf.tif": pair.psf}
    if name == "scenes":
        pairs = load_scene_pairs()
        files = {}
        for n, raw, truth in zip(pairs.names, pairs.raws, pairs.truths):
            files[f"raw_{n}.tif"] = np.moveaxis(raw, 0, -1)
            files[f"truth_{n}.tif"] = np.moveaxis(truth, 0, -1)
        return files
    d = _npz("diffusercam_3d.npz")
    files = {"usaf_raw.png": d["image"]}
    files.update({f"psfs/psf{k:02d}.tif": plane for k, plane in enumerate(d["psf_stack"])})
    return files


def export_captures(name: str, folder, *, overwrite: bool = False) -> list[Path]:
    """Write a built-in capture set as image files, the way a camera gives them (dark
    level not subtracted):

    * ``"hand"``: ``hand_raw.tif`` and ``hand_psf.tif``, float32 counts, 300 × 400
      (the DiffuserCam tutorial pair, box-averaged by 4; dark level 34 counts);
    * ``"usaf3d"``: ``usaf_raw.png`` (16-bit counts, 270 × 320, sensor bias 100) and
      ``psfs/psf00.tif`` … ``psf43.tif`` (16-bit, the stack's normalised values × 65535;
      plane 0 nearest the camera);
    * ``"scenes"``: ``raw_imNN.tif`` and ``truth_imNN.tif`` for the seven pairs of
      [`load_scene_pairs`][diffcam.data.load_scene_pairs], float32 RGB TIFFs (135 × 240 ×
      3).

    All files are written together
    ([`diffcam.io.atomic_output`][diffcam.io.writing.atomic_output]); an existing file is an
    error unless ``overwrite``.

    Returns:
        The paths written.

    Raises:
        DiffcamError: an unknown name, a folder that cannot be one
            (`diffcam.io.make_output_folder`), or files that exist (without
            ``overwrite``).
    """
    import tifffile
    from skimage.io import imsave


    if name not in CAPTURES:
        raise DiffcamError(f"unknown capture set {name!r}; choose one of {CAPTURES}.")
    folder = make_output_folder(folder)     # before the captures are read
    files = _capture_files(name)
    paths = [folder / f for f in files]
    for subfolder in {p.parent for p in paths}:
        make_output_folder(subfolder)
    existing = [str(p) for p in paths if p.exists()]
    if existing and not overwrite:
        raise DiffcamError(f"{existing[0]} exists ({len(existing)} of the {len(paths)} "
                           f"files); choose another folder, or overwrite (--force).")
    with atomic_output(*paths) as temps:
        for tmp, image in zip(temps if len(paths) > 1 else [temps], files.values()):
            if tmp.suffix == ".png":
                imsave(tmp, image, check_contrast=False)
            elif image.ndim == 3 and image.shape[-1] == 3:
                tifffile.imwrite(tmp, image, photometric="rgb")
            else:
                tifffile.imwrite(tmp, image)
    return paths
