"""The ``diffcam`` command line. Lengths take units (``25mm``, ``3.45um``, ``532nm``)."""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import sys
import time
from pathlib import Path

import numpy as np

from diffcam.apps.compile_cache import DEFAULT_MAX_MB, enable_compilation_cache
from diffcam.apps.common import (DefaultsFormatter, Parser, count, grid_count,
                                 iterations_count, length_arg, lengths_arg, limits, one_line_warnings,
                                 planes_arg, positions_arg, read_psfs, save_figure,
                                 save_image, save_open_figures, save_rgb)
from diffcam.apps.scene_psf_cli import add_calibrate_psf
from diffcam.core.errors import DiffcamError
from diffcam.apps.design_cli import add_design
from diffcam.apps.fit_cli import add_fit, cmd_compare_stack, cmd_predict
from diffcam.apps.processes import (distributed_settings, end_process, ERRORS,
                                    in_distributed_run, initialize_from_environment,
                                    report_error, run_processes)
from diffcam.apps.reconstruct_args import add_reconstruct
from diffcam import apps, calibrate, core, evaluate, model, optics  # lazy: loaded on use
from diffcam.core import memory
from diffcam.core.version import installed_version
from diffcam.data import CAPTURES, export_captures
from diffcam.io import check_output_path, interrupts_as_keyboard_interrupt, read_image

# --help loads no JAX: the numerical modules load when a command first uses them
__all__ = ["main", "run", "build_parser", "save_image", "save_rgb", "save_figure",
           "save_open_figures"]


MAX_RESTARTS = 100
"""Most random starts ``diffcam calibrate --restarts`` takes (each is a full run of
the projections)."""


def _camera_for(phase_file, z2, crop):

    shape = tuple(np.shape(phase_file.phase))
    if crop is not None and (crop > shape[0] or crop > shape[1]):
        raise DiffcamError(f"--crop {crop} is larger than the phase grid {shape}.")
    return model.Camera(wavelength=phase_file.wavelength, z2=z2, dx=phase_file.dx,
                        aperture_radius=phase_file.aperture_radius, shape=shape,
                        crop=None if crop is None else (crop, crop))


def _cmd_psf(args) -> int:

    kind = calibrate.model_kind(args.phase)
    if kind == "field-psf":
        return apps.field_cli.cmd_psf_field(args)
    if args.at is not None:
        raise DiffcamError("--at (field positions) is for a field-dependent PSF from "
                           "`diffcam calibrate-psf --field`.")
    if kind == "stack-fit":
        if args.processes != 1:
            raise DiffcamError("--processes is for a phase file; a stack-fit model's "
                               "planes are computed by one process.")
        return _psf_from_stack_fit(args)
    model_only = [f for f, v in (("--planes", args.planes is not None),
                                 ("--kappa", args.kappa is not None),
                                 ("--rendered-only", args.rendered_only)) if v]
    if model_only:
        raise DiffcamError(f"{', '.join(model_only)} {'is' if len(model_only) == 1 else 'are'}"
                           f" for a stack-fit model from `diffcam fit`; a phase file takes "
                           f"depths: --z1 and --z2.")
    if args.z1 is None or args.z2 is None:
        raise DiffcamError("a phase file needs --z1 (depths) and --z2 (diffuser to sensor), "
                           "with units, e.g. --z1 22mm:30mm:1mm --z2 1mm.")
    suffix = Path(args.out).suffix.lower()
    if suffix not in (".npz", ".tif", ".tiff"):
        raise DiffcamError(f"{args.out}: write the stack as .npz or .tif, not {suffix!r}.")
    several = _several_processes(args)
    if kind is None:
        raise calibrate.model_file.not_a_model(args.phase)
    if several:
        return run_processes("psf", args.argv, args.processes, outputs=[args.out])
    phase_file = calibrate.load_phase(args.phase)
    camera = _camera_for(phase_file, args.z2, args.crop)
    depths = args.z1
    # streamed to the file chunk by chunk: memory does not grow with the number of depths
    stack = model.psf_stack(phase_file.phase, camera, depths, progress=len(depths) > 1,
                            out=args.out)
    print(f"diffcam psf: {len(depths)} PSFs of {stack.shape[-2]}×{stack.shape[-1]} "
          f"(z1 {depths[0] * 1e3:g}–{depths[-1] * 1e3:g} mm, z2 {args.z2 * 1e3:g} mm) → {args.out}")
    return 0


