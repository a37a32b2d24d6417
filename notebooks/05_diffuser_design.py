# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Designing a diffuser for 3-D, and judging it against a random one
#
# A diffuser camera holds depth in one capture when the PSFs of different depths differ.
# `diffcam.design` optimises a manufacturable surface (a smooth height map: heights
# 0–2 µm, features ≥ 30 µm, n 1.5) so that the PSFs over a depth range correlate as
# little as possible, with gradients through the wave model of the camera.
#
# The camera here: 128² pixels of 3 µm, z2 = 2 mm, an aperture of radius 0.45 of the
# frame width, 8 depths from 10 to 60 mm. The design sees the light a camera records
# (three lines over a 12 nm band, a 50 µm source); the judge is a higher-fidelity
# simulator (the field on a 2× finer grid, integrated over each pixel, the source's
# off-axis PSFs), a measured calibration with shot noise, captures of a held-out
# volume with shot and read noise, and the 3-D ADMM-TV solver `diffcam reconstruct
# --3d` uses. The random surface has the same limits. (`docs/diffuser_design.md`
# measures the same on more scenes and surfaces.)
#
# Set `DIFFCAM_NOTEBOOK_SMALL=1` to run shorter (the test suite does).

# %%
import dataclasses
import os
import sys

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

from diffcam.calibrate.simulation import (HIGH_FIDELITY_SPECTRUM, high_fidelity_psfs,
                                         recorded_psfs)
from diffcam.design import DesignOptions, SmoothSurface, depth_range, design
from diffcam.design.objective import pair_correlations, standardised
from diffcam.design.surfaces import height_map
from diffcam.evaluate import psnr
from diffcam.model import Camera
from diffcam.model.sensor import read_noise, shot_noise
from diffcam.optics.propagation import effective_distance, transfer_pad
from diffcam.reconstruct import admm_tv_3d, convolution_model
from diffcam.reconstruct.admm import VOLUME

SMALL = os.environ.get("DIFFCAM_NOTEBOOK_SMALL") == "1"
STEPS, ITERATIONS = (60, 100) if SMALL else (300, 200)
N, PIXEL, Z2, INDEX = 128, 3e-6, 2e-3, 1.5
z1 = depth_range(10e-3, 60e-3, 8)            # even in 1/z1: neighbours equally alike

# The aperture's footprint on the sensor, radius a·(1 + z2/z1), reaches 0.54 of the frame
# at 10 mm: the grid is padded by 31 samples a side so that no PSF wraps around; the
# judge's grid, 2× finer, also needs N·dx²/λ ≥ z_eff at the farthest depth.
camera = Camera(wavelength=532e-9, z2=Z2, dx=PIXEL, aperture_radius=0.45 * N * PIXEL,
                shape=(N, N), pad=(31, 31))
pad = max(31, transfer_pad(N, PIXEL, 2 * HIGH_FIDELITY_SPECTRUM[0].max(),
                           effective_distance(z1.max(), Z2)))
judge_camera = dataclasses.replace(camera, pad=(pad, pad))

# %% [markdown]
# ## The design
#
# Adam on the surface's spline coefficients, `STEPS` steps, against the smooth maximum
# of the pairwise PSF correlations plus 0.1 × their spread (sparse, high-contrast PSFs).

# %%
start = SmoothSurface.random(0, (N, N), PIXEL, feature_size=30e-6, height_max=2e-6)
random_surface = SmoothSurface.random(100, (N, N), PIXEL, feature_size=30e-6,
                                      height_max=2e-6)
light = DesignOptions(steps=STEPS, bandwidth=6e-9, source_radius=50e-6, progress=False)
designed = design(start, camera, z1, INDEX, light)

fig, ax = plt.subplots(figsize=(6, 3.2), layout="constrained")
ax.plot(designed.history[:, 2], label="largest correlation between depths (design model)")
ax.plot(designed.history[:, 3], label="spread (L1/L2 ratio)")
ax.set_xlabel("Adam step")
ax.legend();

# %% [markdown]
# ## The PSFs across depth, as the higher-fidelity simulator makes them
#
# The designed surface gathers the light into a few compact foci on a ring: the ring
# scales with the magnification 1 + z2/z1, and the foci are sharp at one end of the
# range and blurred at the other — two depth cues. A random surface spreads a caustic
# net over its whole footprint.

