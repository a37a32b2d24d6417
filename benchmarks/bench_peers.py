"""diffcam beside the JAX optics peers (chromatix, dLux): one PSF stack, forward and gradient.

    python -m benchmarks.bench_peers [--sizes 512 1024] [--depths 32] [--grad-depths 32 256]
        [--grad-sizes 1024] [--repeats 5] [--chromatix-python /path/to/python3.12]

The workload, the same physics in every library, written the way its users write it: a
point source at z1 (``--depths`` depths, 20–60 mm) in front of a thin random-phase diffuser
(:func:`diffcam.random_diffuser`, 30 µm features) with a circular aperture of radius
0.3·N·dx, Fresnel transfer-function propagation over z2 = 1 mm, PSF = |field|² on the
full N × N grid (2 µm pitch, 532 nm), float32.

Forward candidates (the stack of PSFs):

- ``diffcam psf_stack``: :func:`diffcam.psf_stack` (host loop of chunks), scaling path
  (default) and direct path (``Camera(method="direct")``);
- ``diffcam jit(vmap(psf))``: ``jax.jit(jax.vmap(lambda z: diffcam.psf(phase, camera, z)))``;
- ``diffcam psf_map``: ``jax.jit(lambda p, z: diffcam.psf_map(lambda h: h, p, camera, z))``;
- ``, FFTW``: ``psf_stack`` and ``jit(vmap(psf))`` on the opt-in FFTW backend
  (``set_fft("fftw")``), whose FFTs run on FFTW's own threads wherever XLA's program
  starts them (XLA's own FFT takes one thread when it starts on a pool thread, as the
  FFTs of a composed loop do: ``docs/design.md``, "The backend seam");
- ``chromatix``: ``chromatix.functional`` (``point_source`` with a ``circular_pupil``
  → ``phase_change`` → ``transfer_propagate``, no padding, intensity), in micrometres
  (its point source flattens in metres): all depths in one call (``z`` an array: the
  field gets a batch axis), ``jax.vmap`` over depth, and ``jax.lax.map`` over depth;
- ``dLux``: a ``dl.Wavefront`` (``center=-dx/2``, which puts the axis on pixel N/2 as
  diffcam and chromatix do: dLux's default grid centres it between pixels, a
  half-pixel shift of aperture and source worth 1 − Pearson 1.8e-3 at 512²) given the point source's spherical
  phase (``add_phase`` of k·r²/(2·z1) on ``wf.coordinates()``), a ``dl.layers.Optic``
  with the aperture (``dlu.circle``) as transmission and the diffuser as phase, and
  ``dl.layers.ASMPropagator(z2, dl.PadSpec(pad=1))``: dLux's paraxial angular-spectrum
  (Fresnel transfer-function) propagator, from its abcdLux backend; ``wf.psf``.
  ``jax.vmap`` and ``jax.lax.map`` over depth.

``lax.map`` runs ``max(1, 2**20 // N²)`` depths a step, as many as ``psf_stack`` and
``psf_map`` put in a chunk (one at 1024²).

Gradient candidates, ``jax.jit(jax.value_and_grad(loss))`` with respect to the diffuser
phase, loss = Σ_z Σ w·PSF_z with one fixed random plane w reused at every depth: diffcam
through ``psf_loss(lambda h: jnp.sum(h * w), ...)``, through
``psf_map(lambda h: jnp.sum(h * w), ...)`` summed (both paths) and through a
composed ``vmap(psf)``; chromatix and dLux through ``vmap`` and through ``lax.map`` of a
``jax.checkpoint``-ed depth. At ``--grad-depths`` (default 32 and 256) on
``--grad-sizes`` (default 1024). ``x_forward`` is value_and_grad ÷ the forward of the same
candidate at the same size and depth count (``psf_loss``'s: ``psf_map``'s; above
``--depths``, the forwards of ``psf_map`` and the ``lax.map`` peers are run for it).

Before timing, every candidate's output is compared with diffcam's direct path, one
:func:`diffcam.psf` per depth (gradients: a per-depth ``jax.grad`` summed over depths;
diffcam's scaling-path gradients against the scaling path's, `reference_method`):
``worst_1mp`` is the largest 1 − Pearson over depths (over the gradient for gradients),
and a candidate above 1e-3 is reported and not timed.

Each candidate runs in its own fresh process (the chromatix ones under
``--chromatix-python``), which stays alive while the candidates of its table are timed
interleaved: ``--repeats`` rounds of one call each, the median reported; the first call
(compile and run) is ``first_s`` and excluded. A candidate whose calls add up to more
than ``--budget`` seconds is timed fewer times (``repeats`` says how many). Peak memory
(``peak_mb``): after the first call, the process's peak RSS (VmHWM) is reset through
``/proc/self/clear_refs`` and one call made (the first timed round); ``peak_mb`` is that
peak minus the RSS just before the call (the returned stack included: 4·nz·N² bytes, the same for every forward
candidate). Between calls a process frees its outputs and returns freed heap to the
system (``malloc_trim``), so every call starts alike. A jitted candidate whose compiled
program needs more memory than the machine has free (XLA's ``memory_analysis``) is not
run: ``status`` says so. ``load`` is the 1-minute load average during its calls.

How the peers install: dLux from the package registry (``pip install dlux``; 0.15.1 has
its Fresnel propagator in its abcdLux dependency). chromatix's registry release is a
2022 placeholder: its current source needs Python ≥ 3.12; make a Python 3.12 virtual
environment, ``pip install`` a checkout of ``chromatix-team/chromatix`` and ``pip install
-e`` this repository into it (same JAX version as here), and pass its interpreter as
``--chromatix-python``. Without one, chromatix runs in this interpreter if it imports
here, and is skipped with a message otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

LAM, DX, Z2 = 532e-9, 2e-6, 1e-3
Z_RANGE = (20e-3, 60e-3)
THRESHOLD = 1e-3
ROOT = Path(__file__).resolve().parents[1]

FORWARD = {
    # name: (library, pairing key for value_and_grad ÷ forward)
    "diffcam psf_stack (scaling)": "diffcam",
    "diffcam psf_stack (direct)": "diffcam",
    "diffcam psf_stack, FFTW (scaling)": "diffcam",
    "diffcam psf_stack, FFTW (direct)": "diffcam",
    "diffcam jit(vmap(psf)) (scaling)": "diffcam",
    "diffcam jit(vmap(psf)) (direct)": "diffcam",
    "diffcam jit(vmap(psf)), FFTW (scaling)": "diffcam",
    "diffcam jit(vmap(psf)), FFTW (direct)": "diffcam",
    "diffcam psf_map (scaling)": "diffcam",
    "diffcam psf_map (direct)": "diffcam",
    "chromatix (z batched)": "chromatix",
    "chromatix (vmap)": "chromatix",
    "chromatix (lax.map)": "chromatix",
    "dLux (vmap)": "dLux",
    "dLux (lax.map)": "dLux",
}
GRAD = {
    "diffcam psf_loss (scaling)": "diffcam",
    "diffcam psf_loss (direct)": "diffcam",
    "diffcam psf_map (scaling)": "diffcam",
    "diffcam psf_map (direct)": "diffcam",
    "diffcam vmap(psf) (scaling)": "diffcam",
    "diffcam vmap(psf) (direct)": "diffcam",
    "chromatix (vmap)": "chromatix",
    "chromatix (lax.map + checkpoint)": "chromatix",
    "dLux (vmap)": "dLux",
    "dLux (lax.map + checkpoint)": "dLux",
}
FORWARD_OF = {"diffcam psf_loss (scaling)": "diffcam psf_map (scaling)",
              "diffcam psf_loss (direct)": "diffcam psf_map (direct)",
              "diffcam vmap(psf) (scaling)": "diffcam jit(vmap(psf)) (scaling)",
              "diffcam vmap(psf) (direct)": "diffcam jit(vmap(psf)) (direct)",
              "chromatix (lax.map + checkpoint)": "chromatix (lax.map)",
              "dLux (lax.map + checkpoint)": "dLux (lax.map)"}
"""The forward candidate a gradient candidate is divided by (by default its own name)."""

MANY_DEPTHS = ("psf_map", "lax.map")
"""The forward candidates also run at a gradient's depth count above ``--depths``: those
whose value_and_grad divides by them there (the vmap gradients are run there too, if
XLA's plan fits in free memory, but have no forward beside them)."""


# ------------------------------------------------------------------ the candidates

def chunk_depths(n: int) -> int:
    """Depths a ``lax.map`` step (and a diffcam chunk): about 2**20 field samples."""
    return max(1, 2 ** 20 // (n * n))


def _diffcam(name, n, phase, depths, w, kind):
    import jax
    import jax.numpy as jnp
    import diffcam
    method = "direct" if "(direct)" in name else "scaling"
    if "FFTW" in name:   # the opt-in backend (the fftw extra); an error if it cannot load
        from diffcam.core.backend import set_fft
        set_fft("fftw")
    cam = diffcam.Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_radius=0.3 * n * DX,
                         shape=(n, n), method=method)
    diffcam.psf(phase, cam, float(depths[0]))  # the checks, once, eagerly
    p, z = jnp.asarray(phase), jnp.asarray(depths, jnp.float32)
    if kind == "forward":
        if "psf_stack" in name:
            return lambda: diffcam.psf_stack(phase, cam, depths, progress=False), None
        if "vmap" in name:
            f = jax.jit(lambda p, z: jax.vmap(lambda zi: diffcam.psf(p, cam, zi))(z))
        else:
            f = jax.jit(lambda p, z: diffcam.psf_map(lambda h: h, p, cam, z))
        return f, (p, z)
    wj = jnp.asarray(w)
    if "psf_loss" in name:
        def loss(p, z):
            return diffcam.psf_loss(lambda h: jnp.sum(h * wj), p, cam, z)
    elif "psf_map" in name:
        def loss(p, z):
            return jnp.sum(diffcam.psf_map(lambda h: jnp.sum(h * wj), p, cam, z))
    else:
        def loss(p, z):
            return jnp.sum(jax.vmap(lambda zi: diffcam.psf(p, cam, zi))(z) * wj)
    return jax.jit(jax.value_and_grad(loss)), (p, z)


def chromatix_psfs(n, dx, wavelength, z2, aperture_radius):
    """``stack(phase, z)``: chromatix's PSFs of the depths z (metres; an array: one
    batched field) or of one depth, (…, n, n), through a diffuser of ``phase`` (radians)
    in a circular aperture, on an n² grid of pitch dx (all lengths in metres)."""
    import jax.numpy as jnp
    import chromatix.functional as cf
    um = 1e6  # chromatix works in micrometres
    dx, lam, z2, radius = dx * um, wavelength * um, z2 * um, aperture_radius * um

    def pupil(field):
        return cf.circular_pupil(field, 2 * radius)

    def stack(p, z):
        field = cf.point_source((n, n), dx, lam, z * um, n=1.0, pupil=pupil)
        field = cf.phase_change(field, p)
        field = cf.transfer_propagate(field, z2, n=1.0, pad_width=0)
        return field.intensity.reshape(jnp.shape(z) + (n, n))
    return stack


def _chromatix(name, n, phase, depths, w, kind):
    import jax
    import jax.numpy as jnp
    stack = chromatix_psfs(n, DX, LAM, Z2, 0.3 * n * DX)
    p, z = jnp.asarray(phase), jnp.asarray(depths, jnp.float32)
    chunk = chunk_depths(n)
    if "batched" in name:
        forward = stack
    elif "vmap" in name:
        def forward(p, z):
            return jax.vmap(lambda zi: stack(p, zi))(z)
    else:
        one = jax.checkpoint(stack) if kind != "forward" else stack

        def forward(p, z):
            return jax.lax.map(lambda zi: one(p, zi), z, batch_size=chunk)
    if kind == "forward":
        return jax.jit(forward), (p, z)
    wj = jnp.asarray(w)
    if "lax.map" in name:  # reduce each depth inside the map: nothing kept per depth
        def loss(p, z):
            return jnp.sum(jax.lax.map(lambda zi: jnp.sum(one(p, zi) * wj), z,
                                       batch_size=chunk))
    else:
        def loss(p, z):
            return jnp.sum(forward(p, z) * wj)
    return jax.jit(jax.value_and_grad(loss)), (p, z)


def dlux_psf(n, dx, wavelength, z2, aperture_radius):
    """``one(phase, z1)``: dLux's PSF of one depth z1, (n, n), as `chromatix_psfs`."""
    import jax.numpy as jnp
    import dLux as dl
    import dLux.utils as dlu
    center = jnp.array([-dx / 2])  # the axis on pixel N/2, as diffcam's and chromatix's
    propagator = dl.layers.ASMPropagator(z2, dl.PadSpec(pad=1))

    def one(p, z1):
        wf = dl.Wavefront(wavelength, n, pixel_scale=dx, center=center)
        coords = wf.coordinates()
        wf = wf.add_phase(wf.wavenumber * jnp.sum(coords ** 2, axis=0) / (2 * z1))
        wf = dl.layers.Optic(transmission=dlu.circle(coords, aperture_radius), phase=p)(wf)
        return propagator(wf).psf
    return one


def _dlux(name, n, phase, depths, w, kind):
    import jax
    import jax.numpy as jnp
    one = dlux_psf(n, DX, LAM, Z2, 0.3 * n * DX)
    p, z = jnp.asarray(phase), jnp.asarray(depths, jnp.float32)
    chunk = chunk_depths(n)
    if "vmap" in name:
        def forward(p, z):
            return jax.vmap(lambda zi: one(p, zi))(z)
    else:
        step = jax.checkpoint(one) if kind != "forward" else one

        def forward(p, z):
            return jax.lax.map(lambda zi: step(p, zi), z, batch_size=chunk)
    if kind == "forward":
        return jax.jit(forward), (p, z)
    wj = jnp.asarray(w)
    if "lax.map" in name:
        def loss(p, z):
            return jnp.sum(jax.lax.map(lambda zi: jnp.sum(step(p, zi) * wj), z,
                                       batch_size=chunk))
    else:
        def loss(p, z):
            return jnp.sum(forward(p, z) * wj)
    return jax.jit(jax.value_and_grad(loss)), (p, z)


BUILDERS = {"diffcam": _diffcam, "chromatix": _chromatix, "dLux": _dlux}


def library(name: str) -> str:
    return name.split()[0]


# ------------------------------------------------------------------ the worker process

def _status(key: str) -> int:
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1]) * 1024
    return 0


