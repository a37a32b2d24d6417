"""``diffcam reconstruct``: a scene (one plane) or, with ``--3d``, a volume from a raw
capture and the PSFs of its depths.

    diffcam reconstruct raw.png --psf psfs.tif --depth 25mm -o scene.png
    diffcam reconstruct raw.png --psf psfs/ --3d -o volume.tif
    diffcam reconstruct raw.png --psf 'psfs/*.png' --3d --dark-raw auto --dark-psf auto -o volume.tif
    diffcam reconstruct raw.png --psf model.npz --planes 0:43:2 --3d -o volume.tif

A PSF SOURCE is a PSF image or stack file (PNG/TIFF/``.npy`` image, multi-page TIFF,
``.npz``/``.tif`` from ``diffcam psf``, MATLAB ``.mat``), a folder of single-plane
images (natural name order: ``psf9`` before ``psf10``), a quoted glob of them, or a
stack-fit model from ``diffcam fit`` (its planes rendered by ``StackFit.predict``).
See ``docs/cli_reconstruct.md``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam.apps.common import (count, DefaultsFormatter, has_stack_meta,
                                 iterations_count, length_arg, planes_arg, read_psfs,
                                 save_figure, save_image, save_rgb)
from diffcam.apps.fit_cli import model_planes
from diffcam.apps.volume_views import depth_map_figure, montage_figure, projections_figure
from diffcam.calibrate import load_stack_fit
from diffcam.calibrate.stack_result import FORMAT, MAX_PLANES
from diffcam.core.grid import crop_to
from diffcam.io import (as_rgb, atomic_output, BackgroundWarning, border_dark_level,
                        check_output_path, downsample, image_files, IMAGE_SUFFIXES,
                        npz_keys, read_image, read_npz, read_psf_stack, subtract_background)
from diffcam.reconstruct import (admm_tv, admm_tv_3d, focus_sweep, richardson_lucy,
                                 richardson_lucy_3d, wiener)
from diffcam.reconstruct.admm import VOLUME
from diffcam.reconstruct.checks import MAX_ITERATIONS

DARK_RING = 6        # pixels: width of the frame-border band whose median is the dark level
SWEEP_ITERATIONS = 60  # ADMM iterations per plane of the 2-D focus sweep
ITERATIONS = {"admm": 100, "rl": 1000}
"""Default iterations per method in 2-D, measured on the shipped hand (docs/real_data.md):
ADMM-TV has converged by 100 (correlation 0.998 with a 200-step FISTA reference, the
same at 300); Richardson–Lucy needs about 1000 (0.996; at 150 the fingers are not
resolved, 0.959)."""
WORKING_SIZE = 480
"""Pixels on the longer side up to which ``reconstruct`` works at the capture's own
resolution by default; larger captures are box-averaged by the least integer factor
that brings them there (:func:`working_factor`). The defaults (iterations, ADMM-TV's
``tau``) were measured on captures of 400 and 480 pixels per side; on the tutorial hand
at its full 1200 × 1600 they leave the fine detail unresolved (docs/scene_psf.md)."""
ITERATIONS_3D = {"admm": 60, "rl": 300}
"""The same for ``--3d``: ADMM-TV with :data:`diffcam.reconstruct.admm.VOLUME` 60 (the
shipped USAF capture, 44 planes of 270 × 320: the measurements behind the choice are in
docs/volume.md); Richardson–Lucy 300."""


class PsfSource(NamedTuple):
    """PSFs read from a source.

    Attributes:
        psfs: float32 ``(my, mx)`` (one PSF) or ``(nz, my, mx)``, in the source's units.
        depths: source depth z1 of each plane, metres, or ``None`` if unknown.
        planes: plane number of each plane (index in the stack or the model).
        names: file of each plane (folder/glob sources), else ``None``.
        colour: ``psfs`` is ``(3, my, mx)``, one PSF per colour channel (R, G, B).
    """

    psfs: np.ndarray
    depths: np.ndarray | None
    planes: list[int]
    names: list[str] | None
    colour: bool = False

    def labels(self) -> list[str]:
        """One label per plane: the depth when known, else the plane number (and file)."""
        if self.depths is not None:
            return [f"z1 {d * 1e3:.4g} mm" for d in self.depths]
        files = self.names or [None] * len(self.planes)
        return [f"plane {t}" + (f" ({f})" if f else "") for t, f in zip(self.planes, files)]


def is_stack_fit(path) -> bool:
    """Whether ``path`` is an ``.npz`` whose ``metadata`` says ``diffcam-stack-fit``."""
    import json


    path = Path(path)
    if path.suffix.lower() != ".npz" or not path.exists():
        return False
    if "metadata" not in npz_keys(path, what="a diffcam .npz file"):
        return False
    meta = read_npz(path, ["metadata"], what="a diffcam stack-fit file")["metadata"]
    try:
        return json.loads(str(meta[()])).get("format") == FORMAT
    except (ValueError, AttributeError, IndexError):
        return False


def _read_model(path, planes) -> PsfSource:
    """The planes (default all) a stack-fit model renders, clipped at 0."""

    fit = load_stack_fit(path)
    planes = model_planes(fit, planes, path)
    if min(planes) < 0:
        raise DiffcamError(f"--planes {planes}: plane numbers start at 0.")
    # unit mean per plane, dark-free; the carried residuals can dip below 0: clip them
    return PsfSource(np.clip(fit.predict(planes), 0, None), None, list(planes), None)


def read_psf_source(source: str, planes: list[int] | None = None) -> PsfSource:
    """PSFs from a file, folder, glob or stack-fit model (module docstring); ``planes``
    selects planes of the stack (default all; for a model, the planes to render)."""

    files = image_files(source)
    if files is None and is_stack_fit(source):
        return _read_model(source, planes)
    if files is not None:
        try:
            psfs, depths = read_psf_stack(files), None
        except DiffcamError as err:
            raise DiffcamError(f"{source}: {err}") from None
    else:
        psfs, depths = read_psfs(source)
    psfs = np.asarray(psfs, np.float32)
    if psfs.ndim == 2:
        if planes is not None:
            raise DiffcamError(f"{source}: holds one PSF; --planes selects planes of a stack.")
        return PsfSource(psfs, None, [0], None)
    names = None if files is None else [f.name for f in files]
    selected = list(range(len(psfs))) if planes is None else list(planes)
    bad = [t for t in selected if not 0 <= t < len(psfs)]
    if bad:
        raise DiffcamError(f"--planes: plane(s) {bad} outside the stack of {len(psfs)} "
                           f"planes (0 … {len(psfs) - 1}) in {source}.")
    return PsfSource(psfs[selected], None if depths is None else np.asarray(depths)[selected],
                     selected, None if names is None else [names[t] for t in selected])


def _dark_arg(text: str):
    """``auto``, a level in counts, or one level per colour channel ``R,G,B``
    (argparse type)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"give a dark level in counts, one per channel "
                                         f"(R,G,B) or 'auto', not {text!r}") from None
    if not np.all(np.isfinite(values)) or len(values) not in (1, 3):
        raise argparse.ArgumentTypeError(f"the dark level must be one finite number or "
                                         f"three (R,G,B), not {text!r}")
    return values[0] if len(values) == 1 else np.asarray(values)


