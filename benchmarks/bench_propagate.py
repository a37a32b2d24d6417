"""Propagation workload: one Fresnel / angular-spectrum step, complex64, N × N.

Side by side in one run: diffcam's propagators, the bare jitted JAX ``fft2`` + ``ifft2``
pair (the limit for an FFT-based step), a straightforward numpy implementation,
scipy.fft with 2 workers, pyfftw (planned, 2 threads) and torch if installed, and the
optics peers that import here (diffractsim's JAX backend, LightPipes ``Forvard``).
waveprop is left out: it imports torchvision at module level, which does not load
beside the CPU torch build on these machines (see ../shared/PEERS.md).

    python -m benchmarks.bench_propagate [--sizes 1024 2048 4096] [--repeats 5]
"""

from __future__ import annotations

import argparse
import types

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.harness import markdown_table, optional_import, time_against, write_json
from diffcam.optics.propagation import (angular_spectrum, apply_transfer, fresnel_tf,
                               transfer_function)

WAVELENGTH, DX = 532e-9, 5e-6
Z = 1e-3


def _field(n):
    rng = np.random.default_rng(0)
    return (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))).astype(np.complex64)


def _numpy_tf(u, n):
    f = np.fft.fftfreq(n, DX)
    H = np.exp(-1j * np.pi * WAVELENGTH * Z * (f[:, None] ** 2 + f[None, :] ** 2))
    return np.fft.ifft2(np.fft.fft2(u) * H)


def candidates_for(n: int, notes: list[str]) -> dict:
    u_np = _field(n)
    u = jnp.asarray(u_np)
    cands = {}

    fft_pair = jax.jit(lambda x: jnp.fft.ifft2(jnp.fft.fft2(x)))
    cands["jax fft2+ifft2 (limit)"] = lambda: fft_pair(u)
    tf_jit = jax.jit(lambda x: fresnel_tf(x, DX, WAVELENGTH, Z))
    cands["diffcam fresnel_tf (jit)"] = lambda: tf_jit(u)
    as_jit = jax.jit(lambda x: angular_spectrum(x, DX, WAVELENGTH, Z))
    cands["diffcam angular_spectrum (jit)"] = lambda: as_jit(u)
    cands["diffcam fresnel_tf (eager, validated)"] = lambda: fresnel_tf(u, DX, WAVELENGTH, Z)
    H = transfer_function((n, n), DX, WAVELENGTH, Z, method="angular_spectrum").astype(
        jnp.complex64)
    cands["diffcam apply_transfer (prebuilt H)"] = lambda: apply_transfer(u, H)

    cands["numpy (H per call)"] = lambda: _numpy_tf(u_np, n)
    f = np.fft.fftfreq(n, DX)
    H_np = np.exp(-1j * np.pi * WAVELENGTH * Z * (f[:, None] ** 2 + f[None, :] ** 2)
                  ).astype(np.complex64)
    import scipy.fft as sfft
    cands["scipy.fft workers=2"] = lambda: sfft.ifft2(sfft.fft2(u_np, workers=2) * H_np,
                                                      workers=2)
    pyfftw = optional_import("pyfftw", notes)
    if pyfftw is not None:
        a = pyfftw.empty_aligned((n, n), dtype="complex64")
        fwd = pyfftw.FFTW(a, pyfftw.empty_aligned((n, n), dtype="complex64"), axes=(0, 1),
                          threads=2, flags=("FFTW_MEASURE",))
        b = pyfftw.empty_aligned((n, n), dtype="complex64")
        inv = pyfftw.FFTW(b, pyfftw.empty_aligned((n, n), dtype="complex64"), axes=(0, 1),
                          direction="FFTW_BACKWARD", threads=2, flags=("FFTW_MEASURE",))

        def fftw_step():
            a[:] = u_np
            b[:] = fwd() * H_np
            return inv()
        cands["pyfftw 2 threads (planned)"] = fftw_step
    torch = optional_import("torch", notes)
    if torch is not None:
        ut, Ht = torch.from_numpy(u_np), torch.from_numpy(H_np)
        cands["torch CPU"] = lambda: torch.fft.ifft2(torch.fft.fft2(ut) * Ht)

    ds = optional_import("diffractsim", notes)
    if ds is not None:
        ds.set_backend("JAX")
        from diffractsim.propagation_methods.angular_spectrum_method import \
            angular_spectrum_method
        sim = types.SimpleNamespace(Nx=n, Ny=n, dx=DX, dy=DX)
        cands["diffractsim JAX backend"] = lambda: angular_spectrum_method(sim, u, Z, WAVELENGTH)
    lp = optional_import("LightPipes", notes)
    if lp is not None:
        F = lp.Begin(n * DX, WAVELENGTH, n)
        F.field = u_np.astype(np.complex128)
        cands["LightPipes Forvard"] = lambda: lp.Forvard(F, Z)
    return cands


LIMIT = "jax fft2+ifft2 (limit)"


def run(sizes=(1024, 2048, 4096), repeats=5) -> list[dict]:
    """Each candidate timed in alternation with the bare FFT pair alone, its ratio to
    that run's pair (``limit_ms``; ``harness.time_against``)."""
    rows, notes = [], []
    for n in sizes:
        cands = candidates_for(n, notes)
        budget = 20.0 if n >= 4096 else None
        limit = cands.pop(LIMIT)
        stats = time_against(limit, cands, repeats=repeats, budget_s=budget)
        stats = {LIMIT: stats.pop(None), **stats}
        best_fft = min(v["median_s"] for k, v in stats.items()
                       if k.startswith(("scipy", "pyfftw", "torch")))
        for name, s in stats.items():
            rows.append({"N": n, "candidate": name, "median_ms": 1e3 * s["median_s"],
                         "limit_ms": 1e3 * s["unit_s"],
                         "first_call_ms": 1e3 * s["first_s"], "repeats": s["repeats"],
                         "x_jax_fft_pair": s["median_s"] / s["unit_s"],
                         "x_best_fft_lib": s["median_s"] / best_fft})
    for note in sorted(set(notes)):
        print("note:", note)
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args(argv)
    rows = run(args.sizes, args.repeats)
    print(markdown_table(rows, ["N", "candidate", "median_ms", "limit_ms", "x_jax_fft_pair",
                                "x_best_fft_lib", "first_call_ms", "repeats"]))
    print("wrote", write_json("propagate", rows))


if __name__ == "__main__":
    main()