def _trim() -> None:
    """Free what Python holds and give freed heap back to the system."""
    import ctypes
    import gc
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except OSError:
        pass


def _block(x):
    import jax
    return jax.block_until_ready(x)


def worker(spec: dict) -> None:
    """Build one candidate, answer the parent's commands on stdin (one JSON per line)."""
    import jax

    def say(**message):
        print(json.dumps(message), flush=True)

    data = np.load(spec["inputs"])
    phase, depths, w = data["phase"], data["depths"], data["w"]
    name, kind, n = spec["name"], spec["kind"], spec["n"]
    lib = library(name)
    mod = __import__(lib)
    versions = {"python": sys.version.split()[0], "jax": jax.__version__,
                lib: getattr(mod, "__version__", None)}
    try:
        fn, args = BUILDERS[lib](name, n, phase, depths, w, kind)
        call = (lambda: fn(*args)) if args is not None else fn
        t = time.perf_counter()
        if args is not None:  # compile ahead, and see whether the program fits
            compiled = fn.lower(*args).compile()
            need = _xla_bytes(compiled)
            free = _available_bytes()
            if need is not None and free is not None and need > 0.8 * free:
                say(status=f"out of memory: XLA plans {need / 2**30:.1f} GB, "
                           f"{free / 2**30:.1f} GB free", versions=versions)
                return
            call = lambda: compiled(*args)  # noqa: E731
        out = _block(call())
        first_s = time.perf_counter() - t
    except Exception as e:  # a peer that fails is reported, never fatal
        say(status=f"failed: {type(e).__name__}: {str(e)[:300]}", versions=versions)
        return
    if kind == "forward":
        np.save(spec["output"], np.asarray(out, np.float32).reshape(len(depths), n, n))
    else:
        np.save(spec["output"], np.asarray(out[1], np.float32))
    del out
    say(status="ready", first_s=first_s, versions=versions)
    for line in sys.stdin:
        command = line.strip()
        if command == "quit":
            return
        _trim()
        if command == "memory":
            open("/proc/self/clear_refs", "w").write("5")  # the peak (VmHWM) is now
            rss0 = _status("VmRSS")
            t = time.perf_counter()
            out = _block(call())
            dt = time.perf_counter() - t
            peak = _status("VmHWM") - rss0
            del out
            say(peak_mb=peak / 2 ** 20, time_s=dt, load=os.getloadavg()[0])
        elif command == "time":
            t = time.perf_counter()
            out = _block(call())
            dt = time.perf_counter() - t
            del out
            say(time_s=dt, load=os.getloadavg()[0])


