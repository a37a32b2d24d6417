"""Benchmark: 3-D from one capture — the README's ``reconstruct --3d`` command on the
shipped USAF capture, against a DiffuserCam-settings reference and the peers, judged
by the x–z ridge of the tilted target; and the paper's Fig. 10 on real data.

    python -m benchmarks.bench_3d [--reference-iterations 300] [--peer-iterations 10]
        [--scico-python PY] [--lensless-python PY] [--skip-fig10] [--figure PATH]

Rows (one run, one machine; the peers run as subprocesses in their own environments,
``--scico-python``/``--lensless-python`` or the ``SCICO_PYTHON``/``LENSLESS_PYTHON``
environment variables; a missing peer is a printed note):

* ``readme (xla)``, ``readme (fftw)``: ``diffcam data usaf3d`` then the README's
  ``diffcam reconstruct captures/usaf_raw.png --psf captures/psfs --3d -o usaf.tif`` in
  a fresh process (:func:`benchmarks.harness.run_probed`: wall time with start-up, peak
  RSS), with ``DIFFCAM_FFT`` unset and ``=fftw``; the volume is read back and judged.
* ``readme, --psf-envelope auto``, ``readme, --psf-envelope none``: the same command
  (XLA's FFT) with each PSF plane times a vertical envelope fitted to the capture
  instead of the sensor window, and with neither: the effect of the window.
* ``reference``: :func:`diffcam.reconstruct.admm_tv_3d` with DiffuserCam's settings
  (raw minus its 100-count bias, the stack's 2-count dark level removed, τ = 6e-4 on
  raw counts, isotropic 3-D TV), residual balancing and each PSF plane's vertical
  envelope matched to the capture (:func:`diffcam.io.envelope_widths`),
  ``--reference-iterations``.
* ``scico``, ``lensless``: ``benchmarks/peers_3d/*.py`` for ``--peer-iterations``
  (their seconds per iteration; their ridges only mean something for full runs).

Seconds per iteration of diffcam's loop are measured in process on the compiled solver
(two lengths, the difference divided by the extra iterations), beside the cost of the
FFTs one iteration needs (a real FFT pair of the stack and one of a plane). The ridge
(:func:`diffcam.evaluate.volume.ridge_measures`) is measured on the box of the target
found in the reference's max projection, the same box for every row. The printed
residual is checked against the residual of the returned volume recomputed with
:func:`diffcam.reconstruct.convolution_model`.

Fig. 10: the capture reconstructed with the CLI's solver settings (``VOLUME``) and the
measured stack, the stack :func:`diffcam.calibrate.fit_stack` predicts from planes 5 and
27, and the scaling baseline's (``benchmarks.bench_stack_volume.stacks``); each stack as
it is (so that the stacks alone differ) and with its envelope estimated from the capture
(``, envelope``: what ``reconstruct --3d`` does); per-column ridge depths compared with
the measured stack's, treated alike. A fourth stack, ``neighbours``
(:func:`neighbour_stack`: each plane from its two measured neighbours), is the floor of
that agreement: nearer the measured stack than any prediction from two planes.

Results: ``benchmarks/results/bench_3d.json`` and the figure (default
``benchmarks/results/bench_3d.png``).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.harness import markdown_table, run_probed, write_json
from diffcam.apps.reconstruct_args import ITERATIONS_3D

LIT = 0.2
"""A column is lit when its x–z peak is at least this share of the brightest column's:
``lit_rms`` is the ridge's scatter over the lit columns, beside the issue's ``rms``."""

README_COMMAND = ["reconstruct", "captures/usaf_raw.png", "--psf", "captures/psfs", "--3d",
                  "-o", "usaf.tif"]
PEERS = {"scico": ("SCICO_PYTHON", "scico_admm_tv.py"),
         "lensless": ("LENSLESS_PYTHON", "lensless_fista.py")}


def readme_run(fft: str | None, extra=()) -> tuple[dict, np.ndarray]:
    """The README's command (plus ``extra`` options) in a fresh process
    (``DIFFCAM_FFT=fft`` if given): its record and the volume it wrote."""
    import tifffile

    with tempfile.TemporaryDirectory() as work:
        run_probed([sys.executable, "-m", "diffcam", "data", "usaf3d", "-o", "captures"],
                   cwd=work)
        saved = os.environ.get("DIFFCAM_FFT")
        if fft:
            os.environ["DIFFCAM_FFT"] = fft
        else:
            os.environ.pop("DIFFCAM_FFT", None)
        try:
            record = run_probed([sys.executable, "-m", "diffcam", *README_COMMAND, *extra],
                                cwd=work)
        finally:
            os.environ.pop("DIFFCAM_FFT", None)
            if saved is not None:
                os.environ["DIFFCAM_FFT"] = saved
        if record["rc"] != 0:
            raise RuntimeError(f"the README command failed: {record['stderr']}")
        volume = tifffile.imread(Path(work) / "usaf.tif")
    printed = re.search(r"residual ([0-9.eE+-]+)", record["stdout"])
    return {"wall_s": record["wall_s"], "peak_mb": record["peak_bytes"] / 2 ** 20,
            "printed_residual": float(printed.group(1)) if printed else None,
            "stdout": record["stdout"].strip()}, volume


def inputs(downsample: int = 1):
    """The capture (raw counts minus the bias) and the stack (minus its dark level)."""
    from diffcam.data import load_psf_stack_3d, load_raw_3d
    from diffcam.io import downsample as box

    raw, psf = load_raw_3d(), np.clip(load_psf_stack_3d() - 2 / 65535, 0, None)
    return (raw, psf) if downsample == 1 else (box(raw, downsample), box(psf, downsample))


def seconds_per_iteration(raw, psf, options, lengths=(5, 15)) -> dict:
    """diffcam's loop, compiled, timed at two lengths; and the FFTs of one iteration."""
    import jax
    import jax.numpy as jnp

    from diffcam.core.backend import irfft2, rfft2
    from diffcam.reconstruct import admm_tv_3d
    from diffcam.reconstruct.operators import grid_shapes

    b = raw / np.linalg.norm(raw)
    times = []
    for n in lengths:
        admm_tv_3d(b, psf, n, options, progress=False)         # compile
        t = time.perf_counter()
        jax.block_until_ready(admm_tv_3d(b, psf, n, options, progress=False).image)
        times.append(time.perf_counter() - t)
    per_it = (times[1] - times[0]) / (lengths[1] - lengths[0])
    grid = grid_shapes(raw.shape, psf.shape, "crop")[1]
    stack = jnp.zeros((psf.shape[0],) + grid, jnp.float32)
    ffts = jax.jit(lambda v: irfft2(rfft2(v), s=grid).sum(0)
                   + irfft2(rfft2(v[0]), s=grid))
    jax.block_until_ready(ffts(stack))
    t = time.perf_counter()
    for _ in range(5):
        jax.block_until_ready(ffts(stack))
    return {"s_per_it": per_it, "fft_s_per_it": (time.perf_counter() - t) / 5}


