"""Diffuser design, judged by 3-D reconstruction: does a diffuser designed for
depth discrimination reconstruct held-out volumes better than a random diffuser of the
same limits and a regular microlens array?

    python -m benchmarks.bench_design_3d                # → benchmarks/results/design_3d.json

The diffusers (`Geometry`: `diffcam design`'s camera, 3 µm pixels, z2 2 mm, aperture
radius a quarter of the frame width (``--aperture-fraction``; a wider aperture's grid is
padded, `Geometry.footprint_pad`), n 1.5, heights 0–2 µm (``--height-max``), features
≥ 30 µm (``--feature-size``); ``--n`` samples across):

- ``designed``: `diffcam.design.design` of a random smooth surface (seed 0) over
  ``--depths`` depths 10–60 mm (``--near``, ``--far``) even in 1/z1, ``--steps`` Adam
  steps, sparsity weight 0.1 (``diffcam design``'s defaults), designed in this run
  through the model's PSFs (one wavelength, a point source); with ``--design-model
  high-fidelity``, through PSFs of the truth's three lines and 50 µm source disc
  (`DesignOptions` ``bandwidth``, ``source_radius``); with ``--design-model truth``,
  through the truth's own PSFs: its lines and source disc, and its field on a 2× finer
  grid integrated over each pixel (``oversample`` 2, on `Geometry.truth_camera`); the
  source the design models assume is the truth's unless ``--design-source-radius``
  says otherwise;
  ``designed, w = 0`` the same without the spread term (``--weights``: the weights
  designed, the first is ``designed``);
- ``start``: that random surface before the design (the same surface, undesigned);
- ``random``: another random smooth surface of the same feature size and height range
  (seed 100), the baseline a user would buy; ``--random-seeds K`` judges K more
  (``random 101`` …) and records their PSNRs' spread (``random_surfaces_psnr_db``) and
  each design's gain over their mean;
- ``regular lenslets``: a regular square microlens array (36 lenses at 256², as many
  per area at other sizes), all lenses alike;
- ``designed lenslets`` (``--no-lenslets`` leaves it out): a random lenslet array
  (seed 0) designed alike;
- ``designed end to end`` (``--end-to-end-steps N``): the same start designed by the
  end-to-end objective (`diffcam.design.end_to_end`: 2 training volumes of its own,
  20 unrolled ADMM-TV iterations with `VOLUME`, ``--photons``, its TV weight learnt)
  through the PSFs of ``--design-model``, judged like the others (the solver's learnt
  weight is not used here).

Each diffuser's truth PSFs come from
`diffcam.calibrate.simulation.high_fidelity_psfs` (the height map's phase at 532 nm on a
2× finer grid, three wavelengths 526–538 nm, a source of 50 µm radius
(``--source-radius``), pixel integration) at the reconstruction depths; its model PSFs from
`diffcam.model.stack.psf_stack` (one wavelength, a point source, the sensor grid;
``--truth model`` makes the captures with these, an ablation without model error). The
solver inverts with the diffuser's calibration (``--calibration``): by default the PSF
stack a user of the fabricated diffuser measures, a point source at each depth recorded
through the truth PSFs with Poisson noise at ``--calibration-photons`` photons at each
PSF's brightest pixel (``measured``); or the model PSFs (``model``, the diffuser used
as designed, uncalibrated). The scenes are made here and seen by nothing else:
``--scenes`` sparse volumes (Gaussian blobs of σ 1 pixel, 2 per depth plane on average,
at random planes and positions within the central half of the field) and the two-point
test (two blobs at the field's centre, on planes k apart, one volume per k: k = 2 …
nz − 1 in steps of nz // 8). A capture is the solvers' crop model,
``b = crop(Σ_z h_z^hf * x_z)`` (`diffcam.reconstruct.operators.convolution_model`,
boundary ``"crop"``), scaled to ``--photons`` photons per sensor pixel on average for
the same scene whatever the diffuser (each PSF has unit sum on the sensor's frame, so a
source gets fewer only where its PSF, moved off axis, leaves the sensor), with Poisson
noise and Gaussian read noise of ``READ_NOISE`` photons.

The scenes, captures, reconstructions and scores below are
`benchmarks.design_3d_volumes`. Every volume is reconstructed by
`diffcam.reconstruct.admm_tv_3d` (crop model) from the capture scaled to unit L2 norm,
with the settings ``diffcam reconstruct --3d`` uses
(`diffcam.reconstruct.admm.VOLUME`, chosen on the DiffuserCam 3-D capture) and
``--iterations`` iterations: the same for every diffuser, nothing tuned here; or, with
``--tune``, the TV and L1 weights chosen per diffuser on a training scene (`tuned`).
Scores, over the central half of the field where the scenes lie:

- volume PSNR (dB) after the least-squares scale of the estimate to the truth, per
  scene, and its mean; ``gain_db_over_random`` is the designed diffuser's mean minus the
  random one's (and over the regular array, the start); ``empty_volume_psnr_db`` is an
  all-zero estimate's, the floor (the scenes are sparse);
- two-point depth resolution: the axial profile (the estimate summed over 5 × 5 pixels
  about the points, per plane) is resolved when it has a peak within one plane of each
  point, with a plane between the peaks whose value is ≤ 80 % of the lower peak
  (``DIP``, a Rayleigh-like dip); the smallest separation Δz (mm, between the planes'
  depths) resolved;
- with ``--two-point-depths M``, the same test on M depths over the range (22: the
  8 depths and two between each pair), by bisection (`finer_two_point`):
  ``finer_resolved_dz_mm``;
- with ``--bounds``, what bounds the volume PSNR (`bounds`): the scenes reconstructed
  with the truth PSFs, with and without noise, the estimate without its depth, and the
  shares of its error on the sources, on their other planes and elsewhere;
- the largest cross-depth correlation of the model PSFs (`evaluate_design`), and of the
  truth PSFs (``truth_max_correlation``).

The default run (128², 8 depths, 4 scenes, 300 design steps, 200 iterations, six
diffusers) takes about 8 minutes on 2 shared cores; ``--n 256 --depths 16 --steps
300`` is `bench_design`'s design (with ``--scenes 3 --iterations 100`` and four
diffusers about 20 minutes).
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax.numpy as jnp
import numpy as np

from benchmarks.bench_design import FAR, FEATURE, H_MAX, INDEX, NEAR, PIXEL, Z2, camera
from benchmarks.design_3d_volumes import (READ_NOISE, bounds, calibration, capture,
                                         depth_blind, finer_two_point, reconstruct,
                                         resolved, scene, tuned, two_point,
                                         two_point_planes, volume_psnr)
from benchmarks.harness import write_json
from diffcam.calibrate.simulation import HIGH_FIDELITY_SPECTRUM, high_fidelity_psfs
from diffcam.design import (DesignOptions, LensletArray, SmoothSurface, depth_range,
                            design, evaluate_design)
from diffcam.design.objective import DepthObjective, pair_correlations, standardised
from diffcam.design.surfaces import height_map
from diffcam.model import Camera, psf_stack
from diffcam.optics.propagation import effective_distance, transfer_pad
from diffcam.reconstruct.admm import VOLUME
from diffcam.reconstruct.operators import grid_shapes

SOURCE_RADIUS = 50e-6
"""Radius of the truth PSFs' source (and of the calibration's), metres (``--source-radius``
in µm)."""
APERTURE_FRACTION = 0.25
"""The aperture radius as a fraction of the frame width (``--aperture-fraction``)."""
DESIGN_MODELS = {
    "point": {},
    "high-fidelity": {"bandwidth": float(np.ptp(HIGH_FIDELITY_SPECTRUM[0])) / 2,
                      "source_radius": SOURCE_RADIUS},
    "truth": {"bandwidth": float(np.ptp(HIGH_FIDELITY_SPECTRUM[0])) / 2,
              "source_radius": SOURCE_RADIUS, "oversample": 2}}
"""``--design-model``: the `DesignOptions` of the PSFs the depth designs optimise."""


@dataclasses.dataclass(frozen=True)
class Geometry:
    """A run's camera and fabrication limits: ``n`` samples of `PIXEL` across the
    sensor, an aperture of radius ``aperture_fraction`` of the frame width (unitless),
    depths ``near`` to ``far`` (metres), surfaces of minimum feature ``feature_size``
    and heights in (0, ``height_max``) (metres)."""

    n: int
    near: float = NEAR
    far: float = FAR
    aperture_fraction: float = APERTURE_FRACTION
    feature_size: float = FEATURE
    height_max: float = H_MAX

    @property
    def aperture_radius(self) -> float:
        """Metres."""
        return self.aperture_fraction * self.n * PIXEL

    def footprint_pad(self) -> int:
        """Samples per side the propagation grid grows by: as much as the aperture's
        footprint on the sensor at the nearest depth (radius a·(1 + z2/near)) grows
        over the quarter-frame camera's, so that the PSFs keep its margin against
        wrap-around (none for a quarter of the frame or less)."""
        growth = (self.aperture_fraction - APERTURE_FRACTION) * (1 + Z2 / self.near)
        return max(0, int(np.ceil(growth * self.n - 1e-9)))

    def camera(self) -> Camera:
        """The model's camera (`bench_design.camera` at this aperture)."""
        pad = self.footprint_pad()
        return dataclasses.replace(camera(self.n), aperture_radius=self.aperture_radius,
                                   pad=(pad, pad))

    def truth_camera(self) -> Camera:
        """`camera` padded so that the high-fidelity model's grid (2× finer) also
        samples the Fresnel transfer function of the farthest depth at the longest
        wavelength (N·dx² / λ ≥ z_eff)."""
        sampled = transfer_pad(self.n, PIXEL, 2 * HIGH_FIDELITY_SPECTRUM[0].max(),
                               effective_distance(self.far, Z2))
        pad = max(self.footprint_pad(), sampled)
        return dataclasses.replace(self.camera(), pad=(pad, pad))

    def smooth(self, seed: int) -> SmoothSurface:
        """A random smooth surface of these limits."""
        return SmoothSurface.random(seed, (self.n, self.n), PIXEL, self.feature_size,
                                    self.height_max)

    def lenslets(self, seed: int, regular: bool = False) -> LensletArray:
        """A random (or ``regular``) microlens array of these limits, its centres within
        the aperture, as many lenses per aperture area as `bench_design`'s 36 at radius
        64 `PIXEL` (256² and a quarter of the frame)."""
        count = max(1, round(36 * (self.aperture_radius / (64 * PIXEL)) ** 2))
        return LensletArray.random(seed, (self.n, self.n), PIXEL, self.feature_size,
                                   self.height_max, count, self.aperture_radius,
                                   regular=regular)


