"""Every benchmark has a committed result and a generated section in
benchmarks/RESULTS.md, the page is what its generator writes from the committed JSON,
and every result the harness writes records its command line, dates, load, machine and
versions."""

import json
import re
import shlex
import sys
import types
from pathlib import Path

import pytest

from benchmarks import harness, results_md

ROOT = Path(__file__).resolve().parents[1]
MODULES = results_md.benchmarks()
RECORDS = results_md.load_records()
PAGE = results_md.PAGE.read_text()

# Their results are run on the branch that changes the code they measure; they are
# required here like every other benchmark.
REQUIRED = {"bench_psf", "bench_propagate", "bench_grad", "bench_fft"}


def test_the_benchmarks_are_found():
    assert len(MODULES) >= 20 and REQUIRED <= set(MODULES), MODULES


@pytest.mark.parametrize("module", MODULES)
def test_every_benchmark_has_a_committed_result_and_a_section(module):
    names = [n for n, r in RECORDS.items() if results_md.benchmark_of(n, r, MODULES) == module]
    assert names, (f"benchmarks/{module}.py has no result in benchmarks/results/: run "
                   f"python -m benchmarks.{module}, commit its JSON and run "
                   "python -m benchmarks.results_md")
    for name in names:
        assert f"→ `benchmarks/results/{name}.json`." in PAGE, f"no section for {name}.json"


def test_results_page_is_current():
    assert PAGE == results_md.render(), "stale: run python -m benchmarks.results_md"


def test_every_result_names_a_benchmark_that_exists():
    orphans = {n: results_md.benchmark_of(n, r, MODULES) for n, r in RECORDS.items()}
    orphans = {n: m for n, m in orphans.items() if m not in MODULES}
    assert not orphans, orphans


@pytest.mark.parametrize("name", [n for n, r in RECORDS.items() if "versions" in r])
def test_a_recorded_command_reruns_that_benchmark(name):
    record = RECORDS[name]
    assert re.search(rf"python -m benchmarks\.({record['benchmark']}|run)\b",
                     record["command_line"]), record["command_line"]
    assert record["date"]["start"] <= record["date"]["end"]


def test_write_json_records_the_run(tmp_path, monkeypatch):
    monkeypatch.setattr(harness, "RESULTS", tmp_path)
    path = harness.write_json("probe", [{"x": 1.5}], {"claim": "holds"})
    record = json.loads(path.read_text())
    assert record["benchmark"] == "test_benchmarks_results"
    assert record["command_line"].endswith(shlex.join(["python", *sys.orig_argv[1:]]))
    m, v = record["machine"], record["versions"]
    assert m["cpus"] >= 1 and m["memory_gb"] > 0 and m["cpu_model"]
    assert all(len(record["load"][k]) == 3 for k in ("start", "end"))
    assert record["date"]["start"] <= record["date"]["end"]
    for lib in ("python", "jax", "jaxlib", "numpy", "diffcam"):
        assert v[lib], lib
    assert set(harness.PEERS) <= set(v)
    assert record["rows"] == [{"x": 1.5}] and record["claim"] == "holds"
    with pytest.raises(ValueError, match="load"):
        harness.write_json("probe", [], {"load": 0})


def test_the_page_shows_the_run_and_lists_what_is_missing(tmp_path, monkeypatch):
    """A result written now gets a section with its load, machine and versions; a
    benchmark without a result is listed as such."""
    monkeypatch.setattr(harness, "RESULTS", tmp_path / "results")
    bench_alpha = {"__spec__": types.SimpleNamespace(name="benchmarks.bench_alpha"),
                   "harness": harness}
    exec('harness.write_json("alpha", [{"case": "a", "seconds": 0.25}])', bench_alpha)
    bench = tmp_path / "bench"
    bench.mkdir()
    for stem in ("bench_alpha", "bench_beta"):
        (bench / f"{stem}.py").write_text("")
    page = results_md.render(tmp_path / "results", bench)
    record = json.loads((tmp_path / "results" / "alpha.json").read_text())
    assert record["benchmark"] == "bench_alpha"
    load = record["load"]["start"][0]
    assert f"`{record['command_line']}` → `benchmarks/results/alpha.json`." in page
    assert f"Load average (1/5/15 min): {load:.1f}/" in page
    assert f"jaxlib {record['versions']['jaxlib']}" in page
    assert f"{record['machine']['cpus']} cores" in page
    assert "| a | 0.25 |" in page
    # the probe ran under pytest, not as the benchmark's documented command
    assert "The documented run is `python -m benchmarks.bench_alpha`;" in page
    assert page.rstrip().endswith("`python -m benchmarks.bench_beta`.")
    assert "bench_alpha`," not in page
    # a result recorded before the harness kept its command is its benchmark's all the same
    legacy = {"workload": "beta_big", "machine": {"cpus": 2, "loadavg": [3.0, 2.0, 1.0]},
              "rows": [{"case": "b"}]}
    (tmp_path / "results" / "beta_big.json").write_text(json.dumps(legacy))
    page = results_md.render(tmp_path / "results", bench)
    assert ("`python -m benchmarks.bench_beta` → `benchmarks/results/beta_big.json`. Ran on "
            "2 CPUs at load 3.0") in page
    assert "does not record its date, command line" in page
    assert "without a committed result" not in page
