"""Huge pages for fresh buffers (diffcam.core.memory): what the process is told is what
the kernel's page-fault counter shows, in fresh processes (glibc reads its tunables when
a process starts)."""

import json
import os
import subprocess
import sys

import pytest

from diffcam.core import memory

PROBE = r"""
import json, resource, sys
import jax, jax.numpy as jnp
from diffcam.core import memory
double = jax.jit(lambda x: x * 2)
x = jnp.ones((3072, 3072), jnp.complex64)   # 72 MiB: glibc serves it with mmap
faults = []
for _ in range(int(sys.argv[1])):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    double(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(json.dumps({"state": memory.huge_pages(), "status": memory.status(),
                  "keeps": memory.keeps_memory(),
                  "faults": faults[1:], "pages": 3072 * 3072 * 8 // resource.getpagesize()}))
"""


def _probe(tunables, calls=6):
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    if tunables:
        env["GLIBC_TUNABLES"] = tunables
    done = subprocess.run([sys.executable, "-c", PROBE, str(calls)], capture_output=True,
                          text=True, env=env, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def plain():
    """The probe with glibc's defaults."""
    return _probe(None)


@pytest.mark.skipif(memory.huge_pages() == "unavailable" or memory._thp_mode() == "always",
                    reason="needs glibc >= 2.35 and transparent huge pages in madvise mode")
def test_the_tunable_takes_the_page_faults_out_of_fresh_buffers(plain):
    huge = _probe(memory.TUNABLE)
    assert plain["state"] == "off" and memory.TUNABLE in plain["status"]
    assert huge["state"] == "on" and "huge pages" in huge["status"]
    # 4 KiB pages: every call's fresh 72 MiB output faults each of its pages in
    assert min(plain["faults"]) >= 0.9 * plain["pages"]
    # huge pages: 2 MiB each, 512 times fewer faults (a little more where the kernel
    # has no free huge page at hand)
    assert sorted(huge["faults"])[2] <= 0.05 * huge["pages"]
    # glibc cuts the variable at the first ':' in place; a tunable after it still counts
    assert _probe(f"glibc.malloc.perturb=0:{memory.TUNABLE}")["state"] == "on"


@pytest.mark.skipif((memory._glibc_version() or (0, 0)) < (2, 26),
                    reason="needs glibc's tunables (glibc >= 2.26)")
def test_keeping_freed_blocks_takes_every_page_fault_out(plain):
    """With KEEP the 72 MiB output a call frees becomes a later call's buffer: once the
    heap has grown (a block a call at first: XLA's aligned requests do not fit a freed
    block of their own size), calls fault no page at all."""
    kept = _probe(memory.KEEP, calls=48)
    assert kept["keeps"] and "kept for reuse" in kept["status"]
    # alone it settles within ~6 calls, beside other busy processes within ~20, and
    # there a later call still grows it now and then (3 of the last 24 on a loaded
    # machine); with glibc's defaults every call faults all its pages
    faulting = [f for f in kept["faults"][-24:] if f > 0.001 * kept["pages"]]
    assert len(faulting) <= 6, kept["faults"]
    assert not plain["keeps"] and "kept" not in plain["status"]


def test_the_state_is_read_from_the_start_environment(monkeypatch):
    """Setting the variable from Python does not give this process huge pages, so the
    report does not change."""
    before = memory.huge_pages()
    monkeypatch.setenv("GLIBC_TUNABLES", memory.TUNABLE)
    assert memory.huge_pages() == before


@pytest.mark.parametrize("tunables, keeps", [
    ({}, False),
    ({"glibc.malloc.mmap_max": "0", "glibc.malloc.arena_max": "1"}, False),
    ({"glibc.malloc.mmap_max": "0", "glibc.malloc.arena_max": "1",
      "glibc.malloc.trim_threshold": "0x40000000"}, True),
    ({"glibc.malloc.mmap_max": "0", "glibc.malloc.arena_max": "2",
      "glibc.malloc.trim_threshold": "17179869184"}, False),
    ({"glibc.malloc.mmap_max": "zero"}, False)])
def test_keeping_is_all_three_tunables(monkeypatch, tunables, keeps):
    """KEEP needs all three settings (a partial or unreadable one reports no reuse,
    and never raises: ``diffcam -v`` prints the status)."""
    monkeypatch.setattr(memory, "_tunables", lambda: tunables)
    if memory._glibc_version() is None:
        keeps = False
    assert memory.keeps_memory() is keeps
    assert ("kept for reuse" in memory.status()) is keeps
