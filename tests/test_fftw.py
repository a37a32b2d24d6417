"""The FFTW backend (``diffcam.core.fftw``) behind the FFT seam: numpy's transforms to
float tolerance in float32 and float64, batched, inside ``jit``, loops and ``vmap``;
derivatives in both modes checked against finite differences and against ``jnp.fft``'s
own rules; the seam's ``norm`` and ``s`` as numpy's; the backend switch and its errors.

The test extra installs pyFFTW (which ships FFTW), so FFTW must load here: a machine
where it does not fails these tests instead of skipping them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import diffcam.core.backend as backend
from diffcam.core import fftw
from diffcam.core.errors import DiffcamError

SHAPES = [(6, 10), (5, 7), (3, 4, 9), (2, 3, 8, 5), (1, 1)]


@pytest.fixture(autouse=True)
def fftw_backend():
    """Every test here with FFTW behind the seam, and the environment's choice after."""
    assert backend.set_fft("fftw") == "fftw"
    yield
    backend._setting["backend"] = None
    jax.clear_caches()


def _complex(rng, shape, dtype=np.complex64):
    return (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(dtype)


def _tol(dtype):
    return dict(rtol=2e-5, atol=2e-4) if np.dtype(dtype).itemsize <= 8 else dict(rtol=1e-12,
                                                                                  atol=1e-11)


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("precision", ["single", "double"])
def test_transforms_are_numpys(shape, precision, x64):
    rng = np.random.default_rng(1)
    cdtype = np.complex64 if precision == "single" else np.complex128
    u = _complex(rng, shape, cdtype)
    r = u.real.copy()
    tol = _tol(cdtype)
    for ours, ref in [(backend.fft2(u), np.fft.fft2(u)), (backend.ifft2(u), np.fft.ifft2(u)),
                      (backend.rfft2(r), np.fft.rfft2(r)),
                      (backend.irfft2(np.fft.rfft2(r), s=shape[-2:]), r)]:
        assert ours.dtype in (cdtype, r.dtype)
        np.testing.assert_allclose(np.asarray(ours), ref, **tol)
    # a half spectrum that is not Hermitian where it should be: numpy drops the same parts
    h = _complex(rng, shape[:-1] + (shape[-1] // 2 + 1,), cdtype)
    np.testing.assert_allclose(np.asarray(backend.irfft2(h, s=shape[-2:])),
                               np.fft.irfft2(h, s=shape[-2:]), **tol)


@pytest.mark.parametrize("norm", [None, "backward", "ortho", "forward"])
def test_norm_and_sizes_as_numpy(norm):
    rng = np.random.default_rng(2)
    u = _complex(rng, (3, 8, 6))
    np.testing.assert_allclose(np.asarray(backend.fft2(u, norm=norm)),
                               np.fft.fft2(u, norm=norm), **_tol(u.dtype))
    np.testing.assert_allclose(np.asarray(backend.ifft2(u, norm=norm)),
                               np.fft.ifft2(u, norm=norm), **_tol(u.dtype))
    r = u.real.copy()
    for s in [(8, 6), (10, 4), (5, 9)]:  # the input cropped or zero-padded to s
        np.testing.assert_allclose(np.asarray(backend.rfft2(r, s=s)),
                                   np.fft.rfft2(r, s=s), **_tol(u.dtype))
        h = np.fft.rfft2(r)
        np.testing.assert_allclose(np.asarray(backend.irfft2(h, s=s)),
                                   np.fft.irfft2(h, s=s), **_tol(u.dtype))
    # a real input to fft2 is promoted as numpy does
    np.testing.assert_allclose(np.asarray(backend.fft2(r)), np.fft.fft2(r), **_tol(u.dtype))
    with pytest.raises(DiffcamError, match="norm"):
        backend.fft2(u, norm="half")


def test_jit_loops_and_vmap():
    """Inside a jitted fori_loop and scan, and vmapped over a middle axis."""
    rng = np.random.default_rng(3)
    u = _complex(rng, (4, 12, 10))
    h = np.exp(1j * rng.uniform(0, 2 * np.pi, (12, 10))).astype(np.complex64)

    @jax.jit
    def steps(u):
        return jax.lax.fori_loop(0, 5, lambda i, v: backend.ifft2(backend.fft2(v) * h), u)

    expected = u
    for _ in range(5):
        expected = np.fft.ifft2(np.fft.fft2(expected) * h)
    np.testing.assert_allclose(np.asarray(steps(u)), expected, **_tol(u.dtype))

    r = u.real
    total, _ = jax.lax.scan(lambda c, x: (c + backend.irfft2(backend.rfft2(x), s=x.shape),
                                          None), jnp.zeros(r.shape[1:]), r)
    np.testing.assert_allclose(np.asarray(total), r.sum(0), atol=1e-5)

    x = _complex(rng, (5, 3, 8, 6))  # mapped over axis 1: each slice is (5, 8, 6)
    np.testing.assert_allclose(np.asarray(jax.vmap(backend.fft2, in_axes=1, out_axes=1)(x)),
                               np.fft.fft2(x), **_tol(x.dtype))
    # nested vmap of the real transforms
    rr = rng.normal(size=(2, 3, 6, 8)).astype(np.float32)
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.vmap(backend.rfft2))(rr)),
                               np.fft.rfft2(rr), **_tol(np.complex64))