def reference(raw, psf, iterations) -> tuple[dict, np.ndarray]:
    """DiffuserCam's settings (raw counts, τ 6e-4, 3-D TV) with residual balancing and
    the PSF envelope matched to the capture; and the residual of the returned volume
    recomputed with the forward model."""
    from diffcam.core.grid import crop_to
    from diffcam.io import apply_envelope, envelope_widths
    from diffcam.reconstruct import AdmmOptions, admm_tv_3d, convolution_model
    from diffcam.reconstruct.loop import relative_residual

    psf = apply_envelope(psf, envelope_widths(raw, psf))
    t = time.perf_counter()
    rec = admm_tv_3d(raw, psf, iterations, AdmmOptions(balance=True), progress=False)
    seconds = time.perf_counter() - t
    model = convolution_model(psf, raw.shape, "crop", volume=True)
    recomputed = float(relative_residual(model(rec.image), raw))
    return ({"wall_s": seconds, "printed_residual": float(rec.final_residual),
             "recomputed_residual": recomputed, "split_gap": float(rec.split_gap),
             "iterations": iterations},
            np.asarray(crop_to(rec.image, raw.shape)))


def peer(name: str, python: str | None, raw, psf, iterations: int, note: list):
    """Run a peer driver; its record and volume, or None with a note."""
    if not python or not Path(python).exists():
        note.append(f"{name}: no interpreter (set --{name}-python or "
                    f"{PEERS[name][0]}); skipped")
        return None, None
    driver = Path(__file__).resolve().parent / "peers_3d" / PEERS[name][1]
    with tempfile.TemporaryDirectory() as work:
        src, dst = Path(work) / "in.npz", Path(work) / "out.npz"
        np.savez(src, raw=raw, psf=psf)
        t = time.perf_counter()
        done = subprocess.run([python, str(driver), str(src), str(dst), str(iterations)],
                              capture_output=True, text=True)
        wall = time.perf_counter() - t
        if done.returncode != 0:
            note.append(f"{name}: failed ({done.stderr.strip().splitlines()[-1:]}); skipped")
            return None, None
        out = np.load(dst)
        return ({"wall_s": wall, "s_per_it": float(out["seconds_per_iteration"]),
                 "iterations": iterations}, np.clip(out["volume"], 0, None))


