"""FFTW as diffcam's CPU FFT, callable inside ``jit``, ``vmap``, loops and both modes of
differentiation.

XLA's CPU FFT runs its library (ducc0) on one thread in common cases (an FFT that
follows another operation: [`diffcam.core.backend`][diffcam.core.backend]); called directly,
the same class of library is up to 2x faster at 4096² on two cores. This module runs the 2-D
transforms of [`diffcam.core.backend`][diffcam.core.backend] through FFTW instead, as XLA
FFI custom calls (``fftw_ffi.cc``, a small C++ file compiled on first use with the machine's
C++ compiler into diffcam's cache folder) on FFTW's own threads.

FFTW itself comes from pyFFTW's wheel (``pip install 'diffcam[fftw]'``, which ships
FFTW's shared libraries) or from the system (``libfftw3f`` and ``libfftw3``, e.g.
Debian's ``libfftw3-dev``). FFTW is GPL-licensed: a program that uses this backend
runs GPL code; diffcam's own code stays BSD-3-Clause, and without FFTW it uses XLA's
FFT.

Three linear primitives, each over the last two axes, batched over leading ones,
unnormalised (FFTW's conventions)::

    c2c(x, sign)   sign −1: Σ x e^{−2πi k·n/N}; +1: Σ x e^{+2πi k·n/N}
    r2c(x)         real (…, ny, nx) → (…, ny, nx//2 + 1), sign −1
    c2r(x, nx)     (…, ny, nx//2 + 1) → real (…, ny, nx), sign +1, the input taken as
                   the half spectrum of a real array (imaginary parts that Hermitian
                   symmetry makes zero are ignored)

Their transposes (JAX's, not conjugated), which give reverse mode::

    c2c(·, s)ᵀ = c2c(·, s)                  (the DFT matrix is symmetric)
    r2cᵀ(c)    = c2r(conj(c) / w, nx)       w = 2 on the half spectrum's columns that
    c2rᵀ(c)    = w · conj(r2c(c))           stand for two, 1 at k = 0 (and nx/2, even nx)

Forward mode applies each primitive to the tangent; ``vmap`` moves the mapped axis to
the front. Use it through [`diffcam.core.backend`][diffcam.core.backend], which picks the
backend.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import ctypes.util
import functools
import glob
import hashlib
import importlib.util
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from diffcam.core.errors import DiffcamError, environment_count

__all__ = ["c2c", "r2c", "c2r", "load", "configure", "threads", "environment_threads",
           "save_wisdom", "cache_folder"]

_SOURCE = Path(__file__).with_name("fftw_ffi.cc")
_FUNCTIONS = ("plan_many_dft", "plan_many_dft_r2c", "plan_many_dft_c2r", "execute_dft",
              "execute_dft_r2c", "execute_dft_c2r", "destroy_plan", "plan_with_nthreads",
              "alignment_of", "malloc", "free", "set_timelimit", "export_wisdom_to_string",
              "import_wisdom_from_string")  # the order of struct Api in fftw_ffi.cc
_PREFIX = {0: "fftwf_", 1: "fftw_"}    # single, double precision
_STEM = {0: "fftw3f", 1: "fftw3"}
PLANNING = {"estimate": 1 << 6, "measure": 0, "patient": 1 << 5}  # FFTW's flags
PLANNING_SECONDS = 30.0  # FFTW's time limit per plan (measure, patient)


def cache_folder() -> Path:
    """Where the compiled FFI library is kept: ``$DIFFCAM_CACHE``, else
    ``$XDG_CACHE_HOME/diffcam``, else ``~/.cache/diffcam``."""
    if os.environ.get("DIFFCAM_CACHE"):
        return Path(os.environ["DIFFCAM_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "diffcam"


def _fftw_files(precision: int) -> tuple[str, str | None]:
    """FFTW's library and its threads library for one precision: pyFFTW's bundled
    copies first, else the system's. Raises DiffcamError when there is none."""
    stem = _STEM[precision]
    spec = importlib.util.find_spec("pyfftw")
    if spec is not None and spec.origin:
        package = Path(spec.origin).parent
        # pyFFTW's wheels before 0.15.1 name the folder pyFFTW.libs
        for folder in (package.parent / "pyfftw.libs", package.parent / "pyFFTW.libs",
                       package / ".dylibs"):
            main = sorted(glob.glob(str(folder / f"lib{stem}-*.so*"))
                          + glob.glob(str(folder / f"lib{stem}.*dylib")))
            threads = sorted(glob.glob(str(folder / f"lib{stem}_omp-*.so*"))
                             + glob.glob(str(folder / f"lib{stem}_threads-*.so*"))
                             + glob.glob(str(folder / f"lib{stem}_threads.*dylib")))
            if main:
                # the wheel's copies find each other only through the extension's
                # RPATH: load their OpenMP runtime first
                for runtime in glob.glob(str(folder / "libgomp-*.so*")):
                    ctypes.CDLL(runtime, mode=ctypes.RTLD_GLOBAL)
                return main[0], threads[0] if threads else None
    main = ctypes.util.find_library(stem)
    if main is None:
        raise DiffcamError(
            f"FFTW (lib{stem}) was not found: install it with pip install 'diffcam[fftw]' "
            "(pyFFTW's wheel ships FFTW) or from the system (e.g. libfftw3-dev), or use "
            "XLA's FFT (DIFFCAM_FFT=xla).")
    threads = (ctypes.util.find_library(f"{stem}_threads")
               or ctypes.util.find_library(f"{stem}_omp"))
    return main, threads


