"""Benchmark: fit two planes, predict the other 42, compare with the scaling baseline.

For ``--pairs`` pairs (i, j) with 10 <= j - i <= 30 drawn from ``--seed``, on the
original stack and on a transformed copy (one random rotation/flip + a random crop to
~80 % of the area, the same for all planes), run

* the scaling baseline (nearest given plane magnified about the registered fixed point),
* the wave model (depth law zeta(t) = zeta_i s(t)^-kappa, kappa fitted),
* the frozen-distance ablation (same model, zeta(t) = zeta_i for all planes),

and report the mean / worst Pearson over the 42 held-out planes.  Prints a Markdown
table and writes everything (incl. per-plane scores) to ``--out`` after every case.

    python scripts/stack_fit_prototype/bench.py --pairs 6 --seed 12 --out bench.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
import json
import time

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import stackfit as sf  # noqa: E402

DATA = str(Path(__file__).resolve().parents[2] / "diffcam" / "data" / "diffusercam_3d.npz")
TRANSFORMS = ["rot90", "rot180", "rot270", "flipud", "fliplr", "transpose"]

# the fit settings used for every case (see REPORT.md)
FIT = dict(zetas=(32.0, 64.0, 128.0), n_gs=30, max_steps=400, patience=40,
           time_budget=55.0, val_block=1, val_frac=0.10)


def draw_cases(n_pairs: int, seed: int, n_planes: int):
    """Pairs (i, j), 10..30 apart, and one transform (kind, crop rng seed) per pair."""
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(n_pairs):
        gap = int(rng.integers(10, 31))
        i = int(rng.integers(0, n_planes - gap))
        kind = str(rng.choice(TRANSFORMS))
        crop_seed = int(rng.integers(0, 2 ** 31))
        cases.append((i, i + gap, kind, crop_seed))
    return cases


def scores(pred, stack, held):
    return np.array([sf.pearson(pred[t], stack[t]) for t in held])


def run_case(stack, i, j, label, verbose=False):
    """Everything for one (stack, pair): returns a JSON-able dict."""
    n = stack.shape[0]
    held = [t for t in range(n) if t not in (i, j)]
    imgs = [stack[i].astype(np.float32), stack[j].astype(np.float32)]
    out = {"label": label, "i": i, "j": j, "shape": list(stack.shape[1:])}

    reg = sf.register(imgs[0], imgs[1])
    out["registration"] = {"s_j": reg.s_j, "centre": list(reg.centre), "r": reg.r,
                           "seconds": reg.seconds}
    t0 = time.time()
    base = sf.baseline_stack({i: imgs[0], j: imgs[1]}, reg, n)
    out["baseline_seconds"] = time.time() - t0
    rb = scores(base, stack, held)

    for name, kw in (("model", dict(kappa=0.0, fit_kappa=True)),
                     ("frozen", dict(frozen=True))):
        fit = sf.fit_wave(imgs, i, j, reg, verbose=verbose, **FIT, **kw)
        t0 = time.time()
        pred = sf.predict_stack(fit, n)
        t_pred = time.time() - t0
        r = scores(pred, stack, held)
        p = {k: float(v) for k, v in fit.params.items() if np.ndim(v) == 0}
        p["centre"] = [float(c) for c in np.asarray(fit.params["centre"])]
        out[name] = {
            "mean": float(r.mean()), "min": float(r.min()),
            "worst_plane": int(held[int(r.argmin())]),
            "beats_baseline_all": bool((r > rb).all()),
            "n_beats": int((r > rb).sum()),
            "fit_seconds": fit.seconds, "predict_seconds": t_pred,
            "best_step": fit.best_step, "steps": fit.steps,
            "stop_reason": fit.stop_reason,
            "best_val_r": float(max(fit.val_history)),
            "zeta_scan": fit.zeta_scan, "scalars": p,
            "per_plane": r.tolist(),
        }
    out["baseline"] = {"mean": float(rb.mean()), "min": float(rb.min()),
                       "per_plane": rb.tolist()}
    out["held"] = held
    return out


def table(results):
    rows = ["| pair | transform | model mean | worst plane (r) | baseline mean | "
            "frozen mean | fit s | predict s | steps (best/run) | model > baseline "
            "at every plane |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        m, f, b = r["model"], r["frozen"], r["baseline"]
        rows.append(
            f"| ({r['i']}, {r['j']}) | {r['label']} | {m['mean']:.4f} | "
            f"{m['worst_plane']} ({m['min']:.4f}) | {b['mean']:.4f} | {f['mean']:.4f} | "
            f"{m['fit_seconds']:.1f} | {m['predict_seconds']:.1f} | "
            f"{m['best_step']}/{m['steps']} | "
            f"{'yes' if m['beats_baseline_all'] else 'no'} ({m['n_beats']}/42) |")
    if results:
        mm = np.mean([r["model"]["mean"] for r in results])
        bb = np.mean([r["baseline"]["mean"] for r in results])
        ff = np.mean([r["frozen"]["mean"] for r in results])
        rows.append(f"| **all** | | **{mm:.4f}** | | {bb:.4f} | {ff:.4f} | | | | "
                    f"{sum(r['model']['beats_baseline_all'] for r in results)}"
                    f"/{len(results)} |")
    return "\n".join(rows)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pairs", type=int, default=6)
    ap.add_argument("--seed", type=int, default=12)
    ap.add_argument("--out", default="bench.json")
    ap.add_argument("--crop", type=float, default=0.8)
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args()

    raw = np.load(DATA)["psf_stack"].astype(np.float64) / 65535.0
    original = sf.preprocess(raw)
    cases = draw_cases(a.pairs, a.seed, raw.shape[0])
    results = []
    for (i, j, kind, crop_seed) in cases:
        for label in ("original", f"{kind}+crop{a.crop:g}"):
            if label == "original":
                stack = original
            else:
                stack = sf.preprocess(sf.transform_stack(
                    raw, kind, a.crop, np.random.default_rng(crop_seed)))
            res = run_case(stack, i, j, label, verbose=a.verbose)
            results.append(res)
            print(f"done ({i},{j}) {label}: model {res['model']['mean']:.4f} "
                  f"frozen {res['frozen']['mean']:.4f} "
                  f"baseline {res['baseline']['mean']:.4f} "
                  f"fit {res['model']['fit_seconds']:.1f}s", flush=True)
            with open(a.out, "w") as fh:
                json.dump({"settings": FIT, "seed": a.seed, "cases": results}, fh,
                          indent=1)
    print(table(results))


if __name__ == "__main__":
    main()
