"""Progress: the jitted loops tick the open bar once per iteration (batched or not),
nothing breaks under jit or grad, the opt-outs hold, and a log (stderr not a terminal,
as under pytest) gets a few plain lines instead of a bar's carriage returns."""

import io
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffcam.calibrate import CalibrationGeometry, gerchberg_saxton
from diffcam.core import progress
from diffcam.reconstruct import admm_tv, focus_sweep, richardson_lucy


@pytest.fixture
def problem():
    rng = np.random.default_rng(0)
    psf = rng.random((5, 5)) ** 4
    return rng.random((24, 24)) + 0.1, psf


def _ticks(run, total):
    """Iterations counted by an outer bar while ``run()`` executes."""
    with progress.progress_bar(total, "test"):
        bar = progress._BARS[-1]
        run()
        return bar.n


@pytest.mark.slow
def test_solvers_tick_once_per_iteration(problem):
    image, psf = problem
    assert _ticks(lambda: richardson_lucy(image, psf, 37, progress=False), 37) == 37
    assert _ticks(lambda: admm_tv(image, psf, 23, progress=False), 23) == 23
    # a batch of 3 problems still counts iterations, not problems
    stack = np.stack([psf, psf.T, psf[::-1]])
    assert _ticks(lambda: focus_sweep(image, stack, 11, progress=False), 11) == 11


def test_projections_tick(problem):
    image, _ = problem
    geometry = CalibrationGeometry(dx=5e-6, wavelength=532e-9, focal_length=5e-2)
    near = 1 + 0.5 * image[:16, :16]
    far = np.abs(np.fft.fft2(np.exp(1j * image[:16, :16]))) ** 2
    n = _ticks(lambda: gerchberg_saxton(near, far, geometry, iterations=9, restarts=2,
                                        key=jax.random.key(0), progress=False), 9)
    assert n == 9


def test_inner_bar_shown_and_closed(problem, capsys, monkeypatch):
    """With no delay the solver's own progress reaches stderr and its bar is closed after
    the run; progress=False and DIFFCAM_PROGRESS=0 print nothing."""
    image, psf = problem
    monkeypatch.setattr(progress, "LINE_EVERY", 0.0)
    richardson_lucy(image, psf, 5)
    assert "Richardson–Lucy" in capsys.readouterr().err and not progress._BARS
    richardson_lucy(image, psf, 5, progress=False)
    assert capsys.readouterr().err == ""
    monkeypatch.setenv("DIFFCAM_PROGRESS", "0")
    richardson_lucy(image, psf, 5)
    assert capsys.readouterr().err == ""


@pytest.mark.usefixtures("debug_nans")
def test_ticks_under_jit_and_grad(problem):
    """The tick is transparent to jit and reverse mode: same values as without a bar."""
    image, psf = problem
    f = lambda h: jnp.sum(richardson_lucy(image, h, 4, progress=False).image ** 2)  # noqa: E731
    g1 = jax.jit(jax.grad(f))(jnp.asarray(psf))
    with progress.progress_bar(4, "outer"):
        g2 = jax.grad(f)(jnp.asarray(psf))
    assert np.all(np.isfinite(g1)) and np.allclose(g1, g2, rtol=1e-5)


def test_log_gets_occasional_plain_lines(capsys, monkeypatch):
    """Off a terminal: whole lines no closer than LINE_EVERY, and a last line with the
    final count; no carriage returns."""
    clock = iter(np.arange(0.0, 1000.0, 0.5))       # each reading half a second later
    monkeypatch.setattr(progress.time, "perf_counter", lambda: float(next(clock)))
    with progress.new_bar(400, "stack fit", unit="step") as bar:
        for _ in range(400):
            bar.update(1)
            bar.set_postfix(val="0.9700")
    lines = capsys.readouterr().err.splitlines()
    # 200 s of updates: one line per 30 s, then the last
    assert len(lines) == 200 // 30 + 1
    assert lines[0].startswith("stack fit: 60/400 step, 30 s")
    assert lines[-1].startswith("stack fit: 400/400 step") and lines[-1].endswith("val=0.9700")


def test_quick_runs_and_opt_outs_print_nothing(capsys, monkeypatch):
    with progress.new_bar(10, "quick") as bar:      # well under LINE_EVERY
        bar.update(10)
    with progress.new_bar(10, "off", progress=False) as bar:
        monkeypatch.setattr(progress, "LINE_EVERY", -100.0)
        bar.update(10)
    assert capsys.readouterr().err == ""


def test_a_terminal_gets_a_tqdm_bar(monkeypatch):
    """On a terminal (stderr a tty) the bar is tqdm's, drawn on stderr once DELAY seconds
    have passed (tqdm's ``delay``; 0 here)."""
    from tqdm import tqdm

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", Terminal())
    monkeypatch.setattr(progress, "DELAY", 0.0)
    with progress.new_bar(3, "PSF stack", unit="depth") as bar:
        bar.update(3)
    assert isinstance(bar, tqdm) and "PSF stack" in sys.stderr.getvalue()