def _compile() -> Path:
    """The FFI library built from ``fftw_ffi.cc`` for this jaxlib: compiled once into
    `cache_folder` (written under a temporary name and moved into place)."""
    include = jax.ffi.include_dir()
    key = hashlib.sha256(_SOURCE.read_bytes() + jax.__version__.encode()
                         + include.encode()).hexdigest()[:16]
    folder = cache_folder()
    target = folder / f"fftw_ffi-{key}.so"
    if target.exists():
        return target
    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        raise DiffcamError("the FFTW backend compiles a small C++ file on first use and "
                           "found no C++ compiler (set CXX, or install g++ or clang++), "
                           "or use XLA's FFT (DIFFCAM_FFT=xla).")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, temp = tempfile.mkstemp(prefix=".fftw_ffi-", suffix=".so", dir=folder)
        os.close(fd)
    except OSError as e:
        raise DiffcamError(f"cannot write the FFTW backend's library to {folder} ({e}); "
                           "set DIFFCAM_CACHE to a writable folder.") from None
    command = [compiler, "-O2", "-std=c++17", "-shared", "-fPIC", "-w", "-I", include,
               str(_SOURCE), "-o", temp]
    try:
        done = subprocess.run(command, capture_output=True, text=True)
        failure = done.stderr[-2000:] if done.returncode != 0 else None
    except OSError as e:
        failure = str(e)
    if failure is not None:
        os.unlink(temp)
        raise DiffcamError("compiling the FFTW backend failed (" + " ".join(command)
                           + "):\n" + failure + "\nSet CXX to a C++ compiler, or use XLA's "
                           "FFT (DIFFCAM_FFT=xla).")
    os.chmod(temp, 0o755)
    os.replace(temp, target)
    return target


# How long a thread of FFTW's OpenMP team spins for more work before it sleeps, in
# libgomp's busy-wait iterations (its default is 300,000). Within a transform the team
# must not sleep: with no spin (GOMP_SPINCOUNT=0) Richardson–Lucy's iterations at 1024²
# took 15.7 ms against 11.5. After a transform it should: a spinning thread holds a core
# that XLA's next operations need, and psf_stack took 15.8 ms a PSF at 1024² against
# 12.4 with 30,000 (medians of 4–5 processes of python -m benchmarks.bench_fft).
OPENMP_SPIN = 30_000


@contextlib.contextmanager
def _openmp_spin():
    """``GOMP_SPINCOUNT`` = `OPENMP_SPIN` while FFTW's OpenMP runtime loads (it
    reads the variable once, then), unless the user set it or ``OMP_WAIT_POLICY``. The
    environment is restored after, so child processes do not inherit it. A runtime
    already loaded by another library keeps its settings."""
    if "GOMP_SPINCOUNT" in os.environ or "OMP_WAIT_POLICY" in os.environ:
        yield
        return
    os.environ["GOMP_SPINCOUNT"] = str(OPENMP_SPIN)
    try:
        yield
    finally:
        del os.environ["GOMP_SPINCOUNT"]


