"""Run the benchmark workloads, print Markdown tables and write JSON.

    python -m benchmarks.run                   # every workload, default sizes
    python -m benchmarks.run propagate psf     # some of them
    python -m benchmarks.run --quick           # small sizes, for a smoke test

Each workload lives in ``benchmarks/bench_<name>.py`` and exposes ``main(argv)``;
results go to ``benchmarks/results/<name>.json`` with the machine's load recorded.
Peers that are not installed (``pip install -e '.[bench]'``) are skipped with a note.
"""

from __future__ import annotations

import argparse
import importlib

WORKLOADS = ["propagate", "psf", "retrieval", "deconvolve", "stack_fit", "cli_memory",
             "overhead", "real_data", "fft", "grad", "fig6_seeds", "peers"]
QUICK = {"propagate": ["--sizes", "512", "1024"],
         "psf": ["--sizes", "512", "--depths", "8", "--no-memory"],
         "retrieval": ["--sizes", "512", "--repeats", "2"],
         "deconvolve": ["--quick"],
         "stack_fit": ["--quick"],
         "cli_memory": ["--quick"],
         "overhead": ["--sizes", "128", "--repeats", "5"],
         "real_data": ["--downsample", "4"],
         "grad": ["--sizes", "256", "--repeats", "3"],
         "fig6_seeds": ["--seeds", "0"],
         "peers": ["--sizes", "256", "--depths", "4", "--grad-sizes", "256",
                   "--grad-depths", "4", "8", "--repeats", "2", "--name", "peers_quick"],
         "fft": ["--sizes", "512", "--repeats", "3", "--workload-sizes", "256", "--rounds", "1"]}


def main(argv=None):
    p = argparse.ArgumentParser(description="diffcam benchmarks")
    p.add_argument("workloads", nargs="*", default=WORKLOADS, choices=WORKLOADS + [[]])
    p.add_argument("--quick", action="store_true", help="small sizes only")
    args = p.parse_args(argv)
    for name in args.workloads or WORKLOADS:
        try:
            module = importlib.import_module(f"benchmarks.bench_{name}")
        except ModuleNotFoundError as e:
            print(f"## {name}: not available ({e})")
            continue
        print(f"## {name}")
        module.main(QUICK.get(name, []) if args.quick else [])


if __name__ == "__main__":
    main()
