"""Where the horizontal seams of the PSF fitted from the Lensless Learning pairs come
from, and what removing them costs.

    python -m benchmarks.bench_scene_psf_seams [--figure PNG]

The shipped pairs (135 × 240), pair im43 held out, one PSF fitted to the other six
(`fit_psf_from_scenes`, 300 iterations, no flip). A seam is a row of the PSF that
differs from its two neighbours across the whole width: the PSF's row means minus the
mean of the two neighbouring rows, relative to the mean row (the four rows at each edge
of the PSF's support left out). Two experiments:

* **the sensor cut**: the bottom 0, 10 or 20 rows of every raw and truth removed (a
  shorter sensor). A seam that the diffuser makes stays at its offset from the optical
  axis; a seam at the offset where the pictures' common bottom edge (the last truth row
  whose mean exceeds 0.03, the same row in all seven pairs) leaves the sensor moves with
  the sensor's bottom border, to ``ny - edge``;
* **the border taper** (`ScenePsfOptions.border_taper`): the misfit weighted by a Tukey
  window falling to 0 over 15 % of each border, so that an edge's copy fades out of the
  data term instead of leaving it at one row; the held-out raw predicted (Pearson per
  channel) and reconstructed (ADMM-TV, FISTA; scored as in `bench_scene_psf`).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.bench_scene_psf import PICTURE_LEVEL, reconstruct, scores
from benchmarks.harness import markdown_table, write_json

CUTS = (0, 10, 20)
TAPER = 0.15
EDGE = 4
"""Rows at each edge of the PSF's support left out of the seam search."""


def seams(psf: np.ndarray, count: int = 3) -> list[tuple[int, float]]:
    """The ``count`` strongest seams of a ``(c, ny, nx)`` PSF: (offset from the optical
    axis in rows, positive down; relative strength), strongest first."""
    rows = psf.sum(axis=0).mean(axis=1)
    excess = (rows[1:-1] - 0.5 * (rows[:-2] + rows[2:])) / rows.mean()
    excess[:EDGE - 1], excess[len(excess) - EDGE + 1:] = 0, 0
    order = np.argsort(np.abs(excess))[::-1][:count]
    return [(int(i + 1 - len(rows) // 2), float(excess[i])) for i in order]


def main(argv=None):
    from diffcam.calibrate.scene.fit import fit_psf_from_scenes, predict_raw
    from diffcam.data import load_scene_pairs
    from diffcam.evaluate.metrics import pearson

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--figure", type=Path, help="write the PSF row profiles here")
    args = p.parse_args(argv)
    pairs = load_scene_pairs()
    raws, truths = pairs.raws, pairs.truths
    edge = int(np.flatnonzero(truths.mean(axis=(0, 1, 3)) > PICTURE_LEVEL)[-1]) + 1
    rows, psfs = [], {}
    for cut, taper in [(c, 0.0) for c in CUTS] + [(0, TAPER)]:
        ny = raws.shape[-2] - cut
        t = time.perf_counter()
        cal = fit_psf_from_scenes(raws[1:, :, :ny], truths[1:, :, :ny], flip="none",
                                  border_taper=taper, progress=False)
        row = {"rows_cut": cut, "sensor_rows": ny, "border_taper": taper,
               "edge_leaves_at": ny - edge, "fit_s": time.perf_counter() - t}
        for k, (offset, strength) in enumerate(seams(cal.psf), 1):
            row.update({f"seam{k}_offset": offset, f"seam{k}_strength": strength})
        if cut == 0:
            row["predict_pearson"] = np.asarray(pearson(predict_raw(cal, truths[0]),
                                                        raws[0])).tolist()
            held = raws[0] - cal.offset[:, None, None]
            for method in ("admm", "fista"):
                s = scores(reconstruct(method, held, cal.psf), truths[0])
                row.update({f"{method}_{k}": v for k, v in s.items()
                            if k in ("psnr", "ssim", "psnr_picture")})
        rows.append(row)
        psfs[(cut, taper)] = cal.psf
        print(f"- cut {cut}, taper {taper}: seams {seams(cal.psf)}", flush=True)
    print(markdown_table(rows, list(rows[0])))
    if args.figure:
        figure(psfs, edge, args.figure)
        print(f"wrote {args.figure}")
    print(f"wrote {write_json('scene_psf_seams', rows, {'picture_bottom_row': edge})}")


def figure(psfs: dict, edge: int, path: Path) -> None:
    """The PSF's row means against the offset from the axis for each sensor cut, the
    offsets where the pictures' bottom edge leaves the sensor marked; and the PSF
    without and with the border taper."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffcam.apps.cli import save_figure

    fig, axes = plt.subplot_mosaic([["rows", "rows"], ["plain", "taper"]],
                                   figsize=(12, 8), layout="constrained")
    for (cut, taper), psf in psfs.items():
        if taper:
            continue
        ny = psf.shape[-2]
        line, = axes["rows"].plot(np.arange(ny) - ny // 2, psf.sum(axis=0).mean(axis=1),
                                  label=f"sensor {ny} rows (bottom {cut} cut)")
        axes["rows"].axvline(ny - edge, color=line.get_color(), ls=":")
    axes["rows"].set(xlabel="PSF row: offset from the optical axis (pixels)",
                     ylabel="row mean", title="dotted: where the pictures' bottom edge "
                                              "leaves that sensor")
    axes["rows"].legend(fontsize=8)
    for key, (title, psf) in {"plain": ("every pixel weighed alike (the default)",
                                        psfs[(0, 0.0)]),
                              "taper": (f"border taper {TAPER}", psfs[(0, TAPER)])}.items():
        image = np.moveaxis(psf, 0, -1)
        axes[key].imshow(np.clip(image / np.percentile(image, 99.5), 0, 1) ** 0.5)
        axes[key].set_title(title, fontsize=9)
        axes[key].axis("off")
    fig.suptitle("PSF fitted to six Lensless Learning pairs (135 × 240)", fontsize=10)
    save_figure(fig, path)


if __name__ == "__main__":
    main()
