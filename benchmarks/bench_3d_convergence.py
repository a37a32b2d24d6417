"""Benchmark: convergence per second of the 3-D ADMM-TV solve on the shipped capture —
over-relaxation and the penalties' starting values, iteration by iteration.

    python -m benchmarks.bench_3d_convergence [--iterations 20 40 60 100]
        [--settings default plain]

The inputs are the README command's (``diffcam data usaf3d``, then what ``diffcam
reconstruct --3d`` reads and the PSF envelope it estimates); each setting is
:data:`diffcam.reconstruct.admm.VOLUME` with the fields of :data:`SETTINGS` replaced,
run for each iteration count from a cold start (one process, compiled once per count).
Per row: the returned volume's residual ``||A w - b|| / ||b||`` and objective (on the
raw scaled to unit L2 norm), the split gap, the solve's seconds (compilation included;
the machine may be shared: compare rows of one run), and the ridge
(:func:`diffcam.evaluate.volume.ridge_measures`) on three boxes: the side-by-side
table's (``benchmarks/bench_3d.py``), DiffuserCam's settings without the envelope, and
each volume's own :func:`~diffcam.evaluate.volume.target_box`.

Results: ``benchmarks/results/bench_3d_convergence.json``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.harness import markdown_table, write_json

BOXES = {"side": (97, 186, 127, 208), "diffcam": (100, 181, 127, 214), "own": None}
"""The boxes (rows and columns, ends excluded) the ridge is judged on; ``None``: each
volume's own target box."""

SETTINGS = {
    "default": {},
    "plain": {"mu1": 1e-3, "mu2": 1e-3, "mu3": 1e-3, "relaxation": 1.0},
    "relaxed": {"mu1": 1e-3, "mu2": 1e-3, "mu3": 1e-3, "relaxation": 1.7},
    "warm penalties": {"relaxation": 1.0},
}
"""Replacements of ``VOLUME``'s fields: ``default`` is ``VOLUME`` itself; ``plain``
starts residual balancing at 1e-3 without relaxation; ``relaxed`` adds α = 1.7;
``warm penalties`` keeps ``VOLUME``'s starting penalties without relaxation."""


def readme_inputs() -> tuple[np.ndarray, np.ndarray]:
    """The raw and the enveloped PSF stack as ``diffcam reconstruct --3d`` solves them."""
    from diffcam.apps.cli import build_parser
    from diffcam.apps.reconstruct_inputs import match_envelope, read_inputs

    with tempfile.TemporaryDirectory() as work:
        subprocess.run([sys.executable, "-m", "diffcam", "data", "usaf3d", "-o", "captures"],
                       cwd=work, check=True, capture_output=True)
        args = build_parser().parse_args(
            ["reconstruct", f"{work}/captures/usaf_raw.png", "--psf", f"{work}/captures/psfs",
             "--3d", "-o", f"{work}/out.tif"])
        raw, source = read_inputs(args, lambda _: None)
    return raw, match_envelope(raw, source.psfs, "auto", lambda _: None)[0]


def solve(raw, psfs, iterations: int, replace: dict) -> dict:
    """One cold solve with ``VOLUME`` and ``replace``: convergence and ridge measures."""
    import jax

    from diffcam.core.grid import crop_to
    from diffcam.evaluate.volume import Box, ridge_measures
    from diffcam.reconstruct import AdmmOptions, admm_tv_3d
    from diffcam.reconstruct.admm import VOLUME

    t = time.perf_counter()
    rec = admm_tv_3d(raw / np.linalg.norm(raw), psfs, iterations,
                     AdmmOptions.of(VOLUME, **replace), progress=False)
    jax.block_until_ready(rec.image)
    row = {"iterations": iterations, "seconds": time.perf_counter() - t,
           "residual": float(rec.final_residual), "objective": float(rec.final_objective),
           "split_gap": float(rec.split_gap)}
    volume = np.asarray(crop_to(rec.image, raw.shape))
    for name, box in BOXES.items():
        ridge = ridge_measures(volume, None if box is None else Box(*box)).summary()
        row.update({f"{name}_{k}": v for k, v in ridge.items()})
    return row


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, nargs="+", default=[20, 40, 60, 100])
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS),
                        default=list(SETTINGS))
    args = parser.parse_args(argv)
    raw, psfs = readme_inputs()
    rows = []
    for name in args.settings:
        for n in args.iterations:
            rows.append({"setting": name, **solve(raw, psfs, n, SETTINGS[name])})
            print(rows[-1], flush=True)
    print(markdown_table(rows, ["setting", "iterations", "seconds", "residual", "objective",
                                "split_gap", "side_slope", "side_rms", "side_axial_width",
                                "side_outside", "diffcam_rms", "diffcam_outside", "own_rms",
                                "own_outside"]))
    from diffcam.reconstruct.admm import VOLUME

    path = write_json("bench_3d_convergence", rows,
                      {"settings": {k: SETTINGS[k] for k in args.settings},
                       "boxes": BOXES, "volume_options": str(VOLUME),
                       "shared_machine_load": os.getloadavg()})
    print("wrote", path)


if __name__ == "__main__":
    main()
