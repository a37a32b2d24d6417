"""The paper's Table 1 on real data: a PSF calibrated from scenes, then every solver
scored against the ground truth of captures the calibration did not see.

    python -m benchmarks.bench_scene_psf [--source DIR] [--downsample F] [--figure PNG]
    python -m benchmarks.bench_scene_psf --source DIR --folds im43 --pairs-used 6 \
        --solvers admm fista --name scene_psf_full_im43   # the published 270 × 480,
    python -m benchmarks.bench_scene_psf --combine benchmarks/results/scene_psf_full_*.json \
        --name scene_psf_full                            # one fold a run, then combined
    python -m benchmarks.bench_scene_psf --source DIR --folds im43 --via-cli RUNDIR \
        --name scene_psf_cli              # the same fold through `diffcam` commands

Data: the seven Lensless Learning pairs (a DiffuserCam colour capture of a picture on a
monitor, and a lensed photograph of it registered to the sensor), as shipped
(:func:`diffcam.data.load_scene_pairs`, 135 × 240), or the original float32 arrays
(270 × 480, BGR) from ``--source DIR`` (``DIR/diffuser/imNN.npy``,
``DIR/lensed/imNN.npy``) box-averaged by ``--downsample``.

Leave-one-out: for each pair, the PSF is fitted (:func:`fit_psf_from_scenes`, default
options) to the other six, and to the next one and three of them; with six, a
field-dependent PSF too (:func:`fit_field_psf_from_scenes`: kernels at the sensor's
corners, ``--grid``, interpolated across the field, same iterations and flip); the
held-out raw is

* predicted from its truth (Pearson per channel: must-show 2);
* reconstructed (dark offset from the calibration subtracted) with ADMM-TV (the command
  line's default: unit-L2 raw and PSF, 100 iterations, the DiffuserCam tutorial's
  penalties), Richardson–Lucy (1000 iterations, crop model), Wiener (1e-3, crop) and
  plain non-negative least squares (FISTA, 200 iterations: the floor);
* scored on the sensor frame against the truth, after the calibration's flip, with the
  estimate clipped to the truth's range [0, 1]: PSNR (data range 1, over all three
  channels), SSIM (scikit-image's, data range 1, mean of the channels) and Pearson
  (mean of the channels).

The PSF carries the gain between the truth's units and the sensor's, so every estimate
is in the truth's units: nothing is rescaled after the fact.

``--via-cli RUNDIR`` runs the same fold as a user would, with ``diffcam calibrate-psf``
(one PSF; ``--field``) on the other six pairs' files and ``diffcam reconstruct`` of the
held-out raw (the one PSF with ``--dark-raw`` set to its fitted offset; the field file
subtracts its own), ADMM-TV and FISTA at their command-line defaults, and scores the
``.npy`` results as above, beside this benchmark's rows for the fold from
``benchmarks/results/scene_psf_full.json``. A command whose output is already in
RUNDIR is not run again (its row says so).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import markdown_table, write_json

NAMES = ("im43", "im65", "im157", "im189", "im326", "im394", "im643")
SOLVERS = ("admm", "rl", "wiener", "fista")
FIELD_SOLVERS = ("admm", "fista")
PAIRS_USED = (6, 3, 1)
PICTURE_LEVEL = 0.03
"""A truth's row or column mean above this is inside the monitor picture."""


def load(source: Path | None, downsample: int) -> tuple[np.ndarray, np.ndarray]:
    """Raws and truths ``(7, 3, ny, nx)``, RGB."""
    from diffcam.data import load_scene_pairs
    from diffcam.io import downsample as box, read_rgb

    if source is None:
        pairs = load_scene_pairs(downsample_by=downsample)
        return pairs.raws, pairs.truths
    raws, truths = ([read_rgb(source / kind / f"{n}.npy", channel_order="BGR")
                     for n in NAMES] for kind in ("diffuser", "lensed"))
    raws, truths = np.stack(list(raws)), np.stack(list(truths))
    return (box(raws, downsample), box(truths, downsample)) if downsample > 1 else (raws, truths)