def diffusers(geometry: Geometry, z1: np.ndarray, depth: DesignOptions,
              weights: list[float], lenslets: bool,
              end_to_end: DesignOptions | None = None) -> dict:
    """The diffusers by name: (surface, seconds the design took or None). The smooth
    surface is designed by ``depth`` once per sparsity weight (the first is
    ``designed``), and with ``end_to_end`` options also by the end-to-end objective
    (``designed end to end``); the depth designs on the truth camera if ``depth``
    oversamples (its finer grid needs the padding)."""
    cam = geometry.camera() if depth.oversample == 1 else geometry.truth_camera()
    start = geometry.smooth(0)
    out = {}
    for k, weight in enumerate(weights):
        options = dataclasses.replace(depth, sparsity_weight=weight)
        t = time.perf_counter()
        surface = design(start, cam, z1, INDEX, options).surface
        out["designed" if k == 0 else f"designed, w = {weight:g}"] = (
            surface, time.perf_counter() - t)
    if end_to_end is not None:
        t = time.perf_counter()
        designed = design(start, cam, z1, INDEX, end_to_end).surface
        out["designed end to end"] = (designed, time.perf_counter() - t)
    out["start"] = (start, None)
    out["random"] = (geometry.smooth(100), None)
    out["regular lenslets"] = (geometry.lenslets(0, regular=True), None)
    if lenslets:
        t = time.perf_counter()
        out["designed lenslets"] = (design(geometry.lenslets(0), cam, z1, INDEX,
                                           dataclasses.replace(
            depth, sparsity_weight=weights[0])).surface, time.perf_counter() - t)
    return out