def _xla_bytes(compiled) -> int | None:
    try:
        m = compiled.memory_analysis()
        return int(m.temp_size_in_bytes + m.output_size_in_bytes + m.argument_size_in_bytes)
    except Exception:  # memory analysis is optional in XLA backends
        return None


def _available_bytes() -> int | None:
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


# ------------------------------------------------------------------ the parent

class Candidate:
    """A worker process running one candidate."""

    def __init__(self, name, kind, n, inputs, tmp, python, timeout):
        self.name, self.kind, self.n, self.timeout = name, kind, n, timeout
        self.output = str(Path(tmp) / f"{kind}_{n}_{abs(hash(name))}.npy")
        spec = {"name": name, "kind": kind, "n": n, "inputs": inputs, "output": self.output}
        self.proc = subprocess.Popen([python, "-m", "benchmarks.bench_peers", "--worker",
                                      json.dumps(spec)], cwd=ROOT, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True)
        self.row = {"kind": kind, "N": n, "candidate": name, "library": library(name),
                    "times_s": [], "loads": []}

    def read(self, timeout=None) -> dict | None:
        """The worker's next message; None (and the worker ended) past the timeout."""
        timeout = self.timeout if timeout is None else timeout
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        line = self.proc.stdout.readline() if ready else ""
        if not line:
            alive = self.proc.poll() is None
            self.stop()
            err = self.proc.stderr.read()[-300:].strip() if not alive else ""
            self.row["status"] = (f"skipped: > {timeout:.0f} s" if alive
                                  else f"failed: {err or 'worker ended'}")
            return None
        return json.loads(line)

    def send(self, command: str) -> dict | None:
        if self.proc.poll() is not None:
            return None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return self.read()

    def stop(self):
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=30)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


