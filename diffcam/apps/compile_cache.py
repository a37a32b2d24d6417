"""JAX's persistent compilation cache for the ``diffcam`` command.

Each ``diffcam`` command is a fresh process, and XLA compiles its programs again in
each one: a second ``diffcam predict`` of the same model recompiles the renderer
(≈ 1.5 s on 2 cores) before it renders anything. The command line therefore keeps
compiled programs on disk, in the ``jax`` folder of diffcam's cache folder
(`diffcam.core.fftw.cache_folder`: ``$DIFFCAM_CACHE``, else
``$XDG_CACHE_HOME/diffcam``, else ``~/.cache/diffcam``), and a later run of the same
program on the same machine and JAX version loads it instead of compiling.

The folder is capped at `DEFAULT_MAX_MB` megabytes (``DIFFCAM_CACHE_MAX_MB``
chooses another cap) by JAX's own eviction (``jax_compilation_cache_max_size``, which
locks the folder with the ``filelock`` package): before a new program is written, the
programs used least recently are deleted until the folder, the new program included,
fits. JAX dates each program by a ``KEY-atime`` file beside its ``KEY-cache`` file and
cannot evict without it; programs written without a cap have none, so
`enable_compilation_cache` first dates them by their modification time.

The user's settings come first: ``JAX_COMPILATION_CACHE_DIR`` (and JAX's other
``JAX_PERSISTENT_CACHE_*`` and ``JAX_COMPILATION_CACHE_*`` variables) are left to JAX,
with no cap of diffcam's on that folder, and ``DIFFCAM_NO_CACHE=1`` turns the cache
off. A cache folder that cannot be created or written is one line on stderr, and the
command runs without the cache. The library (``import diffcam``) never turns it on.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from diffcam import core  # lazy: diffcam.core.fftw loads JAX on use
from diffcam.core.errors import environment_count

__all__ = ["NO_CACHE", "MAX_MB", "DEFAULT_MAX_MB", "MIN_COMPILE_SECONDS",
           "enable_compilation_cache", "cache_cap"]

NO_CACHE = "DIFFCAM_NO_CACHE"
"""Environment variable: ``1`` (any value but empty or ``0``) turns the cache off."""

MAX_MB = "DIFFCAM_CACHE_MAX_MB"
"""Environment variable: the cap of diffcam's cache folder, in megabytes (10⁶ bytes), a
whole number of at least 1."""

DEFAULT_MAX_MB = 1000
"""The cap of diffcam's cache folder without ``DIFFCAM_CACHE_MAX_MB`` (MB): about 1400
programs of a 44-plane ``diffcam predict`` (0.7 MB each)."""

MIN_COMPILE_SECONDS = 0.2
"""Programs that compile faster than this (s) are not written to the cache: reading a
small program back costs about as much as compiling it (JAX's own default is 1 s)."""


def enable_compilation_cache() -> str | None:
    """Turn on JAX's persistent compilation cache for this process, before anything
    compiles (module docstring). Returns the cache folder, or ``None`` when it is off
    (``DIFFCAM_NO_CACHE``, or a folder that cannot be written: one line on stderr).

    Raises:
        DiffcamError: ``DIFFCAM_CACHE_MAX_MB`` is not a whole number ≥ 1.
    """
    if os.environ.get(NO_CACHE, "").strip() not in ("", "0"):
        return None
    folder = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    settings = {"jax_persistent_cache_min_compile_time_secs": MIN_COMPILE_SECONDS}
    if not folder:
        cap = cache_cap()
        folder = str(core.fftw.cache_folder() / "jax")  # loads JAX: the command needs it
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=folder):
                pass
            _date_undated(Path(folder))
        except OSError as err:
            print(f"diffcam: compilation cache off: cannot write {folder} "
                  f"({err.strerror or err}); set {NO_CACHE}=1 to skip it.", file=sys.stderr)
            return None
        settings["jax_compilation_cache_max_size"] = cap
    import jax

    settings["jax_compilation_cache_dir"] = folder
    for name, value in settings.items():
        if name.upper() not in os.environ:
            jax.config.update(name, value)
    return folder


def cache_cap() -> int:
    """The cap of diffcam's cache folder in bytes: ``$DIFFCAM_CACHE_MAX_MB`` megabytes,
    else `DEFAULT_MAX_MB`.

    Raises:
        DiffcamError: the variable is set to anything but a whole number ≥ 1.
    """
    megabytes = environment_count(MAX_MB, f"for {DEFAULT_MAX_MB} MB")
    return (megabytes or DEFAULT_MAX_MB) * 10**6


def _date_undated(folder: Path) -> None:
    """Give each program in ``folder`` that has no ``-atime`` file its modification
    time as its last use, holding JAX's lock on the folder (``.lockfile``), so that
    JAX's eviction can order it (module docstring). A lock held elsewhere for 10 s
    leaves them for the next command."""
    undated = [p for p in folder.glob("*-cache") if not _atime_file(p).exists()]
    if not undated:
        return
    import filelock

    try:
        with filelock.FileLock(folder / ".lockfile", timeout=10):
            for program in undated:
                atime = _atime_file(program)
                try:
                    stamp = program.stat().st_mtime_ns
                except FileNotFoundError:  # evicted meanwhile by another process
                    continue
                if not atime.exists():
                    atime.write_bytes(stamp.to_bytes(8, "little"))
    except filelock.Timeout:
        pass


def _atime_file(program: Path) -> Path:
    """The file in which JAX's eviction keeps the last use of ``program`` (KEY-cache)."""
    return program.with_name(program.name.removesuffix("-cache") + "-atime")
