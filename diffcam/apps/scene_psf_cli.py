"""``diffcam calibrate-psf``: the camera's PSF from raw captures of scenes whose ground
truth is known (`diffcam.calibrate.scene.fit.fit_psf_from_scenes`), or with ``--field``
the camera's field-dependent PSF (`diffcam.calibrate.scene.fit.fit_field_psf_from_scenes`).

    diffcam data scenes -o scenes
    diffcam calibrate-psf scenes/raw_*.tif --truth scenes/truth_*.tif -o psf.tif
    diffcam calibrate-psf diffuser/im*.npy --truth lensed/im*.npy --channel-order BGR -o psf.tif
    diffcam calibrate-psf diffuser/im*.npy --truth lensed/im*.npy --channel-order BGR \
        --field 2x2 -o field.npz

Raws and truths pair up in the order given (a shell glob sorts both alike). Colour
files give one PSF per channel, written as an RGB TIFF; grayscale files one PSF. With
two pairs or more, one pair is held out of a second fit and predicted from its truth:
the printed Pearson correlation per channel says how well the calibration explains a
capture it did not see.

``--field GYxGX`` fits kernels at a ``GY × GX`` grid of field positions spanning the
sensor, interpolated across the field, one model per channel, and writes them
(`diffcam.model.field.save_field_psf`, with the flip, the dark offset per channel,
the inputs and the held-out scores in its metadata) for ``diffcam reconstruct --psf
field.npz``. It fits the one PSF too (it chooses the flip), predicts the held-out pair
with both and says which predicts it better.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam import calibrate, evaluate, model  # lazy: loaded on use
from diffcam.apps.common import iterations_count
from diffcam.io import as_rgb, atomic_output, check_output_path, read_image

CHANNEL_ORDERS = ("RGB", "BGR")


def read_pairs(raws, truths, channel_order: str) -> tuple[np.ndarray, np.ndarray]:
    """The raw and truth files as ``(k, c, ny, nx)`` arrays (RGB for colour), checked
    (`diffcam.calibrate.scene.pairs.check_scene_pairs`)."""

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
        return calibrate.scene.pairs.check_scene_pairs([read(p) for p in raws],
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

    out = check_output_path(args.out, suffixes=(".npz",) if args.field else (".tif", ".tiff"))
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
    again = calibrate.ScenePsfOptions.of(options, flip=cal.flip)
    if k >= 2 and not args.no_check:
        summary["holdout_pearson"] = holdout_scores(raws, truths, again).tolist()
    if args.field:
        summary = _field_calibration(raws, truths, again, summary, args)
    else:
        write_psf(out, cal.psf)
    if args.json:
        with atomic_output(args.json) as tmp:
            tmp.write_text(json.dumps(summary, indent=2))
    line = _field_line(summary) if args.field else _one_psf_line(summary)
    print(f"diffcam calibrate-psf: {line} → {out}")
    return 0


def _one_psf_line(summary: dict) -> str:
    """One line on a one-PSF calibration: flip, offset, misfit, held-out scores."""
    held = ("" if "holdout_pearson" not in summary else "; held-out pair predicted with "
            "Pearson " + ", ".join(f"{v:.3f}" for v in summary["holdout_pearson"]))
    return (f"one PSF per channel (rank 1), flip {summary['flip']}, offset "
            f"{', '.join(f'{v:.3g}' for v in summary['offset'])}, relative misfit "
            f"{summary['residual']:.3g}{held}")


def _field_calibration(raws, truths, options, one_psf: dict, args) -> dict:
    """Fit the field-dependent PSF (``args.field``), check it on the held-out pair
    against the one PSF's scores in ``one_psf``, write it to ``args.out``; what was
    fitted, as a dict."""
    grid = args.field
    field = calibrate.fit_field_psf_from_scenes(raws, truths, grid, options,
                                                progress=not args.quiet)
    summary = {**one_psf, "model": f"field {grid[0]}×{grid[1]} per channel",
               "grid": list(grid), "sensor": list(raws.shape[-2:]),
               "rank": field.fields[0].rank,
               "model_error": max(float(f.error()) for f in field.fields),
               "rank_1_error": max(float(f.error(1)) for f in field.fields),
               "offset": field.offset.tolist(), "residual": float(field.residual[-1]),
               "one_psf_residual": one_psf["residual"], "raws": list(args.raws),
               "truths": list(args.truth), "channel_order": args.channel_order}
    summary.pop("holdout_pearson", None)
    if "holdout_pearson" in one_psf:
        held = calibrate.fit_field_psf_from_scenes(raws[:-1], truths[:-1], grid, options,
                                                   progress=not args.quiet)
        summary["holdout"] = {
            "pair": args.raws[-1], "one_psf_pearson": one_psf["holdout_pearson"],
            "field_pearson": np.asarray(evaluate.pearson(
                calibrate.predict_raw(held, truths[-1]), raws[-1])).tolist()}
    channels = "RGB" if len(field.fields) == 3 else None    # the file's channel order
    model.save_field_psf(args.out, field.fields if channels else field.fields[0],
                         channels=channels,
                         **{k: v for k, v in summary.items() if k != "channels"})
    return summary


def _field_line(summary: dict) -> str:
    """One line on a field-dependent calibration: its model, rank, model error, misfit
    and held-out scores, and which model predicts the held-out pair better."""
    gy, gx = summary["grid"]
    line = (f"field-dependent PSF, {gy}×{gx} field positions per channel, rank "
            f"{summary['rank']}, model error {summary['model_error']:.2g} (rank 1 would "
            f"leave {summary['rank_1_error']:.2g}), flip {summary['flip']}, relative misfit "
            f"{summary['residual']:.3g} (one PSF: {summary['one_psf_residual']:.3g})")
    held = summary.get("holdout")
    if held is None:
        return line
    field, one = (np.asarray(held[key]) for key in ("field_pearson", "one_psf_pearson"))
    verdict = ("the field model predicts it better" if field.mean() > one.mean() else
               "one PSF predicts it as well or better: the field dependence is below what "
               "this check resolves; calibrate-psf without --field is the default")
    return (f"{line}; held-out pair predicted with Pearson "
            f"{', '.join(f'{v:.3f}' for v in field)} (one PSF: "
            f"{', '.join(f'{v:.3f}' for v in one)}): {verdict}")


def field_grid(text: str) -> tuple[int, int]:
    """``GYxGX`` (``2x2``, ``2×3``): rows and columns of field positions, 1 to 5 each
    and two positions at least (argparse type)."""
    parts = text.lower().replace("×", "x").split("x")
    try:
        gy, gx = (int(v) for v in parts)
    except ValueError:
        gy = gx = 0
    if not (1 <= gy <= 5 and 1 <= gx <= 5 and gy * gx >= 2):
        raise argparse.ArgumentTypeError(
            f"give rows×columns of field positions, 1 to 5 each and two positions at "
            f"least, e.g. 2x2 (a 1x1 grid is one PSF: leave out --field); not {text!r:.40}")
    return gy, gx


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
    cal.add_argument("--field", type=field_grid, metavar="GYxGX",
                     help="fit a field-dependent PSF: kernels at a GY×GX grid of field "
                          "positions spanning the sensor (e.g. 2x2), written as .npz for "
                          "`diffcam reconstruct --psf`")
    cal.add_argument("-o", "--out", required=True,
                     help="PSF .tif (RGB for colour input); with --field a .npz")
    cal.set_defaults(func=_cmd_calibrate_psf)
