"""``diffcam demo``: the built-in demonstration, writing a report folder.

Runs on data shipped with the packages (scikit-image's "cameraman" as the diffuser
phase, as in the paper's simulation), with nothing downloaded:

1. checks the propagators against two closed forms (on-axis Fresnel intensity behind a
   circular aperture; the Airy pattern of a Fourier lens),
2. builds the paper's diffuser (cameraman scaled to [−π, π], aperture radius 1.2 mm,
   5 µm pitch) and its PSF for a point at z1 = 25 mm with the sensor at z2 = 1 mm,
3. writes ``demo.png`` and ``metrics.json`` and prints one line of figures.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from . import grid
from .optics import apply_phase, circular_aperture, point_source_field
from .propagate import fourier_lens, propagate
from .sampling import plan_sampling

WAVELENGTH = 532e-9
DX = 5e-6
APERTURE_RADIUS = 1.2e-3
Z1, Z2 = 25e-3, 1e-3
FOCAL_LENGTH = 5e-2


def cameraman_phase(n: int = 512) -> np.ndarray:
    """The paper's ground-truth diffuser phase: "cameraman" scaled linearly to [−π, π]."""
    from skimage.data import camera
    from skimage.transform import resize

    img = camera().astype(np.float64)
    if n != img.shape[0]:
        img = resize(img, (n, n), anti_aliasing=True)
    img = (img - img.min()) / (img.max() - img.min())
    return (2 * img - 1) * np.pi


def _closed_form_checks(n: int) -> dict:
    """Relative errors of the propagators against two closed forms."""
    from scipy.special import j1

    dx = 2e-6
    aperture = circular_aperture((n, n), dx, 40 * dx)
    a = np.sqrt(float(aperture.sum()) / np.pi) * dx
    fresnel_number = 2.5
    z = a * a / (WAVELENGTH * fresnel_number)
    out = propagate(aperture.astype(np.complex64), dx, WAVELENGTH, z, pad=0)
    i_axis = float(abs(out[n // 2, n // 2]) ** 2)
    i_ref = 4 * np.sin(np.pi * fresnel_number / 2) ** 2
    far, (du, _) = fourier_lens(aperture.astype(np.complex64), dx, WAVELENGTH, FOCAL_LENGTH)
    prof = np.abs(np.asarray(far[n // 2, n // 2:])) ** 2
    prof /= prof[0]
    v = 2 * np.pi / WAVELENGTH * a * np.arange(len(prof)) * du / FOCAL_LENGTH
    v[0] = 1e-12
    airy = (2 * j1(v) / v) ** 2
    keep = v < 10.2
    return {"fresnel_on_axis_rel_error": abs(i_axis - i_ref) / i_ref,
            "airy_profile_rms": float(np.sqrt(np.mean((prof[keep] - airy[keep]) ** 2)))}


def run_demo(out_dir: str | os.PathLike = "diffcam-report", n: int = 1024,
             quiet: bool = False) -> dict:
    """Run the demonstration; return the figures that were written to ``metrics.json``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if quiet else print
    t0 = time.perf_counter()

    say("[1/3] propagators against closed forms ...")
    checks = _closed_form_checks(n)

    say(f"[2/3] diffuser PSF, z1 = {Z1 * 1e3:g} mm, z2 = {Z2 * 1e3:g} mm, grid {n}² ...")
    plan = plan_sampling(WAVELENGTH, DX, n, Z1, Z2, APERTURE_RADIUS)
    phase = grid.pad_to(cameraman_phase(512), (n, n))
    aperture = circular_aperture((n, n), DX, APERTURE_RADIUS)
    source = point_source_field((n, n), DX, WAVELENGTH, Z1, aperture_radius=APERTURE_RADIUS)
    field = apply_phase(source * aperture, phase)
    sensor, choice = propagate(field, DX, WAVELENGTH, Z2, return_choice=True)
    psf = np.abs(np.asarray(sensor)) ** 2
    psf /= psf.sum()

    say("[3/3] writing the report ...")
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    half = 300
    c = n // 2
    ext = np.array([-half, half, half, -half]) * DX * 1e3
    axes[0].imshow(np.asarray(phase)[c - half:c + half, c - half:c + half] *
                   np.asarray(aperture)[c - half:c + half, c - half:c + half],
                   cmap="twilight", extent=ext)
    axes[0].set_title("diffuser phase θd (rad) inside the aperture")
    axes[1].imshow(psf[c - half:c + half, c - half:c + half] ** 0.5, cmap="inferno", extent=ext)
    axes[1].set_title(f"PSF at z1 = {Z1 * 1e3:g} mm, z2 = {Z2 * 1e3:g} mm (√ intensity)")
    for ax in axes:
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
    fig.tight_layout()
    fig.savefig(out / "demo.png", dpi=110)
    plt.close(fig)

    metrics = {
        **checks,
        "grid": n,
        "propagator": str(choice),
        "fresnel_number_z2": plan.fresnel_number_z2,
        "chirp_margin": plan.chirp_margin,
        "psf_peak_to_mean": float(psf.max() / psf[psf > 0].mean()),
        "wall_time_s": time.perf_counter() - t0,
    }
    with open(out / "metrics.json", "w") as fh:
        json.dump(metrics, fh, indent=2)
    say(f"diffcam demo: Fresnel on-axis error {checks['fresnel_on_axis_rel_error']:.2e}, "
        f"Airy profile RMS {checks['airy_profile_rms']:.2e}, PSF by {choice.method}, "
        f"N_F(z2) = {plan.fresnel_number_z2:.0f}, {metrics['wall_time_s']:.1f} s → "
        f"{out / 'demo.png'}")
    return metrics
