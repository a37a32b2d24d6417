"""``diffcam reconstruct``: a scene (one plane) or, with ``--3d``, a volume from a raw
capture and the PSFs of its depths.

    diffcam reconstruct raw.png --psf psfs.tif --depth 25mm -o scene.png
    diffcam reconstruct raw.png --psf psfs/ --3d -o volume.tif
    diffcam reconstruct raw.png --psf 'psfs/*.png' --3d --dark-raw auto --dark-psf auto -o volume.tif
    diffcam reconstruct raw.png --psf model.npz --planes 0:43:2 --3d -o volume.tif
    diffcam reconstruct raw.npy --channel-order BGR --psf field.npz --method fista -o scene.npy

A PSF SOURCE is a PSF image or stack file (PNG/TIFF/``.npy`` image, multi-page TIFF,
``.npz``/``.tif`` from ``diffcam psf``, MATLAB ``.mat``), a folder of single-plane
images (natural name order: ``psf9`` before ``psf10``), a quoted glob of them, or a
stack-fit model from ``diffcam fit`` (its planes rendered by ``StackFit.predict``), or
a field-dependent PSF from ``diffcam calibrate-psf --field`` (2-D; each channel solved
with its model's operator, `diffcam.reconstruct.field_model`). The last line says
which model was used: a shift-invariant PSF, or a field-dependent one with its rank
and model error. See ``docs/cli_reconstruct.md``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from diffcam.apps.common import finite_result, save_figure, save_image, save_rgb
from diffcam.apps.reconstruct_args import ITERATIONS, ITERATIONS_3D
from diffcam.apps.reconstruct_inputs import (PsfSource, match_envelope, read_field_inputs,
                                             read_inputs, white_balance)
from diffcam.apps.volume_views import depth_map_figure, montage_figure, projections_figure
from diffcam.core.errors import DiffcamError
from diffcam.core.grid import crop_to
from diffcam.io import atomic_output, check_output_path
from diffcam import calibrate  # lazy: loaded on use
from diffcam.reconstruct import (admm_tv, admm_tv_3d, field_model, fista, focus_sweep,
                                 richardson_lucy, richardson_lucy_3d, wiener)
from diffcam.reconstruct.admm import VOLUME
from diffcam.reconstruct.sensor_terms import legendre_terms

SWEEP_ITERATIONS = 60  # ADMM iterations per plane of the 2-D focus sweep


def _reporter(quiet: bool):
    """A function printing one progress line to stderr (nothing with ``--quiet``)."""
    def say(text: str) -> None:
        if not quiet:
            print(f"diffcam reconstruct: {text}", file=sys.stderr, flush=True)
    return say


def _pick_plane(raw, source: PsfSource, args, say) -> np.ndarray:
    """The one PSF of a 2-D reconstruction: by --depth, --plane or a focus sweep (the
    plane whose PSF leaves the least data misfit, `diffcam.reconstruct.focus_sweep`)."""

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


def _unit_norm(a) -> tuple[np.ndarray, np.ndarray]:
    """``a / ||a||₂`` per image (over the last two axes: each colour channel, each PSF
    on its own; float32) and the norms ``(..., 1, 1)``, both computed in float64:
    float32 squares overflow from 1.8e19, and the norm of a raw ×1e37 exceeds float32."""
    a = np.asarray(a, np.float64)
    norm = np.linalg.norm(a, axis=(-2, -1), keepdims=True)
    return (a / norm).astype(np.float32), norm


def _iterations(args) -> int:
    """``--iterations``, or the method's measured default (`ITERATIONS`,
    `ITERATIONS_3D`)."""
    if args.iterations is None:
        return (ITERATIONS_3D if args.three_d else ITERATIONS).get(args.method, 1)
    return args.iterations


def _check_2d(args) -> None:
    """Refuse the options of a volume in a 2-D reconstruction; check ``-o``."""
    check_output_path(args.out, suffixes=(".png", ".tif", ".tiff", ".npy"))
    if args.psf_envelope is not None:
        raise DiffcamError("--psf-envelope shapes the PSF stack of a volume; use it with "
                           "--3d.")
    if args.background is not None:
        raise DiffcamError("--background is a term of the --3d ADMM solve; use it with "
                           "--3d.")


def _say_solving(raw, args, iterations: int, say) -> None:
    say(f"reconstructing {raw.shape[-2]}×{raw.shape[-1]}"
        + (" in colour (R, G, B)" if raw.ndim == 3 else "") + f": {args.method}"
        + ("" if args.method == "wiener" else f", {iterations} iterations"))


def _run_2d(args, say) -> int:

    _check_2d(args)
    say(f"reading {args.raw} and {args.psf}")
    raw, source = read_inputs(args, say)
    psf = _pick_plane(raw, source, args, say)
    iterations = _iterations(args)
    _say_solving(raw, args, iterations, say)
    if args.method == "rl":
        rec = richardson_lucy(raw, psf, iterations, boundary="crop", progress=not args.quiet)
    elif args.method == "admm":
        (unit_raw, raw_norm), (unit_psf, psf_norm) = _unit_norm(raw), _unit_norm(psf)
        rec = admm_tv(unit_raw, unit_psf, iterations, progress=not args.quiet)
        # back to raw / PSF units, in float64 (the scale may exceed float32's range)
        rec = rec._replace(image=np.asarray(rec.image, np.float64) * (raw_norm / psf_norm))
    elif args.method == "fista":
        rec = fista(raw, psf, iterations, progress=not args.quiet)
    else:
        rec = wiener(raw, psf, boundary="crop")
    _write_2d(args, raw, rec.image, say)
    print(f"diffcam reconstruct: shift-invariant PSF, {args.method}, "
          f"{int(np.max(rec.iterations))} iterations, residual {final_residual(rec):.3g} "
          f"→ {args.out}")
    return 0


def _write_2d(args, raw, image, say) -> None:
    """Write a 2-D result (``(oy, ox)`` or ``(3, oy, ox)``), cropped to the sensor's
    frame unless ``--full-field``; colour white-balanced by ``--white-balance``."""
    image = np.asarray(image if args.full_field else crop_to(image, raw.shape[-2:]))
    say(f"writing {args.out}")
    if raw.ndim == 3:
        save_rgb(args.out, white_balance(image, args.white_balance))
    else:
        save_image(args.out, image)


FIELD_METHODS = ("admm", "fista")


def _run_field(args, say) -> int:
    """2-D with a field-dependent PSF (``--psf FIELD.npz``)."""

    _check_2d(args)
    if args.method not in FIELD_METHODS:
        raise DiffcamError(f"{args.psf} is a field-dependent PSF: solve with --method "
                           f"admm or fista.")
    say(f"reading {args.raw} and {args.psf}")
    raw, fields, meta = read_field_inputs(args, say)
    iterations = _iterations(args)
    _say_solving(raw, args, iterations, say)
    image, recs = _solve_field(raw, fields, args.method, iterations, not args.quiet)
    _write_2d(args, raw, image, say)
    worst = max(fields, key=lambda f: float(f.error()))
    grid = meta.get("grid")
    print(f"diffcam reconstruct: field-dependent model"
          + (f" ({grid[0]}×{grid[1]} field positions)" if grid else "")
          + f", rank {worst.rank}, model error {float(worst.error()):.2g}, {args.method}, "
          f"{max(int(np.max(r.iterations)) for r in recs)} iterations, residual "
          f"{max(final_residual(r) for r in recs):.3g} → {args.out}")
    return 0


def _solve_field(raw, fields: tuple, method: str, iterations: int, progress: bool):
    """Each channel of ``raw`` solved with its field model's operator
    (`diffcam.reconstruct.field_model`): ADMM-TV for the channel scaled to unit L2 norm
    (the scale of its default weights) and scaled back, or FISTA on the channel as it
    is. The image ``(oy, ox)`` or ``(3, oy, ox)`` on the object grid, in the raw's
    units per unit of the model, and each channel's `Reconstruction`."""
    images, recs = [], []
    for channel, field in zip(raw if raw.ndim == 3 else raw[None], fields):
        operator = field_model(field, channel.shape)
        if method == "admm":
            unit, norm = _unit_norm(channel)
            rec = admm_tv(unit, operator, iterations, progress=progress)
            rec = rec._replace(image=np.asarray(rec.image, np.float64) * norm)
        else:
            rec = fista(channel, operator, iterations, progress=progress)
        images.append(np.asarray(rec.image))
        recs.append(rec)
    return (np.stack(images) if raw.ndim == 3 else images[0]), recs


