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
# # Fig. 9 — PSFs over depth: the wave model against the scaling baseline
#
# PSFs for z1 = 22 … 30 mm from the calibrated diffuser phase, against the truth, beside
# the "scaling" baseline (one PSF measured at 22 mm, magnified by
# (1 + z2/z1)/(1 + z2/z1_ref)). The baseline is fed an ideal reference and a realistically
# captured one (Poisson noise, background, the source 0.3 mm out of its plane). The
# "model, true phase" curve is diffcam's model given the true phase: the floor of what a
# retrieved phase can reach against data the model did not make.

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
settings = paper.Settings(grid=640 if SMALL else 1024, gs_iterations=10,
                          calibration_iterations=100 if SMALL else 300)

# %%
fig3 = paper.fig3_phase_retrieval(cameraman_phase(), settings)
cam = paper.camera(settings)
phase, _ = resolve_twin(fig3["calibrated"],
                              paper.captured_reference(fig3["truth"], cam, paper.DEPTHS[0]),
                              cam, paper.DEPTHS[0])
# the demo's calls exactly (same crops), so the numbers are the demo's at the same size
sweeps = {"z2 = 1 mm": paper.fig9_depth_sweep(fig3["truth"], phase, settings),
          "z2 = 5 mm": paper.fig9_depth_sweep(fig3["truth"], phase, settings, z2=5e-3,
                                              crop=min(settings.grid, 704))}

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), layout="constrained")
for ax, (label, rows) in zip(axes, sweeps.items()):
    z = [r["z1_mm"] for r in rows]
    for key, style in (("model", "o-"), ("model_true_phase", "x:"), ("scaling_ideal", "s--"),
                       ("scaling_captured", "^:")):
        ax.plot(z, [r[key] for r in rows], style, label=key.replace("_", " "))
    ax.set_title(label)
    ax.set_xlabel("source depth z1 (mm)")
    ax.set_ylabel("Pearson with the true PSF")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
for label, rows in sweeps.items():
    print(label)
    for r in rows:
        print(f"  {r['z1_mm']:5.1f} mm  model {r['model']:.4f}  (true phase "
              f"{r['model_true_phase']:.4f})  scaling {r['scaling_ideal']:.4f}"
              f"  scaling (captured ref) {r['scaling_captured']:.4f}")

# %% [markdown]
# Run as a script, the notebook writes its figures to `figures/` (or `$DIFFCAM_FIGURES`);
# in Jupyter they show inline.

# %%
import sys

from diffcam.apps.cli import save_open_figures

if "ipykernel" not in sys.modules:
    print("figures:", *save_open_figures("03_fig9_depth_sweep"))