def reconstruct(method: str, raw: np.ndarray, psf) -> np.ndarray:
    """The scene on the sensor frame, in the truth's units (``A x ≈ raw``); ``psf`` is
    ``(3, ny, nx)`` or a field-dependent PSF per channel (a tuple of ``FieldPSF``)."""
    from diffcam.core.grid import crop_to
    from diffcam.reconstruct import admm_tv, fista, field_model, richardson_lucy, wiener

    norm = lambda a: np.linalg.norm(a, axis=(-2, -1), keepdims=True)  # noqa: E731
    if isinstance(psf, tuple):
        models = [field_model(f, raw.shape[-2:]) for f in psf]
        if method == "admm":
            x = [admm_tv(r / norm(r), m, 100, progress=False).image * norm(r)
                 for r, m in zip(raw, models)]
        else:
            x = [fista(r, m, 200, progress=False).image for r, m in zip(raw, models)]
        return np.stack([np.asarray(crop_to(v, raw.shape)) for v in x])
    if method == "admm":
        x = admm_tv(raw / norm(raw), psf / norm(psf), 100, progress=False).image
        x = x * (norm(raw) / norm(psf))
    elif method == "rl":
        x = richardson_lucy(np.clip(raw, 0, None), psf, 1000, boundary="crop",
                            progress=False).image
    elif method == "wiener":
        x = wiener(raw, psf, 1e-3, boundary="crop").image / psf.sum(axis=(-2, -1),
                                                                    keepdims=True)
    else:
        x = fista(raw, psf, 200, progress=False).image
    return np.asarray(crop_to(x, raw.shape))


