"""``diffcam fit``, ``diffcam predict`` and ``diffcam compare-stack``: a wave model of a
PSF stack fitted to a few of its planes (`diffcam.calibrate.fit_stack`).

    diffcam fit psfs.tif --planes 5,25 -o model.npz
    diffcam predict model.npz --planes 0:43 -o predicted.tif
    diffcam compare-stack psfs.tif --model model.npz -o compare.png --json compare.json

A STACK is a multi-page TIFF, a 3-D ``.npy``, an ``.npz`` holding one 3-D array (or
``--key NAME``), a MATLAB ``.mat`` stack, a folder of single-plane images (sorted by
name) or a quoted glob of them (``'psf/*.png'``). Planes are indices into it: ``5,25``,
``0:43`` (both ends included) or a mix (``0:10,20``).
"""

from __future__ import annotations

import argparse
import math
import json
import time
from pathlib import Path

import numpy as np

from diffcam.core.errors import DiffcamError
from diffcam import apps, calibrate, evaluate  # lazy: loaded on use (fit_stack: optax, optimistix)
from diffcam.apps.common import (iterations_count, length_arg, planes_arg, positions_arg,
                                 save_figure, save_image)
from diffcam.io import (atomic_output, check_output_path, image_files, npz_keys,
                        read_image, read_mat_stack, read_npz, read_psf_stack)



def _saturation_arg(text):
    """A finite pixel level, or 'none' (no saturation check)."""
    if text.strip().lower() == "none":
        return "none"
    try:
        level = float(text)
    except ValueError:
        level = math.nan
    if not math.isfinite(level):
        raise argparse.ArgumentTypeError(f"{text!r} is not a pixel level: give a finite "
                                         f"number in the stack's units, or 'none'")
    return level


def read_stack(source: str, key: str | None = None) -> tuple[np.ndarray, float | None]:
    """A PSF stack from a file, folder or glob → (float32 (n, ny, nx), saturation level
    in the stack's units or ``None`` for float data)."""

    path = Path(source)
    full_scale = None
    files = image_files(source)
    if files is not None:
        stack = read_psf_stack(files)
        full_scale = read_image(files[0]).full_scale
    elif path.suffix.lower() == ".npz":
        names = npz_keys(path, what="a PSF stack (.npz)")
        if key is None:
            arrays = read_npz(path, names, what="a PSF stack (.npz)") if len(names) <= 16 \
                else {}
            three = [n for n, a in arrays.items() if a.ndim == 3]
            if len(three) != 1:
                raise DiffcamError(f"{path}: holds arrays {names}; say which one is the "
                                   f"stack with --key NAME.")
            key = three[0]
        data = read_npz(path, [key], what="a PSF stack (.npz)")[key]
        if data.ndim != 3:
            raise DiffcamError(f"{path}: array {key!r} has shape {data.shape}; a stack is "
                               f"(n_planes, ny, nx).")
        if np.issubdtype(data.dtype, np.integer):
            full_scale = float(np.iinfo(data.dtype).max)
        stack = data
    elif path.suffix.lower() == ".mat":
        stack = read_mat_stack(path, key)
    else:
        capture = read_image(path)
        stack, full_scale = capture.image, capture.full_scale
    if np.ndim(stack) != 3:
        raise DiffcamError(f"{source}: expected a stack of planes (n, ny, nx), got shape "
                           f"{np.shape(stack)}.")
    bad = np.flatnonzero(~np.isfinite(stack).all(axis=(1, 2)))
    if bad.size:
        raise DiffcamError(f"{source}: plane(s) {bad[:5].tolist()} hold NaN or Inf values; "
                           f"clean the stack (np.nan_to_num) first.")
    return np.asarray(stack), None if full_scale is None else 0.999 * full_scale


