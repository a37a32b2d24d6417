"""Benchmark: where the stack model's rendering alone falls below the scaling baseline,
and the most that a correction on the sensor side could recover there.

Usage: python -m benchmarks.bench_stack_limits [--cases 10,39 0,26 2,22,41]
       [--time-budget 400]

The cases are those of :mod:`benchmarks.bench_stack_fit` where the rendering alone loses
to the baseline at some held-out plane (original orientation). Per case,
:func:`diffcam.calibrate.fit_stack` with the defaults (a longer time budget, so that a
busy machine does not cut the fit short), then for each given plane and each held-out
plane next to one:

- ``rendered``/``baseline``: Pearson with the measured plane over the frame, and in
  annuli about the fitted magnification centre (``r0_30`` … ``r90_120``, pixels) as
  ``rendered/baseline``;
- ``envelope``: the rendering times the measured/rendered ratio, both blurred by 15 px.
  It uses the measured plane, so it is an oracle: the most that any smooth
  multiplicative correction (envelope, vignetting, the sensor's angular response) could
  give;
- ``blur``: the best over the fitted blur scaled by 0.7, 0.85, 1.15 and 1.3 (the
  source's size and bandwidth), with that scale;
- ``response``: the rendering raised to the power γ fitted on the given planes (a
  pointwise sensor response), with γ.

The baseline is the nearest given plane magnified about the registered centre
(:func:`diffcam.evaluate.scaling_baseline`). Results go to
``benchmarks/results/stack_limits.json``; a Markdown table is printed.
"""

from __future__ import annotations

import argparse

import equinox as eqx
import numpy as np
from scipy import ndimage
from scipy.optimize import minimize_scalar

from benchmarks.harness import markdown_table, write_json
from diffcam.calibrate import fit_stack, prepare_planes
from diffcam.calibrate.stack.model import render_planes
from diffcam.data import load_psf_stack_3d
from diffcam.evaluate import pearson, scaling_baseline

ANNULI = ((0, 30), (30, 60), (60, 90), (90, 120))
BLUR_SCALES = (0.7, 0.85, 1.15, 1.3)
ENVELOPE_SIGMA = 15.0
COLUMNS = ["case", "plane", "given", "rendered", "baseline", "envelope", "blur",
           "blur_scale", "response", "gamma"] + [f"r{a}_{b}" for a, b in ANNULI]


def _pearson(a, b, mask=None) -> float:
    return float(pearson(a, b, mask=mask))


def _planes_of_interest(planes: list[int], n: int) -> list[int]:
    """The given planes and the held-out planes next to them."""
    near = {t + d for t in planes for d in (-1, 0, 1)}
    return sorted(t for t in near if 0 <= t < n)


def _response_gamma(rendered: dict, measured: np.ndarray, planes: list[int]) -> float:
    """The power γ that best maps the rendering onto the given planes."""
    def loss(g):
        return -np.mean([_pearson(np.clip(rendered[k], 0, None) ** g, measured[k])
                         for k in planes])
    return float(minimize_scalar(loss, bounds=(0.5, 2.0), method="bounded").x)


def _blurred_renderings(fit, ts: list[int]) -> dict:
    """{scale: {plane: rendering}} with the fitted blur scaled."""
    out = {}
    for scale in BLUR_SCALES:
        model = eqx.tree_at(lambda m: m.log_sigma, fit.model,
                            fit.model.log_sigma + np.log(scale))
        out[scale] = dict(zip(ts, render_planes(model, ts)))
    return out


def _envelope(rendering: np.ndarray, measured: np.ndarray) -> np.ndarray:
    smooth_r = ndimage.gaussian_filter(rendering, ENVELOPE_SIGMA)
    ratio = ndimage.gaussian_filter(measured, ENVELOPE_SIGMA) / np.maximum(
        smooth_r, 1e-6 * smooth_r.max())
    return rendering * ratio


def run_case(stack: np.ndarray, planes: list[int], time_budget: float) -> list[dict]:
    """Fit the case and measure every plane of interest: JSON rows."""
    fit = fit_stack(stack, planes, time_budget=time_budget, progress=False)
    measured = np.asarray(prepare_planes(stack), np.float64)
    ts = _planes_of_interest(planes, stack.shape[0])
    rendered = dict(zip(ts, render_planes(fit.model, ts)))
    baseline = dict(zip(ts, scaling_baseline({k: measured[k] for k in planes}, ts,
                                             registration=fit.registration)))
    blurred = _blurred_renderings(fit, ts)
    gamma = _response_gamma(rendered, measured, planes)
    yy, xx = np.indices(measured.shape[1:])
    cy, cx = (float(c) for c in np.asarray(fit.model.centre))
    radius = np.hypot(yy - cy, xx - cx)
    rows = []
    for t in ts:
        m, r, b = measured[t], rendered[t], baseline[t]
        blur = {s: _pearson(blurred[s][t], m) for s in BLUR_SCALES}
        best = max(blur, key=blur.get)
        row = {"case": "(" + ", ".join(map(str, planes)) + ")", "plane": t,
               "given": t in planes, "rendered": _pearson(r, m), "baseline": _pearson(b, m),
               "envelope": _pearson(_envelope(r, m), m), "blur": blur[best],
               "blur_scale": best, "response": _pearson(np.clip(r, 0, None) ** gamma, m),
               "gamma": gamma, "fit_seconds": fit.seconds, "stop": fit.stop_reason}
        for a, c in ANNULI:
            ring = (radius >= a) & (radius < c)
            row[f"r{a}_{c}"] = f"{_pearson(r, m, ring):.4f}/{_pearson(b, m, ring):.4f}"
        rows.append(row)
        print({k: v for k, v in row.items() if k != "stop"}, flush=True)
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=["10,39", "0,26", "2,22,41"],
                        help="given planes of each case, comma-separated")
    parser.add_argument("--time-budget", type=float, default=400.0, help="seconds per fit")
    args = parser.parse_args(argv)
    stack = np.asarray(load_psf_stack_3d(), np.float64)
    rows = []
    for case in args.cases:
        rows += run_case(stack, [int(p) for p in case.split(",")], args.time_budget)
    table = [{k: (f"{v:.4f}" if isinstance(v, float) and k not in ("blur_scale", "gamma")
                  else v) for k, v in r.items()} for r in rows]
    for r in table:
        r["gamma"] = f"{float(r['gamma']):.3f}"
    print(markdown_table(table, COLUMNS))
    print("wrote", write_json("stack_limits", rows, {"cases": args.cases,
                                                      "time_budget": args.time_budget,
                                                      "envelope_sigma_px": ENVELOPE_SIGMA}))


if __name__ == "__main__":
    main()
