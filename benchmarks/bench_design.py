"""Diffuser design (diffcam.design): how far a design lowers the largest cross-depth PSF
correlation, beside the diffusers a user would take instead, and what it costs.

    python -m benchmarks.bench_design                 # → benchmarks/results/design.json

Decorrelation (``diffcam design``'s defaults: 256² at 3 µm, z2 2 mm, aperture radius
0.192 mm, n 1.5, heights 0–2 µm, features ≥ 30 µm, 16 depths 10–60 mm even in 1/z1,
300 Adam steps): for each parametrisation and seed, the largest correlation at the
random start and after the design, and for baselines that are not optimised — another
random surface of the same feature size and height range, and for the microlens array a
regular array of as many lenses. Each is also scored on a held-out grid of 61 depths
over the same range (4× finer), so a gain only at the sampled depths would show. The
smooth surface is also designed without the spread term (sparsity weight 0): an
ablation of what that term costs or gives.

Cost: the whole design's wall time and seconds per step at 256² over 16 depths;
XLA's temporaries of the loss and of its gradient (``memory_analysis``) for the two ways
of computing the PSFs (`psf_map`, and ``jax.vmap`` of `psf`), with their times per
step; at 512² over 32 depths a whole 300-step design (``--large-steps N`` below 300
extrapolates from N steps, and the row says so).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.harness import time_interleaved, write_json
from diffcam.design import (DesignOptions, LensletArray, SmoothSurface, depth_range,
                            design, evaluate_design)
from diffcam.design.objective import (DepthObjective, depth_objective, objective_terms,
                                      spread, standardised)
from diffcam.design.surfaces import height_map
from diffcam.model import Camera, psf

PIXEL, Z2, INDEX, H_MAX, FEATURE, LENSES = 3e-6, 2e-3, 1.5, 2e-6, 30e-6, 36
NEAR, FAR = 10e-3, 60e-3


def camera(n: int) -> Camera:
    """`diffcam design`'s camera at n² (no padding is needed at these sizes)."""
    return Camera(wavelength=532e-9, z2=Z2, dx=PIXEL, aperture_radius=n * PIXEL / 4,
                  shape=(n, n))


def start(kind: str, seed: int, n: int):
    if kind == "smooth":
        return SmoothSurface.random(seed, (n, n), PIXEL, FEATURE, H_MAX)
    regular = kind == "regular lenslets"
    return LensletArray.random(seed, (n, n), PIXEL, FEATURE, H_MAX, LENSES,
                               n * PIXEL / 4, regular=regular)


def _scores(surface, objective, held_out) -> tuple[float, float, float]:
    """(max correlation on the design's depths, on the held-out grid, spread)."""
    on = evaluate_design(surface, objective)
    off = evaluate_design(surface, objective._replace(z1=held_out))
    return on["max_correlation"], off["max_correlation"], on["spread"]


def decorrelation(kind: str, seed: int, steps: int, weight: float = 0.1) -> dict:
    n = 256
    cam, z1 = camera(n), depth_range(NEAR, FAR, 16)
    held_out = depth_range(NEAR, FAR, 61)
    first = start(kind, seed, n)
    options = DesignOptions(steps=steps, sparsity_weight=weight, progress=False)
    t = time.perf_counter()
    result = design(first, cam, z1, INDEX, options)
    wall = time.perf_counter() - t
    objective = result.objective()
    before = _scores(first, objective, held_out)
    after = _scores(result.surface, objective, held_out)
    base_kind = "regular lenslets" if kind == "lenslets" else kind
    baseline = _scores(start(base_kind, seed + 100, n), objective, held_out)
    h = np.asarray(result.height_map().height)
    return {"surface": kind, "seed": seed, "sparsity_weight": weight, "steps": result.steps,
            "start": round(before[0], 4), "design": round(after[0], 4),
            "baseline": round(baseline[0], 4),
            "baseline_is": "regular array" if kind == "lenslets" else "random, same limits",
            "held_out_start": round(before[1], 4), "held_out_design": round(after[1], 4),
            "held_out_baseline": round(baseline[1], 4),
            "spread_start": round(before[2], 3), "spread_design": round(after[2], 3),
            "height_um": f"{h.min() * 1e6:.2f}–{h.max() * 1e6:.2f}",
            "wall_s": round(wall, 1), "wall_per_step_s": round(wall / result.steps, 3)}