class VolumePaths(NamedTuple):
    """The files of ``--3d -o OUT.tif``."""

    volume: Path        # OUT.tif
    max: Path           # OUT_max.png
    depth: Path         # OUT_depth.png
    projections: Path   # OUT_projections.png
    montage: Path       # OUT_montage.png


def volume_paths(out) -> VolumePaths:
    """``OUT.tif`` and its companions (`VolumePaths`), each checked writable
    (`diffcam.io.check_output_path`) before any work."""

    out = check_output_path(out, suffixes=(".tif", ".tiff"))
    paths = VolumePaths(out, *(out.with_name(f"{out.stem}_{name}.png") for name in
                               VolumePaths._fields[1:]))
    for p in paths[1:]:
        check_output_path(p)
    return paths


def _footprint_mode(args) -> str:
    """``--psf-envelope``, or its default ``auto`` (``mask``, the sensor window, is
    ADMM's alone: Richardson–Lucy's forward model has none)."""
    mode = args.psf_envelope or "auto"
    if mode == "mask" and args.method == "rl":
        raise DiffcamError("--psf-envelope mask puts a sensor window in the ADMM solve; "
                           "use --method admm, or --psf-envelope auto|none with rl.")
    return mode


def _solve_3d(raw, psfs, args, window):
    """The volume and its `Reconstruction`; ADMM-TV solves
    for the raw scaled to unit L2 norm (the scale the weights of
    `diffcam.reconstruct.admm.VOLUME` are for), with the sensor window ``window``
    (`diffcam.io.SensorWindow`, or None), and the volume is scaled back to counts."""

    if args.method == "rl":
        rec = richardson_lucy_3d(raw, psfs, _iterations(args), progress=not args.quiet)
        return rec.image, rec
    unit_raw, norm = _unit_norm(raw)
    response = None if window is None else window.response(raw.shape)
    rec = admm_tv_3d(unit_raw, psfs, _iterations(args), VOLUME, sensor_response=response,
                     background=args.background, progress=not args.quiet)
    if rec.background is not None:
        rec = rec._replace(background=rec.background * norm)
    return np.asarray(rec.image, np.float64) * norm, rec


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
    if args.method in ("wiener", "fista"):
        raise DiffcamError(f"--3d solves with --method rl or admm; {args.method} is 2-D "
                           f"only.")
    if calibrate.model_kind(args.psf) == "field-psf":
        raise DiffcamError(f"{args.psf} is a 2-D field-dependent PSF (one depth); "
                           f"reconstruct with it without --3d.")
    if args.method == "rl" and args.background is not None:
        raise DiffcamError("--background is a term of the ADMM solve; drop it or use "
                           "--method admm.")
    paths, mode = volume_paths(args.out), _footprint_mode(args)
    say(f"reading {args.raw} and {args.psf}")
    raw, source = read_inputs(args, say)
    if raw.ndim != 2 or source.colour:
        raise DiffcamError(f"{args.raw}: --3d reconstructs grayscale captures with a "
                           f"grayscale PSF stack; reconstruct colour in 2-D.")
    if source.psfs.ndim != 3:
        raise DiffcamError(f"{args.psf}: --3d needs a PSF stack (one PSF per depth), got one "
                           f"PSF of shape {source.psfs.shape}.")
    footprint = match_envelope(raw, source.psfs, mode, say)
    source = source._replace(psfs=footprint.psfs)
    nz, my, mx = source.psfs.shape
    say(f"reconstructing {nz} planes from a {raw.shape[0]}×{raw.shape[1]} image ({my}×{mx} "
        f"PSFs): {args.method}, {_iterations(args)} iterations")
    t0 = time.perf_counter()
    image, rec = _solve_3d(raw, source.psfs, args, footprint.window)
    volume = finite_result(paths.volume, np.asarray(
        image if args.full_field else crop_to(image, raw.shape), np.float32))
    seconds = time.perf_counter() - t0
    info = _volume_info(args, rec, seconds, footprint)
    say(f"writing {paths.volume} and " + ", ".join(p.name for p in paths[1:]))
    write_volume(paths, volume, source, info)
    gap = "" if rec.split_gap is None else f", split gap {info['split_gap']:.2g}"
    model = {"mask": f"sensor window σ {info['sensor_window_sigma_px']} px",
             "auto": "PSF envelope", "none": "PSFs as measured"}[info["psf_envelope"]]
    print(f"diffcam reconstruct: {args.method} 3-D, {nz} planes, {model}, "
          f"{info['iterations']} iterations ({seconds:.1f} s), residual "
          f"{info['residual']:.3g}{gap} → {paths.volume}")
    return 0


