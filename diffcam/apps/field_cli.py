"""``diffcam psf`` and ``diffcam compare`` of a field-dependent PSF (`diffcam
calibrate-psf --field`, `diffcam.model.field.save_field_psf`): the model's PSFs at
field positions, and how well they match PSFs measured there, beside the one on-axis
PSF a shift-invariant model uses everywhere.

Positions are chief rays on the sensor, ``(y, x)`` pixels from the optical axis (the
centre of the model's kernel frame), as `diffcam.model.field.FieldPSF.positions` holds
them. The PSFs are registered: each moved so that its chief ray sits on the axis
(`diffcam.model.field.register`).
"""

from __future__ import annotations

import json

import numpy as np

from diffcam import evaluate, model
from diffcam.apps.common import read_psfs, save_figure, save_image
from diffcam.core.errors import DiffcamError
from diffcam.io import atomic_output, check_output_path

def field_models(path) -> tuple[tuple[model.FieldPSF, ...], str | None]:
    """The file's models (one per channel) and its channel letters (None: one model)."""
    fields, meta = model.load_field_psf(path)
    channels = meta.get("channels")
    return ((fields,) if isinstance(fields, model.FieldPSF) else fields), channels


SPAN_MARGIN = 0.1
"""How far outside its positions' span (a fraction of the span, each side) a field
model is asked for PSFs: beyond that its weights extrapolate."""


def check_inside(field: model.FieldPSF, at: np.ndarray | None) -> None:
    """Refuse positions ``at`` (``(m, 2)`` pixels) outside the model's positions' span
    by more than `SPAN_MARGIN` of it, along an axis the positions span."""
    if at is None:
        return
    span = np.asarray(field.positions, np.float64).reshape(-1, 2)
    low, high = span.min(axis=0), span.max(axis=0)
    margin = SPAN_MARGIN * (high - low)
    outside = ((at < low - margin) | (at > high + margin)) & (high > low)
    if outside.any():
        y, x = at[np.argmax(outside.any(axis=1))]
        raise DiffcamError(f"--at {y:g},{x:g} lies outside the model's field (its positions "
                           f"span y {low[0]:g}…{high[0]:g}, x {low[1]:g}…{high[1]:g} pixels "
                           f"from the axis), where it would extrapolate; give positions "
                           f"within it, or build the model over a wider field.")


def psfs_at(field: model.FieldPSF, at: np.ndarray | None) -> np.ndarray:
    """The registered PSFs ``([nz,] m, my, mx)`` of ``field`` at positions ``at``
    (``(m, 2)`` pixels; the same at every depth of a volume model), or at the
    positions it was built from."""
    if at is None:
        return np.asarray(field.at(field.positions))
    points = np.broadcast_to(at, field.positions.shape[:-2] + at.shape)
    return np.asarray(field.at(points.astype(np.asarray(field.kernels).dtype)))


def cmd_psf_field(args) -> int:
    """``diffcam psf FIELD.npz [--at Y,X;…] -o OUT``: the model's registered PSFs at
    the positions, ``(m, my, mx)``, per depth ``(nz, m, my, mx)`` and per channel
    (a leading channel axis)."""
    given = [f for f, v in (("--z1", args.z1), ("--z2", args.z2), ("--planes", args.planes),
                            ("--kappa", args.kappa), ("--crop", args.crop)) if v is not None]
    if given or args.rendered_only or args.processes != 1:
        raise DiffcamError(f"{args.phase} is a field-dependent PSF: it takes field positions "
                           f"(--at Y,X;…, pixels from the axis), not "
                           f"{', '.join(given) or '--rendered-only or --processes'}.")
    check_output_path(args.out, suffixes=(".tif", ".tiff", ".npy"))
    fields, channels = field_models(args.phase)
    check_inside(fields[0], args.at)
    psfs = np.stack([psfs_at(f, args.at) for f in fields]) if channels else psfs_at(
        fields[0], args.at)
    save_image(args.out, psfs)
    where = "its own positions" if args.at is None else f"{len(args.at)} field position(s)"
    print(f"diffcam psf: field-dependent PSF (rank {fields[0].rank}, model error "
          f"{float(max(f.error() for f in fields)):.3g}) at {where}, registered to their "
          f"chief rays: {'×'.join(str(n) for n in psfs.shape)} "
          f"({'channels ' + channels + ', ' if channels else ''}positions, pixels) "
          f"→ {args.out}")
    return 0