def one_minus_pearson(a, b) -> float:
    a = np.asarray(a, np.float64).ravel()
    b = np.asarray(b, np.float64).ravel()
    return float(1 - np.corrcoef(a, b)[0, 1])


def reference_method(kind, name) -> str:
    """The path a candidate is checked against: diffcam's direct path, but a gradient
    of diffcam's scaling path against the scaling path's own (the two discretisations'
    gradients differ, 1 − Pearson 0.04 with a white-noise weight, their PSFs 1.2e-4)."""
    scaling = name.startswith("diffcam") and "(scaling)" in name
    return "scaling" if kind == "value_and_grad" and scaling else "direct"


def reference(kind, n, phase, depths, w, method="direct"):
    """One :func:`diffcam.psf` per depth on ``method``'s path: the PSFs (forward) or
    the gradient of the loss as a sum of per-depth gradients."""
    import jax
    import jax.numpy as jnp
    import diffcam
    cam = diffcam.Camera(wavelength=LAM, z2=Z2, dx=DX, aperture_radius=0.3 * n * DX,
                         shape=(n, n), method=method)
    p = jnp.asarray(phase)
    if kind == "forward":
        one = jax.jit(lambda p, z: diffcam.psf(p, cam, z))
        return np.stack([np.asarray(one(p, jnp.float32(z))) for z in depths])
    wj = jnp.asarray(w)
    g = jax.jit(jax.grad(lambda p, z: jnp.sum(diffcam.psf(p, cam, z) * wj)))
    total = np.zeros((n, n), np.float64)
    for z in depths:
        total += np.asarray(g(p, jnp.float32(z)), np.float64)
    return total


