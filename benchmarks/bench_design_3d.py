"""Diffuser design, judged by 3-D reconstruction: does a diffuser designed for
depth discrimination reconstruct held-out volumes better than a random diffuser of the
same limits and a regular microlens array?

    python -m benchmarks.bench_design_3d                # → benchmarks/results/design_3d.json

The diffusers (`diffcam design`'s camera: 3 µm pixels, z2 2 mm, aperture radius a
quarter of the frame, n 1.5, heights 0–2 µm, features ≥ 30 µm; ``--n`` samples across):

- ``designed``: `diffcam.design.design` of a random smooth surface (seed 0) over
  ``--depths`` depths 10–60 mm (``--near``, ``--far``) even in 1/z1, ``--steps`` Adam
  steps, sparsity weight 0.1 (``diffcam design``'s defaults), designed in this run
  through the model's PSFs (one wavelength, a point source); with ``--design-model
  high-fidelity``, through PSFs of the truth's three lines and 50 µm source disc
  (`DesignOptions` ``bandwidth``, ``source_radius``); with ``--design-model truth``,
  through the truth's own PSFs: its lines and source disc, and its field on a 2× finer
  grid integrated over each pixel (``oversample`` 2, on `truth_camera`);
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
the same scene whatever the diffuser (a diffuser that loses light off the sensor gets
fewer), with Poisson noise and Gaussian read noise of ``READ_NOISE`` photons.

Every volume is reconstructed by `diffcam.reconstruct.admm_tv_3d` (crop model) from the
capture scaled to unit L2 norm, with the settings ``diffcam reconstruct --3d`` uses
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
from benchmarks.harness import write_json
from diffcam.calibrate.simulation import HIGH_FIDELITY_SPECTRUM, high_fidelity_psfs
from diffcam.design import (DesignOptions, LensletArray, SmoothSurface, depth_range,
                            design, evaluate_design)
from diffcam.design.objective import DepthObjective, pair_correlations, standardised
from diffcam.design.surfaces import height_map
from diffcam.evaluate import psnr
from diffcam.model import psf_stack
from diffcam.optics.propagation import effective_distance
from diffcam.reconstruct import admm_tv_3d, convolution_model
from diffcam.reconstruct.admm import VOLUME, AdmmOptions
from diffcam.reconstruct.operators import grid_shapes

READ_NOISE = 2.0
"""Gaussian read noise, photons (electrons) per pixel."""
DIP = 0.8
"""Two points are resolved when the axial profile between their peaks falls to this
fraction of the lower peak (or below)."""
TUNING_FACTORS = (0.1, 1.0, 10.0)
"""With ``--tune``, the factors on `VOLUME`'s TV and L1 weights tried per diffuser."""
TRAINING_SEED = 2000
"""The seed of the scene ``--tune`` chooses the weights on (held-out scenes: 1000 + k)."""
CALIBRATION_SEED = 3000
"""The seed of the calibration PSFs' noise (captures: 7; scenes: 1000 + k, 2000)."""
SOURCE_RADIUS = 50e-6
"""Radius of the truth PSFs' source (and of the calibration's), metres (``--source-radius``
in µm)."""
FINE_TWO_POINT_SEED = 4000
"""The seed of the finer two-point test's captures (plus the points' plane count apart:
every diffuser gets the same noise for the same pair)."""
SOURCE_SHARE = 0.1
"""`bounds`: a voxel is on a source where the truth is at least this share of its peak."""
BLOB_SIGMA = 1.0
"""Standard deviation of a scene's Gaussian blobs, object-grid samples."""
DESIGN_MODELS = {
    "point": {},
    "high-fidelity": {"bandwidth": float(np.ptp(HIGH_FIDELITY_SPECTRUM[0])) / 2,
                      "source_radius": SOURCE_RADIUS},
    "truth": {"bandwidth": float(np.ptp(HIGH_FIDELITY_SPECTRUM[0])) / 2,
              "source_radius": SOURCE_RADIUS, "oversample": 2}}
"""``--design-model``: the `DesignOptions` of the PSFs the depth designs optimise."""