def _psfs_by_vmap(surface, objective):
    """The objective with the PSFs from ``jax.vmap`` of `psf` (chunked by its
    custom_vmap) instead of `psf_map`."""
    diffuser = height_map(surface, objective.refractive_index)
    z1 = jnp.asarray(objective.z1, jnp.float32)
    h = jax.vmap(lambda z: psf(diffuser, objective.camera, z))(z1)
    return objective_terms(standardised(h), spread(h), objective)


def cost(n: int, depths: int, repeats: int) -> list[dict]:
    """Temporaries and time per step of the loss and its gradient, both PSF routes."""
    surface = start("smooth", 0, n)
    objective = DepthObjective(camera(n), depth_range(NEAR, FAR, depths), INDEX)
    rows = []
    for route, fn in (("psf_map", depth_objective), ("vmap(psf)", _psfs_by_vmap)):
        def value(c, f=fn):
            return f(dataclasses.replace(surface, coefficients=c), objective)[0]
        loss, grad = jax.jit(value), jax.jit(jax.value_and_grad(value))
        c = surface.coefficients
        mem = {what: f.lower(c).compile().memory_analysis().temp_size_in_bytes / 2 ** 20
               for what, f in (("forward", loss), ("gradient", grad))}
        t = time_interleaved({"forward": lambda: loss(c), "gradient": lambda: grad(c)},
                             repeats=repeats)
        rows.append({"N": n, "depths": depths, "route": route,
                     "forward_temp_mb": round(mem["forward"], 1),
                     "gradient_temp_mb": round(mem["gradient"], 1),
                     "memory_ratio": round(mem["gradient"] / mem["forward"], 2),
                     "forward_s": round(t["forward"]["median_s"], 3),
                     "gradient_s": round(t["gradient"]["median_s"], 3),
                     "gradient_first_s": round(t["gradient"]["first_s"], 1)})
    return rows


def large(steps: int) -> dict:
    """512² over 32 depths: the first step (compiling) and ``steps`` − 1 more, continued
    from its checkpoint; below the default 300 steps the whole run is extrapolated from
    the seconds per step (the row says which)."""
    n, depths = 512, 32
    cam, z1 = camera(n), depth_range(NEAR, FAR, depths)
    with tempfile.TemporaryDirectory() as folder:
        options = DesignOptions(steps=1, progress=False,
                                checkpoint=os.path.join(folder, "large.npz"))
        t = time.perf_counter()
        design(start("smooth", 0, n), cam, z1, INDEX, options)
        first_s = time.perf_counter() - t
        t = time.perf_counter()
        result = design(start("smooth", 0, n), cam, z1, INDEX,
                        dataclasses.replace(options, steps=steps))
        per_step = (time.perf_counter() - t) / (steps - 1)
    whole = first_s + 299 * per_step
    return {"N": n, "depths": depths, "steps_run": steps, "first_step_s": round(first_s, 1),
            "s_per_step": round(per_step, 2),
            "run_300_steps_min": round(whole / 60, 1),
            "run_is": "measured" if steps >= 300 else f"extrapolated from {steps} steps",
            "start": round(result.history[0, 2], 4),
            "design": round(result.final["max_correlation"], 4)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--large-steps", type=int, default=300,
                        help="steps of the 512² design (below 300: extrapolated)")
    args = parser.parse_args(argv)
    rows = [decorrelation("smooth", seed, args.steps) for seed in range(args.seeds)]
    rows.append(decorrelation("smooth", 0, args.steps, weight=0.0))
    rows += [decorrelation("lenslets", seed, args.steps) for seed in range(args.seeds)]
    for row in rows:
        print(row, flush=True)
    costs = cost(256, 16, repeats=5) + cost(512, 32, repeats=2)
    print(costs, flush=True)
    big = large(args.large_steps)
    print(big, flush=True)
    smooth = [r for r in rows if r["surface"] == "smooth" and r["sparsity_weight"] > 0]
    claim = (f"at 256² over 16 depths (10–60 mm) the design lowers the largest "
             f"cross-depth PSF correlation of a random smooth surface from "
             f"{smooth[0]['start']} to {smooth[0]['design']} (held-out 61 depths: "
             f"{smooth[0]['held_out_start']} → {smooth[0]['held_out_design']}); the whole "
             f"{smooth[0]['steps']}-step run takes {smooth[0]['wall_s']} s on "
             f"{os.cpu_count()} cores; the gradient's temporaries are "
             f"{costs[0]['memory_ratio']}× the forward pass's (psf_map); at 512² over 32 "
             f"depths {big['s_per_step']} s per step, 300 steps {big['run_300_steps_min']} "
             f"min ({big['run_is']})")
    write_json("design", rows, {"cost": costs, "large": big, "claim": claim})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
