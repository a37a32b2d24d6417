"""Benchmark: fit the stack wave model to two (or more) planes of the built-in
DiffuserCam stack, predict the others, and compare with the scaling baseline.

Usage: python -m benchmarks.bench_stack_fit [--pairs 6] [--seed 12] [--crop 0.8]
       [--spread 3 5] [--quick]

``--spread K …`` adds, per K, a case of K given planes spread evenly over the stack
(two planes in from each end), on the original and on a transformed copy.

Pairs (i, j) with 10 ≤ j − i ≤ 30 are drawn from ``--seed``; each is run on the original
stack and on a transformed copy (one rotation/flip drawn from the same seed, then a
random crop keeping ``--crop`` of the area, the same for every plane), so nothing can
rely on the frame centre or orientation. Per case:

- ``model``: :func:`diffcam.calibrate.fit_stack` with default options (the scaling
  theorem's depth law, κ = 1), its
  held-out planes predicted with :meth:`StackFit.predict` (rendered model plus the
  carried residuals of the measured planes);
- ``baseline``: :func:`diffcam.evaluate.scaling_baseline` from the same given planes and
  the fit's registration — what a user would do without the model;
- ``frozen``: the frozen-distance ablation (a second fit with ``frozen=True``: ζ the
  same at every plane; predicted the same way);
- ``rendered``: the model's rendering alone (``residual=False``: no measured detail);
- ``blend``: the baseline with the measured planes mixed by the weights the model
  uses for its residuals (``scaling_baseline(blend=True)``: no model at all).

Scores are Pearson over the full (transformed) frame against the measured plane,
prepared by :func:`diffcam.calibrate.prepare_planes` (border-median dark level, unit
mean), mean and worst over the held-out planes; ``rendered_above`` counts the held-out
planes where the rendering alone beats the baseline, ``outside_gain`` is the model's
mean gain over the baseline on the planes outside the given range (extrapolated),
``frozen_cost_outside`` what the frozen ablation loses there, ``depth_effect_outside``
how much the depth law changes the fitted model's rendering there (1 − Pearson between
the rendering with κ = 1 and with κ = 0, the same field: the largest cost the ablation
could show were the κ = 1 rendering exact), ``z2M_first_mm``/``z2M_last_mm`` the
identifiable distance z2·M at the stack's first and last planes (the same planes in
every case) for the nominal pitch and wavelength below; the all-row cell is their
spread over the cases. ``JAX_ENABLE_X64=1`` runs the fits in float64 (recorded).
Fit seconds include registration,
the GS start, compilation and all steps (default time budget 60 s); predict seconds
include compilation. The machine is shared: timings are noisy, and a fit cut by its time
budget says so in ``stop_reason``. Results go to ``benchmarks/results/stack_fit.json``
(with per-plane scores) and a Markdown table is printed, its last row the means (fit
and predict seconds: the maximum; worst_r: the minimum). ``--quick`` runs one pair.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import jax
import numpy as np

from benchmarks.harness import markdown_table, write_json
from diffcam.calibrate import StackFitWarning, fit_stack, prepare_planes
from diffcam.data import load_psf_stack_3d
from diffcam.evaluate.metrics import pearson
from diffcam.evaluate.registration import scaling_baseline

# Nominal physical units for the identifiable distance z2·M (the stack records neither):
# the PCO.edge 5.5 pixel (6.5 µm) binned 8×, and green light. z2·M scales as pitch²/λ.
PIXEL_PITCH = 8 * 6.5e-6
WAVELENGTH = 532e-9

TRANSFORMS = ["rot90", "rot180", "rot270", "flipud", "fliplr", "transpose"]


def transform_stack(stack: np.ndarray, kind: str, crop: float, rng) -> np.ndarray:
    """The same rotation/flip and a random crop (keeping ``crop`` of the area, √crop of
    each side) applied to every plane of ``stack`` (n, ny, nx)."""
    ops = {"none": lambda a: a,
           "rot90": lambda a: np.rot90(a, 1, axes=(1, 2)),
           "rot180": lambda a: np.rot90(a, 2, axes=(1, 2)),
           "rot270": lambda a: np.rot90(a, 3, axes=(1, 2)),
           "flipud": lambda a: a[:, ::-1, :],
           "fliplr": lambda a: a[:, :, ::-1],
           "transpose": lambda a: np.swapaxes(a, 1, 2)}
    a = np.ascontiguousarray(ops[kind](stack))
    if crop >= 1.0:
        return a
    h, w = a.shape[1:]
    ch, cw = int(round(h * np.sqrt(crop))), int(round(w * np.sqrt(crop)))
    y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    return np.ascontiguousarray(a[:, y0:y0 + ch, x0:x0 + cw])


def draw_cases(n_pairs: int, seed: int, n_planes: int):
    """[(i, j, transform, crop seed)]: gaps 10–30, one transform per pair."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(n_pairs):
        gap = int(rng.integers(10, 31))
        i = int(rng.integers(0, n_planes - gap))
        cases.append((i, i + gap, str(rng.choice(TRANSFORMS)), int(rng.integers(0, 2**31))))
    return cases


