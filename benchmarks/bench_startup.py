"""Start-up of the ``diffcam`` command: imports, ``--help``, and a fresh ``diffcam
predict`` of the 44-plane stack model with the compilation cache off, empty and warm.

    python -m benchmarks.bench_startup [--rounds 5] [--model MODEL.npz]

Unless ``--model`` names one, the model is fitted first: ``diffcam fit`` on the shipped
44-plane stack (``diffcam data usaf3d``), planes 5 and 27. Every case runs in a fresh
process (:func:`benchmarks.harness.run_probed`: wall time and peak RSS of the command),
one of each in turn per round, so a slow spell of the shared machine hits all alike;
medians over the rounds. ``python -c pass`` is the interpreter's own start. The
predicts: ``DIFFCAM_NO_CACHE=1``; an empty cache folder each round; a cache folder
filled by one predict before the rounds. All write the same bytes (checked).

The claim (issue #32, must-show 5): all 44 planes predicted by a fresh ``diffcam
predict`` in at most 2 s on 2 cores, with the compilation cache warm.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import markdown_table, run_probed, write_json

TARGET_S = 2.0
PLANES = "5,27"


@contextlib.contextmanager
def environment(**values):
    """``os.environ`` with ``values`` set (``None``: removed), restored after."""
    saved = {k: os.environ.get(k) for k in values}
    try:
        for k, v in values.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
        yield
    finally:
        for k, v in saved.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)


def fit_model(folder: Path) -> Path:
    """The 44-plane model of docs/stack_fit.md, fitted by the command line (its
    compilation cache off: the benchmark writes nothing to the user's cache)."""
    cli = [sys.executable, "-m", "diffcam"]
    model = folder / "model.npz"
    with environment(DIFFCAM_NO_CACHE="1"):
        subprocess.run([*cli, "data", "usaf3d", "-o", str(folder / "captures")],
                       check=True, capture_output=True)
        subprocess.run([*cli, "fit", str(folder / "captures" / "psfs"), "--planes", PLANES,
                        "-o", str(model), "--no-progress"], check=True, capture_output=True)
    return model


def cases(model: Path, folder: Path, round_: int) -> dict[str, tuple[list[str], dict]]:
    """Case name → (command, environment) for one round."""
    py, cli = [sys.executable, "-c"], [sys.executable, "-m", "diffcam"]
    predict = [*cli, "predict", str(model), "-o"]
    return {
        "python -c pass": ([*py, "pass"], {}),
        "import diffcam": ([*py, "import diffcam"], {}),
        "import diffcam.apps.cli": ([*py, "import diffcam.apps.cli"], {}),
        "diffcam --help": ([*cli, "--help"], {"XDG_CACHE_HOME": str(folder / "warm")}),
        "predict, cache off": ([*predict, str(folder / "off.tif")],
                               {"DIFFCAM_NO_CACHE": "1"}),
        "predict, empty cache": ([*predict, str(folder / "empty.tif")],
                                 {"XDG_CACHE_HOME": str(folder / f"empty{round_}")}),
        "predict, warm cache": ([*predict, str(folder / "warm.tif")],
                                {"XDG_CACHE_HOME": str(folder / "warm")}),
    }


def run(model: Path, folder: Path, rounds: int) -> list[dict]:
    """One row per case: median, min and max wall time (s) and the peak RSS (MB)."""
    base = {"DIFFCAM_NO_CACHE": None, "DIFFCAM_CACHE": None, "XDG_CACHE_HOME": None,
            "JAX_COMPILATION_CACHE_DIR": None}
    with environment(**{**base, "XDG_CACHE_HOME": str(folder / "warm")}):
        run_probed([sys.executable, "-m", "diffcam", "predict", str(model), "-o",
                    str(folder / "warm.tif")])
    records: dict[str, list[dict]] = {}
    loads = []
    for r in range(rounds):
        loads.append(os.getloadavg()[0])
        for name, (cmd, env) in cases(model, folder, r).items():
            with environment(**{**base, **env}):
                record = run_probed(cmd)
            if record["rc"]:
                raise RuntimeError(f"{name} failed ({record['rc']}): {record['stderr']}")
            records.setdefault(name, []).append(record)
    outputs = {(folder / f"{n}.tif").read_bytes() for n in ("off", "empty", "warm")}
    rows = []
    for name, runs in records.items():
        walls = [r["wall_s"] for r in runs]
        rows.append({"case": name, "median_s": statistics.median(walls),
                     "min_s": min(walls), "max_s": max(walls),
                     "peak_rss_mb": statistics.median(r["peak_bytes"] for r in runs) / 2**20,
                     "rounds": len(runs), "loadavg": statistics.median(loads)})
    if len(outputs) != 1:
        raise RuntimeError("the predicts with the cache off, empty and warm wrote "
                           "different files")
    return rows


COLUMNS = ["case", "median_s", "min_s", "max_s", "peak_rss_mb", "rounds", "loadavg"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=5, help="runs of each case")
    p.add_argument("--model", type=Path, help="a stack model (default: fit one, ~1 min)")
    args = p.parse_args(argv)
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="diffcam-bench-") as tmp:
        folder = Path(tmp)
        model = args.model or fit_model(folder)
        rows = run(model, folder, args.rounds)
    warm = next(r for r in rows if r["case"] == "predict, warm cache")["median_s"]
    off = next(r for r in rows if r["case"] == "predict, cache off")["median_s"]
    verdict = (f"a fresh `diffcam predict` of all 44 planes: {warm:.2f} s with the cache "
               f"warm ({'within' if warm <= TARGET_S else 'ABOVE'} {TARGET_S:g} s), "
               f"{off:.2f} s with it off; the three write the same file")
    print(markdown_table(rows, COLUMNS))
    print(f"- {verdict}; {time.perf_counter() - t:.0f} s in all")
    path = write_json("startup", rows, {"claim": verdict, "within_target": warm <= TARGET_S,
                                        "command": "python -m benchmarks.bench_startup"})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