def _several_processes(args) -> bool:
    """Whether ``diffcam psf`` starts ``--processes`` copies of itself
    (`run_processes`). A copy it started, or one task of
    a cluster's launcher, has joined the run instead (`_join_run`)."""

    cpus = os.cpu_count() or 1
    if not 1 <= args.processes <= cpus:
        raise DiffcamError(f"--processes must be at least 1 and at most the {cpus} CPUs "
                           f"of this machine, got {args.processes}.")
    if distributed_settings() is not None:
        return False
    if args.processes > 1:
        check_output_path(args.out)  # before any process starts
    return args.processes > 1


def _join_run(args) -> None:
    """``diffcam psf`` of a phase file in a process that the environment makes one of
    several (a copy ``--processes`` started, or one task of a cluster's launcher):
    ``jax.distributed.initialize()``, before anything touches JAX's backend (``-v``
    lists its devices, ``DIFFCAM_FFT=fftw`` asks for its platform)."""

    if args.command != "psf" or distributed_settings() is None:
        return
    if calibrate.model_kind(args.phase) == "stack-fit":
        return  # one process computes its planes: _cmd_psf refuses --processes
    if args.processes > 1 and ERRORS not in os.environ:
        raise DiffcamError("this process is already one of several (JAX_PROCESS_ID or a "
                           "SLURM step of several tasks); leave out --processes.")
    initialize_from_environment()


def _psf_from_stack_fit(args) -> int:
    """``diffcam psf MODEL.npz --planes …``: the planes of a stack fit (as `diffcam
    predict`); a stack fit knows plane indices, not depths."""

    given = [f for f, v in (("--z1", args.z1), ("--z2", args.z2), ("--crop", args.crop))
             if v is not None]
    if given:
        raise DiffcamError(f"{args.phase} is a stack-fit model: it predicts plane indices "
                           f"(--planes 0:43), it does not take {', '.join(given)}.")
    return cmd_predict(argparse.Namespace(model=args.phase, planes=args.planes,
                                           kappa=args.kappa, rendered_only=args.rendered_only,
                                           out=args.out, at=None))


def _grid_for(aperture_radius, dx):
    """Calibration grid: twice the aperture diameter (a Nyquist-sampled far field)."""

    return core.backend.fft_size(int(np.ceil(4 * aperture_radius / dx)))


def _cmd_calibrate(args) -> int:
    import jax


    check_output_path(args.out, suffixes=(".npz",))
    dx = args.dx or args.pixel
    n = args.grid or _grid_for(args.aperture_radius, dx)
    geometry = calibrate.CalibrationGeometry(dx=dx, wavelength=args.wavelength,
                                             focal_length=args.focal_length,
                                             near_distance=args.near_distance)
    near, far = read_image(args.near).image, read_image(args.far).image
    prepared = calibrate.prepare_captures(near, far, geometry, (n, n),
                                          sensor_pitch=args.pixel,
                                          background=(args.background, args.background),
                                          saturation=args.saturation)
    aperture = optics.circular_aperture((n, n), dx, args.aperture_radius)
    key = jax.random.key(args.seed)
    reference = None if args.psf is None else _reference_psf(dx, (n, n), args)
    planes = () if reference is None else [
        calibrate.psf_plane(reference[0], reference[1], args.psf_z1)]
    print(f"diffcam calibrate: {n}×{n} grid at {dx * 1e6:g} µm, solver {args.solver}, "
          f"{args.iterations} iterations{', PSF as a third plane' if planes else ''} ...",
          flush=True)
    if args.solver == "default":
        result = calibrate.retrieve_phase(
            prepared.near, prepared.far, geometry, aperture, iterations=args.iterations,
            planes=planes, key=key, restarts=args.restarts,
            masks=(prepared.near_mask, prepared.far_mask))
    else:
        result = calibrate.retrieve_projections(
            prepared.near, prepared.far, geometry, method=args.solver,
            iterations=args.iterations, planes=planes, key=key,
            restarts=args.restarts or (1 if planes else 4))
    phase = np.asarray(result.phase)
    info = {"solver": result.stats.get("method", args.solver), "iterations": args.iterations,
            "seed": args.seed, "focal_length": args.focal_length,
            "near_distance": args.near_distance,
            "final_error": float(np.asarray(result.history)[-1]),
            "twin_resolved": False, "near": str(args.near), "far": str(args.far)}
    if reference is not None:
        psf_ref, camera = reference
        phase, info["twin_chosen"] = calibrate.resolve_twin(phase, psf_ref, camera, args.psf_z1)
        info.update(twin_resolved=True, psf=str(args.psf))
    calibrate.save_phase(args.out, calibrate.PhaseFile(phase, dx, args.wavelength,
                                                       args.aperture_radius, info))
    twin = "twin resolved by the PSF" if info["twin_resolved"] else \
        "phase known up to piston and the conjugate twin: pass --psf to resolve it"
    print(f"diffcam calibrate: final error {info['final_error']:.3g} → {args.out} ({twin})")
    return 0


