"""``diffcam design``: a diffuser surface optimised so that the PSFs of a depth range are
unlike each other (`diffcam.design.optimise.design`), written as a design file and a
TIFF height map in metres.

    diffcam design -o diffuser.npz                      # smooth surface, 256², 16 depths
    diffcam design --surface lenslets --lenses 36 -o mla.npz
    diffcam design -o diffuser.npz --steps 600 --resume   # continue the same design
"""

from __future__ import annotations

import math
from pathlib import Path

from diffcam import design, model, optics  # lazy: loaded on use (JAX, optax)
from diffcam.apps.common import count, grid_count, iterations_count, length_arg
from diffcam.core.errors import DiffcamError
from diffcam.io import check_output_path

__all__ = ["add_design"]


def _camera(args):
    """The camera of the design: the grid, z2 and aperture of the command line (the
    aperture defaults to a quarter of the grid's width), zero-padded so the Fresnel
    transfer function of the farthest depth's z_eff = z1·z2/(z1 + z2) does not alias at
    the longest wavelength λ + bandwidth on the field's grid, ``oversample``× finer
    than the pixels (padded width N·dx ≥ oversample·λ·z_eff/dx)."""
    radius = args.aperture if args.aperture is not None else args.grid * args.pixel / 4
    z_eff = optics.propagation.effective_distance(args.far, args.z2)
    pad = optics.propagation.transfer_pad(args.grid, args.pixel,
                       args.oversample * (args.wavelength + args.bandwidth), z_eff)
    return model.Camera(wavelength=args.wavelength, z2=args.z2, dx=args.pixel,
                        aperture_radius=radius, shape=(args.grid, args.grid), pad=pad)


def _light(args) -> str:
    """What the PSFs are of, when not one line from a point sampled at pixel centres."""
    parts = ([f"lines ±{args.bandwidth * 1e9:g} nm"] if args.bandwidth > 0 else []) + (
        [f"a disc source of radius {args.source_radius * 1e6:g} µm"]
        if args.source_radius > 0 else []) + (
        [f"{args.oversample}× oversampled, integrated over pixels"]
        if args.oversample > 1 else [])
    return "; PSFs of " + ", ".join(parts) if parts else ""


def _start(args, camera):
    """The random start: a smooth surface or a microlens array within the aperture."""
    shape = (args.grid, args.grid)
    if args.surface == "smooth":
        return design.SmoothSurface.random(args.seed, shape, args.pixel, args.feature,
                                           args.height)
    return design.LensletArray.random(args.seed, shape, args.pixel, args.feature,
                                      args.height, args.lenses,
                                      float(camera.aperture_radius))


def _cmd_design(args) -> int:
    out = check_output_path(args.out, suffixes=(".npz",))
    check_output_path(design.tiff_path(out))
    if args.near >= args.far:
        raise DiffcamError(f"--near ({args.near:g} m) must be closer than --far "
                           f"({args.far:g} m).")
    camera = _camera(args)
    z1 = design.depth_range(args.near, args.far, args.depths)
    options = design.DesignOptions(steps=args.steps, learning_rate=args.learning_rate,
                                   time_budget=args.time_budget, checkpoint=str(out),
                                   resume=args.resume, progress=not args.no_progress,
                                   objective=args.objective.replace("-", "_"),
                                   scenes=args.scenes, photons=args.photons,
                                   bandwidth=args.bandwidth,
                                   source_radius=args.source_radius,
                                   oversample=args.oversample)
    print(f"diffcam design: {args.surface} surface, {args.grid}×{args.grid} at "
          f"{args.pixel * 1e6:g} µm, heights 0–{args.height * 1e6:g} µm, features ≥ "
          f"{args.feature * 1e6:g} µm, n = {args.index:g}; {args.depths} depths "
          f"{args.near * 1e3:g}–{args.far * 1e3:g} mm (even in 1/z1), z2 "
          f"{args.z2 * 1e3:g} mm, aperture radius {float(camera.aperture_radius) * 1e3:.3g} "
          f"mm{_light(args)} ...", flush=True)
    result = design.design(_start(args, camera), camera, z1, args.index, options)
    before, after = result.history[0, 2], result.final["max_correlation"]
    per_step = result.seconds / max(result.steps, 1)
    if result.log_tau is not None:
        print(f"diffcam design: training volumes' relative reconstruction error "
              f"{result.history[0, 0]:.4f} (start) → {result.final['loss']:.4f}, TV weight "
              f"{options.tau:g} → {math.exp(float(result.log_tau)):.3g}")
    print(f"diffcam design: max cross-depth PSF correlation {before:.4f} (start) → "
          f"{after:.4f}; PSF spread {result.history[0, 3]:.3f} → "
          f"{result.final['spread']:.3f}\n"
          f"  {result.steps} steps ({result.stop_reason}), {result.seconds:.1f} s "
          f"({per_step:.3f} s/step, compilation included) → {out}, "
          f"{design.tiff_path(out)} (height map, m)")
    return 0


