"""``diffcam demo``: the paper's Section 3.1 end to end, written to a report folder.

Runs on built-in data only (scikit-image's "cameraman" is the diffuser phase, as in the
paper; the random diffuser and the test objects are generated), nothing downloaded. The
captures and true PSFs come from a higher-fidelity simulation than the model that
inverts them (`diffcam.apps.paper`), so no score is perfect by construction:

1. Fig. 3 — phase retrieval from near/far intensities: textbook Gerchberg–Saxton
   (which stagnates) and diffcam's default calibration, scored on the central 300²;
2. the twin ambiguity resolved by one captured PSF at z1 = 22 mm;
3. Fig. 5 — PSFs at z1 = 25 mm, z2 = 1 mm from the true and retrieved phases, and
   Richardson–Lucy (150 iterations) of an "F";
4. Fig. 6 — the same with a 30 µm random diffuser and a textured "flower": near/far
   alone stall on it; one PSF at 22 mm as a third plane retrieves it;
5. Fig. 9 — PSFs over z1 = 22 … 30 mm: model vs truth vs the scaling baseline anchored
   at 22 mm (ideal and realistically captured reference), at z2 = 1 mm and 5 mm.

Writes ``fig3_phase.png``, ``fig5_cameraman.png``, ``fig6_random.png``,
``fig9_depths.png``, ``metrics.json`` and ``report.md``.
"""

from __future__ import annotations

import json
import os
import time

import numpy as np

from diffcam.apps import paper
from diffcam.apps.common import save_figure
from diffcam.io import make_output_folder
from diffcam import calibrate   # calibrate.resolve_twin: optimistix loads with it
from diffcam.calibrate.simulation import cameraman_phase
from diffcam.core.backend import fft_status
from diffcam.evaluate.metrics import phase_offset, wrap_phase

_STEPS = 5


def _plot_phases(path, fig3):
    import matplotlib.pyplot as plt

    n = fig3["truth"].shape[0]
    c, h = n // 2, 260
    win = (slice(c - h, c + h), slice(c - h, c + h))
    mask = fig3["aperture"][win] > 0
    panels = [("true phase θd", fig3["truth"]),
              (f"textbook GS (P = {fig3['gs_scores']['pearson']:.3f})", fig3["gs"]),
              (f"diffcam calibration (P = {fig3['resolved_scores']['pearson']:.3f})",
               fig3["resolved"])]
    fig, axes = plt.subplots(1, 4, figsize=(18, 4.6), layout="constrained")

    for ax, (title, ph) in zip(axes, panels):
        d = phase_offset(ph[win], fig3["truth"][win], mask=mask)  # show piston-aligned
        shown = ax.imshow(np.where(mask, wrap_phase(ph[win] - d), np.nan), cmap="twilight",
                          vmin=-np.pi, vmax=np.pi)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.colorbar(shown, ax=axes[:3], shrink=0.8, label="phase (rad), piston-aligned")
    _scale_bar(axes[0], 1e-3 / paper.DX, "1 mm")
    far = fig3["far"][c - 128:c + 128, c - 128:c + 128]
    shown = axes[3].imshow(np.log10(far / far.max() + 1e-6), cmap="magma")
    axes[3].set_title("far-field capture (log10), centre", fontsize=10)
    axes[3].axis("off")
    fig.colorbar(shown, ax=axes[3], shrink=0.8)
    save_figure(fig, path)


def _scale_bar(ax, length: float, label: str) -> None:
    """A white bar of ``length`` samples in the lower left of an image axis."""
    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    x, y = x0 + 0.06 * (x1 - x0), y0 + 0.08 * (y1 - y0)   # from the bottom, either way up
    ax.plot([x, x + length], [y, y], color="white", lw=3)
    ax.text(x + length / 2, y, label, color="white", ha="center", va="bottom", fontsize=8)