class _Backend:
    """The loaded FFI library and FFTW, bound and registered with XLA."""

    def __init__(self) -> None:
        self.shim = ctypes.CDLL(str(_compile()))
        self.shim.diffcam_fftw_export_wisdom.restype = ctypes.c_void_p
        self.shim.diffcam_fftw_configure.argtypes = [ctypes.c_int, ctypes.c_uint,
                                                     ctypes.c_double]
        self.threads_supported = True
        self.keep = []  # the FFTW libraries, loaded for the process's lifetime
        self.files = {}
        with _openmp_spin():
            for precision in (0, 1):
                self._bind(precision)
        for name in ("C2C", "R2C", "C2R"):
            jax.ffi.register_ffi_target(f"diffcam_fftw_{name.lower()}",
                                        jax.ffi.pycapsule(getattr(self.shim, f"DiffcamFftw{name}")),
                                        platform="cpu")

    def _bind(self, precision: int) -> None:
        """Load FFTW of one precision (0: single, 1: double) and hand the addresses of
        its functions to the FFI library."""
        main, threads = _fftw_files(precision)
        self.files[precision] = main
        lib = ctypes.CDLL(main, mode=ctypes.RTLD_GLOBAL)
        self.keep.append(lib)
        table = []
        for name in _FUNCTIONS:
            if name == "plan_with_nthreads":
                continue
            table.append(ctypes.cast(getattr(lib, _PREFIX[precision] + name),
                                     ctypes.c_void_p).value)
        with_threads = self.shim.diffcam_fftw_no_threads
        if threads is not None:
            tlib = ctypes.CDLL(threads, mode=ctypes.RTLD_GLOBAL)
            self.keep.append(tlib)
            if getattr(tlib, _PREFIX[precision] + "init_threads")():
                with_threads = getattr(tlib, _PREFIX[precision] + "plan_with_nthreads")
        if with_threads is self.shim.diffcam_fftw_no_threads:
            self.threads_supported = False
        table.insert(_FUNCTIONS.index("plan_with_nthreads"),
                     ctypes.cast(with_threads, ctypes.c_void_p).value)
        array = (ctypes.c_void_p * len(table))(*table)
        if self.shim.diffcam_fftw_bind(precision, array) != 0:
            raise DiffcamError("binding FFTW failed")


@functools.cache
def load() -> _Backend:
    """Compile (first time only), load and register the FFTW backend, with the wisdom
    kept from earlier runs; raises [`DiffcamError`][diffcam.core.errors.DiffcamError] saying
    what is missing and what to do."""
    backend = _Backend()
    _configure(backend, _threads(None), "measure")
    for precision in (0, 1):
        try:
            wisdom = _wisdom_file(backend, precision).read_bytes()
        except OSError:
            continue
        backend.shim.diffcam_fftw_import_wisdom(precision, ctypes.c_char_p(wisdom))
    atexit.register(save_wisdom)
    return backend


def configure(threads: int | None = None, planning: str = "measure") -> None:
    """Threads and planning effort of the FFTW plans made from now on (plans are kept
    per shape, so set this before the first transform of a shape).

    Args:
        threads: FFTW's threads; default ``$DIFFCAM_FFT_THREADS``, else the CPUs this
            process may run on.
        planning: ``"measure"`` (default: FFTW times candidate algorithms for each new
            shape, 0.5 s at 1024², 6 s at 4096² here, then keeps what it found in
            diffcam's cache folder for later runs), ``"patient"`` (longer, at most
            30 s per shape) or ``"estimate"`` (no timing: plans in microseconds, but
            measured here up to 10x slower to run).
    """
    threads = _threads(threads)             # the arguments first, then the library
    if planning not in PLANNING:
        raise DiffcamError(f"planning must be one of {sorted(PLANNING)}, not {planning!r}.")
    _configure(load(), threads, planning)


def environment_threads() -> int | None:
    """``$DIFFCAM_FFT_THREADS`` as a whole number ≥ 1, or None when it is unset."""
    return environment_count("DIFFCAM_FFT_THREADS", "to use every CPU")


def _threads(threads: int | None) -> int:
    """``threads`` checked (a positive int, not a bool), or ``$DIFFCAM_FFT_THREADS``
    (`environment_threads`), or the CPUs this process may use."""
    if threads is None:
        threads = environment_threads()
        return _cpus() if threads is None else threads
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise DiffcamError(f"threads must be a positive integer (FFTW's threads), not "
                           f"{threads!r:.40}; None uses every CPU.")
    return int(threads)


def _configure(backend: _Backend, threads: int, planning: str) -> None:
    if not backend.threads_supported:
        threads = 1
    backend.shim.diffcam_fftw_configure(int(threads), PLANNING[planning],
                                        ctypes.c_double(PLANNING_SECONDS))
    backend.threads = int(threads)


def _wisdom_file(backend: _Backend, precision: int) -> Path:
    """FFTW's wisdom for this library and machine, kept between runs."""
    tag = hashlib.sha256(f"{backend.files[precision]}|{platform.machine()}|"
                         f"{platform.node()}".encode()).hexdigest()[:12]
    return cache_folder() / f"fftw-wisdom-{_STEM[precision]}-{tag}.txt"