def scores(estimate: np.ndarray, truth: np.ndarray) -> dict:
    """PSNR (dB), SSIM and Pearson of a ``(3, ny, nx)`` estimate against the truth."""
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from diffcam.evaluate.metrics import pearson

    clipped = np.clip(estimate, 0, 1)
    rows, cols = (np.flatnonzero(truth.mean(axis=(0, a)) > PICTURE_LEVEL) for a in (2, 1))
    inside = (slice(None), slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
    truth_in, mapped = truth[inside], np.clip(affine_fit(estimate[inside], truth[inside]), 0, 1)
    return {"psnr": float(peak_signal_noise_ratio(truth, clipped, data_range=1)),
            "ssim": float(np.mean([structural_similarity(t, e, data_range=1)
                                   for t, e in zip(truth, clipped)])),
            "pearson": float(np.mean(np.asarray(pearson(clipped, truth)))),
            "psnr_picture": float(peak_signal_noise_ratio(truth_in, mapped, data_range=1)),
            "ssim_picture": float(np.mean([structural_similarity(t, e, data_range=1)
                                           for t, e in zip(truth_in, mapped)]))}


def affine_fit(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``a·estimate + b`` per channel, ``a, b`` the least-squares fit to the truth."""
    out = []
    for e, t in zip(estimate, truth):
        design = np.stack([e.ravel(), np.ones(e.size)], axis=1)
        (a, b), *_ = np.linalg.lstsq(design, t.ravel(), rcond=None)
        out.append(a * e + b)
    return np.stack(out)


def fold(raws, truths, k: int, args) -> tuple[list[dict], dict]:
    """Leave pair ``k`` out: rows of scores, and the arrays for the figure."""
    from diffcam.calibrate.scene.fit import fit_field_psf_from_scenes, fit_psf_from_scenes
    from diffcam.calibrate.scene.pairs import flip_scene

    others = [(k + j) % len(raws) for j in range(1, len(raws))]
    rows, shown = [], {}
    for used in args.pairs_used:
        t = time.perf_counter()
        cal = fit_psf_from_scenes(raws[others[:used]], truths[others[:used]], progress=False)
        calibrations = [("one PSF", cal, time.perf_counter() - t)]
        if used == len(raws) - 1 and args.grid:
            t = time.perf_counter()
            field = fit_field_psf_from_scenes(raws[others], truths[others], tuple(args.grid),
                                              flip=cal.flip, progress=False)
            calibrations.append((f"field {args.grid[0]}×{args.grid[1]}", field,
                                 time.perf_counter() - t))
        for model, c, fit_s in calibrations:
            solvers = [m for m in args.solvers if model == "one PSF" or m in FIELD_SOLVERS]
            rows += held_out(raws[k], truths[k], c, solvers if used == len(raws) - 1
                             else [m for m in ("admm",) if m in args.solvers],
                             {"pair": NAMES[k], "pairs_used": used, "model": model,
                              "flip": c.flip, "fit_s": fit_s,
                              "misfit": float(c.residual[-1])}, shown)
        if used == len(raws) - 1:
            shown.update(raw=raws[k], truth=flip_scene(truths[k], cal.flip), psf=cal.psf)
    return rows, shown


def held_out(raw, truth, cal, solvers, row: dict, shown: dict) -> list[dict]:
    """Rows of one calibration on the held-out pair: its raw predicted from its truth
    and reconstructed by each solver (the estimates of the one-PSF model into
    ``shown``)."""
    from diffcam.calibrate.scene.fit import predict_raw
    from diffcam.calibrate.scene.pairs import flip_scene
    from diffcam.evaluate.metrics import pearson

    predicted = np.asarray(pearson(predict_raw(cal, truth), raw))
    truth = flip_scene(truth, cal.flip)                    # the truth in the sensor frame
    raw = raw - cal.offset[:, None, None]
    kernels = getattr(cal, "fields", None) or cal.psf
    rows = []
    for method in solvers:
        t = time.perf_counter()
        estimate = reconstruct(method, raw, kernels)
        rows.append({**row, "method": method, "predict_pearson_min": float(predicted.min()),
                     "predict_pearson": predicted.tolist(), **scores(estimate, truth),
                     "solve_s": time.perf_counter() - t})
        if row["model"] == "one PSF":
            shown[method] = estimate
    return rows


def summary(rows: list[dict]) -> list[dict]:
    """Mean scores per (pairs used, model, method)."""
    out = []
    keys = dict.fromkeys((r["pairs_used"], r["model"], r["method"]) for r in rows)
    for used, model, method in keys:
        sel = [r for r in rows if (r["pairs_used"], r["model"], r["method"])
               == (used, model, method)]
        out.append({"pairs_used": used, "model": model, "method": method, "n": len(sel),
                    **{m: float(np.mean([r[m] for r in sel]))
                       for m in ("psnr", "ssim", "pearson", "psnr_picture", "ssim_picture",
                                 "predict_pearson_min", "misfit")},
                    "worst_predict_pearson": float(np.min(
                        [r["predict_pearson_min"] for r in sel]))})
    return out


def figure(shown: dict, path: Path, name: str) -> None:
    """Raw, PSF, reconstructions and truth of one held-out pair, side by side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffcam.apps.cli import save_figure

    def rgb(a, top=None):
        a = np.moveaxis(np.asarray(a), 0, -1)
        return np.clip(a / (top or np.percentile(a, 99.5)), 0, 1)

    panels = [("raw (held out)", rgb(shown["raw"])), ("PSF fitted to the other six",
                                                      rgb(shown["psf"]) ** 0.5)]
    panels += [(f"{m}", rgb(shown[m], 1.0)) for m in SOLVERS if m in shown]
    panels += [("ground truth (lensed)", rgb(shown["truth"], 1.0))]
    fig, axes = plt.subplots(2, 4, figsize=(16, 5.2), layout="constrained")
    for ax, (title, image) in zip(axes.flat, panels):
        ax.imshow(image)
        ax.set_title(title, fontsize=9)
    for ax in axes.flat:
        ax.axis("off")
    fig.suptitle(f"Lensless Learning {name}, calibrated on the other six pairs (sensor "
                 f"frame; reconstructions clipped to the truth's range [0, 1])", fontsize=10)
    save_figure(fig, path)


def combine(paths: list[Path], name: str) -> None:
    """One results JSON from the rows of several runs over different folds."""
    import json

    records = [json.loads(p.read_text()) for p in paths]
    rows = [r for rec in records for r in rec["rows"]]
    table = summary(rows)
    print(markdown_table(table, list(table[0])))
    extra = {k: records[0][k] for k in ("data", "shape", "downsample")}
    parts = [{k: rec[k] for k in ("command_line", "date", "load", "git")} for rec in records]
    print(f"wrote {write_json(name, rows, {**extra, 'summary': table, 'parts': parts})}")


def via_cli(source: Path, name: str, run_dir: Path, grid) -> list[dict]:
    """Rows of fold ``name`` through the ``diffcam`` commands (module docstring)."""
    import json

    from diffcam.calibrate.scene.pairs import flip_scene
    from diffcam.io import read_rgb

    k = NAMES.index(name)
    others = [NAMES[(k + j) % len(NAMES)] for j in range(1, len(NAMES))]
    pairs = [str(source / "diffuser" / f"{n}.npy") for n in others] + ["--truth"] + [
        str(source / "lensed" / f"{n}.npy") for n in others] + ["--channel-order", "BGR"]
    field = f"{grid[0]}x{grid[1]}"
    ran = {"psf": _run_once(run_dir, "psf.tif", ["calibrate-psf", *pairs, "-o", "psf.tif",
                                                  "--json", "psf.json"]),
           "field": _run_once(run_dir, "field.npz", ["calibrate-psf", *pairs, "--field",
                                                      field, "-o", "field.npz", "--json",
                                                      "field.json"])}
    cal = {m: json.loads((run_dir / f"{m}.json").read_text()) for m in ("psf", "field")}
    dark = ",".join(repr(v) for v in cal["psf"]["offset"])
    raw = str(source / "diffuser" / f"{name}.npy")
    truth = flip_scene(read_rgb(source / "lensed" / f"{name}.npy", channel_order="BGR"),
                       cal["psf"]["flip"])
    rows = []
    for model, psf, extra in (("one PSF", "psf.tif", [f"--dark-raw={dark}"]),
                              (f"field {grid[0]}×{grid[1]}", "field.npz", [])):
        for method in FIELD_SOLVERS:
            out = f"{psf.split('.')[0]}_{method}.npy"
            t = time.perf_counter()
            command = ["reconstruct", raw, "--channel-order", "BGR", "--psf", psf, *extra,
                       "--method", method, "-o", out]
            run = _run_once(run_dir, out, command)
            wall = time.perf_counter() - t if run else None
            estimate = np.moveaxis(np.load(run_dir / out), -1, 0).astype(np.float64)
            rows.append({"pair": name, "model": model, "method": method,
                         **scores(estimate, truth), "reconstruct_wall_s": wall,
                         "calibration_run": ran["psf" if psf == "psf.tif" else "field"],
                         "command": "diffcam " + " ".join(command)})
    return rows


def _run_once(run_dir: Path, output: str, command: list[str]) -> bool:
    """``diffcam COMMAND`` in ``run_dir`` (this checkout's package), unless ``output``
    is there already; whether it ran."""
    import os
    import subprocess
    import sys

    if (run_dir / output).exists():
        print(f"reusing {run_dir / output}")
        return False
    print("diffcam " + " ".join(command), flush=True)
    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, "-m", "diffcam", *command], cwd=run_dir, check=True,
                   env={**os.environ, "PYTHONPATH": str(root)})
    return True