def _reference_psf(dx, shape, args):
    """The captured PSF of ``--psf`` (same pitch as the grid) and its camera:
    ``(psf on the camera's crop, Camera)``."""

    if args.psf_z1 is None or args.psf_z2 is None:
        raise DiffcamError("--psf needs --psf-z1 and --psf-z2 (the PSF's source depth and "
                           "the diffuser-to-sensor distance).")
    captured = read_image(args.psf).image
    if captured.ndim != 2:
        raise DiffcamError(f"{args.psf}: expected one PSF image, got shape {captured.shape}.")
    crop = tuple(min(a, b) for a, b in zip(captured.shape, shape))
    camera = model.Camera(wavelength=args.wavelength, z2=args.psf_z2, dx=dx,
                          aperture_radius=args.aperture_radius, shape=shape, crop=crop)
    return core.grid.crop_to(captured, crop), camera


def _cmd_compare(args) -> int:

    if (args.model is None) == (args.phase is None):
        raise DiffcamError("give the camera model: --model FILE (a phase file from `diffcam "
                           "calibrate`, with --z2, or a stack fit from `diffcam fit`); "
                           "--phase is the same option.")
    path = args.model or args.phase
    kind = calibrate.model_kind(path)
    if kind is None:
        raise calibrate.model_file.not_a_model(path)
    if kind == "field-psf":
        return apps.field_cli.cmd_compare_field(args, path)
    if args.at is not None:
        raise DiffcamError("--at (field positions) is for a field-dependent PSF from "
                           "`diffcam calibrate-psf --field`.")
    if kind == "stack-fit":
        return _compare_stack_fit(args, path)
    if args.z2 is None:
        raise DiffcamError(f"{path} is a phase file: it needs --z2 (diffuser to sensor, "
                           f"with a unit).")
    if args.json is not None or args.key is not None:
        raise DiffcamError("--json and --key go with a stack fit; with a phase file the "
                           "table is printed and the figure written.")
    captured, depths = read_psfs(args.captured)
    if captured.ndim != 3:
        raise DiffcamError(f"{args.captured}: expected a stack of PSFs (nz, ny, nx), got "
                           f"shape {captured.shape}.")
    if args.z1 is not None:
        depths = args.z1
    if depths is None or len(depths) != len(captured):
        raise DiffcamError(f"give --z1 with one depth per captured PSF ({len(captured)}).")
    phase_file = calibrate.load_phase(path)
    pitch = args.pixel or phase_file.dx
    camera = _camera_for(phase_file, args.z2, None)
    stack = model.psf_stack(phase_file.phase, camera, depths, progress=len(depths) > 8)
    stack = np.asarray(model.sensor.bin_pixels(stack, phase_file.dx, pitch,
                                               captured.shape[-2:]))
    anchor = int(np.argmin(np.abs(np.asarray(depths) - (args.anchor or depths[0]))))
    scaled = np.asarray(evaluate.magnify_psf(captured[anchor], pitch, depths[anchor], depths,
                                             args.z2, kind="area"))
    f_model = np.asarray(evaluate.psf_fidelity(stack, captured)["pearson"])
    f_scaled = np.asarray(evaluate.psf_fidelity(scaled, captured)["pearson"])
    rows = ["| z1 (mm) | model Pearson | scaling Pearson |", "|---|---|---|"]
    rows += [f"| {z * 1e3:.3f} | {a:.4f} | {b:.4f} |" for z, a, b in
             zip(depths, f_model, f_scaled)]
    print("\n".join(rows))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(np.asarray(depths) * 1e3, f_model, "o-", label="wave model (phase file)")
    ax.plot(np.asarray(depths) * 1e3, f_scaled, "s--",
            label=f"scaling from {depths[anchor] * 1e3:g} mm")
    ax.set_xlabel("z1 (mm)")
    ax.set_ylabel("Pearson with the captured PSF")
    ax.legend()
    save_figure(fig, args.out)
    print(f"diffcam compare: → {args.out}")
    return 0