def spread_planes(count: int, n_planes: int) -> list[int]:
    """``count`` given planes spread evenly over the stack, 2 planes in from each end
    (so the end planes are extrapolated)."""
    return [int(round(t)) for t in np.linspace(2, n_planes - 3, count)]


def run_case(raw: np.ndarray, planes: list[int], label: str, **options) -> dict:
    """Model, baseline and frozen ablation for one stack and set of given planes: one
    JSON-able row."""
    n = raw.shape[0]
    measured = prepare_planes(raw)
    held = [t for t in range(n) if t not in planes]
    lo, hi = min(planes), max(planes)
    outside = np.array([t < lo or t > hi for t in held])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StackFitWarning)
        t0 = time.perf_counter()
        fit = fit_stack(raw, planes, progress=False, pixel_pitch=PIXEL_PITCH,
                        wavelength=WAVELENGTH, **options)
        fit_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        pred = fit.predict(held)
        predict_s = time.perf_counter() - t0
        frozen_fit = fit_stack(raw, planes, progress=False, frozen=True,
                               registration=fit.registration, **options)
        frozen = frozen_fit.predict(held)
        rendered = fit.predict(held, residual=False)
        unlawful = fit.predict(held, residual=False, kappa=0.0)
    given = {k: measured[k] for k in planes}
    base = scaling_baseline(given, held, registration=fit.registration)
    blend = scaling_baseline(given, held, registration=fit.registration, blend=True)
    r_model, r_base, r_frozen, r_rendered, r_blend = (
        np.asarray(pearson(x, measured[held])) for x in (pred, base, frozen, rendered, blend))
    worst = int(np.argmin(r_model))
    ident = fit.identifiable
    z2m = ident.get("z2_M_range_m") or [None, None]
    depth_effect = 1.0 - np.asarray(pearson(rendered, unlawful))
    return {
        "pair": "(" + ", ".join(map(str, planes)) + ")", "transform": label,
        "shape": list(raw.shape[1:]),
        "model_mean": float(r_model.mean()), "worst_plane": held[worst],
        "worst_r": float(r_model[worst]), "baseline_mean": float(r_base.mean()),
        "frozen_mean": float(r_frozen.mean()), "rendered_mean": float(r_rendered.mean()),
        "blend_mean": float(r_blend.mean()),
        "above_baseline": f"{int((r_model > r_base).sum())}/{len(held)}",
        "all_above": bool((r_model > r_base).all()),
        "rendered_above": f"{int((r_rendered > r_base).sum())}/{len(held)}",
        "rendered_all_above": bool((r_rendered > r_base).all()),
        "outside_gain": float((r_model - r_base)[outside].mean()) if outside.any() else None,
        "frozen_cost_outside": float((r_model - r_frozen)[outside].mean())
        if outside.any() else None,
        "depth_effect_outside": float(depth_effect[outside].mean())
        if outside.any() else None,
        "z2M_ref_m": ident.get("z2_M_reference_m"),
        "z2M_range_m": ident.get("z2_M_range_m"),
        "z2M_first_mm": None if z2m[0] is None else 1e3 * z2m[0],
        "z2M_last_mm": None if z2m[1] is None else 1e3 * z2m[1],
        "fit_s": fit_s, "predict_s": predict_s,
        "steps": f"{fit.best_step}/{fit.steps}", "stop_reason": fit.stop_reason,
        "frozen_stop_reason": frozen_fit.stop_reason,
        "validation": fit.validation_score, "baseline_validation": fit.baseline_validation,
        "summary": fit.summary(), "held": held, "per_plane_model": r_model.tolist(),
        "per_plane_baseline": r_base.tolist(), "per_plane_frozen": r_frozen.tolist(),
        "per_plane_rendered": r_rendered.tolist(), "per_plane_blend": r_blend.tolist(),
        "load": os.getloadavg()[0],
    }


COLUMNS = ["pair", "transform", "model_mean", "worst_plane", "worst_r", "baseline_mean",
           "frozen_mean", "rendered_mean", "blend_mean", "above_baseline", "rendered_above",
           "outside_gain", "frozen_cost_outside", "depth_effect_outside", "z2M_first_mm",
           "z2M_last_mm", "fit_s", "predict_s", "steps", "load"]


