"""The documentation: the site builds strictly and offline with an API entry for every
public name and no raw Sphinx role, the rendered notebooks hold their sources' code and
show figures but no progress reports or stray return values, RESULTS.md is what its
generator writes, reference text carries no work log, and every command block of the
README and the docs runs as written."""

import html
import importlib
import json
import os
import pkgutil
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = sorted((ROOT / "docs").rglob("*.md"))
API_MODULES = ["diffcam", "diffcam.calibrate", "diffcam.model", "diffcam.optics",
               "diffcam.reconstruct", "diffcam.evaluate", "diffcam.io", "diffcam.data",
               "diffcam.design"]

# work-log wording that reference text must not carry: dates, numbered or named working
# sessions, "previously", "formerly", "former …", "until <date>", "an earlier run", "in
# the four runs before", "was fixed/wrong/tried…"
HISTORY = re.compile(
    r"\b20\d\d-[01]\d-[0-3]\d\b"
    r"|\b(first|earlier|later|latest|previous|numbered|that|this|one|\w+th) session\b"
    r"|\bsessions? \d+|\bpreviously\b|\bformerly\b|\bformer\b"
    r"|\buntil (that|this) session|\buntil 20\d\d|\bearlier run\b|\bin the \w+ runs before\b"
    r"|\bwas (fixed|wrong|changed|dropped|removed|reverted|tried|not reproduced)\b"
    r"|\btried first\b|\bused to be\b|\bnot re-?measured\b", re.I)


def _public_modules() -> list[str]:
    import diffcam.core
    return API_MODULES + [f"diffcam.core.{m.name}"
                          for m in pkgutil.iter_modules(diffcam.core.__path__)]