def stacks(surface, z1: np.ndarray, geometry: Geometry,
           args) -> tuple[np.ndarray, np.ndarray]:
    """The diffuser's truth PSFs at the depths ``z1`` (``--truth``) and those its solver
    inverts with (``--calibration``)."""
    cam = geometry.camera()
    diffuser = height_map(surface, INDEX)
    model_psfs = psf_stack(diffuser, cam, z1, progress=False)
    truth_psfs = model_psfs if args.truth == "model" else high_fidelity_psfs(
        diffuser.phase(cam.wavelength), geometry.truth_camera(), z1,
        source_radius=args.source_radius * 1e-6)
    solver_psfs = model_psfs if args.calibration == "model" else calibration(
        np.asarray(truth_psfs), args.calibration_photons)
    return truth_psfs, solver_psfs


def judge(name, surface, z1, geometry, volumes, pairs, args,
          design_s) -> tuple[tuple, dict]:
    """One diffuser: captures through its truth PSFs, reconstructions with its
    calibration (measured or model PSFs); (its truth PSFs and two-point volumes, for
    `figure`) and its scores."""
    n = geometry.n
    truth_psfs, solver_psfs = stacks(surface, z1, geometry, args)
    options = VOLUME
    if args.tune:
        options = tuned(truth_psfs, solver_psfs, n, volumes.shape[-2:], args)
    rng = np.random.default_rng(7)
    b = np.stack([capture(v, truth_psfs, n, args.photons, rng) for v in volumes])
    t = time.perf_counter()
    estimate = reconstruct(b, solver_psfs, args.iterations, options)
    solve_s = time.perf_counter() - t
    scenes = args.scenes
    scores = [volume_psnr(estimate[s], volumes[s], n) for s in range(scenes)]
    separations = [(float(z1[j] - z1[i]) * 1e3, resolved(estimate[scenes + m], (i, j)))
                   for m, (i, j) in enumerate(pairs)]
    smallest = min((dz for dz, ok in separations if ok), default=None)
    objective = DepthObjective(geometry.camera(), z1, INDEX)
    shown = (np.asarray(truth_psfs), estimate[scenes:])
    truth_max = jnp.max(pair_correlations(standardised(jnp.asarray(truth_psfs))))
    extra = {}
    if args.two_point_depths:
        fine = depth_range(args.near * 1e-3, args.far * 1e-3, args.two_point_depths)
        tried = finer_two_point(*stacks(surface, fine, geometry, args), fine, n,
                                volumes.shape[-2:], args, options)
        extra["finer_resolved_dz_mm"] = min(
            (t["dz_mm"] for t in tried if t["resolved"]), default=None)
        extra["finer_two_point"] = tried
    if args.bounds:
        extra.update(bounds(volumes[:scenes], b[:scenes], estimate[:scenes], truth_psfs,
                            n, args, options))
    return shown, {"diffuser": name, "max_correlation": round(
                evaluate_design(surface, objective)["max_correlation"], 4),
            "truth_max_correlation": round(float(truth_max), 4),
            "psnr_db": round(float(np.mean(scores)), 2),
            "psnr_per_scene": [round(s, 2) for s in scores],
            "resolved_dz_mm": None if smallest is None else round(smallest, 2),
            "two_point": [{"dz_mm": round(dz, 2), "resolved": ok} for dz, ok in separations],
            "design_s": None if design_s is None else round(design_s, 1),
            "tau": options.tau, "sparsity": options.sparsity,
            "reconstruct_s": round(solve_s, 1), **extra}


