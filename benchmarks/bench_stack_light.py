"""Benchmark: the absolute magnification, and z1 in units of z2, from the light of two
measured planes (inverse-square law), on ``bench_stack_fit``'s cases.

Usage: python -m benchmarks.bench_stack_light [--pairs 6] [--seed 12] [--crop 0.8]
       [--spread 3 5]

The same cases as :mod:`benchmarks.bench_stack_fit` (the same seed draws the same pairs,
transforms and crops). Per case, as :func:`diffcam.calibrate.fit_stack` does: the given
planes' light (summed after the border-median dark level), the relative magnification
M(anchor)/M(reference) registered between the reference (first given plane) and the
anchor (the given plane farthest from it), and
:func:`diffcam.evaluate.registration.magnification_from_light`. Reported:

- ``M_first``/``M_last``: M = 1 + z2/z1 at the stack's first and last planes (the same
  planes in every case), and ``z1_first_z2``/``z1_last_z2``: z1/z2 there; the all-row
  cells are their spread over the cases (the identifiability asked of a depth law);
- ``law_mean_err``/``law_max_err``: the other planes' light predicted by the law,
  ∝ (M(t) − 1)², against their measured light (relative error, mean and worst);
- ``linear_mean_err``/``linear_max_err``: the baseline a user would use instead, the
  light interpolated (and extrapolated) linearly in the plane index through the two
  planes.

No fit: registration only (about 3 s a case). Results go to
``benchmarks/results/stack_light.json``; a Markdown table is printed.
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks.bench_stack_fit import TRANSFORMS, draw_cases, spread_planes, transform_stack
from benchmarks.harness import markdown_table, write_json
from diffcam.calibrate import prepare_planes
from diffcam.data import load_psf_stack_3d
from diffcam.evaluate.registration import (magnification_from_light, register_magnification,
                                           relative_magnification_at)
from diffcam.io.preprocessing import plane_light

COLUMNS = ["pair", "transform", "M_first", "M_last", "z1_first_z2", "z1_last_z2",
           "law_mean_err", "law_max_err", "linear_mean_err", "linear_max_err"]


def run_case(stack: np.ndarray, planes: list[int], label: str) -> dict:
    """Magnification and z1/z2 from the light of the reference and anchor planes, and
    the other planes' light by the law and by linear interpolation: one JSON row."""
    n = stack.shape[0]
    light = plane_light(stack)
    ref = planes[0]
    anchor = max(planes[1:], key=lambda t: abs(t - ref))
    prepared = prepare_planes(stack[[ref, anchor]])
    m = register_magnification(prepared[0], prepared[1]).magnification
    m_ref = magnification_from_light(light[ref], light[anchor], m)
    t = np.arange(n)
    big_m = m_ref * relative_magnification_at(t, m, ref, anchor)
    law = light[ref] * ((big_m - 1) / (m_ref - 1)) ** 2
    linear = light[ref] + (light[anchor] - light[ref]) * (t - ref) / (anchor - ref)
    held = np.setdiff1d(t, planes)
    err = {k: np.abs(v[held] / light[held] - 1) for k, v in (("law", law), ("linear", linear))}
    return {"pair": "(" + ", ".join(map(str, planes)) + ")", "transform": label,
            "M_first": float(big_m[0]), "M_last": float(big_m[-1]),
            "z1_first_z2": float(1 / (big_m[0] - 1)), "z1_last_z2": float(1 / (big_m[-1] - 1)),
            **{f"{k}_mean_err": float(e.mean()) for k, e in err.items()},
            **{f"{k}_max_err": float(e.max()) for k, e in err.items()}}


def spread(rows: list[dict], key: str) -> str:
    v = [r[key] for r in rows]
    return f"{min(v):.3f}–{max(v):.3f} ({100 * (max(v) / min(v) - 1):.1f} %)"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=6)
    parser.add_argument("--seed", type=int, default=12)
    parser.add_argument("--crop", type=float, default=0.8, help="area kept by the crop")
    parser.add_argument("--spread", type=int, nargs="*", default=[3, 5])
    args = parser.parse_args(argv)
    raw = np.asarray(load_psf_stack_3d(), np.float64)
    cases = [([i, j], kind, seed) for i, j, kind, seed in
             draw_cases(args.pairs, args.seed, raw.shape[0])]
    rng = np.random.default_rng(args.seed + 1)
    cases += [(spread_planes(k, raw.shape[0]), str(rng.choice(TRANSFORMS)),
               int(rng.integers(0, 2**31))) for k in args.spread]
    rows = []
    for planes, kind, crop_seed in cases:
        for label in ("original", f"{kind}+crop{args.crop:g}"):
            stack = raw if label == "original" else transform_stack(
                raw, kind, args.crop, np.random.default_rng(crop_seed))
            rows.append(run_case(stack, planes, label))
            print(rows[-1], flush=True)
    table = [{k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()}
             for r in rows]
    table.append({"pair": "**all**",
                  **{k: spread(rows, k) for k in ("M_first", "M_last", "z1_first_z2",
                                                   "z1_last_z2")},
                  **{k: f"{np.mean([r[k] for r in rows]):.4f}"
                     for k in ("law_mean_err", "linear_mean_err")},
                  **{k: f"{max(r[k] for r in rows):.4f}"
                     for k in ("law_max_err", "linear_max_err")}})
    print(markdown_table(table, COLUMNS))
    print("wrote", write_json("stack_light", rows, {"seed": args.seed, "pairs": len(cases),
                                                     "crop": args.crop}))


if __name__ == "__main__":
    main()
