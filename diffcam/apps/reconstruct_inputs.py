"""What ``diffcam reconstruct`` reads: the raw capture and its PSF source (image,
stack, folder, glob, stack-fit model or field-dependent PSF), dark levels, colour, and
the checks that the two hold light and are not swapped."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from diffcam.apps.common import has_stack_meta, read_psfs
from diffcam.apps.fit_cli import model_planes
from diffcam.core.errors import DiffcamError
from diffcam import calibrate, model  # lazy: loaded on use
from diffcam.io import (BackgroundWarning, IMAGE_SUFFIXES, SensorWindow, apply_envelope,
                        as_rgb, border_dark_level, downsample, envelope_widths,
                        fit_sensor_window, image_files, read_image, read_psf_stack,
                        subtract_background)

DARK_RING = 6        # pixels: width of the frame-border band whose median is the dark level
WORKING_SIZE = 480
"""Pixels on the longer side up to which ``reconstruct`` works at the capture's own
resolution by default; larger captures are box-averaged by the least integer factor
that brings them there (`working_factor`). The defaults (iterations, ADMM-TV's
``tau``) were measured on captures of 400 and 480 pixels per side; on the tutorial hand
at its full 1200 × 1600 they leave the fine detail unresolved (docs/scene_psf.md)."""

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


def read_model(path, planes) -> PsfSource:
    """The planes (default all) a stack-fit model renders, clipped at 0."""

    fit = calibrate.model_file.load_stack_model(path)
    planes = model_planes(fit, planes, path)
    if min(planes) < 0:
        raise DiffcamError(f"--planes {planes}: plane numbers start at 0.")
    # dark-free, each plane with its light (inverse-square law) where the fit knows it,
    # else at unit mean; the carried residuals can dip below 0: clip them
    light = fit.identifiable.get("magnification_reference_from_light") is not None
    return PsfSource(np.clip(fit.predict(planes, light=light), 0, None), None, list(planes),
                     None)


def read_psf_source(source: str, planes: list[int] | None = None) -> PsfSource:
    """PSFs from a file, folder, glob or stack-fit model (module docstring); ``planes``
    selects planes of the stack (default all; for a model, the planes to render)."""

    files = image_files(source)
    kind = None if files is not None else calibrate.model_kind(source)
    if kind == "stack-fit":
        return read_model(source, planes)
    if kind == "phase":
        raise DiffcamError(f"{source} is a phase file: it gives PSFs at depths z1 once z2 is "
                           f"known; render them with `diffcam psf {source}"
                           f" --z1 … --z2 … -o psfs.tif` and pass --psf psfs.tif.")
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


def dark_arg(text: str):
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


def subtract_dark(images, level, what: str, say=print):
    """``images`` minus ``level`` (counts, or ``"auto"``: the border median,
    `diffcam.io.border_dark_level`); clipping noise below 0 is reported through
    ``say`` as one line."""
    import warnings


    if level is None:
        return images
    background = border_dark_level(images, DARK_RING) if is_auto(level) else level
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


class Footprint(NamedTuple):
    """How a volume's PSF footprints are matched to the capture (`match_envelope`)."""

    psfs: np.ndarray                    # the stack to solve with
    widths: np.ndarray | None           # "auto": the envelope's σ per plane, pixels
    window: SensorWindow | None         # "mask": the sensor window, pixels


def match_envelope(raw: np.ndarray, psfs: np.ndarray, mode: str, say) -> Footprint:
    """The PSF footprints matched to the capture's light: ``mode`` ``"mask"``: the PSFs
    as measured and a sensor window fitted to the capture (`diffcam.io.fit_sensor_window`,
    the solver's ``sensor_response``); ``"auto"``: each plane times a vertical envelope
    (`diffcam.io.envelope_widths` then `diffcam.io.apply_envelope`); ``"none"``: the
    PSFs as measured."""
    if mode == "none":
        return Footprint(psfs, None, None)
    if mode == "mask":
        window = fit_sensor_window(raw, psfs)
        say(f"sensor window fitted to the capture: vertical Gaussian σ {window.sigma:.1f} px "
            f"about row {window.centre_row:.1f} (the PSFs as measured)")
        return Footprint(psfs, None, window)
    widths = envelope_widths(raw, psfs)
    say(f"PSF envelope matched to the capture: vertical Gaussian σ {widths[0]:.0f} px "
        f"(plane 0) to {widths[-1]:.0f} px (plane {len(widths) - 1})")
    return Footprint(apply_envelope(psfs, widths), widths, None)


def gains_arg(text: str):
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


