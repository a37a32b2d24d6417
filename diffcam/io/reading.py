"""Reading captures and PSF stacks: PNG, TIFF, ``.npy``, MATLAB ``.mat`` and ``.npz``,
every damaged, truncated or oversized file one `DiffcamError`
line naming the file, with the size a header declares checked against
`diffcam.io.MAX_READ_BYTES` before anything is allocated."""

from __future__ import annotations

import contextlib
import glob
import os
import re
import struct
import sys
import zipfile
from pathlib import Path
from typing import Iterator, NamedTuple, Sequence

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError

__all__ = ["Capture", "read_image", "as_rgb", "read_rgb", "IMAGE_SUFFIXES", "natural_key",
           "image_files", "read_psf_stack", "read_mat_stack", "read_npz", "npz_keys",
           "file_kind", "check_read_size"]


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
            [`MAX_READ_BYTES`][diffcam.io.MAX_READ_BYTES]. Checked before any pixel is read.

    Returns:
        [`Capture`][diffcam.io.reading.Capture] with the channel axis moved first.

    Raises:
        DiffcamError: missing, empty, corrupt, truncated, oversized or unsupported
            files; NaN/Inf values; a colour ``.npy`` without ``channel_order``; a 16-bit
            colour PNG (which Pillow would silently reduce to 8 bits).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise DiffcamError(f"{path}: unsupported file type {suffix!r}; diffcam reads "
                           f"{', '.join(IMAGE_SUFFIXES)} images and .mat PSF stacks "
                           f"(read_mat_stack).")
    _check_file(path)
    limit = _limit(max_bytes)
    with _file_errors(path, f"as {suffix[1:].upper()}"):
        data = _READERS[suffix](path, limit)
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
    """[`read_image`][diffcam.io.reading.read_image] then
    [`as_rgb`][diffcam.io.reading.as_rgb]: float32 ``(3, ny, nx)``, R, G, B
    (``channel_order`` is the file's, e.g. ``"BGR"``)."""
    return as_rgb(read_image(path, channel_order=channel_order))


IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
"""Suffixes of the single-plane images diffcam reads
([`read_image`][diffcam.io.reading.read_image]), and that a folder or glob of PSFs may hold."""


def natural_key(path) -> list:
    """Sort key of a file name with its digit runs compared as numbers (9 < 10)."""
    return [int(part) if part.isdigit() else part.lower()
            for part in re.split(r"(\d+)", Path(path).name)]


def image_files(source: str | os.PathLike) -> list[Path] | None:
    """The single-plane image files ([`IMAGE_SUFFIXES`][diffcam.io.reading.IMAGE_SUFFIXES])
    of a folder or a glob pattern, in natural order (``psf_9`` before ``psf_10``); ``None``
    when ``source`` is neither (one file).

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

    ``max_bytes`` bounds each file, as in [`read_image`][diffcam.io.reading.read_image].

    Raises:
        ShapeError: if the files differ in shape or hold colour/stacks.
        DiffcamError: a file cannot be read (see
            [`read_image`][diffcam.io.reading.read_image]).
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
            [`read_image`][diffcam.io.reading.read_image]); default
            [`MAX_READ_BYTES`][diffcam.io.MAX_READ_BYTES].

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
    checked against ``max_bytes`` (default [`MAX_READ_BYTES`][diffcam.io.MAX_READ_BYTES])
    before it is read, so a damaged header or a zip bomb cannot allocate more.

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
    # the package's constant, read at each call: assigning diffcam.io.MAX_READ_BYTES
    # takes effect
    limit = sys.modules["diffcam.io"].MAX_READ_BYTES if max_bytes is None else max_bytes
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
    ``max_bytes`` (default [`MAX_READ_BYTES`][diffcam.io.MAX_READ_BYTES]): a DiffcamError
    saying how big."""
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



_READERS = {".png": _read_png, ".tif": _read_tiff, ".tiff": _read_tiff, ".npy": _read_npy}