def agreement(kind, out, ref) -> float:
    if kind == "forward":
        return max(one_minus_pearson(o, r) for o, r in zip(out, ref))
    return one_minus_pearson(out, ref)


def run_table(kind, n, nz, names, pythons, tmp, repeats, budget, timeout, log):
    """Start one worker per candidate, check them, measure memory, time interleaved."""
    import diffcam
    rng = np.random.default_rng(0)
    import jax
    phase = np.asarray(diffcam.random_diffuser(jax.random.key(0), (n, n), DX, LAM),
                       np.float32)
    depths = np.linspace(*Z_RANGE, nz)
    w = rng.random((n, n)).astype(np.float32)
    inputs = str(Path(tmp) / f"inputs_{n}_{nz}.npz")
    np.savez(inputs, phase=phase, depths=depths, w=w)
    live, rows = [], []
    for name in names:
        c = Candidate(name, kind, n, inputs, tmp, pythons[library(name)], timeout)
        c.row["depths"] = nz
        rows.append(c.row)
        msg = c.read()
        if msg is None:
            log(f"  {name}: {c.row['status']}")
            continue
        c.row["versions"] = msg.get("versions")
        if msg["status"] != "ready":
            c.row["status"] = msg["status"]
            log(f"  {name}: {msg['status']}")
            c.stop()
            continue
        c.row["first_s"] = msg["first_s"]
        live.append(c)
    refs = {}
    for method in sorted({reference_method(kind, c.name) for c in live}):
        t = time.perf_counter()
        refs[method] = reference(kind, n, phase, depths, w, method)
        log(f"  reference ({kind}, diffcam {method}, per depth): "
            f"{time.perf_counter() - t:.1f} s")
    for c in list(live):
        out = np.load(c.output)
        os.remove(c.output)
        c.row["worst_1mp"] = agreement(kind, out, refs[reference_method(kind, c.name)])
        del out
        if not c.row["worst_1mp"] <= THRESHOLD:
            c.row["status"] = f"disagrees: 1 − Pearson {c.row['worst_1mp']:.2g} > {THRESHOLD}"
            c.stop()
            live.remove(c)
    del refs
    for c in list(live):
        msg = c.send("memory")
        if msg is None:
            live.remove(c)
            continue
        c.row["peak_mb"] = msg["peak_mb"]
        c.row["times_s"].append(msg["time_s"])
        c.row["loads"].append(msg["load"])
    for _ in range(repeats - 1):
        for c in list(live):
            if c.row["times_s"] and sum(c.row["times_s"]) > budget:
                continue
            msg = c.send("time")
            if msg is None:
                live.remove(c)
                continue
            c.row["times_s"].append(msg["time_s"])
            c.row["loads"].append(msg["load"])
    for c in live:
        c.stop()
        c.row["status"] = "ok"
    for r in rows:
        ts = r.pop("times_s")
        loads = r.pop("loads")
        if ts:
            r.update(median_s=float(np.median(ts)), min_s=min(ts), times_s=ts,
                     repeats=len(ts), load=float(np.median(loads)))
        log(f"  {r['candidate']}: {_short(r)}")
    return rows