def diffusers(n: int, z1: np.ndarray, depth: DesignOptions, weights: list[float],
              lenslets: bool, end_to_end: DesignOptions | None = None) -> dict:
    """The diffusers by name: (surface, seconds the design took or None). The smooth
    surface is designed by ``depth`` once per sparsity weight (the first is
    ``designed``), and with ``end_to_end`` options also by the end-to-end objective
    (``designed end to end``); the depth designs on `truth_camera` if ``depth``
    oversamples (its finer grid needs the padding)."""
    cam = camera(n) if depth.oversample == 1 else truth_camera(n, float(np.max(z1)))
    lenses = max(1, round(36 * (n / 256) ** 2))
    region = n * PIXEL / 4
    start = SmoothSurface.random(0, (n, n), PIXEL, FEATURE, H_MAX)
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
    out["random"] = (SmoothSurface.random(100, (n, n), PIXEL, FEATURE, H_MAX), None)
    out["regular lenslets"] = (LensletArray.random(0, (n, n), PIXEL, FEATURE, H_MAX, lenses,
                                                   region, regular=True), None)
    if lenslets:
        first = LensletArray.random(0, (n, n), PIXEL, FEATURE, H_MAX, lenses, region)
        t = time.perf_counter()
        out["designed lenslets"] = (design(first, cam, z1, INDEX, dataclasses.replace(
            depth, sparsity_weight=weights[0])).surface, time.perf_counter() - t)
    return out


def truth_camera(n: int, far: float):
    """`camera` padded so that the high-fidelity model's grid (2× finer) samples the
    Fresnel transfer function of the farthest depth ``far`` (m) at the longest
    wavelength (N·dx²/λ ≥ z_eff)."""
    fine_dx = PIXEL / 2
    need = effective_distance(far, Z2) * HIGH_FIDELITY_SPECTRUM[0].max() / fine_dx ** 2
    pad = max(0, int(np.ceil((need / 2 - n) / 2)))
    return dataclasses.replace(camera(n), pad=(pad, pad))


def blob(volume: np.ndarray, plane: int, y: float, x: float, amplitude: float) -> None:
    """Add a Gaussian blob (σ `BLOB_SIGMA` samples) at (plane, y, x) of ``volume``."""
    oy, ox = volume.shape[-2:]
    yy, xx = np.arange(oy)[:, None], np.arange(ox)[None, :]
    volume[plane] += amplitude * np.exp(-((yy - y) ** 2 + (xx - x) ** 2)
                                        / (2 * BLOB_SIGMA ** 2))


