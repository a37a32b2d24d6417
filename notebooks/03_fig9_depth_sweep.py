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
# captured one (Poisson noise, background, the source 4 µm off axis and 0.3 mm out of its
# plane). At z2 = 1 mm the scaling theorem makes the baseline nearly exact; at 5 mm
# diffraction breaks it.

# %%
import os

import matplotlib.pyplot as plt

from diffcam.apps import paper
from diffcam.calibrate import cameraman_phase, resolve_twin

SMALL = os.environ.get("DIFFCAM_NOTEBOOK_SMALL") == "1"
settings = paper.Settings(grid=640 if SMALL else 1024, gs_iterations=10,
                          calibration_iterations=100 if SMALL else 300,
                          psf_crop=512 if SMALL else 576)

# %%
fig3 = paper.fig3_phase_retrieval(cameraman_phase(), settings)
cam = paper.camera(settings)
phase, _ = resolve_twin(fig3["calibrated"],
                              paper.captured_reference(fig3["truth"], cam, paper.DEPTHS[0]),
                              cam, paper.DEPTHS[0])
sweeps = {f"z2 = {z2 * 1e3:g} mm": paper.fig9_depth_sweep(fig3["truth"], phase, settings, z2=z2,
                                                         crop=min(settings.grid, 640))
          for z2 in (1e-3, 5e-3)}

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 4))
for ax, (label, rows) in zip(axes, sweeps.items()):
    z = [r["z1_mm"] for r in rows]
    for key in ("model", "scaling_ideal", "scaling_captured"):
        ax.plot(z, [r[key] for r in rows], "o-", label=key)
    ax.set_title(label)
    ax.set_xlabel("z1 (mm)")
    ax.legend()
for label, rows in sweeps.items():
    print(label)
    for r in rows:
        print(f"  {r['z1_mm']:5.1f} mm  model {r['model']:.4f}  scaling {r['scaling_ideal']:.4f}"
              f"  scaling (captured ref) {r['scaling_captured']:.4f}")
