"""Benchmark: Richardson–Lucy (150 iterations, float32, PSF the size of the image) in
diffcam against scikit-image, and ADMM-TV (5 iterations) on the DiffuserCam tutorial pair.

Usage: python benchmarks/bench_deconvolve.py [--sizes 512 1024 2048] [--repeats 5] [--quick]

Candidates run interleaved (repeat 1 of every candidate, then repeat 2, ...), each timed
with its result on the host; the table gives the median run time, and for diffcam the
compile time separately (first call minus the median). The machine load
(``os.getloadavg()``) is recorded before and after each size. scikit-image is run fewer
times where it takes minutes (``--skimage-max-seconds``). Results go to
``benchmarks/results/deconvolve.json`` and a Markdown table is printed.

``run(sizes, repeats)`` is the entry point for ``benchmarks/run.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

from diffcam.reconstruct import admm_tv, richardson_lucy

NUM_ITER = 150
RESULTS = Path(__file__).resolve().parent / "results" / "deconvolve.json"


def _problem(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    psf = (rng.random((n, n)) ** 8).astype(np.float32)
    psf /= psf.sum()
    image = rng.random((n, n)).astype(np.float32) + 0.1
    return image, psf


def _candidates(image, psf):
    """name -> (callable returning a NumPy array, is_jax)."""
    cands = {
        "diffcam RL same, skimage convention": (
            lambda: np.asarray(richardson_lucy(image, psf, NUM_ITER, convention="skimage").image),
            True),
        "diffcam RL same (adjoint)": (
            lambda: np.asarray(richardson_lucy(image, psf, NUM_ITER).image), True),
        "diffcam RL circular": (
            lambda: np.asarray(richardson_lucy(image, psf, NUM_ITER, boundary="circular").image),
            True),
        "diffcam RL crop model": (
            lambda: np.asarray(richardson_lucy(image, psf, NUM_ITER, boundary="crop").image),
            True),
    }
    try:
        from skimage.restoration import richardson_lucy as skimage_rl
        cands["scikit-image richardson_lucy (clip=False)"] = (
            lambda: skimage_rl(image, psf, NUM_ITER, clip=False), False)
    except ImportError:
        print("note: scikit-image missing; its row is skipped")
    return cands


def _time(fn):
    start = time.perf_counter()
    out = fn()
    return time.perf_counter() - start, out


def run(sizes=(512, 1024, 2048), repeats: int = 5, skimage_max_seconds: float = 600.0
        ) -> list[dict]:
    """Time every candidate at every size; return one dict per (size, candidate)."""
    rows = []
    for n in sizes:
        image, psf = _problem(n)
        cands = _candidates(image, psf)
        load_before = os.getloadavg()
        first, times, outputs = {}, {k: [] for k in cands}, {}
        for name, (fn, is_jax) in cands.items():     # warm-up = compile for JAX
            if is_jax:
                first[name], outputs[name] = _time(fn)
        budget = {k: repeats for k in cands}
        for r in range(repeats):
            for name, (fn, is_jax) in cands.items():
                if r >= budget[name]:
                    continue
                t, out = _time(fn)
                times[name].append(t)
                outputs.setdefault(name, out)
                if not is_jax and t * repeats > skimage_max_seconds:
                    budget[name] = max(1, int(skimage_max_seconds // t))
        load_after = os.getloadavg()
        ref = outputs.get("scikit-image richardson_lucy (clip=False)")
        sk_median = statistics.median(times[next(k for k in cands if "scikit" in k)]) \
            if ref is not None else None
        for name in cands:
            median = statistics.median(times[name])
            row = {"workload": f"RL {NUM_ITER} it", "size": n, "candidate": name,
                   "median_s": median, "repeats": len(times[name]),
                   "compile_s": (first[name] - median) if name in first else None,
                   "load_before": load_before, "load_after": load_after}
            if ref is not None:
                row["speedup_vs_skimage"] = sk_median / median
                if "skimage convention" in name or "scikit" in name:
                    out = outputs[name]
                    row["rel_l2_vs_skimage"] = float(np.linalg.norm(out - ref)
                                                     / np.linalg.norm(ref))
            rows.append(row)
            print(f"  {n}² {name}: {median:.3f} s x{len(times[name])}", flush=True)
    rows.append(_admm_tutorial(repeats))
    return rows


def _admm_tutorial(repeats: int) -> dict:
    """ADMM-TV, 5 iterations, on the L2-normalised tutorial pair (300x400)."""
    from diffcam.data import load_tutorial_pair
    from diffcam.io import normalise_l2
    pair = load_tutorial_pair()
    psf, image = normalise_l2(pair.psf), normalise_l2(pair.image)
    fn = lambda: np.asarray(admm_tv(image, psf, 5).image)  # noqa: E731
    first, _ = _time(fn)
    times = [_time(fn)[0] for _ in range(max(repeats, 5))]
    median = statistics.median(times)
    return {"workload": "ADMM-TV 5 it, tutorial pair", "size": "300x400",
            "candidate": "diffcam admm_tv (crop model, grid 640x810)", "median_s": median,
            "repeats": len(times), "compile_s": first - median,
            "load_before": os.getloadavg(), "load_after": os.getloadavg(),
            "published_elsewhere": "LenslessPiCam numpy 1.26 s, torch CPU 4.32 s, "
                                   "DiffuserCam reference 6.81 s (i9-10900X)"}


def markdown(rows: list[dict]) -> str:
    lines = ["| workload | size | candidate | median | repeats | compile | vs skimage | "
             "rel. L2 vs skimage | load (1 min) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        speed = f"{r['speedup_vs_skimage']:.1f}x" if "speedup_vs_skimage" in r else ""
        diff = f"{r['rel_l2_vs_skimage']:.1e}" if "rel_l2_vs_skimage" in r else ""
        comp = f"{r['compile_s']:.2f} s" if r.get("compile_s") is not None else ""
        lines.append(f"| {r['workload']} | {r['size']} | {r['candidate']} | "
                     f"{r['median_s']:.3f} s | {r['repeats']} | {comp} | {speed} | {diff} | "
                     f"{r['load_before'][0]:.1f}→{r['load_after'][0]:.1f} |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="512² only, 2 repeats")
    parser.add_argument("--skimage-max-seconds", type=float, default=600.0,
                        help="time budget per size for scikit-image's repeats")
    args = parser.parse_args(argv)
    sizes, repeats = ([512], 2) if args.quick else (args.sizes, args.repeats)
    print("note: no peer RL implementation (LenslessPiCam, waveprop) is installed; "
          "scikit-image is the reference.")
    rows = run(sizes, repeats, args.skimage_max_seconds)
    table = markdown(rows)
    print(table)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps({
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                    "jax": jax.__version__, "backend": jax.default_backend()},
        "rows": rows}, indent=2))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
