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
# # Figs. 5 and 6 — PSFs from retrieved phases, and Richardson–Lucy reconstructions
#
# The PSF of a point at z1 = 25 mm with the sensor at z2 = 1 mm (paper Eq. 7, by the
# Fresnel scaling theorem), from the true diffuser phase and from phases retrieved with
# more and more iterations. A test object convolved with the *true* PSF is deconvolved
# (150 Richardson–Lucy iterations) with each PSF. The retrieved phase carries the twin
# ambiguity; one captured PSF at 22 mm resolves it (`diffcam.calibrate.resolve_twin`).

#
# The captures and the true PSFs come from a higher-fidelity simulation than the model
# that inverts them (`diffcam.apps.paper`: a 2× finer diffuser grid, three wavelengths, a
# 50 µm source, pixel integration, Poisson noise), so no score is 1 by construction.
# %%
import os

import matplotlib.pyplot as plt

from diffcam.apps import paper
from diffcam.calibrate import cameraman_phase, resolve_twin

SMALL = os.environ.get("DIFFCAM_NOTEBOOK_SMALL") == "1"
settings = paper.Settings(grid=640 if SMALL else 1024, gs_iterations=30 if SMALL else 2000,
                          calibration_iterations=100 if SMALL else 300,
                          rl_iterations=30 if SMALL else 150, psf_crop=512 if SMALL else 576)

# %%
fig3 = paper.fig3_phase_retrieval(cameraman_phase(), settings)
cam = paper.camera(settings)
reference = paper.captured_reference(fig3["truth"], cam, paper.DEPTHS[0])
stages = {"true phase": None, "textbook GS": fig3["gs"]}
for it in (10, settings.calibration_iterations):
    phase = paper.paper_phase(fig3["near"], fig3["far"], iterations=it, refine_iterations=0,
                            restarts=1).phase
    stages[f"calibration {it} it"] = resolve_twin(phase, reference, cam,
                                                        paper.DEPTHS[0])[0]
rows = paper.fig5_psf_and_reconstruction(fig3["truth"], stages, paper.letter_f(), settings)
for r in rows[1:]:
    print(f"{r['stage']:>22}: phase MSE {r['phase_mse']:.3f}, PSF Pearson {r['psf_pearson']:.4f},"
          f" RL SSIM {r['recon_ssim']:.4f}, Pearson {r['recon_pearson']:.4f}")

# %%
fig, axes = plt.subplots(2, len(rows) - 1, figsize=(3.5 * (len(rows) - 1), 7),
                         layout="constrained")
for j, r in enumerate(rows[1:]):
    axes[0, j].imshow(r["_psf"] ** 0.5, cmap="inferno")
    axes[0, j].set_title(r["stage"])
    axes[1, j].imshow(r["_recon"], cmap="gray")
for ax in axes.ravel():
    ax.axis("off")

# %% [markdown]
# ## Fig. 6 — a random diffuser (30 µm features, about 1°) and a textured object
#
# This phase spans many 2π, and the near/far projections stall on it. One captured PSF
# (here at 22 mm) used as a third intensity plane (`diffcam.calibrate.psf_plane`, passed
# to the projections as `planes=`) retrieves it, twin included.

# %%
rnd = paper.fig3_phase_retrieval(paper.random_phase(), settings, psf_z1=paper.DEPTHS[0])
resolved, _ = resolve_twin(
    rnd["calibrated"], paper.captured_reference(rnd["truth"], cam, paper.DEPTHS[0]), cam,
    paper.DEPTHS[0])
rows6 = paper.fig5_psf_and_reconstruction(
    rnd["truth"], {"true phase": None, "near/far calibration": resolved,
                   "+ PSF at 22 mm": rnd["with_psf"]}, paper.flower(), settings)
for r in rows6[1:]:
    print(f"{r['stage']:>20}: phase MSE {r['phase_mse']:.3f}, PSF Pearson "
          f"{r['psf_pearson']:.4f}, RL SSIM {r['recon_ssim']:.4f}")

# %% [markdown]
# Run as a script, the notebook writes its figures to `figures/` (or `$DIFFCAM_FIGURES`);
# in Jupyter they show inline.

# %%
import sys

from diffcam.apps.cli import save_open_figures

if "ipykernel" not in sys.modules:
    print("figures:", *save_open_figures("02_fig5_fig6_psf_and_reconstruction"))
