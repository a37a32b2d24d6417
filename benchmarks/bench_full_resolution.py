"""A full-size capture through ``diffcam reconstruct`` with its defaults, against the same
capture box-averaged by 4: does the working resolution the command chooses keep the
fine detail?

    python -m benchmarks.bench_full_resolution --full DIR

``DIR`` holds the DiffuserCam tutorial's ``rawdata_hand_sample.tif`` and
``psf_sample.tif`` (1200 × 1600). Three runs of ``diffcam reconstruct`` (ADMM-TV
defaults), each in a fresh process: the full-size pair with the default working
resolution, the full-size pair with ``--downsample 1``, and the shipped 4×-box-averaged
pair (``diffcam data hand``). Every result is brought to 300 × 400 (box average) and
scored by its *high-pass* Pearson correlation (the image minus its Gaussian blur of
σ = :data:`SIGMA` pixels: fine detail only) with plain non-negative FISTA on the
4× pair (:func:`benchmarks.bench_real_data.fista_reference`) and with the 4× run; a
3.5-pixel Gaussian blur of the FISTA reference is scored beside them as a yardstick.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.bench_real_data import fista_reference
from benchmarks.harness import markdown_table, run_probed, write_json

SIGMA = 4.0  # pixels of the 300 × 400 frame


def high_pass_pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of ``a`` and ``b`` after removing their Gaussian blur."""
    from scipy.ndimage import gaussian_filter

    from diffcam.evaluate.metrics import pearson

    fine = [x - gaussian_filter(x.astype(np.float64), SIGMA) for x in (a, b)]
    return float(pearson(*fine))


def main(argv=None):
    from scipy.ndimage import gaussian_filter

    from diffcam.data import load_tutorial_pair
    from diffcam.io import downsample

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--full", type=Path, required=True, help="folder of the full-size pair")
    args = p.parse_args(argv)
    pair = load_tutorial_pair(subtract_background=False)
    reference = fista_reference(pair.image, pair.psf)
    work = Path(tempfile.mkdtemp(prefix="fullres-"))
    diffcam = [sys.executable, "-m", "diffcam"]
    run_probed(diffcam + ["data", "hand", "-o", str(work)])
    full = [str(args.full / "rawdata_hand_sample.tif"), "--psf", str(args.full / "psf_sample.tif")]
    runs = {"4× pair, defaults": [str(work / "hand_raw.tif"), "--psf", str(work / "hand_psf.tif")],
            "full size, defaults": full,
            "full size, --downsample 1": full + ["--downsample", "1"]}
    rows, images = [], {}
    for name, cmd in runs.items():
        out = work / f"{len(rows)}.npy"
        probe = run_probed(diffcam + ["reconstruct", *cmd, "-o", str(out), "--quiet"])
        image = np.load(out)
        factor = image.shape[0] // reference.shape[0]
        images[name] = downsample(image, factor) if factor > 1 else image
        rows.append({"run": name, "output": "×".join(map(str, image.shape)),
                     "wall_s": probe["wall_s"], "peak_rss_mb": probe["peak_bytes"] / 2**20})
    for row in rows:
        image = images[row["run"]]
        row["hp_pearson_vs_fista_4x"] = high_pass_pearson(image, reference)
        row["hp_pearson_vs_cli_4x"] = high_pass_pearson(image, images["4× pair, defaults"])
    rows.append({"run": "yardstick: FISTA 4× blurred by σ = 3.5 px",
                 "hp_pearson_vs_fista_4x": high_pass_pearson(
                     gaussian_filter(reference, 3.5), reference)})
    print(markdown_table(rows, list(rows[0])))
    print(f"wrote {write_json('full_resolution', rows, {'sigma_px': SIGMA})}")


if __name__ == "__main__":
    main()