def _short(r) -> str:
    if r.get("status") != "ok":
        return r.get("status", "?")
    return (f"{r['median_s']:.3f} s (×{r['repeats']}), peak {r['peak_mb']:.0f} MB, "
            f"1 − Pearson {r['worst_1mp']:.1e}, first {r['first_s']:.1f} s")


def _chromatix_python(option: str | None, notes: list[str]) -> str | None:
    if option:
        probe = subprocess.run([option, "-c", "import chromatix, diffcam"],
                               capture_output=True, text=True, cwd=ROOT)
        if probe.returncode == 0:
            return option
        notes.append(f"chromatix skipped: {option} cannot import chromatix and diffcam "
                     f"({probe.stderr.strip().splitlines()[-1:]})")
        return None
    import importlib.util
    if importlib.util.find_spec("chromatix") is not None:
        try:
            import chromatix.functional  # noqa: F401  the registry placeholder has none
            return sys.executable
        except Exception as e:
            notes.append(f"chromatix skipped: it imports here but has no functional API "
                         f"({type(e).__name__}: {e}); give --chromatix-python")
            return None
    notes.append("chromatix skipped: not importable in this interpreter and no "
                 "--chromatix-python given (its current source needs Python ≥ 3.12)")
    return None


def _brief(status: str) -> str:
    return status if len(status) <= 60 else status[:57] + "…"


