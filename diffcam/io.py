"""Reading real captures, and the preprocessing steps that make them fit to reconstruct.

The I/O edge: files come in as 8/16-bit PNG or TIFF, float ``.npy`` or MATLAB ``.mat``
PSF stacks; they leave as float32 NumPy arrays in sensor counts with colour channels on
a leading axis. Each preprocessing step is a separate, tested function, applied in this
order (LenslessPiCam-style, as the DiffuserCam tutorial does it)::

    capture = read_image("raw.tif")                       # counts, (ny, nx) or (c, ny, nx)
    mask = saturation_mask(capture)                       # pixels at full scale
    level = dark_level(psf_capture.image, (slice(5, 15), slice(5, 15)))
    image = subtract_background(capture.image, level)     # small negatives clipped
    image = downsample(image, 4)                          # box average
    image = normalise_l2(image)

Everything here is NumPy (files are read once, outside ``jit``); the results go to the
JAX solvers in :mod:`diffcam.reconstruct`.
"""

from __future__ import annotations

import os
import warnings
import zlib
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, check_field

__all__ = [
    "Capture",
    "read_image",
    "read_psf_stack",
    "read_mat_stack",
    "dark_level",
    "subtract_background",
    "saturation_mask",
    "downsample",
    "normalise_l2",
    "BackgroundWarning",
]

_IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
_SATURATION = 0.999  # of full scale: at or above it a pixel counts as saturated


class BackgroundWarning(UserWarning):
    """Small negative values after background subtraction were clipped to zero."""


class Capture(NamedTuple):
    """An image read from a file.

    Attributes:
        image: float32 ``(ny, nx)``, or ``(c, ny, nx)`` with channels first, or a stack
            ``(n, ny, nx)`` from a multi-page TIFF / 3-D ``.npy``; in the file's units
            (counts for integer files).
        channels: channel names in the order of the leading axis, e.g. ``("R", "G",
            "B")`` or ``("B", "G", "R")``; ``None`` for a grayscale image or a stack.
        full_scale: the largest value the file's integer type can hold (255, 65535) —
            the saturation level; ``None`` for float data.
        path: the file read.
    """

    image: np.ndarray
    channels: tuple[str, ...] | None
    full_scale: float | None
    path: str


