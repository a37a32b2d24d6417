"""Package namespaces that import their modules on first use (PEP 562).

``import diffcam`` and ``import diffcam.calibrate`` (``.model``, ``.optics``,
``.evaluate``) import nothing heavy: each public name is imported from its module the
first time it is used, so a command that needs only a few modules (``diffcam
predict``) does not pay for SciPy, optax or optimistix, and ``diffcam --help`` loads no
JAX.

A lazy package keeps its public names, and where each comes from, as ordinary
``from … import …`` lines and an ``__all__`` in the stub ``__init__.pyi`` beside its
``__init__.py`` (type checkers and the API documentation read the same file)::

    # __init__.py
    from diffcam.core.lazy import attach_stub

    __getattr__, __dir__, __all__ = attach_stub(__name__, __file__)

A submodule that no stub line names (``diffcam.calibrate.phase.pipeline``) is imported on
first attribute access as well; a package without a stub (``diffcam.core``) gets only
that, so ``diffcam.core.grid.MAX_GRID_SAMPLES`` works after a bare ``import diffcam``.

[`module_constant`][diffcam.core.lazy.module_constant] reads such a limit without importing
its module (the command line's ``--help`` shows the limits, and loads no JAX).
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import operator
import sys
from pathlib import Path

__all__ = ["attach_stub", "stub_names", "module_constant"]


def stub_names(stub: str | Path) -> tuple[dict[str, tuple[str, str]], list[str]]:
    """The ``from MODULE import NAME [as ALIAS]`` lines of a stub as ``{ALIAS: (MODULE,
    NAME)}``, and its ``__all__`` (every imported name when it has none)."""
    tree = ast.parse(Path(stub).read_text(encoding="utf-8"))
    origin, exported = {}, None
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for alias in node.names:
                origin[alias.asname or alias.name] = (node.module, alias.name)
        elif isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            exported = list(ast.literal_eval(node.value))
    return origin, exported if exported is not None else list(origin)


def attach_stub(package: str, init_file: str):
    """``(__getattr__, __dir__, __all__)`` for the package ``package`` whose
    ``__init__.py`` is ``init_file``: the names of the ``__init__.pyi`` beside it (none
    if it has no stub), each imported from its module on first access and then kept in
    the package; any other name that is a submodule is imported as well."""
    stub = Path(init_file).with_suffix(".pyi")
    origin, exported = stub_names(stub) if stub.is_file() else ({}, [])

    def __getattr__(name: str):
        if name in origin:
            module, attr = origin[name]
            if module == package:       # ``from diffcam import calibrate``: a submodule
                value = importlib.import_module(f"{package}.{attr}")
            else:
                value = getattr(importlib.import_module(module), attr)
        elif not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}"):
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(origin))

    return __getattr__, __dir__, exported


_ARITHMETIC = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
               ast.Pow: operator.pow, ast.FloorDiv: operator.floordiv}


def module_constant(dotted: str) -> int | float:
    """The number ``MODULE.NAME`` (``"diffcam.core.grid.MAX_GRID_SAMPLES"``), without
    importing ``MODULE`` while nothing has: then the value its source assigns (a number,
    or ``+ - * ** //`` of numbers, e.g. ``2 ** 28``) is the value it has. Once
    ``MODULE`` is imported, its attribute (a value the user assigned included).

    Raises:
        AttributeError: the source assigns ``NAME`` no such number.
    """
    module, name = dotted.rsplit(".", 1)
    if module in sys.modules:
        return getattr(sys.modules[module], name)
    for node in ast.parse(_source(module)).body:
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == name for t in node.targets):
            return _number(node.value, dotted)
    raise AttributeError(f"{module} assigns no number to {name}")


def _source(module: str) -> str:
    """The source of ``module`` of an installed package, found without importing its
    parent packages (``diffcam.reconstruct`` imports its solvers)."""
    top, *parts = module.split(".")
    path = Path(importlib.util.find_spec(top).submodule_search_locations[0], *parts)
    file = path / "__init__.py" if path.is_dir() else path.with_suffix(".py")
    return file.read_text(encoding="utf-8")


def _number(node: ast.expr, what: str) -> int | float:
    """The value of a number, or of arithmetic on numbers, in a module's source."""
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        return node.value
    if isinstance(node, ast.BinOp) and type(node.op) in _ARITHMETIC:
        return _ARITHMETIC[type(node.op)](_number(node.left, what), _number(node.right, what))
    raise AttributeError(f"{what} is not a number or arithmetic on numbers")