def _cmd_demo(args) -> int:

    settings = apps.paper.Settings
    base = settings(grid=4000) if args.full else settings()
    changes = {k: v for k, v in (("grid", args.grid), ("gs_iterations", args.gs_iterations),
                                 ("calibration_iterations", args.calibration_iterations))
               if v is not None}
    apps.demo.run_demo(args.out, settings=settings(**{**base.__dict__, **changes}))
    return 0


def _cmd_plan(args) -> int:

    print(optics.plan_sampling(args.wavelength, args.pixel, args.n, args.z1, args.z2,
                               args.aperture_radius, max_offset=args.max_offset))
    return 0


def _add_demo(sub) -> None:
    demo = sub.add_parser("demo", help="run the built-in demonstration and write a report",
                          description="Run the built-in demonstration on built-in data and "
                                      "write PNG figures and metrics.json to a folder.")
    demo.add_argument("-o", "--out", default="diffcam-report", help="report folder")
    demo.add_argument("--full", action="store_true",
                      help="the paper's 4000×4000 grid (about 30 min and 6 GB of memory "
                           "on 2 cores)")
    demo.add_argument("--grid", type=grid_count(600),
                      help="simulation grid, samples per side, at least 600: the 512² "
                           "diffuser needs room for the far field (default 1024; 4000 "
                           "with --full)")
    demo.add_argument("--gs-iterations", type=iterations_count(),
                      help="textbook GS iterations (2000)")
    demo.add_argument("--calibration-iterations", type=iterations_count(),
                      help="iterations of diffcam's calibration (300)")
    demo.set_defaults(func=_cmd_demo)


def _cmd_data(args) -> int:

    paths = export_captures(args.name, args.out, overwrite=args.force)
    print(f"diffcam data: {len(paths)} files → {args.out}")
    return 0


def _add_data(sub) -> None:

    data = sub.add_parser("data", help="write a built-in capture set as image files",
                          description="Write a built-in measured capture set (Waller Lab "
                                      "DiffuserCam data) as the image files a camera gives: "
                                      "'hand' (a 2-D capture and its PSF) or 'usaf3d' (a "
                                      "3-D capture and its 44-plane PSF stack, one file "
                                      "per plane) or 'scenes' (seven colour captures, each "
                                      "with the lensed photograph of its scene). See "
                                      "docs/real_data.md and docs/scene_psf.md.")
    data.add_argument("name", choices=list(CAPTURES), help="capture set")
    data.add_argument("-o", "--out", default="captures", help="folder (default: captures)")
    data.add_argument("--force", action="store_true", help="overwrite existing files")
    data.set_defaults(func=_cmd_data)


