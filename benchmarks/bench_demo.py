"""``diffcam demo`` run several times: wall time, peak memory and the numbers it prints,
so that the README quotes each as the range over runs.

    python -m benchmarks.bench_demo [--runs 2] [--cpus all 1] [--grid 1024]

Each run is a fresh process (:func:`benchmarks.harness.run_probed`: the peak RSS of the
command alone) writing to its own temporary folder; ``--cpus 1`` pins a run to one core
(``taskset``), which changes how XLA splits its CPU work and so the rounding of its
reductions. The demo is seeded: runs differ only through that rounding, which the
iterative calibrations amplify.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from benchmarks.harness import markdown_table, run_probed, write_json

COLUMNS = ["cpus", "run", "wall_s", "peak_gb", "fig3_gs", "fig3_calibrated", "fig5_psf",
           "fig6_nearfar_psf", "fig6_psf", "fig9_model"]


def _numbers(metrics: dict) -> dict:
    """The demo's headline numbers from its ``metrics.json``."""
    fig5 = metrics["fig5"][-1]                      # the calibration's last stage
    fig6 = metrics["fig6"]["stages"][-1]            # calibration + one PSF
    model = [r["model"] for r in metrics["fig9"]["z2_1mm"]]
    return {"fig3_gs": metrics["fig3"]["phase_pearson_gs"],
            "fig3_calibrated": metrics["fig3"]["phase_pearson_calibrated"],
            "fig5_psf": fig5["psf_pearson"], "fig6_psf": fig6["psf_pearson"],
            "fig6_nearfar_psf": metrics["fig6"]["stages"][-2]["psf_pearson"],
            "fig9_model": sum(model) / len(model)}


def run(cpus: str, index: int, grid: int, work: Path) -> dict:
    """One ``diffcam demo`` on ``cpus`` ("all" or a count, the first cores)."""
    out = work / f"cpus{cpus}_run{index}"
    cmd = [sys.executable, "-m", "diffcam", "demo", "-o", str(out), "--grid", str(grid)]
    if cpus != "all":
        cmd = ["taskset", "-c", f"0-{int(cpus) - 1}", *cmd]
    record = run_probed(cmd, cwd=work)
    if record["rc"]:
        raise RuntimeError(f"diffcam demo failed: {record['stderr']}")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"cpus": cpus, "run": index, "wall_s": record["wall_s"],
            "peak_gb": record["peak_bytes"] / 1e9, **_numbers(metrics)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=2, help="runs per CPU setting")
    p.add_argument("--cpus", nargs="+", default=["all", "1"],
                   help="CPU settings: 'all' or a number of cores")
    p.add_argument("--grid", type=int, default=1024, help="the demo's --grid")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="diffcam-demo-") as work:
        for index in range(args.runs):
            for cpus in args.cpus:          # alternated, so a slow spell hits both
                rows.append(run(cpus, index, args.grid, Path(work)))
                print(markdown_table(rows[-1:], COLUMNS), flush=True)
    print(markdown_table(rows, COLUMNS))
    write_json("demo", rows, {"grid": args.grid, "columns": COLUMNS})


if __name__ == "__main__":
    main()
