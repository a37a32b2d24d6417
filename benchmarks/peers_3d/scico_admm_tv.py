"""Peer driver (runs in scico's own environment): ADMM-TV of a volume from one capture
with scico's public API, the set-up of scico's DiffuserCam example as PEERS.md
records it (TV weight 3e-3 over the lateral axes, L1 weight 1e-2, non-negativity, each
PSF plane scaled to unit L2 norm, the G0-block-circulant x-step, 2× padded grid).

    python scico_admm_tv.py IN.npz OUT.npz ITERATIONS

IN.npz holds ``raw`` (ny, nx) and ``psf`` (nz, ny, nx); OUT.npz gets ``volume``
(nz, ny, nx, on the sensor frame), ``seconds_per_iteration`` (after the first
iteration, which compiles) and ``seconds``.
"""

import sys
import time

import numpy as np

import jax.numpy as jnp
import scico.numpy as snp
from scico import functional, linop, loss
from scico.optimize.admm import ADMM, G0BlockCircularConvolveSolver


def main(src, dst, iterations):
    data = np.load(src)
    raw = data["raw"].astype(np.float32)
    psf = data["psf"].astype(np.float32)
    psf = psf / np.linalg.norm(psf, axis=(1, 2), keepdims=True)
    nz, ny, nx = psf.shape
    shape = (nz, 2 * ny, 2 * nx)
    kernel = np.zeros(shape, np.float32)
    kernel[:, :ny, :nx] = psf
    window = (slice(ny // 2, ny // 2 + ny), slice(nx // 2, nx // 2 + nx))
    mask = np.zeros(shape[1:], np.float32)
    mask[window] = 1
    y = np.zeros(shape[1:], np.float32)
    y[window] = raw / raw.max()
    conv = linop.CircularConvolve(h=jnp.asarray(kernel), input_shape=shape, ndims=2,
                                  h_center=np.array([ny // 2, nx // 2]))
    summed = linop.Sum(input_shape=shape, axis=0)
    g_list = [loss.SquaredL2Loss(y=jnp.asarray(y), A=linop.Diagonal(jnp.asarray(mask))),
              3e-3 * functional.L1Norm(),
              1e-2 * functional.L1Norm(), functional.NonNegativeIndicator()]
    c_list = [summed @ conv,
              linop.FiniteDifference(input_shape=shape, axes=(1, 2), circular=True),
              linop.Identity(shape), linop.Identity(shape)]
    solver = ADMM(f=functional.ZeroFunctional(), g_list=g_list, C_list=c_list,
                  rho_list=[1e-1, 1e-1, 1e-1, 1e-1], x0=jnp.zeros(shape, jnp.float32),
                  maxiter=1, subproblem_solver=G0BlockCircularConvolveSolver(ndims=2))
    t0 = time.perf_counter()
    solver.solve()                                   # compiles, one iteration
    t1 = time.perf_counter()
    solver.maxiter = iterations - 1
    x = solver.solve()
    x.block_until_ready()
    t2 = time.perf_counter()
    volume = np.asarray(x)[:, window[0], window[1]]
    np.savez(dst, volume=volume, seconds=t2 - t0,
             seconds_per_iteration=(t2 - t1) / max(iterations - 1, 1))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]))