@pytest.mark.parametrize("which", ["fft2", pytest.param("ifft2", marks=pytest.mark.slow),
                                   "rfft2", "irfft2_even",
                                   pytest.param("irfft2_odd", marks=pytest.mark.slow)])
def test_derivatives_both_modes(which, x64):
    """Finite differences (check_grads, both modes, second order) and jnp.fft's own
    JVP and VJP, in float64."""
    rng = np.random.default_rng(4)
    shape = (2, 6, 8) if which != "irfft2_odd" else (2, 6, 7)
    f, ref, x = {
        "fft2": (backend.fft2, jnp.fft.fft2, _complex(rng, shape, np.complex128)),
        "ifft2": (backend.ifft2, jnp.fft.ifft2, _complex(rng, shape, np.complex128)),
        "rfft2": (backend.rfft2, jnp.fft.rfft2, rng.normal(size=shape)),
        "irfft2_even": (lambda a: backend.irfft2(a, s=shape[-2:]),
                        lambda a: jnp.fft.irfft2(a, s=shape[-2:]),
                        _complex(rng, shape[:-1] + (shape[-1] // 2 + 1,), np.complex128)),
        "irfft2_odd": (lambda a: backend.irfft2(a, s=shape[-2:]),
                       lambda a: jnp.fft.irfft2(a, s=shape[-2:]),
                       _complex(rng, shape[:-1] + (shape[-1] // 2 + 1,), np.complex128)),
    }[which]
    x = jnp.asarray(x)
    check_grads(jax.jit(f), (x,), order=2, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)
    t = jnp.asarray(rng.normal(size=x.shape) + (1j * rng.normal(size=x.shape)
                                                 if jnp.iscomplexobj(x) else 0), x.dtype)
    np.testing.assert_allclose(jax.jvp(f, (x,), (t,))[1], jax.jvp(ref, (x,), (t,))[1],
                               rtol=1e-10, atol=1e-10)
    y, vjp = jax.vjp(f, x)
    ct = jnp.asarray(rng.normal(size=y.shape) + (1j * rng.normal(size=y.shape)
                                                  if jnp.iscomplexobj(y) else 0), y.dtype)
    np.testing.assert_allclose(vjp(ct)[0], jax.vjp(ref, x)[1](ct)[0], rtol=1e-10, atol=1e-10)


def test_gradient_of_a_propagation_loss():
    """jax.grad through a Fresnel step, float32: FFTW's gradient equals XLA's."""
    rng = np.random.default_rng(5)
    phase = jnp.asarray(rng.uniform(-np.pi, np.pi, (32, 32)), jnp.float32)
    h = jnp.asarray(np.exp(1j * rng.uniform(0, 2 * np.pi, (32, 32))), jnp.complex64)
    target = jnp.asarray(rng.uniform(0, 1, (32, 32)), jnp.float32)

    def loss(p):
        field = backend.transfer_step(jnp.exp(1j * p), h)
        return jnp.sum((jnp.abs(field) ** 2 - target) ** 2)

    g_fftw = jax.grad(loss)(phase)
    backend.set_fft("xla")
    g_xla = jax.grad(loss)(phase)
    np.testing.assert_allclose(np.asarray(g_fftw), np.asarray(g_xla), rtol=1e-4, atol=1e-4)


def test_threads_and_planning_do_not_change_results():
    rng = np.random.default_rng(6)
    u = _complex(rng, (2, 48, 40))
    out = {}
    for threads, planning in [(1, "estimate"), (2, "measure"), (None, "estimate")]:
        fftw.configure(threads=threads, planning=planning)
        out[threads, planning] = np.asarray(jax.jit(backend.fft2)(u))
        jax.clear_caches()
    values = list(out.values())
    for v in values[1:]:
        np.testing.assert_allclose(v, values[0], rtol=1e-5, atol=1e-4)
    with pytest.raises(DiffcamError, match="threads"):
        fftw.configure(threads=0)
    with pytest.raises(DiffcamError, match="planning"):
        fftw.configure(planning="exhaustive-ish")


def test_backend_switch_and_its_errors(monkeypatch):
    assert backend.fft_backend() == "fftw" and backend.fft_status().startswith("FFT: FFTW")
    assert backend.set_fft("xla") == "xla" and backend.fft_status() == "FFT: XLA"
    with pytest.raises(DiffcamError, match="auto, fftw, xla"):
        backend.set_fft("ducc")
    backend._setting["backend"] = None
    monkeypatch.setenv("DIFFCAM_FFT", "fastest")
    with pytest.raises(DiffcamError, match="DIFFCAM_FFT"):
        backend.fft_backend()
    monkeypatch.delenv("DIFFCAM_FFT")
    assert backend.fft_backend() == "xla"  # the default
    # FFTW failing to load: "fftw" raises and keeps the former choice, "auto" falls
    # back to XLA and says why
    def broken(**_):
        raise DiffcamError("FFTW (libfftw3f) was not found: install it")
    monkeypatch.setattr(fftw, "configure", broken)
    with pytest.raises(DiffcamError, match="not found"):
        backend.set_fft("fftw")
    assert backend.fft_backend() == "xla"
    assert backend.set_fft("auto") == "xla"
    assert backend.fft_status() == "FFT: XLA (FFTW unavailable: FFTW (libfftw3f) was not found: install it)"
    # no FFTW anywhere: a clear error naming the fix (checked on the finder itself; the
    # loaded libraries of this process stay)
    monkeypatch.setattr(fftw.importlib.util, "find_spec", lambda name: None)
    monkeypatch.setattr(fftw.ctypes.util, "find_library", lambda name: None)
    with pytest.raises(DiffcamError, match=r"diffcam\[fftw\]"):
        fftw._fftw_files(0)


def test_compile_errors_are_clear(tmp_path, monkeypatch):
    """A missing compiler or an unwritable cache folder: a DiffcamError that says what
    to do (the compiled library is looked up first, so a fresh cache folder is used)."""
    monkeypatch.setenv("DIFFCAM_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    with pytest.raises(DiffcamError, match="no-such-compiler"):
        fftw._compile()
    monkeypatch.delenv("CXX")
    monkeypatch.setattr(fftw.shutil, "which", lambda name: None)
    with pytest.raises(DiffcamError, match="C\\+\\+ compiler"):
        fftw._compile()
    assert not list((tmp_path / "cache").glob("*.so")), "a half-built library was left"


def test_wisdom_is_kept_between_runs(tmp_path, monkeypatch):
    """What FFTW measured is written to the cache folder (atomically) and reads back."""
    import ctypes

    jax.block_until_ready(jax.jit(backend.fft2)(jnp.ones((2, 36, 20), jnp.complex64)))
    monkeypatch.setenv("DIFFCAM_CACHE", str(tmp_path))
    fftw.save_wisdom()
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == 2 and all(f.startswith("fftw-wisdom-") for f in files), files
    single = next(p for p in tmp_path.iterdir() if "fftw3f-" in p.name).read_bytes()
    assert b"fftw" in single.lower()
    assert fftw.load().shim.diffcam_fftw_import_wisdom(0, ctypes.c_char_p(single)) == 1
    assert fftw.load().shim.diffcam_fftw_import_wisdom(0, ctypes.c_char_p(b"garbage")) == 0


@pytest.mark.parametrize("user", [None, "1234"])
def test_openmp_team_spins_briefly_and_the_environment_is_left_alone(user):
    """FFTW's OpenMP runtime, in its own report (``OMP_DISPLAY_ENV``), spins
    ``OPENMP_SPIN`` iterations before a thread sleeps, unless the user set
    ``GOMP_SPINCOUNT``; the process's environment is as it was (child processes do not
    inherit the setting). A fresh process: the runtime reads it once, as it loads."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("GOMP_SPINCOUNT",
                                                          "OMP_WAIT_POLICY")}
    env.update(OMP_DISPLAY_ENV="verbose", DIFFCAM_FFT="fftw")
    if user is not None:
        env["GOMP_SPINCOUNT"] = user
    code = ("import os; from diffcam.core import fftw; fftw.load(); "
            "print(os.environ.get('GOMP_SPINCOUNT'))")
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    expected = user or str(fftw.OPENMP_SPIN)
    assert f"GOMP_SPINCOUNT = '{expected}'" in r.stderr, r.stderr
    assert r.stdout.split()[-1] == str(user), r.stdout
