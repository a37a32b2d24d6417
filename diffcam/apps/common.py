"""What the ``diffcam`` subcommands share: argparse types (lengths with units, checked
counts, plane lists), the parser whose usage errors are one line, the ``--help``
formatter and the limits each help states, image
and figure writers, and the PSF readers. The command modules (`cli`,
`fit_cli`, `reconstruct_cli`,
`scene_psf_cli`, `demo`) import from here, never
from each other's private names."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam.core.units import parse_length, parse_length_range
from diffcam import model  # lazy: loaded on use
from diffcam.core.lazy import module_constant
from diffcam.io import (MAX_READ_BYTES, atomic_output, make_output_folder, read_image,
                        read_mat_stack)


def _units(parse, name):
    """An argparse type that reads lengths with units; errors become usage errors."""
    def convert(text):
        try:
            return parse(text, name=name)
        except DiffcamError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    convert.__name__ = name
    return convert


class Parser(argparse.ArgumentParser):
    """A subcommand's parser: a usage error is one line, ``diffcam CMD: error: …
    (see diffcam CMD --help)``, exit status 2, instead of the whole usage block."""

    def error(self, message):
        option = re.fullmatch(r"argument (--[\w-]+).*: expected one argument", message)
        if option:               # or a value that starts with '-', e.g. --at -40,0
            message += (f"; a value that starts with '-' goes after '=': "
                        f"{option[1]}=-…")
        self.exit(2, f"{self.prog}: error: {message.rstrip('.')} (see {self.prog} "
                     f"--help)\n")


def length_arg(name):
    """An argparse type: one length with a unit (``25mm``), in metres."""
    return _units(parse_length, name)


def lengths_arg(name):
    """An argparse type: lengths with a unit (``25mm``, ``22mm,25mm``, ``22mm:30mm:1mm``),
    in metres."""
    return _units(parse_length_range, name)


def count(low: int, high: int, limit: str = ""):
    """An argparse type: a whole number from ``low`` to ``high``, else a usage error;
    ``limit`` names the constant that sets ``high``. Hostile counts (0, −1, 10⁹) are
    refused while the command line is read, before any work."""
    def convert(text):
        try:
            n = int(text)
        except ValueError:
            n = None
        if n is None or not low <= n <= high:
            raise argparse.ArgumentTypeError(
                f"give a whole number from {low} to {high}{f' ({limit})' if limit else ''}, "
                f"not {text!r:.40}")
        return n
    convert.__name__ = "count"
    return convert


def iterations_count():
    """`count` for an iteration count: 1 to
    `diffcam.reconstruct.checks.MAX_ITERATIONS`."""

    name = "diffcam.reconstruct.checks.MAX_ITERATIONS"
    return count(1, module_constant(name), name)


def grid_count(low: int = 2):
    """`count` for samples per side of a square grid: ``low`` to the side of
    `diffcam.core.grid.MAX_GRID_SAMPLES`."""

    name = "diffcam.core.grid.MAX_GRID_SAMPLES"
    return count(low, math.isqrt(module_constant(name)), name)


def finite_result(path, result: np.ndarray) -> np.ndarray:
    """``result``, unless it holds NaN/Inf (a result beyond float32's range): then a
    DiffcamError naming ``path``, before anything is written there."""
    bad = result.size - int(np.count_nonzero(np.isfinite(result)))
    if bad:
        raise DiffcamError(f"{path}: the result holds {bad} NaN/Inf value(s), so nothing "
                           f"was written; an input scaled beyond float32's range (divide it "
                           f"by a constant) or a solver that diverged (fewer iterations).")
    return result


def save_image(path, image, *, bits: int = 16) -> None:
    """Write an image atomically: ``.png`` (``bits`` 16 or 8, min–max scaled),
    ``.tif``/``.tiff`` (float32, multi-page for a stack), or ``.npy`` (as is)."""
    image = finite_result(path, np.asarray(image, dtype=np.float32))
    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".tif", ".tiff", ".npy"):
        raise DiffcamError(f"{path}: write .png, .tif or .npy, not {suffix!r}.")
    if bits not in (8, 16):
        raise DiffcamError(f"{path}: a PNG holds 8 or 16 bits per pixel, not {bits}.")
    with atomic_output(path) as tmp:
        if suffix == ".png":
            from skimage.io import imsave

            if image.ndim != 2:
                raise DiffcamError(f"{path}: PNG holds one 2-D image, got shape "
                                   f"{image.shape}; write .tif for a stack.")
            lo, hi = float(image.min()), float(image.max())
            scaled = (image - lo) / (hi - lo) if hi > lo else np.zeros_like(image)
            top, dtype = (255, np.uint8) if bits == 8 else (65535, np.uint16)
            imsave(tmp, np.round(scaled * top).astype(dtype), check_contrast=False)
        elif suffix == ".npy":
            np.save(tmp, image)
        else:
            import tifffile

            tifffile.imwrite(tmp, image, imagej=image.ndim == 3)


def save_rgb(path, image) -> None:
    """Write a colour image ``(3, ny, nx)`` (R, G, B) atomically: ``.npy`` float32
    ``(ny, nx, 3)`` as is; ``.png`` 8 bits and ``.tif``/``.tiff`` 16 bits per channel,
    scaled so that the 99.9th percentile of all channels is full scale (the few brighter
    pixels saturate; negatives clip to 0; one scale keeps the colour balance)."""
    image = np.moveaxis(finite_result(path, np.asarray(image, dtype=np.float32)), 0, -1)
    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".tif", ".tiff", ".npy"):
        raise DiffcamError(f"{path}: write .png, .tif or .npy, not {suffix!r}.")
    if image.ndim != 3 or image.shape[-1] != 3:
        raise DiffcamError(f"{path}: a colour image has 3 channels, got shape "
                           f"{np.moveaxis(image, -1, 0).shape}.")
    with atomic_output(path) as tmp:
        if suffix == ".npy":
            np.save(tmp, image)
            return
        top = float(np.percentile(image, 99.9))
        scaled = np.clip(image / top, 0, 1) if top > 0 else np.zeros_like(image)
        if suffix == ".png":
            from skimage.io import imsave

            imsave(tmp, np.round(scaled * 255).astype(np.uint8), check_contrast=False)
        else:
            import tifffile

            tifffile.imwrite(tmp, np.round(scaled * 65535).astype(np.uint16),
                             photometric="rgb")


class DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """``--help`` shows ``(default: X)`` where there is a default to show (not None/off)."""

    def _get_help_string(self, action):
        if action.default is None or action.default is False or action.required \
                or action.default == argparse.SUPPRESS or "default" in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


def save_figure(fig, path) -> None:
    """Lay out ``fig`` (unless it has a layout engine, e.g. ``layout="constrained"``),
    write it atomically to ``path`` (format from the suffix), close it."""
    import matplotlib.pyplot as plt

    if fig.get_layout_engine() is None:
        fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def save_open_figures(stem: str, folder=None) -> list[Path]:
    """Write every open matplotlib figure as ``FOLDER/STEM_k.png`` (k = 1, 2, … in the
    order they were made) with `save_figure`, and close them: how a notebook run
    as a script leaves its figures. ``FOLDER``: ``$DIFFCAM_FIGURES``, else ``figures``
    in the working folder (made if missing)."""
    import matplotlib.pyplot as plt

    folder = make_output_folder(folder or os.environ.get("DIFFCAM_FIGURES") or "figures")
    paths = []
    for k, number in enumerate(plt.get_fignums(), start=1):
        paths.append(folder / f"{stem}_{k}.png")
        save_figure(plt.figure(number), paths[-1])
    return paths


def read_psfs(path):
    """A PSF or PSF stack from an image file, a MATLAB ``.mat`` stack or a stack written
    by diffcam (``.npz``, ``.npy`` with its ``.json``, ``.tif`` with stack metadata);
    returns ``(psfs, depths in metres or None)`` with psfs ``(my, mx)`` or ``(nz, my, mx)``."""

    suffix = Path(path).suffix.lower()
    if suffix == ".mat":
        return read_mat_stack(path), None
    if suffix == ".npz" or (suffix == ".npy" and Path(str(path) + ".json").exists()) or (
            suffix in (".tif", ".tiff") and has_stack_meta(path)):
        stack, meta = model.load_stack(path)
        return np.asarray(stack), np.asarray(meta.depths)
    return read_image(path).image, None


def has_stack_meta(path) -> bool:
    """Whether a TIFF carries diffcam's stack metadata (else it is read as an image)."""
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            return "Info" in (tif.imagej_metadata or {})
    except Exception:  # not a readable TIFF: read_image will say what is wrong
        return False


def parse_planes(text: str) -> list[int]:
    """``"5,25"`` → [5, 25]; ``"0:43"`` → 0 … 43 (both ends included); ``"0:10:2,30"``
    (a step) and mixes of both."""

    items = [_plane_items(item, text) for item in str(text).split(",") if item.strip()]
    n, limit = sum(len(r) for r in items), "diffcam.calibrate.stack.result.MAX_PLANES"
    if n > module_constant(limit):
        raise DiffcamError(f"planes {text!r}: {n} planes, more than the "
                           f"{module_constant(limit)} one run takes ({limit}).")
    out = [t for r in items for t in r]
    if not out:
        raise DiffcamError(f"planes {text!r}: no plane index given.")
    return out


def _plane_items(item: str, text: str) -> range:
    """One comma-separated item of a plane list as a range (not yet expanded)."""
    try:
        if ":" not in item:
            return range(int(item), int(item) + 1)
        parts = [int(p) for p in item.split(":")]
        if len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] <= 0) \
                or parts[1] < parts[0]:
            raise ValueError
        return range(parts[0], parts[1] + 1, parts[2] if len(parts) == 3 else 1)
    except ValueError:
        raise DiffcamError(f"planes {text!r}: give indices as 5,25 or a range 0:43 "
                           f"(both ends included, a ≤ b).") from None


