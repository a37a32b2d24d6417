"""Progress reports for long loops: one place for every long-running computation.

A jitted loop calls [`tick`][diffcam.core.progress.tick] with its iteration index once per
iteration; the call is a ``jax.debug.callback`` to a module-level function, so it is
compiled once and does not depend on any bar. On the host, the tick advances the innermost
bar opened by [`progress_bar`][diffcam.core.progress.progress_bar] around the call, if any;
without one it does nothing. A solver called under a caller's ``jit`` runs after its
``progress_bar`` block has closed, so it shows nothing. Host loops open a bar with
[`new_bar`][diffcam.core.progress.new_bar] and advance it themselves.

On a terminal a tqdm bar appears for runs longer than [`DELAY`][diffcam.core.progress.DELAY]
seconds; elsewhere (a log file, a pipe, CI) a plain line every
[`LINE_EVERY`][diffcam.core.progress.LINE_EVERY] seconds and one at the end, so runs shorter
than that stay silent. ``progress=False`` on the public functions, or ``DIFFCAM_PROGRESS=0``
in the environment, turns them off. A tick costs a few microseconds per iteration
(``docs/real_data.md``).
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from typing import Iterator

import jax
import numpy as np

__all__ = ["tick", "progress_bar", "new_bar", "enabled", "DELAY", "LINE_EVERY"]

DELAY = 2.0
"""Seconds before a bar appears on a terminal."""
LINE_EVERY = 30.0
"""Seconds between plain progress lines when stderr is not a terminal."""
_BARS: list = []  # the bars open now, innermost last


def enabled(progress: bool = True) -> bool:
    """``progress``, unless ``DIFFCAM_PROGRESS=0`` turns every bar off."""
    return bool(progress) and os.environ.get("DIFFCAM_PROGRESS", "1") != "0"


def _advance(k) -> None:
    """Host side of `tick`: set the innermost bar to ``max(k) + 1`` iterations (a
    batched solve ticks once per problem; the bar counts iterations, not problems)."""
    if _BARS:
        bar = _BARS[-1]
        done = int(np.max(k)) + 1
        if done > bar.n:
            bar.update(done - bar.n)


def tick(k: jax.Array) -> None:
    """Report iteration ``k`` (0-based, traced) of a loop to the open progress bar."""
    jax.debug.callback(_advance, k)


@contextmanager
def progress_bar(total: int, desc: str, progress: bool = True,
                 unit: str = "it") -> Iterator[None]:
    """A tqdm bar of ``total`` steps that [`tick`][diffcam.core.progress.tick] advances
    while the block runs.

    The block must wait for the computation (``jax.block_until_ready``), since JAX
    dispatches asynchronously. With ``progress`` false (or ``DIFFCAM_PROGRESS=0``) it
    opens nothing.
    """
    if not enabled(progress):
        yield
        return
    bar = new_bar(total, desc, unit=unit)
    _BARS.append(bar)
    try:
        yield
    finally:
        _BARS.remove(bar)
        bar.close()


def new_bar(total: int, desc: str, unit: str = "it", progress: bool = True):
    """A progress bar of ``total`` steps with tqdm's ``update``, ``set_postfix``,
    ``close`` and ``n``, also a context manager: a tqdm bar when stderr is a terminal,
    else [`PlainProgress`][diffcam.core.progress.PlainProgress] lines. ``progress`` false
    (or ``DIFFCAM_PROGRESS=0``) gives a bar that shows nothing."""
    show = enabled(progress)
    if show and sys.stderr.isatty():
        from tqdm.auto import tqdm

        return tqdm(total=int(total), desc=desc, unit=unit, delay=DELAY, leave=False)
    return PlainProgress(total, desc, unit=unit, show=show)


class PlainProgress:
    """Progress for a log: ``desc: n/total unit, t s`` on stderr at most every
    [`LINE_EVERY`][diffcam.core.progress.LINE_EVERY] seconds, and a last line on
    [`close`][diffcam.core.progress.PlainProgress.close] if any was printed."""

    def __init__(self, total: int, desc: str, unit: str = "it", show: bool = True):
        self.total, self.desc, self.unit, self.show = int(total), desc, unit, show
        self.n, self.postfix, self.printed = 0, "", False
        self.start = self.last = time.perf_counter()

    def update(self, steps: int = 1) -> None:
        self.n += int(steps)
        now = time.perf_counter()
        if self.show and now - self.last >= LINE_EVERY:
            self._line(now)

    def set_postfix(self, **values) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def close(self) -> None:
        if self.show and self.printed:
            self._line(time.perf_counter())
        self.show = False

    def _line(self, now: float) -> None:
        extra = f", {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {self.n}/{self.total} {self.unit}, {now - self.start:.0f} s"
              f"{extra}", file=sys.stderr, flush=True)
        self.last, self.printed = now, True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
