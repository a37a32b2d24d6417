"""Per-call overhead on small grids: each public call against the same computation
fused in one ``jax.jit`` (issue: within 1.5× at 128²–512²).

    python -m benchmarks.bench_overhead [--sizes 128 256 512] [--repeats 30]

Rows (compile excluded), each timed interleaved with its fused twin: a sample is as
many calls as take about 20 ms, each call waited for, and the ratio is the median over
the rounds of each round's call ÷ fused (paired, so the machine's drift cancels; small
grids run in a fraction of a millisecond, where single calls swing by tens of per cent):

* ``psf``: one eager :func:`diffcam.psf` call (checks included) vs ``jax.jit`` of it;
* ``psf_stack``: per PSF, :func:`diffcam.psf_stack` over 32 depths (host chunks, checks)
  vs one ``jax.jit(jax.vmap(psf))`` over the depths;
* ``fresnel_tf``: one eager call vs ``jax.jit`` of it;
* ``gs``: :func:`diffcam.calibrate.gerchberg_saxton`, 20 iterations, vs the same
  iteration written as plain JAX (FFT, amplitude replacement) in one jitted
  ``fori_loop``.
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.harness import block, markdown_table, time_interleaved, write_json

LAM, DX, Z2 = 532e-9, 5e-6, 1e-3
TARGET = 1.5
SAMPLE_S = 0.02   # each timed sample: calls adding up to about this many seconds


def _camera(n):
    from diffcam import Camera
    return Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_radius=0.3 * n * DX,
                  shape=(n, n), crop=(3 * n // 4, 3 * n // 4))


def _gs_fused(near_amp, far_amp, iterations):
    """Textbook GS, plain JAX: the reference for the fused cost."""
    def body(_, u):
        u = far_amp * jnp.exp(1j * jnp.angle(jnp.fft.fft2(u)))
        return near_amp * jnp.exp(1j * jnp.angle(jnp.fft.ifft2(u)))
    return jax.lax.fori_loop(0, iterations, body, near_amp.astype(jnp.complex64))


def rows_for(n: int, repeats: int) -> list[dict]:
    import diffcam as dc
    from diffcam.calibrate import CalibrationGeometry, calibration_intensities, gerchberg_saxton
    from diffcam.optics.propagation import fresnel_tf

    cam = _camera(n)
    phase = dc.random_diffuser(jax.random.key(0), (n, n), DX, LAM)
    depths = np.linspace(22e-3, 30e-3, 32)
    field = jnp.exp(1j * phase)
    geometry = CalibrationGeometry(dx=DX, wavelength=LAM, focal_length=5e-2)
    near, far = calibration_intensities(phase, cam.aperture(), geometry)
    near_amp, far_amp = jnp.sqrt(near), jnp.sqrt(far)
    psf_jit = jax.jit(lambda p: dc.psf(p, cam, 25e-3))
    stack_jit = jax.jit(jax.vmap(lambda z, p: dc.psf(p, cam, z), (0, None)))
    tf_jit = jax.jit(lambda u: fresnel_tf(u, DX, LAM, Z2))
    gs_jit = jax.jit(_gs_fused, static_argnums=2)
    pairs = {
        "psf": (lambda: dc.psf(phase, cam, 25e-3), lambda: psf_jit(phase), 1),
        "psf_stack": (lambda: dc.psf_stack(phase, cam, depths, progress=False),
                      lambda: stack_jit(jnp.asarray(depths), phase), len(depths)),
        "fresnel_tf": (lambda: fresnel_tf(field, DX, LAM, Z2), lambda: tf_jit(field), 1),
        "gs": (lambda: gerchberg_saxton(near, far, geometry, iterations=20, restarts=1,
                                        key=jax.random.key(1), progress=False).phase,
               lambda: gs_jit(near_amp, far_amp, 20), 1),
    }
    rows = []
    for name, (call, fused, per) in pairs.items():
        block(call())                           # compiles
        start = time.perf_counter()
        block(call())
        calls = max(1, int(SAMPLE_S / (time.perf_counter() - start)))
        t = time_interleaved({"call": _calls(call, calls), "fused": _calls(fused, calls)},
                             repeats=repeats)
        a, b = (np.asarray(t[k]["times_s"]) / (calls * per) for k in ("call", "fused"))
        ratio = float(np.median(a / b))    # paired: each round's two samples side by side
        rows.append({"N": n, "workload": name, "call_ms": np.median(a) * 1e3,
                     "fused_ms": np.median(b) * 1e3, "ratio": ratio, "ok": ratio <= TARGET,
                     "calls_per_sample": calls, "loadavg": os.getloadavg()[0]})
    return rows


def _calls(fn, calls):
    """``calls`` calls of ``fn``, each waited for (an eager call waits for its own
    checks; the fused twin gets no head start from queueing calls)."""
    def run():
        for _ in range(calls):
            out = block(fn())
        return out
    return run


COLUMNS = ["N", "workload", "call_ms", "fused_ms", "ratio", "ok", "calls_per_sample",
           "loadavg"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    p.add_argument("--repeats", type=int, default=30)
    args = p.parse_args(argv)
    rows = [r for n in args.sizes for r in rows_for(n, args.repeats)]
    print(markdown_table(rows, COLUMNS))
    print(f"wrote {write_json('overhead', rows, {'target_ratio': TARGET})}")


if __name__ == "__main__":
    main()