def markdown(rows) -> str:
    """Forward: one line per candidate, a column per size; gradients: one per depth count."""
    def cell(r, key, fmt):
        if r is None:
            return ""
        if r.get("status") != "ok":
            return _brief(r.get("status", ""))
        return fmt.format(r[key])
    fw = [r for r in rows if r["kind"] == "forward"]
    sizes = sorted({r["N"] for r in fw})
    lines = []
    for nz in sorted({r["depths"] for r in fw}):
        head = ([f"{nz}-PSF stack"] + [f"{n}² s" for n in sizes] + [f"peak RSS {n}²" for n in sizes]
                + ["worst 1 − Pearson"])
        lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for name in FORWARD:
            got = {r["N"]: r for r in fw if r["candidate"] == name and r["depths"] == nz}
            if not got:
                continue
            worst = max((r.get("worst_1mp", 0) or 0) for r in got.values())
            lines.append("| " + " | ".join(
                [name] + [cell(got.get(n), "median_s", "{:.3f}") for n in sizes]
                + [cell(got.get(n), "peak_mb", "{:.0f} MB") for n in sizes]
                + [f"{worst:.1e}"]) + " |")
    gr = [r for r in rows if r["kind"] == "value_and_grad"]
    for n in sorted({r["N"] for r in gr}):
        counts = sorted({r["depths"] for r in gr if r["N"] == n})
        head = [f"value_and_grad {n}²"] + [f"{k} depths: s / ÷ forward / peak RSS"
                                           for k in counts] + ["worst 1 − Pearson"]
        lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for name in GRAD:
            got = {r["depths"]: r for r in gr if r["candidate"] == name and r["N"] == n}
            if not got:
                continue
            cells = []
            for k in counts:
                r = got.get(k)
                if r is None:
                    cells.append("")
                elif r.get("status") != "ok":
                    cells.append(_brief(r["status"]))
                else:
                    x = r.get("x_forward")
                    cells.append(f"{r['median_s']:.2f} s / "
                                 f"{'' if x is None else f'{x:.2f}×'} / {r['peak_mb']:.0f} MB")
            worst = max((r.get("worst_1mp", 0) or 0) for r in got.values())
            lines.append("| " + " | ".join([name] + cells + [f"{worst:.1e}"]) + " |")
    return "\n".join(lines)


