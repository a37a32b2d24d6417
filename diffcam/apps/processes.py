"""One command run as several JAX processes: ``diffcam psf --processes N``, or a cluster's
launcher (SLURM's ``srun``) starting one ``diffcam psf`` per task.

The engine is JAX's multi-controller runtime: each process calls
``jax.distributed.initialize()``, ``jax.devices()`` then lists every process's devices,
and `diffcam.model.stack.psf_stack` shards the depth axis over all of them. This
module only starts the processes and reads their environment:

- **Environment** (`distributed_settings`): ``JAX_COORDINATOR_ADDRESS`` (host:port
  of process 0, the variable ``jax.distributed.initialize()`` reads itself),
  ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID``; or, without them, a SLURM job step of
  several tasks (``srun``), whose variables ``jax.distributed.initialize()`` reads.
- **One machine** (`run_processes`): N copies of the command, process 0 on the
  terminal (progress bar, summary) and the others silent. They are not bound to CPUs:
  on a machine others use too, bound processes ran slower than unbound ones
  (benchmarks/bench_distributed.py). The first process to fail ends the others (SIGTERM, then SIGKILL
  after `GRACE` seconds); one line says which process failed and why, and
  temporary files the run left beside its outputs are removed, so an existing output
  keeps its old bytes.

A process that fails after ``jax.distributed.initialize()`` ends with ``os._exit``
(`end_process`): a normal interpreter exit would wait in JAX's shutdown barrier
for peers that are blocked in a collective, until the heartbeat timeout (100 s) aborts
it.
"""

from __future__ import annotations

import atexit
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Mapping, Sequence

from diffcam.core.errors import DiffcamError
from diffcam.io import temporary_files, Terminated

__all__ = ["distributed_settings", "initialize_from_environment", "run_processes",
           "report_error", "in_distributed_run", "worker_env", "free_port", "GRACE",
           "end_process"]

ADDRESS, COUNT, RANK = "JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"
ERRORS = "DIFFCAM_PROCESS_ERRORS"  # set by run_processes: a folder for the error lines
GRACE = 10.0  # seconds between SIGTERM and SIGKILL when a run is ended
_POLL = 0.05  # seconds between looks at the processes


def distributed_settings(env: Mapping[str, str] | None = None) -> dict | None:
    """The ``jax.distributed.initialize`` arguments the environment asks for, or
    ``None`` for a run of one process.

    ``JAX_COORDINATOR_ADDRESS`` with ``JAX_NUM_PROCESSES`` and ``JAX_PROCESS_ID`` give
    them explicitly; a SLURM job step of several tasks (``SLURM_STEP_NUM_TASKS`` > 1, set
    by ``srun``) gives ``{}``: JAX reads SLURM's variables itself.

    Raises:
        DiffcamError: the variables are incomplete or not integers in range.
    """
    env = os.environ if env is None else env
    given = [k for k in (ADDRESS, COUNT, RANK) if env.get(k)]
    if not given:
        tasks = env.get("SLURM_STEP_NUM_TASKS", "1")
        return {} if tasks.isdigit() and int(tasks) > 1 else None
    if len(given) == 1 and given[0] == ADDRESS:
        return None  # JAX's own variable alone: a single process that set it elsewhere
    if len(given) < 3:
        missing = sorted({ADDRESS, COUNT, RANK} - set(given))
        raise DiffcamError(f"{', '.join(given)} set but not {', '.join(missing)}: a run of "
                           f"several processes needs all three (or none).")
    try:
        count, rank = int(env[COUNT]), int(env[RANK])
    except ValueError:
        raise DiffcamError(f"{COUNT}={env[COUNT]!r} and {RANK}={env[RANK]!r} must be "
                           f"integers.") from None
    if count < 1 or not 0 <= rank < count:
        raise DiffcamError(f"{RANK}={rank} must be in 0 … {COUNT} − 1 = {count - 1}.")
    host, _, port = env[ADDRESS].strip().rpartition(":")
    if not host.strip("[]") or not (port.isascii() and port.isdigit()
                                    and 0 < int(port) < 65536):
        raise DiffcamError(f"{ADDRESS}={env[ADDRESS]!r:.60} must be host:port (process 0's "
                           f"address and a TCP port 1 … 65535, e.g. node1:6123).")
    return {"coordinator_address": env[ADDRESS], "num_processes": count,
            "process_id": rank}


def initialize_from_environment() -> bool:
    """``jax.distributed.initialize()`` as `distributed_settings` says, with gloo
    collectives for CPU devices; call it before any other JAX call. Returns whether
    this process is one of several."""
    settings = distributed_settings()
    if settings is None:
        return False
    import jax

    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(**settings)
    return jax.process_count() > 1


def in_distributed_run() -> bool:
    """Whether this process is one of several in a ``jax.distributed`` run."""
    if "jax" not in sys.modules:
        return False
    import jax

    return jax.distributed.is_initialized() and jax.process_count() > 1