def is_auto(level) -> bool:
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
    if args.white_balance is not None and raw.ndim != 3:
        raise DiffcamError(f"{args.raw}: a grayscale raw has no colour to balance; leave "
                           f"out --white-balance (it sets the gains of R, G and B).")
    source = colour_psf(args.psf, raw, args.channel_order) or read_psf_source(args.psf,
                                                                               args.planes)
    raw = subtract_dark(raw, raw_level, f"{args.raw} (raw dark level)", say)
    psfs = subtract_dark(source.psfs, psf_level, f"{args.psf} (PSF dark level)", say)
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
    """Warn (stderr) when the raw lights fewer effective pixels (`lit_pixels`)
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
    capture's longer side to `WORKING_SIZE` pixels or fewer, said through ``say``."""
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
    ``channel_order`` (the raw's) applies to a colour ``.npy``; a PNG or TIFF PSF is RGB
    by its format, whatever the raw's order (``calibrate-psf`` writes RGB TIFFs).
    """

    path = Path(source)
    if (path.suffix.lower() not in IMAGE_SUFFIXES or not path.is_file()
            or Path(f"{path}.json").exists() or has_stack_meta(path)):
        return None
    npy = path.suffix.lower() == ".npy"
    capture = read_image(path, channel_order=channel_order if npy else None)
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
    if is_auto(gains):
        means = image.mean(axis=(-2, -1))
        if np.any(means <= 0):
            raise DiffcamError("--white-balance auto: a channel of the reconstruction is "
                               "dark; give the gains (R,G,B).")
        gains = means.mean() / means
    return image * np.asarray(gains, image.dtype)[:, None, None]


FIELD_ONLY_ONE_PLANE = ("planes", "plane", "depth")


def read_field_inputs(args, say) -> tuple[np.ndarray, tuple, dict]:
    """The raw capture, its dark offset subtracted, and the field-dependent PSF of
    ``--psf`` (`diffcam.model.field.load_field_psf`): one model per channel of the raw
    (a one-model file is shared by the channels), and the file's metadata.

    The dark offset is the one the calibration fitted (the file's ``offset``, one per
    channel, subtracted as the model's term, without clipping) or else ``--dark-raw``.
    The raw must have the sensor's pixels the model was fitted on: it is not
    downsampled."""
    fields, meta = model.load_field_psf(args.psf)
    fields = (fields,) if isinstance(fields, model.FieldPSF) else fields
    _refuse_for_field(args, fields, meta)
    raw = read_raw(args.raw, args.channel_order)
    if raw.ndim == 2 and len(fields) > 1:
        raise DiffcamError(f"{args.psf}: a colour field model for a grayscale raw; give a "
                           f"colour raw or a grayscale model.")
    sensor = meta.get("sensor")
    if (sensor is not None and list(raw.shape[-2:]) != list(sensor)) or any(
            f.kernels.shape[-2] > raw.shape[-2] or f.kernels.shape[-1] > raw.shape[-1]
            for f in fields):
        raise DiffcamError(f"{args.raw}: {raw.shape[-2]}×{raw.shape[-1]} pixels, but the "
                           f"field model {args.psf} was fitted on "
                           f"{'×'.join(str(n) for n in sensor or fields[0].kernels.shape[-2:])}"
                           f"; give the raw at the model's size.")
    offset = meta.get("offset")
    if offset is None:
        raw = subtract_dark(raw, args.dark_raw, f"{args.raw} (raw dark level)", say)
    else:
        offset = np.asarray(offset, np.float32)
        say(f"dark offset from the calibration subtracted: "
            f"{', '.join(f'{v:.3g}' for v in offset)}")
        raw = raw - (offset[:, None, None] if raw.ndim == 3 else offset[0])
    if not np.max(raw) > 0:
        raise DiffcamError(f"{args.raw}: no light: every pixel is 0 or below once the "
                           f"dark level is off; check the capture and the dark level.")
    return raw, fields * (3 if raw.ndim == 3 and len(fields) == 1 else 1), meta


def _refuse_for_field(args, fields: tuple, meta: dict) -> None:
    """Refuse the options that do not apply to a field-dependent PSF, one line each."""
    if fields[0].volume:
        raise DiffcamError(f"{args.psf}: a 3-D field model (kernels per depth); "
                           f"`diffcam reconstruct` takes a 2-D one (`calibrate-psf --field`).")
    if args.bias is not None or args.dark_psf is not None:
        raise DiffcamError(f"{args.psf} is a field-dependent PSF, with no dark level of its "
                           f"own; leave out --bias and --dark-psf (--dark-raw sets the raw's).")
    if args.dark_raw is not None and meta.get("offset") is not None:
        raise DiffcamError(f"{args.psf} carries the dark offset its calibration fitted, and "
                           f"it is subtracted; leave out --dark-raw.")
    if args.downsample not in (None, 1):
        raise DiffcamError(f"{args.psf} is fitted on its sensor's pixels; reconstruct at "
                           f"that size (leave out --downsample).")
    given = [f"--{name}" for name in FIELD_ONLY_ONE_PLANE if getattr(args, name) is not None]
    if given:
        raise DiffcamError(f"{args.psf} is a field-dependent PSF at one depth; "
                           f"{', '.join(given)} choose(s) planes of a PSF stack.")