def neighbour_stack(measured: np.ndarray) -> np.ndarray:
    """Each plane from its two measured neighbours, magnified to it about the registered
    fixed point and averaged (an end plane from its one neighbour): a stack nearer the
    measured one than any prediction from two planes, the floor of Fig. 10's
    per-column agreement."""
    import dataclasses

    from diffcam.evaluate.registration import (register_magnification,
                                               relative_magnification_at, scaling_baseline)

    n = len(measured)
    law = register_magnification(measured[0], measured[-1])
    out = np.empty_like(measured)
    for t in range(n):
        a, b = (t - 1, t + 1) if 0 < t < n - 1 else ((1, 2) if t == 0 else (n - 3, n - 2))
        ratio = (relative_magnification_at(b, law.magnification, 0, n - 1)
                 / relative_magnification_at(a, law.magnification, 0, n - 1))
        out[t] = scaling_baseline({a: measured[a], b: measured[b]}, [t], blend=True,
                                  registration=dataclasses.replace(law, magnification=ratio))[0]
    return out


def fig10(raw, iterations: int, downsample: int = 1) -> tuple[dict, dict]:
    """Volumes with the measured, model-predicted, baseline and neighbour stacks
    (``VOLUME``): each stack as it is, and each with its envelope estimated from the
    capture (as ``reconstruct --3d`` does; keys ``"NAME, envelope"``); and each stack's
    mean Pearson with the measured planes."""
    from benchmarks.bench_stack_volume import stacks
    from diffcam.core.grid import crop_to
    from diffcam.data import load_psf_stack_3d
    from diffcam.evaluate import pearson
    from diffcam.io import apply_envelope, envelope_widths
    from diffcam.reconstruct import admm_tv_3d
    from diffcam.reconstruct.admm import VOLUME

    from diffcam.io import downsample as box

    psfs, _ = stacks(load_psf_stack_3d(), [5, 27])
    psfs["neighbours"] = neighbour_stack(np.asarray(psfs["measured"], np.float64))
    score = {name: float(np.mean(pearson(np.asarray(s), np.asarray(psfs["measured"]))))
             for name, s in psfs.items()}
    psfs = {name: box(np.clip(s, 0, None).astype(np.float32), downsample)
            for name, s in psfs.items()}
    psfs.update({f"{name}, envelope": apply_envelope(s, envelope_widths(raw, s))
                 for name, s in list(psfs.items())})
    b = raw / np.linalg.norm(raw)
    return {name: np.asarray(crop_to(admm_tv_3d(b, s, iterations, VOLUME,
                                                progress=False).image, raw.shape))
            for name, s in psfs.items()}, score


def ridge_row(name, volume, box, extra=None) -> dict:
    from diffcam.evaluate.volume import ridge_measures

    r = ridge_measures(volume, box)
    lit = r.brightness >= LIT
    cols = np.arange(box.left, box.right)[lit]
    line = np.polyval(np.polyfit(cols, r.peaks[lit], 1), cols)
    return {"run": name, **r.summary(), **(extra or {}),
            "lit_rms": float(np.sqrt(np.mean((r.peaks[lit] - line) ** 2))),
            "lit_columns": int(lit.sum()), "peaks": r.peaks.tolist(),
            "brightness": r.brightness.round(4).tolist()}


def agreement(row: dict, measured: dict) -> dict:
    """Slope difference and share of columns within one and two planes of the measured
    stack's."""
    peaks, ref = np.asarray(row["peaks"]), np.asarray(measured["peaks"])
    return {"slope_diff": abs(row["slope"] - measured["slope"]),
            "within_1_plane": float(np.mean(np.abs(peaks - ref) <= 1)),
            "within_2_planes": float(np.mean(np.abs(peaks - ref) <= 2))}


