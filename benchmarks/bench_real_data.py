"""The README's "Real data" commands, run as written: wall time, peak memory, and how good
the reconstructions are, against the command line's former defaults.

    python -m benchmarks.bench_real_data [--downsample F] [--figure docs/real_data.png]

Each command of the README's ``sh`` block under "## Real data" runs in a fresh process
(:func:`benchmarks.harness.run_probed`: peak RSS of the command alone) in a temporary
folder; ``--downsample F`` adds ``--downsample F`` to every ``reconstruct`` (the tests
run them so). Every ``reconstruct`` runs again with the former defaults (Richardson–Lucy,
150 iterations: :data:`BEFORE`).

The measures, on data no diffcam model made:

* the hand has no ground truth; it is scored by Pearson correlation with an independent
  reconstruction: plain non-negative FISTA, 200 iterations, on a 2×-padded linear
  convolution (:func:`fista_reference`, the check of the data's provenance notes);
* the tilted USAF target is scored by how steadily its in-focus depth moves across it
  (Spearman correlation of column and in-focus plane, :func:`depth_ramp`; the target is
  tilted, so a good volume gives a monotone ramp);
* the volume from the fitted model is scored by its Pearson correlation with the volume
  from the measured stack.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import markdown_table, run_probed, write_json

ROOT = Path(__file__).resolve().parents[1]
BEFORE = ["--method", "rl", "--iterations", "150"]
"""The command line's former defaults (Richardson–Lucy, 150 iterations) as options."""


def readme_commands(readme: Path = ROOT / "README.md") -> list[list[str]]:
    """The ``diffcam`` commands of the first ``sh`` block under "## Real data", each as
    argv (comments and the shell set-up line dropped)."""
    text = readme.read_text()
    section = text.split("## Real data", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, flags=re.S).group(1)
    lines = [shlex.split(line, comments=True) for line in block.splitlines()]
    return [argv for argv in lines if argv and argv[0] == "diffcam"]


