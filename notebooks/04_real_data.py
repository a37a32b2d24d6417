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
# # Real diffuser-camera data: reconstruction walkthrough
#
# The measured data that ships with diffcam (Waller Lab, BSD-3-Clause; see
# `diffcam/data/PROVENANCE.md`):
#
# 1. the DiffuserCam tutorial pair — one PSF and a raw capture of a hand — reconstructed
#    with Richardson–Lucy and with ADMM-TV (at 150 Richardson–Lucy iterations the fingers
#    are a blur; about 1000 resolve them; ADMM-TV has converged by 100);
# 2. the DiffuserCam 3-D example — a 44-plane PSF stack and a raw capture of a tilted
#    USAF target — deconvolved plane by plane to find where each part is in focus.
#
# Set `DIFFCAM_NOTEBOOK_SMALL=1` to run at a reduced size (the test suite does).

# %%
import os
import sys

import matplotlib.pyplot as plt
import numpy as np

from diffcam.core.grid import crop_to
from diffcam.data import load_psf_stack_3d, load_raw_3d, load_tutorial_pair
from diffcam.reconstruct import admm_tv, focus_sweep, richardson_lucy

SMALL = os.environ.get("DIFFCAM_NOTEBOOK_SMALL") == "1"
RL_ITERATIONS = 50 if SMALL else 1000     # the command line's defaults (docs/real_data.md)
ADMM_ITERATIONS = 20 if SMALL else 100

# %% [markdown]
# ## 1. The tutorial pair
# Background (the dark corner of the PSF, 34 counts) is subtracted from both images by
# the loader, as in the tutorial notebooks; `downsample_by` box-averages further.

# %%
pair = load_tutorial_pair(downsample_by=2 if SMALL else 1)
rl = richardson_lucy(pair.image, pair.psf, RL_ITERATIONS, boundary="crop")
admm = admm_tv(pair.image / np.linalg.norm(pair.image), pair.psf / np.linalg.norm(pair.psf),
               ADMM_ITERATIONS)
print(f"RL residual {float(rl.residual[-1]):.4f}, "
      f"ADMM residual {float(np.nanmin(admm.residual)):.4f}")

fig, axes = plt.subplots(1, 4, figsize=(16, 3.6), layout="constrained")
for ax, img, title in zip(axes, [pair.psf, pair.image, crop_to(rl.image, pair.image.shape),
                                 crop_to(admm.image, pair.image.shape)],
                          ["PSF", "raw capture", f"Richardson–Lucy ({RL_ITERATIONS} it)",
                           f"ADMM-TV ({ADMM_ITERATIONS} it)"]):
    shown = ax.imshow(np.asarray(img), cmap="gray")
    fig.colorbar(shown, ax=ax, shrink=0.7)
    ax.set_title(title)
    ax.axis("off")

# %% [markdown]
# ## 2. The 3-D example: which depth is in focus where?
# One batched call deconvolves the capture with every PSF of the stack (ADMM-TV); the
# plane whose PSF leaves the least data misfit explains the capture best. The other
# measure, the sharpness of the reconstructions, depends on the solver: of these ADMM-TV
# ones it peaks near the misfit's minimum, of Richardson–Lucy ones it falls steadily with
# depth and picks the first plane (docs/real_data.md).

# %%
stack = load_psf_stack_3d(downsample_by=2 if SMALL else 1)
raw = load_raw_3d(downsample_by=2 if SMALL else 1)
planes = stack[::4] if SMALL else stack
step = 4 if SMALL else 1
sweep = focus_sweep(raw, planes, iterations=20 if SMALL else 60)
print("best-fitting plane:", step * int(sweep.best), "of", len(stack))

fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), layout="constrained")
depth = step * np.arange(len(planes))
axes[0].plot(depth, np.asarray(sweep.misfit), "o-")
axes[0].set_xlabel("plane (0 nearest the camera)")
axes[0].set_ylabel("data misfit ||Ax − b|| / ||b||")
axes[1].plot(depth, np.asarray(sweep.sharpness), "s-", color="C1")
axes[1].set_xlabel("plane")
axes[1].set_ylabel("sharpness (mean square / squared mean)")
axes[2].imshow(np.asarray(sweep.reconstruction.image[int(sweep.best)]), cmap="gray")
axes[2].set_title(f"reconstruction at plane {step * int(sweep.best)}")
axes[2].axis("off");

