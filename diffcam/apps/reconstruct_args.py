"""The command line of ``diffcam reconstruct`` (`add_reconstruct`): its options,
their defaults and help, built without loading the solvers; the command itself is
`diffcam.apps.reconstruct_cli.cmd_reconstruct`, loaded when it runs."""

from __future__ import annotations

from diffcam import apps  # lazy: diffcam.apps.reconstruct_cli loads when the command runs
from diffcam.apps.common import (DefaultsFormatter, count, iterations_count, length_arg,
                                 planes_arg)
from diffcam.apps.reconstruct_inputs import DARK_RING, WORKING_SIZE, dark_arg, gains_arg
from diffcam.core.lazy import module_constant

ITERATIONS = {"admm": 100, "rl": 1000, "fista": 200}
"""Default iterations per method in 2-D, measured on the shipped hand (docs/real_data.md):
ADMM-TV has converged by 100 (correlation 0.998 with a 200-step FISTA reference, the
same at 300); Richardson–Lucy needs about 1000 (0.996; at 150 the fingers are not
resolved, 0.959). FISTA (plain non-negative least squares, regularised by its early
stop) 200, as the Lensless Learning benchmark runs it (docs/scene_psf.md)."""
ITERATIONS_3D = {"admm": 60, "rl": 300}
"""The same for ``--3d``: ADMM-TV with `diffcam.reconstruct.admm.VOLUME` 60 (the
shipped USAF capture, 44 planes of 270 × 320: the measurements behind the choice are in
docs/volume.md); Richardson–Lucy 300."""


def _cmd_reconstruct(args) -> int:
    """`diffcam.apps.reconstruct_cli.cmd_reconstruct`, its module loaded now."""
    return apps.reconstruct_cli.cmd_reconstruct(args)


def add_reconstruct(sub) -> None:
    """Add ``reconstruct`` to the ``diffcam`` subcommands."""

    max_planes = module_constant("diffcam.calibrate.stack.result.MAX_PLANES")
    rec = sub.add_parser(
        "reconstruct", help="deconvolve a sensor image with a PSF (or a volume with --3d)",
        formatter_class=DefaultsFormatter,
        description="Reconstruct a scene from a raw capture and the PSF of its depth. With "
                    "a PSF stack, pick the plane by --depth, --plane, or else the plane "
                    "whose PSF explains the capture best (least data misfit); with --3d, "
                    "reconstruct every plane as a volume "
                    "(OUT.tif, OUT_max.png, OUT_depth.png, OUT_projections.png, "
                    "OUT_montage.png). ADMM-TV solves for the raw scaled to unit L2 norm "
                    "(each colour channel on its own); "
                    "in 3-D with lateral TV 1e-5, axial TV 2e-6, an L1 weight of 2e-5, "
                    "residual-balanced penalties and over-relaxation 1.85 "
                    "(diffcam.reconstruct.admm.VOLUME), "
                    "each PSF plane's vertical footprint first matched to the "
                    "capture's (--psf-envelope), all recorded in OUT.tif's metadata. See "
                    "docs/cli_reconstruct.md and docs/volume.md.")
    rec.add_argument("raw", help="raw capture, grayscale or colour (.png, .tif, .npy)")
    rec.add_argument("--channel-order", choices=["RGB", "BGR"], metavar="ORDER",
                     help="channel order of the colour raw (and of a colour .npy PSF), RGB "
                          "or BGR (OpenCV .npy arrays); needed for colour .npy; PNG/TIFF "
                          "raws are RGB by default, PNG/TIFF PSFs always")
    rec.add_argument("--white-balance", type=gains_arg, metavar="auto|R,G,B",
                     help="colour: gains per channel, or 'auto' (grey world); default none "
                          "(a PSF per channel from calibrate-psf already balances them)")
    rec.add_argument("--psf", required=True, metavar="SOURCE",
                     help="PSF image or stack (.png/.tif/.npy, multi-page TIFF, .npz or .tif "
                          "from `diffcam psf`, .mat), a folder or a quoted glob "
                          "('psfs/*.png') of single-plane images (natural name order), "
                          "a model .npz from `diffcam fit`, or a field-dependent PSF .npz "
                          "from `diffcam calibrate-psf --field` (2-D)")
    rec.add_argument("--planes", type=planes_arg, metavar="PLANES",
                     help="planes of the stack or model to use, e.g. 0:43 (ends included), "
                          f"0:43:2 or 3,7,12 (default: all; at most {max_planes})")
    rec.add_argument("--3d", dest="three_d", action="store_true",
                     help="reconstruct a volume over all the (selected) planes; -o OUT.tif")
    rec.add_argument("--depth", type=length_arg("depth"), metavar="Z1",
                     help="2-D: source depth z1 to use, with a unit (25mm)")
    rec.add_argument("--plane", type=count(0, max_planes - 1), metavar="INDEX",
                     help="2-D: index of the PSF plane to use")
    rec.add_argument("--method", choices=["admm", "rl", "wiener", "fista"], default="admm",
                     help="ADMM-TV, Richardson–Lucy, Wiener (2-D only) or FISTA (plain "
                          "non-negative least squares, 2-D only); a field-dependent PSF "
                          "takes admm or fista")
    rec.add_argument("--iterations", type=iterations_count(), metavar="N",
                     help="solver iterations (default: " + ", ".join(
                         f"{n} for {m}" for m, n in ITERATIONS.items()) + "; with --3d "
                          + ", ".join(f"{n} for {m}" for m, n in ITERATIONS_3D.items())
                          + "; at most "
                          + f"{module_constant('diffcam.reconstruct.checks.MAX_ITERATIONS')})")
    _add_input_arguments(rec)
    rec.set_defaults(func=_cmd_reconstruct)


def _add_input_arguments(rec) -> None:
    """The options of ``reconstruct`` that prepare its inputs and shape its output."""

    rec.add_argument("--bias", type=float, metavar="COUNTS",
                     help="sensor bias, counts: the same level subtracted from both the raw "
                          "and the PSFs (not with --dark-raw/--dark-psf)")
    rec.add_argument("--dark-raw", type=dark_arg, metavar="COUNTS|auto",
                     help="dark level of the raw, counts (R,G,B: one per colour channel), "
                          f"or 'auto': the median of a {DARK_RING}-pixel ring at the frame "
                          "border, per channel")
    rec.add_argument("--dark-psf", type=dark_arg, metavar="COUNTS|auto",
                     help="dark level of the PSFs, counts, or 'auto': per plane, the "
                          f"median of a {DARK_RING}-pixel ring at the frame border")
    rec.add_argument("--psf-envelope", choices=["mask", "auto", "none"],
                     help="--3d: 'auto' (default) multiplies each PSF plane by the "
                          "vertical Gaussian whose footprint explains the capture's row "
                          "profile best (diffcam.io.envelope_widths); 'mask' (admm only) "
                          "keeps the PSFs as measured and puts a vertical Gaussian sensor "
                          "window S(y), fitted to the capture's row profile, in the "
                          "forward model b = S·crop(Σ h*v) (diffcam.io.fit_sensor_window); "
                          "'none' uses the PSFs as measured; σ goes to OUT.tif's metadata")
    degree = "diffcam.reconstruct.sensor_terms.MAX_BACKGROUND_DEGREE"
    rec.add_argument("--background", type=count(0, module_constant(degree), degree),
                     metavar="DEGREE",
                     help="--3d with admm: solve jointly for a smooth background on the "
                          "sensor, a 2-D polynomial of this degree (ambient or scattered "
                          "light, a dark-level gradient; summary in OUT.tif's metadata); "
                          "default: none (docs/volume.md measures it)")
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