def fista_reference(raw: np.ndarray, psf: np.ndarray, iterations: int = 200) -> np.ndarray:
    """Non-negative FISTA (Beck & Teboulle 2009) for ``raw = crop(psf * x)`` with a
    2×-padded linear convolution, step ``1.8 / max|H|²``; raw and PSF scaled to unit L2
    norm. Plain NumPy, written apart from diffcam's solvers: a reference, not a rival.
    Returns the estimate on the raw's frame."""
    ny, nx = raw.shape
    shape = (2 * ny, 2 * nx)
    window = (slice(ny // 2, ny // 2 + ny), slice(nx // 2, nx // 2 + nx))
    h = np.zeros(shape)
    py, px = psf.shape
    h[ny - py // 2:ny - py // 2 + py, nx - px // 2:nx - px // 2 + px] = psf / np.linalg.norm(psf)
    otf = np.fft.rfft2(np.fft.ifftshift(h))
    b = raw / np.linalg.norm(raw)

    def forward(x):
        return np.fft.irfft2(np.fft.rfft2(x) * otf, s=shape)[window]

    def adjoint(r):
        z = np.zeros(shape)
        z[window] = r
        return np.fft.irfft2(np.fft.rfft2(z) * np.conj(otf), s=shape)

    step = 1.8 / np.max(np.abs(otf)) ** 2
    x = y = np.zeros(shape)
    t = 1.0
    for _ in range(iterations):
        x_new = np.maximum(y - step * adjoint(forward(y) - b), 0)
        t_new = (1 + np.sqrt(1 + 4 * t * t)) / 2
        y = x_new + (t - 1) / t_new * (x_new - x)
        x, t = x_new, t_new
    return x[window]


def depth_ramp(volume: np.ndarray) -> float:
    """Spearman correlation between column and in-focus plane across the target: each
    column's plane is the one holding most of the column's light; columns with less than
    30 % of the brightest column's light are not target."""
    from scipy.stats import spearmanr

    columns = np.asarray(volume).sum(axis=1)            # (nz, nx)
    energy = columns.sum(axis=0)
    target = np.where(energy > 0.3 * energy.max())[0]
    return float(spearmanr(target, columns[:, target].argmax(axis=0))[0])


def pearson(a, b) -> float:
    return float(np.corrcoef(np.ravel(a), np.ravel(b))[0, 1])


def _read(path: Path) -> np.ndarray:
    from diffcam.io import read_image
    import tifffile

    if path.suffix == ".tif":
        return tifffile.imread(path).astype(np.float64)
    return read_image(path).image.astype(np.float64)


def run(downsample: int = 1, fit_budget: float | None = None, work: Path | None = None):
    """Run the README's commands (and the ``reconstruct`` ones again with :data:`BEFORE`)
    in ``work`` (a new temporary folder by default). Returns ``(rows, work)``."""
    work = Path(work or tempfile.mkdtemp(prefix="diffcam-real-"))
    rows = []
    for argv in readme_commands():
        assert argv[0] == "diffcam", argv
        args = argv[1:]
        if args[0] == "reconstruct" and downsample > 1:
            args = args + ["--downsample", str(downsample)]
        if args[0] == "fit" and fit_budget:
            args = args + ["--time-budget", str(fit_budget)]
        variants = [("after", args)]
        if args[0] == "reconstruct" and "model.npz" not in args:
            out = args[args.index("-o") + 1]
            stem, suffix = os.path.splitext(out)
            before = args[:args.index("-o") + 1] + [f"{stem}_before{suffix}"] + \
                args[args.index("-o") + 2:] + BEFORE
            variants.append(("before", before))
        for label, a in variants:
            record = run_probed([sys.executable, "-m", "diffcam", *a], cwd=work)
            if record["rc"]:
                raise RuntimeError(f"`diffcam {shlex.join(a)}` failed: {record['stderr']}")
            rows.append({"command": "diffcam " + shlex.join(argv[1:]), "defaults": label,
                         "wall_s": record["wall_s"],
                         "peak_rss_mb": record["peak_bytes"] / 2**20})
    return rows, work


def scores(work: Path, downsample: int = 1) -> dict:
    """The quality measures of the module docstring, from the files in ``work``."""
    from diffcam.io import border_dark_level, downsample as box

    raw = _read(work / "captures/hand_raw.tif")
    psf = _read(work / "captures/hand_psf.tif")
    psf = np.clip(psf - border_dark_level(psf), 0, None)
    if downsample > 1:
        raw, psf = box(raw, downsample), box(psf, downsample)
    reference = fista_reference(raw, psf)
    out = {f"hand_{k}": pearson(_read(work / f"hand{s}.png"), reference)
           for k, s in (("after", ""), ("before", "_before"))}
    for k, s in (("after", ""), ("before", "_before")):
        out[f"usaf_ramp_{k}"] = depth_ramp(_read(work / f"usaf{s}.tif"))
    out["usaf_ramp_model"] = depth_ramp(_read(work / "usaf_model.tif"))
    out["usaf_model_volume_pearson"] = pearson(_read(work / "usaf_model.tif"),
                                               _read(work / "usaf.tif"))
    return out


def figure(work: Path, path: Path) -> None:
    """Before/after panels: the hand, the 2-D USAF plane, the 3-D max projections, the
    depth map, and the model's max projection."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffcam.apps.cli import save_figure

    panels = [("hand_before.png", "hand: RL 150 (former default)"),
              ("hand.png", "hand: ADMM-TV 100 (default)"),
              ("usaf_2d_before.png", "USAF, one plane: RL 150"),
              ("usaf_2d.png", "USAF, one plane: ADMM-TV"),
              ("usaf_before_max.png", "USAF volume, max projection: RL 150"),
              ("usaf_max.png", "USAF volume, max projection: ADMM-TV"),
              ("usaf_depth.png", "USAF volume: depth map"),
              ("usaf_model_max.png", "volume from the stack model (2 planes)")]
    fig, axes = plt.subplots(2, 4, figsize=(16, 6.6), layout="constrained")
    for ax, (name, title) in zip(axes.flat, panels):
        image = _read(work / name) if name != "usaf_depth.png" else plt.imread(work / name)
        ax.imshow(image, cmap="gray", vmax=None if image.ndim == 3 else
                  np.percentile(image, 99.8))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle("Shipped DiffuserCam captures, the README's commands (pixels of the "
                 "sensor frame; no scale is published for these captures)", fontsize=10)
    save_figure(fig, path)


COLUMNS = ["command", "defaults", "wall_s", "peak_rss_mb"]


def defaults_sweep(downsample: int = 1) -> list[dict]:
    """How the command line's 2-D defaults were chosen: each solver and iteration count on
    the shipped hand (:func:`diffcam.data.load_tutorial_pair`, dark level subtracted),
    scored by Pearson correlation with :func:`fista_reference` on the sensor frame, with
    the data misfit and the wall time (compilation included)."""
    from diffcam.core.grid import crop_to
    from diffcam.data import load_tutorial_pair
    from diffcam.reconstruct import admm_tv, richardson_lucy, wiener

    pair = load_tutorial_pair(downsample_by=downsample)
    raw, psf = pair.image.astype(np.float64), pair.psf.astype(np.float64)
    reference = fista_reference(raw, psf)
    unit = (raw / np.linalg.norm(raw), psf / np.linalg.norm(psf))
    candidates = [("rl, same", n, lambda n: richardson_lucy(raw, psf, n)) for n in (150, 1000)]
    candidates += [("rl, crop", n, lambda n: richardson_lucy(raw, psf, n, boundary="crop"))
                   for n in (150, 1000)]
    candidates += [("admm", n, lambda n: admm_tv(*unit, n)) for n in (30, 100, 300)]
    candidates += [("wiener, crop", 1, lambda n: wiener(raw, psf, 1e-3, boundary="crop"))]
    rows = []
    for method, n, solve in candidates:
        t = time.perf_counter()
        rec = solve(n)
        image = np.asarray(crop_to(rec.image, raw.shape))
        rows.append({"method": method, "iterations": n, "shape": f"{raw.shape[0]}×{raw.shape[1]}",
                     "pearson_vs_fista": pearson(image, reference),
                     "misfit": float(np.nanmin(rec.residual)),
                     "seconds": time.perf_counter() - t})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--downsample", type=int, default=1, help="added to every reconstruct")
    p.add_argument("--figure", type=Path, help="write the before/after figure here")
    p.add_argument("--defaults", action="store_true",
                   help="only the solver/iteration sweep on the hand that chose the defaults")
    args = p.parse_args(argv)
    t = time.perf_counter()
    if args.defaults:
        rows = defaults_sweep(args.downsample)
        print(markdown_table(rows, list(rows[0])))
        print(f"wrote {write_json('real_data_defaults', rows)}")
        return
    rows, work = run(args.downsample)
    measured = scores(work, args.downsample)
    print(markdown_table(rows, COLUMNS))
    print(markdown_table([{"measure": k, "value": v} for k, v in measured.items()],
                         ["measure", "value"]))
    print(f"- {time.perf_counter() - t:.0f} s in all; files in {work}")
    if args.figure:
        figure(work, args.figure)
        print(f"wrote {args.figure}")
    print(f"wrote {write_json('real_data', rows, {'scores': measured, 'downsample': args.downsample})}")


if __name__ == "__main__":
    main()