def _record(name, rows, notes, wall_s, complete):
    """Write the JSON of the rows so far (rewritten after every table, so that a run cut
    short leaves what it measured, ``complete`` false); return its path and the table."""
    import copy
    from benchmarks import harness
    rows = copy.deepcopy(rows)
    for r in rows:
        if r["kind"] == "value_and_grad" and r.get("status") == "ok":
            fname = FORWARD_OF.get(r["candidate"], r["candidate"])
            f = next((q for q in rows if q["kind"] == "forward" and q["N"] == r["N"]
                      and q["depths"] == r["depths"] and q["candidate"] == fname
                      and q.get("status") == "ok"), None)
            r["x_forward"] = None if f is None else r["median_s"] / f["median_s"]
            r["forward"] = fname
    table = markdown(rows)
    versions = {}
    for r in rows:
        for k, v in (r.pop("versions", None) or {}).items():
            versions.setdefault(f"{r['library']}: {k}", v)
    start = dict(harness._START)  # one run: the same start however often it is written
    path = harness.write_json(name, rows, {
        "complete": complete, "notes": notes, "peer_versions": versions, "table": table,
        "wall_s": wall_s,
        "memory": "peak_mb: peak RSS (VmHWM, reset after the first call) − RSS before "
                  "the call, in the candidate's own process; the returned stack included",
        "agreement": f"worst_1mp: largest 1 − Pearson against diffcam's direct path, one "
                     f"psf per depth (gradients: per-depth grads summed; diffcam's "
                     f"scaling-path gradients against the scaling path's); > {THRESHOLD} "
                     f"is not timed"})
    harness._START.update(start)
    return path, table


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    p.add_argument("--depths", type=int, default=32)
    p.add_argument("--grad-sizes", type=int, nargs="*", default=[1024])
    p.add_argument("--grad-depths", type=int, nargs="*", default=[32, 256])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--budget", type=float, default=30.0,
                   help="seconds of timed calls after which a candidate is timed no more")
    p.add_argument("--timeout", type=float, default=600.0,
                   help="seconds a worker may take for one step before it is stopped")
    p.add_argument("--chromatix-python", default=None,
                   help="an interpreter where chromatix and diffcam import (Python ≥ 3.12)")
    p.add_argument("--only", nargs="*", default=None, help="candidates whose name contains")
    p.add_argument("--name", default="peers")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker is not None:
        return worker(json.loads(args.worker))
    notes: list[str] = []
    pythons = {"diffcam": sys.executable, "dLux": sys.executable,
               "chromatix": _chromatix_python(args.chromatix_python, notes)}
    import importlib.util
    if importlib.util.find_spec("dLux") is None:
        notes.append("dLux skipped: not installed (pip install dlux)")
        pythons["dLux"] = None
    for note in notes:
        print(f"- {note}", flush=True)

    def keep(name):
        return pythons[library(name)] is not None and (
            args.only is None or any(s in name for s in args.only))

    def log(text):
        print(text, flush=True)

    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench_peers_") as tmp:
        plan = [("forward", n, args.depths, [c for c in FORWARD if keep(c)])
                for n in args.sizes]
        for n in args.grad_sizes:
            for nz in args.grad_depths:
                many = nz > args.depths
                if many:  # the forward at this depth count, for x_forward
                    plan.append(("forward", n, nz,
                                 [c for c in FORWARD if keep(c) and
                                  any(m in c for m in MANY_DEPTHS)]))
                plan.append(("value_and_grad", n, nz, [c for c in GRAD if keep(c)]))
        for kind, n, nz, names in plan:
            log(f"{kind}, {n}², {nz} depths ({time.perf_counter() - t0:.0f} s so far):")
            rows += run_table(kind, n, nz, names, pythons, tmp, args.repeats, args.budget,
                              args.timeout, log)
            path, table = _record(args.name, rows, notes, time.perf_counter() - t0,
                                  complete=(kind, n, nz) == plan[-1][:3])
    print(table)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
