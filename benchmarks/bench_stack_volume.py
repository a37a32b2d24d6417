"""Benchmark: 3-D reconstruction of the shipped raw capture with a PSF stack predicted
from two measured planes, against the reconstruction with the measured stack.

Usage: python -m benchmarks.bench_stack_volume [--planes 5,27] [--iterations 200]
       [--downsample 2] [--solver admm|rl] [--figure PATH]

The raw capture (``example_raw.png``, a tilted USAF target, bias subtracted, in counts)
is reconstructed three times with :func:`diffcam.reconstruct.admm_tv_3d` (3-D TV, its
defaults: μ1 = μ2 = μ3 = 1e-3, τ = 6e-4; ``--solver rl``: :func:`richardson_lucy_3d`),
each time
with a 44-plane stack prepared the same way (:func:`diffcam.calibrate.prepare_planes`:
border-median dark level, unit mean per plane; then box-downsampled and clipped at 0):

- ``measured``: the measured stack — the reference;
- ``model``: predicted by :func:`diffcam.calibrate.fit_stack` from the two ``--planes``
  only (:meth:`StackFit.predict`);
- ``baseline``: the scaling baseline from the same two planes (nearest plane magnified).

Volumes are cropped to the sensor's frame (the solvers reconstruct a padded grid).
Scores against the measured-stack volume: Pearson over the whole volume; per depth
plane, the Pearson of that plane's slice; and the depth of best focus per region — the
target is tilted across the columns, so for each column holding the target (light > 30 %
of the brightest column's in the measured volume) the plane holding most of its light;
reported as the mean absolute difference in planes, the share within ± 2 planes and the
rank correlation with the measured volume's depths. A figure shows the three max projections and depth maps. Results go to
``benchmarks/results/stack_volume.json``; the figure to ``--figure`` (default
``benchmarks/results/stack_volume.png``).
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np

from benchmarks.harness import markdown_table, write_json
from diffcam.calibrate import StackFitWarning, fit_stack, prepare_planes
from diffcam.core.grid import crop_to
from diffcam.data import load_psf_stack_3d, load_raw_3d
from diffcam.evaluate.metrics import pearson
from diffcam.evaluate.registration import scaling_baseline
from diffcam.io import downsample
from diffcam.reconstruct import admm_tv_3d, richardson_lucy_3d

def column_depths(volume: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Depth of best focus of each of ``columns``: the plane holding most of the
    column's light (the target is tilted across the columns)."""
    return volume.sum(axis=1)[:, columns].argmax(axis=0)


def target_columns(volume: np.ndarray) -> np.ndarray:
    """The columns holding the target: light summed over depth and rows > 30 % of the
    brightest column's."""
    energy = volume.sum(axis=(0, 1))
    return np.where(energy > 0.3 * energy.max())[0]


def compare_volumes(volume: np.ndarray, reference: np.ndarray) -> dict:
    """Scores of ``volume`` against the ``reference`` volume (both (nz, h, w))."""
    from scipy.stats import spearmanr

    cols = target_columns(reference)
    depth, ref_depth = column_depths(volume, cols), column_depths(reference, cols)
    w = volume.shape[-1]
    per_plane = np.asarray(pearson(volume, reference))
    return {"volume_pearson": float(pearson(volume.reshape(-1, w), reference.reshape(-1, w))),
            "plane_pearson_mean": float(np.nanmean(per_plane)),
            "depth_error_planes": float(np.mean(np.abs(depth - ref_depth))),
            "same_depth_pm2": float(np.mean(np.abs(depth - ref_depth) <= 2)),
            "depth_spearman": float(spearmanr(depth, ref_depth)[0]),
            "columns": int(cols.size), "depths": depth.tolist(),
            "reference_depths": ref_depth.tolist(), "per_plane": per_plane.tolist()}


def stacks(raw_stack: np.ndarray, planes: list[int]) -> tuple[dict, object]:
    """The measured, model-predicted and baseline stacks (prepared, full size)."""
    measured = prepare_planes(raw_stack)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", StackFitWarning)
        fit = fit_stack(raw_stack, planes, progress=False, saturation=None,
                        time_budget=math.inf)
    n = raw_stack.shape[0]
    base = scaling_baseline({t: measured[t] for t in planes}, n,
                            registration=fit.registration)
    return {"measured": measured, "model": fit.predict(n), "baseline": base}, fit


def figure(volumes: dict, path) -> None:
    """Max projections (top) and depth maps (bottom) of every volume."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffcam.apps.cli import save_figure

    names = list(volumes)
    fig, axes = plt.subplots(2, len(names), figsize=(3.6 * len(names), 6.2),
                             layout="constrained")
    vmax = max(float(v.max(axis=0).max()) for v in volumes.values())
    for k, name in enumerate(names):
        v = volumes[name]
        mip = v.max(axis=0)
        im = axes[0, k].imshow(mip, cmap="gray", vmin=0, vmax=vmax)
        axes[0, k].set_title(f"{name}: max projection")
        depth = np.where(mip > 0.1 * mip.max(), np.argmax(v, axis=0), np.nan)
        dm = axes[1, k].imshow(depth, cmap="viridis", vmin=0, vmax=v.shape[0] - 1)
        axes[1, k].set_title(f"{name}: depth of the maximum")
        for ax in axes[:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.colorbar(im, ax=axes[0, :], shrink=0.8, label="intensity (a.u.)")
    fig.colorbar(dm, ax=axes[1, :], shrink=0.8, label="plane (0 = nearest)")
    save_figure(fig, path)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--planes", default="5,27", help="the two measured planes used")
    parser.add_argument("--iterations", type=int, default=40, help="solver iterations")
    parser.add_argument("--solver", choices=["admm", "rl"], default="admm")
    parser.add_argument("--downsample", type=int, default=2, help="box-average factor")
    parser.add_argument("--figure", default="benchmarks/results/stack_volume.png")
    args = parser.parse_args(argv)
    planes = [int(p) for p in args.planes.split(",")]
    t0 = time.perf_counter()
    psfs, fit = stacks(load_psf_stack_3d(), planes)
    fit_s = time.perf_counter() - t0
    raw = downsample(load_raw_3d(), args.downsample)
    volumes, seconds = {}, {}
    for name, stack in psfs.items():
        t0 = time.perf_counter()
        psf = np.clip(downsample(stack.astype(np.float32), args.downsample), 0, None)
        rec = admm_tv_3d(raw, psf, args.iterations) if args.solver == "admm" \
            else richardson_lucy_3d(raw, psf, args.iterations)
        volumes[name] = np.asarray(crop_to(rec.image, raw.shape), np.float64)
        seconds[name] = time.perf_counter() - t0
    rows = [{"stack": name, **compare_volumes(volumes[name], volumes["measured"]),
             "seconds": seconds[name]} for name in ("model", "baseline")]
    figure(volumes, args.figure)
    meta = {"planes": planes, "iterations": args.iterations, "downsample": args.downsample,
            "solver": args.solver,
            "fit_seconds": fit_s, "fit": fit.summary(), "figure": args.figure}
    cols = ["stack", "volume_pearson", "plane_pearson_mean", "depth_error_planes",
            "same_depth_pm2", "depth_spearman", "columns", "seconds"]
    print(markdown_table([{k: (f"{v:.4f}" if isinstance(v, float) else v)
                           for k, v in r.items()} for r in rows], cols))
    print("wrote", write_json("stack_volume", rows, meta), "and", args.figure)


if __name__ == "__main__":
    main()
