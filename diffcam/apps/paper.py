"""The paper's simulation experiments (Optics Express 2019, Section 3.1), as functions.

Each returns plain numbers and arrays, so the demo (`diffcam.apps.demo`), the notebooks
and the tests share one implementation:

- `fig3_phase_retrieval` — cameraman phase → near/far captures → textbook GS
  and diffcam's default calibration, scored by the phase metric of docs/design.md;
- `fig5_psf_and_reconstruction` — PSFs from true and retrieved phases at
  z1 = 25 mm, z2 = 1 mm; Richardson–Lucy of a test object; a table per stage;
- `fig9_depth_sweep` — PSFs over z1 = 22 … 30 mm: model vs truth vs the scaling
  baseline anchored at 22 mm (ideal and realistically captured reference).

**No inverse crime.** The captures and the true PSFs are made by a higher-fidelity model
than the one that inverts them (`diffcam.calibrate.simulation.high_fidelity_captures`
and `high_fidelity_psfs`: the diffuser on a grid 2×
finer, three wavelengths over 12 nm, a 50 µm source, pixel integration, Poisson noise);
diffcam's model (monochromatic, at the sensor pitch, a point source) inverts them and
predicts the PSFs. Even the true phase through diffcam's model then scores below 1: the
"true phase, diffcam's model" rows and curves are that floor.

Geometry (docs/design.md, "The paper's simulation"): 5 µm pitch, diffuser 512 × 512 at
the grid centre, aperture radius 1.2 mm, λ = 532 nm, Fourier lens f = 5 cm.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from diffcam.model import Camera, psf, random_diffuser
from diffcam.core.grid import pad_to
from diffcam.evaluate.metrics import pearson, phase_scores, psf_fidelity, ssim
from diffcam.optics.elements import circular_aperture
from diffcam.reconstruct import convolution_model, richardson_lucy
from diffcam.calibrate import CalibrationGeometry, gerchberg_saxton, paper_simulation, psf_plane
from diffcam.calibrate.simulation import (PAPER_APERTURE_RADIUS, PAPER_DX, PAPER_FOCAL_LENGTH,
                                          PAPER_WAVELENGTH, high_fidelity_captures,
                                          high_fidelity_psfs)
from diffcam import calibrate   # calibrate.retrieve_phase: optimistix loads with it
from diffcam.evaluate.baseline import magnify_psf
from diffcam.model.stack import psf_stack

WAVELENGTH, DX = PAPER_WAVELENGTH, PAPER_DX
APERTURE_RADIUS, FOCAL_LENGTH = PAPER_APERTURE_RADIUS, PAPER_FOCAL_LENGTH
DIFFUSER_SIZE = 512
Z1, Z2 = 25e-3, 1e-3
DEPTHS = np.arange(22, 31) * 1e-3
SCORE_WINDOW = 300  # the paper scores phases on the central 300 × 300
CAPTURE_PHOTONS = 1e5   # photons at the brightest pixel of the near and far captures
PSF_PHOTONS = 1e5       # ... and of a true PSF (the captured reference: 1e4)
TRUTH_MODEL = ("higher-fidelity simulation: diffuser on a 2× finer grid, 3 wavelengths "
               "(526/532/538 nm), a 50 µm source, pixel integration, Poisson noise "
               f"({CAPTURE_PHOTONS:.0e} photons at the peak)")


@dataclasses.dataclass(frozen=True)
class Settings:
    """Sizes of a run: ``grid`` samples per side of the simulation, iteration counts."""

    grid: int = 1024
    gs_iterations: int = 2000
    calibration_iterations: int = 300
    rl_iterations: int = 150
    psf_crop: int = 576


def letter_f(size: int = 70) -> np.ndarray:
    """The paper's test object: a block letter "F", ``size`` samples tall (70 = 0.35 mm)."""
    obj = np.zeros((size, size), np.float32)
    s = max(size // 5, 1)
    left = size // 5
    obj[:, left:left + s] = 1
    obj[:s, left:size - size // 8] = 1
    obj[size // 2 - s // 2:size // 2 + s - s // 2, left:size - size // 4] = 1
    return obj


def flower(size: int = 120, petals: int = 6, holes: int = 24, seed: int = 0) -> np.ndarray:
    """A textured "flower" with fine holes (the paper's Fig. 6 object), ``size`` samples."""
    rng = np.random.default_rng(seed)
    c = (np.arange(size) - size // 2) / (size / 2)
    y, x = np.meshgrid(c, c, indexing="ij")
    r, t = np.hypot(x, y), np.arctan2(y, x)
    obj = (r < 0.35 + 0.6 * np.abs(np.cos(petals / 2 * t))).astype(np.float32)
    obj *= 0.6 + 0.4 * np.cos(12 * np.pi * r) ** 2
    obj[r < 0.2] = 1.0
    for _ in range(holes):  # holes of 1–2 samples radius in the petals
        cy, cx = rng.integers(0, size, 2)
        hole = (np.arange(size)[:, None] - cy) ** 2 + (np.arange(size)[None, :] - cx) ** 2
        obj[hole <= rng.integers(1, 4)] = 0
    return obj


def random_phase(seed: int = 0) -> np.ndarray:
    """The Fig. 6 diffuser: random phase, 30 µm features, about 1° deflection."""
    return np.asarray(random_diffuser(jax.random.PRNGKey(seed), (DIFFUSER_SIZE,) * 2, DX,
                                      WAVELENGTH, feature_size=30e-6))


def geometry() -> CalibrationGeometry:
    """The paper's calibration set-up (near field at the diffuser, as in its simulation)."""
    return CalibrationGeometry(dx=DX, wavelength=WAVELENGTH, focal_length=FOCAL_LENGTH)


def _scores(estimate, truth, n):
    """The phase figures of docs/design.md on the central 300 × 300, inside the aperture."""
    c, h = n // 2, SCORE_WINDOW // 2
    win = (slice(c - h, c + h), slice(c - h, c + h))
    mask = np.asarray(circular_aperture((n, n), DX, APERTURE_RADIUS))[win]
    s = phase_scores(jnp.asarray(estimate)[win], jnp.asarray(truth)[win], mask=mask)
    return {k: float(v) for k, v in s.items()}


def paper_phase(near, far, *, iterations: int, refine_iterations: int = 50, restarts: int = 2,
                planes=()):
    """diffcam's default calibration path (`diffcam.calibrate.retrieve_phase`: RAAR with
    random restarts, then ``refine_iterations`` least-squares steps, 0 for none) on the
    paper's aperture; a RetrievalResult. With ``planes`` (a captured PSF,
    `diffcam.calibrate.psf_plane`) it starts flat, once."""
    n = np.shape(near)[-1]
    aperture = circular_aperture((n, n), DX, APERTURE_RADIUS)
    refine = None if not refine_iterations else calibrate.FitOptions.of(
        calibrate.phase.pipeline.POLISH, iterations=refine_iterations)
    return calibrate.retrieve_phase(near, far, geometry(), aperture, iterations=iterations,
                                    refine=refine, planes=planes,
                                    restarts=None if planes else restarts)


def fig3_phase_retrieval(truth_512: np.ndarray, s: Settings, seed: int = 0,
                         psf_z1: float | None = None) -> dict:
    """Near/far captures of the diffuser ``truth_512`` in the paper's set-up on the
    ``s.grid`` grid, made by `diffcam.calibrate.simulation.high_fidelity_captures`
    (module docstring); textbook GS and the default calibration; phase figures and wall
    times. With ``psf_z1`` (metres), also the calibration with one captured PSF at that
    depth as a third plane (``"with_psf"`` keys)."""
    n = s.grid
    sim = paper_simulation(n, DIFFUSER_SIZE, phase=truth_512)
    truth, aperture = np.asarray(sim.phase), sim.aperture
    near, far = high_fidelity_captures(truth, PAPER_APERTURE_RADIUS, geometry(),
                                       photons=CAPTURE_PHOTONS, seed=seed)
    t = time.perf_counter()
    gs = gerchberg_saxton(near, far, geometry(), iterations=s.gs_iterations,
                          key=jax.random.PRNGKey(seed))
    t_gs = time.perf_counter() - t
    t = time.perf_counter()
    cal = paper_phase(near, far, iterations=s.calibration_iterations)
    t_cal = time.perf_counter() - t
    out = {"truth": truth, "aperture": np.asarray(aperture), "far": np.asarray(far),
           "gs": np.asarray(gs.phase), "calibrated": np.asarray(cal.phase),
           "gs_scores": _scores(gs.phase, truth, n), "gs_seconds": t_gs,
           "calibrated_scores": _scores(cal.phase, truth, n), "calibrated_seconds": t_cal,
           "flat_scores": _scores(np.zeros_like(truth), truth, n),
           "calibration_method": cal.stats["method"],
           "near": np.asarray(near)}
    if psf_z1 is not None:
        cam = camera(s)
        captured = high_fidelity_psfs(truth, cam, psf_z1, photons=PSF_PHOTONS, seed=seed)[0]
        plane = psf_plane(jnp.asarray(captured), cam, psf_z1)
        t = time.perf_counter()
        with_psf = paper_phase(near, far, iterations=s.calibration_iterations, planes=[plane])
        out.update(with_psf=np.asarray(with_psf.phase),
                   with_psf_seconds=time.perf_counter() - t,
                   with_psf_scores=_scores(with_psf.phase, truth, n))
    return out


def _object_scores(rec, scene, margin: int = 8):
    """SSIM and Pearson of a reconstruction on the object's bounding box (plus
    ``margin`` samples): the full frame is mostly black background, which inflates SSIM."""
    ys, xs = np.nonzero(scene)
    box = (slice(max(ys.min() - margin, 0), ys.max() + margin + 1),
           slice(max(xs.min() - margin, 0), xs.max() + margin + 1))
    r, t = jnp.asarray(rec)[box], jnp.asarray(scene)[box]
    return float(ssim(r, t, data_range=float(t.max()))), float(pearson(r, t))


def camera(s: Settings, z2: float = Z2, crop: int | None = None) -> Camera:
    """The simulated camera on the ``s.grid`` grid (scaling-theorem PSFs)."""
    c = crop or s.psf_crop
    return Camera(wavelength=WAVELENGTH, z2=z2, dx=DX, aperture_radius=APERTURE_RADIUS,
                  shape=(s.grid, s.grid), crop=(c, c))


def _embed(obj, shape):
    return np.asarray(pad_to(jnp.asarray(obj), shape))


def fig5_psf_and_reconstruction(truth: np.ndarray, stages: dict, obj: np.ndarray,
                                s: Settings) -> list[dict]:
    """For each stage (name → phase on the grid; ``None``: the true phase): phase MSE,
    PSF Pearson against the true PSF (`high_fidelity_psfs`, noise-free), and SSIM /
    Pearson of a Richardson–Lucy reconstruction of ``obj`` from a sensor image made with
    the true PSF; every stage's PSF, the true phase's included, is diffcam's model."""
    cam = camera(s)
    true_psf = jnp.asarray(high_fidelity_psfs(truth, cam, Z1)[0])
    scene = _embed(obj, cam.out_shape)
    sensor = convolution_model(true_psf, cam.out_shape)(jnp.asarray(scene))
    rows = []
    for name, phase in stages.items():
        p = psf(jnp.asarray(truth if phase is None else phase), cam, Z1)
        rec = richardson_lucy(sensor, p, s.rl_iterations).image
        rec = rec * (scene.sum() / rec.sum())
        rows.append({
            "stage": name,
            "phase_mse": 0.0 if phase is None else _scores(phase, truth, s.grid)["mse"],
            "object_ssim": _object_scores(rec, scene)[0],
            "object_pearson": _object_scores(rec, scene)[1],
            "psf_pearson": float(pearson(p, true_psf)),
            "recon_ssim": float(ssim(rec, scene, data_range=float(scene.max()))),
            "recon_pearson": float(pearson(rec, scene)),
            "_psf": np.asarray(p), "_recon": np.asarray(rec),
        })
    rows.insert(0, {"stage": "sensor image", "_sensor": np.asarray(sensor),
                    "_scene": scene})
    return rows


def captured_reference(truth, cam, z1_ref, *, defocus=0.3e-3, photons=1e4,
                       background=0.01, seed=0):
    """A realistically captured reference PSF: the higher-fidelity PSF
    (`high_fidelity_psfs`) with the source out of its nominal plane by ``defocus``
    (m), Poisson noise at ``photons`` at the peak over a ``background`` (fraction of the
    peak) that is then subtracted."""
    p = high_fidelity_psfs(truth, cam, z1_ref + defocus)[0]
    p = p / p.max() * photons + background * photons
    noisy = np.random.default_rng(seed).poisson(p).astype(np.float32)
    noisy = np.clip(noisy - background * photons, 0, None)
    return jnp.asarray(noisy / noisy.sum())


def fig9_depth_sweep(truth: np.ndarray, model_phase: np.ndarray, s: Settings,
                     z2: float = Z2, crop: int | None = None) -> list[dict]:
    """Per depth: Pearson (after registration) against the true PSF
    (`high_fidelity_psfs`, noise-free) of diffcam's model PSF from ``model_phase``
    and from the true phase (the model's floor), and of the scaling baseline from an
    ideal (the true PSF) and from a captured reference at 22 mm."""
    cam = camera(s, z2=z2, crop=crop)
    true = jnp.asarray(high_fidelity_psfs(truth, cam, DEPTHS))
    model = psf_stack(jnp.asarray(model_phase), cam, DEPTHS, progress=False)
    model_true = psf_stack(jnp.asarray(truth), cam, DEPTHS, progress=False)
    ideal = magnify_psf(true[0], DX, DEPTHS[0], DEPTHS, z2)
    captured = magnify_psf(captured_reference(truth, cam, DEPTHS[0]), DX, DEPTHS[0], DEPTHS, z2)
    scores = [psf_fidelity(jnp.asarray(a), true)["pearson"]
              for a in (model, model_true, ideal, captured)]
    return [{"z1_mm": round(float(z) * 1e3, 3), "model": float(a),
             "model_true_phase": float(b), "scaling_ideal": float(c),
             "scaling_captured": float(d)} for z, a, b, c, d in zip(DEPTHS, *scores)]
