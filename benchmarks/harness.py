"""Timing harness shared by every benchmark workload.

Candidates are timed *interleaved* (one call of each in turn, repeated), so a slow
spell of the machine hits all of them alike; the first call of each is reported
separately as compile (or warm-up) time; results are medians. The machine's load
average is recorded before and after, since these machines are shared and noisy.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable

RESULTS = Path(__file__).resolve().parent / "results"


def block(x):
    """Wait for JAX results (no-op for numpy and others)."""
    if hasattr(x, "block_until_ready"):
        return x.block_until_ready()
    if isinstance(x, (tuple, list)):
        for y in x:
            block(y)
    return x


def time_interleaved(candidates: dict[str, Callable[[], object]], repeats: int = 5,
                     budget_s: float | None = None) -> dict[str, dict]:
    """Time zero-argument callables interleaved; return per-candidate statistics.

    Each candidate is called once untimed-for-the-median (its first-call time is the
    ``first_s``, i.e. compile + run for jitted code), then ``repeats`` times in
    round-robin order. A candidate whose single call exceeds ``budget_s`` is timed
    fewer times (at least once), and ``repeats`` says how many. ``output`` is what the
    first call returned, for accuracy checks beside the timing.
    """
    stats = {name: {"first_s": None, "times": []} for name in candidates}
    outputs = {}
    for name, fn in candidates.items():
        t = time.perf_counter()
        outputs[name] = block(fn())
        stats[name]["first_s"] = time.perf_counter() - t
    for _ in range(repeats):
        for name, fn in candidates.items():
            s = stats[name]
            if s["times"] and budget_s is not None and sum(s["times"]) > budget_s:
                continue
            t = time.perf_counter()
            block(fn())
            s["times"].append(time.perf_counter() - t)
    out = {}
    for name, s in stats.items():
        times = s["times"] or [s["first_s"]]
        out[name] = {"median_s": statistics.median(times), "min_s": min(times),
                     "times_s": times, "first_s": s["first_s"], "repeats": len(s["times"]),
                     "output": outputs[name]}
    return out


def time_against(unit: Callable[[], object], candidates: dict[str, Callable[[], object]],
                 repeats: int = 5, budget_s: float | None = None) -> dict[str, dict]:
    """:func:`time_interleaved` of each candidate in alternation with ``unit`` alone.

    Each candidate's statistics gain ``unit_s``, the unit's median in its own run, so
    ``median_s / unit_s`` is a paired ratio. Here fresh buffers page-fault at a cost
    that depends on what ran just before (a candidate that allocates and frees
    gigabytes slows the next one's allocations), so a ratio taken from one shared
    round-robin mixes in the neighbours. The key ``None`` holds the unit's statistics
    over all the runs (median of medians, repeats summed).
    """
    out, units = {}, []
    for name, fn in candidates.items():
        t = time_interleaved({None: unit, name: fn}, repeats=repeats, budget_s=budget_s)
        out[name] = dict(t[name], unit_s=t[None]["median_s"])
        units.append(t[None])
    unit_s = statistics.median(u["median_s"] for u in units)
    out[None] = {"median_s": unit_s, "unit_s": unit_s, "first_s": units[0]["first_s"],
                 "repeats": sum(u["repeats"] for u in units)}
    return out


PEERS = ("scipy", "skimage", "pyfftw", "torch", "LightPipes", "diffractsim", "scico",
         "optimistix", "optax", "jaxopt", "equinox", "lineax")
"""Libraries a benchmark compares against or builds on: their versions are recorded
(and shown on RESULTS.md) when the benchmark imported them."""

_START = {"date": None, "loadavg": None}


def _mark_start() -> None:
    """Note the time and load now: where the next result's run began."""
    _START.update(date=_utc_now(), loadavg=list(os.getloadavg()))


def _utc_now() -> str:
    from datetime import datetime, timezone
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _cpu_model() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def _memory_gb() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return round(int(line.split()[1]) * 1024 / 2**30, 2)
    except (OSError, ValueError):
        pass
    return None


def _version(module: str) -> str | None:
    """The version of an imported module (its distribution's where it has none)."""
    m = sys.modules.get(module)
    if m is None:
        return None
    v = getattr(m, "__version__", None)
    if v is None:
        from importlib import metadata
        for dist in metadata.packages_distributions().get(module, []):
            try:
                return metadata.version(dist)
            except metadata.PackageNotFoundError:
                pass
    return None if v is None else str(v)


def machine() -> dict:
    """The machine: CPU model, logical cores, memory (GiB), platform."""
    return {"cpu_model": _cpu_model(), "cpus": os.cpu_count(), "memory_gb": _memory_gb(),
            "platform": platform.platform()}


def versions() -> dict:
    """Python, JAX, jaxlib, NumPy and diffcam, and every peer of :data:`PEERS` that
    this process imported (its value ``None`` when it did not)."""
    import jax
    import jaxlib
    import numpy
    from diffcam.core.version import installed_version
    out = {"python": sys.version.split()[0], "jax": jax.__version__,
           "jaxlib": jaxlib.__version__, "numpy": numpy.__version__,
           "diffcam": installed_version()}
    out.update({peer: _version(peer) for peer in PEERS})
    return out


def _git() -> dict | None:
    """The commit the benchmark ran at, and the tracked files changed since it."""
    import subprocess
    root = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=root, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode:
        return None
    return {"commit": head.stdout.strip(),
            "modified": [line[3:] for line in dirty.stdout.splitlines()]}


def command_line() -> str:
    """The command that started this process, as typed (``python -m benchmarks.…``),
    prefixed by the settings of the environment that change what runs (``JAX_*``,
    ``XLA_*``, ``DIFFCAM_*``, ``OMP_NUM_THREADS``)."""
    import shlex
    env = [f"{k}={shlex.quote(v)}" for k, v in sorted(os.environ.items())
           if k.startswith(("JAX_", "XLA_", "DIFFCAM_")) or k == "OMP_NUM_THREADS"]
    argv = list(getattr(sys, "orig_argv", None) or [sys.executable, *sys.argv])
    argv[0] = "python"
    return " ".join(env + [shlex.join(argv)])


PROVENANCE = ("workload", "benchmark", "command_line", "date", "load", "machine",
              "versions", "git")
"""The keys :func:`write_json` writes beside the rows; a workload's ``extra`` may not
use them."""


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    """A Markdown table of ``rows`` (dicts) in ``columns`` order; floats to 3 s.f."""
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3g}"
        return "" if v is None else str(v)
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(c)) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def write_json(name: str, rows: list[dict], extra: dict | None = None) -> Path:
    """Write ``benchmarks/results/<name>.json``: the rows, the workload's ``extra`` and
    the record of the run (:data:`PROVENANCE`): the benchmark module that called, the
    command line, the dates (UTC) and 1-, 5- and 15-minute load averages at its start
    and now, the machine (:func:`machine`), the versions (:func:`versions`) and the git
    commit. The start is when this module was imported, or when the previous result
    of this process was written (``benchmarks.run`` runs several workloads in one)."""
    clash = set(extra or {}) & set(PROVENANCE + ("rows",))
    if clash:
        raise ValueError(f"extra keys {sorted(clash)} would hide the run's record")
    caller = sys._getframe(1).f_globals
    spec = caller.get("__spec__")
    module = spec.name if spec is not None else Path(caller.get("__file__", "?")).stem
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    record = {"workload": name, "benchmark": module.rsplit(".", 1)[-1],
              "command_line": command_line(),
              "date": {"start": _START["date"], "end": _utc_now()},
              "load": {"start": _START["loadavg"], "end": list(os.getloadavg())},
              "machine": machine(), "versions": versions(), "git": _git(),
              "rows": rows, **(extra or {})}
    path.write_text(json.dumps(record, indent=2, default=str))
    _mark_start()
    return path


