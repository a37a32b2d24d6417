"""Write ``benchmarks/RESULTS.md`` from the recorded results, ``benchmarks/results/*.json``.

    python -m benchmarks.results_md            # rewrite RESULTS.md
    python -m benchmarks.results_md --check    # exit 1 if RESULTS.md is not what it writes

One section per JSON file, in :data:`SECTIONS` order (others after, by name): the
command that wrote it, when, on which machine, at what load and with which versions
(:func:`benchmarks.harness.write_json` records them), a table of its rows and the
workload's own verdict when it records one; last, the benchmarks of
``benchmarks/bench_*.py`` that have no result yet. RESULTS.md holds the current results
only; a benchmark run rewrites its JSON, and this command the page.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from benchmarks.harness import PEERS, RESULTS

PAGE = Path(__file__).resolve().parent / "RESULTS.md"
BENCH_DIR = Path(__file__).resolve().parent

DESIGN_BOUNDS_COLUMNS = ["diffuser", "truth_max_correlation", "psnr_db",
                         "psnr_db_exact_psfs", "psnr_db_noiseless", "depth_blind_psnr_db",
                         "error_on_sources", "error_other_planes", "error_elsewhere",
                         "resolved_dz_mm", "finer_resolved_dz_mm", "design_s"]
"""The columns of a `bench_design_3d` run with ``--bounds`` and ``--two-point-depths``."""

SECTIONS = {
    # JSON name: (title, command, columns of the table: None for every scalar column).
    # The command is the JSON's own ``command_line`` where it records one; the one
    # given here stands for results recorded before the harness kept command lines.
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
    "bench_3d_field": ("3-D from one capture: the camera's off-axis terms fitted to its light "
                       "profiles, and the volumes of each footprint model",
                       "python -m benchmarks.bench_3d_field",
                       ["run", "iterations", "sparsity", "aperture_distance_mm",
                        "acceptance_exponent", "p_q2_per_px2", "vignetting_exponent",
                        "row_misfit", "column_misfit", "light", "slope", "rms", "lit_rms",
                        "dim_share", "axial_width", "outside", "residual", "seconds",
                        "meets"]),
    "bench_3d_convergence": ("3-D from one capture: the solve's convergence by iteration "
                             "count, over-relaxation and the penalties' start",
                             "python -m benchmarks.bench_3d_convergence",
                             ["setting", "iterations", "seconds", "residual", "objective",
                              "split_gap", "side_slope", "side_rms", "side_axial_width",
                              "side_outside", "diffcam_rms", "diffcam_outside", "own_rms",
                              "own_outside"]),
    "psf": ("PSF stacks: PSFs per second and working memory against a numpy loop and peers",
            "python -m benchmarks.bench_psf",
            ["N", "candidate", "depths", "ms_per_psf", "psf_per_s", "x_fresnel_tf",
             "fresnel_tf_ms", "working_mb_8", "working_mb_all", "xla_temp_mb", "loadavg"]),
    "propagate": ("One propagation step against the FFT pair and the FFT libraries",
                  "python -m benchmarks.bench_propagate",
                  ["N", "candidate", "median_ms", "limit_ms", "x_jax_fft_pair",
                   "x_best_fft_lib", "first_call_ms", "repeats"]),
    "grad_xla": ("Reverse mode against the forward pass, both PSF paths",
                 "python -m benchmarks.bench_grad",
                 ["N", "path", "forward_ms", "value_and_grad_ms", "ratio", "floor",
                  "forward_temp_mb", "grad_temp_mb", "memory_ratio", "hand_ratio",
                  "plain_ratio", "hand_grad_error"]),
    "fft": ("CPU FFT: diffcam's seam (XLA and FFTW) against pyFFTW and the FFT libraries",
            "python -m benchmarks.bench_fft",
            ["N", "row", "candidate", "ms", "pyfftw_ms", "vs_pyfftw", "xla_ms", "speedup",
             "ok", "loadavg"]),
    "field": ("A PSF that changes across the field: the low-rank model against a NumPy "
              "reference, and its cost per rank in ADMM-TV",
              "python -m benchmarks.bench_field",
              ["part", "K", "model", "forward_rel_err", "adjoint_rel_err", "diffcam_s",
               "numpy_s", "speedup", "admm_s_per_it", "cost_ratio", "fwd_adj_s",
               "fwd_adj_ratio", "temp_mb", "argument_mb"]),
    "field_truth": ("A PSF that changes across the field: a per-point known truth from "
                    "the engine, with a stop away from the diffuser and a pixel response",
                    "python -m benchmarks.bench_field_truth",
                    ["half", "field_deg", "stop_mm", "p", "rank_1pct", "rank_0p1pct", "K",
                     "psnr_shift_invariant", "psnr_flat_field", "psnr_field_model",
                     "gain_db", "seconds"]),
    "field_truth_3d": ("A PSF that changes across the field, in 3-D: a per-point known "
                       "truth over three depths, reconstructed as a volume",
                       "python -m benchmarks.bench_field_truth --depths 10,15,30 "
                       "--spacing 3 --halves 12,24 --stops 0,0.1,0.3 --exponents 0,40 "
                       "--grid 256 --aperture 0.25 --iterations 1000",
                       ["half", "field_deg", "stop_mm", "p", "rank_1pct", "rank_0p1pct",
                        "K", "psnr_shift_invariant", "psnr_flat_field",
                        "psnr_field_model", "gain_db", "psnr_depth_blind", "seconds"]),
    "peers": ("PSF stacks beside the JAX optics peers (chromatix, dLux): forward and "
              "value_and_grad, time and peak memory",
              "python -m benchmarks.bench_peers --chromatix-python /path/to/python3.12",
              ["kind", "N", "depths", "candidate", "median_s", "x_forward", "peak_mb",
               "worst_1mp", "repeats", "first_s", "load", "status"]),
    "distributed": ("PSF stacks over two processes against one",
                    "python -m benchmarks.bench_distributed",
                    ["config", "N", "depths", "repeat", "psfs_per_s", "peak_mb_each",
                     "first_s"]),
    "overhead": ("Per-call overhead on small grids: each public call against the same "
                 "computation fused in one `jax.jit`",
                 "python -m benchmarks.bench_overhead", None),
    "cli_memory": ("Peak memory of `diffcam psf` against the number of depths",
                   "python -m benchmarks.bench_cli_memory", None),
    "real_data": ("The README's real-data commands: wall time, peak memory and scores, "
                  "against Richardson–Lucy at 150 iterations",
                  "python -m benchmarks.bench_real_data", None),
    "real_data_defaults": ("The real-data defaults: solvers and iteration counts on the hand",
                           "python -m benchmarks.bench_real_data --defaults", None),
    "full_resolution": ("A full-size capture through `diffcam reconstruct`'s defaults, "
                        "against the 4× box-averaged pair",
                        "python -m benchmarks.bench_full_resolution --full DIR", None),
    "retrieval": ("Phase retrieval: Gerchberg–Saxton iterations per second against numpy "
                  "and scipy.fft, and time to a phase Pearson",
                  "python -m benchmarks.bench_retrieval", None),
    "deconvolve": ("Richardson–Lucy against scikit-image, and ADMM-TV on the tutorial pair",
                   "python -m benchmarks.bench_deconvolve", None),
    "scene_psf": ("The paper's Table 1 on real data: a PSF calibrated from scenes, every "
                  "solver scored on held-out captures",
                  "python -m benchmarks.bench_scene_psf", None),
    "design": ("Diffuser design: the largest cross-depth PSF correlation at the start, "
               "after the design and for unoptimised baselines, and the cost",
               "python -m benchmarks.bench_design",
               ["surface", "seed", "sparsity_weight", "steps", "start", "design", "baseline",
                "baseline_is", "held_out_start", "held_out_design", "held_out_baseline",
                "spread_start", "spread_design", "height_um", "wall_s", "wall_per_step_s"]),
    "design_peers": ("Diffuser design: one step beside the same step with chromatix's and "
                     "dLux's PSFs",
                     "python -m benchmarks.bench_design_peers --chromatix-python "
                     "/path/to/python3.12",
                     ["candidate", "N", "depths", "step_s", "x_design", "peak_mb", "first_s",
                      "loss", "grad_1mp", "load"]),
    "design_fidelity": ("Diffuser design: the neighbouring depths' PSF correlation with "
                        "the high-fidelity simulator's effects one at a time",
                        "python -m benchmarks.bench_design_fidelity",
                        ["diffuser", "model", "box", "none", "grid", "bandwidth", "source",
                         "all but grid", "all but bandwidth", "all but source", "all"]),
    **{name: (f"Diffuser design judged by 3-D reconstruction of held-out volumes{size}",
              f"python -m benchmarks.bench_design_3d{args}",
              ["diffuser", "max_correlation", "psnr_db", "psnr_per_scene", "resolved_dz_mm",
               "tau", "sparsity", "design_s", "reconstruct_s"])
       for name, size, args in (
           ("design_3d", ", 128² over 8 depths, measured calibration", ""),
           ("design_3d_1000_photons", ", 1000 photons per pixel, both objectives",
            " --photons 1000 --weights 0.1 0 --no-lenslets --end-to-end-steps 60 "
            "--name design_3d_1000_photons"),
           ("design_3d_10000_photons", ", 10000 photons per pixel",
            " --photons 10000 --weights 0.1 0 --no-lenslets --name design_3d_10000_photons"),
           ("design_3d_10000_photons_model_psfs", ", 10000 photons per pixel, model PSFs",
            " --photons 10000 --calibration model --weights 0.1 0 --no-lenslets "
            "--name design_3d_10000_photons_model_psfs"),
           ("design_3d_hf_design", ", designed through broadband disc-source PSFs",
            " --design-model high-fidelity --weights 0.1 0 --no-lenslets "
            "--name design_3d_hf_design"),
           ("design_3d_10000_photons_hf_design", ", 10000 photons per pixel, designed "
            "through broadband disc-source PSFs", " --photons 10000 --design-model "
            "high-fidelity --weights 0.1 0 --no-lenslets --figure docs/design_3d.png "
            "--name design_3d_10000_photons_hf_design"),
           ("design_3d_256", ", 256² over 16 depths, model PSFs", " --n 256 --depths 16 "
            "--steps 300 --scenes 3 --iterations 100 --calibration model "
            "--name design_3d_256"),
           ("design_3d_model_truth", ", captures made with the solver's own PSFs (no "
            "model error)", " --steps 300 --weights 0.1 0 --truth model --calibration "
            "model --name design_3d_model_truth"),
           ("design_3d_tuned", ", TV and L1 weights chosen per diffuser on a training "
            "scene, model PSFs", " --tune --calibration model --name design_3d_tuned"),
           ("design_3d_256_model_truth", ", 256² over 16 depths, captures made with the "
            "solver's own PSFs", " --n 256 --depths 16 --steps 300 --scenes 3 "
            "--iterations 100 --truth model --calibration model --weights 0.1 0 "
            "--no-lenslets --name design_3d_256_model_truth"),
           ("design_3d_4_depths", ", 4 depths over 10–60 mm, model PSFs",
            " --depths 4 --calibration model --name design_3d_4_depths"),
           ("design_3d_near", ", 8 depths over 5–20 mm, model PSFs",
            " --near 5 --far 20 --calibration model --name design_3d_near"),
           ("design_3d_1000_photons_random_seeds", ", 1000 photons per pixel, seven random "
            "surfaces", " --photons 1000 --weights 0.1 --no-lenslets --random-seeds 6 "
            "--name design_3d_1000_photons_random_seeds"),
           ("design_3d_1000_photons_10um_source", ", 1000 photons per pixel, a source of "
            "10 µm radius", " --photons 1000 --weights 0.1 0 --no-lenslets --source-radius "
            "10 --name design_3d_1000_photons_10um_source"),
           ("design_3d_end_to_end", ", the end-to-end objective beside depth "
            "discrimination, model PSFs", " --weights 0.1 --no-lenslets "
            "--end-to-end-steps 60 --calibration model --name design_3d_end_to_end"))},
    **{f"design_3d_1000_photons_aperture_{name}": (
        f"Diffuser design judged by 3-D reconstruction of held-out volumes, 1000 photons "
        f"per pixel, aperture radius {label}",
        f"python -m benchmarks.bench_design_3d --photons 1000 --no-lenslets --random-seeds "
        f"6 {args} --name design_3d_1000_photons_aperture_{name}",
        ["diffuser", "max_correlation", "truth_max_correlation", "psnr_db", "psnr_per_scene",
         "resolved_dz_mm", "design_s", "reconstruct_s"])
       for name, label, args in (
           ("35", "0.35 of the frame width", "--weights 0.1 0 --aperture-fraction 0.35"),
           ("45", "0.45 of the frame width", "--weights 0.1 0 --aperture-fraction 0.45"),
           ("45_15um", "0.45 of the frame width, features ≥ 15 µm",
            "--weights 0.1 0 --aperture-fraction 0.45 --feature-size 15"),
           ("45_4um", "0.45 of the frame width, heights 0–4 µm",
            "--weights 0.1 0 --aperture-fraction 0.45 --height-max 4"),
           ("45_truth_design", "0.45 of the frame width, designed through the truth's PSFs",
            "--weights 0.1 --aperture-fraction 0.45 --design-model truth"),
           ("35_truth_design", "0.35 of the frame width, designed through the truth's PSFs",
            "--weights 0.1 --aperture-fraction 0.35 --design-model truth"),
           ("45_truth_end_to_end", "0.45 of the frame width, both objectives through the "
            "truth's PSFs", "--weights 0.1 --aperture-fraction 0.45 --design-model truth "
            "--end-to-end-steps 60"),
           ("45_hf_design", "0.45 of the frame width, designed through broadband "
            "disc-source PSFs without pixel integration",
            "--weights 0.1 --aperture-fraction 0.45 --design-model high-fidelity"))},
    "design_3d_1000_photons_aperture_45_hf_design_25um": (
        "Diffuser design judged by 3-D reconstruction of held-out volumes, 1000 photons per "
        "pixel, aperture radius 0.45 of the frame width, designed through broadband PSFs of "
        "a 25 µm source (the truth's: 50 µm) without pixel integration",
        "python -m benchmarks.bench_design_3d --photons 1000 --weights 0.1 --no-lenslets "
        "--design-model high-fidelity --design-source-radius 25 --aperture-fraction 0.45 "
        "--name design_3d_1000_photons_aperture_45_hf_design_25um",
        ["diffuser", "max_correlation", "truth_max_correlation", "psnr_db", "psnr_per_scene",
         "resolved_dz_mm", "design_s", "reconstruct_s"]),
    "design_3d_1000_photons_aperture_45_truth_design_bounds": (
        "The same at 0.45 on 8 scenes, a two-point test on 22 depths and what bounds the "
        "volume PSNR",
        "python -m benchmarks.bench_design_3d --photons 1000 --no-lenslets --weights 0.1 "
        "--aperture-fraction 0.45 --design-model truth --scenes 8 --two-point-depths 22 "
        "--bounds --figure docs/design_3d_aperture.png "
        "--name design_3d_1000_photons_aperture_45_truth_design_bounds",
        DESIGN_BOUNDS_COLUMNS),
    "design_3d_1000_photons_truth_design": (
        "Diffuser design judged by 3-D reconstruction of held-out volumes, 1000 photons per "
        "pixel, designed through the truth's PSFs (light, source, pixel integration)",
        "python -m benchmarks.bench_design_3d --photons 1000 --design-model truth "
        "--weights 0.1 0 --name design_3d_1000_photons_truth_design",
        ["diffuser", "max_correlation", "truth_max_correlation", "psnr_db", "psnr_per_scene",
         "resolved_dz_mm", "tau", "sparsity", "design_s", "reconstruct_s"]),
    "design_3d_1000_photons_truth_design_tuned": (
        "The same, TV and L1 weights chosen per diffuser on a training scene",
        "python -m benchmarks.bench_design_3d --photons 1000 --design-model truth "
        "--weights 0.1 --no-lenslets --tune --name design_3d_1000_photons_truth_design_tuned",
        ["diffuser", "max_correlation", "truth_max_correlation", "psnr_db", "psnr_per_scene",
         "resolved_dz_mm", "tau", "sparsity", "design_s", "reconstruct_s"]),
    "design_3d_1000_photons_truth_end_to_end": (
        "Diffuser design judged by 3-D reconstruction of held-out volumes, 1000 photons per "
        "pixel, both objectives through the truth's PSFs, a two-point test on 22 depths and "
        "what bounds the volume PSNR",
        "python -m benchmarks.bench_design_3d --photons 1000 --design-model truth "
        "--weights 0.1 --no-lenslets --end-to-end-steps 60 --two-point-depths 22 --bounds "
        "--name design_3d_1000_photons_truth_end_to_end",
        DESIGN_BOUNDS_COLUMNS),
    "scene_psf_full": ("The same at the published 270 × 480: one PSF and a field-dependent "
                       "PSF, scored inside the monitor picture too",
                       "python -m benchmarks.bench_scene_psf --source DIR --folds … "
                       "--pairs-used 6 --solvers admm fista --name scene_psf_full_…, then "
                       "--combine", None),
    "scene_psf_cli": ("The same fold through the command line: `diffcam calibrate-psf` and "
                      "`diffcam reconstruct` as a user runs them, beside the benchmark's rows",
                      "python -m benchmarks.bench_scene_psf --source DIR --folds im43 "
                      "--via-cli RUNDIR --name scene_psf_cli",
                      ["pair", "model", "method", "psnr", "ssim", "pearson", "psnr_picture",
                       "ssim_picture", "reconstruct_wall_s", "calibration_run", "command"]),
    "scene_psf_seams": ("The fitted PSF's horizontal seams: where they sit as the sensor is "
                        "cut, and the border taper that removes them",
                        "python -m benchmarks.bench_scene_psf_seams", None),
    "fig6_seeds": ("The demo's Fig. 6 calibration over capture-noise seeds",
                   "python -m benchmarks.bench_fig6_seeds", None),
}


EXTRA_TABLES = {"real_data": ["scores"], "scene_psf": ["summary"], "design": ["cost", "large"],
                "scene_psf_full": ["summary"], "scene_psf_cli": ["comparison"],
                **{f"design_3d{v}": ["gains"] for v in (
                    "", "_256", "_model_truth", "_tuned", "_4_depths", "_near",
                    "_256_model_truth", "_end_to_end", "_1000_photons", "_10000_photons",
                    "_hf_design", "_10000_photons_hf_design", "_10000_photons_model_psfs",
                    "_1000_photons_truth_design", "_1000_photons_truth_design_tuned",
                    "_1000_photons_truth_end_to_end", "_1000_photons_10um_source")},
                "design_3d_1000_photons_random_seeds": ["gains", "random_surfaces_psnr_db"]}
"""Keys of a results JSON besides its rows that the page shows as tables too: a dict
as measure and value, a list of dicts as rows."""


def benchmarks(bench_dir: Path = BENCH_DIR) -> list[str]:
    """The benchmark modules, ``bench_<name>`` for every ``benchmarks/bench_*.py``."""
    return sorted(p.stem for p in bench_dir.glob("bench_*.py"))


def benchmark_of(name: str, record: dict, modules: list[str]) -> str | None:
    """The benchmark module that wrote results JSON ``name``: as the JSON records it, or
    for results recorded before the harness kept it, the module whose name the JSON's
    starts with (``stack_fit_lbfgs`` → ``bench_stack_fit``; the longest such)."""
    if record.get("benchmark"):
        return record["benchmark"]
    stem = name.removeprefix("bench_")
    fits = [m for m in modules
            if stem == m.removeprefix("bench_") or stem.startswith(m.removeprefix("bench_") + "_")]
    return max(fits, key=len) if fits else None


HEADER = """# Benchmark results

