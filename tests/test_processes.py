"""Several JAX processes (diffcam.apps.processes): the environment that asks for them, and
``diffcam psf --processes N``, which writes the file one process writes, and ends every
process, keeping the old output, when one of them dies."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from diffcam.apps.processes import distributed_settings
from diffcam.core.errors import DiffcamError
from diffcam.io import temporary_files

N = 96


def test_settings_from_the_environment():
    """JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID give the arguments
    of jax.distributed.initialize; a SLURM step of several tasks gives none (JAX reads
    SLURM's variables); one process, or JAX's address variable alone, asks for nothing;
    an incomplete or out-of-range set is an error that names what is wrong."""
    env = {"JAX_COORDINATOR_ADDRESS": "node1:6123", "JAX_NUM_PROCESSES": "4",
           "JAX_PROCESS_ID": "3"}
    assert distributed_settings(env) == {"coordinator_address": "node1:6123",
                                         "num_processes": 4, "process_id": 3}
    assert distributed_settings({"SLURM_STEP_NUM_TASKS": "8", "SLURM_PROCID": "5"}) == {}
    assert distributed_settings({"SLURM_STEP_NUM_TASKS": "1"}) is None
    assert distributed_settings({}) is None
    assert distributed_settings({"JAX_COORDINATOR_ADDRESS": "node1:6123"}) is None
    with pytest.raises(DiffcamError, match="not JAX_NUM_PROCESSES"):
        distributed_settings({**env, "JAX_NUM_PROCESSES": ""})
    with pytest.raises(DiffcamError, match="0 … JAX_NUM_PROCESSES − 1 = 3"):
        distributed_settings({**env, "JAX_PROCESS_ID": "4"})
    with pytest.raises(DiffcamError, match="integers"):
        distributed_settings({**env, "JAX_PROCESS_ID": "one"})


def test_temporary_files_are_the_ones_atomic_output_makes(tmp_path):
    """temporary_files(target) lists what atomic_output creates beside the target while
    it writes (and that alone: not other files of similar names)."""
    from diffcam.io import atomic_output

    target = tmp_path / "stack.tif"
    (tmp_path / ".stack.tmp-notmine.tif").write_bytes(b"")
    (tmp_path / ".other.tmp-0123abcd.tif").write_bytes(b"")
    assert temporary_files(target) == set()
    with atomic_output(target) as temp:
        assert temporary_files(target) == {Path(os.path.realpath(temp))}
    assert temporary_files(target) == set()


def test_bad_processes_fail_before_starting_any(tmp_path, capsys):
    """--processes 0, or --processes 2 with an output that cannot be written, is one
    error line (status 2) before any process starts."""
    from diffcam.apps.cli import main

    for args, message in [(["--processes", "0", "-o", str(tmp_path / "s.tif")],
                           "at least 1"),
                          (["--processes", "2", "-o", str(tmp_path / "no" / "s.tif")],
                           "does not exist")]:
        status = main(["psf", str(tmp_path / "phase.npz"), "--z1", "20mm", "--z2", "1mm",
                       *args])
        errors = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
        assert status == 2 and len(errors) == 1 and message in errors[0], errors


@pytest.fixture(scope="module")
def phase_file(tmp_path_factory):
    from diffcam.calibrate.phase.file import PhaseFile, save_phase
    from diffcam.model import random_diffuser

    path = tmp_path_factory.mktemp("processes") / "phase.npz"
    phase = np.asarray(random_diffuser(jax.random.key(3), (N, N), 4e-6, 532e-9, 40e-6))
    save_phase(path, PhaseFile(phase, 4e-6, 532e-9, 0.15e-3, {}))
    return path


def _psf(*args, **popen):
    return subprocess.Popen([sys.executable, "-m", "diffcam", "psf", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            **popen)


@pytest.mark.slow  # four runs of diffcam psf, two of them as two processes: 40 s
def test_two_processes_write_the_single_process_file(phase_file, tmp_path):
    """``diffcam psf … --processes 2`` writes the bytes ``diffcam psf …`` writes, as
    .npz and as .tif (7 depths: the last chunk padded), and prints one summary."""
    for suffix in (".npz", ".tif"):
        runs = {}
        for count in (1, 2):
            out = tmp_path / f"p{count}{suffix}"
            proc = _psf(phase_file, "--z1", "20mm:26mm:1mm", "--z2", "1mm", "--crop", "80",
                        "--processes", count, "-o", out)
            stdout, stderr = proc.communicate(timeout=300)
            assert proc.returncode == 0, stderr
            assert stdout.count("diffcam psf: 7 PSFs") == 1, stdout
            runs[count] = out.read_bytes()
        assert runs[1] == runs[2]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p1.npz", "p1.tif", "p2.npz",
                                                           "p2.tif"]


@pytest.mark.slow  # two runs of diffcam psf as two processes: 20 s
def test_verbose_two_processes_write_what_quiet_ones_write(phase_file, tmp_path):
    """``diffcam -v psf … --processes 2``: the processes join their run before ``-v``
    lists JAX's devices (``jax.distributed.initialize()`` refuses to run after that), and
    the file and the summary are those of the run without ``-v``; the device line and
    the wall time go to stderr."""
    runs = {}
    for flags in ((), ("-v",)):
        folder = tmp_path / f"run{len(flags)}"
        folder.mkdir()
        out = folder / "stack.tif"  # the same name: the summaries can be compared
        proc = subprocess.Popen([sys.executable, "-m", "diffcam", *flags, "psf",
                                 str(phase_file), "--z1", "20mm:26mm:1mm", "--z2", "1mm",
                                 "--crop", "80", "--processes", "2", "-o", "stack.tif"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                cwd=folder)
        stdout, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 0, stderr
        runs[flags] = out.read_bytes(), stdout, stderr
    (quiet, said, _), (loud, said_loud, told) = runs[()], runs[("-v",)]
    assert loud == quiet and said_loud == said and said.count("diffcam psf: 7 PSFs") == 1
    assert "error" not in told and "diffcam psf: JAX " in told, told
    assert told.rstrip().endswith(" s"), told


def _children(pid):
    """{JAX_PROCESS_ID: pid} of the processes ``pid`` started (Linux /proc)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            env = (entry / "environ").read_bytes().split(b"\0")
        except (OSError, IndexError):
            continue
        if ppid == pid:
            ranks = [v.split(b"=", 1)[1] for v in env if v.startswith(b"JAX_PROCESS_ID=")]
            found[int(ranks[0])] = int(entry.name)
    return found


def _written(out) -> int:
    """Bytes in the temporary file(s) beside ``out``."""
    return sum(p.stat().st_size for p in temporary_files(out) if p.exists())


@pytest.mark.slow  # three two-process runs, each ended after 20-25 s
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("victim", [1, 0, "launcher"])
def test_a_killed_process_ends_the_run_and_keeps_the_old_file(phase_file, tmp_path, victim):
    """SIGKILL to one of the two processes (1, or 0, the one writing the temporary file)
    once 10 of the 1201 PSFs are in the temporary file ends the run: the other process
    is ended, the command exits with status 2 and one line naming the killed process,
    the old .tif keeps its bytes and no temporary file is left (the launcher removes the
    one process 0 could not). SIGTERM to the command itself ends both processes, with
    the same guarantees."""
    out = tmp_path / "stack.tif"
    old = os.urandom(4096)
    out.write_bytes(old)
    proc = _psf(phase_file, "--z1", "20mm:80mm:0.05mm", "--z2", "1mm", "--processes", 2,
                "-o", out, env=dict(os.environ, DIFFCAM_PROGRESS="0"))
    deadline = time.monotonic() + 120
    while _written(out) < 10 * N * N * 4 and proc.poll() is None \
            and time.monotonic() < deadline:
        time.sleep(0.05)  # until process 0 has written 10 PSFs into its temporary file
    assert proc.poll() is None and _written(out), "the run did not start writing"
    children = _children(proc.pid)
    assert sorted(children) == [0, 1]
    if victim == "launcher":
        proc.send_signal(signal.SIGTERM)
    else:
        os.kill(children[victim], signal.SIGKILL)
    stdout, stderr = proc.communicate(timeout=60)
    errors = [line for line in stderr.splitlines() if "error:" in line]
    if victim == "launcher":
        assert proc.returncode == 128 + signal.SIGTERM, stderr
    else:
        assert proc.returncode == 2, stderr
        assert errors == [f"diffcam psf: error: process {victim} was killed by SIGKILL; "
                          f"nothing was written."], stderr
    assert "Traceback" not in stderr and "PSFs of" not in stdout
    assert not set(_children(proc.pid)) and all(
        not Path(f"/proc/{pid}").exists() for pid in children.values())
    assert out.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stack.tif"]


@pytest.mark.parametrize("status, runs_atexit", [(0, True), (2, True), (130, False)])
def test_end_process_keeps_status_output_and_exit_functions(status, runs_atexit):
    """end_process: the status is the process's, buffered output is written, and the
    atexit functions run (after an interrupt, 130, they do not)."""
    code = ("import atexit, sys; from diffcam.apps.processes import end_process; "
            "atexit.register(lambda: print('atexit ran')); print('buffered', end=' '); "
            f"sys.stderr.write('err'); end_process({status})")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == status
    assert r.stdout.split() == ["buffered"] + (["atexit", "ran"] if runs_atexit else [])
    assert r.stderr == "err"