def _volume_info(args, rec, seconds: float, footprint) -> dict:
    """What the volume's metadata records: solver, settings, dark levels, the PSF
    envelope's widths (pixels, per plane; ``None`` without one) or the sensor window's
    centre row and σ (pixels of the reconstructed frame; ``None`` without one), how far
    it converged."""
    import dataclasses

    widths, window = footprint.widths, footprint.window
    info = {"method": args.method, "iterations": int(np.max(rec.iterations)),
            "seconds": round(seconds, 2), "residual": final_residual(rec),
            "dark_raw": args.dark_raw, "dark_psf": args.dark_psf, "bias": args.bias,
            "downsample": args.downsample, "psf_envelope": _footprint_mode(args),
            "psf_envelope_sigma_px": None if widths is None else np.round(widths, 1).tolist(),
            "sensor_window_sigma_px": None if window is None else round(window.sigma, 1),
            "sensor_window_centre_row_px":
                None if window is None else round(window.centre_row, 1)}
    if args.method == "admm":
        info["options"] = {f.name: getattr(VOLUME, f.name)
                           for f in dataclasses.fields(VOLUME)}
        info["options"]["background"] = args.background
        info["split_gap"] = float(np.max(rec.split_gap))
        info["background_counts"] = _background_summary(rec.background, args.background)
    return info


def _background_summary(background, degree) -> dict | None:
    """The fitted sensor background (``--background``) in the raw's units (as read,
    less any dark level): its coefficients on the polynomials ``P_i(y) P_j(x)``
    (`diffcam.reconstruct.sensor_terms.legendre_terms`), mean, least and largest value;
    ``None`` without one."""
    if background is None:
        return None
    b = np.asarray(background, np.float64)
    terms, pairs = legendre_terms(b.shape, degree)
    c = np.linalg.lstsq(terms.reshape(len(terms), -1).T, b.ravel(), rcond=None)[0]
    return {"degree": degree, "legendre_ij": [list(p) for p in pairs],
            "coefficients": [float(x) for x in c], "mean": float(b.mean()),
            "min": float(b.min()), "max": float(b.max())}


def cmd_reconstruct(args) -> int:
    """``diffcam reconstruct``, its command line read
    (`diffcam.apps.reconstruct_args`)."""
    say = _reporter(args.quiet)
    if args.three_d:
        return _run_3d(args, say)
    if calibrate.model_kind(args.psf) == "field-psf":
        return _run_field(args, say)
    return _run_2d(args, say)


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
