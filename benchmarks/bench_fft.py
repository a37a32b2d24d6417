"""CPU FFT at the library's speed: diffcam's FFT seam with its FFTW backend and with
XLA's FFT, beside the FFT libraries called directly (issue: one step ≤ 1.2× pyFFTW).

    python -m benchmarks.bench_fft [--sizes 1024 2048 4096] [--repeats 7]
                                   [--workload-sizes 1024 2048] [--rounds 2]

Part 1, one process (complex64, medians, compile excluded), each candidate timed in
alternation with pyFFTW's version of the row alone and its ratio taken to that run's
pyFFTW (``benchmarks.harness.time_against``):

* ``pair``: ``ifft2(fft2(u))``; ``step``: one Fresnel transfer-function step at half its
  sampling limit (:func:`diffcam.optics.propagation.fresnel_tf`: FFT, product with the kernel, inverse
  FFT). diffcam runs jitted, compiled ahead of time once per backend;
* ``loop step``: the same step jitted with its input donated, called as ``u = step(u)``
  (a field propagated in a loop): XLA writes the output over the input's buffer instead
  of a fresh one (a fresh 4096² buffer is 32768 page faults here);
* ``fresh step``: the ``step`` programs again, against pyFFTW writing its step into a
  new array per call (``pyfftw.empty_aligned``, the input kept): the like-for-like
  reference for a step that returns a fresh array;
* pyFFTW: ``FFTW`` objects planned with ``FFTW_MEASURE`` on every thread, the step's
  product in place in numpy (normalisation left to the product, as diffcam folds it);
  scipy.fft with ``workers`` = every thread; numpy.fft (one thread).

Run it again as ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1 python -m benchmarks.bench_fft``
to see fresh buffers with huge pages (:mod:`diffcam.core.memory`; JSON
``fft_huge_pages.json``).

Part 2, whole workloads per iteration / per PSF, FFTW against XLA's FFT: each backend
runs in its own process (a backend is chosen when a function is traced, and diffcam's
functions keep their traces), the processes alternated ``--rounds`` times; the median
over the rounds. ``psf_stack`` per PSF (32 depths), Gerchberg–Saxton per iteration (50),
Richardson–Lucy per iteration (100, ``boundary="circular"``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from benchmarks.harness import markdown_table, time_against, write_json

LAM, DX = 532e-9, 2e-6
TARGET = 1.2


def _threads() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def transform_rows(n: int, repeats: int) -> list[dict]:
    import jax
    import jax.numpy as jnp

    from diffcam.core import backend, fftw
    from diffcam.optics.propagation import fresnel_tf

    fftw.load()  # first: pyFFTW shares FFTW's OpenMP runtime, which keeps the settings
    import pyfftw  # it read as it loaded (fftw.OPENMP_SPIN)
    import scipy.fft

    rng = np.random.default_rng(0)
    u = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))).astype(np.complex64)
    uj = jnp.asarray(u)
    z = 0.5 * n * DX ** 2 / LAM  # half the transfer function's sampling limit
    programs = {}
    for name in ("fftw", "xla"):
        backend.set_fft(name)
        programs[name, "pair"] = jax.jit(
            lambda v: backend.ifft2(backend.fft2(v))).lower(uj).compile()
        programs[name, "step"] = jax.jit(
            lambda v: fresnel_tf(v, DX, LAM, z)).lower(uj).compile()
        programs[name, "loop step"] = jax.jit(
            lambda v: fresnel_tf(v, DX, LAM, z), donate_argnums=0).lower(uj).compile()
    backend._setting["backend"] = None
    # the libraries' step multiplies by a kernel of the same size (its values do not
    # change the time), with the inverse's 1/N² folded in
    H = (np.exp(1j * rng.uniform(0, 2 * np.pi, (n, n))) / (n * n)).astype(np.complex64)

    threads = _threads()
    a = pyfftw.empty_aligned((n, n), "complex64")
    b = pyfftw.empty_aligned((n, n), "complex64")
    forward = pyfftw.FFTW(a, b, axes=(0, 1), threads=threads, flags=("FFTW_MEASURE",))
    inverse = pyfftw.FFTW(b, a, axes=(0, 1), direction="FFTW_BACKWARD", threads=threads,
                          flags=("FFTW_MEASURE",), normalise_idft=False)
    # "fresh step": pyFFTW's step into a new array per call (the input kept), what the
    # jitted step returning a fresh array does: both pay for new memory (plans of their
    # own, since calling a plan with new arrays rebinds it)
    c = pyfftw.empty_aligned((n, n), "complex64")
    fresh_forward = pyfftw.FFTW(a, c, axes=(0, 1), threads=threads, flags=("FFTW_MEASURE",))
    in_place = pyfftw.FFTW(c, c, axes=(0, 1), direction="FFTW_BACKWARD", threads=threads,
                           flags=("FFTW_MEASURE",), normalise_idft=False)
    a[:] = u

    def pyfftw_pair():
        forward()
        return inverse()

    def pyfftw_step():
        forward()
        np.multiply(b, H, out=b)
        return inverse()

    def pyfftw_fresh_step():
        out = pyfftw.empty_aligned((n, n), "complex64")
        fresh_forward(a, out)
        np.multiply(out, H, out=out)
        return in_place(out, out)

    # "loop step": u = step(u), the input donated (a field propagated in a loop), so the
    # output reuses its buffer as pyFFTW reuses its arrays
    fields = {name: jnp.array(uj) for name in ("fftw", "xla")}

    def loop_step(name):
        fields[name] = programs[name, "loop step"](fields[name])
        return fields[name]

    rows = []
    for kind in ("pair", "step", "loop step", "fresh step"):
        program = "step" if kind == "fresh step" else kind
        candidates = {
            "diffcam FFTW": (lambda p=programs["fftw", program]: p(uj))
                            if kind != "loop step" else (lambda: loop_step("fftw")),
            "diffcam XLA": (lambda p=programs["xla", program]: p(uj))
                           if kind != "loop step" else (lambda: loop_step("xla")),
            "pyFFTW": {"pair": pyfftw_pair, "fresh step": pyfftw_fresh_step}.get(
                kind, pyfftw_step),
            "scipy.fft": (lambda: scipy.fft.ifft2(scipy.fft.fft2(u, workers=threads),
                                                  workers=threads)) if kind == "pair" else
                         (lambda: scipy.fft.ifft2(scipy.fft.fft2(u, workers=threads) * H,
                                                  workers=threads)),
            "numpy.fft": (lambda: np.fft.ifft2(np.fft.fft2(u))) if kind == "pair" else
                         (lambda: np.fft.ifft2(np.fft.fft2(u) * H)),
        }
        if kind in ("loop step", "fresh step"):   # scipy and numpy: in "step" already
            del candidates["scipy.fft"], candidates["numpy.fft"]
        # each candidate in alternation with pyFFTW alone, its ratio to that run's
        # pyFFTW (a paired ratio: this machine's speed drifts by tens of per cent)
        reference = candidates.pop("pyFFTW")
        t = time_against(reference, candidates, repeats=repeats)
        for name, s in t.items():
            ratio = s["median_s"] / s["unit_s"]
            rows.append({"N": n, "row": kind, "candidate": name or "pyFFTW",
                         "ms": s["median_s"] * 1e3, "pyfftw_ms": s["unit_s"] * 1e3,
                         "vs_pyfftw": ratio,
                         "ok": (ratio <= TARGET) if name == "diffcam FFTW" else "",
                         "loadavg": os.getloadavg()[0]})
    # the seam's transforms agree with each other (a benchmark of wrong answers is none)
    out_f = np.asarray(programs["fftw", "step"](uj))
    assert np.allclose(np.asarray(programs["fftw", "loop step"](jnp.array(uj))), out_f)
    out_x = np.asarray(programs["xla", "step"](uj))
    assert np.abs(out_f - out_x).max() <= 1e-3 * np.abs(out_x).max(), "FFTW and XLA disagree"
    return rows


def workload_times(n: int, repeats: int) -> dict[str, float]:
    """Seconds per PSF / per iteration under the backend set by ``DIFFCAM_FFT``."""
    import jax

    import diffcam as dc
    from benchmarks.harness import time_interleaved as timed
    from diffcam.calibrate import CalibrationGeometry, calibration_intensities, gerchberg_saxton
    from diffcam.reconstruct import richardson_lucy

    cam = dc.Camera(wavelength=LAM, z2=1e-3, dx=5e-6, aperture_radius=0.3 * n * 5e-6,
                    shape=(n, n))
    phase = dc.random_diffuser(jax.random.key(0), (n, n), 5e-6, LAM)
    depths = np.linspace(22e-3, 30e-3, 32)
    geometry = CalibrationGeometry(dx=5e-6, wavelength=LAM, focal_length=5e-2)
    near, far = calibration_intensities(phase, cam.aperture(), geometry)
    psf = np.asarray(dc.psf(phase, cam, 25e-3))
    image = np.random.default_rng(1).uniform(0, 1, (n, n)).astype(np.float32)
    t = timed({
        "psf_stack per PSF": lambda: dc.psf_stack(phase, cam, depths, progress=False),
        "GS per iteration": lambda: gerchberg_saxton(near, far, geometry, iterations=50,
                                                     restarts=1, key=jax.random.key(1),
                                                     progress=False).phase,
        "RL per iteration": lambda: richardson_lucy(image, psf, 100, boundary="circular",
                                                    progress=False).image,
    }, repeats=repeats)
    per = {"psf_stack per PSF": len(depths), "GS per iteration": 50, "RL per iteration": 100}
    return {k: t[k]["median_s"] / per[k] for k in t}


def workload_rows(n: int, rounds: int, repeats: int) -> list[dict]:
    runs = {"fftw": [], "xla": []}
    for _ in range(rounds):
        for name in runs:
            env = dict(os.environ, DIFFCAM_FFT=name)
            done = subprocess.run([sys.executable, "-m", "benchmarks.bench_fft", "--child",
                                   str(n), "--repeats", str(repeats)], env=env,
                                  capture_output=True, text=True, check=True)
            runs[name].append(json.loads(done.stdout.strip().splitlines()[-1]))
    rows = []
    for key in runs["fftw"][0]:
        f = float(np.median([r[key] for r in runs["fftw"]]))
        x = float(np.median([r[key] for r in runs["xla"]]))
        rows.append({"N": n, "row": key, "candidate": "FFTW vs XLA", "ms": f * 1e3,
                     "xla_ms": x * 1e3, "speedup": x / f, "loadavg": os.getloadavg()[0]})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--workload-sizes", type=int, nargs="*", default=[1024, 2048])
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(workload_times(args.child, args.repeats)))
        return
    rows = [r for n in args.sizes for r in transform_rows(n, args.repeats)]
    print(markdown_table(rows, ["N", "row", "candidate", "ms", "pyfftw_ms", "vs_pyfftw", "ok",
                                "loadavg"]))
    work = [r for n in args.workload_sizes
            for r in workload_rows(n, args.rounds, max(3, args.repeats // 2))] \
        if args.rounds else []
    if work:
        print(markdown_table(work, ["N", "row", "ms", "xla_ms", "speedup", "loadavg"]))
    from diffcam.core import memory
    name = "fft_huge_pages" if memory.huge_pages() == "on" else "fft"
    extra = {"target_vs_pyfftw": TARGET, "threads": _threads(), "memory": memory.status()}
    print(f"{memory.status()}\nwrote {write_json(name, rows + work, extra)}")


if __name__ == "__main__":
    main()