def _plot_stages(path, rows, title):
    import matplotlib.pyplot as plt

    head, stages = rows[0], rows[1:]
    ys, xs = np.nonzero(head["_scene"])  # show the object's neighbourhood, twice its size
    h = max(np.ptp(ys), np.ptp(xs)) + 1
    cy, cx = (ys.min() + ys.max()) // 2, (xs.min() + xs.max()) // 2
    near = (slice(max(cy - h, 0), cy + h), slice(max(cx - h, 0), cx + h))
    fig, axes = plt.subplots(2, len(stages) + 1, figsize=(3.6 * (len(stages) + 1), 7.6),
                             layout="constrained")
    axes[0, 0].imshow(head["_sensor"], cmap="gray")
    axes[0, 0].set_title("sensor image", fontsize=9)
    _scale_bar(axes[0, 0], 0.5e-3 / paper.DX, "0.5 mm")
    axes[1, 0].imshow(head["_scene"][near], cmap="gray", vmin=0)
    axes[1, 0].set_title("object (zoomed)", fontsize=9)
    _scale_bar(axes[1, 0], 0.1e-3 / paper.DX, "0.1 mm")
    for j, row in enumerate(stages, start=1):
        axes[0, j].imshow(row["_psf"] ** 0.5, cmap="inferno")
        axes[0, j].set_title(f"PSF: {row['stage']}\nPearson {row['psf_pearson']:.3f}",
                             fontsize=9)
        axes[1, j].imshow(row["_recon"][near], cmap="gray", vmin=0)
        axes[1, j].set_title(f"RL on the object: SSIM {row['object_ssim']:.3f}, "
                             f"P {row['object_pearson']:.3f}", fontsize=9)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"{title} (√PSF shown; data: {paper.TRUTH_MODEL.split(':')[0]})",
                 fontsize=10)
    save_figure(fig, path)


def _plot_depths(path, sweeps):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(sweeps), figsize=(6.5 * len(sweeps), 4.4),
                             layout="constrained")
    labels = {"model": "model, retrieved phase", "model_true_phase": "model, true phase",
              "scaling_ideal": "scaling, ideal 22 mm PSF",
              "scaling_captured": "scaling, captured 22 mm PSF"}
    for ax, (label, rows) in zip(np.atleast_1d(axes), sweeps.items()):
        z = [r["z1_mm"] for r in rows]
        for (key, name), style in zip(labels.items(), ("o-", "x:", "s--", "^:")):
            ax.plot(z, [r[key] for r in rows], style, label=name)
        ax.set_xlabel("source depth z1 (mm)")
        ax.set_ylabel("Pearson with the true PSF")
        ax.set_title(label)
        ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    save_figure(fig, path)


def _table(rows, columns) -> str:
    def fmt(v):
        return f"{v:.4f}" if isinstance(v, float) else str(v)
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def _public(rows):
    return [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]


def run_demo(out_dir: str | os.PathLike = "diffcam-report", *, full: bool = False,
             settings: paper.Settings | None = None, quiet: bool = False) -> dict:
    """Run the demonstration; write the report; return the metrics written."""
    out = make_output_folder(out_dir)      # before anything is loaded or computed
    import matplotlib

    matplotlib.use("Agg")
    s = settings or (paper.Settings(grid=4000) if full else paper.Settings())
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, flush=True))
    scale = (s.grid / 1024) ** 2 * np.log2(s.grid) / 10
    say(f"diffcam demo: grid {s.grid}² at 5 µm, GS {s.gs_iterations} iterations; expect about "
        f"{max(1, round(3 * scale ** 0.8))} min on a 2-core CPU ({fft_status()}). "
        f"Report → {out}/")
    t0 = time.perf_counter()
    fig3 = _fig3(s, out, say)
    fig5 = _fig5(s, fig3, out, say)
    rnd, fig6 = _fig6(s, out, say)
    say(f"[5/{_STEPS}] Fig. 9: PSFs over z1 = 22 … 30 mm vs the scaling baseline ...")
    sweeps = {"z2 = 1 mm": paper.fig9_depth_sweep(fig3["truth"], fig3["resolved"], s),
              "z2 = 5 mm": paper.fig9_depth_sweep(fig3["truth"], fig3["resolved"], s,
                                                  z2=5e-3, crop=min(s.grid, 704))}
    _plot_depths(out / "fig9_depths.png", sweeps)
    metrics = _metrics(s, fig3, fig5, rnd, fig6, sweeps)
    metrics["wall_time_s"] = time.perf_counter() - t0
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "report.md").write_text(_report(s, metrics, fig3, sweeps))
    say(f"diffcam demo: phase Pearson GS {metrics['fig3']['phase_pearson_gs']:.3f} → diffcam "
        f"{metrics['fig3']['phase_pearson_calibrated']:.4f}; PSF Pearson at 25 mm "
        f"{fig5[-1]['psf_pearson']:.4f}; {metrics['wall_time_s']:.0f} s → {out / 'report.md'}")
    return metrics


