"""Package namespaces that import their modules on first use (PEP 562).

``import diffcam`` and ``import diffcam.calibrate`` import nothing heavy: each public
name is imported from its module the first time it is used, so a command that needs
only a few modules (``diffcam predict``) does not pay for SciPy, optax or optimistix.

A lazy package keeps its public names, and where each comes from, as ordinary
``from … import …`` lines and an ``__all__`` in the stub ``__init__.pyi`` beside its
``__init__.py`` (type checkers and the API documentation read the same file)::

    # __init__.py
    from diffcam.core.lazy import attach_stub

    __getattr__, __dir__, __all__ = attach_stub(__name__, __file__)

A submodule that no stub line names (``diffcam.calibrate.pipeline``) is imported on
first attribute access as well; a package without a stub (``diffcam.core``) gets only
that, so ``diffcam.core.grid.MAX_GRID_SAMPLES`` works after a bare ``import diffcam``.
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys
from pathlib import Path

__all__ = ["attach_stub", "stub_names"]


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