def _cmd_fit(args) -> int:

    check_output_path(args.out, suffixes=(".npz",))
    stack, level = read_stack(args.stack, args.key)
    if args.saturation is not None:
        level = None if args.saturation == "none" else args.saturation
    overrides = {k: v for k, v in (("max_steps", args.max_steps),
                                   ("time_budget", args.time_budget),
                                   ("patience", args.patience), ("seed", args.seed))
                 if v is not None}
    if args.frozen:
        overrides["frozen"] = True
    print(f"diffcam fit: {stack.shape[0]} planes of {stack.shape[1]}×{stack.shape[2]}, "
          f"fitting planes {args.planes} ...", flush=True)
    fit = calibrate.fit_stack(stack, args.planes, saturation=level, progress=not args.no_progress,
                    pixel_pitch=args.pixel, wavelength=args.wavelength, z2=args.z2,
                    **overrides)
    fit.save(args.out)
    worse = "  (WORSE than the baseline: prefer it)" if fit.worse_than_baseline else ""
    print(f"diffcam fit: stopped: {fit.stop_reason}; best step {fit.best_step} of "
          f"{fit.steps}\n"
          f"  validation Pearson: model {fit.validation_score:.4f}, scaling baseline "
          f"{fit.baseline_validation:.4f}{worse}\n"
          f"  ζ_ref {fit.model.zeta_pixels:.3g} px² (λ·z2·M/pixel²){_z2m(fit)}"
          f"{_zeta_start(fit)}, κ "
          f"{float(fit.model.kappa):.3f}, magnification {fit.registration.magnification:.5f}"
          f" about ({fit.registration.centre[0]:.1f}, {fit.registration.centre[1]:.1f}) px\n"
          f"{_depths_from_light(fit)}"
          f"  {fit.seconds:.1f} s → {args.out}")
    return 0


def _depths_from_light(fit) -> str:
    """The line on M(t) and z1(t) that the planes' light fixes (inverse-square law)."""
    m = fit.identifiable.get("magnification_range_from_light")
    if m is None:
        return "  the planes' light does not follow the inverse-square law: no depths from it\n"
    z = fit.identifiable["z1_over_z2_range_from_light"]
    z1 = fit.identifiable.get("z1_range_from_light_m")
    mm = "" if z1 is None else f" = {1e3 * z1[0]:.3g}–{1e3 * z1[1]:.3g} mm"
    ends = (0, fit.n_planes - 1) if fit.n_planes else sorted({fit.planes[0],
                                                               fit.model.anchor})
    return (f"  the planes' light (inverse-square law): M = 1 + z2/z1 from {m[0]:.3f} to "
            f"{m[1]:.3f} over planes {ends[0]}–{ends[1]}, z1 = {z[0]:.3g}–{z[1]:.3g} z2"
            f"{mm}\n")


def _z2m(fit) -> str:
    """z2·M at the reference plane in mm, when the pitch and wavelength were given."""
    z2m = fit.identifiable.get("z2_M_reference_m")
    return "" if z2m is None else f" = z2·M {1e3 * z2m:.2f} mm at plane {fit.planes[0]}"


def _zeta_start(fit) -> str:
    """Where ζ_ref started: two planes can leave it near its start (docs/stack_fit.md,
    "Two planes of this stack do not pin the distance")."""
    o = fit.model.oversample
    starts = ", ".join(f"{z / o ** 2:.3g}" for z in fit.zeta_scan)
    physical = None not in (fit.physical.get(k) for k in ("pixel_pitch", "wavelength", "z2"))
    how = "" if physical or fit.options.get("zetas") else \
        " (the default: --pixel, --wavelength and --z2 give a physical one)"
    return f", from a start at {starts} px²{how}"


def cmd_predict(args) -> int:

    if calibrate.model_kind(args.model) == "field-psf":
        return apps.field_cli.cmd_psf_field(argparse.Namespace(
            phase=args.model, at=args.at, out=args.out, planes=args.planes, kappa=args.kappa,
            rendered_only=args.rendered_only, z1=None, z2=None, crop=None, processes=1))
    if args.at is not None:
        raise DiffcamError("--at (field positions) is for a field-dependent PSF from "
                           "`diffcam calibrate-psf --field`.")
    check_output_path(args.out, suffixes=(".tif", ".tiff", ".npy"))
    fit = calibrate.model_file.load_stack_model(args.model)
    t0 = time.perf_counter()
    planes = model_planes(fit, args.planes, args.model)
    pred = fit.predict(planes, kappa=args.kappa, residual=not args.rendered_only)
    save_image(args.out, pred)
    print(f"diffcam predict: {len(planes)} planes of {pred.shape[1]}×{pred.shape[2]} "
          f"({time.perf_counter() - t0:.1f} s) → {args.out}")
    return 0


