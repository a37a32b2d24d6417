"""``diffcam calibrate-psf``: the camera's PSF from raw captures of scenes whose ground
truth is known (`diffcam.calibrate.scene_psf.fit_psf_from_scenes`).

    diffcam data scenes -o scenes
    diffcam calibrate-psf scenes/raw_*.tif --truth scenes/truth_*.tif -o psf.tif
    diffcam calibrate-psf diffuser/im*.npy --truth lensed/im*.npy --channel-order BGR -o psf.tif

Raws and truths pair up in the order given (a shell glob sorts both alike). Colour
files give one PSF per channel, written as an RGB TIFF; grayscale files one PSF. With
two pairs or more, one pair is held out of a second fit and predicted from its truth:
the printed Pearson correlation per channel says how well the calibration explains a
capture it did not see. The model is one PSF per channel (rank 1): a field-dependent
PSF (`diffcam.calibrate.scene_psf.fit_field_psf_from_scenes`) predicts held-out
Lensless Learning raws about as well and, at 270 × 480, reconstructs them 0.2 to 0.5 dB
better with the same solver (docs/scene_psf.md); `diffcam reconstruct` does not take
it.
"""

from __future__ import annotations

import json
import sys

import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam import calibrate, evaluate  # lazy: loaded on use
from diffcam.apps.common import iterations_count
from diffcam.io import as_rgb, atomic_output, check_output_path, read_image

CHANNEL_ORDERS = ("RGB", "BGR")


def read_pairs(raws, truths, channel_order: str) -> tuple[np.ndarray, np.ndarray]:
    """The raw and truth files as ``(k, c, ny, nx)`` arrays (RGB for colour), checked
    (`diffcam.calibrate.scene_psf.check_scene_pairs`)."""

    if len(raws) != len(truths):
        raise DiffcamError(f"{len(raws)} raw file(s) but {len(truths)} --truth file(s); "
                           f"give one truth per raw, in the same order.")

    def read(path):
        capture = read_image(path, channel_order=channel_order)
        if capture.channels is None:
            if capture.image.ndim != 2:
                raise DiffcamError(f"{path}: a stack of {capture.image.shape[0]} images; "
                                   f"give one image per file.")
            return capture.image
        return as_rgb(capture)

    try:
        return calibrate.scene_psf.check_scene_pairs([read(p) for p in raws],
                                                     [read(p) for p in truths])
    except DiffcamError as err:
        raise DiffcamError(f"{err} (raws {raws[0]} …, truths {truths[0]} …)") from None


def holdout_scores(raws, truths, options) -> np.ndarray:
    """Pearson correlation per channel of the last pair's raw with its prediction by a
    PSF fitted to the other pairs."""

    cal = calibrate.fit_psf_from_scenes(raws[:-1], truths[:-1], options)
    predicted = calibrate.predict_raw(cal, truths[-1])
    return np.asarray(evaluate.pearson(predicted, raws[-1]))


def write_psf(path, psf: np.ndarray) -> None:
    """The PSF as a float32 TIFF, atomically: RGB ``(ny, nx, 3)`` for three channels,
    grayscale for one."""
    import tifffile


    with atomic_output(path) as tmp:
        if len(psf) == 3:
            tifffile.imwrite(tmp, np.moveaxis(psf, 0, -1), photometric="rgb")
        else:
            tifffile.imwrite(tmp, psf[0])


def _cmd_calibrate_psf(args) -> int:

    out = check_output_path(args.out, suffixes=(".tif", ".tiff"))
    if args.json:
        check_output_path(args.json, suffixes=(".json",))
    options = calibrate.ScenePsfOptions(iterations=args.iterations, flip=args.flip)
    raws, truths = read_pairs(args.raws, args.truth, args.channel_order)
    k, c, ny, nx = raws.shape
    print(f"diffcam calibrate-psf: {k} pair(s), {c} channel(s), {ny}×{nx}; FISTA, "
          f"{args.iterations} iterations", file=sys.stderr)
    cal = calibrate.fit_psf_from_scenes(raws, truths, options, progress=not args.quiet)
    summary = {"pairs": k, "channels": c, "model": "one PSF per channel", "rank": 1,
               "flip": cal.flip,
               "flip_residuals": cal.flip_residuals, "offset": cal.offset.tolist(),
               "residual": float(cal.residual[-1]), "iterations": args.iterations}
    if k >= 2 and not args.no_check:
        again = calibrate.ScenePsfOptions.of(options, flip=cal.flip)
        scores = holdout_scores(raws, truths, again)
        summary["holdout_pearson"] = scores.tolist()
    write_psf(out, cal.psf)
    if args.json:
        with atomic_output(args.json) as tmp:
            tmp.write_text(json.dumps(summary, indent=2))
    held = ("" if "holdout_pearson" not in summary else "; held-out pair predicted with "
            "Pearson " + ", ".join(f"{v:.3f}" for v in summary["holdout_pearson"]))
    print(f"diffcam calibrate-psf: one PSF per channel (rank 1), flip {cal.flip}, offset "
          f"{', '.join(f'{v:.3g}' for v in cal.offset)}, relative misfit "
          f"{summary['residual']:.3g}{held} → {out}")
    return 0


def add_calibrate_psf(sub) -> None:
    """Add ``calibrate-psf`` to the ``diffcam`` subcommands."""

    cal = sub.add_parser(
        "calibrate-psf", help="PSF from raw captures of scenes with known ground truth",
        description="Fit the camera's PSF (one per colour channel) to raw captures and "
                    "the ground-truth scene of each (a lensed photograph on the sensor "
                    "grid), by non-negative least squares; the flip between the two "
                    "frames and a dark offset per channel are fitted too. See "
                    "docs/scene_psf.md.")
    cal.add_argument("raws", nargs="+", help="raw captures (.png, .tif, .npy)")
    cal.add_argument("--truth", nargs="+", required=True, metavar="TRUTH",
                     help="ground-truth scene of each raw, same order and shape")
    cal.add_argument("--channel-order", choices=CHANNEL_ORDERS, metavar="ORDER",
                     help="channel order of colour files: RGB or BGR (OpenCV .npy "
                          "arrays); needed for colour .npy, PNG/TIFF are RGB by default")
    cal.add_argument("--flip", choices=["auto", "none", "y", "x", "yx"], default="auto",
                     help="flip of the truths into the sensor frame; auto tries each")
    cal.add_argument("--iterations", type=iterations_count(), default=300, metavar="N",
                     help="FISTA iterations (early stopping is the regularisation)")
    cal.add_argument("--no-check", action="store_true",
                     help="skip the held-out check (a second fit without the last pair)")
    cal.add_argument("--json", metavar="FILE", help="write what was fitted as JSON")
    cal.add_argument("--quiet", action="store_true", help="no progress bars")
    cal.add_argument("-o", "--out", required=True, help="PSF .tif (RGB for colour input)")
    cal.set_defaults(func=_cmd_calibrate_psf)
