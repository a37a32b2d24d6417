"""Benchmark: when does the wave model of a PSF stack beat one magnified PSF? A regime
map on simulated stacks the fitted model did not make.

Usage: python -m benchmarks.bench_stack_regimes [--quick] [--seeds 3 4 5] [--options JSON]

Every row is :mod:`benchmarks.bench_stack_sim`'s protocol (12 planes, planes 3 and 8
given, the others predicted and scored by Pearson against the noise-free planes) on a
camera varied one setting at a time around a DiffuserCam-scale centre: z2 = 5 mm,
sources from 20 to 200 mm, a 768² field at 3 µm, 1.5° diffuser, light 532 ± 17 nm,
a point source. Varied: z2 (so the magnification range M = 1 + z2/z1), the diffuser's
deflection, the source's radius and the spectral width. Columns:

- ``model_gain``: the model's held-out mean minus the scaling baseline's;
- ``rendered_gain``: the same for the rendering alone (no carried residual);
- ``outside_gain``: the model's gain on the planes outside the given pair;
- ``frozen_cost_outside``: what freezing the distance (no depth law) costs there;
- ``above``: held-out planes where the model beats the baseline.

Gains are means over the diffusers of ``--seeds`` (one random diffuser each), ``above``
their total.

Results go to ``benchmarks/results/stack_regimes.json``.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from benchmarks.bench_stack_sim import curves
from benchmarks.harness import markdown_table, write_json

PLANES = [3, 8]
CENTRE = {"z2": 5e-3, "z1_near": 20e-3, "z1_far": 200e-3, "dx": 3e-6,
          "deflection": 1.5, "bandwidth": 17e-9, "source_radius": 0.0}
VARIATIONS = [("centre", {}),
              ("z2 1 mm", {"z2": 1e-3}), ("z2 2.5 mm", {"z2": 2.5e-3}),
              ("z2 10 mm", {"z2": 10e-3}),
              ("deflection 0.75°", {"deflection": 0.75}), ("deflection 3°", {"deflection": 3.0}),
              ("source radius 0.1 mm", {"source_radius": 0.1e-3}),
              ("source radius 0.3 mm", {"source_radius": 0.3e-3}),
              ("monochromatic", {"bandwidth": 0.0}), ("532 ± 40 nm", {"bandwidth": 40e-9})]
COLUMNS = ["setting", "M_range", "model_gain", "rendered_gain", "outside_gain",
           "frozen_cost_outside", "above", "zeta_reference_px2", "seconds"]


def one_diffuser(camera: dict, fit_options: dict) -> dict:
    """The gains of one simulated stack (module docstring), per-plane curves kept."""
    scores, z1, fit = curves(PLANES, fit_options, **camera)
    truth = "noise-free"
    base = scores[("baseline", truth)]
    held = np.array([t for t in range(len(z1)) if t not in PLANES])
    outside = np.array([t for t in held if t < min(PLANES) or t > max(PLANES)])
    model, rendered, frozen = (scores[(p, truth)] for p in ("model", "rendered", "frozen"))
    m = 1 + camera["z2"] / z1
    return {"M_range": f"{m.min():.3f}–{m.max():.3f}",
            "model_gain": float((model - base)[held].mean()),
            "rendered_gain": float((rendered - base)[held].mean()),
            "outside_gain": float((model - base)[outside].mean()),
            "frozen_cost_outside": float((model - frozen)[outside].mean()),
            "above": int((model[held] > base[held]).sum()), "held": len(held),
            "zeta_reference_px2": fit.summary()["zeta_reference_px2"],
            "per_plane": {p: scores[(p, truth)].tolist()
                          for p in ("model", "rendered", "frozen", "baseline")}}


def row(setting: str, camera: dict, fit_options: dict, seeds) -> dict:
    """One setting over the diffusers of ``seeds``: mean gains, total planes above."""
    t0 = time.perf_counter()
    runs = [one_diffuser({**camera, "seed": int(s)}, fit_options) for s in seeds]
    mean = {k: float(np.mean([r[k] for r in runs]))
            for k in ("model_gain", "rendered_gain", "outside_gain", "frozen_cost_outside",
                      "zeta_reference_px2")}
    return {"setting": setting, "M_range": runs[0]["M_range"], **mean,
            "above": f"{sum(r['above'] for r in runs)}/{sum(r['held'] for r in runs)}",
            "seconds": time.perf_counter() - t0, "camera": camera, "seeds": list(seeds),
            "runs": runs}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the centre only")
    parser.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5],
                        help="diffuser seeds (one simulated stack each)")
    parser.add_argument("--options", type=json.loads, default={},
                        help="StackFitOptions overrides as JSON")
    args = parser.parse_args(argv)
    rows = []
    for setting, change in VARIATIONS[:1] if args.quick else VARIATIONS:
        rows.append(row(setting, {**CENTRE, **change}, args.options, args.seeds))
        r = rows[-1]
        print(f"{setting}: model {r['model_gain']:+.4f}, rendered {r['rendered_gain']:+.4f}, "
              f"outside {r['outside_gain']:+.4f}, frozen cost {r['frozen_cost_outside']:+.4f}, "
              f"{r['above']} above ({r['seconds']:.0f} s)", flush=True)
        write_json("stack_regimes", rows, {"planes": PLANES, "centre": CENTRE,
                                           "seeds": args.seeds, "options": args.options})
    print(markdown_table([{k: (f"{r[k]:+.4f}" if isinstance(r[k], float) and k != "seconds"
                               else r[k]) for k in COLUMNS} for r in rows], COLUMNS))


if __name__ == "__main__":
    main()
