"""Paper Fig. 3: retrieve the "cameraman" diffuser phase from near/far intensities.

Section 3.1 of the paper: diffuser 512×512 at 5 µm, phase = cameraman scaled to [−π, π],
circular aperture of radius 1.2 mm, near-field intensity 1 inside the aperture, far
field through a Fourier lens f = 5 cm at 532 nm, embedded in an N×N grid (paper:
N = 4000). Scored on the central 300×300 pixels by the docs/design.md phase metrics
(piston-aligned, twin-resolved, raw Pearson; phase MSE) beside reference estimates
that carry no information (flat, random) to show the metric's floor.

    python scripts/retrieval_fig3.py --n 1024                   # exact captures
    python scripts/retrieval_fig3.py --n 1024 --noisy            # synthetic captures
    python scripts/retrieval_fig3.py --n 4000 --methods raar --gs-iterations 0
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from diffcam.core.grid import crop_to, pad_to
from diffcam.evaluate.metrics import phase_scores
from diffcam.optics.elements import circular_aperture
from diffcam.calibrate.phase.pipeline import POLISH
from diffcam.calibrate import (CalibrationGeometry, FitOptions, retrieve_phase, calibration_intensities,
                               cameraman_phase, prepare_captures, retrieve_projections,
                               synthetic_captures)

DX, WAVELENGTH, FOCAL, RADIUS, SIZE, SCORED = 5e-6, 532e-9, 0.05, 1.2e-3, 512, 300


def scores(phase, truth, mask):
    return {k: round(float(v), 4) for k, v in
            phase_scores(crop_to(phase, truth.shape), truth, mask=mask).items()}


def noisy_captures(theta, aperture, geometry, n, key, pitch_error, far_exposures=None):
    """Sensor at 3.45 µm (the paper's camera), Poisson 1e4 photons at peak, 12 bits, 2 %
    background; the far capture is resampled with a pitch that is off by ``pitch_error``
    (the synthetic sensor is on the optical axis, so no centring)."""
    sensor_pitch = 3.45e-6
    sensor_shape = (int(n * DX / sensor_pitch) // 2 * 2,) * 2
    near_raw, far_raw = synthetic_captures(theta, aperture, geometry, key,
                                           sensor_pitch=sensor_pitch, sensor_shape=sensor_shape,
                                           far_exposures=far_exposures)
    bg = round(0.02 * 4095)
    exposure = (1.0, 1.0 if far_exposures is None else far_exposures)
    near, _, _, _ = prepare_captures(near_raw, far_raw, geometry, (n, n),
                                     sensor_pitch=sensor_pitch, background=(bg, bg),
                                     exposure=exposure, saturation=4095, centre=False)
    _, far, near_mask, far_mask = prepare_captures(
        near_raw, far_raw, geometry, (n, n), sensor_pitch=sensor_pitch * (1 + pitch_error),
        background=(bg, bg), exposure=exposure, saturation=4095, centre=False)
    return near, far, (near_mask, far_mask)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=1024, help="grid size N (paper: 4000)")
    ap.add_argument("--methods", default="gs,hio,raar")
    ap.add_argument("--gs-iterations", type=int, default=2000)
    ap.add_argument("--iterations", type=int, default=300, help="HIO/RAAR iterations")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--restarts", type=int, default=4, help="restarts of the default path")
    ap.add_argument("--refine", type=int, default=100, help="least-squares steps after RAAR")
    ap.add_argument("--noisy", action="store_true", help="synthetic noisy captures")
    ap.add_argument("--pitch-error", type=float, default=0.01)
    ap.add_argument("--hdr", default="", help="far exposure series, e.g. 1,30,1000")
    ap.add_argument("--json", help="write the figures to this file")
    args = ap.parse_args()

    n = args.n
    geometry = CalibrationGeometry(dx=DX, wavelength=WAVELENGTH, focal_length=FOCAL)
    truth = cameraman_phase(SIZE)
    aperture = circular_aperture((n, n), DX, RADIUS)
    theta = pad_to(truth, (n, n))
    t = time.perf_counter()
    if args.noisy:
        hdr = tuple(float(t) for t in args.hdr.split(",")) if args.hdr else None
        near, far, masks = noisy_captures(theta, aperture, geometry, n, jax.random.key(99),
                                          args.pitch_error, hdr)
    else:
        near, far = calibration_intensities(theta, aperture, geometry)
        masks = None
    print(f"noisy: {args.noisy}, pitch error {args.pitch_error}, hdr {args.hdr or 'no'}")
    print(f"grid {n}², far pitch {geometry.far_pitch((n, n))[0] * 1e6:.3f} µm, captures "
          f"{'noisy' if args.noisy else 'exact'} in {time.perf_counter() - t:.1f} s", flush=True)
    mask = jnp.zeros((SIZE, SIZE)).at[(SIZE - SCORED) // 2:(SIZE + SCORED) // 2,
                                       (SIZE - SCORED) // 2:(SIZE + SCORED) // 2].set(1.0)
    rows = [{"solver": "reference: flat estimate", **scores(jnp.zeros((n, n)), truth, mask)},
            {"solver": "reference: random estimate",
             **scores(jax.random.uniform(jax.random.key(7), (n, n), minval=-np.pi,
                                         maxval=np.pi), truth, mask)}]
    for method in args.methods.split(","):
        its = args.gs_iterations if method == "gs" else args.iterations
        if its == 0:
            continue
        for seed in range(args.seeds):
            r = retrieve_projections(near, far, geometry, method=method, iterations=its,
                                     key=jax.random.key(seed))
            rows.append({"solver": f"{method} {its} it, seed {seed}",
                         **scores(r.phase, truth, mask), "error": float(r.history[-1]),
                         "wall_s": round(r.stats["wall_time"], 1)})
            print(rows[-1], flush=True)
    refine = FitOptions.of(POLISH, iterations=args.refine) if args.refine else None
    r = retrieve_phase(near, far, geometry, aperture, key=jax.random.key(0),
                       restarts=args.restarts, iterations=args.iterations, refine=refine,
                       masks=masks)
    rows.append({"solver": f"calibrate: raar {args.iterations} it × {args.restarts} restarts"
                           f" + lsq {args.refine}", **scores(r.phase, truth, mask),
                 "wall_s": round(r.stats["wall_time"], 1)})
    print(rows[-1], flush=True)
    print("\n| solver | pearson | twin-resolved | raw | phase MSE | twin-resolved MSE (rad²) "
          "| wall (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['solver']} | {row['pearson']} | {row['twin_resolved']} | {row['raw']} | "
              f"{row['mse']} | {row['mse_twin_resolved']} | {row.get('wall_s', '')} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"n": n, "noisy": args.noisy, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
