"""The paper's simulation experiments (Optics Express 2019, Section 3.1), as functions.

Each returns plain numbers and arrays, so the demo (:mod:`diffcam.apps.demo`), the notebooks
and the tests share one implementation:

- :func:`fig3_phase_retrieval` — cameraman phase → near/far intensities → textbook GS
  and diffcam's default calibration, scored by the phase metric of docs/design.md;
- :func:`fig5_psf_and_reconstruction` — PSFs from true and retrieved phases at
  z1 = 25 mm, z2 = 1 mm; Richardson–Lucy of a test object; a table per stage;
- :func:`fig9_depth_sweep` — PSFs over z1 = 22 … 30 mm: model vs truth vs the scaling
  baseline anchored at 22 mm (ideal and realistically captured reference).

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
                                PAPER_WAVELENGTH)
from diffcam.calibrate import FitOptions, retrieve_phase
from diffcam.calibrate.pipeline import POLISH
from diffcam.evaluate.baseline import magnify_psf
from diffcam.model.stack import psf_stack

WAVELENGTH, DX = PAPER_WAVELENGTH, PAPER_DX
APERTURE_RADIUS, FOCAL_LENGTH = PAPER_APERTURE_RADIUS, PAPER_FOCAL_LENGTH
DIFFUSER_SIZE = 512
Z1, Z2 = 25e-3, 1e-3
DEPTHS = np.arange(22, 31) * 1e-3
SCORE_WINDOW = 300  # the paper scores phases on the central 300 × 300


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
    """diffcam's default calibration path (:func:`diffcam.calibrate.retrieve_phase`: RAAR with
    random restarts, then ``refine_iterations`` least-squares steps, 0 for none) on the
    paper's aperture; a RetrievalResult. With ``planes`` (a captured PSF,
    :func:`diffcam.calibrate.psf_plane`) it starts flat, once."""
    n = np.shape(near)[-1]
    aperture = circular_aperture((n, n), DX, APERTURE_RADIUS)
    refine = FitOptions.of(POLISH, iterations=refine_iterations) if refine_iterations else None
    return retrieve_phase(near, far, geometry(), aperture, iterations=iterations,
                          refine=refine, planes=planes, restarts=None if planes else restarts)


def fig3_phase_retrieval(truth_512: np.ndarray, s: Settings, seed: int = 0,
                         psf_z1: float | None = None) -> dict:
    """Near/far intensities of the diffuser ``truth_512`` in the paper's set-up
    (:func:`diffcam.calibrate.paper_simulation` on the ``s.grid`` grid); textbook GS and
    the default calibration; phase figures and wall times. With ``psf_z1`` (metres), also
    the calibration with one captured PSF at that depth as a third plane (``"with_psf"``
    keys)."""
    n = s.grid
    sim = paper_simulation(n, DIFFUSER_SIZE, phase=truth_512)
    truth, aperture, near, far = np.asarray(sim.phase), sim.aperture, sim.near, sim.far
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
        plane = psf_plane(psf(jnp.asarray(truth), cam, psf_z1), cam, psf_z1)
        t = time.perf_counter()
        with_psf = paper_phase(near, far, iterations=s.calibration_iterations, planes=[plane])
        out.update(with_psf=np.asarray(with_psf.phase),
                   with_psf_seconds=time.perf_counter() - t,
                   with_psf_scores=_scores(with_psf.phase, truth, n))
    return out


def camera(s: Settings, z2: float = Z2, crop: int | None = None) -> Camera:
    """The simulated camera on the ``s.grid`` grid (scaling-theorem PSFs)."""
    c = crop or s.psf_crop
    return Camera(wavelength=WAVELENGTH, z2=z2, dx=DX, aperture_radius=APERTURE_RADIUS,
                  shape=(s.grid, s.grid), crop=(c, c))


def _embed(obj, shape):
    return np.asarray(pad_to(jnp.asarray(obj), shape))


def fig5_psf_and_reconstruction(truth: np.ndarray, stages: dict, obj: np.ndarray,
                                s: Settings) -> list[dict]:
    """For each stage (name → phase on the grid): phase MSE, PSF Pearson against the
    true PSF, and SSIM / Pearson of a Richardson–Lucy reconstruction of ``obj`` from a
    sensor image made with the true PSF."""
    cam = camera(s)
    true_psf = psf(jnp.asarray(truth), cam, Z1)
    scene = _embed(obj, cam.out_shape)
    sensor = convolution_model(true_psf, cam.out_shape)(jnp.asarray(scene))
    rows = []
    for name, phase in stages.items():
        p = true_psf if phase is None else psf(jnp.asarray(phase), cam, Z1)
        rec = richardson_lucy(sensor, p, s.rl_iterations).image
        rec = rec * (scene.sum() / rec.sum())
        rows.append({
            "stage": name,
            "phase_mse": 0.0 if phase is None else _scores(phase, truth, s.grid)["mse"],
            "psf_pearson": float(pearson(p, true_psf)),
            "recon_ssim": float(ssim(rec, scene, data_range=float(scene.max()))),
            "recon_pearson": float(pearson(rec, scene)),
            "_psf": np.asarray(p), "_recon": np.asarray(rec),
        })
    rows.insert(0, {"stage": "sensor image", "_sensor": np.asarray(sensor),
                    "_scene": scene})
    return rows


def captured_reference(truth, cam, z1_ref, *, offset=4e-6, defocus=0.3e-3, photons=1e4,
                       background=0.01, seed=0):
    """A realistically captured reference PSF: the point source slightly off axis and
    out of its nominal plane, Poisson noise at ``photons`` peak, a background offset."""
    p = psf(jnp.asarray(truth), cam, z1_ref + defocus, x1=offset)
    p = p / p.max() * photons + background * photons
    noisy = jax.random.poisson(jax.random.PRNGKey(seed), p).astype(jnp.float32)
    noisy = jnp.clip(noisy - background * photons, 0, None)
    return noisy / noisy.sum()


def fig9_depth_sweep(truth: np.ndarray, model_phase: np.ndarray, s: Settings,
                     z2: float = Z2, crop: int | None = None) -> list[dict]:
    """Per depth: Pearson (after registration) of the model PSF (from ``model_phase``) and
    of the scaling baseline from an ideal and from a captured reference at 22 mm, all
    against the true PSF."""
    cam = camera(s, z2=z2, crop=crop)
    true = psf_stack(jnp.asarray(truth), cam, DEPTHS, progress=False)
    model = psf_stack(jnp.asarray(model_phase), cam, DEPTHS, progress=False)
    ideal = magnify_psf(jnp.asarray(true[0]), DX, DEPTHS[0], DEPTHS, z2)
    captured = magnify_psf(captured_reference(truth, cam, DEPTHS[0]), DX, DEPTHS[0], DEPTHS, z2)
    f_model = psf_fidelity(jnp.asarray(model), jnp.asarray(true))["pearson"]
    f_ideal = psf_fidelity(ideal, jnp.asarray(true))["pearson"]
    f_capt = psf_fidelity(captured, jnp.asarray(true))["pearson"]
    return [{"z1_mm": round(float(z) * 1e3, 3), "model": float(a), "scaling_ideal": float(b),
             "scaling_captured": float(c)} for z, a, b, c in zip(DEPTHS, f_model, f_ideal,
                                                                  f_capt)]