def optional_import(name: str, note: list[str]):
    """Import a peer, or record a note that it is missing and return None."""
    try:
        return __import__(name)
    except Exception as e:  # a missing peer is skipped, never fatal
        note.append(f"{name} not available ({type(e).__name__}: {e}); skipped")
        return None


_PROBE = """
import json, resource, subprocess, sys, time
t = time.perf_counter()
done = subprocess.run(sys.argv[1:], capture_output=True, text=True)
peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024  # Linux: KiB
print(json.dumps({"rc": done.returncode, "wall_s": time.perf_counter() - t,
                  "peak_bytes": peak, "stdout": done.stdout[-400:],
                  "stderr": done.stderr[-2000:]}))
"""


def run_probed(cmd: list[str], cwd=None, timeout: float = 3600) -> dict:
    """Run ``cmd`` in a fresh probe process whose only child it is, so that
    ``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` is the command's own peak RSS.
    Returns ``{"rc", "wall_s", "peak_bytes", "stdout", "stderr"}`` (the last 400 and
    2000 characters of the outputs)."""
    import json
    import subprocess
    import sys

    probe = subprocess.run([sys.executable, "-c", _PROBE, *cmd], capture_output=True,
                           text=True, timeout=timeout,
                           cwd=cwd or Path(__file__).resolve().parents[1])
    return json.loads(probe.stdout.strip().splitlines()[-1])


_mark_start()
