"""The design file: one ``.npz`` that holds a diffuser design whole, and the TIFF height
map beside it that a fabrication tool reads.

The ``.npz`` holds the height map in metres (float32, as the PSFs were computed from
it), the surface's parameters, the optimiser's state, the objective's history and a JSON
metadata entry: format name and version, refractive index, pitch, wavelength, z2,
aperture, the depths, the fabrication limits, the settings, the lens table of a
microlens array, and the max cross-depth correlation before and after. It is written
atomically (`diffcam.io.atomic_output`), and it is also the design's checkpoint:
`diffcam.design.optimise.design` continues from it.

The TIFF (same name, ``.tif``) is the height map alone: one float32 page in metres, its
resolution tags set to the pitch (pixels per centimetre), the metadata in its
description.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam.design.result import HISTORY_COLUMNS, Design, DesignOptions
from diffcam.design.surfaces import LensletArray, SmoothSurface, lenslet_table
from diffcam.io import atomic_output, check_output_path, npz_keys, read_npz
from diffcam.model.camera import Camera

__all__ = ["save_design", "load_design", "tiff_path", "FORMAT", "FORMAT_VERSION"]

FORMAT = "diffcam-design"
FORMAT_VERSION = 4
_KINDS = {"smooth": SmoothSurface, "lenslets": LensletArray}
_WHAT = "a diffcam design file"


def tiff_path(path: str | os.PathLike) -> Path:
    """Where the TIFF height map of the design file ``path`` goes: the same name,
    ``.tif``."""
    return Path(path).with_suffix(".tif")


def _kind(surface) -> str:
    return next(k for k, cls in _KINDS.items() if isinstance(surface, cls))


def _statics(surface) -> dict:
    """The surface's fabrication limits and grid (its static fields)."""
    return {f.name: getattr(surface, f.name) for f in dataclasses.fields(surface)
            if f.metadata.get("static")}


def _metadata(design: Design, height: np.ndarray) -> dict:
    cam = design.camera
    if cam.aperture_radius is None:
        raise DiffcamError("a design file records a circular aperture (aperture_radius); "
                           "design with Camera(aperture_radius=…).")
    kind = _kind(design.surface)
    meta = {"format": FORMAT, "version": FORMAT_VERSION, "unit": "m",
            "refractive_index": float(design.refractive_index),
            "camera": {"wavelength": float(cam.wavelength), "z2": float(cam.z2),
                       "dx": float(cam.dx), "aperture_radius": float(cam.aperture_radius),
                       "shape": list(cam.shape), "pad": list(cam.pad),
                       "crop": None if cam.crop is None else list(cam.crop),
                       "method": cam.method, "edge": cam.edge},
            "z1": [float(z) for z in design.z1],
            "surface": {"kind": kind, **_statics(design.surface)},
            "options": dataclasses.asdict(design.options),
            "history_columns": list(HISTORY_COLUMNS), "final": design.final,
            "stop_reason": design.stop_reason, "seconds": float(design.seconds),
            "log_tau": None if design.log_tau is None else float(design.log_tau),
            "height_range": [float(height.min()), float(height.max())]}
    if kind == "lenslets":
        meta["lenses"] = lenslet_table(design.surface, design.refractive_index)
    return meta


def save_design(design: Design, path: str | os.PathLike, *, tiff: bool = True) -> Path:
    """Write ``design`` to ``path`` (``.npz``) and, if ``tiff``, its height map to
    `tiff_path` (float32, metres), both atomically. Returns ``path``.

    Raises:
        DiffcamError: the path cannot be written, or the camera has no circular aperture.
    """
    path = check_output_path(path, suffixes=(".npz",))
    height = np.asarray(design.height_map().height, np.float32)
    meta = _metadata(design, height)
    leaves = jax.tree_util.tree_leaves(design.optimiser_state)
    arrays = {"height": height, "parameters": np.asarray(_parameters(design.surface)),
              "history": np.asarray(design.history, np.float64),
              **{f"optimiser_{i}": np.asarray(v) for i, v in enumerate(leaves)}}
    targets = (path, tiff_path(path)) if tiff else (path,)
    with atomic_output(*targets) as temps:
        temps = (temps,) if not tiff else temps
        with open(temps[0], "wb") as fh:
            np.savez(fh, metadata=np.array(json.dumps(meta)), **arrays)
        if tiff:
            _write_tiff(temps[1], height, meta)
    return path


def _parameters(surface):
    return surface.coefficients if isinstance(surface, SmoothSurface) else surface.params


def _write_tiff(path, height: np.ndarray, meta: dict) -> None:
    import tifffile
    per_cm = 1e-2 / meta["camera"]["dx"]
    description = {"shape": list(height.shape),   # tifffile's JSON description
                   **{k: meta[k] for k in ("format", "unit", "refractive_index", "camera",
                                           "surface", "height_range")}}
    tifffile.imwrite(path, height, resolution=(per_cm, per_cm), resolutionunit="CENTIMETER",
                     description=json.dumps(description), metadata=None)


