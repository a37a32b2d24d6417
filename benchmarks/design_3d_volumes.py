"""The held-out volumes of `bench_design_3d`, their captures through a diffuser's truth
PSFs, their reconstruction and their scores: sparse scenes of Gaussian blobs and the
two-point test, captures with shot and read noise, the measured calibration stack,
ADMM-TV volumes, volume PSNR and the two-point criterion."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from diffcam.calibrate.simulation import recorded_psfs
from diffcam.evaluate import psnr
from diffcam.reconstruct import admm_tv_3d, convolution_model
from diffcam.reconstruct.admm import VOLUME, AdmmOptions

READ_NOISE = 2.0
"""Gaussian read noise, photons (electrons) per pixel."""
DIP = 0.8
"""Two points are resolved when the axial profile between their peaks falls to this
fraction of the lower peak (or below)."""
BLOB_SIGMA = 1.0
"""Standard deviation of a scene's Gaussian blobs, object-grid samples."""
CALIBRATION_SEED = 3000
"""The seed of the calibration PSFs' noise (captures: 7; scenes: 1000 + k, 2000)."""
TUNING_FACTORS = (0.1, 1.0, 10.0)
"""With ``--tune``, the factors on `VOLUME`'s TV and L1 weights tried per diffuser."""
TRAINING_SEED = 2000
"""The seed of the scene ``--tune`` chooses the weights on (held-out scenes: 1000 + k)."""
FINE_TWO_POINT_SEED = 4000
"""The seed of the finer two-point test's captures (plus the points' plane count apart:
every diffuser gets the same noise for the same pair)."""
SOURCE_SHARE = 0.1
"""`bounds`: a voxel is on a source where the truth is at least this share of its peak."""


def calibration(truth_psfs: np.ndarray, photons: float) -> np.ndarray:
    """The PSF stack measured through ``truth_psfs`` (each of unit sum): Poisson noise
    at ``photons`` at each PSF's brightest pixel, each normalised to unit sum."""
    return recorded_psfs(truth_psfs, photons, np.random.default_rng(CALIBRATION_SEED))


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


def reconstruct(b: np.ndarray, psfs: np.ndarray, iterations: int,
                options: AdmmOptions) -> np.ndarray:
    """ADMM-TV volumes of the captures ``b`` (…, n, n), each scaled to unit L2 norm."""
    unit = b / np.linalg.norm(b, axis=(-2, -1), keepdims=True)
    return np.asarray(admm_tv_3d(unit, psfs, iterations, options,
                                 progress=False).image)


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


def depth_blind(volume: np.ndarray) -> np.ndarray:
    """``volume``'s mean over planes, on every plane: its lateral content, no depth."""
    return np.broadcast_to(volume.mean(axis=0), volume.shape)


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
