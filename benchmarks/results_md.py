"""Write ``benchmarks/RESULTS.md`` from the recorded results, ``benchmarks/results/*.json``.

    python -m benchmarks.results_md            # rewrite RESULTS.md
    python -m benchmarks.results_md --check    # exit 1 if RESULTS.md is not what it writes

One section per JSON file, in :data:`SECTIONS` order (others after, by name): the
command that wrote it, the machine it ran on, a table of its rows and the workload's
own verdict when it records one. RESULTS.md holds the current results only; a
benchmark run rewrites its JSON, and this command the page.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.harness import RESULTS

PAGE = Path(__file__).resolve().parent / "RESULTS.md"

SECTIONS = {
    # JSON name: (title, command, columns of the table: None for every scalar column)
    "demo": ("`diffcam demo`, run after run",
             "python -m benchmarks.bench_demo --runs 2 --cpus all 1",
             ["cpus", "run", "wall_s", "peak_gb", "fig3_gs", "fig3_calibrated",
              "fig5_psf", "fig6_nearfar_psf", "fig6_psf", "fig9_model"]),
    "stack_fit": ("Measured PSF stack: planes fitted, the others predicted",
                  "python -m benchmarks.bench_stack_fit --pairs 6 --spread 3 5 "
                  "--time-budget 400",
                  ["pair", "transform", "model_mean", "baseline_mean", "rendered_mean",
                   "blend_mean", "frozen_mean", "above_baseline", "rendered_above",
                   "outside_gain", "frozen_cost_outside", "depth_effect_outside",
                   "z2M_first_mm", "steps", "fit_s"]),
    **{f"stack_fit_{o}": (f"Measured PSF stack, one pair: {label}",
                          f"python -m benchmarks.bench_stack_fit --quick --time-budget 400 "
                          f"--options '{{\"optimiser\": \"{o}\"}}' --name stack_fit_{o}",
                          ["pair", "transform", "model_mean", "baseline_mean",
                           "rendered_mean", "above_baseline", "steps", "fit_s"])
       for o, label in (("lbfgs", "optimistix LBFGS instead of Adam"),
                        ("nonlinear_cg", "optimistix NonlinearCG instead of Adam"))},
    "stack_fit_oversample3": ("Measured PSF stack: 3 × 3 samples per pixel (one field "
                              "coefficient per pixel, the default distance start)",
                              "python -m benchmarks.bench_stack_fit --pairs 6 --spread 3 5 "
                              "--time-budget 400 --options '{\"oversample\": 3, "
                              "\"field_stride\": 3, \"zetas\": [36.0]}' "
                              "--name stack_fit_oversample3",
                              ["pair", "transform", "model_mean", "baseline_mean",
                               "rendered_mean", "frozen_mean", "above_baseline",
                               "rendered_above", "steps", "stop_reason", "fit_s", "load"]),
    "stack_fit_float64": ("Measured PSF stack, one pair, in float64",
                          "JAX_ENABLE_X64=1 python -m benchmarks.bench_stack_fit --quick "
                          "--time-budget 400 --name stack_fit_float64",
                          ["pair", "transform", "model_mean", "baseline_mean",
                           "rendered_mean", "above_baseline", "steps", "fit_s",
                           "predict_s", "load"]),
    "stack_light": ("Measured PSF stack: the magnification from two planes' light "
                    "(inverse-square law)",
                    "python -m benchmarks.bench_stack_light",
                    ["pair", "transform", "M_first", "M_last", "z1_first_z2", "z1_last_z2",
                     "law_mean_err", "law_max_err", "linear_mean_err", "linear_max_err"]),
    "stack_limits": ("Measured PSF stack: the rendering alone next to a given plane, "
                     "and the most a sensor-side correction recovers",
                     "python -m benchmarks.bench_stack_limits",
                     ["case", "plane", "given", "rendered", "baseline", "envelope", "blur",
                      "blur_scale", "response", "gamma", "r0_30", "r30_60", "r60_90",
                      "r90_120"]),
    "startup": ("Start-up: a fresh `diffcam` process, with the compilation cache off, "
                "empty and warm",
                "python -m benchmarks.bench_startup --rounds 5", None),
    "stack_volume": ("3-D reconstruction of the real capture with a predicted stack",
                     "python -m benchmarks.bench_stack_volume",
                     ["stack", "volume_pearson", "plane_pearson_mean",
                      "depth_error_planes", "same_depth_pm2", "depth_spearman"]),
    "stack_sim": ("Fig. 9 on simulated data the model did not make",
                  "python -m benchmarks.bench_stack_sim",
                  ["predictor", "truth", "held_out_mean", "worst", "above_baseline"]),
    "stack_sim_z2_5mm": ("Fig. 9 at DiffuserCam's scale (z2 = 5 mm, planes on both sides "
                         "of the given pair)",
                         "python -m benchmarks.bench_stack_sim --z2 5 --z1 20:200 --dx 2 "
                         "--planes 3,8 --name stack_sim_z2_5mm",
                         ["predictor", "truth", "held_out_mean", "worst", "above_baseline"]),
    "stack_regimes": ("When the wave model helps: a regime map on simulated stacks",
                      "python -m benchmarks.bench_stack_regimes",
                      ["setting", "M_range", "model_gain", "rendered_gain", "outside_gain",
                       "frozen_cost_outside", "above", "zeta_reference_px2"]),
    "bench_3d": ("3-D from one capture: the README's `reconstruct --3d` judged by the "
                 "tilted target's depth ridge, beside a reference and the peers",
                 "python -m benchmarks.bench_3d --peer-iterations 5",
                 ["run", "s_per_it", "fft_s_per_it", "s_per_it_vs_scico", "slope", "rms",
                  "lit_rms", "axial_width", "outside", "wall_s", "peak_mb",
                  "printed_residual", "recomputed_residual", "stack_pearson", "slope_diff",
                  "within_1_plane", "within_2_planes"]),
    "bench_3d_convergence": ("3-D from one capture: the solve's convergence by iteration "
                             "count, over-relaxation and the penalties' start",
                             "python -m benchmarks.bench_3d_convergence",
                             ["setting", "iterations", "seconds", "residual", "objective",
                              "split_gap", "side_slope", "side_rms", "side_axial_width",
                              "side_outside", "diffcam_rms", "diffcam_outside", "own_rms",
                              "own_outside"]),
    "peers": ("PSF stacks beside the JAX optics peers (chromatix, dLux): forward and "
              "value_and_grad, time and peak memory",
              "python -m benchmarks.bench_peers --chromatix-python /path/to/python3.12",
              ["kind", "N", "depths", "candidate", "median_s", "x_forward", "peak_mb",
               "worst_1mp", "repeats", "first_s", "load", "status"]),
    "distributed": ("PSF stacks over two processes against one",
                    "python -m benchmarks.bench_distributed",
                    ["config", "N", "depths", "repeat", "psfs_per_s", "peak_mb_each",
                     "first_s"]),
}

NOT_RECORDED = ["bench_propagate", "bench_retrieval", "bench_psf", "bench_deconvolve",
                "bench_grad", "bench_fft", "bench_overhead", "bench_cli_memory",
                "bench_real_data", "bench_fig6_seeds", "bench_scene_psf",
                "bench_full_resolution"]
"""Workloads whose results are not committed: the pages that quote them name the
command, and running it writes the JSON this page is generated from."""

HEADER = """# Benchmark results