def _add_plan(sub) -> None:
    plan = sub.add_parser("plan", help="check the sampling of a diffuser-camera geometry",
                          description="Report Fresnel numbers, point-source chirp sampling, "
                                      "propagator validity and padding before simulating.")
    plan.add_argument("--wavelength", type=length_arg("wavelength"), default="532nm",
                      help="wavelength, with a unit")
    plan.add_argument("--pixel", type=length_arg("pixel"), required=True,
                      help="grid pitch, with a unit (3.45um)")
    plan.add_argument("--n", type=grid_count(), required=True, help="samples per side")
    plan.add_argument("--z1", type=length_arg("z1"), required=True,
                      help="smallest source depth, with a unit (22mm)")
    plan.add_argument("--z2", type=length_arg("z2"), required=True,
                      help="diffuser to sensor, with a unit (1mm)")
    plan.add_argument("--aperture-radius", type=length_arg("aperture-radius"), required=True,
                      help="aperture radius, with a unit (2.3mm)")
    plan.add_argument("--max-offset", type=length_arg("max-offset"), default="0mm",
                      help="largest lateral source offset, with a unit")
    plan.set_defaults(func=_cmd_plan)


def _add_calibrate(sub) -> None:
    cal = sub.add_parser("calibrate", help="diffuser phase from near/far captures",
                         description="Estimate the diffuser phase from a near-field capture "
                                     "(diffuser on the sensor) and a far-field capture (back "
                                     "focal plane of a Fourier lens); writes a phase .npz.")
    cal.add_argument("near", help="near-field capture (.png, .tif, .npy)")
    cal.add_argument("far", help="far-field capture at the lens's back focal plane")
    cal.add_argument("--focal-length", type=length_arg("focal-length"), required=True,
                     help="Fourier lens focal length, with a unit (5cm)")
    cal.add_argument("--wavelength", type=length_arg("wavelength"), required=True,
                     help="wavelength, with a unit (532nm)")
    cal.add_argument("--pixel", type=length_arg("pixel"), required=True,
                     help="sensor pixel pitch of both captures, with a unit (3.45um)")
    cal.add_argument("--aperture-radius", type=length_arg("aperture-radius"), required=True,
                     help="radius of the aperture before the diffuser, with a unit")
    cal.add_argument("--near-distance", type=length_arg("near-distance"), default="0mm",
                     help="diffuser to near-capture plane, free-space equivalent (0.5 mm "
                          "of n = 1.5 cover glass ≈ 0.33mm)")
    cal.add_argument("--dx", type=length_arg("dx"), help="diffuser grid pitch (default: --pixel)")
    cal.add_argument("--grid", type=grid_count(16),
                     help="calibration grid (default: 2× the aperture)")
    cal.add_argument("--background", type=float, default=0.0, help="dark level, counts")
    cal.add_argument("--saturation", type=float, help="raw count of a saturated pixel")
    cal.add_argument("--solver", choices=["default", "gs", "hio", "raar"], default="default",
                     help="default: RAAR with restarts, then least squares")
    cal.add_argument("--iterations", type=iterations_count(), default=300,
                     help="projection iterations")
    cal.add_argument("--restarts", type=count(1, MAX_RESTARTS, "diffcam.apps.cli.MAX_RESTARTS"),
                     help="random starts of the projections (default 4; 1 with --psf, "
                          "which starts flat)")
    cal.add_argument("--seed", type=int, default=0, help="seed of the random starts")
    cal.add_argument("--psf", help="a captured on-axis PSF at the grid pitch, background "
                     "subtracted: a third intensity plane for the projections (it resolves "
                     "the twin and un-stalls strongly scattering diffusers)")
    cal.add_argument("--psf-z1", type=length_arg("psf-z1"), help="source depth of --psf")
    cal.add_argument("--psf-z2", type=length_arg("psf-z2"), help="diffuser to sensor for --psf")
    cal.add_argument("-o", "--out", required=True, help="phase file (.npz)")
    cal.set_defaults(func=_cmd_calibrate)


