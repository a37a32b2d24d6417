"""Peak memory of ``diffcam psf`` against the number of depths: the stack streams to disk.

    python -m benchmarks.bench_cli_memory [--size 512] [--depths 26 101 401] [--quick]

A random diffuser (:func:`diffcam.model.random_diffuser`, 5 µm pitch, 532 nm, aperture
radius 0.3·N·dx) is saved as a phase file with :func:`diffcam.calibrate.save_phase`; then
``python -m diffcam psf PHASE --z1 22mm:30mm:STEP --z2 1mm -o out.tif`` runs once per
depth count, each in a fresh probe process whose only child is the CLI, so
``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` is the CLI's own peak RSS (MB:
2**20 bytes). The claim: the peak stays within 10 % from the fewest to the most depths,
while the TIFF written grows with them (N² float32 per depth).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks.harness import markdown_table, run_probed, write_json

LAM, DX, Z2, Z1_RANGE = 532e-9, 5e-6, 1e-3, (22e-3, 30e-3)
FLAT = 0.10   # the claim: peak RSS within 10 % across depth counts

def write_phase(path: Path, n: int) -> None:
    """A random diffuser on an n² grid as a diffcam phase file (``.npz``)."""
    from diffcam.calibrate import PhaseFile, save_phase
    from diffcam.model import random_diffuser

    phase = np.asarray(random_diffuser(jax.random.key(0), (n, n), DX, LAM))
    save_phase(path, PhaseFile(phase, DX, LAM, 0.3 * n * DX, {"made_by": __name__}))


def depth_range(count: int) -> str:
    """The ``--z1`` range of ``count`` depths over :data:`Z1_RANGE`, in µm (end included)."""
    lo, hi = (round(z * 1e6) for z in Z1_RANGE)
    step = (hi - lo) / (count - 1)
    return f"{lo}um:{hi}um:{step:.10g}um"


def run_cli(phase: Path, out: Path, count: int) -> dict:
    """One ``diffcam psf`` run in a fresh probe; its peak RSS, wall time and output size."""
    cmd = [sys.executable, "-m", "diffcam", "psf", str(phase), "--z1", depth_range(count),
           "--z2", f"{Z2 * 1e3:g}mm", "-o", str(out)]
    record = run_probed(cmd)
    if record["rc"]:
        raise RuntimeError(f"diffcam psf failed ({record['rc']}): {record['stderr']}")
    if f"{count} PSFs" not in record["stdout"]:
        raise RuntimeError(f"expected {count} PSFs, the CLI said: {record['stdout']}")
    return {"depths": count, "peak_rss_mb": record["peak_bytes"] / 2**20,
            "wall_s": record["wall_s"], "tif_mb": out.stat().st_size / 2**20}


def run(size: int = 512, counts=(26, 101, 401)) -> list[dict]:
    """Rows of :func:`run_cli` for each depth count, with the ratio to the first's peak."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="diffcam-bench-") as tmp:
        phase = Path(tmp) / "phase.npz"
        write_phase(phase, size)
        for count in counts:
            out = Path(tmp) / f"stack_{count}.tif"
            row = {"N": size, **run_cli(phase, out, count), "loadavg": os.getloadavg()[0]}
            out.unlink()
            rows.append(row)
    for row in rows:
        row["x_first"] = row["peak_rss_mb"] / rows[0]["peak_rss_mb"]
    return rows


COLUMNS = ["N", "depths", "peak_rss_mb", "x_first", "tif_mb", "wall_s", "loadavg"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512, help="phase grid N (N² samples)")
    p.add_argument("--depths", type=int, nargs="+", default=[26, 101, 401])
    p.add_argument("--quick", action="store_true", help="256² grid, 26 and 101 depths")
    args = p.parse_args(argv)
    size, counts = (256, [26, 101]) if args.quick else (args.size, args.depths)
    t = time.perf_counter()
    rows = run(size, counts)
    peaks = [r["peak_rss_mb"] for r in rows]
    spread = max(peaks) / min(peaks) - 1
    verdict = (f"peak RSS spread {spread:.1%} over {counts[0]}–{counts[-1]} depths "
               f"({'flat' if spread <= FLAT else 'NOT flat'} within {FLAT:.0%})")
    print(markdown_table(rows, COLUMNS))
    print(f"- {verdict}; {time.perf_counter() - t:.0f} s in all")
    path = write_json("cli_memory", rows, {"claim": verdict, "flat": spread <= FLAT,
                                           "memory": "peak_rss_mb: ru_maxrss of the "
                                                     "`diffcam psf` process, 2**20 bytes"})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