# %% [markdown]
# ## 3. The whole stack from two measured planes
# `fit_stack` fits a wave model to planes 5 and 27 only (`docs/stack_fit.md`) and
# predicts the other 42; `compare_stack` scores every plane against the measurement,
# beside the scaling baseline (the nearest given plane magnified) and the
# frozen-distance ablation — the paper's Fig. 9 on real data.

# %%
import warnings

from diffcam.apps.fit_cli import compare_stack
from diffcam.calibrate import StackFitWarning, fit_stack, prepare_planes
from diffcam.evaluate import scaling_baseline
from diffcam.io import downsample
from diffcam.reconstruct import admm_tv_3d

measured_stack = load_psf_stack_3d(downsample_by=2 if SMALL else 1)
GIVEN = [5, 27]
with warnings.catch_warnings():
    warnings.simplefilter("ignore", StackFitWarning)   # reported in fit.summary()
    fit = fit_stack(measured_stack, GIVEN, progress=False,
                    **({"max_steps": 40} if SMALL else {}))
print(fit.stop_reason, f"in {fit.seconds:.1f} s")
scores = compare_stack(measured_stack, fit)
held = scores["mean_held_out"]
print({k: round(v, 4) for k, v in held.items() if isinstance(v, float)},
      f"above the baseline at {held['above_baseline']}/{held['held_out']} planes")

rows = scores["per_plane"]
fig, ax = plt.subplots(figsize=(8, 3.6), layout="constrained")
for key, style, label in [("model", "o-", "wave model"), ("baseline", "s--", "scaling baseline"),
                          ("frozen", ":", "frozen distance (κ = 0)")]:
    ax.plot([r["plane"] for r in rows], [r[key] for r in rows], style, ms=3,
            label=f"{label} ({held[key]:.4f})")
for t in GIVEN:
    ax.axvline(t, color="0.7", lw=0.8)
ax.set_xlabel("plane (0 = nearest source)")
ax.set_ylabel("Pearson with the measured PSF")
ax.legend();

# %% [markdown]
# ## 4. 3-D reconstruction with the predicted stack
# The tilted USAF target reconstructed by ADMM-TV 3-D with the measured stack and with
# the stack predicted from the two planes (both prepared alike: dark level, unit mean per
# plane); colour is the depth of the brightest plane.

# %%
factor = 1 if SMALL else 2
prepared = {"measured": prepare_planes(measured_stack),
            "predicted from planes 5, 27": fit.predict(measured_stack.shape[0]),
            "scaling baseline": scaling_baseline(
                {t: prepare_planes(measured_stack[t]) for t in GIVEN}, measured_stack.shape[0],
                registration=fit.registration)}
raw3d = load_raw_3d(downsample_by=2)
volumes = {}
for name, psfs in prepared.items():
    psfs = np.clip(downsample(np.asarray(psfs, np.float32), factor) if factor > 1 else psfs, 0, None)
    rec = admm_tv_3d(raw3d, psfs, 20 if SMALL else 40)
    volumes[name] = np.asarray(crop_to(rec.image, raw3d.shape))
reference = volumes["measured"]
fig, axes = plt.subplots(2, 3, figsize=(13, 6.5), layout="constrained")
for k, (name, vol) in enumerate(volumes.items()):
    r = np.corrcoef(vol.ravel(), reference.ravel())[0, 1]
    mip = vol.max(axis=0)
    im = axes[0, k].imshow(mip, cmap="gray")
    axes[0, k].set_title(f"{name}\nvolume Pearson vs measured {r:.4f}")
    depth = np.where(mip > 0.1 * mip.max(), vol.argmax(axis=0), np.nan)
    dm = axes[1, k].imshow(depth, cmap="viridis", vmin=0, vmax=vol.shape[0] - 1)
    for ax in axes[:, k]:
        ax.axis("off")
fig.colorbar(dm, ax=axes[1, :], shrink=0.8, label="plane of the maximum");

# %% [markdown]
# Run as a script (`python notebooks/04_real_data.py`), the notebook writes its figures
# to `figures/` (or `$DIFFCAM_FIGURES`); in Jupyter they show inline.

# %%
from diffcam.apps.cli import save_open_figures

if not plt.isinteractive() and "ipykernel" not in sys.modules:
    print("figures:", *save_open_figures("04_real_data"))