Generated by `python -m benchmarks.results_md` from `benchmarks/results/*.json`; each
section names the command that wrote its JSON (`python -m benchmarks.run` runs the
workloads of its `WORKLOADS` list in one go), when it ran, the machine, the load
average at its start and end and the versions. The machine is a shared 2-core CPU VM
with no GPU: times are upper bounds, and ratios between candidates timed in the same
run are what carry over to other machines.
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
    """A Markdown table of ``rows``. With ``columns`` None: every scalar key, in order
    of appearance, and a table of its own for each run of rows of another kind (rows
    whose first key differs, as a benchmark's speed rows and its accuracy rows)."""
    if columns is None:
        groups = []
        for r in rows:
            if groups and next(iter(r), None) == next(iter(groups[-1][0]), None):
                groups[-1].append(r)
            else:
                groups.append([r])
        if len(groups) > 1:
            return "\n\n".join(_table(g, None) for g in groups)
        columns = list(dict.fromkeys(k for r in rows for k, v in r.items()
                                     if not isinstance(v, (dict, list))))
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    lines += ["| " + " | ".join(_cell(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def _load(values) -> str:
    return "/".join(f"{v:.1f}" for v in values) if values else "not recorded"


def _provenance(record: dict) -> str:
    """When, where, at what load and with which versions a result ran."""
    m = record.get("machine", {})
    if "versions" not in record:  # recorded before the harness kept the whole record
        libs = ", ".join(f"{k} {m[k]}" for k in ("jax", "numpy", "scipy") if m.get(k))
        load = m.get("loadavg") or [float("nan")]
        return (f"Ran on {m.get('cpus', '?')} CPUs at load {load[0]:.1f} (1-minute "
                f"average at the end), Python {m.get('python', '?')}, {libs}; this JSON "
                "does not record its date, command line, CPU model, memory, load at the "
                "start, or jaxlib and diffcam versions.")
    v, date, load, git = record["versions"], record["date"], record["load"], record.get("git")
    core = ", ".join(f"{k} {v[k]}" for k in ("python", "jax", "jaxlib", "numpy", "diffcam"))
    peers = ", ".join(f"{k} {v[k]}" for k in PEERS if v.get(k)) or "none"
    at = ""
    if git:
        changed = git.get("modified") or []
        at = f" at commit {git['commit'][:10]}" + (
            f" (tracked files changed: {', '.join(changed)})" if changed else "")
    start, end = (date.get("start") or "?"), (date.get("end") or "?")
    return (f"Ran {start} → {end}{at}. Machine: {m.get('cpu_model')}, "
            f"{m.get('cpus')} cores, {m.get('memory_gb')} GiB, {m.get('platform')}. "
            f"Load average (1/5/15 min): {_load(load.get('start'))} at the start, "
            f"{_load(load.get('end'))} at the end. Versions: {core}; peers imported: "
            f"{peers}.")


def section(name: str, record: dict, modules: list[str] | None = None) -> str:
    """The Markdown section of one results JSON (``modules``: the benchmark modules,
    :func:`benchmarks` by default)."""
    modules = benchmarks() if modules is None else modules
    module = benchmark_of(name, record, modules) or f"bench_{name}"
    title, command, columns = SECTIONS.get(
        name, (name, f"python -m benchmarks.{module}", None))
    ran = record.get("command_line") or command
    parts = [f"## {title}", "", f"`{ran}` → `benchmarks/results/{name}.json`. "
             + _provenance(record)]
    if ran.split() != command.split():
        parts[-1] += (f" The documented run is `{command}`; this result ran with the "
                      "options above.")
    rows = record.get("rows") or []
    if rows:
        parts += ["", _table(rows, columns)]
    for key in EXTRA_TABLES.get(name, []):
        extra = record.get(key)
        if isinstance(extra, dict):
            extra = [{"measure": k, "value": v} for k, v in extra.items()]
        if extra:
            parts += ["", f"`{key}`:", "", _table(extra, None)]
    if record.get("claim"):
        parts += ["", f"Verdict: {record['claim']}"]
    return "\n".join(parts)


def load_records(results: Path = RESULTS) -> dict[str, dict]:
    """Every results JSON in ``results``, by name."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}


def unrecorded(records: dict[str, dict], modules: list[str]) -> list[str]:
    """The benchmark modules that no results JSON comes from."""
    done = {benchmark_of(n, r, modules) for n, r in records.items()}
    return [m for m in modules if m not in done]


def render(results: Path = RESULTS, bench_dir: Path = BENCH_DIR) -> str:
    """The whole page from the JSON files in ``results``."""
    records = load_records(results)
    order = [n for n in SECTIONS if n in records] + sorted(set(records) - set(SECTIONS))
    modules = benchmarks(bench_dir)
    parts = [HEADER] + [section(n, records[n], modules) for n in order]
    missing = unrecorded(records, modules)
    if missing:
        parts.append("## Benchmarks without a committed result\n\n"
                     + ", ".join(f"`python -m benchmarks.{b}`" for b in missing) + ".")
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