def add_design(sub) -> None:
    """Add ``design`` to the ``diffcam`` subcommands."""

    p = sub.add_parser(
        "design", help="optimise a manufacturable diffuser for depth discrimination",
        description="Optimise a diffuser surface (a smooth random surface, or a microlens "
                    "array) so that the PSFs of a depth range are unlike each other: the "
                    "largest Pearson correlation between two depths' PSFs is lowered, the "
                    "PSFs kept sparse. Writes the design file (.npz: height map, settings, "
                    "history; also the checkpoint --resume continues from) and the height "
                    "map as a float32 TIFF in metres. See docs/diffuser_design.md.")
    p.add_argument("--surface", choices=["smooth", "lenslets"], default="smooth",
                   help="parametrisation")
    p.add_argument("--grid", type=grid_count(16), default=256, help="samples per side")
    p.add_argument("--pixel", type=length_arg("pixel"), default="3um", help="grid pitch")
    p.add_argument("--wavelength", type=length_arg("wavelength"), default="532nm")
    p.add_argument("--z2", type=length_arg("z2"), default="2mm", help="diffuser to sensor")
    p.add_argument("--aperture", type=length_arg("aperture"),
                   help="aperture radius (default: a quarter of the grid's width)")
    p.add_argument("--near", type=length_arg("near"), default="10mm", help="closest depth z1")
    p.add_argument("--far", type=length_arg("far"), default="60mm", help="farthest depth z1")
    p.add_argument("--depths", type=count(2, 4096), default=16,
                   help="depths, evenly spaced in 1/z1")
    p.add_argument("--index", type=float, default=1.5, help="refractive index of the material")
    p.add_argument("--height", type=length_arg("height"), default="2um",
                   help="largest height (the surface lies in 0 … height)")
    p.add_argument("--feature", type=length_arg("feature"), default="30um",
                   help="minimum feature size (smallest lens diameter)")
    p.add_argument("--lenses", type=count(1, 10000), default=36,
                   help="lenses of a microlens array")
    p.add_argument("--objective", choices=["depth", "end-to-end"], default="depth",
                   help="depth discrimination, or the reconstruction of training volumes "
                        "by unrolled ADMM-TV (its TV weight learnt too)")
    p.add_argument("--scenes", type=count(1, 1000), default=4,
                   help="end to end: training volumes")
    p.add_argument("--photons", type=float, default=100.0,
                   help="end to end: photo-electrons per sensor pixel on average (shot "
                        "noise)")
    p.add_argument("--bandwidth", type=length_arg("bandwidth"), default="0",
                   help="design through three lines λ − bandwidth, λ, λ + bandwidth "
                        "(weights ½, 1, ½; default 0: one line)")
    p.add_argument("--source-radius", type=length_arg("source radius"), default="0",
                   help="design through the PSFs of a disc source of this radius "
                        "(default 0: a point)")
    p.add_argument("--oversample", type=count(1, 8), default=1,
                   help="field samples per pixel, per side: >1 integrates the "
                        "irradiance over each pixel (the grid is padded to match)")
    p.add_argument("--steps", type=iterations_count(), default=300, help="Adam steps in all")
    p.add_argument("--learning-rate", type=float, default=0.2, help="Adam's step size")
    p.add_argument("--time-budget", type=float,
                   help="also stop after this many seconds (default: the steps alone)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random start")
    p.add_argument("--resume", action="store_true",
                   help="continue the design in --out (same settings) up to --steps")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("-o", "--out", required=True, type=Path, help="design file (.npz)")
    p.set_defaults(func=_cmd_design)
