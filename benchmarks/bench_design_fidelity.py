"""Which of the high-fidelity simulator's effects undoes a design's depth
decorrelation? The largest correlation between neighbouring depths' PSFs of
`bench_design_3d`'s diffusers, with the truth's effects switched on one at a time.

    python -m benchmarks.bench_design_fidelity   # → benchmarks/results/design_fidelity.json

The diffusers are `bench_design_3d`'s (128², 8 depths over 10–60 mm, 300 design steps
through the model's point-source PSFs, sparsity weights 0.1 and 0; the random surface
of the same limits; the regular microlens array). Each diffuser's PSFs at those depths:

- ``model``: `diffcam.model.stack.psf_stack` (the design model: one wavelength, a point
  source, the field sampled at the sensor pitch);
- ``box``: the model's PSFs convolved with one pixel's box (a pixel's integration of
  the irradiance the model samples at its centre, not of a finer field);
- `diffcam.calibrate.simulation.high_fidelity_psfs` with ``oversample`` 1 or 2 (the
  field on a 2× finer grid, the phase cubic-interpolated, integrated over each pixel),
  ``spectrum`` one line (532 nm) or three (526–538 nm), ``source_radius`` 0 or 50 µm:
  ``none`` (all off, the model through the truth's code), each alone, all but one, and
  ``all`` (the truth of `bench_design_3d`).

Per diffuser and case: the largest Pearson correlation of neighbouring depths' PSFs
(`neighbour_max`; the largest of any two depths, ρ_max, is the same pair here).
"""

from __future__ import annotations

import argparse
import time

import jax.numpy as jnp
import numpy as np

from benchmarks.bench_design import FAR, INDEX, NEAR, camera
from benchmarks.bench_design_3d import SOURCE_RADIUS, Geometry, diffusers
from benchmarks.harness import write_json
from diffcam.calibrate.simulation import HIGH_FIDELITY_SPECTRUM, high_fidelity_psfs
from diffcam.design import DesignOptions, depth_range
from diffcam.design.objective import correlation_matrix, standardised
from diffcam.design.surfaces import height_map
from diffcam.model import psf_stack

EFFECTS = ("grid", "bandwidth", "source")
"""The truth's effects: a 2× finer field integrated over each pixel, three lines,
a 50 µm disc source."""
CASES = {"none": (), "grid": ("grid",), "bandwidth": ("bandwidth",),
         "source": ("source",), "all but grid": ("bandwidth", "source"),
         "all but bandwidth": ("grid", "source"), "all but source": ("grid", "bandwidth"),
         "all": EFFECTS}


def neighbour_max(psfs) -> float:
    """The largest Pearson correlation of the PSFs of neighbouring depths."""
    c = np.asarray(correlation_matrix(standardised(jnp.asarray(psfs, jnp.float32))))
    return float(np.max(np.diag(c, 1)))


def box_filtered(psfs) -> np.ndarray:
    """``psfs`` convolved with a one-pixel box: the transfer sinc(fy)·sinc(fx) (f in
    cycles per pixel), applied circularly."""
    ny, nx = np.shape(psfs)[-2:]
    transfer = np.sinc(np.fft.fftfreq(ny))[:, None] * np.sinc(np.fft.rfftfreq(nx))[None, :]
    return np.fft.irfft2(np.fft.rfft2(psfs) * transfer, s=(ny, nx))


def case_psfs(phase, effects: tuple, n: int, z1) -> np.ndarray:
    """`high_fidelity_psfs` with the truth's ``effects`` on, the others off."""
    return high_fidelity_psfs(
        phase, Geometry(n).truth_camera(), z1,
        oversample=2 if "grid" in effects else 1,
        spectrum=HIGH_FIDELITY_SPECTRUM if "bandwidth" in effects else None,
        source_radius=SOURCE_RADIUS if "source" in effects else 0.0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=128, help="samples across the sensor")
    parser.add_argument("--depths", type=int, default=8)
    parser.add_argument("--steps", type=int, default=300, help="Adam steps of the design")
    parser.add_argument("--name", default="design_fidelity")
    args = parser.parse_args(argv)
    n, z1 = args.n, depth_range(NEAR, FAR, args.depths)
    made = diffusers(Geometry(n), z1, DesignOptions(steps=args.steps, progress=False), [0.1, 0.0],
                     lenslets=False)
    rows = []
    for name in ("designed", "designed, w = 0", "random", "regular lenslets"):
        t = time.perf_counter()
        diffuser = height_map(made[name][0], INDEX)
        model = np.asarray(psf_stack(diffuser, camera(n), z1, progress=False))
        row = {"diffuser": name, "model": neighbour_max(model),
               "box": neighbour_max(box_filtered(model))}
        phase = diffuser.phase(camera(n).wavelength)
        for case, effects in CASES.items():
            row[case] = neighbour_max(case_psfs(phase, effects, n, z1))
        row = {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}
        row["seconds"] = round(time.perf_counter() - t, 1)
        rows.append(row)
        print(row, flush=True)
    by = {r["diffuser"]: r for r in rows}
    claim = ("largest neighbour-depth correlation, designed (w 0.1) / random: " + "; ".join(
        f"{case} {by['designed'][case]} / {by['random'][case]}"
        for case in ("model", "box", *CASES)))
    print(claim)
    write_json(args.name, rows, {
        "settings": {"n": n, "depths_mm": [round(z * 1e3, 2) for z in z1],
                     "steps": args.steps, "source_radius_m": SOURCE_RADIUS,
                     "spectrum_m": HIGH_FIDELITY_SPECTRUM[0].tolist()},
        "claim": claim})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
