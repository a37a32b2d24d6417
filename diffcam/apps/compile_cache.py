"""JAX's persistent compilation cache for the ``diffcam`` command.

Each ``diffcam`` command is a fresh process, and XLA compiles its programs again in
each one: a second ``diffcam predict`` of the same model recompiles the renderer
(≈ 1.5 s on 2 cores) before it renders anything. The command line therefore keeps
compiled programs on disk, in the ``jax`` folder of diffcam's cache folder
(:func:`diffcam.core.fftw.cache_folder`: ``$DIFFCAM_CACHE``, else
``$XDG_CACHE_HOME/diffcam``, else ``~/.cache/diffcam``), and a later run of the same
program on the same machine and JAX version loads it instead of compiling.

The user's settings come first: ``JAX_COMPILATION_CACHE_DIR`` (and JAX's other
``JAX_PERSISTENT_CACHE_*`` variables) are left to JAX, and ``DIFFCAM_NO_CACHE=1`` turns
the cache off. A cache folder that cannot be created or written is one line on stderr,
and the command runs without the cache. The cache is never pruned: delete the folder to
empty it. The library (``import diffcam``) never turns it on.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

from diffcam.core.fftw import cache_folder

__all__ = ["NO_CACHE", "MIN_COMPILE_SECONDS", "enable_compilation_cache"]

NO_CACHE = "DIFFCAM_NO_CACHE"
"""Environment variable: ``1`` (any value but empty or ``0``) turns the cache off."""

MIN_COMPILE_SECONDS = 0.2
"""Programs that compile faster than this (s) are not written to the cache: reading a
small program back costs about as much as compiling it (JAX's own default is 1 s)."""


def enable_compilation_cache() -> str | None:
    """Turn on JAX's persistent compilation cache for this process, before anything
    compiles (module docstring). Returns the cache folder, or ``None`` when it is off
    (``DIFFCAM_NO_CACHE``, or a folder that cannot be written: one line on stderr)."""
    if os.environ.get(NO_CACHE, "").strip() not in ("", "0"):
        return None
    folder = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not folder:
        folder = str(cache_folder() / "jax")
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError as err:
            print(f"diffcam: compilation cache off: cannot write {folder} "
                  f"({err.strerror or err}); set {NO_CACHE}=1 to skip it.", file=sys.stderr)
            return None
    import jax

    settings = {"jax_compilation_cache_dir": folder,
                "jax_persistent_cache_min_compile_time_secs": MIN_COMPILE_SECONDS}
    for name, value in settings.items():
        if name.upper() not in os.environ:
            jax.config.update(name, value)
    return folder
