"""Fresh buffers and their page faults: whether this process gets huge pages and keeps
freed blocks for reuse (CPU, Linux, glibc).

XLA allocates every output and temporary of a jitted call afresh. glibc serves a block
above its mmap threshold with ``mmap`` and hands it back with ``munmap`` when it is
freed, so the next call's block is new memory again, which the kernel zero-fills on
first touch, one page fault per page. The threshold starts at 128 KiB and rises to the
size of each mapped block that is freed, up to 32 MiB on 64-bit systems (``mallopt(3)``,
``M_MMAP_THRESHOLD``). So after a process's first calls, smaller blocks come from the
heap and are reused, while a block of 32 MiB or more (a 2048² complex64 field is
32 MiB, 4096² is 128 MiB) is mapped afresh on every call. The heap's free top is also
given back to the kernel above ``M_TRIM_THRESHOLD`` (twice the mmap threshold once that
has moved), and faults again when reused. With 4 KiB pages a fresh field costs 8192
faults at 2048² and 32768 at 4096². With huge pages (2 MiB) it is 16 and 64.

Measured on the project's 2-core VM (FFTW backend, one Fresnel step, ratio to pyFFTW's
planned FFTW, which writes into arrays it owns; ``docs/fft.md``): 1.27× at 2048² and
1.52× at 4096² with 4 KiB pages; 0.96× and 1.19× with huge pages; 0.82× and 1.11× when
the step's input is donated (``u = step(u)``), so that no fresh buffer is needed.

glibc asks the kernel for huge pages on its own blocks when the process starts with
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (glibc ≥ 2.35, and transparent huge pages in
``madvise`` or ``always`` mode, as on most Linux distributions). A tunable is read
when the process starts, so a library cannot set it for itself. Set it in the shell
before starting Python, or in a Jupyter kernel's ``env``:

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 diffcam demo

Huge pages still fault, once per 2 MiB, and glibc still returns every large block to
the kernel, which must supply (and zero) the next one. :data:`KEEP` stops that: one
malloc arena for all threads, no ``mmap`` for blocks, no trimming of the heap. A freed
block stays in the process, and once the heap has grown to what a program needs, its
calls cost no page fault and almost no kernel time. Set both together, before Python
starts:

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1:glibc.malloc.arena_max=1:glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=17179869184 python run.py

Measured on the same VM with the 4096² scaling PSF's ``value_and_grad`` (FFTW;
``python -m benchmarks.bench_grad``). With huge pages alone, calls took 505–970 ms,
about one in four slow, with 50–350 ms of system time each. With both settings, once
the heap had grown, calls took 494–545 ms with 1.5–5 ms of system time and no fault.

The price is memory, and a slow start:
- XLA's aligned requests do not fit exactly into a freed block of their own size, so
  the heap grows by about one block per call for the first calls. In a probe, eight
  72 MiB blocks were added before it settled; beside another busy process, the growth
  went on for up to 19 calls, and an occasional later call grew it once more. The
  calls that grow it are slow (about 850 ms of system time for 384 MB here).
- The process then keeps its largest footprint until it exits: a peak of 2.6 GB
  against 1.3 GB for the 4096² gradient.

So it suits a long run of one size (a fit of many gradient steps), not a session that
tries many sizes.

Neither setting changes a result. :func:`status` (printed by ``diffcam -v``) says
which is in use.
"""

from __future__ import annotations

import os
import platform
import re
from itertools import takewhile
from pathlib import Path

__all__ = ["huge_pages", "keeps_memory", "status", "TUNABLE", "KEEP"]

TUNABLE = "glibc.malloc.hugetlb=1"
KEEP = ("glibc.malloc.arena_max=1:glibc.malloc.mmap_max=0:"
        "glibc.malloc.trim_threshold=17179869184")
_THP = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def _thp_mode() -> str | None:
    """The kernel's transparent huge page mode (``always``, ``madvise``, ``never``),
    or None where there is none to read."""
    try:
        found = re.search(r"\[(\w+)\]", _THP.read_text())
    except OSError:
        return None
    return found.group(1) if found else None


def _glibc_version() -> tuple[int, int] | None:
    if platform.system() != "Linux":
        return None
    lib, version = platform.libc_ver()
    if lib != "glibc" or not version:
        return None
    major, minor = (int(p) for p in version.split(".")[:2])
    return major, minor


def _tunables() -> dict[str, str]:
    """The glibc tunables this process started with, ``{name: value}``: read from the
    environment it started with (``/proc/self/environ``, what glibc read), not from
    ``os.environ``, which Python code may have changed since. glibc parses
    ``GLIBC_TUNABLES`` in place there, ending each tunable with a NUL, so the tunables
    after the first follow it as entries of their own."""
    try:
        items = Path("/proc/self/environ").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        items = [f"GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '')}"]
    for k, item in enumerate(items):
        if item.startswith("GLIBC_TUNABLES="):
            after = takewhile(lambda i: i.startswith("glibc."), items[k + 1:])
            parts = ":".join([item[len("GLIBC_TUNABLES="):], *after]).split(":")
            return dict(p.split("=", 1) for p in parts if "=" in p)
    return {}


def huge_pages() -> str:
    """``"on"``: large blocks get huge pages (the kernel gives them to every large
    mapping, or this process started with :data:`TUNABLE`); ``"off"``: they could, with
    :data:`TUNABLE` set before Python starts; ``"unavailable"``: not on this system."""
    mode = _thp_mode()
    if mode is None or mode == "never":
        return "unavailable"
    if mode == "always":
        return "on"
    version = _glibc_version()
    if version is None or version < (2, 35):
        return "unavailable"
    return "on" if _tunables().get("glibc.malloc.hugetlb") in ("1", "2") else "off"


def keeps_memory() -> bool:
    """True when this process started with :data:`KEEP` (or stricter): freed blocks
    stay in the process for the next call (glibc only)."""
    if _glibc_version() is None:
        return False
    t = _tunables()
    try:
        return (int(t.get("glibc.malloc.mmap_max", "-1"), 0) == 0
                and int(t.get("glibc.malloc.arena_max", "0"), 0) == 1
                and int(t.get("glibc.malloc.trim_threshold", "0"), 0) >= 1 << 30)
    except ValueError:
        return False


def status() -> str:
    """One line for logs and reports."""
    state = huge_pages()
    pages = "huge pages for large blocks" if state == "on" else "4 KiB pages"
    if keeps_memory():
        return f"memory: {pages}, freed blocks kept for reuse"
    if state == "off":
        return (f"memory: {pages} (GLIBC_TUNABLES={TUNABLE} before starting Python "
                f"cuts the page faults of fresh buffers: diffcam.core.memory)")
    return f"memory: {pages}"