def figure(volumes: dict, box, path) -> None:
    """Max projection (top) and x–z projection (bottom) of every volume, the target box
    drawn on the max projection."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from diffcam.apps.cli import save_figure

    names = list(volumes)
    fig, axes = plt.subplots(2, len(names), figsize=(3.2 * len(names), 5.6),
                             layout="constrained", squeeze=False)
    for k, name in enumerate(names):
        v = volumes[name]
        mip, xz = v.max(axis=0), v.max(axis=1)
        axes[0, k].imshow(mip, cmap="gray", vmin=0, vmax=np.percentile(mip, 99.7))
        axes[0, k].add_patch(Rectangle((box.left, box.top), box.right - box.left,
                                       box.bottom - box.top, fill=False, ec="tab:red"))
        axes[0, k].set_title(name, fontsize=9)
        axes[1, k].imshow(xz, cmap="gray", aspect="auto", vmin=0,
                          vmax=np.percentile(xz, 99.7))
        axes[1, k].set_xlabel("x (pixels)")
        axes[1, k].set_ylabel("plane")
    save_figure(fig, path)


def _arguments(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference-iterations", type=int, default=300)
    parser.add_argument("--peer-iterations", type=int, default=10)
    parser.add_argument("--scico-python", default=os.environ.get("SCICO_PYTHON"))
    parser.add_argument("--lensless-python", default=os.environ.get("LENSLESS_PYTHON"))
    parser.add_argument("--skip-fig10", action="store_true")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke run: frames binned 4x, 5 iterations everywhere")
    parser.add_argument("--figure", default="benchmarks/results/bench_3d.png")
    return parser.parse_args(argv)


def _speeds(raw, psf, rows) -> None:
    """diffcam's s/it with XLA's FFT and FFTW into the README rows, and the ratio to
    scico's."""
    from diffcam.core.backend import set_fft
    from diffcam.reconstruct.admm import VOLUME

    speed = {}
    for fft in ("xla", "fftw"):
        set_fft(fft)
        speed[fft] = seconds_per_iteration(raw, psf, VOLUME)
    set_fft("xla")
    scico = next((r["s_per_it"] for r in rows if r["run"] == "scico"), None)
    for row in rows:
        if row["run"].startswith("readme ("):
            row.update(speed["fftw" if "fftw" in row["run"] else "xla"])
            if scico:
                row["s_per_it_vs_scico"] = row["s_per_it"] / scico


def _fig10_rows(raw, box, iterations, down, volumes) -> list[dict]:
    stacks_volumes, score = fig10(raw, iterations, down)
    measured = {env: ridge_row("fig10 measured", stacks_volumes["measured" + env], box)
                for env in ("", ", envelope")}
    rows = []
    for name, v in stacks_volumes.items():
        row = ridge_row(f"fig10 {name}", v, box)
        env = ", envelope" if name.endswith(", envelope") else ""
        rows.append({**row, **agreement(row, measured[env]),
                     "stack_pearson": score[name.removesuffix(", envelope")]})
        volumes[f"fig10 {name}"] = v
    return rows


def main(argv=None) -> None:
    from diffcam.evaluate.volume import target_box
    from diffcam.reconstruct.admm import VOLUME

    args = _arguments(argv)
    down, its = (4, 5) if args.quick else (1, None)
    extra = ["--downsample", "4", "--iterations", "5"] if args.quick else []
    raw, psf = inputs(down)
    note: list[str] = []
    ref_record, ref_volume = reference(raw, psf, its or args.reference_iterations)
    box = target_box(ref_volume.max(axis=0))
    rows = [ridge_row("reference", ref_volume, box, ref_record)]
    volumes = {"reference": ref_volume}
    for name, fft, options in (("readme (xla)", None, []), ("readme (fftw)", "fftw", []),
                               *((f"readme, --psf-envelope {mode}", None,
                                  ["--psf-envelope", mode]) for mode in ("auto", "none"))):
        record, volumes[name] = readme_run(fft, extra + options)
        rows.append(ridge_row(name, volumes[name], box, record))
    for name in PEERS:
        record, volume = peer(name, getattr(args, f"{name}_python"), raw, psf,
                              its or args.peer_iterations, note)
        if record is not None:
            volumes[name] = volume
            rows.append(ridge_row(name, volume, box, record))
    _speeds(raw, psf, rows)
    fig10_rows = [] if args.skip_fig10 else _fig10_rows(
        raw, box, its or ITERATIONS_3D["admm"], down, volumes)
    print(markdown_table(rows, ["run", "s_per_it", "fft_s_per_it", "s_per_it_vs_scico",
                                "slope", "rms", "lit_rms", "axial_width", "outside", "wall_s",
                                "peak_mb", "printed_residual", "recomputed_residual"]))
    if fig10_rows:
        print(markdown_table(fig10_rows, ["run", "stack_pearson", "slope", "rms",
                                          "lit_rms", "axial_width", "outside", "slope_diff",
                                          "within_1_plane", "within_2_planes"]))
    for line in note:
        print("note:", line)
    figure(volumes, box, args.figure)
    path = write_json("bench_3d", rows + fig10_rows,
                      {"box": list(box), "notes": note, "figure": args.figure,
                       "volume_options": str(VOLUME), "shared_machine_load": os.getloadavg()})
    print("wrote", path, "and", args.figure)


if __name__ == "__main__":
    main()
