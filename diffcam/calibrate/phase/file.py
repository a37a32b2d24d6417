"""Save and load a retrieved diffuser phase with what it means (``.npz``, versioned).

A phase file holds θd (radians, float32, on a centred grid) and the numbers needed to
use it: the grid pitch, the wavelength it is a phase at, the aperture, and how it was
obtained. ``diffcam calibrate`` writes one; ``diffcam psf`` and ``diffcam compare``
read it.

Writing is atomic (`diffcam.io.atomic_output`): a failed or interrupted save
leaves an existing file byte for byte as it was. Reading turns every damaged file into
one `DiffcamError` line naming the file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
from dataclasses import dataclass, field

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, check_finite, check_positive
from diffcam.io import atomic_output, check_output_path, read_npz

__all__ = ["PhaseFile", "save_phase", "load_phase", "PHASE_FORMAT_VERSION"]

PHASE_FORMAT_VERSION = 1
_LENGTHS = ("dx", "wavelength", "aperture_radius")
_HINT = "write one with `diffcam calibrate` or diffcam.calibrate.save_phase"


@dataclass(frozen=True)
class PhaseFile:
    """A diffuser phase and its metadata (SI units).

    Attributes:
        phase: θd, radians, ``(ny, nx)``, index ``(ny//2, nx//2)`` on the optical axis.
        dx: grid pitch, metres per sample.
        wavelength: the wavelength θd is a phase at, metres.
        aperture_radius: metres.
        info: how it was obtained (solver, iterations, focal length, near distance,
            whether the twin was resolved, ...): JSON-able; NumPy scalars and arrays
            are stored as the equivalent numbers and lists.
    """

    phase: np.ndarray
    dx: float
    wavelength: float
    aperture_radius: float
    info: dict = field(default_factory=dict)
    format_version: int = PHASE_FORMAT_VERSION


def save_phase(path: str | os.PathLike, phase_file: PhaseFile) -> None:
    """Write ``phase_file`` to ``path`` (``.npz``; the round trip is exact).

    The path is checked first
    ([`diffcam.io.check_output_path`][diffcam.io.writing.check_output_path]), then the phase
    and the metadata are validated and serialised, and only then is anything written,
    atomically: an existing file at ``path`` is either untouched or wholly replaced.

    Raises:
        DiffcamError: an unwritable path, a phase that is not a finite 2-D array,
            lengths that are not positive numbers (metres), or ``info`` that cannot be
            stored as JSON.
    """
    if not os.fspath(path).endswith(".npz"):
        raise DiffcamError(f"phase files are .npz, got {path!r}.")
    path = check_output_path(path)
    phase = np.asarray(phase_file.phase)
    if phase.ndim != 2 or 0 in phase.shape:
        raise ShapeError(f"phase must be a non-empty 2-D array (ny, nx), got shape "
                         f"{phase.shape}.")
    if not (np.issubdtype(phase.dtype, np.floating) or np.issubdtype(phase.dtype, np.integer)):
        raise DiffcamError(f"phase must be real radians, got dtype {phase.dtype}.")
    check_finite("phase", phase)
    phase = phase.astype(np.float32)
    meta = {}
    for name in _LENGTHS:
        value = getattr(phase_file, name)
        check_positive(name, value, "m")
        if np.size(value) != 1:
            raise DiffcamError(f"{name} must be one number in metres, got {value!r}.")
        meta[name] = float(np.asarray(value).reshape(()))
    if not isinstance(phase_file.info, dict):
        raise DiffcamError(f"info must be a dict of JSON-able values, got "
                           f"{type(phase_file.info).__name__}.")
    meta["info"] = phase_file.info
    version = phase_file.format_version
    if isinstance(version, bool) or not isinstance(version, (int, np.integer)):
        raise DiffcamError(f"format_version must be an integer, got {version!r}.")
    meta["format_version"] = int(version)
    try:
        text = json.dumps(meta, default=_plain)
    except (TypeError, ValueError) as err:
        raise DiffcamError(f"info cannot be stored in a phase file ({err}); give plain "
                           f"numbers, strings, lists and dicts. Nothing was written to "
                           f"{path}.") from None
    with atomic_output(path) as temp, open(temp, "wb") as fh:
        np.savez(fh, phase=phase, meta=np.array(text))


def load_phase(path: str | os.PathLike) -> PhaseFile:
    """Read a phase file written by [`save_phase`][diffcam.calibrate.phase.file.save_phase].

    Raises:
        DiffcamError: a missing, truncated or corrupt file, one without the phase or
            its metadata, a newer format, or values that are not a valid phase file
            (non-finite or non-2-D phase, non-positive lengths).
    """
    arrays = read_npz(path, ("phase", "meta"), what="a diffcam phase file")
    phase, meta = arrays["phase"], arrays["meta"]
    if meta.shape != () or meta.dtype.kind not in "US":
        raise DiffcamError(f"{path}: not a diffcam phase file (its metadata is not "
                           f"text); {_HINT}.")
    try:
        meta = json.loads(str(meta))
    except ValueError as err:
        raise DiffcamError(f"{path}: the phase file's metadata is not valid JSON "
                           f"({err}); {_HINT}.") from None
    if not isinstance(meta, dict):
        raise DiffcamError(f"{path}: the phase file's metadata is not a JSON object; {_HINT}.")
    version = meta.get("format_version", 0)
    if not isinstance(version, int) or isinstance(version, bool):
        raise DiffcamError(f"{path}: format_version {version!r} is not an integer; {_HINT}.")
    if version > PHASE_FORMAT_VERSION:
        raise DiffcamError(f"{path}: phase format {version} is newer than this "
                           f"diffcam reads ({PHASE_FORMAT_VERSION}); upgrade diffcam.")
    known = {f.name for f in dataclasses.fields(PhaseFile)} - {"phase"}
    unknown = sorted(set(meta) - known)
    missing = [k for k in _LENGTHS if k not in meta]
    if unknown or missing:
        what = f"unknown fields {unknown}" if unknown else f"no {missing[0]!r}"
        raise DiffcamError(f"{path}: not a diffcam phase file ({what}); {_HINT}.")
    for name in _LENGTHS:
        value = meta[name]
        if (not isinstance(value, numbers.Real) or isinstance(value, bool)
                or not math.isfinite(value) or value <= 0):
            raise DiffcamError(f"{path}: {name} must be a positive length in metres, got "
                               f"{value!r}.")
    if not isinstance(meta.get("info", {}), dict):
        raise DiffcamError(f"{path}: info must be a JSON object, got "
                           f"{type(meta['info']).__name__}.")
    if phase.ndim != 2 or 0 in phase.shape or not np.issubdtype(phase.dtype, np.floating):
        raise DiffcamError(f"{path}: the phase must be a non-empty 2-D float array, got "
                           f"shape {phase.shape} of {phase.dtype}.")
    finite = np.isfinite(phase)
    if not finite.all():
        raise DiffcamError(f"{path}: the phase holds {int(finite.size - finite.sum())} "
                           f"NaN/Inf value(s); the file is damaged.")
    return PhaseFile(phase=phase, **meta)


def _plain(value):
    """JSON for NumPy (and JAX) numbers and arrays in ``info``: ``np.int64(3)`` -> 3."""
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "__array__") and hasattr(value, "shape"):
        return np.asarray(value).tolist()
    raise TypeError(f"{type(value).__name__} {value!r:.60} is not JSON-able")
