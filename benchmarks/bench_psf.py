"""PSF stacks: PSFs per second and working memory, diffcam against a numpy loop and peers.

    python -m benchmarks.bench_psf [--sizes 1024 2048] [--depths 64] [--repeats 5]

For each grid size N (aperture radius 0.3·N·dx at 5 µm, z2 = 1 mm, random phase):

- ``fresnel_tf``: one jitted step of :func:`diffcam.optics.propagation.fresnel_tf` on N² (the
  unit; an eager call adds validation, 1.2–1.3× at 1024²). Each candidate is timed
  in alternation with the step alone, and its ratio is to that run's step
  (``fresnel_tf_ms``): page faults on fresh buffers cost more here after another
  candidate has made and freed gigabytes (one run timed the 2048² step at 77 ms
  among the stacks and 30 ms beside the FFT pair);
- ``jax fft2+ifft2``: the bare FFT pair (the limit of a step);
- ``direct`` / ``scaling``: :func:`diffcam.model.stack.psf_stack` over ``depths`` z1 in
  22–30 mm, per PSF (field, propagation, intensity, normalisation; no sensor step),
  the stack returned in host memory;
- ``direct, on device`` / ``scaling, on device``: the same chunks left on the device
  (``iter_psf_stack(to_host=False)``): the computation the issue's ratio is about,
  without the host stack's copy and first-touch page faults;
- ``numpy (plain)``: the same direct Eq. 7 as a plain numpy loop, numpy's defaults
  (complex128), the propagation kernel built once (fewer depths, per PSF);
- ``numpy``: the same, tuned: complex64, base field precomputed, separable chirp;
- ``LightPipes``: Lens(−z1) → CircAperture → MultPhase → Forvard(z2) → Intensity, if
  installed (few depths, per PSF);
- ``grad``: reverse mode, jax.grad of Σ w·PSF with respect to the phase, one depth.

Times are medians of interleaved repeats (``benchmarks.harness``). Working memory is
the peak RSS (VmHWM, reset through ``/proc/self/clear_refs`` after a warm-up call) of a
fresh subprocess that builds the stack, minus its RSS just before the stack call, minus
the returned stack's bytes: measured at two depth
counts to show it is flat in the number of depths. XLA's own figure
(``memory_analysis().temp_size_in_bytes`` of the chunk's two compiled calls plus the
two field-sized buffers they pass on, or of the gradient) is reported beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks.harness import (markdown_table, optional_import, time_against,
                                write_json)
from diffcam.model import Camera, psf
from diffcam.optics.propagation import fresnel_tf
from diffcam.model.point_spread import diffuser_fields
from diffcam.model.stack import _chunk_inputs, _chunk_outputs, iter_psf_stack, psf_stack

LAM, DX, Z2 = 532e-9, 5e-6, 1e-3


def _camera(n, method):
    return Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_radius=0.3 * n * DX, shape=(n, n),
                  method=method)


def _numpy_psf(base, h, n, z1):
    """Tuned numpy: complex64, base field and kernel precomputed, separable chirp."""
    x = (np.arange(n) - n // 2) * DX
    c = np.exp(1j * np.pi * x * x / (LAM * z1)).astype(np.complex64)
    out = np.fft.ifft2(np.fft.fft2(base * c[:, None] * c[None, :]) * h)
    i = np.abs(out) ** 2
    return i / i.sum()


def _plain_numpy_psf(phase, aperture_radius, h, n, z1):
    """Paper Eq. 7 as written, numpy defaults (float64/complex128): point-source field
    at the aperture, aperture, diffuser phase, propagation by z2 (kernel ``h`` built
    once per stack), intensity, unit sum."""
    x = (np.arange(n) - n // 2) * DX
    xx, yy = np.meshgrid(x, x)
    r2 = xx ** 2 + yy ** 2
    u1 = np.exp(1j * np.pi * r2 / (LAM * z1)) / (1j * LAM * z1)
    u = u1 * (r2 <= aperture_radius ** 2) * np.exp(1j * phase)
    out = np.fft.ifft2(np.fft.fft2(u) * h)
    i = np.abs(out) ** 2
    return i / i.sum()


def _on_device(phase, camera, depths):
    """The stack's chunks, kept on the device (the last one waited for)."""
    chunks = [c for _, c in iter_psf_stack(phase, camera, depths, to_host=False,
                                           accept_undersampling=True)]
    chunks[-1].block_until_ready()
    return chunks


