"""Freed memory kept for the next call: glibc's allocator told not to hand large blocks
back to the system (CPU, Linux).

XLA allocates every output and temporary of a jitted call afresh. glibc serves a block
of 32 MiB or more (a 2048² complex64 field is 32 MiB, 4096² is 128 MiB) with ``mmap``
and returns it with ``munmap`` when freed, so the next call's block is new memory again
and the kernel zero-fills it page by page on first touch: one page fault per 4 KiB,
about 0.7 µs each here. Measured on the project's 2-core machine (FFTW backend, one
Fresnel step, ``benchmarks/bench_fft.py`` and ``docs/fft.md``): 8193 page faults per
step at 2048², 32769 at 4096², which made the step 1.27× and 1.52× pyFFTW's planned
FFTW; with the policy below no page faults at all, 1.05× and 1.04×.

The policy, ``DIFFCAM_MALLOC=keep`` (opt-in; applied once, when diffcam is imported):

- ``M_MMAP_MAX = 0``: large blocks come from the heap, not from ``mmap``;
- ``M_TRIM_THRESHOLD`` = :data:`KEEP_BYTES`: up to that much freed memory at the top
  of the heap stays in the process instead of being handed back;
- ``M_ARENA_MAX = 1``: every thread allocates from the one main heap. glibc gives
  threads other than the main one heaps of at most 64 MiB and serves any larger block
  from ``mmap`` whatever the settings above say; XLA allocates on its own threads.

Why it is not the default: the heap keeps holes. XLA asks for aligned blocks, and
glibc (2.36 here) cannot serve an aligned request from a freed block of exactly the
same size, so until freed neighbours merge, each call may take new memory from the
top of the heap. Measured with a jitted ``x * 2`` on a 72 MiB array
(``tests/test_memory.py``'s probe): the heap grew by one block per call for the first
10 calls (720 MiB) and then stayed put, every later call free of page faults; with
``DIFFCAM_MALLOC=system`` (glibc's defaults) each call faults all 18432 pages of its
output and the resident size stays flat. So ``keep`` is for long runs of same-sized
calls on a machine with memory to spare (fitting loops, benchmarks at 2048²–4096²);
:func:`release` hands back what is free. The arena setting takes effect only for
threads that have not yet allocated: set the variable before starting Python (diffcam
applies it when imported, which must come before the first JAX computation). Other C
libraries (musl, macOS, Windows) are left alone.
"""

from __future__ import annotations

import ctypes
import os
import platform
import warnings

__all__ = ["KEEP_BYTES", "keep_freed_memory", "release", "status"]

KEEP_BYTES = 1 << 30   # freed memory kept at the top of the heap, bytes
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8   # glibc's malloc.h
_state = {"policy": None}


def _glibc():
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL("libc.so.6")
    except OSError:
        return None


def keep_freed_memory() -> str:
    """Apply ``$DIFFCAM_MALLOC`` (``system``, the default, or ``keep``) once per
    process; returns the policy in force: ``"keep"``, ``"system"`` or
    ``"unsupported"`` (not glibc)."""
    if _state["policy"] is None:
        choice = os.environ.get("DIFFCAM_MALLOC", "system").strip().lower() or "system"
        libc = _glibc()
        if choice not in ("keep", "system"):
            warnings.warn(f"DIFFCAM_MALLOC is 'keep' or 'system', not {choice!r}: "
                          "glibc's defaults are left alone.", stacklevel=2)
        if choice != "keep":
            _state["policy"] = "system"
        elif libc is None:
            _state["policy"] = "unsupported"
        else:
            done = (libc.mallopt(_M_MMAP_MAX, 0), libc.mallopt(_M_TRIM_THRESHOLD, KEEP_BYTES),
                    libc.mallopt(_M_ARENA_MAX, 1))
            _state["policy"] = "keep" if all(done) else "system"
    return _state["policy"]


def release() -> bool:
    """Hand the freed memory the policy kept back to the system (glibc's
    ``malloc_trim``); True if some was. The next large call page-faults its buffers
    again."""
    libc = _glibc()
    return bool(libc.malloc_trim(0)) if libc is not None else False


def status() -> str:
    """One line for logs and reports."""
    policy = keep_freed_memory()
    if policy == "keep":
        return f"memory: freed blocks kept (glibc, up to {KEEP_BYTES >> 20} MiB)"
    if policy == "unsupported":
        return "memory: the system's allocator (not glibc)"
    return "memory: the system's allocator"