def _blocks(path: Path, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", path.read_text(), flags=re.S)


# --- fast checks ---------------------------------------------------------------------

def test_readme_is_short_with_an_early_api_example():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150, f"README.md has {len(lines)} lines"
    start = lines.index("```python") + 1
    assert start < 60, f"the API example starts at line {start}"


def test_results_page_is_what_its_generator_writes():
    from benchmarks.results_md import PAGE, render
    assert PAGE.read_text() == render(), "run python -m benchmarks.results_md"
    headings = [line for line in PAGE.read_text().splitlines() if line.startswith("#")]
    assert all(not HISTORY.search(h) for h in headings), headings


@pytest.mark.parametrize("path", [*sorted((ROOT / "diffcam").rglob("*.py")), *PAGES,
                                  ROOT / "README.md"], ids=lambda p: str(p.relative_to(ROOT)))
def test_reference_text_carries_no_work_log(path):
    hits = [f"{path.name}:{i}: {line.strip()}"
            for i, line in enumerate(path.read_text().splitlines(), 1)
            if HISTORY.search(line)]
    assert not hits, "history belongs in CHANGELOG.md and git:\n" + "\n".join(hits)


def test_history_pattern_catches_work_log_and_spares_prose():
    """The grep above is only as good as its patterns: it must flag the wording the
    issue quotes and leave ordinary prose alone."""
    for log in ("Until 2026-11-25 this calibration ran on a wrong float32 gradient",
                "the tenth session", "in the four runs before", "the former default",
                "Until that session the gradient was wrong", "an earlier run's ratios"):
        assert HISTORY.search(log), log
    for prose in ("raise it for the session by assigning to the constant",
                  "waits until the files are in place", "the old output survives",
                  "checks that public entry points run before tracing",
                  "a field the caller no longer needs"):
        assert not HISTORY.search(prose), prose


def test_rendered_notebooks_hold_their_sources_and_figures():
    """Each notebook is on the site executed (docs/notebooks/*.ipynb, written by
    scripts/render_notebooks.py) with the code of its jupytext source and at least one
    figure, and the site's navigation lists it."""
    import jupytext
    nav = (ROOT / "mkdocs.yml").read_text()
    sources = sorted((ROOT / "notebooks").glob("*.py"))
    assert sources
    for source in sources:
        rendered = ROOT / "docs" / "notebooks" / f"{source.stem}.ipynb"
        assert rendered.exists(), f"run python scripts/render_notebooks.py {source.stem}"
        assert f"notebooks/{source.stem}.ipynb" in nav
        code = [c.source for c in jupytext.read(source).cells if c.cell_type == "code"]
        cells = json.loads(rendered.read_text())["cells"]
        ran = [c for c in cells if c["cell_type"] == "code"]
        assert ["".join(c["source"]) for c in ran] == code, f"{rendered.name} is stale"
        figures = [o for c in ran for o in c["outputs"] if "image/png" in o.get("data", {})]
        assert figures, f"{rendered.name} shows no figure"


ROLE = re.compile(r":(mod|class|func|data|meth|attr|obj|exc):`")
# what a notebook must not show: a progress report on stderr, or the value a plotting
# call returns (a tuple of limits, an Axes, a Legend, a Colorbar, a Text, a list of
# Line2D) echoed as the cell's Out[n]
STRAY_VALUE = re.compile(r"^\(np\.float64|^\[?<matplotlib\.|^Text\(|^\(-?[\d.]+, -?[\d.]+")


def test_sources_carry_no_sphinx_roles():
    """The site is mkdocs: cross-references are Markdown ([`name`][diffcam.x.y]) or
    plain code, never Sphinx roles, which the API pages would print raw."""
    hits = [f"{path.relative_to(ROOT)}:{i}: {line.strip()}"
            for path in sorted((ROOT / "diffcam").rglob("*.py*")) if path.suffix in (".py", ".pyi")
            for i, line in enumerate(path.read_text().splitlines(), 1) if ROLE.search(line)]
    assert not hits, "\n".join(hits)


def test_rendered_notebooks_show_no_progress_or_stray_values():
    for rendered in sorted((ROOT / "docs" / "notebooks").glob("*.ipynb")):
        for n, cell in enumerate(json.loads(rendered.read_text())["cells"]):
            for out in cell.get("outputs", []):
                assert out.get("name") != "stderr", (rendered.name, n, "".join(out["text"]))
                text = "".join(out.get("data", {}).get("text/plain", ""))
                assert not (out["output_type"] == "execute_result" and STRAY_VALUE.search(text)), \
                    (rendered.name, n, text)


def test_stray_value_pattern_catches_plotting_returns():
    for stray in ("(np.float64(-0.5), np.float64(639.5), np.float64(539.5), np.float64(-0.5))",
                  "<matplotlib.legend.Legend at 0x7f1070657950>", "Text(0.5, 1.0, 'PSF')",
                  "[<matplotlib.lines.Line2D at 0x7f10>]", "(-0.5, 639.5, 539.5, -0.5)"):
        assert STRAY_VALUE.search(stray), stray
    for value in ("0.9658", "{'model': 0.98}", "array([1, 2])", "'(5, 27)'"):
        assert not STRAY_VALUE.search(value), value


def test_cross_references_name_objects_that_exist():
    """Every Markdown cross-reference (`[text][diffcam.x.y]`) in the sources and the docs
    names an importable object: the strict site build refuses a stale one, and this
    check finds it without building the site."""
    targets = {(path.relative_to(ROOT), target)
               for path in [*(ROOT / "diffcam").rglob("*.py"), *PAGES]
               for target in re.findall(r"\]\[(diffcam(?:\.\w+)*)\]", path.read_text())}
    missing = []
    for path, target in sorted(targets):
        parts = target.split(".")
        for split in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:split]))
            except ImportError:
                continue
            try:
                for name in parts[split:]:
                    obj = getattr(obj, name)
            except AttributeError:
                missing.append(f"{path}: {target}")
            break
        else:
            missing.append(f"{path}: {target}")
    assert not missing, "\n".join(missing)


def test_api_pages_cover_every_public_module():
    """Every module with an ``__all__`` is on an API page (the built site's entries are
    checked by test_site_builds_with_every_public_name)."""
    directives = {line.split(":::", 1)[1].strip() for page in (ROOT / "docs" / "api").glob("*.md")
                  for line in page.read_text().splitlines() if line.startswith(":::")}
    assert set(API_MODULES) | {"diffcam.core"} <= directives


# --- slow: the site, and the command blocks --------------------------------------------

@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(out)],
                       cwd=ROOT, capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-4000:]
    return out