MAX_POSITIONS = 4096
"""Most field positions ``--at`` takes."""


def positions_arg(text: str) -> np.ndarray:
    """An argparse type: field positions ``Y,X;Y,X;…`` in sensor pixels from the axis,
    as an ``(m, 2)`` array."""
    try:
        points = np.array([[float(v) for v in p.split(",")] for p in text.split(";")
                           if p.strip()], dtype=np.float64)
    except ValueError:
        points = np.zeros((0, 0))
    if (points.ndim != 2 or points.shape[1:] != (2,) or not 1 <= len(points) <= MAX_POSITIONS
            or not np.isfinite(points).all()):
        raise argparse.ArgumentTypeError(
            f"give field positions as Y,X pixels from the axis, separated by ';' "
            f"(e.g. '0,0;40,-25'), 1 to {MAX_POSITIONS} of them; got {text!r}")
    return points


def planes_arg(text):
    try:
        return parse_planes(text)
    except DiffcamError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


@contextlib.contextmanager
def one_line_warnings(command: str):
    """Warnings on stderr as one line, ``diffcam COMMAND: warning (Category): message``,
    without Python's file name and source line."""
    shown = warnings.formatwarning
    warnings.formatwarning = lambda message, category, *_, **__: (
        f"diffcam {command}: warning ({category.__name__}): {message}\n")
    try:
        yield
    finally:
        warnings.formatwarning = shown


