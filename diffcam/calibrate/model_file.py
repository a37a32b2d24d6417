"""The camera-model files, read through one door.

diffcam writes three kinds of camera model, all ``.npz`` with their provenance inside:

- a **phase file** (``diffcam calibrate``, `save_phase`): the
  diffuser phase θd in SI units (grid pitch, wavelength, aperture, how it was
  retrieved). It gives the PSF at any source depth z1 once the diffuser-to-sensor
  distance z2 is given (``diffcam psf PHASE --z1 … --z2 …``);
- a **stack fit** (``diffcam fit``, `save`): the
  field, distance and magnification law fitted to measured planes of a PSF stack, the
  given planes, the fit's history and options. It gives the planes of that stack by
  index (``diffcam predict FIT``); its planes fix z2·M(z1), not z2 and z1 apart;
- a **field-dependent PSF** (``diffcam calibrate-psf --field``,
  `diffcam.model.field.save_field_psf`): kernels at field positions across the
  sensor and their weights, one model per colour channel, at the depth of the scenes
  it was fitted to. ``diffcam reconstruct --psf FIELD`` solves with it.

`model_kind` tells them apart from the file's contents (not its name);
`load_model` reads the first two. ``diffcam psf``, ``predict``, ``compare`` and
``reconstruct`` all take a model file this way, and each says in one line what to do
with the other kind when it needs depths or plane indices that the file cannot give.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from diffcam.calibrate.phase.file import PhaseFile, load_phase
from diffcam.calibrate.stack.result import FORMAT, StackFit, load_stack_fit
from diffcam.core.errors import DiffcamError
from diffcam.io import npz_keys, read_npz

__all__ = ["model_kind", "load_model", "load_stack_model", "not_a_model", "field_psf_refused",
           "MODEL_FILES"]

MODEL_FILES = "a phase file from `diffcam calibrate` or a stack fit from `diffcam fit`"


def model_kind(path: str | os.PathLike) -> str | None:
    """``"phase"``, ``"stack-fit"``, ``"field-psf"``, or ``None`` for anything else (another suffix, a
    missing file, an ``.npz`` of other arrays). Reads the zip directory, and for a
    stack fit its metadata entry; a damaged ``.npz`` raises
    [`DiffcamError`][diffcam.core.errors.DiffcamError]."""
    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.is_file():
        return None
    keys = set(npz_keys(path, what="a diffcam model file"))
    if {"phase", "meta"} <= keys:
        return "phase"
    if {"kernels", "coefficients", "meta"} <= keys:
        return "field-psf"
    if "metadata" not in keys:
        return None
    meta = read_npz(path, ["metadata"], what="a diffcam model file")["metadata"]
    try:
        fmt = json.loads(str(meta[()])).get("format")
    except (ValueError, AttributeError, IndexError):
        return None
    return "stack-fit" if fmt == FORMAT else None


def load_model(path: str | os.PathLike) -> PhaseFile | StackFit:
    """The camera model in ``path``: a [`PhaseFile`][diffcam.calibrate.phase.file.PhaseFile]
    or a [`StackFit`][diffcam.calibrate.stack.result.StackFit].

    Raises:
        DiffcamError: a file of neither kind (one line naming both; a field-dependent
            PSF: the command that takes it), or a damaged or outdated one (the kind's
            own loader's message).
    """
    kind = model_kind(path)
    if kind == "phase":
        return load_phase(path)
    if kind == "stack-fit":
        return load_stack_fit(path)
    if kind == "field-psf":
        raise field_psf_refused(path)
    raise not_a_model(path)


def load_stack_model(path: str | os.PathLike) -> StackFit:
    """`load_model` for what renders planes by index (``diffcam predict``,
    ``compare`` against a stack): a phase file is refused with the command that
    renders it at depths instead."""
    model = load_model(path)
    if isinstance(model, PhaseFile):
        raise DiffcamError(f"{path} is a phase file: it gives PSFs at depths z1, not plane "
                           f"indices; render them with `diffcam psf {path} --z1 … --z2 …`.")
    return model


def field_psf_refused(path: str | os.PathLike) -> DiffcamError:
    """The one-line error for a field-dependent PSF where depths or planes are needed."""
    return DiffcamError(f"{path} is a field-dependent PSF (diffcam calibrate-psf --field): "
                        f"the camera across its field at one depth, not at depths or plane "
                        f"indices; its PSFs across the field: `diffcam psf {path} --at "
                        f"Y,X;…`; reconstruct with it: `diffcam reconstruct RAW --psf {path}`.")


def not_a_model(path: str | os.PathLike) -> DiffcamError:
    """The one-line error for a file that is neither kind of model."""
    if not Path(path).exists():
        return DiffcamError(f"{path}: no such file; give {MODEL_FILES}.")
    return DiffcamError(f"{path}: not a diffcam camera model; give {MODEL_FILES}.")
