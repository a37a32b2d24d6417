"""Start-up of the package and the command line: lazy namespaces
(diffcam.core.lazy), which third-party modules an import loads, and the command
line's persistent compilation cache (diffcam.apps.compile_cache)."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

import diffcam
import diffcam.calibrate
import diffcam.evaluate
import diffcam.model
import diffcam.optics
from diffcam.core.lazy import attach_stub, stub_names

HEAVY = ("scipy", "optax", "optimistix", "lineax", "matplotlib", "skimage")


def _loaded_after(statement: str) -> list[str]:
    """The top-level modules among :data:`HEAVY` and ``jax`` that ``statement`` loads
    in a fresh interpreter."""
    code = (f"import sys, json; {statement}; "
            f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}})))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300, check=True)
    loaded = set(json.loads(r.stdout.splitlines()[-1]))
    return sorted(loaded & {*HEAVY, "jax"})


def test_import_diffcam_loads_neither_scipy_nor_jax():
    assert _loaded_after("import diffcam") == []


def test_the_command_line_and_predict_path_load_no_scipy_or_optimisers():
    """Starting the CLI, reading a stack fit and predicting need JAX, not SciPy, optax,
    optimistix or matplotlib; fitting loads them (the check can fail)."""
    light = _loaded_after("import diffcam.apps.cli, diffcam.calibrate.model_file")
    assert light == ["jax"]
    assert {"scipy", "optax", "optimistix"} <= set(
        _loaded_after("import diffcam.apps.cli; diffcam.calibrate.fit_stack"))


def test_help_loads_no_jax():
    """The parser of ``diffcam`` and the help of every subcommand (what ``--help``
    runs) import no JAX: the commands import their numerical modules when they run,
    and the limits the helps name are read from source."""
    helps = ("from diffcam.apps.cli import build_parser; p = build_parser(); "
             "[p.format_help()] + [c.format_help() for c in p._actions[-1].choices.values()]")
    assert _loaded_after(helps) == []


def test_module_constant_reads_the_source_until_the_module_is_imported(monkeypatch):
    """``module_constant`` evaluates ``2 ** 28`` from diffcam.core.grid's source without
    importing it, and reads the attribute (an assigned value too) once it is imported."""
    from diffcam.core import grid
    from diffcam.core.lazy import module_constant

    code = ("import sys; from diffcam.core.lazy import module_constant as m; "
            "print(m('diffcam.core.grid.MAX_GRID_SAMPLES'), "
            "m('diffcam.reconstruct.checks.MAX_ITERATIONS'), "
            "sorted(n for n in sys.modules if n.startswith(('jax', 'diffcam.core.grid'))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300, check=True)
    assert r.stdout.split() == [str(2**28), "100000", "[]"]
    monkeypatch.setattr(grid, "MAX_GRID_SAMPLES", 400)
    assert module_constant("diffcam.core.grid.MAX_GRID_SAMPLES") == 400
    with pytest.raises(AttributeError, match="NOT_THERE"):
        module_constant("diffcam.core.grid.NOT_THERE")


@pytest.mark.parametrize("package", [diffcam, diffcam.calibrate, diffcam.model, diffcam.optics,
                                     diffcam.evaluate])
def test_every_public_name_resolves_to_its_modules_object(package):
    """Each name of the stub is the object its module defines, is listed by dir(), and
    stays in the package after first use; unknown names are AttributeErrors."""
    origin, exported = stub_names(package.__file__[:-3] + ".pyi")
    assert sorted(exported) == sorted(package.__all__) and set(exported) <= set(origin)
    for name in exported:
        module, attr = origin[name]
        value = getattr(package, name)
        source = importlib.import_module(module)
        expected = importlib.import_module(f"{module}.{attr}") \
            if module == package.__name__ else getattr(source, attr)
        assert value is expected, name
        assert name in vars(package) and name in dir(package)
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        getattr(package, "not_a_name")


def test_a_lazy_package_imports_an_unlisted_submodule_on_access():
    assert diffcam.calibrate.phase.pipeline is importlib.import_module("diffcam.calibrate.phase.pipeline")
    # the limits the error messages name are reachable from a bare ``import diffcam``
    code = ("import diffcam; print(diffcam.core.grid.MAX_GRID_SAMPLES, "
            "diffcam.calibrate.stack.result.MAX_PLANES, diffcam.io.MAX_READ_BYTES)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["268435456", "4096", str(4 * 2**30)]


def test_stub_names_reads_imports_aliases_and_all(tmp_path):
    stub = tmp_path / "__init__.pyi"
    stub.write_text("from a.b import c, d as e\nfrom a import f\n__all__ = ['c', 'e']\n")
    assert stub_names(stub) == ({"c": ("a.b", "c"), "e": ("a.b", "d"), "f": ("a", "f")},
                                ["c", "e"])
    stub.write_text("from a.b import c\n")
    assert stub_names(stub)[1] == ["c"]
    (tmp_path / "__init__.py").write_text("")
    getattr_, dir_, exported = attach_stub("planted", str(tmp_path / "__init__.py"))
    assert exported == ["c"]
    with pytest.raises(AttributeError):
        getattr_("__path__")


# --- the command line's compilation cache ------------------------------------------------

@pytest.fixture(scope="module")
def phase_file(tmp_path_factory):
    from diffcam.calibrate import PhaseFile, save_phase

    path = tmp_path_factory.mktemp("phase") / "phase.npz"
    rng = np.random.default_rng(0)
    save_phase(path, PhaseFile(rng.uniform(-np.pi, np.pi, (64, 64)), 5e-6, 532e-9,
                               0.1e-3))
    return path


def _psf(phase, out, **env):
    """``diffcam psf PHASE --z1 20mm --z2 1mm -o OUT`` in a subprocess, the cache
    settings of the test session (``DIFFCAM_NO_CACHE``) replaced by ``env``."""
    base = {k: v for k, v in os.environ.items()
            if k not in ("DIFFCAM_NO_CACHE", "DIFFCAM_CACHE", "XDG_CACHE_HOME",
                         "JAX_COMPILATION_CACHE_DIR")}
    # every program is written, however fast it compiled: the test does not rely on timing
    base["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    return subprocess.run([sys.executable, "-m", "diffcam", "psf", str(phase), "--z1",
                           "20mm", "--z2", "1mm", "-o", str(out)], capture_output=True,
                          text=True, timeout=600, env={**base, **env})


def test_a_second_run_reads_the_cache_and_writes_the_same_file(phase_file, tmp_path):
    home = tmp_path / "xdg"
    first = _psf(phase_file, tmp_path / "a.tif", XDG_CACHE_HOME=str(home))
    assert first.returncode == 0, first.stderr
    entries = sorted((home / "diffcam" / "jax").iterdir())
    assert entries, "the first run left no compiled program"
    second = _psf(phase_file, tmp_path / "b.tif", XDG_CACHE_HOME=str(home))
    assert second.returncode == 0, second.stderr
    assert (tmp_path / "a.tif").read_bytes() == (tmp_path / "b.tif").read_bytes()
    assert sorted((home / "diffcam" / "jax").iterdir()) == entries  # read, not rewritten


@pytest.mark.slow
def test_the_users_cache_settings_come_first(phase_file, tmp_path):
    """JAX_COMPILATION_CACHE_DIR is used instead of the XDG folder; DIFFCAM_NO_CACHE=1
    writes nothing; a folder that cannot be made is one line on stderr, and the command
    still succeeds."""
    own, home = tmp_path / "own", tmp_path / "xdg"
    r = _psf(phase_file, tmp_path / "a.tif", JAX_COMPILATION_CACHE_DIR=str(own),
             XDG_CACHE_HOME=str(home))
    assert r.returncode == 0, r.stderr
    assert any(own.iterdir()) and not home.exists()
    r = _psf(phase_file, tmp_path / "b.tif", DIFFCAM_NO_CACHE="1", XDG_CACHE_HOME=str(home))
    assert r.returncode == 0, r.stderr
    assert not home.exists()
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    r = _psf(phase_file, tmp_path / "c.tif", XDG_CACHE_HOME=str(blocker))
    assert r.returncode == 0, r.stderr
    warning = [line for line in r.stderr.splitlines() if "compilation cache" in line]
    assert len(warning) == 1 and "DIFFCAM_NO_CACHE=1" in warning[0]
    assert (tmp_path / "c.tif").read_bytes() == (tmp_path / "a.tif").read_bytes()


@pytest.mark.slow  # 5 s of subprocesses; the cache's reuse by default: the test above
def test_a_cache_over_its_cap_loses_its_least_recently_used_programs(phase_file, tmp_path):
    """A 1 MB cap (DIFFCAM_CACHE_MAX_MB=1) on a folder holding 1.2 MB: the run's new
    programs evict the least recently used one first, a program written without a cap
    (no -atime file: dated by its modification time) included, and the folder ends
    under the cap; a cap that is not a whole number is one line and exit status 2."""
    home = tmp_path / "xdg"
    folder = home / "diffcam" / "jax"
    folder.mkdir(parents=True)
    now = time.time_ns()
    for age, name in ((300, "undated"), (200, "older"), (100, "newer")):
        program = folder / f"{name}-cache"
        program.write_bytes(bytes(400_000))
        stamp = now - age * 10**9
        if name == "undated":
            os.utime(program, ns=(stamp, stamp))
        else:
            (folder / f"{name}-atime").write_bytes(stamp.to_bytes(8, "little"))
    r = _psf(phase_file, tmp_path / "a.tif", XDG_CACHE_HOME=str(home),
             DIFFCAM_CACHE_MAX_MB="1")
    assert r.returncode == 0 and "warning" not in r.stderr, r.stderr
    programs = {p.name: p.stat().st_size for p in folder.glob("*-cache")}
    assert "undated-cache" not in programs and {"older-cache", "newer-cache"} < set(programs)
    assert len(programs) > 2 and sum(programs.values()) <= 10**6
    bad = _psf(phase_file, tmp_path / "b.tif", XDG_CACHE_HOME=str(home),
               DIFFCAM_CACHE_MAX_MB="1.5")
    assert bad.returncode == 2 and not (tmp_path / "b.tif").exists()
    assert bad.stderr.count("\n") == 1 and "DIFFCAM_CACHE_MAX_MB" in bad.stderr, bad.stderr