def end_process(status: int) -> None:
    """End a ``diffcam`` command's process with ``status``, without the interpreter's
    teardown unless it is one process of a successful ``jax.distributed`` run.

    The teardown (finalising modules, JAX's client and its threads) costs 0.25 s on 2
    cores after any command and does nothing a command needs: its outputs are written,
    fsynced and moved into place (`diffcam.io.atomic_output`) before this runs,
    and the functions registered with `atexit` (FFTW's wisdom, logging) run
    first. After an interrupt (status 130) the teardown is also unsafe: XLA's threads
    may still run the interrupted computation, and tearing the interpreter down under
    them crashed with SIGSEGV in about one run of five (an interrupted ``diffcam
    psf``). A failed process of a ``jax.distributed`` run must not wait in JAX's
    shutdown barrier (module docstring); a successful one does, with its peers.
    """
    sys.stdout.flush()
    sys.stderr.flush()
    if status == 0 and in_distributed_run():
        sys.exit(status)
    if status != 130:
        _ignore_late_interrupts()
        atexit._run_exitfuncs()  # what a normal exit would run, teardown aside
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(status)


def _ignore_late_interrupts() -> None:
    """SIGINT from here on is ignored: the command's work is over, and a
    ``KeyboardInterrupt`` raised inside an `atexit` function (JAX's own clean-up) would
    print a traceback on the way out."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def report_error(command: str, message: str) -> None:
    """Say what went wrong in one line: on stderr, prefixed by the process index in a
    run of several processes; under `run_processes`, in a file it reads (it
    prints one line for the whole run)."""
    folder = os.environ.get(ERRORS)
    if folder:  # run_processes started this process, and set its JAX_PROCESS_ID
        line = message.splitlines()[0] if message else "failed"
        Path(folder, f"{os.environ[RANK]}.txt").write_text(f"{time.time_ns()} {line}")
        return
    where = ""
    if in_distributed_run():
        import jax

        where = f"process {jax.process_index()}: " if jax.process_index() else ""
    print(f"diffcam {command}: error: {where}{message}", file=sys.stderr)


def free_port() -> int:
    """A TCP port on localhost that is free now (for process 0's coordinator)."""
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def worker_env(address: str, count: int, rank: int) -> dict[str, str]:
    """The environment of process ``rank`` of ``count`` whose process 0 listens at
    ``address`` (host:port): this process's, with the variables
    `distributed_settings` reads."""
    return dict(os.environ, **{ADDRESS: address, COUNT: str(count), RANK: str(rank)})


def _start(argv: Sequence[str], count: int, errors: str) -> list[subprocess.Popen]:
    address = f"localhost:{free_port()}"
    procs = []
    for rank in range(count):
        env = dict(worker_env(address, count, rank), **{ERRORS: errors})
        quiet = None if rank == 0 else subprocess.DEVNULL
        procs.append(subprocess.Popen([sys.executable, "-m", "diffcam", *argv], env=env,
                                      stdout=quiet, stderr=quiet))
    return procs


def _stop(procs: list[subprocess.Popen]) -> None:
    """SIGTERM every running process, SIGKILL what still runs `GRACE` s later."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + GRACE
    for p in procs:
        try:
            p.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _cause(procs, failed: list[int], errors: str) -> str:
    """One line for the failure that ended the run: a process killed by a signal, else
    the earliest error a process reported (its peers' errors follow from it)."""
    for rank in failed:
        code = procs[rank].returncode
        if code < 0:
            return (f"process {rank} was killed by {signal.Signals(-code).name}; nothing "
                    f"was written.")
    reports = []
    for rank in failed:
        path = Path(errors, f"{rank}.txt")
        if path.exists():
            stamp, _, line = path.read_text().partition(" ")
            reports.append((int(stamp), rank, line))
    if not reports:
        return f"process {failed[0]} ended with status {procs[failed[0]].returncode}."
    _, rank, line = min(reports)
    return line if len(procs) == 1 else f"process {rank}: {line}"


def run_processes(command: str, argv: Sequence[str], count: int,
                  outputs: Sequence[str | os.PathLike] = ()) -> int:
    """Run ``diffcam ARGV`` as ``count`` processes of one JAX run on this machine.

    Args:
        command: the subcommand, for messages (``"psf"``).
        argv: the command line, as given to ``diffcam``.
        count: number of processes (≥ 1).
        outputs: the files the run writes; temporary files a failed run leaves beside
            them are removed.

    Returns:
        0 when every process succeeds; else 2, with one line on stderr (Ctrl-C and
        SIGTERM reach the caller as ``KeyboardInterrupt`` and
        `Terminated`, after the processes are ended).
    """

    before = {p for o in outputs for p in temporary_files(o)}
    status = 2
    with tempfile.TemporaryDirectory(prefix="diffcam-errors-") as errors:
        procs = _start(argv, count, errors)
        previous = _on_sigterm()
        try:
            while all(p.poll() in (None, 0) for p in procs):
                if all(p.poll() == 0 for p in procs):
                    status = 0
                    return 0
                time.sleep(_POLL)
            failed = [r for r, p in enumerate(procs) if p.poll() not in (None, 0)]
            _stop(procs)
            print(f"diffcam {command}: error: {_cause(procs, failed, errors)}",
                  file=sys.stderr)
            return status
        finally:
            _stop(procs)
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
            if status:
                for path in {p for o in outputs for p in temporary_files(o)} - before:
                    path.unlink(missing_ok=True)


def _on_sigterm():
    """SIGTERM to the launcher raises ``io.Terminated`` (so its processes are ended and
    its temporary files removed); returns the handler to restore, or ``None``."""
    import threading


    if threading.current_thread() is not threading.main_thread():
        return None

    def handle(signum, frame):
        raise Terminated()

    return signal.signal(signal.SIGTERM, handle)
