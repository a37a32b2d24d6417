"""The package's structure: import layers, no cycles, no late or private imports across
modules, and the size limits of modules, functions and signatures.

The layers, lowest first (a module imports only from its own layer and the ones below):

    core  ←  io, data  ←  optics  ←  model  ←  evaluate  ←  reconstruct  ←  calibrate, design
          ←  apps

``evaluate`` sits below ``reconstruct`` and ``calibrate`` because both score their
fits with its metrics and registration geometry, and it needs neither; ``calibrate``
sits above ``reconstruct`` because calibrating a PSF from scenes deconvolves; ``design``
(a diffuser optimised through the PSFs) sits beside it, above what it optimises through. The
package's ``diffcam/__init__.py`` and ``__main__.py`` re-export the public names and
sit above everything.
"""

from __future__ import annotations

import ast
import textwrap
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "diffcam"

LAYERS = (("core",), ("io", "data"), ("optics",), ("model",), ("evaluate",),
          ("reconstruct",), ("calibrate", "design"), ("apps",))
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 60
MAX_PUBLIC_PARAMETERS = 8


def _layer(module: str) -> int:
    """Layer index of a dotted module name; the package root is above every layer."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in ("__main__",):
        return len(LAYERS)
    for k, names in enumerate(LAYERS):
        if parts[1] in names:
            return k
    raise AssertionError(f"{module}: not in any layer of {LAYERS}; add it to the table.")


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = (root.name,) + path.relative_to(root).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(name: str, path: Path, modules: dict) -> list[tuple[str, str, bool]]:
    """(target module, imported name, at module level) for every import of the package
    in ``path``; a ``from pkg import sub`` of a submodule targets the submodule."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    top_level = {id(n) for n in tree.body}
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for alias in node.names:
                sub = f"{source}.{alias.name}"
                target = sub if sub in modules else source
                if target in modules:
                    found.append((target, alias.name if target == source else "",
                                  id(node) in top_level))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in modules:
                    found.append((alias.name, "", id(node) in top_level))
    return found


def import_problems(root: Path) -> list[str]:
    """Every upward import, late (function-level) import of the package, private name
    imported from another module, and import cycle among the modules under ``root``."""
    modules = _modules(root)
    problems, graph = [], {m: set() for m in modules}
    for name, path in modules.items():
        for target, imported, top in _imports(name, path, modules):
            if _layer(target) > _layer(name):
                problems.append(f"upward import: {name} (layer {_layer(name)}) imports "
                                f"{target} (layer {_layer(target)})")
            if not top:
                problems.append(f"late import: {name} imports {target} inside a function")
            if imported.startswith("_") and target != name:
                problems.append(f"private import: {name} imports {target}.{imported}")
            if top and target != name:
                graph[name].add(target)
    problems += [f"import cycle: {' → '.join(c)}" for c in _cycles(graph)]
    return problems


def _cycles(graph: dict[str, set]) -> list[list[str]]:
    """One cycle per strongly connected component of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp) + [sorted(comp)[0]])

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_imports_follow_the_layers_without_cycles():
    assert import_problems(PACKAGE) == []


def _plant(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "diffcam"
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    for d in [root, *[p for p in root.rglob("*") if p.is_dir()]]:
        (d / "__init__.py").touch()
    return root


def test_the_check_fails_on_a_planted_upward_import_cycle_and_late_import(tmp_path):
    root = _plant(tmp_path, {
        "core/grid.py": "from diffcam.model.camera import Camera\n",
        "model/camera.py": "from diffcam.core.grid import pad\n"
                           "def f():\n    from diffcam.optics.lens import _private\n",
        "optics/lens.py": "_private = 1\n",
    })
    problems = import_problems(root)
    assert any(p.startswith("upward import: diffcam.core.grid") for p in problems)
    assert any(p.startswith("import cycle:") and "diffcam.core.grid" in p
               for p in problems)
    assert any(p.startswith("late import: diffcam.model.camera") for p in problems)
    assert any(p == "private import: diffcam.model.camera imports diffcam.optics.lens._private"
               for p in problems)
    clean = _plant(tmp_path / "clean", {"core/grid.py": "X = 1\n",
                                        "model/camera.py": "from diffcam.core.grid import X\n"})
    assert import_problems(clean) == []


def _function_sizes(path: Path):
    """(name, body lines without the docstring, parameter count) of every function."""
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        body = node.body
        has_doc = isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str)
        start = (body[1].lineno if len(body) > 1 else body[0].end_lineno + 1) if has_doc \
            else body[0].lineno
        a = node.args
        params = [*a.posonlyargs, *a.args, *a.kwonlyargs]
        count = len(params) + (a.vararg is not None) + (a.kwarg is not None)
        if params and params[0].arg in ("self", "cls"):
            count -= 1
        yield node.name, node.end_lineno - start + 1, count


def size_offenders(root: Path) -> list[str]:
    """Modules over :data:`MAX_MODULE_LINES` lines, functions over
    :data:`MAX_FUNCTION_LINES` (docstring excluded), public functions over
    :data:`MAX_PUBLIC_PARAMETERS` parameters (``**overrides`` counts as one)."""
    out = []
    for name, path in _modules(root).items():
        lines = len(path.read_text().splitlines())
        if lines > MAX_MODULE_LINES:
            out.append(f"{name}: {lines} lines")
        for fn, length, params in _function_sizes(path):
            if length > MAX_FUNCTION_LINES:
                out.append(f"{name}.{fn}: {length} lines")
            if not fn.startswith("_") and params > MAX_PUBLIC_PARAMETERS:
                out.append(f"{name}.{fn}: {params} parameters")
    return out


def test_modules_functions_and_signatures_stay_small():
    assert size_offenders(PACKAGE) == []


def test_the_size_check_fails_on_planted_offenders(tmp_path):
    long_body = "".join(f"    x{k} = {k}\n" for k in range(MAX_FUNCTION_LINES + 1))
    source = ("def long():\n    \"\"\"Doc.\"\"\"\n" + long_body
              + "def wide(a, b, c, d, e, f, g, h, i):\n    pass\n"
              + "def _private_wide(a, b, c, d, e, f, g, h, i):\n    pass\n"
              + "def keyed(a, *, b, c, d, e, f, g, **overrides):\n    pass\n"
              + "\n" * MAX_MODULE_LINES)
    root = _plant(tmp_path, {"core/big.py": source})
    offenders = size_offenders(root)
    assert f"diffcam.core.big: {len(source.splitlines())} lines" \
        in offenders
    assert f"diffcam.core.big.long: {MAX_FUNCTION_LINES + 1} lines" in offenders
    assert "diffcam.core.big.wide: 9 parameters" in offenders
    assert not any("_private_wide" in o or "keyed" in o for o in offenders)


@pytest.mark.parametrize("module", sorted(_modules(PACKAGE)))
def test_every_module_is_in_a_layer(module):
    assert 0 <= _layer(module) <= len(LAYERS)
