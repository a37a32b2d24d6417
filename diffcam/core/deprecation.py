"""Old names kept working: each warns once per process, then serves the new one."""

from __future__ import annotations

import functools
import importlib
import importlib.abc
import importlib.util
import sys
import warnings
from typing import Callable

__all__ = ["renamed", "moved_modules"]

_warned: set[str] = set()


def warn_once(old: str, message: str) -> None:
    """A `DeprecationWarning` with ``message``, the first time ``old`` is used."""
    if old not in _warned:
        _warned.add(old)
        warnings.warn(message, DeprecationWarning, stacklevel=3)


def renamed(new: Callable, old: str) -> Callable:
    """``new``, callable as ``old`` too (``old``: the dotted path it replaces, for the
    message)."""
    @functools.wraps(new)
    def alias(*args, **kwargs):
        warn_once(old, f"{old} is now {new.__module__}.{new.__qualname__}; the old name "
                       f"will be removed.")
        return new(*args, **kwargs)

    alias.__doc__ = f"Deprecated name of `{new.__module__}.{new.__qualname__}`."
    alias.__name__ = alias.__qualname__ = old.rpartition(".")[2]
    return alias


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old module path as a module whose every attribute is the new module's."""

    def __init__(self, moves: dict[str, str]):
        self.moves = moves

    def find_spec(self, fullname, path=None, target=None):
        return (importlib.util.spec_from_loader(fullname, self)
                if fullname in self.moves else None)

    def create_module(self, spec):
        return None

    def exec_module(self, module):
        new_path = self.moves[module.__name__]
        warn_once(module.__name__, f"the module {module.__name__} is now {new_path}; the "
                                   f"old path will be removed.")
        new = importlib.import_module(new_path)
        module.__doc__ = f"Moved to `{new_path}`."
        module.__getattr__ = lambda name: getattr(new, name)
        module.__dir__ = lambda: dir(new)


def moved_modules(package: str, moves: dict[str, str]) -> None:
    """Keep ``package.OLD`` importable as ``package.NEW`` for each ``{OLD: NEW}`` of
    ``moves`` (module paths relative to ``package``), warning once on first import."""
    sys.meta_path.append(_MovedModules({f"{package}.{old}": f"{package}.{new}"
                                        for old, new in moves.items()}))