def compare_field(captured: np.ndarray, field: model.FieldPSF, at: np.ndarray) -> dict:
    """Pearson of the field model's PSFs and of the on-axis PSF (the shift-invariant
    model) with PSFs captured at positions ``at`` (``(m, 2)`` pixels), each captured
    PSF registered to its chief ray first; ``captured`` ``(m, my, mx)`` on the model's
    kernel frame, the axis at its centre."""
    if field.volume:
        raise DiffcamError("compare takes a 2-D field model (one depth); a volume model's "
                           "PSFs: `diffcam psf MODEL --at …`.")
    if captured.shape != (len(at),) + tuple(field.kernels.shape[-2:]):
        raise DiffcamError(f"the captured PSFs are {captured.shape}; give one per --at "
                           f"position ({len(at)}) on the model's kernel frame "
                           f"{tuple(field.kernels.shape[-2:])}, the axis at its centre.")
    dtype = np.asarray(field.kernels).dtype
    measured = np.asarray(model.field.register(captured.astype(dtype), at.astype(dtype)))
    predicted = psfs_at(field, at)
    on_axis = np.broadcast_to(psfs_at(field, np.zeros((1, 2)))[0], predicted.shape)
    return {"positions_px": at.tolist(),
            "field_model": np.asarray(evaluate.pearson(predicted, measured)).tolist(),
            "one_psf": np.asarray(evaluate.pearson(on_axis, measured)).tolist()}


def cmd_compare_field(args, path) -> int:
    """``diffcam compare CAPTURED --model FIELD.npz --at Y,X;… -o FIG.png [--json]``."""
    given = [f for f, v in (("--z1", args.z1), ("--z2", args.z2), ("--pixel", args.pixel),
                            ("--anchor", args.anchor), ("--key", args.key)) if v is not None]
    if given:
        raise DiffcamError(f"{path} is a field-dependent PSF: it compares at field "
                           f"positions (--at); it does not take {', '.join(given)}.")
    if args.at is None:
        raise DiffcamError(f"{path} is a field-dependent PSF: give the position of each "
                           f"captured PSF with --at Y,X;… (pixels from the axis).")
    check_output_path(args.out, suffixes=(".png",))
    if args.json is not None:
        check_output_path(args.json, suffixes=(".json",))
    fields, channels = field_models(path)
    check_inside(fields[0], args.at)
    captured = np.asarray(read_psfs(args.captured)[0], np.float64)
    captured = captured[None] if captured.ndim == 2 else captured
    if channels is None:
        scores = {"": compare_field(captured, fields[0], args.at)}
    elif captured.ndim == 4 and captured.shape[1] == len(channels):
        scores = {c: compare_field(captured[:, k], f, args.at)
                  for k, (c, f) in enumerate(zip(channels, fields))}
    else:
        raise DiffcamError(f"{path} is a colour model ({channels}): give the captured PSFs "
                           f"as (positions, {len(channels)}, y, x) (.npy or .tif).")
    _report(scores, args)
    return 0


def _report(scores: dict, args) -> None:
    """Print the table, write the figure and the JSON (``--json``)."""
    rows = ["| position (y, x) px | channel | field model Pearson | one PSF Pearson |",
            "|---|---|---|---|"]
    rows += [f"| {y:g}, {x:g} | {c or '—'} | {a:.4f} | {b:.4f} |"
             for c, s in scores.items()
             for (y, x), a, b in zip(s["positions_px"], s["field_model"], s["one_psf"])]
    print("\n".join(rows))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for c, s in scores.items():
        radius = np.hypot(*np.asarray(s["positions_px"]).T)
        ax.plot(radius, s["field_model"], "o", label=f"field model {c}".strip())
        ax.plot(radius, s["one_psf"], "s", mfc="none", label=f"one on-axis PSF {c}".strip())
    ax.set_xlabel("distance of the chief ray from the axis (pixels)")
    ax.set_ylabel("Pearson with the captured PSF")
    ax.legend()
    save_figure(fig, args.out)
    if args.json is not None:
        with atomic_output(args.json) as tmp, open(tmp, "w") as fh:
            json.dump(scores if len(scores) > 1 else scores[""], fh, indent=1)
    print(f"diffcam compare: → {args.out}" + (f", {args.json}" if args.json else ""))
