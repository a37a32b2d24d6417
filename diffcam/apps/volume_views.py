"""Figures of a reconstructed volume: depth map with colour bar, orthogonal max
projections (x–y, x–z, y–z) and a montage of the planes. ``diffcam reconstruct --3d``
writes them beside the volume (``docs/cli_reconstruct.md``).

Every function takes a volume ``(nz, ny, nx)`` (plane 0 nearest) and a list of one
label per plane, and returns a matplotlib figure (Agg backend) for
`diffcam.apps.cli.save_figure`.
"""

from __future__ import annotations

import numpy as np

from diffcam.evaluate.volume import depth_map

__all__ = ["depth_map_figure", "projections_figure", "montage_figure", "DEPTH_FRACTION"]

DEPTH_FRACTION = 0.2
"""Depth map: pixels whose max projection is below this share of its 99.5th percentile
are masked (no object there), `diffcam.evaluate.volume.depth_map`."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _ticks(nz: int) -> np.ndarray:
    return np.unique(np.linspace(0, nz - 1, min(nz, 9)).round().astype(int))


def depth_map_figure(volume, labels: list[str], bar_label: str = "plane"):
    """The depth map (brightest plane per pixel,
    `depth_map`) coloured by plane, with a colour bar
    labelled by ``labels``."""
    plt = _pyplot()
    nz, ny, nx = np.shape(volume)
    width = 6.0
    fig, ax = plt.subplots(figsize=(width, max(2.5, width * ny / nx * 0.85)),
                           layout="constrained")
    ax.set_facecolor("0.8")  # masked pixels
    image = ax.imshow(depth_map(volume, DEPTH_FRACTION), cmap=plt.get_cmap("turbo", nz),
                      vmin=-0.5, vmax=nz - 0.5, interpolation="nearest")
    ticks = _ticks(nz)
    bar = fig.colorbar(image, ax=ax, ticks=ticks)
    bar.ax.set_yticklabels([labels[t] for t in ticks])
    bar.set_label(bar_label)
    ax.set_title(f"brightest plane per pixel (grey: < {DEPTH_FRACTION:.0%} of the max "
                 f"projection's 99.5th percentile)", fontsize=8)
    ax.set_xlabel("x (pixels)")
    ax.set_ylabel("y (pixels)")
    return fig


def projections_figure(volume, labels: list[str]):
    """Max projections along depth (x–y), along y (x–z, below) and along x (y–z, to the
    right), on one grey scale clipped at the 99.7th percentile; depth drawn with
    ``max(1, ny // nz)`` pixels per plane."""
    plt = _pyplot()
    v = np.asarray(volume, np.float32)
    nz, ny, nx = v.shape
    views = v.max(axis=0), v.max(axis=1), v.max(axis=2).T          # xy, xz, yz
    vmax = float(np.percentile(views[0], 99.7)) or 1.0
    stretch = max(1, ny // nz)
    fig = plt.figure(figsize=(7.5, 7.5 * (ny + nz * stretch) / (nx + nz * stretch)),
                     layout="constrained")
    grid = fig.add_gridspec(2, 2, width_ratios=[nx, nz * stretch],
                            height_ratios=[ny, nz * stretch])
    xy, xz, yz = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[1, 0]), \
        fig.add_subplot(grid[0, 1])
    kw = dict(cmap="gray", vmin=0, vmax=vmax, interpolation="nearest")
    xy.imshow(views[0], **kw)
    xz.imshow(views[1], aspect=1 / stretch, **kw)
    yz.imshow(views[2], aspect=stretch, **kw)
    xy.set_title("max over depth (x–y)", fontsize=9)
    xz.set_xlabel("x (pixels)")
    xz.set_ylabel("plane")
    yz.set_xlabel("plane")
    yz.set_ylabel("y (pixels)")
    xz.set_title("max over y (x–z)", fontsize=9)
    yz.set_title("max over x (y–z)", fontsize=9)
    ticks = _ticks(nz)
    xz.set_yticks(ticks, [labels[t] for t in ticks], fontsize=6)
    yz.set_xticks(ticks, [labels[t] for t in ticks], fontsize=6, rotation=90)
    return fig


def montage_figure(volume, labels: list[str], columns: int = 8):
    """Every plane in a grid of ``columns`` per row, one grey scale for all (clipped at
    the 99.7th percentile of the volume's max projection), each titled by its label."""
    plt = _pyplot()
    v = np.asarray(volume, np.float32)
    nz, ny, nx = v.shape
    rows = -(-nz // columns)
    cols = min(columns, nz)
    vmax = float(np.percentile(v.max(axis=0), 99.7)) or 1.0
    fig, axes = plt.subplots(rows, cols, figsize=(1.6 * cols, 1.6 * rows * ny / nx + 0.3),
                             squeeze=False, layout="constrained")
    for k, ax in enumerate(axes.flat):
        ax.set_axis_off()
        if k < nz:
            ax.imshow(v[k], cmap="gray", vmin=0, vmax=vmax, interpolation="nearest")
            ax.set_title(labels[k], fontsize=6)
    return fig