def limits(command: str) -> str:
    """The resource caps a subcommand enforces before any work, for its ``--help``."""

    caps = [] if command in ("data", "demo", "plan") else [
        f"each array read at most {MAX_READ_BYTES / 2**30:g} GiB (diffcam.io.MAX_READ_BYTES)"]
    if command in ("reconstruct", "predict", "psf", "fit", "compare", "compare-stack"):
        caps.append(_cap("at most {} planes", "diffcam.calibrate.stack.result.MAX_PLANES"))
    if command == "reconstruct":
        caps.append(_cap("at most {} iterations",
                         "diffcam.reconstruct.checks.MAX_ITERATIONS"))
    if command in ("demo", "plan", "calibrate", "psf", "compare"):
        caps.append(_cap("a propagation grid of at most {} samples, padding included",
                         "diffcam.core.grid.MAX_GRID_SAMPLES"))
    said = ("Limits, checked before any work (raise them from Python by assigning to "
            "the constants named): " + "; ".join(caps) + ". ") if caps else ""
    return said + ("Errors are one line on stderr with exit status 2; an existing output "
                   "is replaced whole or not at all.")


def _cap(text: str, limit: str) -> str:
    """``text`` with the value of the constant ``limit`` (dotted), and its name."""
    return f"{text.format(module_constant(limit))} ({limit})"