def cli_table(rows: list[dict], name: str) -> list[dict]:
    """The command-line rows beside this benchmark's rows of the same fold, pair and
    model from ``benchmarks/results/scene_psf_full.json``."""
    import json

    from benchmarks.harness import RESULTS

    bench = json.loads((RESULTS / "scene_psf_full.json").read_text())["rows"]
    table = []
    for r in rows:
        b = next(x for x in bench if (x["pair"], x["model"], x["method"], x["pairs_used"])
                 == (name, r["model"], r["method"], 6))
        table.append({"model": r["model"], "method": r["method"], "psnr_cli": r["psnr"],
                      "psnr_bench": b["psnr"], "ssim_cli": r["ssim"], "ssim_bench": b["ssim"],
                      "psnr_picture_cli": r["psnr_picture"],
                      "psnr_picture_bench": b["psnr_picture"]})
    return table


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--source", type=Path, help="folder of the original .npy pairs")
    p.add_argument("--downsample", type=int, default=1, help="box-average factor")
    p.add_argument("--figure", type=Path, help="write the figure of the first pair here")
    p.add_argument("--pairs", type=int, default=len(NAMES), help="held-out pairs to run")
    p.add_argument("--folds", nargs="+", choices=NAMES, help="held-out pairs by name "
                   "(instead of the first --pairs)")
    p.add_argument("--combine", type=Path, nargs="+", metavar="JSON",
                   help="summarise the rows of these results JSONs (folds run apart)")
    p.add_argument("--pairs-used", type=int, nargs="+", default=list(PAIRS_USED),
                   help="calibrate on this many of the other pairs")
    p.add_argument("--solvers", nargs="+", choices=SOLVERS, default=list(SOLVERS))
    p.add_argument("--grid", type=int, nargs=2, default=[2, 2], metavar=("GY", "GX"),
                   help="field positions of the field-dependent PSF (0 0: none)")
    p.add_argument("--via-cli", type=Path, metavar="RUNDIR",
                   help="run the first of --folds through the diffcam commands in RUNDIR")
    p.add_argument("--name", default="scene_psf", help="results JSON name")
    args = p.parse_args(argv)
    args.grid = args.grid if min(args.grid) > 0 else None
    if args.combine:
        return combine(args.combine, args.name)
    if args.via_cli:
        if args.source is None or not args.folds or args.grid is None:
            p.error("--via-cli needs --source, --folds and a --grid")
        args.via_cli.mkdir(parents=True, exist_ok=True)
        rows = via_cli(args.source.resolve(), args.folds[0], args.via_cli.resolve(),
                       args.grid)
        table = cli_table(rows, args.folds[0])
        print(markdown_table(table, list(table[0])))
        extra = {"data": args.source.name, "comparison": table}
        print(f"wrote {write_json(args.name, rows, extra)}")
        return
    raws, truths = load(args.source, args.downsample)
    t, rows = time.perf_counter(), []
    folds = [NAMES.index(n) for n in args.folds] if args.folds else range(args.pairs)
    for k in folds:
        fold_rows, shown = fold(raws, truths, k, args)
        rows += fold_rows
        if k == folds[0] and args.figure:
            figure(shown, args.figure, NAMES[k])
            print(f"wrote {args.figure}")
        print(f"- {NAMES[k]} done ({time.perf_counter() - t:.0f} s)", flush=True)
    table = summary(rows)
    print(markdown_table(table, list(table[0])))
    data = "shipped" if args.source is None else str(args.source.name)
    extra = {"data": data, "shape": list(raws.shape), "downsample": args.downsample,
             "summary": table}
    print(f"wrote {write_json(args.name, rows, extra)}")


if __name__ == "__main__":
    main()
