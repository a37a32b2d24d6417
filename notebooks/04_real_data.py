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
#    with Richardson–Lucy and with ADMM-TV;
# 2. the DiffuserCam 3-D example — a 44-plane PSF stack and a raw capture of a tilted
#    USAF target — deconvolved plane by plane to find where each part is in focus.
#
# Set `DIFFCAM_NOTEBOOK_SMALL=1` to run at a reduced size (the test suite does).

# %%
import os

import matplotlib.pyplot as plt
import numpy as np

from diffcam.data import load_psf_stack_3d, load_raw_3d, load_tutorial_pair
from diffcam.reconstruct import admm_tv, focus_sweep, richardson_lucy

SMALL = os.environ.get("DIFFCAM_NOTEBOOK_SMALL") == "1"
ITERATIONS = 20 if SMALL else 150

# %% [markdown]
# ## 1. The tutorial pair
# Background (the dark corner of the PSF, 34 counts) is subtracted from both images by
# the loader, as in the tutorial notebooks; `downsample_by` box-averages further.

# %%
pair = load_tutorial_pair(downsample_by=2 if SMALL else 1)
rl = richardson_lucy(pair.image, pair.psf, ITERATIONS)
admm = admm_tv(pair.image / np.linalg.norm(pair.image), pair.psf / np.linalg.norm(pair.psf),
               ITERATIONS)
print(f"RL residual {float(rl.residual[-1]):.3f}, ADMM residual {float(np.nanmin(admm.residual)):.3f}")

fig, axes = plt.subplots(1, 4, figsize=(16, 3.6))
for ax, img, title in zip(axes, [pair.psf, pair.image, rl.image, admm.image],
                          ["PSF", "raw capture", f"Richardson–Lucy ({ITERATIONS} it)",
                           f"ADMM-TV ({ITERATIONS} it)"]):
    ax.imshow(np.asarray(img), cmap="gray")
    ax.set_title(title)
    ax.axis("off")
plt.tight_layout()

# %% [markdown]
# ## 2. The 3-D example: which depth is in focus where?
# One batched call deconvolves the capture with every PSF of the stack; the sharpness of
# each reconstruction ranks the depths.

# %%
stack = load_psf_stack_3d(downsample_by=2 if SMALL else 1)
raw = load_raw_3d(downsample_by=2 if SMALL else 1)
planes = stack[::4] if SMALL else stack
sweep = focus_sweep(raw, planes, iterations=10 if SMALL else 40)
print("sharpest plane:", int(sweep.best), "of", len(planes))

fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
axes[0].plot(np.asarray(sweep.sharpness), "o-")
axes[0].set_xlabel("plane")
axes[0].set_ylabel("sharpness")
axes[1].imshow(np.asarray(sweep.reconstruction.image[int(sweep.best)]), cmap="gray")
axes[1].set_title("reconstruction at the sharpest plane")
plt.tight_layout()