def _fig3(s, out, say) -> dict:
    """Fig. 3 and the twin resolved by a captured PSF at 22 mm (steps 1 and 2)."""
    say(f"[1/{_STEPS}] Fig. 3: phase retrieval (textbook GS, then diffcam's calibration) ...")
    fig3 = paper.fig3_phase_retrieval(cameraman_phase(), s)
    say(f"      GS {s.gs_iterations} it: phase Pearson {fig3['gs_scores']['pearson']:.4f} "
        f"({fig3['gs_seconds']:.0f} s); calibration: twin-resolved "
        f"{fig3['calibrated_scores']['twin_resolved']:.4f} ({fig3['calibrated_seconds']:.0f} s)")
    say(f"[2/{_STEPS}] resolving the twin with a captured PSF at z1 = 22 mm ...")
    cam = paper.camera(s)
    fig3["reference"] = paper.captured_reference(fig3["truth"], cam, paper.DEPTHS[0])
    fig3["resolved"], fig3["twin_chosen"] = calibrate.resolve_twin(fig3["calibrated"], fig3["reference"],
                                                         cam, paper.DEPTHS[0])
    fig3["resolved_scores"] = paper._scores(fig3["resolved"], fig3["truth"], s.grid)
    _plot_phases(out / "fig3_phase.png", fig3)
    return fig3


def _fig5(s, fig3, out, say) -> list[dict]:
    """Fig. 5: PSFs and RL of an 'F' for the phase after several calibration lengths."""
    say(f"[3/{_STEPS}] Fig. 5: PSFs at z1 = 25 mm and Richardson–Lucy of an 'F' ...")
    cam = paper.camera(s)
    stages = {"true phase": None, f"GS {s.gs_iterations} it": fig3["gs"]}
    for it in (10, 50):
        early = paper.paper_phase(fig3["near"], fig3["far"], iterations=it,
                                  refine_iterations=0, restarts=1).phase
        stages[f"calibration {it} it"] = calibrate.resolve_twin(early, fig3["reference"], cam,
                                                      paper.DEPTHS[0])[0]
    stages[f"calibration {s.calibration_iterations} it"] = fig3["resolved"]
    fig5 = paper.fig5_psf_and_reconstruction(fig3["truth"], stages, paper.letter_f(), s)
    _plot_stages(out / "fig5_cameraman.png", fig5, "Fig. 5 — cameraman diffuser, object 'F'")
    return fig5


def _fig6(s, out, say) -> tuple[dict, list[dict]]:
    """Fig. 6: a random 30 µm diffuser, near/far alone and with one PSF as a third plane."""
    say(f"[4/{_STEPS}] Fig. 6: random 30 µm diffuser and a 'flower' ...")
    cam = paper.camera(s)
    rnd = paper.fig3_phase_retrieval(paper.random_phase(), s, psf_z1=paper.DEPTHS[0])
    reference = paper.captured_reference(rnd["truth"], cam, paper.DEPTHS[0])
    rnd["resolved"] = calibrate.resolve_twin(rnd["calibrated"], reference, cam, paper.DEPTHS[0])[0]
    fig6 = paper.fig5_psf_and_reconstruction(
        rnd["truth"], {"true phase": None, f"GS {s.gs_iterations} it": rnd["gs"],
                       f"calibration {s.calibration_iterations} it": rnd["resolved"],
                       "calibration + PSF at 22 mm": rnd["with_psf"]},
        paper.flower(), s)
    _plot_stages(out / "fig6_random.png", fig6, "Fig. 6 — random diffuser, 'flower'")
    return rnd, fig6


def _metrics(s, fig3, fig5, rnd, fig6, sweeps) -> dict:
    """The numbers written to ``metrics.json``."""
    return {
        "grid": s.grid,
        "data": paper.TRUTH_MODEL,
        "fft": fft_status(),
        "fig3": {
            "gs_iterations": s.gs_iterations,
            "phase_pearson_gs": fig3["gs_scores"]["pearson"],
            "phase_pearson_gs_twin_resolved": fig3["gs_scores"]["twin_resolved"],
            "phase_pearson_calibrated": fig3["resolved_scores"]["pearson"],
            "phase_pearson_calibrated_twin_resolved": fig3["resolved_scores"]["twin_resolved"],
            "phase_pearson_calibrated_raw": fig3["resolved_scores"]["raw"],
            "phase_pearson_flat_estimate_floor": fig3["flat_scores"]["pearson"],
            "phase_pearson_flat_estimate_floor_twin_resolved":
                fig3["flat_scores"]["twin_resolved"],
            "phase_mse_calibrated": fig3["resolved_scores"]["mse"],
            "phase_pearson_gs_raw": fig3["gs_scores"]["raw"],
            "phase_mse_gs": fig3["gs_scores"]["mse"],
            "phase_pearson_flat_raw": fig3["flat_scores"]["raw"],
            "phase_mse_flat": fig3["flat_scores"]["mse"],
            "calibration": f"{fig3['calibration_method']} "
                           f"{s.calibration_iterations} it + twin from one PSF",
            "twin_chosen": fig3["twin_chosen"],
            "seconds_gs": fig3["gs_seconds"], "seconds_calibration": fig3["calibrated_seconds"],
            "phase_pearson_paper_gs_2000": 0.7890,
        },
        "fig5": _public(fig5[1:]),
        "fig6": {"phase_pearson_gs": rnd["gs_scores"]["pearson"],
                 "phase_pearson_calibrated": paper._scores(rnd["resolved"], rnd["truth"],
                                                           s.grid)["pearson"],
                 "phase_pearson_calibrated_with_psf": rnd["with_psf_scores"]["pearson"],
                 "phase_mse_calibrated_with_psf": rnd["with_psf_scores"]["mse"],
                 "seconds_calibration_with_psf": rnd["with_psf_seconds"],
                 "stages": _public(fig6[1:])},
        "fig9": {k.replace(" ", "").replace("=", "_"): v for k, v in sweeps.items()},
    }


