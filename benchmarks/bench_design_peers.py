"""One diffuser-design step in diffcam beside the same step with chromatix's and dLux's PSFs.

    python -m benchmarks.bench_design_peers [--sizes 256 512] [--chromatix-python PY]
                                                  # → benchmarks/results/design_peers.json

The problem, `diffcam design`'s defaults (`benchmarks.bench_design.camera`): a random
smooth surface (seed 0; heights 0–2 µm, features ≥ 30 µm, n 1.5) on an N² grid of 3 µm,
z2 2 mm, aperture radius N·3 µm/4, 532 nm, point sources at 16 depths (256²) or 32
(512²) over 10–60 mm even in 1/z1. One step is Adam (optax, step size 0.2) on the
surface's parameters after the value and gradient of the depth-discrimination loss
(`diffcam.design.objective`: the smooth maximum of the PSFs' pairwise correlations plus
0.1 × their mean spread), jitted whole (``eqx.filter_jit``).

Only the PSFs differ between the candidates; the surface, its height → phase
(θ = 2π(n − 1)h/λ), the loss and the optimiser are the same code:

- ``diffcam design``: the loss as `diffcam design` computes it
  (`diffcam.design.objective.depth_objective`: `psf_map`, scaling path, a chunk of
  depths at a time, recomputed in the reverse pass);
- ``diffcam (direct)``: the same on ``Camera(method="direct")``, the discretisation the
  peers share (one Fresnel transfer function over z2 on the N² grid, no padding);
- ``chromatix`` and ``dLux``: their PSFs as `benchmarks.bench_peers` writes them
  (`chromatix_psfs`, `dlux_psf`), through ``jax.vmap`` over depth (what a user writes
  first) and ``jax.lax.map`` of a ``jax.checkpoint``-ed depth (4 chunks, what bounds the
  gradient's memory, as `psf_map` does), each depth reduced to its standardised PSF and
  spread inside the map.

Before timing, each candidate's loss and gradient at the start are compared with
``diffcam (direct)``'s (``grad_1mp``: 1 − Pearson of the gradients over every
parameter; the scaling path's own discretisation differs a little). Each library runs in
its own process (chromatix under ``--chromatix-python``, see `benchmarks.bench_peers`):
the first step (compile and run) is ``first_s``; then ``--repeats`` steps, the median
``step_s``, and ``peak_mb``, the process's peak RSS over those steps (VmHWM, reset
before them) less its RSS before them. The processes run one after another, so ``load`` (the 1-minute load average
after each candidate) says how alike their machines were.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_peers import (ROOT, _chromatix_python, _status, _trim,
                                    one_minus_pearson)

DEPTHS = {256: 16, 512: 32}
LEARNING_RATE = 0.2
CANDIDATES = {"diffcam": ["diffcam design", "diffcam (direct)"],
              "chromatix": ["chromatix (vmap)", "chromatix (lax.map + checkpoint)"],
              "dLux": ["dLux (vmap)", "dLux (lax.map + checkpoint)"]}


def _loss(name: str, n: int):
    """``(loss(surface), surface)`` of candidate ``name`` at n²."""
    import dataclasses

    import jax
    import jax.numpy as jnp
    from benchmarks import bench_design, bench_peers
    from diffcam.design import depth_range
    from diffcam.design.objective import (DepthObjective, depth_objective,
                                          objective_terms, spread, standardised)
    camera = bench_design.camera(n)
    z1 = depth_range(bench_design.NEAR, bench_design.FAR, DEPTHS[n])
    surface = bench_design.start("smooth", 0, n)
    if "direct" in name:
        camera = dataclasses.replace(camera, method="direct")
    objective = DepthObjective(camera, z1, bench_design.INDEX)
    if name.startswith("diffcam"):
        return (lambda s: depth_objective(s, objective)[0]), surface
    geometry = (n, float(camera.dx), float(camera.wavelength), float(camera.z2),
                float(camera.aperture_radius))
    if name.startswith("chromatix"):
        one = bench_peers.chromatix_psfs(*geometry)
    else:
        one = bench_peers.dlux_psf(*geometry)
    depths = jnp.asarray(z1, jnp.float32)

    def both(phase, z):
        h = one(phase, z)
        return standardised(h), spread(h)

    def loss(s):
        phase = 2 * jnp.pi * (bench_design.INDEX - 1) * s.height() / camera.wavelength
        if "lax.map" in name:
            q, sp = jax.lax.map(jax.checkpoint(lambda z: both(phase, z)), depths,
                                batch_size=-(-len(z1) // 4))
        else:
            q, sp = jax.vmap(lambda z: both(phase, z))(depths)
        return objective_terms(q, sp, objective)[0]
    return loss, surface


def worker(library: str, n: int, repeats: int, out: str) -> None:
    """Each of ``library``'s candidates at n²: print one JSON line per candidate; save
    its first gradient (every parameter, flattened) to ``out``_<index>.npy."""
    import equinox as eqx
    import jax
    import optax
    for k, name in enumerate(CANDIDATES[library]):
        loss, surface = _loss(name, n)
        adam = optax.adam(LEARNING_RATE)

        @eqx.filter_jit
        def step(s, state):
            value, grad = eqx.filter_value_and_grad(loss)(s)
            updates, state = adam.update(grad, state)
            return eqx.apply_updates(s, updates), state, value, grad

        state = adam.init(eqx.filter(surface, eqx.is_array))
        t = time.perf_counter()
        s1, _, value, grad = jax.block_until_ready(step(surface, state))
        first = time.perf_counter() - t
        loss_value = float(value)
        leaves = jax.tree_util.tree_leaves(eqx.filter(grad, eqx.is_array))
        np.save(f"{out}_{k}.npy", np.concatenate([np.ravel(g) for g in leaves]))
        del s1, value, grad
        _trim()
        open("/proc/self/clear_refs", "w").write("5")  # the peak (VmHWM) is now
        rss0 = _status("VmRSS")
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            jax.block_until_ready(step(surface, state))
            times.append(time.perf_counter() - t)
        peak_mb = (_status("VmHWM") - rss0) / 2 ** 20
        print(json.dumps({"candidate": name, "library": library, "N": n,
                          "depths": DEPTHS[n], "loss": loss_value, "first_s": first,
                          "peak_mb": peak_mb,
                          "step_s": float(np.median(times)), "repeats": repeats,
                          "load": os.getloadavg()[0],
                          "versions": {"jax": jax.__version__,
                                       library: getattr(__import__(library), "__version__",
                                                        None)}}), flush=True)


def run(library: str, python: str, n: int, repeats: int, tmp: str) -> list[dict]:
    """The library's rows at n², run in a fresh process of ``python``."""
    out = str(Path(tmp) / f"{library}_{n}")
    done = subprocess.run([python, "-m", "benchmarks.bench_design_peers", "--worker",
                           library, str(n), str(repeats), out], cwd=ROOT,
                          capture_output=True, text=True)
    rows = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    for k, row in enumerate(rows):
        row["gradient"] = f"{out}_{k}.npy"
    if done.returncode != 0:
        rows.append({"library": library, "N": n, "candidate": library,
                     "status": f"failed: {done.stderr.strip()[-300:]}"})
    return rows


