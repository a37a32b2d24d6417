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
import os

import numpy as np

from benchmarks.harness import markdown_table, time_interleaved, write_json
from diffcam.reconstruct import admm_tv, richardson_lucy

NUM_ITER = 150
SKIMAGE = "scikit-image richardson_lucy (clip=False)"


def _problem(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    psf = (rng.random((n, n)) ** 8).astype(np.float32)
    psf /= psf.sum()
    image = rng.random((n, n)).astype(np.float32) + 0.1
    return image, psf


def _candidates(image, psf):
    """name -> zero-argument callable returning the estimate."""
    cands = {
        "diffcam RL same, skimage convention":
            lambda: richardson_lucy(image, psf, NUM_ITER, convention="skimage").image,
        "diffcam RL same (adjoint)": lambda: richardson_lucy(image, psf, NUM_ITER).image,
        "diffcam RL circular":
            lambda: richardson_lucy(image, psf, NUM_ITER, boundary="circular").image,
        "diffcam RL crop model":
            lambda: richardson_lucy(image, psf, NUM_ITER, boundary="crop").image,
    }
    try:
        from skimage.restoration import richardson_lucy as skimage_rl
        cands[SKIMAGE] = lambda: skimage_rl(image, psf, NUM_ITER, clip=False)
    except ImportError:
        print("note: scikit-image missing; its row is skipped")
    return cands


def run(sizes=(512, 1024, 2048), repeats: int = 5, skimage_max_seconds: float = 600.0
        ) -> list[dict]:
    """Time every candidate at every size (interleaved, :mod:`benchmarks.harness`); a
    candidate is repeated only while its total stays under ``skimage_max_seconds``."""
    rows = []
    for n in sizes:
        image, psf = _problem(n)
        load_before = os.getloadavg()
        stats = time_interleaved(_candidates(image, psf), repeats, skimage_max_seconds)
        load = f"{load_before[0]:.1f}→{os.getloadavg()[0]:.1f}"
        ref = stats.get(SKIMAGE)
        for name, st in stats.items():
            row = {"workload": f"RL {NUM_ITER} it", "size": n, "candidate": name,
                   "median_s": st["median_s"], "repeats": st["repeats"],
                   "compile_s": st["first_s"] - st["median_s"], "load": load}
            if ref is not None:
                row["speedup_vs_skimage"] = ref["median_s"] / st["median_s"]
                if "skimage convention" in name:
                    out, want = np.asarray(st["output"]), np.asarray(ref["output"])
                    row["rel_l2_vs_skimage"] = float(np.linalg.norm(out - want)
                                                     / np.linalg.norm(want))
            rows.append(row)
            print(f"  {n}² {name}: {st['median_s']:.3f} s x{st['repeats']}", flush=True)
    rows.append(_admm_tutorial(repeats))
    return rows


def _admm_tutorial(repeats: int) -> dict:
    """ADMM-TV, 5 iterations, on the L2-normalised tutorial pair (300x400)."""
    from diffcam.data import load_tutorial_pair
    from diffcam.io import normalise_l2
    pair = load_tutorial_pair()
    psf, image = normalise_l2(pair.psf), normalise_l2(pair.image)
    load_before = os.getloadavg()
    st = time_interleaved({"admm": lambda: admm_tv(image, psf, 5).image}, max(repeats, 5))
    return {"workload": "ADMM-TV 5 it, tutorial pair", "size": "300x400",
            "candidate": "diffcam admm_tv (crop model, grid 640x810)",
            "median_s": st["admm"]["median_s"], "repeats": st["admm"]["repeats"],
            "compile_s": st["admm"]["first_s"] - st["admm"]["median_s"],
            "load": f"{load_before[0]:.1f}→{os.getloadavg()[0]:.1f}",
            "published_elsewhere": "LenslessPiCam ADMM 5 it: numpy 1.26 s, torch CPU 272 ms, "
                                   "DiffuserCam reference 6.81 s (i9-10900X)"}


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
    print(markdown_table(rows, ["workload", "size", "candidate", "median_s", "repeats",
                                "compile_s", "speedup_vs_skimage", "rel_l2_vs_skimage",
                                "load"]))
    print("wrote", write_json("deconvolve", rows))


if __name__ == "__main__":
    main()