def read_image(path: str | os.PathLike, *, channel_order: str | None = None) -> Capture:
    """Read a PNG, TIFF or ``.npy`` capture.

    Args:
        path: file to read (``.png``, ``.tif``/``.tiff``, ``.npy``).
        channel_order: for colour data, the order of the file's channel axis, e.g.
            ``"BGR"`` for arrays saved by OpenCV (the DiffuserCam/LenslessLearning
            ``.npy`` files). PNG and TIFF colour is ``"RGB"`` (or ``"RGBA"``) by the
            format, which is the default there; a colour ``.npy`` has no such rule and
            needs it.

    Returns:
        :class:`Capture` with the channel axis moved first.

    Raises:
        DiffcamError: missing, empty, corrupt or unsupported files; NaN/Inf values; a
            colour ``.npy`` without ``channel_order``; a 16-bit colour PNG (which Pillow
            would silently reduce to 8 bits).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _IMAGE_SUFFIXES:
        raise DiffcamError(f"{path}: unsupported file type {suffix!r}; diffcam reads "
                           f"{', '.join(_IMAGE_SUFFIXES)} images and .mat PSF stacks "
                           f"(read_mat_stack).")
    _check_file(path)
    try:
        if suffix == ".png":
            data = _read_png(path)
        elif suffix in (".tif", ".tiff"):
            import tifffile
            data = tifffile.imread(path)
        else:
            data = np.load(path, allow_pickle=False)
    except DiffcamError:
        raise
    except (OSError, ValueError, EOFError, zlib.error, SyntaxError) as err:
        raise DiffcamError(f"{path}: could not be read as {suffix[1:].upper()} ({err}); "
                           f"the file may be truncated or corrupt — copy it again.") from err
    return _to_capture(np.asarray(data), path, suffix, channel_order)


def read_psf_stack(paths: Sequence[str | os.PathLike]) -> np.ndarray:
    """Read one PSF per file (sorted as given) into a float32 stack ``(nz, my, mx)``.

    Raises:
        ShapeError: if the files differ in shape or hold colour/stacks.
    """
    if len(paths) == 0:
        raise ShapeError("no PSF files given; pass one file per depth, e.g. "
                         "sorted(Path('psf').glob('psf*.tiff')).")
    planes = [read_image(p) for p in paths]
    shapes = {c.image.shape for c in planes}
    if len(shapes) != 1 or planes[0].image.ndim != 2:
        raise ShapeError(f"PSF files must all be grayscale images of one shape, got "
                         f"{sorted(shapes)}; crop them to a common size first.")
    return np.stack([c.image for c in planes])


def read_mat_stack(path: str | os.PathLike, key: str | None = None) -> np.ndarray:
    """Read a DiffuserCam-style PSF stack from a MATLAB ``.mat`` file.

    MATLAB stores the stack as ``(y, x, z)``; it is returned as float32 ``(z, y, x)``.
    Files up to v7.2 are read with ``scipy.io.loadmat``; v7.3 files are HDF5 and read
    with ``h5py`` (which sees MATLAB's column-major arrays with their axes reversed).

    Args:
        path: the ``.mat`` file.
        key: variable name; default the only non-metadata variable (DiffuserCam calls
            it ``psf``).
    """
    path = Path(path)
    _check_file(path)
    import h5py
    if h5py.is_hdf5(path):
        with h5py.File(path, "r") as f:
            names = [k for k in f.keys() if not k.startswith("#")]
            key = _pick_key(path, names, key)
            data = np.asarray(f[key])
        data = np.transpose(data)  # h5py sees MATLAB's column-major (y, x, z) as (z, x, y)
    else:
        import scipy.io
        try:
            contents = scipy.io.loadmat(path)
        except Exception as err:  # scipy's parser raises many types on a damaged file
            raise DiffcamError(f"{path}: not a readable MATLAB file ({err}); it may be "
                               f"truncated — copy it again.") from err
        key = _pick_key(path, [k for k in contents if not k.startswith("__")], key)
        data = np.asarray(contents[key])
    if data.ndim == 2:
        data = data[:, :, None]
    if data.ndim != 3 or not np.issubdtype(data.dtype, np.number):
        raise ShapeError(f"{path}: variable {key!r} has shape {data.shape} and dtype "
                         f"{data.dtype}; expected a numeric (y, x, z) PSF stack.")
    stack = np.ascontiguousarray(np.moveaxis(data, -1, 0), dtype=np.float32)
    _check_values(stack, path)
    return stack


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
    if background.ndim and background.shape == image.shape[:-2]:
        background = background[..., None, None]
    elif background.ndim and background.shape != image.shape:
        raise ShapeError(f"background of shape {background.shape} does not match the "
                         f"image {image.shape}; give a scalar, one level per channel "
                         f"{image.shape[:-2]}, or a dark frame of the image's shape.")
    out = image - background
    _check_values(out, "image - background")
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
    if not isinstance(factor, (int, np.integer)) or factor < 1:
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
    norm = np.sqrt(np.sum(image.astype(np.float64) ** 2, axis=(-2, -1), keepdims=True))
    if np.any(norm == 0):
        raise DiffcamError("cannot L2-normalise an all-zero image (or channel).")
    return (image / norm).astype(np.float32)


def _check_file(path: Path) -> None:
    if not path.is_file():
        raise DiffcamError(f"{path}: no such file.")
    if path.stat().st_size == 0:
        raise DiffcamError(f"{path}: the file is empty (0 bytes); copy it again.")


def _pick_key(path: Path, names: list[str], key: str | None) -> str:
    if key is not None:
        if key not in names:
            raise DiffcamError(f"{path}: no variable {key!r}; it holds {names}.")
        return key
    if len(names) != 1:
        raise DiffcamError(f"{path}: holds variables {names}; say which one with key=...")
    return names[0]


def _read_png(path: Path) -> np.ndarray:
    from PIL import Image
    with open(path, "rb") as f:
        header = f.read(33)
    if header[:8] != b"\x89PNG\r\n\x1a\n" or header[12:16] != b"IHDR":
        raise DiffcamError(f"{path}: not a PNG file (bad signature); is it another format "
                           f"with a .png name, or truncated?")
    bit_depth, colour_type = header[24], header[25]
    if bit_depth == 16 and colour_type in (2, 4, 6):
        raise DiffcamError(f"{path}: 16-bit colour PNG; Pillow would reduce it to 8 bits. "
                           f"Convert it to a 16-bit TIFF (e.g. with tifffile) or .npy.")
    with Image.open(path) as im:
        im.load()
        if im.mode == "P":
            raise DiffcamError(f"{path}: palette PNG; a capture should be grayscale or "
                               f"RGB — re-save it without a palette.")
        return np.array(im)


def _to_capture(data: np.ndarray, path: Path, suffix: str,
                channel_order: str | None) -> Capture:
    if data.size == 0:
        raise DiffcamError(f"{path}: the image is empty (shape {data.shape}).")
    if not (np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.floating)):
        raise DiffcamError(f"{path}: unsupported data type {data.dtype}; expected integer "
                           f"or float pixels.")
    full_scale = float(np.iinfo(data.dtype).max) if np.issubdtype(data.dtype, np.integer) \
        else None
    channels = None
    if data.ndim == 3 and data.shape[-1] in (3, 4):
        if channel_order is None:
            if suffix == ".npy":
                raise DiffcamError(
                    f"{path}: a colour .npy array {data.shape} has no channel order in the "
                    f"file; pass channel_order='BGR' (OpenCV, e.g. LenslessLearning) or "
                    f"'RGB'.")
            channel_order = "RGB" if data.shape[-1] == 3 else "RGBA"
        if len(channel_order) != data.shape[-1]:
            raise DiffcamError(f"{path}: channel_order {channel_order!r} does not match "
                               f"{data.shape[-1]} channels.")
        channels = tuple(channel_order.upper())
        data = np.moveaxis(data, -1, 0)
    elif data.ndim not in (2, 3):
        raise ShapeError(f"{path}: expected a 2-D image, a colour image or a stack, got "
                         f"shape {data.shape}.")
    image = np.ascontiguousarray(data, dtype=np.float32)
    _check_values(image, path)
    return Capture(image=image, channels=channels, full_scale=full_scale, path=str(path))


def _check_values(arr: np.ndarray, where) -> None:
    finite = np.isfinite(arr)
    if not finite.all():
        raise DiffcamError(f"{where}: {int(arr.size - finite.sum())} NaN/Inf value(s); "
                           f"clean the data (np.nan_to_num) or mask those pixels first.")
