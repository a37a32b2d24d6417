"""Fresh buffers and their page faults: whether this process gets huge pages and keeps
freed blocks for reuse (CPU, Linux, glibc).

XLA allocates every output and temporary of a jitted call afresh. glibc maps a block of
32 MiB or more (a 2048² complex64 field) afresh on every call and returns it when freed
(``mallopt(3)``, ``M_MMAP_THRESHOLD``), so the kernel zero-fills it on first touch, one
page fault per page: 8192 faults per 2048² field with 4 KiB pages, 16 with huge pages.

glibc asks the kernel for huge pages on its own blocks when the process starts with
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (glibc ≥ 2.35, transparent huge pages in
``madvise`` or ``always`` mode). A tunable is read when the process starts, so a
library cannot set it for itself: set it in the shell before starting Python, or in a
Jupyter kernel's ``env``:

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 diffcam demo

[`KEEP`][diffcam.core.memory.KEEP] also keeps freed blocks in the process (one malloc arena,
no ``mmap`` for blocks, no heap trimming), so that once the heap has grown a call faults no
page:

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1:glibc.malloc.arena_max=1:glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=17179869184 python run.py

The price: the heap grows by about one block per call for the first calls (XLA's
aligned requests do not fit a freed block of their own size), and the process keeps its
largest footprint until it exits. It suits a long run of one size, such as a fit of
many gradient steps. Neither setting changes a result;
[`status`][diffcam.core.memory.status] (printed by ``diffcam -v``) says which is in use.
What they save: ``python -m benchmarks.bench_fft`` and ``python -m benchmarks.bench_grad``
(``docs/fft.md``).
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
    mapping, or this process started with [`TUNABLE`][diffcam.core.memory.TUNABLE]);
    ``"off"``: they could, with [`TUNABLE`][diffcam.core.memory.TUNABLE] set before Python
    starts; ``"unavailable"``: not on this system."""
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
    """True when this process started with [`KEEP`][diffcam.core.memory.KEEP] (or stricter):
    freed blocks stay in the process for the next call (glibc only)."""
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