def model_planes(fit, planes: list[int] | None, path) -> list[int]:
    """``planes`` (``--planes``), or by default every plane of the model's stack: its
    recorded plane count, checked (a damaged file may declare 0 or 10⁹)."""

    if planes is not None:
        return planes
    n = fit.n_planes
    if n is None:
        raise DiffcamError(f"{path}: the model does not record its stack's plane count; "
                           f"choose planes with --planes (e.g. 0:43).")
    most = calibrate.stack.result.MAX_PLANES
    if not 1 <= n <= most:
        raise DiffcamError(f"{path}: the model declares {n} planes, outside 1 … {most} "
                           f"(diffcam.calibrate.stack.result.MAX_PLANES): the file "
                           f"is damaged; choose planes with --planes.")
    return list(range(n))


def compare_stack(stack, fit) -> dict:
    """Per-plane Pearson of the model's prediction, its rendering alone (no carried
    residual), the scaling baseline and the frozen-distance prediction (κ = 0) against a
    measured stack (prepared like the fit's planes)."""

    if tuple(stack.shape[1:]) != tuple(fit.model.frame):
        raise DiffcamError(f"the stack's frames {tuple(stack.shape[1:])} differ from the "
                           f"model's {tuple(fit.model.frame)}: compare on the frame it "
                           f"was fitted on.")
    bad = [t for t in fit.planes if t >= stack.shape[0]]
    if bad:
        raise DiffcamError(f"the model was fitted to plane(s) {bad}, beyond this stack's "
                           f"{stack.shape[0]} planes.")
    ring = int(fit.options.get("dark_ring", 6))
    measured = calibrate.prepare_planes(stack, ring)
    n = stack.shape[0]
    model = fit.predict(n)
    frozen = fit.predict(n, kappa=0.0)
    rendered = fit.predict(n, residual=False)
    base = evaluate.scaling_baseline({t: measured[t] for t in fit.planes}, n,
                                     registration=fit.registration)
    scores = {k: np.asarray(evaluate.pearson(v, measured))
              for k, v in (("model", model), ("baseline", base), ("frozen", frozen),
                           ("rendered", rendered))}
    rows = [{"plane": t, "given": t in fit.planes,
             **{k: float(v[t]) for k, v in scores.items()}} for t in range(n)]
    held = [r for r in rows if not r["given"]]
    summary = {k: float(np.mean([r[k] for r in held])) if held else float("nan")
               for k in ("model", "baseline", "frozen", "rendered")}
    summary["above_baseline"] = int(sum(r["model"] > r["baseline"] for r in held))
    summary["held_out"] = len(held)
    return {"planes": list(fit.planes), "per_plane": rows, "mean_held_out": summary}


def cmd_compare_stack(args) -> int:

    if args.out:
        check_output_path(args.out, suffixes=(".png", ".pdf", ".svg"))
    if args.json:
        check_output_path(args.json, suffixes=(".json",))
    stack, _ = read_stack(args.stack, args.key)
    fit = calibrate.model_file.load_stack_model(args.model)
    result = compare_stack(stack, fit)
    lines = ["| plane | model | scaling baseline | frozen distance (κ=0) | rendering alone |",
             "|---|---|---|---|---|"]
    for r in result["per_plane"]:
        mark = " (given)" if r["given"] else ""
        lines.append(f"| {r['plane']}{mark} | {r['model']:.4f} | {r['baseline']:.4f} | "
                     f"{r['frozen']:.4f} | {r['rendered']:.4f} |")
    s = result["mean_held_out"]
    lines.append(f"| **held-out mean** | **{s['model']:.4f}** | {s['baseline']:.4f} | "
                 f"{s['frozen']:.4f} | {s['rendered']:.4f} |")
    print("\n".join(lines))
    print(f"diffcam compare-stack: model above the baseline at {s['above_baseline']}/"
          f"{s['held_out']} held-out planes")
    if args.json:
        with atomic_output(args.json) as tmp:
            Path(tmp).write_text(json.dumps(result, indent=1))
    if args.out:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        t = [r["plane"] for r in result["per_plane"]]
        fig, ax = plt.subplots(figsize=(7, 4))
        ax.plot(t, [r["model"] for r in result["per_plane"]], "o-", ms=3,
                label=f"wave model (held-out mean {s['model']:.4f})")
        ax.plot(t, [r["baseline"] for r in result["per_plane"]], "s--", ms=3,
                label=f"scaling baseline ({s['baseline']:.4f})")
        ax.plot(t, [r["frozen"] for r in result["per_plane"]], ":", lw=1,
                label=f"frozen distance κ=0 ({s['frozen']:.4f})")
        ax.plot(t, [r["rendered"] for r in result["per_plane"]], "-.", lw=1,
                label=f"rendering alone ({s['rendered']:.4f})")
        for g in result["planes"]:
            ax.axvline(g, color="0.7", lw=0.8)
        ax.set_xlabel("plane")
        ax.set_ylabel("Pearson with the measured plane")
        ax.set_title(f"fitted to planes {result['planes']} (grey lines)")
        ax.legend(fontsize=8)
        save_figure(fig, args.out)
        print(f"diffcam compare-stack: → {args.out}")
    return 0


