"""The ``diffcam`` command line. Lengths take units (``25mm``, ``3.45um``, ``532nm``)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from .errors import DiffcamError
from .units import parse_length


def _length(name):
    def convert(text):
        try:
            return parse_length(text, name=name)
        except DiffcamError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    convert.__name__ = name
    return convert


@contextlib.contextmanager
def atomic_output(path):
    """Yield a temporary path beside ``path``; move it into place only on success.

    Nothing half-written is left behind on an error or Ctrl-C.
    """
    path = Path(path)
    if path.parent and not path.parent.exists():
        raise DiffcamError(f"output folder {path.parent} does not exist; create it first.")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def save_image(path, image) -> None:
    """Write an image atomically: ``.png`` (16-bit, min–max scaled), ``.tif``/``.tiff``
    (float32, multi-page for a stack), or ``.npy`` (as is)."""
    image = np.asarray(image, dtype=np.float32)
    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".tif", ".tiff", ".npy"):
        raise DiffcamError(f"{path}: write .png, .tif or .npy, not {suffix!r}.")
    with atomic_output(path) as tmp:
        if suffix == ".png":
            from skimage.io import imsave

            if image.ndim != 2:
                raise DiffcamError(f"{path}: PNG holds one 2-D image, got shape "
                                   f"{image.shape}; write .tif for a stack.")
            lo, hi = float(image.min()), float(image.max())
            scaled = (image - lo) / (hi - lo) if hi > lo else np.zeros_like(image)
            imsave(tmp, np.round(scaled * 65535).astype(np.uint16), check_contrast=False)
        elif suffix == ".npy":
            np.save(tmp, image)
        else:
            import tifffile

            tifffile.imwrite(tmp, image, imagej=image.ndim == 3)


def _read_psfs(path):
    """A PSF or PSF stack from an image file or a diffcam ``.npz`` stack; returns
    ``(psfs, depths or None)`` with psfs ``(my, mx)`` or ``(nz, my, mx)``."""
    from .io import read_image

    if Path(path).suffix.lower() == ".npz":
        from .stack import load_stack

        stack = load_stack(path)
        return np.asarray(stack.psfs), np.asarray(stack.z1)
    return read_image(path).image, None


def _cmd_reconstruct(args) -> int:
    from .io import downsample, read_image, subtract_background
    from .reconstruct import admm_tv, focus_sweep, richardson_lucy, wiener

    raw = read_image(args.raw).image
    psfs, depths = _read_psfs(args.psf)
    if raw.ndim != 2:
        raise DiffcamError(f"{args.raw}: expected a grayscale image, got shape {raw.shape}.")
    if args.bias is not None:
        raw = subtract_background(raw, args.bias)
        psfs = subtract_background(psfs, args.bias)
    if args.downsample > 1:
        raw, psfs = downsample(raw, args.downsample), downsample(psfs, args.downsample)
    if psfs.ndim == 3:
        if args.depth is not None:
            if depths is None:
                raise DiffcamError("--depth needs a PSF stack with depths (.npz from "
                                   "`diffcam psf`); use --plane for an image stack.")
            plane = int(np.argmin(np.abs(depths - args.depth)))
        elif args.plane is not None:
            plane = args.plane
        else:
            sweep = focus_sweep(raw, psfs, num_iter=min(args.iterations, 30))
            plane = int(sweep.best)
            print(f"diffcam reconstruct: sharpest plane {plane} of {len(psfs)}")
        if not 0 <= plane < len(psfs):
            raise DiffcamError(f"--plane {plane} is outside the stack of {len(psfs)} PSFs.")
        psfs = psfs[plane]
    if psfs.shape[0] > raw.shape[0] or psfs.shape[1] > raw.shape[1]:
        raise DiffcamError(f"PSF {psfs.shape} is larger than the image {raw.shape}; crop "
                           f"the PSF or use the same downsampling for both.")
    if args.method == "rl":
        rec = richardson_lucy(raw, psfs, args.iterations)
    elif args.method == "admm":
        rec = admm_tv(raw / np.linalg.norm(raw), psfs / np.linalg.norm(psfs), args.iterations)
    else:
        rec = wiener(raw, psfs)
    save_image(args.out, rec.image)
    print(f"diffcam reconstruct: {args.method}, {int(np.max(rec.iterations))} iterations, "
          f"residual {float(np.nanmin(rec.residual)):.3g} → {args.out}")
    return 0


def _cmd_demo(args) -> int:
    from .demo import run_demo
    from .paper import Settings

    base = Settings(grid=4000) if args.full else Settings()
    changes = {k: v for k, v in (("grid", args.grid), ("gs_iterations", args.gs_iterations),
                                 ("calibration_iterations", args.calibration_iterations))
               if v is not None}
    if changes.get("grid", 1024) < 600:
        raise DiffcamError("--grid must be at least 600 samples: the 512² diffuser needs "
                           "room around it for the far field.")
    run_demo(args.out, settings=Settings(**{**base.__dict__, **changes}))
    return 0


def _cmd_plan(args) -> int:
    from .sampling import plan_sampling

    print(plan_sampling(args.wavelength, args.pixel, args.n, args.z1, args.z2,
                        args.aperture_radius, max_offset=args.max_offset))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffcam",
        description="Differentiable wave optics for lensless diffuser cameras.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the built-in demonstration and write a report",
                          description="Run the built-in demonstration on built-in data and "
                                      "write PNG figures and metrics.json to a folder.")
    demo.add_argument("-o", "--out", default="diffcam-report", help="report folder")
    demo.add_argument("--full", action="store_true",
                      help="the paper's 4000×4000 grid (tens of minutes on 2 cores)")
    demo.add_argument("--grid", type=int, help="simulation grid, samples per side "
                                               "(default 1024; 4000 with --full)")
    demo.add_argument("--gs-iterations", type=int, help="textbook GS iterations (2000)")
    demo.add_argument("--calibration-iterations", type=int,
                      help="iterations of diffcam's calibration (300)")
    demo.set_defaults(func=_cmd_demo)

    plan = sub.add_parser("plan", help="check the sampling of a diffuser-camera geometry",
                          description="Report Fresnel numbers, point-source chirp sampling, "
                                      "propagator validity and padding before simulating.")
    plan.add_argument("--wavelength", type=_length("wavelength"), default=532e-9)
    plan.add_argument("--pixel", type=_length("pixel"), required=True, help="grid pitch")
    plan.add_argument("--n", type=int, required=True, help="samples per side")
    plan.add_argument("--z1", type=_length("z1"), required=True, help="smallest source depth")
    plan.add_argument("--z2", type=_length("z2"), required=True, help="diffuser to sensor")
    plan.add_argument("--aperture-radius", type=_length("aperture-radius"), required=True)
    plan.add_argument("--max-offset", type=_length("max-offset"), default=0.0,
                      help="largest lateral source offset")
    plan.set_defaults(func=_cmd_plan)

    rec = sub.add_parser("reconstruct", help="deconvolve a sensor image with a PSF",
                         description="Reconstruct a scene from a raw capture and the PSF of "
                                     "its depth. With a PSF stack, pick the plane by --depth, "
                                     "--plane, or else the sharpest reconstruction.")
    rec.add_argument("raw", help="raw capture (.png, .tif, .npy)")
    rec.add_argument("--psf", required=True,
                     help="PSF image, multi-page TIFF stack, or .npz from `diffcam psf`")
    rec.add_argument("--depth", type=_length("depth"), help="source depth z1 to use")
    rec.add_argument("--plane", type=int, help="index of the PSF plane to use")
    rec.add_argument("--method", choices=["rl", "admm", "wiener"], default="rl")
    rec.add_argument("--iterations", type=int, default=150)
    rec.add_argument("--bias", type=float, help="sensor bias (counts) subtracted from both")
    rec.add_argument("--downsample", type=int, default=1, help="box-average factor")
    rec.add_argument("-o", "--out", required=True, help="output .png, .tif or .npy")
    rec.set_defaults(func=_cmd_reconstruct)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except DiffcamError as e:
        print(f"diffcam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"diffcam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
