"""Old names kept working: each warns once per process, then calls the new one."""

from __future__ import annotations

import functools
import warnings
from typing import Callable

__all__ = ["renamed"]

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