def _report(s, metrics, fig3, sweeps) -> str:
    """``report.md``: the tables of ``metrics`` and the figures."""
    cols = ["stage", "phase_mse", "psf_pearson", "object_ssim", "object_pearson",
            "recon_ssim", "recon_pearson"]
    f3 = metrics["fig3"]
    report = [
        "# diffcam demo report", "",
        f"Grid {s.grid}² at 5 µm, diffuser 512², aperture radius 1.2 mm, λ = 532 nm, "
        f"f = 5 cm; wall time {metrics['wall_time_s']:.0f} s.", "",
        f"**The data**: near/far captures and true PSFs from a {paper.TRUTH_MODEL}; "
        "diffcam's model (monochromatic, at the 5 µm pitch, a point source) inverts them "
        "and predicts the PSFs, so no score is 1 by construction. `object_*` scores are "
        "on the object's bounding box, `recon_*` on the whole frame (mostly background).",
        ""
        "## Fig. 3 — phase retrieval (central 300², the phase metric of docs/design.md)", "",
        _table([{"solver": f"textbook GS, {s.gs_iterations} it", "pearson": f3["phase_pearson_gs"],
                 "twin_resolved": f3["phase_pearson_gs_twin_resolved"],
                 "raw": f3["phase_pearson_gs_raw"], "mse": f3["phase_mse_gs"],
                 "seconds": f3["seconds_gs"]},
                {"solver": f3["calibration"], "pearson": f3["phase_pearson_calibrated"],
                 "twin_resolved": f3["phase_pearson_calibrated_twin_resolved"],
                 "raw": f3["phase_pearson_calibrated_raw"], "mse": f3["phase_mse_calibrated"],
                 "seconds": f3["seconds_calibration"]},
                {"solver": "paper, GS 2000 it", "pearson": 0.7890},
                {"solver": "a flat estimate (the metric's floor)",
                 "pearson": f3["phase_pearson_flat_estimate_floor"],
                 "twin_resolved": f3["phase_pearson_flat_estimate_floor_twin_resolved"],
                 "raw": f3["phase_pearson_flat_raw"], "mse": f3["phase_mse_flat"]}],
               ["solver", "pearson", "twin_resolved", "raw", "mse", "seconds"]), "",
        "The metric aligns the piston and scores θtrue + wrap(θest − θtrue − d) against "
        "θtrue, so even a flat estimate scores high (last row): read the phase MSE "
        "(rad², after the same alignment) "
        "beside it; `raw` is the Pearson without the piston alignment (wrapped phases: "
        "near zero for any estimate).", "",
        "![](fig3_phase.png)", "",
        "## Fig. 5 — cameraman diffuser, z1 = 25 mm, z2 = 1 mm, RL of an 'F'", "",
        _table(metrics["fig5"], cols), "", "![](fig5_cameraman.png)", "",
        "## Fig. 6 — random 30 µm diffuser, 'flower'", "",
        _table(metrics["fig6"]["stages"], cols), "",
        "This diffuser's phase spans many 2π: near/far projections stall on it (GS and "
        "the default calibration rows). One PSF at 22 mm, used as a third intensity "
        "plane in the projections (diffcam.calibrate.psf_plane), retrieves it, twin "
        "included; the PSFs and reconstructions above are scored at 25 mm.", "",
        "![](fig6_random.png)", "",
        "## Fig. 9 — PSF Pearson per depth (registered), scaling anchored at 22 mm", "",
    ]
    for label, rows in sweeps.items():
        report += [f"### {label}", "",
                   _table(rows, ["z1_mm", "model", "model_true_phase", "scaling_ideal",
                                 "scaling_captured"]), ""]
    report += ["![](fig9_depths.png)", ""]
    return "\n".join(report)
