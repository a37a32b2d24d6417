"""Save and load a retrieved diffuser phase with what it means (``.npz``, versioned).

A phase file holds θd (radians, float32, on a centred grid) and the numbers needed to
use it: the grid pitch, the wavelength it is a phase at, the aperture, and how it was
obtained. ``diffcam calibrate`` writes one; ``diffcam psf`` and ``diffcam compare``
read it.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field

import numpy as np

from diffcam.core.errors import DiffcamError, ShapeError, check_finite, check_positive

__all__ = ["PhaseFile", "save_phase", "load_phase", "PHASE_FORMAT_VERSION"]

PHASE_FORMAT_VERSION = 1


@dataclass(frozen=True)
class PhaseFile:
    """A diffuser phase and its metadata (SI units).

    Attributes:
        phase: θd, radians, ``(ny, nx)``, index ``(ny//2, nx//2)`` on the optical axis.
        dx: grid pitch, metres per sample.
        wavelength: the wavelength θd is a phase at, metres.
        aperture_radius: metres.
        info: how it was obtained (solver, iterations, focal length, near distance,
            whether the twin was resolved, ...): JSON-able.
    """

    phase: np.ndarray
    dx: float
    wavelength: float
    aperture_radius: float
    info: dict = field(default_factory=dict)
    format_version: int = PHASE_FORMAT_VERSION


def save_phase(path: str | os.PathLike, phase_file: PhaseFile) -> None:
    """Write ``phase_file`` to ``path`` (``.npz``; the round trip is exact)."""
    phase = np.asarray(phase_file.phase, dtype=np.float32)
    if phase.ndim != 2:
        raise ShapeError(f"phase must be 2-D (ny, nx), got shape {phase.shape}.")
    check_finite("phase", phase)
    for name in ("dx", "wavelength", "aperture_radius"):
        check_positive(name, getattr(phase_file, name), "m")
    if not os.fspath(path).endswith(".npz"):
        raise DiffcamError(f"phase files are .npz, got {path!r}.")
    meta = {k: v for k, v in asdict(phase_file).items() if k != "phase"}
    with open(path, "wb") as fh:  # a file object: numpy appends no second suffix
        np.savez(fh, phase=phase, meta=np.array(json.dumps(meta)))


def load_phase(path: str | os.PathLike) -> PhaseFile:
    """Read a phase file written by :func:`save_phase`."""
    try:
        with np.load(path, allow_pickle=False) as f:
            phase, meta = f["phase"], json.loads(str(f["meta"]))
    except FileNotFoundError:
        raise DiffcamError(f"{path}: no such file.") from None
    except (KeyError, ValueError, OSError) as e:
        raise DiffcamError(f"{path}: not a diffcam phase file ({e}); write one with "
                           f"`diffcam calibrate` or diffcam.calibrate.save_phase.") from None
    if meta.get("format_version", 0) > PHASE_FORMAT_VERSION:
        raise DiffcamError(f"{path}: phase format {meta['format_version']} is newer than this "
                           f"diffcam reads ({PHASE_FORMAT_VERSION}); upgrade diffcam.")
    return PhaseFile(phase=phase, **meta)