@pytest.mark.slow
def test_site_builds_with_every_public_name(site):
    """`mkdocs build --strict` passes, and every name in the ``__all__`` of diffcam, its
    subpackages and the core modules has an entry: under its exported path, or under
    the path where it is defined (a function named like its module)."""
    ids = set()
    for page in (site / "api").glob("*/index.html"):
        ids |= set(re.findall(r'id="(diffcam[^"]*)"', page.read_text()))
    missing = []
    for name in _public_modules():
        module = importlib.import_module(name)
        for member in getattr(module, "__all__", []):
            obj = getattr(module, member)
            defined = f"{getattr(obj, '__module__', '')}.{getattr(obj, '__qualname__', '')}"
            if f"{name}.{member}" not in ids and defined not in ids:
                missing.append(f"{name}.{member}")
    assert not missing, missing


@pytest.mark.slow
def test_site_shows_the_notebooks_with_figures(site):
    for source in sorted((ROOT / "notebooks").glob("*.py")):
        html = (site / "notebooks" / source.stem / "index.html").read_text()
        assert html.count("data:image/png;base64,") >= 1, source.stem
        # an output element of that type (the page's CSS names it too)
        assert not re.search(r'<div[^>]*data-mime-type="application/vnd\.jupyter\.stderr"', html), \
            source.stem
        shown = [re.sub(r"<[^>]+>", "", out).strip() for out in
                 re.findall(r"Out\[\d+\]:.*?</pre>", html, flags=re.S)]
        stray = [s for s in shown if STRAY_VALUE.search(html.unescape(s).split(":", 1)[1].strip())]
        assert not stray, (source.stem, stray)


@pytest.mark.slow
def test_site_prints_no_sphinx_roles(site):
    """No page shows a raw role (":mod: .camera — :class: Camera"), and the header
    links to no repository (there is no public address)."""
    hits = []
    for page in site.rglob("*.html"):
        text = re.sub(r"<[^>]+>", "", page.read_text())
        hits += [f"{page.relative_to(site)}: {m.group(0)}"
                 for m in re.finditer(r":(mod|class|func|data|meth|attr|obj|exc):\s*\S+", text)]
    assert not hits, hits[:20]
    assert 'class="md-source"' not in (site / "index.html").read_text()


# pages whose ``sh`` blocks are synopses of a user's own files, to be fenced as ``text``
# by their editors (the hardening work owns docs/cli_reconstruct.md): listed, not hidden
SYNOPSIS_PAGES = {ROOT / "docs" / "cli_reconstruct.md"}


def _command_blocks():
    """Every ``sh`` block of the README and the docs but the set-up ones (those that
    create the virtual environment: the quick start, which .ci/run runs itself)."""
    found = []
    for path in [ROOT / "README.md", *(p for p in PAGES if p not in SYNOPSIS_PAGES)]:
        for k, block in enumerate(_blocks(path, "sh")):
            if "python3 -m venv" not in block:
                found.append(pytest.param(block, id=f"{path.relative_to(ROOT)}#{k}"))
    return found


def _fresh_shell_env() -> dict:
    """The environment of a new shell: the virtual environment not activated."""
    venv_bin = str(Path(sys.prefix) / "bin")
    path = os.pathsep.join(p for p in os.environ["PATH"].split(os.pathsep) if p != venv_bin)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    return dict(env, PATH=path, MPLBACKEND="Agg")


@pytest.mark.slow
@pytest.mark.parametrize("block", _command_blocks())
def test_command_block_runs_as_written(block):
    """Run in a new bash from the clone's folder, after the quick start (``.venv``)."""
    if not (ROOT / ".venv" / "bin" / "activate").exists():
        pytest.fail("the blocks run after the quick start: create .venv as the README says")
    r = subprocess.run(["bash", "-e", "-c", block], cwd=ROOT, env=_fresh_shell_env(),
                       capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, f"{block}\n--- stderr ---\n{r.stderr[-3000:]}"


@pytest.mark.slow
@pytest.mark.parametrize("page", [p for p in PAGES if _blocks(p, "python")],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_python_blocks_run(page, tmp_path):
    """The docs' Python examples run as written, each page's blocks in order in one
    fresh interpreter (the README's: tests/test_readme.py)."""
    script = "\n".join(_blocks(page, "python"))
    r = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True,
                       text=True, timeout=1800, env=dict(os.environ, MPLBACKEND="Agg"))
    assert r.returncode == 0, r.stderr[-3000:]