def _lightpipes_psf(lp, phase, n, z1):
    f = lp.Begin(n * DX, LAM, n)
    f = lp.Lens(f, -z1)
    f = lp.CircAperture(f, 0.3 * n * DX)
    f = lp.MultPhase(f, phase)
    f = lp.Forvard(f, Z2)
    return lp.Intensity(f, 1)


_PROBE = textwrap.dedent("""
    import json, sys, numpy as np, jax
    from benchmarks.bench_psf import _camera
    from diffcam.model.stack import psf_stack
    n, nz, method = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    cam = _camera(n, method)
    phase = np.random.default_rng(0).uniform(-np.pi, np.pi, (n, n)).astype(np.float32)
    def status(key):
        for line in open('/proc/self/status'):
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    psf_stack(phase, cam, [25e-3], accept_undersampling=True)  # compile, warm up
    import gc; gc.collect()
    open('/proc/self/clear_refs', 'w').write('5')  # reset the peak (VmHWM) to now
    rss0 = status('VmRSS')
    s = psf_stack(phase, cam, np.linspace(22e-3, 30e-3, nz), accept_undersampling=True)
    print(json.dumps({"working_mb": (status('VmHWM') - rss0 - s.nbytes) / 2**20}))
""")


def _working_memory(n, nz, method):
    """Peak RSS delta minus the stack, MB, in a fresh process (see module docstring)."""
    out = subprocess.run([sys.executable, "-c", _PROBE, str(n), str(nz), method],
                         capture_output=True, text=True, timeout=1800,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    if out.returncode:
        return None
    return json.loads(out.stdout.strip().splitlines()[-1])["working_mb"]


def _xla_temp_mb(fn, *args):
    try:
        return fn.lower(*args).compile().memory_analysis().temp_size_in_bytes / 2**20
    except Exception:  # memory analysis is optional in XLA backends
        return None


def run(sizes=(1024, 2048), n_depths=64, repeats=5, memory=True) -> list[dict]:
    """Benchmark rows, one per (N, candidate). See the module docstring."""
    notes: list[str] = []
    lp = optional_import("LightPipes", notes)
    rows = []
    for n in sizes:
        nz = n_depths if n <= 2048 else min(n_depths, 8)
        depths = np.linspace(22e-3, 30e-3, nz)
        rng = np.random.default_rng(0)
        phase = rng.uniform(-np.pi, np.pi, (n, n)).astype(np.float32)
        cams = {m: _camera(n, m) for m in ("direct", "scaling")}
        field = jnp.asarray(np.exp(1j * phase).astype(np.complex64))
        base = np.asarray(cams["direct"].aperture()) * np.exp(1j * phase).astype(np.complex64)
        fy = np.fft.fftfreq(n, DX)
        h = np.exp(-1j * np.pi * LAM * Z2 * fy ** 2).astype(np.complex64)
        h2 = h[:, None] * h[None, :]
        h2_64 = np.exp(-1j * np.pi * LAM * Z2 * (fy[:, None] ** 2 + fy[None, :] ** 2))
        n_np = 4 if n <= 2048 else 1
        w = jnp.asarray(rng.random((n, n)), jnp.float32)
        step = jax.jit(lambda u: fresnel_tf(u, DX, LAM, Z2))  # the unit: a jitted step
        grad = jax.jit(jax.grad(lambda ph: jnp.sum(w * psf(ph, cams["scaling"], 25e-3))))
        pair = jax.jit(lambda u: jnp.fft.ifft2(jnp.fft.fft2(u)))
        cands = {
            "jax fft2+ifft2": lambda: pair(field),
            "direct, on device": lambda: _on_device(phase, cams["direct"], depths),
            "scaling, on device": lambda: _on_device(phase, cams["scaling"], depths),
            "direct": lambda: psf_stack(phase, cams["direct"], depths,
                                        accept_undersampling=True, progress=False),
            "scaling": lambda: psf_stack(phase, cams["scaling"], depths, progress=False),
            "numpy": lambda: [_numpy_psf(base, h2, n, z) for z in depths[:n_np]],
            "numpy (plain)": lambda: [_plain_numpy_psf(phase, 0.3 * n * DX, h2_64, n, z)
                                      for z in depths[:n_np]],
            "grad (scaling)": lambda: grad(jnp.asarray(phase)),
        }
        if lp is not None and n <= 1024:
            cands["LightPipes"] = lambda: [_lightpipes_psf(lp, phase, n, z)
                                           for z in depths[:2]]
        per = {"direct": nz, "scaling": nz, "direct, on device": nz,
               "scaling, on device": nz, "numpy": n_np, "numpy (plain)": n_np,
               "LightPipes": 2}
        t = time_against(lambda: step(field), cands, repeats=repeats, budget_s=120)
        for name in cands:
            s, unit = t[name], t[name]["unit_s"]
            per_psf = s["median_s"] / per.get(name, 1)
            rows.append({"N": n, "candidate": name, "depths": per.get(name, 1),
                         "ms_per_psf": 1e3 * per_psf, "psf_per_s": 1 / per_psf,
                         "x_fresnel_tf": per_psf / unit, "fresnel_tf_ms": 1e3 * unit,
                         "repeats": s["repeats"], "first_s": s["first_s"],
                         "loadavg": os.getloadavg()[0]})
        for m in ("direct", "scaling"):
            cam = cams[m]
            wl, z, pos = cam.wavelength[None], jnp.ones(1) * 25e-3, jnp.zeros((1, 2))
            pre = jax.jit(diffuser_fields)(jnp.asarray(phase), cam, wl)
            fields = _chunk_inputs(None, pre, cam, wl, z, pos, None)
            temps = (_xla_temp_mb(_chunk_inputs, None, pre, cam, wl, z, pos, None),
                     _xla_temp_mb(_chunk_outputs, fields, fields, cam, wl, jnp.ones(1), z,
                                  pos, True, None))
            row = next(r for r in rows if r["N"] == n and r["candidate"] == m)
            row["xla_temp_mb"] = (None if None in temps  # + the two recycled buffers
                                  else sum(temps) + 2 * fields.nbytes / 2 ** 20)
            if memory:
                row["working_mb_8"] = _working_memory(n, min(8, nz), m)
                row["working_mb_all"] = _working_memory(n, nz, m)
        g = next(r for r in rows if r["N"] == n and r["candidate"] == "grad (scaling)")
        g["xla_temp_mb"] = _xla_temp_mb(grad, jnp.asarray(phase))
    run.notes = notes
    return rows


COLUMNS = ["N", "candidate", "depths", "ms_per_psf", "psf_per_s", "fresnel_tf_ms", "x_fresnel_tf",
           "xla_temp_mb", "working_mb_8", "working_mb_all", "loadavg"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4000])
    p.add_argument("--depths", type=int, default=64)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-memory", action="store_true", help="skip the RSS subprocesses")
    args = p.parse_args(argv)
    rows = run(args.sizes, args.depths, args.repeats, memory=not args.no_memory)
    print(markdown_table(rows, COLUMNS))
    for note in getattr(run, "notes", []):
        print(f"- {note}")
    path = write_json("psf", rows, {"notes": getattr(run, "notes", []),
                                    "memory": "working_mb_*: peak RSS − RSS before the "
                                              "stack call − stack bytes (fresh process); "
                                              "xla_temp_mb: XLA memory_analysis temp"})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