def add_fit(sub) -> None:
    """Add ``fit``, ``predict`` and ``compare-stack`` to the ``diffcam`` subcommands."""

    fit = sub.add_parser("fit", help="fit a wave model to a few planes of a PSF stack",
                         description="Fit the stack wave model to the given planes of a "
                                     "PSF stack (the others never enter) and write it as "
                                     "one .npz; prints the stop reason and the validation "
                                     "scores of the model and the scaling baseline.")
    fit.add_argument("stack", help="multi-page TIFF, .npy, .npz (one 3-D array or --key), "
                                   ".mat, a folder or a quoted glob of single-plane images")
    fit.add_argument("--planes", type=planes_arg, required=True,
                     help="given planes, e.g. 5,25 (the first is the reference)")
    fit.add_argument("--key", help="array name inside an .npz or .mat stack")
    fit.add_argument("--max-steps", type=iterations_count(), help="Adam steps at most (400)")
    fit.add_argument("--time-budget", type=float,
                     help="also stop after this many seconds (default: no wall-clock "
                          "limit; the steps alone stop the fit, the same on any machine)")
    fit.add_argument("--patience", type=iterations_count(),
                     help="steps without validation gain (40)")
    fit.add_argument("--seed", type=int, help="seed of the validation split and of the start (0)")
    fit.add_argument("--frozen", action="store_true",
                     help="frozen-distance ablation: ζ the same at every plane")
    fit.add_argument("--saturation", type=_saturation_arg,
                     help="pixel value counted as saturated, or 'none' "
                                          "(default: 0.999 × full scale of integer data)")
    fit.add_argument("--pixel", type=length_arg("pixel"),
                     help="pixel pitch (reported: with --wavelength, the distance z2·M)")
    fit.add_argument("--wavelength", type=length_arg("wavelength"), help="(reported, as above)")
    fit.add_argument("--z2", type=length_arg("z2"),
                     help="diffuser to sensor (reported: with the two above, z1 per plane)")
    fit.add_argument("--no-progress", action="store_true", help="no progress bar")
    fit.add_argument("-o", "--out", required=True, help="model file (.npz)")
    fit.set_defaults(func=_cmd_fit)

    pred = sub.add_parser("predict", help="alias of `diffcam psf MODEL`",
                          description="An alias of `diffcam psf MODEL`: render planes of a "
                                      "stack model from `diffcam fit` (each normalised to "
                                      "unit mean), or a field-dependent PSF at --at.")
    pred.add_argument("model", help="model file from `diffcam fit`, or a field-dependent PSF")
    pred.add_argument("--planes", type=planes_arg,
                      help="planes, e.g. 0:43 (ends included) or 0,5,9 (default: all)")
    pred.add_argument("--kappa", type=float, help="render with this depth-law exponent "
                                                  "(0: frozen distance)")
    pred.add_argument("--rendered-only", action="store_true",
                      help="the model's rendering alone, without the measured planes' "
                           "carried residuals")
    pred.add_argument("--at", type=positions_arg, help="a field-dependent PSF's field "
                      "positions Y,X;… (sensor pixels from the axis)")
    pred.add_argument("-o", "--out", required=True, help="output .tif (multi-page) or .npy")
    pred.set_defaults(func=cmd_predict)

    cmp_ = sub.add_parser("compare-stack", help="alias of `diffcam compare STACK --model`",
                          description="An alias of `diffcam compare STACK --model MODEL`. "
                                      "Pearson of the fitted model, the scaling baseline "
                                      "(from the same given planes) and the frozen-distance "
                                      "rendering (κ = 0) against every plane of a measured "
                                      "stack; prints a table, writes a figure and JSON.")
    cmp_.add_argument("stack", help="the measured stack (as for `diffcam fit`)")
    cmp_.add_argument("--model", required=True, help="model file from `diffcam fit`")
    cmp_.add_argument("--key", help="array name inside an .npz or .mat stack")
    cmp_.add_argument("-o", "--out", help="figure (.png)")
    cmp_.add_argument("--json", help="per-plane scores (.json)")
    cmp_.set_defaults(func=cmd_compare_stack)
