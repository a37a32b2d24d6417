"""Fresh buffers and their page faults: whether this process gets huge pages (CPU,
Linux, glibc).

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

Huge pages change speed, never results. :func:`status` (printed by ``diffcam -v``)
says whether they are in use.
"""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path

__all__ = ["huge_pages", "status", "TUNABLE"]

TUNABLE = "glibc.malloc.hugetlb=1"
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


def _start_environment() -> dict[str, str]:
    """The environment this process started with (what glibc read), not ``os.environ``,
    which Python code may have changed since."""
    try:
        raw = Path("/proc/self/environ").read_bytes()
    except OSError:
        return dict(os.environ)
    pairs = (item.split(b"=", 1) for item in raw.split(b"\0") if b"=" in item)
    return {k.decode(errors="replace"): v.decode(errors="replace") for k, v in pairs}


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
    tunables = _start_environment().get("GLIBC_TUNABLES", "")
    asked = re.search(r"(^|:)glibc\.malloc\.hugetlb=([12])($|:)", tunables)
    return "on" if asked else "off"


def status() -> str:
    """One line for logs and reports."""
    state = huge_pages()
    if state == "on":
        return "memory: huge pages for large blocks"
    if state == "off":
        return (f"memory: 4 KiB pages (GLIBC_TUNABLES={TUNABLE} before starting Python "
                f"cuts the page faults of fresh buffers: diffcam.core.memory)")
    return "memory: 4 KiB pages"