def save_wisdom() -> None:
    """Keep what FFTW's measurements found (run at exit; atomic, best effort)."""
    backend = load()
    for precision in (0, 1):
        pointer = backend.shim.diffcam_fftw_export_wisdom(precision)
        if not pointer:
            continue
        wisdom = ctypes.string_at(pointer)  # a few kB, left to the process's exit
        target = _wisdom_file(backend, precision)
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            if target.exists() and target.read_bytes() == wisdom:
                continue
            fd, temp = tempfile.mkstemp(prefix=".fftw-wisdom-", dir=target.parent)
            with os.fdopen(fd, "wb") as f:
                f.write(wisdom)
            os.replace(temp, target)
        except OSError:
            pass  # a read-only cache: the next run measures again


def threads() -> int:
    """FFTW's threads for plans made from now on."""
    return load().threads


def _cpus() -> int:
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


# ------------------------------------------------------------------- the primitives

def _half(nx: int) -> int:
    return nx // 2 + 1


def _complex(dtype) -> np.dtype:
    return np.dtype(np.complex128 if np.dtype(dtype) in (np.float64, np.complex128)
                    else np.complex64)


def _real(dtype) -> np.dtype:
    return np.dtype(np.float64 if np.dtype(dtype) in (np.float64, np.complex128)
                    else np.float32)


def _weights(nx: int, dtype) -> jax.Array:
    """How many spectrum columns each half-spectrum column stands for (1 or 2)."""
    w = np.full(_half(nx), 2.0)
    w[0] = 1.0
    if nx % 2 == 0:
        w[-1] = 1.0
    return jnp.asarray(w, _real(dtype))


def _primitive(name: str, shape_dtype, call, transpose) -> Primitive:
    p = Primitive(name)
    p.def_abstract_eval(lambda x, **k: jax.core.ShapedArray(*shape_dtype(x.shape, x.dtype, **k)))
    p.def_impl(lambda x, **k: jax.jit(functools.partial(p.bind, **k))(x))
    mlir.register_lowering(p, mlir.lower_fun(call, multiple_results=False), platform="cpu")
    ad.deflinear2(p, transpose)

    def batch(args, dims, **k):
        x = jnp.moveaxis(args[0], dims[0], 0)
        return p.bind(x, **k), 0
    batching.primitive_batchers[p] = batch
    return p


def _c2c_call(x, *, sign):
    # in place: XLA reuses the input's buffer when nothing else needs it (else it
    # copies), instead of a fresh output buffer (a pair at 4096²: 196 ms vs 221)
    return jax.ffi.ffi_call("diffcam_fftw_c2c", jax.ShapeDtypeStruct(x.shape, x.dtype),
                            input_output_aliases={0: 0})(x, sign=np.int64(sign))


def _r2c_call(x):
    shape = x.shape[:-1] + (_half(x.shape[-1]),)
    return jax.ffi.ffi_call("diffcam_fftw_r2c", jax.ShapeDtypeStruct(shape, _complex(x.dtype)))(x)


def _c2r_call(x, *, nx):
    shape = x.shape[:-1] + (nx,)
    return jax.ffi.ffi_call("diffcam_fftw_c2r", jax.ShapeDtypeStruct(shape, _real(x.dtype)))(x)


_c2c_p = _primitive("diffcam_fftw_c2c", lambda s, d, sign: (s, d), _c2c_call,
                    lambda ct, x, *, sign: [_c2c_p.bind(ct, sign=sign)])
_r2c_p = _primitive(
    "diffcam_fftw_r2c", lambda s, d: (s[:-1] + (_half(s[-1]),), _complex(d)), _r2c_call,
    lambda ct, x: [_c2r_p.bind(jnp.conj(ct) / _weights(x.aval.shape[-1], ct.dtype),
                                 nx=x.aval.shape[-1])])
_c2r_p = _primitive(
    "diffcam_fftw_c2r", lambda s, d, nx: (s[:-1] + (nx,), _real(d)), _c2r_call,
    lambda ct, x, *, nx: [_weights(nx, ct.dtype) * jnp.conj(_r2c_p.bind(ct))])


def c2c(x: jax.Array, sign: int) -> jax.Array:
    """Unnormalised 2-D DFT over the last two axes with the exponent's sign ``sign``
    (−1 forward, +1 backward); complex64 or complex128."""
    load()
    return _c2c_p.bind(x, sign=int(sign))


def r2c(x: jax.Array) -> jax.Array:
    """Forward 2-D DFT of a real array, half spectrum along the last axis."""
    load()
    return _r2c_p.bind(x)


def c2r(x: jax.Array, nx: int) -> jax.Array:
    """Unnormalised backward 2-D DFT of a half spectrum onto the real width ``nx``."""
    load()
    if x.shape[-1] != _half(nx):
        raise DiffcamError(f"a half spectrum of width {x.shape[-1]} does not belong to "
                           f"a real width of {nx} (expected {_half(nx)}).")
    return _c2r_p.bind(x, nx=int(nx))