def _subtract_dark(images, level, what: str, say=print):
    """``images`` minus ``level`` (counts, or ``"auto"``: the border median,
    :func:`diffcam.io.border_dark_level`); clipping noise below 0 is reported through
    ``say`` as one line."""
    import warnings


    if level is None:
        return images
    background = border_dark_level(images, DARK_RING) if _is_auto(level) else level
    if np.ndim(background) == 1 and np.ndim(images) != 3:
        raise DiffcamError(f"{what}: one dark level per channel needs a colour image; "
                           f"give one level.")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", BackgroundWarning)
        try:
            out = subtract_background(images, background)
        except DiffcamError as err:
            raise DiffcamError(f"{what}: {err}") from None
    for w in caught:
        say(f"{what}: {w.message}")
    return out


def _gains_arg(text: str):
    """``auto`` or three gains ``R,G,B`` (argparse type)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        gains = [float(v) for v in text.split(",")]
    except ValueError:
        gains = []
    if len(gains) != 3 or not all(np.isfinite(g) and g > 0 for g in gains):
        raise argparse.ArgumentTypeError(f"give three positive gains R,G,B or 'auto', not "
                                         f"{text!r}")
    return gains


def _is_auto(level) -> bool:
    return isinstance(level, str) and level == "auto"


def dark_levels(args) -> tuple:
    """(raw level, PSF level) from ``--bias`` or ``--dark-raw``/``--dark-psf``; none by
    default. On the shipped captures the crop-model solvers absorb a constant offset:
    ADMM-TV's hand changes by < 0.001 in correlation with a FISTA reference for a raw
    dark level of 0 to 200 counts, or a PSF dark level of 0 to 80 (the true one is 34)."""
    if args.bias is not None:
        if args.dark_raw is not None or args.dark_psf is not None:
            raise DiffcamError("--bias subtracts one level from both the raw and the PSFs; "
                               "use either it or --dark-raw/--dark-psf, not both.")
        return args.bias, args.bias
    return args.dark_raw, args.dark_psf


def read_inputs(args, say) -> tuple[np.ndarray, PsfSource]:
    """The raw capture and the PSFs, dark-subtracted and downsampled alike; checks that
    the PSF fits in the raw image. ``say`` reports progress notes."""

    raw_level, psf_level = dark_levels(args)
    if args.downsample is not None and args.downsample < 1:
        raise DiffcamError(f"--downsample {args.downsample}: give a factor of 1 or more.")
    raw = read_raw(args.raw, args.channel_order)
    source = colour_psf(args.psf, raw, args.channel_order) or read_psf_source(args.psf,
                                                                               args.planes)
    raw = _subtract_dark(raw, raw_level, f"{args.raw} (raw dark level)", say)
    psfs = _subtract_dark(source.psfs, psf_level, f"{args.psf} (PSF dark level)", say)
    factor = working_factor(raw.shape, args.downsample, say)
    if factor > 1:
        raw, psfs = downsample(raw, factor), downsample(psfs, factor)
    if psfs.shape[-2] > raw.shape[-2] or psfs.shape[-1] > raw.shape[-1]:
        raise DiffcamError(f"PSF {psfs.shape[-2:]} is larger than the image {raw.shape[-2:]}"
                           f"{' after downsampling' if factor > 1 else ''}; crop "
                           f"the PSF or use the same downsampling for both.")
    check_light(raw, psfs, args)
    check_not_swapped(raw, psfs, args)
    return raw, source._replace(psfs=np.asarray(psfs, np.float32))


def check_light(raw: np.ndarray, psfs: np.ndarray, args) -> None:
    """Refuse a raw capture or a PSF plane without light (every pixel ≤ 0 once the dark
    level is off): there is nothing to deconvolve, or nothing to deconvolve with."""
    if not np.max(raw) > 0:
        raise DiffcamError(f"{args.raw}: no light: every pixel is 0 or below"
                           f"{' after the dark level' if args.dark_raw or args.bias else ''};"
                           f" check the capture and the dark level.")
    planes = np.asarray(psfs).reshape((-1,) + psfs.shape[-2:])
    dark = np.flatnonzero(~(planes.max(axis=(-2, -1)) > 0))
    if dark.size:
        where = "" if len(planes) == 1 else f" (plane(s) {dark[:5].tolist()})"
        raise DiffcamError(f"{args.psf}: the PSF holds no light{where}: every pixel is 0 or "
                           f"below; check the PSF file and its dark level.")


def lit_pixels(images: np.ndarray) -> np.ndarray:
    """The effective number of lit pixels of each frame, (Σx)² / Σx² over its positive
    part: N for a flat frame, 1 for a single bright pixel."""
    x = np.maximum(np.asarray(images, np.float64), 0)
    return x.sum(axis=(-2, -1)) ** 2 / (x ** 2).sum(axis=(-2, -1))


def check_not_swapped(raw: np.ndarray, psfs: np.ndarray, args) -> None:
    """Warn (stderr) when the raw lights fewer effective pixels (:func:`lit_pixels`)
    than its least spread PSF: by Young's inequality a capture ``Σ_z h_z * x_z`` of
    non-negative scenes lights at least as many as the least spread of its PSFs, so the
    two files are likely swapped. On the shipped pairs (hand, USAF volume, seven
    scenes, at 1 to 8 times downsampling) the raw lights 1.8 to 3.0 times more."""
    image = raw.sum(axis=0) if raw.ndim == 3 else raw
    planes = psfs.sum(axis=0) if psfs.ndim == 3 and raw.ndim == 3 else psfs
    raw_lit, psf_lit = float(lit_pixels(image)), float(np.min(lit_pixels(planes)))
    if raw_lit < psf_lit:
        print(f"diffcam reconstruct: warning: the raw {args.raw} lights fewer pixels "
              f"({raw_lit:.0f} effective) than its PSF {args.psf} ({psf_lit:.0f}); a "
              f"capture spreads light more than its PSF: are the two files swapped?",
              file=sys.stderr)


def working_factor(shape, requested: int | None, say) -> int:
    """``requested`` (``--downsample``), or by default the least factor that brings the
    capture's longer side to :data:`WORKING_SIZE` pixels or fewer, said through ``say``."""
    if requested is not None:
        return requested
    ny, nx = shape[-2:]
    factor = -(-max(ny, nx) // WORKING_SIZE)
    if factor > 1:
        say(f"working at {ny // factor}×{nx // factor}: the {ny}×{nx} capture box-averaged "
            f"by {factor} (the defaults suit ≤ {WORKING_SIZE} pixels per side; "
            f"--downsample 1 keeps the full resolution)")
    return factor


def read_raw(path, channel_order: str | None) -> np.ndarray:
    """The raw capture: ``(ny, nx)``, or ``(3, ny, nx)`` in R, G, B order for a colour
    file (``channel_order`` is the file's, e.g. ``"BGR"``)."""

    capture = read_image(path, channel_order=channel_order)
    if capture.channels is not None:
        return as_rgb(capture)
    if capture.image.ndim != 2:
        raise DiffcamError(f"{path}: expected a grayscale or colour (ny, nx, 3) image, got "
                           f"a stack of shape {capture.image.shape}.")
    return capture.image


def colour_psf(source: str, raw: np.ndarray, channel_order: str | None) -> PsfSource | None:
    """One PSF per colour channel if ``source`` is one colour image file (e.g. from
    ``diffcam calibrate-psf``), else ``None`` (a grayscale PSF is shared by the channels).
    """

    path = Path(source)
    if (path.suffix.lower() not in IMAGE_SUFFIXES or not path.is_file()
            or Path(f"{path}.json").exists() or has_stack_meta(path)):
        return None
    capture = read_image(path, channel_order=channel_order)
    if capture.channels is None:
        return None
    if raw.ndim == 2:
        raise DiffcamError(f"{source}: a colour PSF for a grayscale raw; give a colour raw "
                           f"or a grayscale PSF.")
    return PsfSource(as_rgb(capture), None, [0], None, colour=True)


def white_balance(image: np.ndarray, gains) -> np.ndarray:
    """``image`` ``(3, ny, nx)`` times a gain per channel: ``gains`` ``"auto"`` (grey
    world: every channel's mean brought to the mean of the three), three numbers, or
    ``None`` (unchanged)."""
    if gains is None or np.ndim(image) != 3:
        return image
    if _is_auto(gains):
        means = image.mean(axis=(-2, -1))
        if np.any(means <= 0):
            raise DiffcamError("--white-balance auto: a channel of the reconstruction is "
                               "dark; give the gains (R,G,B).")
        gains = means.mean() / means
    return image * np.asarray(gains, image.dtype)[:, None, None]


def _reporter(quiet: bool):
    """A function printing one progress line to stderr (nothing with ``--quiet``)."""
    def say(text: str) -> None:
        if not quiet:
            print(f"diffcam reconstruct: {text}", file=sys.stderr, flush=True)
    return say


def _pick_plane(raw, source: PsfSource, args, say) -> np.ndarray:
    """The one PSF of a 2-D reconstruction: by --depth, --plane or a focus sweep (the
    plane whose PSF leaves the least data misfit, :func:`diffcam.reconstruct.focus_sweep`)."""

    psfs = source.psfs
    if psfs.ndim == 2 or source.colour:
        return psfs
    if args.depth is not None:
        if source.depths is None:
            raise DiffcamError("--depth needs a PSF stack with depths (.npz or .tif from "
                               "`diffcam psf`); use --plane for an image stack.")
        plane = int(np.argmin(np.abs(source.depths - args.depth)))
    elif args.plane is not None:
        plane = args.plane
    else:
        say(f"focus sweep over {len(psfs)} planes (ADMM-TV, {SWEEP_ITERATIONS} iterations "
            f"each)")
        image = raw if raw.ndim == 2 else raw.sum(axis=0)
        plane = int(focus_sweep(image, psfs, SWEEP_ITERATIONS, progress=not args.quiet).best)
        print(f"diffcam reconstruct: plane {plane} of {len(psfs)} explains the image best")
    if not 0 <= plane < len(psfs):
        raise DiffcamError(f"--plane {plane} is outside the stack of {len(psfs)} PSFs.")
    return psfs[plane]


def _iterations(args) -> int:
    """``--iterations``, or the method's measured default (:data:`ITERATIONS`,
    :data:`ITERATIONS_3D`)."""
    if args.iterations is None:
        return (ITERATIONS_3D if args.three_d else ITERATIONS).get(args.method, 1)
    return args.iterations


def _run_2d(args, say) -> int:

    check_output_path(args.out, suffixes=(".png", ".tif", ".tiff", ".npy"))
    say(f"reading {args.raw} and {args.psf}")
    raw, source = read_inputs(args, say)
    psf = _pick_plane(raw, source, args, say)
    iterations = _iterations(args)
    say(f"reconstructing {raw.shape[-2]}×{raw.shape[-1]}"
        + (" in colour (R, G, B)" if raw.ndim == 3 else "") + f": {args.method}"
        + ("" if args.method == "wiener" else f", {iterations} iterations"))
    if args.method == "rl":
        rec = richardson_lucy(raw, psf, iterations, boundary="crop", progress=not args.quiet)
    elif args.method == "admm":
        scale = np.linalg.norm(raw) / np.linalg.norm(psf)   # back to raw / PSF units
        rec = admm_tv(raw / np.linalg.norm(raw), psf / np.linalg.norm(psf), iterations,
                      progress=not args.quiet)
        rec = rec._replace(image=rec.image * scale)
    else:
        rec = wiener(raw, psf, boundary="crop")
    image = np.asarray(rec.image if args.full_field else crop_to(rec.image, raw.shape[-2:]))
    say(f"writing {args.out}")
    if raw.ndim == 3:
        save_rgb(args.out, white_balance(image, args.white_balance))
    else:
        save_image(args.out, image)
    print(f"diffcam reconstruct: {args.method}, {int(np.max(rec.iterations))} iterations, "
          f"residual {final_residual(rec):.3g} → {args.out}")
    return 0


class VolumePaths(NamedTuple):
    """The files of ``--3d -o OUT.tif``."""

    volume: Path        # OUT.tif
    max: Path           # OUT_max.png
    depth: Path         # OUT_depth.png
    projections: Path   # OUT_projections.png
    montage: Path       # OUT_montage.png


def volume_paths(out) -> VolumePaths:
    """``OUT.tif`` and its companions (:class:`VolumePaths`), each checked writable
    (:func:`diffcam.io.check_output_path`) before any work."""

    out = check_output_path(out, suffixes=(".tif", ".tiff"))
    paths = VolumePaths(out, *(out.with_name(f"{out.stem}_{name}.png") for name in
                               VolumePaths._fields[1:]))
    for p in paths[1:]:
        check_output_path(p)
    return paths


def _solve_3d(raw, psfs, args):
    """The volume and its :class:`~diffcam.reconstruct.Reconstruction`; ADMM-TV solves
    for the raw scaled to unit L2 norm (the scale the weights of
    :data:`diffcam.reconstruct.admm.VOLUME` are for) and the volume is scaled back to counts."""

    if args.method == "rl":
        rec = richardson_lucy_3d(raw, psfs, _iterations(args), progress=not args.quiet)
        return rec.image, rec
    norm = float(np.linalg.norm(raw))
    rec = admm_tv_3d(raw / norm, psfs, _iterations(args), VOLUME,
                     progress=not args.quiet)
    return rec.image * norm, rec


def final_residual(rec) -> float:
    """The relative data misfit of the volume a solver returned (ADMM reports it; for
    Richardson–Lucy the last iterate's)."""
    if rec.final_residual is not None:
        return float(np.max(rec.final_residual))
    residual = np.asarray(rec.residual)
    return float(residual[np.isfinite(residual)][-1])


def _run_3d(args, say) -> int:

    if args.plane is not None or args.depth is not None:
        raise DiffcamError("--3d reconstructs every plane of the stack; --plane and --depth "
                           "choose one plane for a 2-D reconstruction (use --planes to "
                           "choose the planes of the volume).")
    if args.method == "wiener":
        raise DiffcamError("--3d solves with --method rl or admm; wiener is 2-D only.")
    paths = volume_paths(args.out)
    say(f"reading {args.raw} and {args.psf}")
    raw, source = read_inputs(args, say)
    if raw.ndim != 2 or source.colour:
        raise DiffcamError(f"{args.raw}: --3d reconstructs grayscale captures with a "
                           f"grayscale PSF stack; reconstruct colour in 2-D.")
    if source.psfs.ndim != 3:
        raise DiffcamError(f"{args.psf}: --3d needs a PSF stack (one PSF per depth), got one "
                           f"PSF of shape {source.psfs.shape}.")
    nz, my, mx = source.psfs.shape
    say(f"reconstructing {nz} planes from a {raw.shape[0]}×{raw.shape[1]} image ({my}×{mx} "
        f"PSFs): {args.method}, {_iterations(args)} iterations")
    t0 = time.perf_counter()
    image, rec = _solve_3d(raw, source.psfs, args)
    volume = np.asarray(image if args.full_field else crop_to(image, raw.shape), np.float32)
    if not np.isfinite(volume).all():
        raise DiffcamError("the reconstruction holds NaN/Inf values; check the dark levels "
                           "and try fewer --iterations.")
    seconds = time.perf_counter() - t0
    info = _volume_info(args, rec, seconds)
    say(f"writing {paths.volume} and " + ", ".join(p.name for p in paths[1:]))
    write_volume(paths, volume, source, info)
    gap = "" if rec.split_gap is None else f", split gap {info['split_gap']:.2g}"
    print(f"diffcam reconstruct: {args.method} 3-D, {nz} planes, {info['iterations']} "
          f"iterations ({seconds:.1f} s), residual {info['residual']:.3g}{gap} → "
          f"{paths.volume}")
    return 0


def _volume_info(args, rec, seconds: float) -> dict:
    """What the volume's metadata records: solver, settings, dark levels, how far it
    converged."""
    import dataclasses


    info = {"method": args.method, "iterations": int(np.max(rec.iterations)),
            "seconds": round(seconds, 2), "residual": final_residual(rec),
            "dark_raw": args.dark_raw, "dark_psf": args.dark_psf, "bias": args.bias,
            "downsample": args.downsample}
    if args.method == "admm":
        info["options"] = {f.name: getattr(VOLUME, f.name)
                           for f in dataclasses.fields(VOLUME)}
        info["split_gap"] = float(np.max(rec.split_gap))
    return info


def _cmd_reconstruct(args) -> int:
    say = _reporter(args.quiet)
    return _run_3d(args, say) if args.three_d else _run_2d(args, say)


def volume_labels(source: PsfSource) -> tuple[list[str], str]:
    """Short per-plane labels for the figures (depth in mm, else plane number) and the
    axis name they need."""
    if source.depths is not None:
        return [f"{d * 1e3:.4g}" for d in source.depths], "source depth z1 (mm)"
    return [str(t) for t in source.planes], "plane"


def write_volume(paths: VolumePaths, volume, source: PsfSource, info: dict) -> None:
    """Write the volume TIFF (ImageJ, axes ZYX, a label per plane, ``info`` as JSON in
    its Info field), its max projection (8-bit PNG), depth map, orthogonal projections
    and plane montage (PNG) together: all are replaced or none."""
    import json

    import matplotlib.pyplot as plt
    import tifffile


    volume = np.asarray(volume, np.float32)
    labels, axis = volume_labels(source)
    figures = (depth_map_figure(volume, labels, axis), projections_figure(volume, labels),
               montage_figure(volume, labels))
    try:
        with atomic_output(*paths) as temps:
            tmp = VolumePaths(*temps)
            tifffile.imwrite(tmp.volume, volume, imagej=True,
                             metadata={"axes": "ZYX", "Labels": source.labels(),
                                       "Info": json.dumps(info)})
            save_image(tmp.max, volume.max(axis=0), bits=8)
            for fig, path in zip(figures, (tmp.depth, tmp.projections, tmp.montage)):
                save_figure(fig, path)
    finally:
        for fig in figures:
            plt.close(fig)


def add_reconstruct(sub) -> None:
    """Add ``reconstruct`` to the ``diffcam`` subcommands."""

    rec = sub.add_parser(
        "reconstruct", help="deconvolve a sensor image with a PSF (or a volume with --3d)",
        formatter_class=DefaultsFormatter,
        description="Reconstruct a scene from a raw capture and the PSF of its depth. With "
                    "a PSF stack, pick the plane by --depth, --plane, or else the plane "
                    "whose PSF explains the capture best (least data misfit); with --3d, "
                    "reconstruct every plane as a volume "
                    "(OUT.tif, OUT_max.png, OUT_depth.png, OUT_projections.png, "
                    "OUT_montage.png). ADMM-TV solves for the raw scaled to unit L2 norm; "
                    "in 3-D with lateral TV 1e-5, axial TV 2e-6, an L1 weight of 2e-5 "
                    "and residual-balanced penalties (diffcam.reconstruct.admm.VOLUME, "
                    "recorded in OUT.tif's metadata). See docs/cli_reconstruct.md.")
    rec.add_argument("raw", help="raw capture, grayscale or colour (.png, .tif, .npy)")
    rec.add_argument("--channel-order", choices=["RGB", "BGR"], metavar="ORDER",
                     help="channel order of colour files, RGB or BGR (OpenCV .npy arrays); "
                          "needed for colour .npy, PNG/TIFF are RGB by default")
    rec.add_argument("--white-balance", type=_gains_arg, metavar="auto|R,G,B",
                     help="colour: gains per channel, or 'auto' (grey world); default none "
                          "(a PSF per channel from calibrate-psf already balances them)")
    rec.add_argument("--psf", required=True, metavar="SOURCE",
                     help="PSF image or stack (.png/.tif/.npy, multi-page TIFF, .npz or .tif "
                          "from `diffcam psf`, .mat), a folder or a quoted glob "
                          "('psfs/*.png') of single-plane images (natural name order), or "
                          "a model .npz from `diffcam fit`")
    rec.add_argument("--planes", type=planes_arg, metavar="PLANES",
                     help="planes of the stack or model to use, e.g. 0:43 (ends included), "
                          f"0:43:2 or 3,7,12 (default: all; at most {MAX_PLANES})")
    rec.add_argument("--3d", dest="three_d", action="store_true",
                     help="reconstruct a volume over all the (selected) planes; -o OUT.tif")
    rec.add_argument("--depth", type=length_arg("depth"), metavar="Z1",
                     help="2-D: source depth z1 to use, with a unit (25mm)")
    rec.add_argument("--plane", type=count(0, MAX_PLANES - 1), metavar="INDEX",
                     help="2-D: index of the PSF plane to use")
    rec.add_argument("--method", choices=["admm", "rl", "wiener"], default="admm",
                     help="ADMM-TV, Richardson–Lucy, or Wiener (2-D only)")
    rec.add_argument("--iterations", type=iterations_count(), metavar="N",
                     help="solver iterations (default: " + ", ".join(
                         f"{n} for {m}" for m, n in ITERATIONS.items()) + "; with --3d "
                          + ", ".join(f"{n} for {m}" for m, n in ITERATIONS_3D.items())
                          + f"; at most {MAX_ITERATIONS})")
    rec.add_argument("--bias", type=float, metavar="COUNTS",
                     help="sensor bias, counts: the same level subtracted from both the raw "
                          "and the PSFs (not with --dark-raw/--dark-psf)")
    rec.add_argument("--dark-raw", type=_dark_arg, metavar="COUNTS|auto",
                     help="dark level of the raw, counts (R,G,B: one per colour channel), "
                          f"or 'auto': the median of a {DARK_RING}-pixel ring at the frame "
                          "border, per channel")
    rec.add_argument("--dark-psf", type=_dark_arg, metavar="COUNTS|auto",
                     help="dark level of the PSFs, counts, or 'auto': per plane, the "
                          f"median of a {DARK_RING}-pixel ring at the frame border")
    rec.add_argument("--downsample", type=int, metavar="FACTOR",
                     help="box-average factor, pixels per side (raw and PSFs alike); "
                          f"default: 1 up to {WORKING_SIZE} pixels per side, else the least "
                          f"factor that brings the capture there")
    rec.add_argument("--full-field", action="store_true",
                     help="keep the solver's object grid (per side: sensor + PSF − 1 pixels, "
                          "rounded up to a fast FFT length; the scene the sensor partly "
                          "sees) instead of cropping the result to the sensor's frame")
    rec.add_argument("--quiet", action="store_true",
                     help="no progress lines or bars on stderr")
    rec.add_argument("-o", "--out", required=True,
                     help="output .png, .tif or .npy (2-D; colour: 8-bit PNG, 16-bit TIFF "
                          "or float32 (ny, nx, 3) .npy); .tif volume (--3d)")
    rec.set_defaults(func=_cmd_reconstruct)
