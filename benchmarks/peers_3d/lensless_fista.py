"""Peer driver (runs in LenslessPiCam's environment): its 3-D FISTA (no TV; its ADMM
is 2-D only) on a volume from one capture, through its public API.

    python lensless_fista.py IN.npz OUT.npz ITERATIONS

IN.npz holds ``raw`` (ny, nx) and ``psf`` (nz, ny, nx); OUT.npz gets ``volume``
(nz, ny, nx), ``seconds_per_iteration`` and ``seconds``.
"""

import sys
import time

import numpy as np

from lensless import FISTA


def main(src, dst, iterations):
    data = np.load(src)
    raw = data["raw"].astype(np.float32)
    psf = data["psf"].astype(np.float32)
    recon = FISTA(psf[..., None] / np.linalg.norm(psf), n_iter=iterations)
    recon.set_data(raw[..., None] / raw.max())
    t0 = time.perf_counter()
    out = recon.apply(n_iter=iterations, disp_iter=None, plot=False)
    seconds = time.perf_counter() - t0
    volume = np.asarray(out[0] if isinstance(out, tuple) else out).reshape(psf.shape)
    np.savez(dst, volume=volume, seconds=seconds, seconds_per_iteration=seconds / iterations)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]))