def field(n: int, object_shape) -> tuple[slice, slice]:
    """The central half of the sensor's field on the object grid (where scenes lie)."""
    return tuple(slice(o // 2 - n // 4, o // 2 + n // 4) for o in object_shape)


def scene(seed: int, nz: int, n: int, object_shape) -> np.ndarray:
    """A sparse volume: 2·nz blobs of amplitude 0.5–1 at random planes and positions
    within `field`."""
    rng = np.random.default_rng(seed)
    volume = np.zeros((nz, *object_shape))
    rows, cols = field(n, object_shape)
    for _ in range(2 * nz):
        blob(volume, rng.integers(nz), rng.uniform(rows.start + 2, rows.stop - 3),
             rng.uniform(cols.start + 2, cols.stop - 3), rng.uniform(0.5, 1.0))
    return volume


def two_point_planes(nz: int, stride: int = 1) -> list[tuple[int, int]]:
    """(near plane, far plane) of the two-point test for k = 2, 2 + stride, … < nz
    planes apart, centred on the middle of the stack."""
    pairs = []
    for k in range(2, nz, stride):
        i = (nz - 1 - k) // 2
        pairs.append((i, i + k))
    return pairs


def two_point(nz: int, object_shape, planes: tuple[int, int]) -> np.ndarray:
    volume = np.zeros((nz, *object_shape))
    cy, cx = (o // 2 for o in object_shape)
    for p in planes:
        blob(volume, p, cy, cx, 1.0)
    return volume


def expected_capture(volume: np.ndarray, truth_psfs: np.ndarray, n: int,
                     photons: float) -> np.ndarray:
    """The noise-free sensor image of ``volume`` through ``truth_psfs`` (crop model),
    scaled to ``photons`` per pixel on average for a scene of this flux (whatever the
    diffuser)."""
    model = convolution_model(jnp.asarray(truth_psfs), (n, n), "crop", volume=True)
    expected = np.asarray(model(jnp.asarray(volume, jnp.float32)), np.float64)
    return expected * photons * n * n / volume.sum()


def capture(volume: np.ndarray, truth_psfs: np.ndarray, n: int, photons: float,
            rng: np.random.Generator) -> np.ndarray:
    """The noisy sensor image of ``volume``: `expected_capture` with Poisson and read
    noise, clipped at 0."""
    expected = expected_capture(volume, truth_psfs, n, photons)
    noisy = rng.poisson(np.clip(expected, 0, None)) + rng.normal(0, READ_NOISE, (n, n))
    return np.clip(noisy, 0, None)


def volume_psnr(estimate: np.ndarray, truth: np.ndarray, n: int,
                align: str | None = "scale") -> float:
    """PSNR (dB) of ``estimate`` within `field`, after its least-squares scale to
    ``truth`` (``align=None``: as it is), over the whole volume (peak: the truth's
    range there)."""
    rows, cols = field(n, truth.shape[-2:])
    e, t = estimate[:, rows, cols], truth[:, rows, cols]
    flat = (lambda v: jnp.asarray(v.reshape(-1, v.shape[-1]), jnp.float32))
    return float(psnr(flat(e), flat(t), align=align))


def resolved(estimate: np.ndarray, planes: tuple[int, int]) -> bool:
    """Whether the axial profile (5 × 5 pixels about the centre) shows the two points:
    a peak within one plane of each, and a plane between them at ≤ `DIP` of the lower."""
    cy, cx = (o // 2 for o in estimate.shape[-2:])
    profile = estimate[:, cy - 2:cy + 3, cx - 2:cx + 3].sum(axis=(-2, -1))
    peaks = []
    for p in planes:
        lo, hi = max(p - 1, 0), min(p + 2, len(profile))
        peaks.append(lo + int(np.argmax(profile[lo:hi])))
    i, j = peaks
    if j - i < 2:
        return False
    return bool(profile[i + 1:j].min() <= DIP * min(profile[i], profile[j]))


def finer_two_point(truth_psfs, solver_psfs, z1: np.ndarray, n: int, object_shape, args,
                    options: AdmmOptions) -> list[dict]:
    """The two-point test on the depth grid ``z1`` (finer than the scenes'), by bisection
    over k, the planes between two points centred on the stack (`two_point_planes`,
    k = 2 … nz − 1): it assumes that a pair is resolved if a closer one is, tests the
    widest pair, then halves the interval; each capture with the noise of seed
    `FINE_TWO_POINT_SEED` + k. Every pair tried, in order: ``planes`` (k), ``dz_mm`` and
    ``resolved``."""
    nz = len(z1)
    pairs = dict(zip(range(2, nz), two_point_planes(nz)))
    tried = []

    def test(k: int) -> bool:
        (i, j), rng = pairs[k], np.random.default_rng(FINE_TWO_POINT_SEED + k)
        b = capture(two_point(nz, object_shape, (i, j)), truth_psfs, n, args.photons, rng)
        ok = resolved(reconstruct(b[None], solver_psfs, args.iterations, options)[0], (i, j))
        tried.append({"planes": k, "dz_mm": round(float(z1[j] - z1[i]) * 1e3, 2),
                      "resolved": ok})
        return ok

    lo, hi = 2, nz - 1
    if test(hi):
        while lo < hi:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if test(mid) else (mid + 1, hi)
    return tried


def bounds(volumes: np.ndarray, b: np.ndarray, estimate: np.ndarray, truth_psfs,
           n: int, args, options: AdmmOptions) -> dict:
    """What bounds a diffuser's volume PSNR on the held-out scenes ``volumes`` (their
    noisy captures ``b`` and the solver's ``estimate``), mean over the scenes, dB:
    ``psnr_db_exact_psfs``, the same captures reconstructed with the truth PSFs (no
    calibration noise, no model error); ``psnr_db_noiseless``, noise-free captures with
    the truth PSFs (the solver's and the diffuser's own limit); ``depth_blind_psnr_db``,
    the estimate's mean over planes put on every plane (its lateral content without
    depth); and where the estimate's squared error sits after its least-squares scale
    (shares of it, within `field`): ``error_on_sources`` (voxels where the truth is
    ≥ `SOURCE_SHARE` of its peak), ``error_other_planes`` (the sources' lateral
    positions on the planes they are not on: depth confusion), ``error_elsewhere``."""
    clean = np.stack([expected_capture(v, truth_psfs, n, args.photons) for v in volumes])
    oracle = reconstruct(np.concatenate([b, clean]), np.asarray(truth_psfs),
                         args.iterations, options)
    scenes, shares, (rows, cols) = len(volumes), [], field(n, volumes.shape[-2:])
    mean = (lambda values: round(float(np.mean(values)), 2))
    for e, t in zip(estimate, volumes):
        e, t = e[:, rows, cols], t[:, rows, cols]
        err = e * np.sum(e * t) / np.sum(e * e) - t
        on = t >= SOURCE_SHARE * t.max()
        depth = np.broadcast_to(on.any(axis=0), on.shape) & ~on
        total = np.sum(err ** 2)
        shares.append([np.sum(err[on] ** 2) / total, np.sum(err[depth] ** 2) / total])
    on, depth = np.mean(shares, axis=0)
    return {"psnr_db_exact_psfs": mean([volume_psnr(oracle[s], volumes[s], n)
                                        for s in range(scenes)]),
            "psnr_db_noiseless": mean([volume_psnr(oracle[scenes + s], volumes[s], n)
                                       for s in range(scenes)]),
            "depth_blind_psnr_db": mean([volume_psnr(depth_blind(e), t, n)
                                         for e, t in zip(estimate, volumes)]),
            "error_on_sources": round(float(on), 3),
            "error_other_planes": round(float(depth), 3),
            "error_elsewhere": round(float(1 - on - depth), 3)}


def depth_blind(volume: np.ndarray) -> np.ndarray:
    """``volume``'s mean over planes, on every plane: its lateral content, no depth."""
    return np.broadcast_to(volume.mean(axis=0), volume.shape)


def reconstruct(b: np.ndarray, psfs: np.ndarray, iterations: int,
                options: AdmmOptions) -> np.ndarray:
    """ADMM-TV volumes of the captures ``b`` (…, n, n), each scaled to unit L2 norm."""
    unit = b / np.linalg.norm(b, axis=(-2, -1), keepdims=True)
    return np.asarray(admm_tv_3d(unit, psfs, iterations, options,
                                 progress=False).image)


def tuned(truth_psfs, solver_psfs, n: int, object_shape, args) -> AdmmOptions:
    """`VOLUME` with its lateral TV (axial TV in proportion) and L1 weights each scaled
    by one of `TUNING_FACTORS`: the pair with the best volume PSNR on the training
    scene (seed `TRAINING_SEED`, not a held-out one)."""
    volume = scene(TRAINING_SEED, len(solver_psfs), n, object_shape)
    b = capture(volume, truth_psfs, n, args.photons, np.random.default_rng(TRAINING_SEED))
    best = None
    for f_tv in TUNING_FACTORS:
        for f_l1 in TUNING_FACTORS:
            options = AdmmOptions.of(VOLUME, tau=VOLUME.tau * f_tv,
                                     tau_axial=VOLUME.tau_axial * f_tv,
                                     sparsity=VOLUME.sparsity * f_l1)
            estimate = reconstruct(b, solver_psfs, args.iterations, options)
            score = volume_psnr(estimate, volume, n) if estimate.any() else -np.inf
            if best is None or score > best[0]:
                best = (score, options)
    return best[1]


def calibration(truth_psfs: np.ndarray, photons: float) -> np.ndarray:
    """The PSF stack measured through ``truth_psfs`` (each of unit sum): Poisson noise
    at ``photons`` at each PSF's brightest pixel, each normalised to unit sum."""
    rng = np.random.default_rng(CALIBRATION_SEED)
    peak = truth_psfs.max(axis=(-2, -1), keepdims=True)
    counts = rng.poisson(np.asarray(truth_psfs, np.float64) / peak * photons)
    return (counts / counts.sum(axis=(-2, -1), keepdims=True)).astype(np.float32)


def stacks(surface, z1: np.ndarray, n: int, args) -> tuple[np.ndarray, np.ndarray]:
    """The diffuser's truth PSFs at the depths ``z1`` (``--truth``) and those its solver
    inverts with (``--calibration``)."""
    cam = camera(n)
    diffuser = height_map(surface, INDEX)
    model_psfs = psf_stack(diffuser, cam, z1, progress=False)
    truth_psfs = model_psfs if args.truth == "model" else high_fidelity_psfs(
        diffuser.phase(cam.wavelength), truth_camera(n, float(z1.max())), z1,
        source_radius=args.source_radius * 1e-6)
    solver_psfs = model_psfs if args.calibration == "model" else calibration(
        np.asarray(truth_psfs), args.calibration_photons)
    return truth_psfs, solver_psfs


def judge(name, surface, z1, n, volumes, pairs, args, design_s) -> tuple[tuple, dict]:
    """One diffuser: captures through its truth PSFs, reconstructions with its
    calibration (measured or model PSFs); (its truth PSFs and two-point volumes, for
    `figure`) and its scores."""
    cam = camera(n)
    truth_psfs, solver_psfs = stacks(surface, z1, n, args)
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
    objective = DepthObjective(cam, z1, INDEX)
    shown = (np.asarray(truth_psfs), estimate[scenes:])
    truth_max = jnp.max(pair_correlations(standardised(jnp.asarray(truth_psfs))))
    extra = {}
    if args.two_point_depths:
        fine = depth_range(args.near * 1e-3, args.far * 1e-3, args.two_point_depths)
        tried = finer_two_point(*stacks(surface, fine, n, args), fine, n,
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


def main(argv=None) -> int:
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
    parser.add_argument("--random-seeds", type=int, default=0,
                        help="judge this many more random surfaces (seeds 101, …): the "
                             "baseline's spread")
    parser.add_argument("--bounds", action="store_true",
                        help="also reconstruct the scenes with the truth PSFs, with and "
                             "without noise, and say where the error sits (bounds)")
    parser.add_argument("--figure", help="also draw each diffuser's PSFs and a "
                        "two-point reconstruction to this image file")
    parser.add_argument("--name", default="design_3d")
    args = parser.parse_args(argv)
    n, z1 = args.n, depth_range(args.near * 1e-3, args.far * 1e-3, args.depths)
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
    light = {k: args.source_radius * 1e-6 if k == "source_radius" else v
             for k, v in DESIGN_MODELS[args.design_model].items()}
    end_to_end = None if args.end_to_end_steps < 1 else DesignOptions(
        objective="end_to_end", steps=args.end_to_end_steps, scenes=2, solver_iterations=20,
        photons=args.photons, progress=False, **light)
    depth = DesignOptions(steps=args.steps, progress=False, **light)
    made = diffusers(n, z1, depth, args.weights, args.lenslets, end_to_end)
    for seed in range(101, 101 + args.random_seeds):
        made[f"random {seed}"] = (SmoothSurface.random(seed, (n, n), PIXEL, FEATURE, H_MAX),
                                  None)
    shown = {}
    for name, (surface, design_s) in made.items():
        shown[name], row = judge(name, surface, z1, n, volumes, pairs, args, design_s)
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
                     "solver": "admm_tv_3d, VOLUME settings, L2-normalised capture"},
        "random_surfaces_psnr_db": spread,
        "empty_volume_psnr_db": floor,
        "depth_blind_truth_psnr_db": blind,
        "claim": claim})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