def markdown(rows) -> str:
    lines = ["| candidate | N² | depths | s per step | × diffcam design | peak RSS of the "
             "steps | first step s | loss | grad 1 − Pearson | load |", "|" + "---|" * 10]
    for r in rows:
        if "step_s" not in r:
            lines.append(f"| {r['candidate']} | {r['N']} | | {r['status']} | | | | | | |")
            continue
        lines.append(f"| {r['candidate']} | {r['N']} | {r['depths']} | {r['step_s']:.3f} | "
                     f"{r['x_design']:.2f}× | {r['peak_mb']:.0f} MB | {r['first_s']:.1f} | "
                     f"{r['loss']:.4f} | "
                     f"{r['grad_1mp']:.1e} | {r['load']:.1f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[256, 512],
                   choices=sorted(DEPTHS))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--chromatix-python", default=None,
                   help="an interpreter where chromatix and diffcam import (Python ≥ 3.12)")
    p.add_argument("--name", default="design_peers")
    p.add_argument("--worker", nargs=4, default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker is not None:
        library, n, repeats, out = args.worker
        return worker(library, int(n), int(repeats), out)
    from benchmarks.harness import write_json
    notes: list[str] = []
    pythons = {"diffcam": sys.executable, "dLux": sys.executable,
               "chromatix": _chromatix_python(args.chromatix_python, notes)}
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_design_peers_") as tmp:
        for n in args.sizes:
            for library, python in pythons.items():
                if python is not None:
                    rows += run(library, python, n, args.repeats, tmp)
                    print(f"{library} {n}²: {rows[-1]}", flush=True)
            ref = next(r for r in rows if r["candidate"] == "diffcam (direct)" and r["N"] == n)
            design = next(r for r in rows if r["candidate"] == "diffcam design" and r["N"] == n)
            g0 = np.load(ref["gradient"])
            for r in rows:
                if r["N"] == n and "gradient" in r:
                    r["grad_1mp"] = one_minus_pearson(np.load(r.pop("gradient")), g0)
                    r["x_design"] = r["step_s"] / design["step_s"]
    table = markdown(rows)
    print(table)
    write_json(args.name, rows, {"notes": notes, "table": table, "claim": claim(rows),
                                 "learning_rate": LEARNING_RATE, "depths": DEPTHS})


def claim(rows) -> str:
    """Per size: diffcam design's seconds per step and each peer's as a multiple."""
    parts = []
    for n in sorted({r["N"] for r in rows}):
        timed = [r for r in rows if r["N"] == n and "step_s" in r]
        design = next(r for r in timed if r["candidate"] == "diffcam design")
        others = ", ".join(f"{r['candidate']} {r['x_design']:.2f}×" for r in timed
                           if r is not design)
        parts.append(f"at {n}² over {design['depths']} depths diffcam design takes "
                     f"{design['step_s']:.3f} s a step; {others}")
    return "; ".join(parts) + " (measured)"


if __name__ == "__main__":
    main()