def load_design(path: str | os.PathLike) -> Design:
    """Read a design file written by `save_design`.

    Raises:
        DiffcamError: a missing, truncated or damaged file, another kind of ``.npz``, a
            newer format version, or arrays that do not fit its metadata.
    """
    names = npz_keys(path, what=_WHAT)
    data = read_npz(path, ["metadata", "height", "parameters", "history"], what=_WHAT)
    try:
        meta = json.loads(str(data["metadata"][()]))
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise DiffcamError(f"{path}: not {_WHAT} (format {meta.get('format')!r}).")
        if not isinstance(meta.get("version"), int) or meta["version"] > FORMAT_VERSION:
            raise DiffcamError(f"{path}: design format version {meta.get('version')!r}; "
                               f"this diffcam reads versions ≤ {FORMAT_VERSION}: upgrade "
                               f"diffcam.")
        surface = _surface_from(meta["surface"], data["parameters"])
        camera = Camera(**{**meta["camera"], "shape": tuple(meta["camera"]["shape"]),
                           "pad": tuple(meta["camera"]["pad"]),
                           "crop": None if meta["camera"]["crop"] is None
                           else tuple(meta["camera"]["crop"])})
        options = DesignOptions(**meta["options"])
        n_opt = sum(name.startswith("optimiser_") for name in names)
        leaves = read_npz(path, [f"optimiser_{i}" for i in range(n_opt)], what=_WHAT)
        log_tau = meta.get("log_tau")
        log_tau = None if log_tau is None else jnp.float32(log_tau)
        if (log_tau is None) != (options.objective == "depth"):
            raise DiffcamError(f"{path}: a design of the {options.objective} objective "
                               f"with{'out' if log_tau is None else ''} a solver weight.")
        design = Design(surface, camera, np.asarray(meta["z1"], np.float64),
                        float(meta["refractive_index"]), options,
                        np.asarray(data["history"], np.float64), dict(meta["final"]), None,
                        str(meta["stop_reason"]), float(meta["seconds"]), log_tau)
        design = dataclasses.replace(design, optimiser_state=_optimiser_state(
            design, [leaves[f"optimiser_{i}"] for i in range(n_opt)], path))
    except DiffcamError as err:
        raise DiffcamError(str(err) if str(err).startswith(str(path)) else
                           f"{path}: damaged {_WHAT}: {err}") from None
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
        raise DiffcamError(f"{path}: not a readable {_WHAT} ({type(err).__name__}: {err}); "
                           f"its metadata are missing or damaged.") from None
    _check_arrays(path, design, data)
    return design


def _surface_from(meta: dict, parameters: np.ndarray):
    meta = dict(meta)
    cls = _KINDS[meta.pop("kind")]
    meta["shape"] = tuple(meta["shape"])
    return cls(np.asarray(parameters), **meta)


def _optimiser_state(design: Design, leaves, path):
    """Adam's state from its saved leaves, in the structure `optax.adam` gives the
    design's parameters."""
    template = design.initial_optimiser_state()
    treedef = jax.tree_util.tree_structure(template)
    shapes = [np.shape(v) for v in jax.tree_util.tree_leaves(template)]
    if [np.shape(v) for v in leaves] != shapes:
        raise DiffcamError(f"{path}: the optimiser state does not fit the surface's "
                           f"parameters; the file is damaged.")
    return jax.tree_util.tree_unflatten(treedef, [jnp.asarray(v) for v in leaves])


def _check_arrays(path, design: Design, data) -> None:
    """The stored height map is the surface's, finite, within its range; the history
    has its columns."""
    height = data["height"]
    if height.shape != tuple(design.camera.shape) or height.dtype != np.float32:
        raise DiffcamError(f"{path}: height map of shape {height.shape} ({height.dtype}) "
                           f"does not fit the camera grid {tuple(design.camera.shape)} "
                           f"(float32); the file is damaged.")
    if not (np.isfinite(height).all() and np.isfinite(_parameters(design.surface)).all()):
        raise DiffcamError(f"{path}: the height map or parameters hold NaN/Inf; the file "
                           f"is damaged.")
    rendered = np.asarray(design.height_map().height, np.float32)
    if not np.allclose(rendered, height, rtol=1e-5, atol=1e-5 * float(np.abs(height).max())):
        raise DiffcamError(f"{path}: the height map is not the surface's parameters' (it "
                           f"was edited or the file is damaged); design again.")
    if design.history.ndim != 2 or design.history.shape[1] != len(HISTORY_COLUMNS):
        raise DiffcamError(f"{path}: history of shape {design.history.shape}, expected "
                           f"(steps, {len(HISTORY_COLUMNS)}); the file is damaged.")
