"""Shared test fixtures: float64 mode, NaN checking, finite-difference gradient checks;
crafted file headers for the hardening tests."""

import os
import struct
import zlib

import jax
import numpy as np
import pytest

# the command line's compilation cache (diffcam.apps.compile_cache) is off in every test
# and the commands they start: nothing is written to the user's cache folder
# (tests/test_startup.py turns it on, in temporary folders)
os.environ["DIFFCAM_NO_CACHE"] = "1"


def pytest_configure(config):
    """The default run (``-m 'not slow'``: small programs, compiled and run once, most
    of their time XLA compiling) compiles with LLVM's lighter optimisation level (1 of
    3), for the commands the tests start too: the same programs (XLA's own passes and
    buffers; fused multiply-adds as at level 3, which level 0 leaves out and
    tests/test_phasor.py notices) in 15 % less CPU time. The slow tests, whose
    programs run long, keep the default. Set before JAX starts its backend (at the
    first computation, during collection)."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "not slow" in (config.option.markexpr or "") \
            and "xla_backend_optimization_level" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_backend_optimization_level=1".strip()


@pytest.fixture
def x64():
    """Run a test with JAX float64 enabled (closed-form comparisons, gradient checks)."""
    with jax.enable_x64(True):
        yield


@pytest.fixture
def debug_nans():
    """Run a test with ``jax_debug_nans`` on (any NaN a JAX op produces raises
    FloatingPointError), restored after: the gradient tests use it through
    ``@pytest.mark.usefixtures("debug_nans")``, so a NaN in a derivative fails loudly."""
    before = jax.config.jax_debug_nans
    jax.config.update("jax_debug_nans", True)
    try:
        yield
    finally:
        jax.config.update("jax_debug_nans", before)


def fd_gradient(f, x, rel_step=1e-6):
    """Central finite difference of scalar f at scalar x with a step relative to |x|."""
    h = rel_step * max(abs(float(x)), 1e-30)
    return (float(f(x + h)) - float(f(x - h))) / (2 * h)


def assert_grad_matches_fd(f, x, rel_step=1e-6, rtol=1e-5):
    """jax.grad of scalar f at scalar x agrees with a relative-step central difference."""
    g = float(jax.grad(f)(x))
    fd = fd_gradient(f, x, rel_step)
    np.testing.assert_allclose(g, fd, rtol=rtol, atol=1e-12 * max(abs(fd), 1.0))


def assert_float32_gradient_matches_float64(gradient, rtol=1e-3):
    """``gradient(dtype)`` (an array, computed in that precision) in float32 equals its
    float64 value to ``rtol`` of the largest entry: nothing in between left float32's
    range (the PSF's normalisation once did, and was 60 % off)."""
    single = np.asarray(gradient(np.float32), np.float64)
    with jax.enable_x64(True):
        double = np.asarray(gradient(np.float64), np.float64)
    assert np.abs(single - double).max() < rtol * np.abs(double).max()


def listing(folder):
    """The names in ``folder``, sorted (to see that no temporary file was left)."""
    return sorted(p.name for p in folder.iterdir())


def tiff_declaring(width, height):
    """A float32 TIFF whose header declares width × height and which holds 16 bytes."""
    entries = [(256, 4, width), (257, 4, height), (258, 3, 32), (259, 3, 1), (262, 3, 1),
               (273, 4, 8), (277, 3, 1), (278, 4, height), (279, 4, 16), (339, 3, 3)]
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHII", tag, kind, 1, value) if kind == 4
        else struct.pack("<HHIHH", tag, kind, 1, value, 0) for tag, kind, value in entries)
    return b"II*\x00" + struct.pack("<I", 24) + b"\x00" * 16 + ifd + b"\x00" * 4


def png_declaring(width, height):
    """A grayscale PNG whose IHDR declares width × height and which holds 64 bytes."""
    chunk = lambda t, d: (struct.pack(">I", len(d)) + t + d  # noqa: E731
                          + struct.pack(">I", zlib.crc32(t + d)))
    return (b"\x89PNG\r\n\x1a\n"
            + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00" * 64)) + chunk(b"IEND", b""))