def _add_psf(sub) -> None:
    ps = sub.add_parser("psf", help="PSFs at depths from a phase file or a stack fit, or "
                                    "across the field from a field-dependent PSF",
                        description="Compute the camera's PSF (paper Eq. 7) for point "
                                    "sources on axis at each depth; writes .npz or a "
                                    "multi-page ImageJ TIFF with metadata. Given a model "
                                    "from `diffcam fit`, predict its planes (--planes; "
                                    "`diffcam predict` is an alias). Given a field-"
                                    "dependent PSF (`diffcam calibrate-psf --field`), its "
                                    "registered PSFs at field positions (--at).")
    ps.add_argument("phase", help="phase file from `diffcam calibrate`, a stack-fit model "
                                  "from `diffcam fit`, or a field-dependent PSF")
    ps.add_argument("--z1", type=lengths_arg("z1"),
                    help="depth(s): 25mm, 22mm,25mm or 22mm:30mm:1mm (end included); "
                         "needed with a phase file")
    ps.add_argument("--z2", type=length_arg("z2"),
                    help="diffuser to sensor; needed with a phase file")
    ps.add_argument("--planes", type=planes_arg,
                    help="stack-fit model only: planes, e.g. 0:43 (default: all)")
    ps.add_argument("--kappa", type=float,
                    help="stack-fit model only: render with this depth-law exponent (0: "
                         "frozen distance)")
    ps.add_argument("--rendered-only", action="store_true",
                    help="stack-fit model only: the model's rendering alone, without the "
                         "measured planes' carried residuals")
    ps.add_argument("--crop", type=grid_count(1), help="square crop of each PSF (samples)")
    ps.add_argument("--at", type=positions_arg,
                    help="field-dependent PSF only: field positions Y,X;… (sensor pixels "
                         "from the axis; default: the model's own)")
    ps.add_argument("-o", "--out", required=True,
                    help="output .npz or .tif (a stack fit: .tif or .npy)")
    ps.add_argument("--processes", type=int, default=1,
                    help="JAX processes on this machine, each computing its share of "
                         "the depths, writing one file (a cluster: start one diffcam psf "
                         "per task instead, see docs/distributed.md)")
    ps.set_defaults(func=_cmd_psf)


def _compare_stack_fit(args, model) -> int:
    """``diffcam compare STACK --model MODEL.npz``: as ``diffcam compare-stack``."""

    given = [f for f, v in (("--z1", args.z1), ("--z2", args.z2), ("--pixel", args.pixel),
                            ("--anchor", args.anchor)) if v is not None]
    if given:
        raise DiffcamError(f"{model} is a stack fit: it compares by plane index; it "
                           f"does not take "
                           f"{', '.join(given)}.")
    return cmd_compare_stack(argparse.Namespace(stack=args.captured, model=model,
                                                 key=args.key, out=args.out, json=args.json))


def _add_compare(sub) -> None:
    cmp_ = sub.add_parser("compare", help="captured vs model vs scaled PSFs per depth",
                          description="Pearson (registered) of the wave model and of the "
                                      "scaling baseline against captured PSFs, per depth; "
                                      "prints a table and writes a figure. With a stack "
                                      "fit (from `diffcam fit`), per plane against the "
                                      "baseline and the frozen-distance rendering "
                                      "(`diffcam compare-stack` is an alias). With a field-"
                                      "dependent PSF, per field position (--at) against "
                                      "the one on-axis PSF.")
    cmp_.add_argument("captured", help="captured PSF stack (multi-page TIFF or diffcam .npz)")
    cmp_.add_argument("--model", help="camera model: a phase file from `diffcam calibrate` "
                                      "(with --z2) or a stack fit from `diffcam fit`")
    cmp_.add_argument("--phase", help="the same as --model")
    cmp_.add_argument("--json", help="with a stack fit: per-plane scores (.json)")
    cmp_.add_argument("--key", help="with a stack fit: array name inside an .npz or .mat "
                                    "stack")
    cmp_.add_argument("--z1", type=lengths_arg("z1"), help="depth of each captured PSF")
    cmp_.add_argument("--z2", type=length_arg("z2"), help="diffuser to sensor (with --phase)")
    cmp_.add_argument("--pixel", type=length_arg("pixel"), help="captured PSFs' pixel pitch")
    cmp_.add_argument("--anchor", type=length_arg("anchor"),
                      help="depth of the PSF the scaling baseline magnifies (default: first)")
    cmp_.add_argument("--at", type=positions_arg, help="with a field-dependent PSF: the "
                      "position Y,X;… of each captured PSF (sensor pixels from the axis)")
    cmp_.add_argument("-o", "--out", required=True, help="figure (.png)")
    cmp_.set_defaults(func=_cmd_compare)