# %%
surfaces = {"designed": designed.surface, "random": random_surface}
truth = {name: np.asarray(high_fidelity_psfs(height_map(s, INDEX).phase(camera.wavelength),
                                             judge_camera, z1))
         for name, s in surfaces.items()}

fig, axes = plt.subplots(2, 3, figsize=(11, 6.6), layout="constrained")
for row, (name, psfs) in zip(axes, truth.items()):
    for ax, k in zip(row[:2], (0, len(z1) - 1)):
        ax.imshow(psfs[k] ** 0.5, cmap="gray")
        ax.set_title(f"{name}: PSF at {z1[k] * 1e3:.0f} mm (√)")
        ax.axis("off")
    pairs = np.asarray(pair_correlations(standardised(jnp.asarray(psfs))))
    matrix = np.eye(len(z1))
    matrix[np.triu_indices(len(z1), 1)] = pairs
    matrix = np.maximum(matrix, matrix.T)
    im = row[2].imshow(matrix, vmin=0.5, vmax=1, cmap="viridis")
    row[2].set_title(f"{name}: depth correlations, max {pairs.max():.3f}")
    row[2].set_xlabel("depth index")
    fig.colorbar(im, ax=row[2], shrink=0.8)

# %% [markdown]
# ## A held-out volume, reconstructed through each diffuser
#
# Sixteen Gaussian blobs at random depths and positions in the central half of the
# field. Each camera is calibrated as a user would calibrate it (a point source at each
# depth, recorded with shot noise at 10⁴ photons at the brightest pixel); the capture
# has 1000 photons per pixel on average, shot noise and 2 photons of read noise.

# %%
rng = np.random.default_rng(1000)
model = convolution_model(jnp.asarray(truth["random"]), (N, N), "crop", volume=True)
volume = np.zeros((len(z1), *model.object_shape))
yy, xx = np.indices(volume.shape[1:])
centre = np.array(volume.shape[1:]) // 2
for _ in range(2 * len(z1)):
    y, x = centre + rng.uniform(-N / 4 + 2, N / 4 - 3, 2)
    volume[rng.integers(len(z1))] += rng.uniform(0.5, 1) * np.exp(
        -((yy - y) ** 2 + (xx - x) ** 2) / 2)

field = tuple(slice(c - N // 4, c + N // 4) for c in centre)
estimates = {}
for key, (name, psfs) in zip(jax.random.split(jax.random.key(7), 2), truth.items()):
    model = convolution_model(jnp.asarray(psfs), (N, N), "crop", volume=True)
    expected = np.asarray(model(jnp.asarray(volume, jnp.float32)), np.float64)
    expected *= 1000 * N * N / volume.sum()
    shot, read = jax.random.split(key)
    capture = np.clip(np.asarray(read_noise(read, shot_noise(shot, expected), 2.0)), 0, None)
    calibration = recorded_psfs(psfs, 1e4, rng)
    estimate = np.asarray(admm_tv_3d(capture / np.linalg.norm(capture), calibration,
                                     ITERATIONS, VOLUME, progress=False).image)
    e, t = (v[:, field[0], field[1]].reshape(len(z1), -1) for v in (estimate, volume))
    estimates[name] = (estimate, float(psnr(jnp.asarray(e, jnp.float32),
                                            jnp.asarray(t, jnp.float32), align="scale")))
    print(f"{name}: volume PSNR {estimates[name][1]:.2f} dB")

# %%
fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), layout="constrained")
views = {"truth": volume, **{f"{k} ({v[1]:.1f} dB)": v[0] for k, v in estimates.items()}}
for ax, (title, v) in zip(axes, views.items()):
    ax.imshow(v[:, field[0], field[1]].max(axis=1), aspect="auto", cmap="magma")
    ax.set_title(f"{title}: x–z max projection")
    ax.set_xlabel("x (pixels)")
    ax.set_ylabel("depth index (0 = 10 mm)")

# %% [markdown]
# Run as a script (`python notebooks/05_diffuser_design.py`), the notebook writes its
# figures to `figures/` (or `$DIFFCAM_FIGURES`); in Jupyter they show inline.

# %%
from diffcam.apps.cli import save_open_figures

if not plt.isinteractive() and "ipykernel" not in sys.modules:
    print("figures:", *save_open_figures("05_diffuser_design"))