def spread(rows: list[dict], key: str) -> str | None:
    """(max − min)/mean of ``key`` over the rows, as a percentage (the all-row cell)."""
    v = [r[key] for r in rows if r[key] is not None]
    return f"{100 * (max(v) - min(v)) / np.mean(v):.1f} % spread" if v else None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=6)
    parser.add_argument("--seed", type=int, default=12)
    parser.add_argument("--crop", type=float, default=0.8, help="area kept by the crop")
    parser.add_argument("--quick", action="store_true", help="one pair")
    parser.add_argument("--time-budget", type=float, default=None,
                        help="each fit's time budget, s (default: the fit's own); a busy "
                             "machine needs more to reach the same step")
    parser.add_argument("--options", type=json.loads, default={},
                        help="fit options as JSON, e.g. '{\"field_stride\": 3}' or "
                             "'{\"fit_kappa\": true}' (the ablations of docs/stack_fit.md)")
    parser.add_argument("--name", default="stack_fit", help="results file name")
    parser.add_argument("--spread", type=int, nargs="*", default=[3, 5],
                        help="also fit this many planes spread over the stack (each count "
                             "once on the original and once transformed)")
    args = parser.parse_args(argv)
    raw = load_psf_stack_3d()
    cases = [([i, j], kind, seed) for i, j, kind, seed in
             draw_cases(1 if args.quick else args.pairs, args.seed, raw.shape[0])]
    rng = np.random.default_rng(args.seed + 1)
    cases += [(spread_planes(k, raw.shape[0]), str(rng.choice(TRANSFORMS)),
               int(rng.integers(0, 2**31))) for k in ([] if args.quick else args.spread)]
    rows = []
    for planes, kind, crop_seed in cases:
        for label in ("original", f"{kind}+crop{args.crop:g}"):
            stack = raw if label == "original" else transform_stack(
                raw, kind, args.crop, np.random.default_rng(crop_seed))
            options = dict(args.options)
            if args.time_budget is not None:
                options["time_budget"] = args.time_budget
            row = run_case(stack, planes, label, **options)
            rows.append(row)
            print(f"{row['pair']} {label}: model {row['model_mean']:.4f}, baseline "
                  f"{row['baseline_mean']:.4f}, frozen {row['frozen_mean']:.4f}, "
                  f"rendered {row['rendered_mean']:.4f} ({row['rendered_above']} above), "
                  f"blend {row['blend_mean']:.4f}, {row['above_baseline']} above, "
                  f"outside gain {row['outside_gain']}, frozen cost outside "
                  f"{row['frozen_cost_outside']}, depth-law effect "
                  f"{row['depth_effect_outside']}, z2·M at the first and last planes "
                  f"{row['z2M_first_mm']}, {row['z2M_last_mm']} mm, "
                  f"fit {row['fit_s']:.1f} s "
                  f"({row['stop_reason']})", flush=True)
            write_json(args.name, rows, {"seed": args.seed, "pairs": len(cases),
                                           "crop": args.crop, "options": args.options,
                                           "float64": bool(jax.config.jax_enable_x64)})
    table = [{k: r[k] for k in COLUMNS} for r in rows]
    if rows:
        table.append({"pair": "**all**",
                      "model_mean": float(np.mean([r["model_mean"] for r in rows])),
                      "baseline_mean": float(np.mean([r["baseline_mean"] for r in rows])),
                      **{k: float(np.mean([r[k] for r in rows]))
                         for k in ("frozen_mean", "rendered_mean", "blend_mean")},
                      "worst_r": float(min(r["worst_r"] for r in rows)),
                      "above_baseline": f"{sum(r['all_above'] for r in rows)}/{len(rows)} "
                                        f"cases all",
                      "outside_gain": float(np.mean([r["outside_gain"] for r in rows
                                                     if r["outside_gain"] is not None])),
                      "frozen_cost_outside": float(np.mean(
                          [r["frozen_cost_outside"] for r in rows
                           if r["frozen_cost_outside"] is not None])),
                      "depth_effect_outside": float(np.mean(
                          [r["depth_effect_outside"] for r in rows
                           if r["depth_effect_outside"] is not None])),
                      **{k: spread(rows, k) for k in ("z2M_first_mm", "z2M_last_mm")},
                      "fit_s": float(max(r["fit_s"] for r in rows)),
                      "predict_s": float(max(r["predict_s"] for r in rows))})
    def fmt(key, v):
        if not isinstance(v, float):
            return v
        if key.startswith("z2M"):
            return f"{v:.2f}"
        return f"{v:.1f}" if key in ("fit_s", "predict_s", "load") else f"{v:.4f}"

    table = [{k: fmt(k, v) for k, v in r.items()} for r in table]
    print(markdown_table(table, COLUMNS))
    print("wrote", write_json(args.name, rows, {"seed": args.seed, "pairs": len(cases),
                                                  "crop": args.crop, "options": args.options,
                                                  "float64": bool(jax.config.jax_enable_x64)}))


if __name__ == "__main__":
    main()