def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="diffcam",
        description="Differentiable wave optics for lensless diffuser cameras.",
        epilog="Compiled programs are kept in $DIFFCAM_CACHE/jax (default ~/.cache/diffcam/"
               "jax, at most DIFFCAM_CACHE_MAX_MB megabytes, default "
               f"{DEFAULT_MAX_MB}), so a repeated command starts faster; "
               "JAX_COMPILATION_CACHE_DIR chooses another folder, DIFFCAM_NO_CACHE=1 turns "
               "the cache off.")
    parser.add_argument("--version", action="version",
                        version=f"diffcam {installed_version()}")
    talk = parser.add_mutually_exclusive_group()
    talk.add_argument("-q", "--quiet", dest="global_quiet", action="store_true",
                      help="print only errors: no progress bars, no summaries")
    talk.add_argument("-v", "--verbose", action="store_true",
                      help="also print the FFT backend, JAX's device and the wall time")
    sub = parser.add_subparsers(dest="command", required=True)
    # every subcommand's --help shows its defaults (a parser may still pass its own)
    sub._parser_class = functools.partial(Parser, formatter_class=DefaultsFormatter)
    for add in (_add_demo, _add_data, _add_plan, add_reconstruct, _add_calibrate,
                add_calibrate_psf, _add_psf, _add_compare, add_fit, add_design):
        add(sub)
    for name, command in sub.choices.items():
        command.epilog = limits(name)
    return parser


def check_environment() -> None:
    """The environment's settings, checked before any work: ``DIFFCAM_FFT`` (a backend,
    `diffcam.core.backend.fft_backend`) and ``DIFFCAM_FFT_THREADS`` (a positive
    integer when set, whichever backend runs)."""

    core.backend.fft_backend()
    core.fftw.environment_threads()


@contextlib.contextmanager
def _verbosity(args):
    """``diffcam -q``: standard output and progress bars off (errors still reach
    stderr); ``diffcam -v``: the FFT backend and device first, the wall time last."""
    if args.global_quiet:
        progress = os.environ.get("DIFFCAM_PROGRESS")
        os.environ["DIFFCAM_PROGRESS"] = "0"
        try:
            with open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
                yield
        finally:
            if progress is None:
                os.environ.pop("DIFFCAM_PROGRESS", None)
            else:
                os.environ["DIFFCAM_PROGRESS"] = progress
        return
    if not args.verbose:
        yield
        return
    import jax


    print(f"diffcam {args.command}: JAX {jax.__version__} on {jax.devices()[0]}; "
          f"{core.backend.fft_status()}; {memory.status()}; compilation cache "
          f"{jax.config.jax_compilation_cache_dir or 'off'}", file=sys.stderr)
    start = time.perf_counter()
    try:
        yield
    finally:
        print(f"diffcam {args.command}: {time.perf_counter() - start:.1f} s", file=sys.stderr)


def main(argv=None, *, compilation_cache: bool = False) -> int:
    """The ``diffcam`` command line ``argv`` (default: ``sys.argv``); returns the exit
    status. ``compilation_cache``: keep compiled programs on disk
    (`enable_compilation_cache`), once the command line
    is read (``--help`` loads no JAX)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    try:
        with interrupts_as_keyboard_interrupt():
            _join_run(args)
            if compilation_cache:
                enable_compilation_cache()
            with _verbosity(args), one_line_warnings(args.command):
                check_environment()
                return args.func(args)
    except DiffcamError as e:
        report_error(args.command, str(e))
        return 2
    except KeyboardInterrupt:
        print(f"diffcam {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # one of several processes: one line, then run() ends at once
        if not in_distributed_run():
            raise
        report_error(args.command, f"{type(e).__name__}: {e}")
        return 1


def run() -> None:
    """The ``diffcam`` command: `main` with compiled programs cached on disk
    (`enable_compilation_cache`), then the process
    ends with its status (`end_process`), also after
    ``--help``, ``--version`` and usage errors (argparse's ``SystemExit``)."""
    try:
        status = main(compilation_cache=True)
    except KeyboardInterrupt:  # came after main's own handler, as it returned
        status = 130
    except SystemExit as done:
        if not isinstance(done.code, (int, type(None))):
            raise
        status = done.code or 0
    end_process(status)


if __name__ == "__main__":
    run()
