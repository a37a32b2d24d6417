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

Both directions are guarded at this edge. Readers turn every damaged, truncated or
oversized file into one :class:`~diffcam.core.errors.DiffcamError` line naming the file
and the problem, and they check the size a header declares against
:data:`MAX_READ_BYTES` before allocating anything. Writers check the output path with
:func:`check_output_path` before any work starts and write through
:func:`atomic_output`: a temporary file beside the target, fsynced and moved into place
with ``os.replace``, so an existing file is either untouched or wholly replaced.
"""

from __future__ import annotations

import contextlib
import glob
import os
import re
import secrets
import signal
import struct
import sys
import threading
import warnings
import zipfile
from functools import partial
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, check_field

__all__ = [
    "Capture",
    "read_image",
    "read_psf_stack",
    "image_files",
    "natural_key",
    "IMAGE_SUFFIXES",
    "border_dark_level",
    "read_mat_stack",
    "dark_level",
    "subtract_background",
    "saturation_mask",
    "downsample",
    "normalise_l2",
    "BackgroundWarning",
    "read_npz",
    "npz_keys",
    "file_kind",
    "check_output_path",
    "atomic_output",
    "Terminated",
    "temporary_files",
    "MAX_READ_BYTES",
]

MAX_READ_BYTES = 4 * 2**30
"""The largest array (bytes, as float32 or the file's own type if wider) a reader will
allocate: 4 GiB. A header declaring more is refused before anything is read, since a
damaged or crafted header can declare terabytes. Raise it for a genuinely larger file,
per call (``max_bytes=``) or for the session (``diffcam.io.MAX_READ_BYTES = 2**36``)."""

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


def read_image(path: str | os.PathLike, *, channel_order: str | None = None,
               max_bytes: int | None = None) -> Capture:
    """Read a PNG, TIFF or ``.npy`` capture.

    Args:
        path: file to read (``.png``, ``.tif``/``.tiff``, ``.npy``).
        channel_order: for colour data, the order of the file's channel axis, e.g.
            ``"BGR"`` for arrays saved by OpenCV (the DiffuserCam/LenslessLearning
            ``.npy`` files). PNG and TIFF colour is ``"RGB"`` (or ``"RGBA"``) by the
            format, which is the default there; a colour ``.npy`` has no such rule and
            needs it.
        max_bytes: refuse an image whose header declares more than this many bytes
            (counted as float32, or the file's type if wider); default
            :data:`MAX_READ_BYTES`. Checked before any pixel is read.

    Returns:
        :class:`Capture` with the channel axis moved first.

    Raises:
        DiffcamError: missing, empty, corrupt, truncated, oversized or unsupported
            files; NaN/Inf values; a colour ``.npy`` without ``channel_order``; a 16-bit
            colour PNG (which Pillow would silently reduce to 8 bits).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in _IMAGE_SUFFIXES:
        raise DiffcamError(f"{path}: unsupported file type {suffix!r}; diffcam reads "
                           f"{', '.join(_IMAGE_SUFFIXES)} images and .mat PSF stacks "
                           f"(read_mat_stack).")
    _check_file(path)
    limit = _limit(max_bytes)
    read = {".png": _read_png, ".tif": _read_tiff, ".tiff": _read_tiff, ".npy": _read_npy}
    with _file_errors(path, f"as {suffix[1:].upper()}"):
        data = read[suffix](path, limit)
    return _to_capture(data, path, suffix, channel_order)


def as_rgb(capture: Capture) -> np.ndarray:
    """A colour capture's image as float32 ``(3, ny, nx)`` in R, G, B order, whatever
    the file's order (``capture.channels``).

    Raises:
        DiffcamError: the capture is grayscale or a stack, or has an alpha channel.
    """
    if capture.channels is None:
        raise DiffcamError(f"{capture.path}: expected a colour image (ny, nx, 3), got shape "
                           f"{capture.image.shape}; give a colour capture, or read it as "
                           f"grayscale.")
    if sorted(capture.channels) != ["B", "G", "R"]:
        raise DiffcamError(f"{capture.path}: channels {''.join(capture.channels)}; expected "
                           f"R, G and B (drop the alpha channel first).")
    return capture.image[[capture.channels.index(c) for c in "RGB"]]


def read_rgb(path: str | os.PathLike, *, channel_order: str | None = None) -> np.ndarray:
    """:func:`read_image` then :func:`as_rgb`: float32 ``(3, ny, nx)``, R, G, B
    (``channel_order`` is the file's, e.g. ``"BGR"``)."""
    return as_rgb(read_image(path, channel_order=channel_order))


IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
"""Suffixes of the single-plane images a folder or glob of PSFs may hold."""


def natural_key(path) -> list:
    """Sort key of a file name with its digit runs compared as numbers (9 < 10)."""
    return [int(part) if part.isdigit() else part.lower()
            for part in re.split(r"(\d+)", Path(path).name)]


def image_files(source: str | os.PathLike) -> list[Path] | None:
    """The single-plane image files (:data:`IMAGE_SUFFIXES`) of a folder or a glob
    pattern, in natural order (``psf_9`` before ``psf_10``); ``None`` when ``source`` is
    neither (one file).

    Raises:
        DiffcamError: an empty folder, or a pattern matching no file.
    """
    source = str(source)
    path = Path(source)
    if path.is_dir():
        files = [p for p in path.iterdir()
                 if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
        if not files:
            raise DiffcamError(f"{source}: the folder holds no "
                               f"{', '.join(IMAGE_SUFFIXES)} images.")
    elif any(c in source for c in "*?[") and not path.exists():
        files = [Path(p) for p in glob.glob(source) if Path(p).is_file()]
        if not files:
            raise DiffcamError(f"{source}: no files match this pattern.")
    else:
        return None
    return sorted(files, key=natural_key)


def read_psf_stack(paths: Sequence[str | os.PathLike], *,
                   max_bytes: int | None = None) -> np.ndarray:
    """Read one PSF per file (sorted as given) into a float32 stack ``(nz, my, mx)``.

    ``max_bytes`` bounds each file, as in :func:`read_image`.

    Raises:
        ShapeError: if the files differ in shape or hold colour/stacks.
        DiffcamError: a file cannot be read (see :func:`read_image`).
    """
    if isinstance(paths, (str, bytes, os.PathLike)):
        raise DiffcamError(f"read_psf_stack takes a list of files, one per depth, got the "
                           f"single path {paths!r}; use read_image for one file.")
    if len(paths) == 0:
        raise ShapeError("no PSF files given; pass one file per depth, e.g. "
                         "sorted(Path('psf').glob('psf*.tiff')).")
    planes = [read_image(p, max_bytes=max_bytes) for p in paths]
    shapes = {c.image.shape for c in planes}
    if len(shapes) != 1 or planes[0].image.ndim != 2:
        raise ShapeError(f"PSF files must all be grayscale images of one shape, got "
                         f"{sorted(shapes)}; crop them to a common size first.")
    return np.stack([c.image for c in planes])


def read_mat_stack(path: str | os.PathLike, key: str | None = None, *,
                   max_bytes: int | None = None) -> np.ndarray:
    """Read a DiffuserCam-style PSF stack from a MATLAB ``.mat`` file.

    MATLAB stores the stack as ``(y, x, z)``; it is returned as float32 ``(z, y, x)``.
    Files up to v7.2 are read with ``scipy.io.loadmat``; v7.3 files are HDF5 and read
    with ``h5py`` (which sees MATLAB's column-major arrays with their axes reversed).

    Args:
        path: the ``.mat`` file.
        key: variable name; default the only non-metadata variable (DiffuserCam calls
            it ``psf``).
        max_bytes: refuse a variable declaring more bytes than this (see
            :func:`read_image`); default :data:`MAX_READ_BYTES`.

    Raises:
        DiffcamError: missing, corrupt, truncated or oversized files, a missing or
            ambiguous variable, non-numeric or complex data, NaN/Inf values.
    """
    path = Path(path)
    _check_file(path)
    limit = _limit(max_bytes)
    import h5py
    with _file_errors(path, "as a MATLAB file"):
        if h5py.is_hdf5(path):
            with h5py.File(path, "r") as f:
                names = [k for k in f.keys() if not k.startswith("#")]
                key = _pick_key(path, names, key)
                item = f[key]
                if not isinstance(item, h5py.Dataset):
                    raise DiffcamError(f"{path}: variable {key!r} is not an array (an HDF5 "
                                       f"{type(item).__name__}); expected a PSF stack.")
                _check_declared(path, f"variable {key!r}", item.shape, item.dtype, limit)
                data = np.asarray(item[()])
            data = np.transpose(data)  # h5py sees MATLAB's column-major (y, x, z) as (z, x, y)
        else:
            import scipy.io
            variables = {name: (shape, cls) for name, shape, cls in scipy.io.whosmat(path)}
            key = _pick_key(path, list(variables), key)
            shape, cls = variables[key]
            _check_declared(path, f"variable {key!r}", shape,
                            np.dtype(_MATLAB_ITEMSIZE.get(cls, np.float64)), limit)
            contents = scipy.io.loadmat(path, variable_names=[key])
            if key not in contents:
                raise DiffcamError(f"{path}: variable {key!r} is listed but cannot be read; "
                                   f"the file may be truncated — copy it again.")
            data = np.asarray(contents[key])
    if data.ndim == 2:
        data = data[:, :, None]
    if data.ndim != 3 or not (np.issubdtype(data.dtype, np.integer)
                              or np.issubdtype(data.dtype, np.floating)):
        raise ShapeError(f"{path}: variable {key!r} has shape {data.shape} and dtype "
                         f"{data.dtype}; expected a real numeric (y, x, z) PSF stack.")
    if 0 in data.shape:
        raise DiffcamError(f"{path}: variable {key!r} is empty (shape {data.shape}).")
    _check_values(data, path)
    with np.errstate(over="ignore"):
        stack = np.ascontiguousarray(np.moveaxis(data, -1, 0), dtype=np.float32)
    if not np.isfinite(stack).all():
        raise DiffcamError(f"{path}: values beyond the float32 range (max |value| "
                           f"{float(np.abs(data).max()):.3g}); rescale the data first.")
    return stack


def read_npz(path: str | os.PathLike, keys: Sequence[str], *, what: str = "an .npz file",
             max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """Read the arrays ``keys`` from an ``.npz`` file, with every failure a DiffcamError.

    Pickled (object) arrays are refused. Each member's declared (uncompressed) size is
    checked against ``max_bytes`` (default :data:`MAX_READ_BYTES`) before it is read, so
    a damaged header or a zip bomb cannot allocate more.

    Args:
        path: the file.
        keys: the array names it must hold.
        what: how to name the file in messages, e.g. ``"a diffcam phase file"``.
        max_bytes: the size limit per array, bytes.

    Returns:
        ``{key: array}``, the arrays as stored (any dtype and shape: check them).
    """
    path = Path(path)
    limit = _limit(max_bytes)
    members = _npz_members(path, what)
    with _file_errors(path, f"as {what}"):
        names = sorted(n[:-4] for n in members if n.endswith(".npy"))
        missing = [k for k in keys if k + ".npy" not in members]
        if missing:
            raise DiffcamError(f"{path}: not {what}: no array {missing[0]!r} (it holds "
                               f"{names}).")
        for k in keys:
            size = members[k + ".npy"].file_size
            if size > limit:
                raise DiffcamError(f"{path}: array {k!r} declares {_fmt_bytes(size)}, more "
                                   f"than the read limit {_fmt_bytes(limit)} (max_bytes, "
                                   f"diffcam.io.MAX_READ_BYTES); the file may be damaged.")
        with np.load(path, allow_pickle=False) as arrays:
            return {k: np.asarray(arrays[k]) for k in keys}


def npz_keys(path: str | os.PathLike, *, what: str = "an .npz file") -> list[str]:
    """The names of the arrays an ``.npz`` file holds, read from its zip directory only
    (nothing is decompressed); every failure a DiffcamError naming ``what``."""
    return sorted(n[:-4] for n in _npz_members(Path(path), what) if n.endswith(".npy"))


def _npz_members(path: Path, what: str) -> dict[str, zipfile.ZipInfo]:
    """The zip directory of ``path``: ``{member name: ZipInfo}``."""
    _check_file(path)
    if not zipfile.is_zipfile(path):
        kind = file_kind(path)
        found = f"it is {kind}" if kind else "not an .npz/zip archive; it may be truncated"
        raise DiffcamError(f"{path}: not {what} ({found}).")
    with _file_errors(path, f"as {what}"):
        with zipfile.ZipFile(path) as archive:
            return {info.filename: info for info in archive.infolist()}


_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "a PNG image"), (b"II*\x00", "a TIFF image"),
               (b"MM\x00*", "a TIFF image"), (b"II+\x00", "a BigTIFF image"),
               (b"MM\x00+", "a BigTIFF image"), (b"\x93NUMPY", "a NumPy .npy array"),
               (b"\xff\xd8\xff", "a JPEG image"), (b"\x89HDF\r\n\x1a\n",
                                                    "an HDF5 file (MATLAB v7.3?)"),
               (b"MATLAB", "a MATLAB .mat file"), (b"\x1f\x8b", "a gzip file"),
               (b"PK\x03\x04", "a zip archive"), (b"%PDF", "a PDF document"))


def file_kind(path: str | os.PathLike) -> str | None:
    """What a file's first bytes say it is (``"a PNG image"``, ``"a TIFF image"``, …),
    whatever its name; ``None`` when they match no format known here."""
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return None
    return next((kind for magic, kind in _SIGNATURES if head.startswith(magic)), None)


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
    _check_values(image, "image")
    _check_values(background, "background")
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


# ---------------------------------------------------------------------------- writing

def check_output_path(path: str | os.PathLike, *,
                      suffixes: Sequence[str] | None = None) -> Path:
    """Check that a file can be written at ``path``; call it before any work starts.

    An output problem should cost nothing: a stack that took an hour to compute must
    not fail at its first write. The checks are: ``path`` is not a folder, its folder
    exists and is a folder, a new file can be created in it (a probe file is created and
    removed, which also catches read-only file systems and root on them), and an
    existing file there is a regular, writable file.

    Args:
        path: the output file.
        suffixes: if given, the accepted file name endings, e.g. ``(".npz",)``.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        DiffcamError: naming the path and what is wrong with it.
    """
    try:
        path = Path(os.fspath(path))
    except TypeError:
        raise DiffcamError(f"an output path must be a str or os.PathLike, got "
                           f"{path!r}.") from None
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise DiffcamError(f"{path}: the output must end in {' or '.join(suffixes)}.")
    if path.is_dir():
        raise DiffcamError(f"{path}: is a folder; give a file name inside it.")
    target = Path(os.path.realpath(path))  # a symlink is written through, not replaced
    folder = target.parent
    if not folder.exists():
        raise DiffcamError(f"{path}: the output folder {folder} does not exist; create it "
                           f"first.")
    if not folder.is_dir():
        raise DiffcamError(f"{path}: {folder} is not a folder.")
    if target.exists():
        if not target.is_file():
            raise DiffcamError(f"{path}: exists and is not a regular file; remove it or "
                               f"choose another name.")
        # the mode bits too: os.access says yes to root for a read-only file
        if not os.access(target, os.W_OK) or not target.stat().st_mode & 0o222:
            raise DiffcamError(f"{path}: the existing file is read-only; diffcam will not "
                               f"replace it. Make it writable or choose another name.")
    try:
        os.close(_create_temp(target, probe=True)[0])
    except OSError as err:
        raise DiffcamError(f"{path}: cannot create files in {folder} "
                           f"({err.strerror or err}); choose another folder or fix its "
                           f"permissions.") from None
    return path


@contextlib.contextmanager
def atomic_output(*paths: str | os.PathLike) -> Iterator:
    """Write files so that each target is either untouched or wholly replaced.

    Yields a temporary path beside each target (in the same folder, with the target's
    suffix, so writers that dispatch on it work): one path for one target, a tuple for
    several. When the block ends normally every temporary file is fsynced and moved
    over its target with ``os.replace`` (atomic on POSIX and Windows), then the folder
    is fsynced. If the block raises anything, ``KeyboardInterrupt`` included, the
    temporary files are removed and the targets keep their old bytes.

    SIGTERM: while the block runs in the main thread and SIGTERM has its default
    action, a SIGTERM raises :class:`Terminated` inside the block instead of killing the
    process at once; the temporary files are removed, the default action is restored
    and the signal is raised again, so the process still ends as killed by SIGTERM. A
    SIGTERM that arrives while the files are being moved into place waits until they
    are (several targets are replaced one after another in that window, so only a hard
    kill can fall between them). Nothing is installed outside the block; a handler of the caller's is left
    alone. A hard kill (SIGKILL, power loss) can leave a temporary ``.name.tmp-*``
    file, never a half-written target.

    New files get the permissions ``0o666 & ~umask``, like any file ``open`` creates.

    Raises:
        DiffcamError: a target cannot be written (:func:`check_output_path`), before
            the block runs.
    """
    if not paths:
        raise DiffcamError("atomic_output needs at least one output path.")
    targets = [Path(os.path.realpath(check_output_path(p))) for p in paths]
    guard = _TermGuard.install()
    temps: list[Path] = []
    try:
        try:
            for target in targets:
                fd, temp = _create_temp(target)
                os.close(fd)
                temps.append(temp)
            yield temps[0] if len(temps) == 1 else tuple(temps)
            if guard is not None:
                guard.deferring = True  # a SIGTERM now waits until the files are in place
                if guard.received:  # the block swallowed Terminated: its output is partial
                    raise Terminated()
            for temp in temps:
                _fsync(temp)
            for temp, target in zip(temps, targets):
                os.replace(temp, target)
            for folder in dict.fromkeys(t.parent for t in targets):
                _fsync(folder)
        except BaseException:
            if guard is not None:
                guard.deferring = True
            for temp in temps:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(temp)
            raise
    finally:
        if guard is not None:
            guard.restore()


class Terminated(SystemExit):
    """SIGTERM arrived while :func:`atomic_output` was writing.

    A ``SystemExit`` (exit status 143, as a shell reports SIGTERM), so ``except
    Exception`` does not swallow it. :func:`atomic_output` re-raises the signal itself
    once its temporary files are gone, so this is seen only if that signal is blocked.
    """

    def __init__(self) -> None:
        super().__init__(128 + signal.SIGTERM)


class _TermGuard:
    """SIGTERM as :class:`Terminated` for the duration of one :func:`atomic_output`."""

    def __init__(self) -> None:
        self.deferring = False  # cleaning up or committing: record, do not raise
        self.received = False

    @classmethod
    def install(cls) -> "_TermGuard | None":
        if threading.current_thread() is not threading.main_thread():
            return None  # signal handlers can only be set from the main thread
        if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
            return None  # the caller (or an outer atomic_output) handles SIGTERM
        guard = cls()
        signal.signal(signal.SIGTERM, guard._handle)
        guard._dropped = _redeliver_dropped(Terminated, guard._again)
        guard._dropped.__enter__()
        return guard

    def _handle(self, signum, frame) -> None:
        first = not self.received
        self.received = True
        if first and not self.deferring:
            self.deferring = True
            raise Terminated()

    def _again(self) -> None:
        """Python dropped the :class:`Terminated` raised by :meth:`_handle`: as if the
        signal had not come yet, and it comes again."""
        self.received = self.deferring = False
        _send_again(signal.SIGTERM)

    def restore(self) -> None:
        self._dropped.__exit__(None, None, None)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        if self.received:
            signal.raise_signal(signal.SIGTERM)  # now with its default action: exit


@contextlib.contextmanager
def interrupts_as_keyboard_interrupt() -> Iterator[None]:
    """SIGINT raises ``KeyboardInterrupt`` as Python's default handler does, and a
    ``KeyboardInterrupt`` that Python drops is delivered again (:func:`_redeliver_dropped`).
    Installed only from the main thread and only over Python's default handler."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    with _redeliver_dropped(KeyboardInterrupt, lambda: _send_again(signal.SIGINT)):
        yield


@contextlib.contextmanager
def _redeliver_dropped(kind: type[BaseException], again) -> Iterator[None]:
    """While the block runs, an exception of ``kind`` that Python prints as "Exception
    ignored" and drops calls ``again()`` instead of being printed.

    A signal handler's exception is dropped so when the signal lands in a garbage-
    collector callback (JAX registers one), a ``__del__`` or a weakref callback; the run
    would then go on as if no signal had come (seen in CI). ``again`` sends it anew.
    """
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, kind):
            again()
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _send_again(signum: int) -> None:
    """Send ``signum`` to the main thread in 50 ms (after the code that dropped it).

    To the thread, not the process: the kernel may hand a process's signal to any of
    its threads (XLA's among them), and a blocking call in the main thread then runs to
    its end before Python's handler runs (a test's 2 s sleep, once in a full run)."""
    if hasattr(signal, "pthread_kill"):
        send = partial(signal.pthread_kill, threading.main_thread().ident, signum)
    else:  # Windows
        send = partial(os.kill, os.getpid(), signum)
    timer = threading.Timer(0.05, send)
    timer.daemon = True
    timer.start()


def _create_temp(target: Path, *, probe: bool = False) -> tuple[int, Path]:
    """Create an empty file beside ``target`` with mode ``0o666 & ~umask`` (unlike
    ``tempfile.mkstemp``'s 0o600). A probe is removed at once."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        kind = "probe" if probe else "tmp"
        temp = target.with_name(f".{target.stem}.{kind}-{secrets.token_hex(4)}{target.suffix}")
        try:
            fd = os.open(temp, flags, 0o666)
        except FileExistsError:
            continue
        if probe:
            os.unlink(temp)
        return fd, temp
    raise FileExistsError(f"no free temporary name beside {target}")


def temporary_files(target: str | os.PathLike) -> set[Path]:
    """The temporary files :func:`atomic_output` has beside ``target`` now: a hard-killed
    writer leaves its own behind, and whoever ran it (a launcher of several processes)
    removes the ones that were not there before."""
    target = Path(os.path.realpath(target))
    hex8 = "[0-9a-f]" * 8  # secrets.token_hex(4), as _create_temp names them
    pattern = f".{glob.escape(target.stem)}.tmp-{hex8}{glob.escape(target.suffix)}"
    return set(target.parent.glob(pattern))


def _fsync(path: Path) -> None:
    """Flush a file's (or a folder's entries') data to the disk, where the OS allows."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_BINARY", 0))
    except OSError:  # folders cannot be opened on Windows
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems refuse fsync on a folder
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------- reading

_MATLAB_ITEMSIZE = {"double": np.float64, "single": np.float32, "int8": np.int8,
                    "uint8": np.uint8, "int16": np.int16, "uint16": np.uint16,
                    "int32": np.int32, "uint32": np.uint32, "int64": np.int64,
                    "uint64": np.uint64, "logical": np.uint8}
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # PNG colour type -> samples per pixel


def _check_file(path: Path) -> None:
    if path.is_dir():
        raise DiffcamError(f"{path}: is a folder, not a file.")
    if not path.is_file():
        raise DiffcamError(f"{path}: no such file.")
    if path.stat().st_size == 0:
        raise DiffcamError(f"{path}: the file is empty (0 bytes); copy it again.")


def _limit(max_bytes) -> int:
    limit = MAX_READ_BYTES if max_bytes is None else max_bytes
    if isinstance(limit, bool) or not isinstance(limit, (int, np.integer)) or limit <= 0:
        raise DiffcamError(f"max_bytes must be a positive integer (bytes), got {limit!r}.")
    return int(limit)


def _fmt_bytes(n: int) -> str:
    for unit, scale in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def check_read_size(path, what: str, shape, dtype, max_bytes: int | None = None) -> None:
    """Refuse to read ``shape``×``dtype`` declared by a header of ``path`` when it exceeds
    ``max_bytes`` (default :data:`MAX_READ_BYTES`): a DiffcamError saying how big."""
    _check_declared(Path(path), what, shape, dtype, _limit(max_bytes))


def _check_declared(path: Path, what: str, shape, dtype, limit: int) -> None:
    """Refuse ``shape``×``dtype`` (as declared by a header) above ``limit`` bytes, counted
    at the larger of the file's item size and float32 (what the reader returns)."""
    count = 1
    for n in shape:
        count *= int(n)  # Python ints: a crafted header cannot overflow this
    need = count * max(np.dtype(dtype).itemsize, 4)
    if need > limit:
        raise DiffcamError(
            f"{path}: {what} declares shape {tuple(int(n) for n in shape)} of "
            f"{np.dtype(dtype)} ({_fmt_bytes(need)} to read), more than the read limit "
            f"{_fmt_bytes(limit)} (max_bytes=, diffcam.io.MAX_READ_BYTES); the header may "
            f"be corrupt, or raise the limit for a file this large.")


def _reason(err: BaseException) -> str:
    """An exception as one short line: its type and the first line of its message."""
    text = str(err).strip().splitlines()
    line = f"{type(err).__name__}: {text[0]}" if text else type(err).__name__
    return line if len(line) <= 160 else line[:157] + "..."


@contextlib.contextmanager
def _file_errors(path: Path, how: str) -> Iterator[None]:
    """Turn whatever a third-party parser raises on a damaged file into one DiffcamError
    line (the parsers raise struct, zlib, zip, index, key, memory and many other errors)."""
    try:
        yield
    except DiffcamError:
        raise
    except Exception as err:  # noqa: BLE001 - the parsers' error types are not a contract
        raise DiffcamError(f"{path}: could not be read {how} ({_reason(err)}); the file may "
                           f"be truncated or corrupt — copy it again.") from None


def _read_tiff(path: Path, limit: int) -> np.ndarray:
    import tifffile
    with tifffile.TiffFile(path) as tif:
        if not tif.series:
            raise DiffcamError(f"{path}: the TIFF holds no image.")
        series = tif.series[0]
        _check_declared(path, "the TIFF", series.shape, series.dtype, limit)
        return np.asarray(series.asarray())


def _read_npy(path: Path, limit: int) -> np.ndarray:
    # a memory map reads only the header; the data are copied once the size is known
    mapped = np.load(path, mmap_mode="r", allow_pickle=False)
    _check_declared(path, "the array", mapped.shape, mapped.dtype, limit)
    return np.array(mapped)


def _pick_key(path: Path, names: list[str], key: str | None) -> str:
    if key is not None:
        if key not in names:
            raise DiffcamError(f"{path}: no variable {key!r}; it holds {names}.")
        return key
    if len(names) != 1:
        raise DiffcamError(f"{path}: holds variables {names}; say which one with key=...")
    return names[0]


def _read_png(path: Path, limit: int) -> np.ndarray:
    from PIL import Image
    with open(path, "rb") as f:
        header = f.read(33)
    if len(header) < 29 or header[:8] != b"\x89PNG\r\n\x1a\n" or header[12:16] != b"IHDR":
        raise DiffcamError(f"{path}: not a PNG file (bad signature); is it another format "
                           f"with a .png name, or truncated?")
    width, height = struct.unpack(">II", header[16:24])
    bit_depth, colour_type = header[24], header[25]
    if bit_depth == 16 and colour_type in (2, 4, 6):
        raise DiffcamError(f"{path}: 16-bit colour PNG; Pillow would reduce it to 8 bits. "
                           f"Convert it to a 16-bit TIFF (e.g. with tifffile) or .npy.")
    if colour_type == 4:
        raise DiffcamError(f"{path}: grayscale PNG with an alpha channel; a capture should "
                           f"be grayscale or RGB — re-save it without alpha.")
    _check_declared(path, "the PNG", (height, width, _PNG_CHANNELS.get(colour_type, 4)),
                    np.uint16 if bit_depth == 16 else np.uint8, limit)
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
    _check_values(data, path)
    with np.errstate(over="ignore"):
        image = np.ascontiguousarray(data, dtype=np.float32)
    if not np.isfinite(image).all():
        raise DiffcamError(f"{path}: values beyond the float32 range (max |value| "
                           f"{float(np.abs(data).max()):.3g}); rescale the data first.")
    return Capture(image=image, channels=channels, full_scale=full_scale, path=str(path))


def _check_values(arr: np.ndarray, where) -> None:
    """Raise a DiffcamError naming ``where`` (a file or an argument) if ``arr`` holds
    NaN or Inf."""
    finite = np.isfinite(arr)
    if not finite.all():
        raise DiffcamError(f"{where}: {int(arr.size - finite.sum())} NaN/Inf value(s); "
                           f"clean the data (np.nan_to_num) or mask those pixels first.")
