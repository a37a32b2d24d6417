"""The allocator policy (diffcam.core.memory): a jitted call's fresh output block comes
from memory already in the process instead of new pages, read off the kernel's own
page-fault counter, in fresh processes (the policy is a per-process setting)."""

import json
import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
    reason="the policy is glibc's (elsewhere it reports 'unsupported', tested below)")

# 72 MiB per output: above the 64 MiB that glibc's per-thread heaps can hold, so only
# the arena setting keeps it off mmap
PROBE = r"""
import json, resource, sys
import diffcam
from diffcam.core import memory
import jax, jax.numpy as jnp
import numpy as np
double = jax.jit(lambda x: x * 2)
x = jnp.ones((3072, 3072), jnp.complex64)
faults = []
for _ in range(24):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    double(x).block_until_ready()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()
held = rss()
released = memory.release()
print(json.dumps({"policy": memory.keep_freed_memory(), "status": memory.status(),
                  "faults": faults, "pages": 3072 * 3072 * 8 // resource.getpagesize(),
                  "released": released, "rss_drop": held - rss()}))
"""


def _probe(**env):
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True,
                          env={**os.environ, **env}, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1]), done.stderr


def test_kept_memory_takes_the_page_faults_out_of_every_call():
    kept, _ = _probe(DIFFCAM_MALLOC="keep")
    system, _ = _probe(DIFFCAM_MALLOC="system")
    assert kept["policy"] == "keep" and "kept" in kept["status"]
    assert system["policy"] == "system"
    # glibc's defaults: every call's 72 MiB output is fresh pages, one fault per page
    assert min(system["faults"]) >= 0.9 * system["pages"]
    # kept: once the heap's holes have merged (about 10 calls here, more under load:
    # docs of diffcam.core.memory), a freed block serves the next call
    assert sorted(kept["faults"][-12:])[6] <= 0.02 * kept["pages"]


def test_release_hands_the_kept_memory_back():
    kept, _ = _probe(DIFFCAM_MALLOC="keep")
    assert kept["released"] and kept["rss_drop"] >= 3072 * 3072 * 8 // 2


def test_an_unknown_setting_warns_and_leaves_the_defaults():
    result, stderr = _probe(DIFFCAM_MALLOC="fast")
    assert result["policy"] == "system"
    assert "DIFFCAM_MALLOC is 'keep' or 'system', not 'fast'" in stderr