Generated by `python -m benchmarks.results_md` from `benchmarks/results/*.json`; each
section names the command that wrote its JSON (`python -m benchmarks.run` runs them
all). The machine is a shared 2-core CPU VM with no GPU: times are upper bounds, and
ratios between candidates timed in the same run are what carry over to other machines.
How each workload times and what it compares: the module docstring of
`benchmarks/bench_<name>.py`."""


def _cell(value) -> str:
    """A table cell: floats to 4 significant figures, lists as their range."""
    if isinstance(value, bool) or value is None:
        return "" if value is None else str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list) and value and all(isinstance(v, (int, float)) for v in value):
        return f"{_cell(float(min(value)))}–{_cell(float(max(value)))}"
    return str(value).replace("|", "/").replace("\n", " ")


def _table(rows: list[dict], columns: list[str] | None) -> str:
    if columns is None:
        columns = [k for k, v in rows[0].items() if not isinstance(v, (dict, list))]
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def _machine(m: dict) -> str:
    load = m.get("loadavg") or [float("nan")]
    libs = ", ".join(f"{k} {m[k]}" for k in ("jax", "numpy", "scipy") if m.get(k))
    return (f"Ran on {m.get('cpus', '?')} CPUs at load {load[0]:.1f} (1-minute average "
            f"at the end), Python {m.get('python', '?')}, {libs}.")


def section(name: str, record: dict) -> str:
    """The Markdown section of one results JSON."""
    title, command, columns = SECTIONS.get(
        name, (name, f"python -m benchmarks.bench_{name}", None))
    parts = [f"## {title}", "", f"`{command}` → `benchmarks/results/{name}.json`. "
             + _machine(record.get("machine", {}))]
    rows = record.get("rows") or []
    if rows:
        parts += ["", _table(rows, columns)]
    if record.get("claim"):
        parts += ["", f"Verdict: {record['claim']}"]
    return "\n".join(parts)


def render(results: Path = RESULTS) -> str:
    """The whole page from the JSON files in ``results``."""
    records = {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}
    order = [n for n in SECTIONS if n in records] + sorted(set(records) - set(SECTIONS))
    missing = ", ".join(f"`python -m benchmarks.{b}`" for b in NOT_RECORDED)
    parts = [HEADER] + [section(n, records[n]) for n in order] + [
        "## Workloads without a committed result\n\n" + missing + "."]
    return "\n\n".join(parts) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true",
                   help="exit 1 if RESULTS.md differs from what would be written")
    args = p.parse_args(argv)
    text = render()
    if args.check:
        same = PAGE.read_text() == text
        print("RESULTS.md is current" if same else
              "RESULTS.md is stale: run python -m benchmarks.results_md")
        return 0 if same else 1
    tmp = PAGE.with_suffix(".md.tmp")
    tmp.write_text(text)
    tmp.replace(PAGE)
    print(f"wrote {PAGE}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
