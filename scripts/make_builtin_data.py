"""Rebuild diffcam/data/*.npz from the measured captures in shared/data/real/.

Usage: python scripts/make_builtin_data.py [SHARED_REAL_DIR]

What it stores (see diffcam/data/PROVENANCE.md):
* tutorial.npz — the DiffuserCam tutorial PSF and hand capture, box-averaged by 4
  (1200x1600 -> 300x400) in float32 counts, plus the dark level of the full-resolution
  PSF's corner [5:15, 5:15].
* diffusercam_3d.npz — the 44-plane PSF stack as uint16 ``round(65535 · value)`` of
  LCAV's global min-max normalised float32 slices (max error 7.7e-6, far below the noise),
  and the raw 3-D capture as its original uint16 counts.
* lensless_learning.npz — the seven Lensless Learning pairs (raw DiffuserCam capture,
  lensed ground truth), box-averaged by 2 (270x480 -> 135x240), BGR reordered to RGB
  channels first, raws as uint16 steps of ``raw_step`` above ``raw_low``, truths as
  uint16 ``round(65535 · value)``.
"""

import sys
from pathlib import Path

import numpy as np

from diffcam.io import dark_level, downsample, read_image, read_psf_stack

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
OUT = Path(__file__).resolve().parents[1] / "diffcam" / "data"


def main(real: Path) -> None:
    tut = real / "diffusercam_tutorial"
    psf = read_image(tut / "psf_sample.tif").image
    raw = read_image(tut / "rawdata_hand_sample.tif").image
    np.savez_compressed(OUT / "tutorial.npz", psf=downsample(psf, 4), image=downsample(raw, 4),
                        dark_level=np.float32(dark_level(psf, (slice(5, 15), slice(5, 15)))),
                        factor=np.int32(4))
    d3 = real / "diffusercam_3d"
    stack = read_psf_stack(sorted((d3 / "psf").glob("psf*.tiff")))
    quantised = np.round(stack.astype(np.float64) * 65535).astype(np.uint16)
    print("3-D stack quantisation error:", np.abs(quantised / 65535 - stack).max())
    raw3 = read_image(d3 / "example_raw.png").image.astype(np.uint16)
    np.savez_compressed(OUT / "diffusercam_3d.npz", psf_stack=quantised, image=raw3)
    _lensless_learning(real / "lenslesslearning")
    for f in sorted(OUT.glob("*.npz")):
        print(f.name, f.stat().st_size, "bytes")


def _lensless_learning(folder: Path) -> None:
    names = ["im43", "im65", "im157", "im189", "im326", "im394", "im643"]

    def rgb(kind):
        bgr = np.stack([read_image(folder / kind / f"{n}.npy", channel_order="BGR").image
                        for n in names])
        return downsample(bgr[:, ::-1], 2)

    raw, truth = rgb("diffuser"), rgb("lensed")
    low = float(np.floor(raw.min() * 1e4) / 1e4)
    step = (float(np.ceil(raw.max() * 1e4) / 1e4) - low) / 65535
    raw_q = np.round((raw - low) / step).astype(np.uint16)
    truth_q = np.round(np.clip(truth, 0, 1) * 65535).astype(np.uint16)
    print("scene pairs quantisation error:", np.abs(raw_q * step + low - raw).max(),
          np.abs(truth_q / 65535 - truth).max())
    np.savez_compressed(OUT / "lensless_learning.npz", raw=raw_q, truth=truth_q,
                        raw_low=np.float32(low), raw_step=np.float64(step),
                        names=np.array(names))


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT)
