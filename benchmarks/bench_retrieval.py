"""Phase-retrieval workload: Gerchberg–Saxton iterations per second, and time to a phase
Pearson, on the paper's Fig. 3 problem (cameraman diffuser, f = 5 cm, 532 nm), complex64.

Side by side, interleaved, in one run:

- diffcam ``retrieve_projections(method="gs")`` (jitted ``lax.scan``, unitary FFTs in
  FFT order, projection u·(A/|u|));
- a textbook numpy GS (``fftshift``-ed FFTs, projection A·exp(j·angle(u)));
- a scipy.fft GS (``workers=2``, no shifts, normalising projection u·(A/|u|)).

Time to target: for GS, HIO and RAAR from one random start at N = 1024, the smallest
iteration count in a doubling ladder whose twin-resolved phase Pearson (docs/design.md, on
the central 300×300) reaches 0.789 (the paper's figure) and 0.99, times the measured
seconds per iteration. A flat estimate's Pearson is recorded as the metric's floor.

    python -m benchmarks.bench_retrieval [--sizes 512 1024 2048 4096] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os

import jax
import numpy as np
import scipy.fft

from benchmarks.harness import markdown_table, time_interleaved, write_json
from diffcam.core.grid import crop_to
from diffcam.evaluate.metrics import phase_scores
from diffcam.calibrate import paper_simulation, retrieve_projections

LADDER = (25, 50, 100, 200, 400, 800, 1600, 3200)
TARGETS = (0.789, 0.99)


def numpy_textbook_gs(near_amp, far_amp, phase0, iterations):
    """GS as textbooks write it: centred FFTs, A·exp(j·angle(u)) projections."""
    sh, ish = np.fft.fftshift, np.fft.ifftshift
    u = (near_amp * np.exp(1j * phase0)).astype(np.complex64)
    for _ in range(iterations):
        U = sh(np.fft.fft2(ish(u)))
        U = far_amp * np.exp(1j * np.angle(U))
        u = sh(np.fft.ifft2(ish(U)))
        u = (near_amp * np.exp(1j * np.angle(u))).astype(np.complex64)
    return np.angle(u)


def scipy_gs(near_amp, far_amp, phase0, iterations):
    """GS with scipy.fft (2 workers), arrays kept in FFT order, u·(A/|u|) projections."""
    near = np.fft.ifftshift(near_amp).astype(np.float32)
    far = np.fft.ifftshift(far_amp).astype(np.float32)
    u = (near * np.exp(1j * np.fft.ifftshift(phase0))).astype(np.complex64)
    for _ in range(iterations):
        U = scipy.fft.fft2(u, workers=2, norm="ortho")
        m = np.abs(U)
        U *= np.divide(far, m, out=np.zeros_like(m), where=m > 0)
        u = scipy.fft.ifft2(U, workers=2, norm="ortho")
        m = np.abs(u)
        u *= np.divide(near, m, out=np.zeros_like(m), where=m > 0)
    return np.angle(np.fft.fftshift(u))


def throughput(n, iterations, repeats):
    sim = paper_simulation(n)
    near_amp = np.sqrt(np.asarray(sim.near, np.float32))
    far_amp = np.sqrt(np.asarray(sim.far, np.float32))
    far_amp *= np.linalg.norm(near_amp) / np.linalg.norm(far_amp)
    phase0 = np.zeros((n, n), np.float32)
    cands = {
        "diffcam": lambda: retrieve_projections(sim.near, sim.far, sim.geometry, method="gs",
                                                iterations=iterations, init="flat").phase,
        "numpy textbook": lambda: numpy_textbook_gs(near_amp, far_amp, phase0, iterations),
        "scipy.fft workers=2": lambda: scipy_gs(near_amp, far_amp, phase0, iterations),
    }
    stats = time_interleaved(cands, repeats=repeats)
    row = {"N": n, "iterations": iterations}
    for name, s in stats.items():
        row[f"{name} it/s"] = iterations / s["median_s"]
        row[f"{name} repeats"] = s["repeats"]
    row["vs numpy"] = row["diffcam it/s"] / row["numpy textbook it/s"]
    row["vs scipy"] = row["diffcam it/s"] / row["scipy.fft workers=2 it/s"]
    return row


def time_to_target(n=1024, seed=2, repeats=3):
    """Iterations and seconds for each projection method to reach each target Pearson."""
    sim = paper_simulation(n)

    def score(phase):
        return float(phase_scores(crop_to(phase, sim.truth.shape), sim.truth,
                                  mask=sim.mask)["twin_resolved"])

    rows = [{"solver": "flat estimate (metric floor)", "pearson": score(jax.numpy.zeros((n, n)))}]
    for method in ("gs", "hio", "raar"):
        run = lambda its: retrieve_projections(sim.near, sim.far, sim.geometry,  # noqa: E731
                                               method=method, iterations=its,
                                               key=jax.random.key(seed))
        per_it = time_interleaved({method: lambda: run(100).phase}, repeats)[method][
            "median_s"] / 100
        row = {"solver": method, "s/iteration": per_it}
        reached = {}
        for its in LADDER:
            p = score(run(its).phase)
            for target in TARGETS:
                if p >= target and target not in reached:
                    reached[target] = its
            if len(reached) == len(TARGETS):
                break
        row["pearson"] = p
        for target in TARGETS:
            its = reached.get(target)
            row[f"iterations to {target}"] = its
            row[f"seconds to {target}"] = None if its is None else its * per_it
        rows.append(row)
    return rows


def run(sizes=(512, 1024, 2048, 4096), iterations=20, repeats=5) -> list[dict]:
    """GS throughput rows (one per N) followed by time-to-target rows (N = 1024)."""
    rows = []
    for n in sizes:
        reps = repeats if n <= 2048 else max(2, repeats // 2)  # 4096²: as affordable
        rows.append(throughput(n, iterations, reps))
        print(rows[-1], flush=True)
    return rows + time_to_target()


def main(argv=None):
    p = argparse.ArgumentParser(description="diffcam phase-retrieval benchmark")
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048, 4096])
    p.add_argument("--iterations", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    load_before = os.getloadavg()
    rows = run(args.sizes, args.iterations, args.repeats)
    load_after = os.getloadavg()
    speed = [r for r in rows if "N" in r]
    target = [r for r in rows if "solver" in r]
    print(markdown_table(speed, ["N", "iterations", "diffcam it/s", "numpy textbook it/s",
                                 "scipy.fft workers=2 it/s", "vs numpy", "vs scipy",
                                 "diffcam repeats"]))
    print()
    print(markdown_table(target, ["solver", "pearson", "s/iteration", "iterations to 0.789",
                                  "seconds to 0.789", "iterations to 0.99",
                                  "seconds to 0.99"]))
    print(f"\nload average before {load_before}, after {load_after}")
    print("wrote", write_json("retrieval", rows, {"loadavg_before": load_before,
                                                  "loadavg_after": load_after}))


if __name__ == "__main__":
    main()
