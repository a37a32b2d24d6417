"""The lowest supported versions: ``.ci/lowest.txt`` (what ``.ci/lowest`` installs and
tests) pins exactly the lower bounds of ``pyproject.toml``, so the two cannot drift."""

from __future__ import annotations

import tomllib
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]


def _pins() -> dict[str, Version]:
    """``.ci/lowest.txt``: one ``name==version`` a line, ``#`` comments."""
    pins = {}
    for line in (ROOT / ".ci" / "lowest.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, sep, pinned = line.partition("==")
            assert sep and pinned, f".ci/lowest.txt: {line!r} is not name==version"
            key = canonicalize_name(name)
            assert key not in pins, f".ci/lowest.txt pins {name} twice"
            pins[key] = Version(pinned)
    return pins


def _lower_bounds(texts: list[str]) -> dict[str, Version | None]:
    """Each requirement's lower bound (``>=`` or ``==``), ``None`` when it has none;
    references to diffcam's own extras are left out."""
    bounds = {}
    for text in texts:
        req = Requirement(text)
        if canonicalize_name(req.name) == "diffcam":
            continue
        lows = [Version(s.version) for s in req.specifier if s.operator in (">=", "==")]
        bounds[canonicalize_name(req.name)] = max(lows) if lows else None
    return bounds


def _project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def test_every_runtime_dependency_has_a_lower_bound_that_is_pinned():
    """Each of pyproject.toml's dependencies has a lower bound, and .ci/lowest.txt pins
    that very version."""
    runtime, pins = _lower_bounds(_project()["dependencies"]), _pins()
    assert "jax" in runtime and "numpy" in runtime
    for name, bound in runtime.items():
        assert bound is not None, f"pyproject.toml: {name} has no lower bound"
        assert pins.get(name) == bound, (f"{name}: pyproject.toml says >={bound}, "
                                         f".ci/lowest.txt pins {pins.get(name)}")


def test_every_pin_is_a_lower_bound_of_pyproject():
    """Every pin of .ci/lowest.txt is the lower bound of the same package in the
    dependencies or the test extra (nothing pinned that pyproject.toml does not bound),
    and the fftw extra's bounds agree with the test extra's."""
    project = _project()
    extras = project["optional-dependencies"]
    bounds = _lower_bounds(project["dependencies"] + extras["test"])
    for name, pinned in _pins().items():
        assert bounds.get(name) == pinned, (f"{name}: .ci/lowest.txt pins {pinned}, "
                                            f"pyproject.toml bounds it at {bounds.get(name)}")
    for name, bound in _lower_bounds(extras["fftw"]).items():
        assert bounds[name] == bound, f"{name}: the fftw extra says {bound}, test {bounds[name]}"