def figure(shown: dict, rows: list[dict], z1: np.ndarray, path) -> None:
    """Per diffuser (a row of panels): its truth PSFs at the nearest and farthest depth,
    and the x–z section through the two points of the smallest separation any diffuser
    resolves (the smallest tried if none does)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffcam.apps.common import save_figure

    resolved_by_any = [k for k in range(len(rows[0]["two_point"]))
                       if any(r["two_point"][k]["resolved"] for r in rows)]
    m = min(resolved_by_any, default=0)
    dz = rows[0]["two_point"][m]["dz_mm"]
    fig, axes = plt.subplots(len(shown), 3, figsize=(9, 2.6 * len(shown)),
                             layout="constrained", squeeze=False)
    for ax, (name, (psfs, estimates)) in zip(axes, shown.items()):
        ax[0].imshow(psfs[0], cmap="gray")
        ax[0].set_title(f"{name}: PSF, {z1[0] * 1e3:.0f} mm", fontsize=9)
        ax[1].imshow(psfs[-1], cmap="gray")
        ax[1].set_title(f"PSF, {z1[-1] * 1e3:.0f} mm", fontsize=9)
        cy, cx = (o // 2 for o in estimates.shape[-2:])
        section = estimates[m][:, cy, cx - 16:cx + 17]
        ax[2].imshow(section, cmap="magma", aspect="auto", extent=(
            -16.5, 16.5, len(section) - 0.5, -0.5))
        ax[2].set_xlabel("x, pixels from the points")
        ax[2].set_title(f"two points {dz:g} mm apart: x–z", fontsize=9)
        ax[2].set_ylabel("plane (0 = nearest)")
        for a in ax[:2]:
            a.set_xticks([])
            a.set_yticks([])
    save_figure(fig, path)


def gain_rows(by: dict, weights: list[float]) -> list[dict]:
    """Per design (objective): its mean volume PSNR minus each baseline's, dB, and the
    smallest two-point separation it resolves."""
    designs = [name for name in by if name.startswith("designed")]
    rows = []
    for name in designs:
        if name == "designed end to end":
            row = {"design": name, "objective": "end to end", "sparsity_weight": None}
        else:
            weight = weights[0] if name in ("designed", "designed lenslets") \
                else float(name.rsplit("= ", 1)[1])
            row = {"design": name, "objective": "depth discrimination",
                   "sparsity_weight": weight}
        row.update({f"gain_db_over_{other.replace(' ', '_')}":
                    round(by[name]["psnr_db"] - by[other]["psnr_db"], 2)
                    for other in ("random", "start", "regular lenslets")})
        row["resolved_dz_mm"] = by[name]["resolved_dz_mm"]
        if "finer_resolved_dz_mm" in by[name]:
            row["finer_resolved_dz_mm"] = by[name]["finer_resolved_dz_mm"]
        rows.append(row)
    return rows


def arguments(argv=None) -> argparse.Namespace:
    """The command line's options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=128, help="samples across the sensor")
    parser.add_argument("--depths", type=int, default=8)
    parser.add_argument("--near", type=float, default=NEAR * 1e3,
                        help="nearest depth, mm")
    parser.add_argument("--far", type=float, default=FAR * 1e3, help="farthest depth, mm")
    parser.add_argument("--steps", type=int, default=300, help="Adam steps of the design")
    parser.add_argument("--scenes", type=int, default=4)
    parser.add_argument("--iterations", type=int, default=200,
                        help="ADMM-TV iterations")
    parser.add_argument("--photons", type=float, default=100.0,
                        help="mean photons per sensor pixel")
    parser.add_argument("--weights", type=float, nargs="+", default=[0.1, 0.0],
                        help="sparsity weights of the smooth designs (the first is "
                             "'designed')")
    parser.add_argument("--truth", choices=("high-fidelity", "model"),
                        default="high-fidelity",
                        help="the captures' PSFs ('model': the solver's own, an ablation "
                             "without model error)")
    parser.add_argument("--calibration", choices=("measured", "model"),
                        default="measured",
                        help="the PSFs the solver inverts with ('measured': recorded "
                             "through the truth PSFs with noise; 'model': the model's, "
                             "uncalibrated)")
    parser.add_argument("--calibration-photons", type=float, default=1e4,
                        help="photons at each calibration PSF's brightest pixel")
    parser.add_argument("--design-model", choices=tuple(DESIGN_MODELS),
                        default="point",
                        help="the PSFs the depth designs optimise ('point': one "
                             "wavelength, a point source; 'high-fidelity': the truth's "
                             "three lines and source disc; 'truth': those and the "
                             "truth's 2× finer grid integrated over each pixel)")
    parser.add_argument("--tune", action="store_true",
                        help="choose the TV and L1 weights per diffuser on a training "
                             "scene (TUNING_FACTORS × VOLUME's)")
    parser.add_argument("--lenslets", action=argparse.BooleanOptionalAction,
                        default=True, help="design a lenslet array too")
    parser.add_argument("--end-to-end-steps", type=int, default=0,
                        help="also design the start by the end-to-end objective, this "
                             "many steps (2 training volumes, 20 unrolled iterations, "
                             "--photons; 0: not)")
    parser.add_argument("--two-point-depths", type=int, default=0,
                        help="also run the two-point test on this many depths over the "
                             "range, by bisection (0: not)")
    parser.add_argument("--source-radius", type=float, default=SOURCE_RADIUS * 1e6,
                        help="radius of the truth's (and the calibration's) source, µm; "
                             "the design models of a source take it too")
    parser.add_argument("--design-source-radius", type=float, default=None,
                        help="the source radius the design models assume, µm (default: "
                             "--source-radius; another value: a design model that "
                             "misjudges the source)")
    parser.add_argument("--aperture-fraction", type=float, default=APERTURE_FRACTION,
                        help="aperture radius as a fraction of the frame width")
    parser.add_argument("--feature-size", type=float, default=FEATURE * 1e6,
                        help="the surfaces' minimum feature size, µm")
    parser.add_argument("--height-max", type=float, default=H_MAX * 1e6,
                        help="the surfaces' height range, µm")
    parser.add_argument("--random-seeds", type=int, default=0,
                        help="judge this many more random surfaces (seeds 101, …): the "
                             "baseline's spread")
    parser.add_argument("--bounds", action="store_true",
                        help="also reconstruct the scenes with the truth PSFs, with and "
                             "without noise, and say where the error sits (bounds)")
    parser.add_argument("--figure", help="also draw each diffuser's PSFs and a "
                        "two-point reconstruction to this image file")
    parser.add_argument("--name", default="design_3d")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = arguments(argv)
    n, z1 = args.n, depth_range(args.near * 1e-3, args.far * 1e-3, args.depths)
    geometry = Geometry(n, args.near * 1e-3, args.far * 1e-3, args.aperture_fraction,
                        args.feature_size * 1e-6, args.height_max * 1e-6)
    object_shape = grid_shapes((n, n), (n, n), "crop")[0]
    pairs = two_point_planes(args.depths, max(1, args.depths // 8))
    volumes = np.stack([scene(1000 + s, args.depths, n, object_shape)
                        for s in range(args.scenes)]
                       + [two_point(args.depths, object_shape, p) for p in pairs])
    rows = []
    floor = round(float(np.mean([volume_psnr(np.zeros_like(v), v, n, None)
                                 for v in volumes[:args.scenes]])), 2)
    blind = round(float(np.mean([volume_psnr(depth_blind(v), v, n)
                                 for v in volumes[:args.scenes]])), 2)
    assumed = args.source_radius if args.design_source_radius is None \
        else args.design_source_radius
    light = {k: assumed * 1e-6 if k == "source_radius" else v
             for k, v in DESIGN_MODELS[args.design_model].items()}
    end_to_end = None if args.end_to_end_steps < 1 else DesignOptions(
        objective="end_to_end", steps=args.end_to_end_steps, scenes=2, solver_iterations=20,
        photons=args.photons, progress=False, **light)
    depth = DesignOptions(steps=args.steps, progress=False, **light)
    made = diffusers(geometry, z1, depth, args.weights, args.lenslets, end_to_end)
    for seed in range(101, 101 + args.random_seeds):
        made[f"random {seed}"] = (geometry.smooth(seed), None)
    shown = {}
    for name, (surface, design_s) in made.items():
        shown[name], row = judge(name, surface, z1, geometry, volumes, pairs, args,
                                 design_s)
        rows.append(row)
        print(row, flush=True)
    if args.figure:
        figure(shown, rows, z1, args.figure)
    by = {r["diffuser"]: r for r in rows}
    gains = gain_rows(by, args.weights)
    randoms = [r["psnr_db"] for r in rows if r["diffuser"].startswith("random")]
    spread = {"count": len(randoms), "mean": round(float(np.mean(randoms)), 2),
              "sd": round(float(np.std(randoms, ddof=1)), 2) if len(randoms) > 1 else None,
              "min": min(randoms), "max": max(randoms)}
    for g in gains:
        g["gain_db_over_random_mean"] = round(by[g["design"]]["psnr_db"] - spread["mean"], 2)
    claim = (f"{n}² over {args.depths} depths ({args.near:g}–{args.far:g} mm), "
             f"{args.steps} design steps, {args.photons:g} photons per pixel, "
             f"{args.calibration} PSFs: volume PSNR designed {by['designed']['psnr_db']} "
             f"dB, random {by['random']['psnr_db']} dB, regular lenslets "
             f"{by['regular lenslets']['psnr_db']} dB (empty volume {floor} dB; gain over "
             f"random {gains[0]['gain_db_over_random']} dB); two points resolved from "
             f"{by['designed']['resolved_dz_mm']} mm (designed), "
             f"{by['random']['resolved_dz_mm']} mm (random), "
             f"{by['regular lenslets']['resolved_dz_mm']} mm (regular lenslets)")
    print(claim)
    write_json(args.name, rows, {
        "gains": gains,
        "settings": {"n": n, "depths_mm": [round(z * 1e3, 2) for z in z1],
                     "steps": args.steps, "scenes": args.scenes,
                     "iterations": args.iterations, "photons_per_pixel": args.photons,
                     "read_noise": READ_NOISE, "truth_psfs": args.truth,
                     "calibration": args.calibration, "design_model": args.design_model,
                     "calibration_photons_at_peak": args.calibration_photons,
                     "tuned_per_diffuser": args.tune,
                     "end_to_end_steps": args.end_to_end_steps,
                     "two_point_depths": args.two_point_depths,
                     "random_seeds": args.random_seeds,
                     "source_radius_um": args.source_radius,
                     "design_source_radius_um": assumed,
                     "aperture_fraction": args.aperture_fraction,
                     "aperture_radius_um": round(geometry.aperture_radius * 1e6, 2),
                     "feature_size_um": args.feature_size,
                     "height_max_um": args.height_max,
                     "pad": geometry.camera().pad[0],
                     "solver": "admm_tv_3d, VOLUME settings, L2-normalised capture"},
        "random_surfaces_psnr_db": spread,
        "empty_volume_psnr_db": floor,
        "depth_blind_truth_psnr_db": blind,
        "claim": claim})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
