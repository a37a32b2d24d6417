"""Writing outputs atomically: `check_output_path` before any work, then
`atomic_output` (a temporary file beside the target, fsynced and moved into place
with ``os.replace``), so an existing file is either untouched or wholly replaced, with
SIGTERM and SIGINT handled on the way."""

from __future__ import annotations

import contextlib
import glob
import os
import secrets
import signal
import sys
import threading
from functools import partial
from pathlib import Path
from typing import Iterator, Sequence

from diffcam.core.errors import DiffcamError

__all__ = ["check_output_path", "make_output_folder", "atomic_output", "Terminated",
           "temporary_files", "interrupts_as_keyboard_interrupt"]


def check_output_path(path: str | os.PathLike, *,
                      suffixes: Sequence[str] | None = None) -> Path:
    """Check that a file can be written at ``path``; call it before any work starts.

    An output problem should cost nothing: a stack that took an hour to compute must
    not fail at its first write. The checks are: ``path`` is not a folder, its folder
    exists and is a folder, a new file can be created in it (a probe file is created and
    removed, which also catches read-only file systems and root on them), and an
    existing file there is a regular, writable file.

    Args:
        path: the output file.
        suffixes: if given, the accepted file name endings, e.g. ``(".npz",)``.

    Returns:
        ``path`` as a `Path`.

    Raises:
        DiffcamError: naming the path and what is wrong with it.
    """
    try:
        path = Path(os.fspath(path))
    except TypeError:
        raise DiffcamError(f"an output path must be a str or os.PathLike, got "
                           f"{path!r}.") from None
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise DiffcamError(f"{path}: the output must end in {' or '.join(suffixes)}.")
    if path.is_dir():
        raise DiffcamError(f"{path}: is a folder; give a file name inside it.")
    target = Path(os.path.realpath(path))  # a symlink is written through, not replaced
    folder = target.parent
    if not folder.exists():
        raise DiffcamError(f"{path}: the output folder {folder} does not exist; create it "
                           f"first.")
    if not folder.is_dir():
        raise DiffcamError(f"{path}: {folder} is not a folder.")
    if target.exists():
        if not target.is_file():
            raise DiffcamError(f"{path}: exists and is not a regular file; remove it or "
                               f"choose another name.")
        # the mode bits too: os.access says yes to root for a read-only file
        if not os.access(target, os.W_OK) or not target.stat().st_mode & 0o222:
            raise DiffcamError(f"{path}: the existing file is read-only; diffcam will not "
                               f"replace it. Make it writable or choose another name.")
    try:
        os.close(_create_temp(target, probe=True)[0])
    except OSError as err:
        raise DiffcamError(f"{path}: cannot create files in {folder} "
                           f"({err.strerror or err}); choose another folder or fix its "
                           f"permissions.") from None
    return path


def make_output_folder(path: str | os.PathLike) -> Path:
    """Create the folder ``path`` (with its parents) that a command writes its files
    into, or say in one line why it cannot be one; call it before any work starts.

    Raises:
        DiffcamError: an empty path (write ``.`` for the working folder), a file where
            the folder or one of its parents should be, or a folder that cannot be
            created or refuses new files (a probe file is created and removed).
    """
    try:
        text = os.fspath(path)
    except TypeError:
        raise DiffcamError(f"an output folder must be a str or os.PathLike, got "
                           f"{path!r}.") from None
    if not str(text).strip():
        raise DiffcamError("the output folder is an empty name; give a folder (. for the "
                           "working folder).")
    path = Path(text)
    for part in (path, *path.parents):
        if part.exists() and not part.is_dir():
            where = "" if part == path else f" ({part} is not a folder)"
            raise DiffcamError(f"{path}: a file stands where the output folder should "
                               f"be{where}; name a folder.")
    try:
        path.mkdir(parents=True, exist_ok=True)
        os.close(_create_temp(path / "folder", probe=True)[0])
    except OSError as err:
        raise DiffcamError(f"{path}: cannot create files in this folder "
                           f"({err.strerror or err}); choose another folder or fix its "
                           f"permissions.") from None
    return path


@contextlib.contextmanager
def atomic_output(*paths: str | os.PathLike) -> Iterator:
    """Write files so that each target is either untouched or wholly replaced.

    Yields a temporary path beside each target (in the same folder, with the target's
    suffix, so writers that dispatch on it work): one path for one target, a tuple for
    several. When the block ends normally every temporary file is fsynced and moved
    over its target with ``os.replace`` (atomic on POSIX and Windows), then the folder
    is fsynced. If the block raises anything, ``KeyboardInterrupt`` included, the
    temporary files are removed and the targets keep their old bytes.

    SIGTERM: while the block runs in the main thread and SIGTERM has its default
    action, a SIGTERM raises [`Terminated`][diffcam.io.writing.Terminated] inside the block
    instead of killing the process at once; the temporary files are removed, the default
    action is restored and the signal is raised again, so the process still ends as killed
    by SIGTERM. A SIGTERM that arrives while the files are being moved into place waits
    until they are (several targets are replaced one after another in that window, so only a
    hard kill can fall between them). Nothing is installed outside the block; a handler of
    the caller's is left alone. A hard kill (SIGKILL, power loss) can leave a temporary
    ``.name.tmp-*`` file, never a half-written target.

    New files get the permissions ``0o666 & ~umask``, like any file ``open`` creates.

    Raises:
        DiffcamError: a target cannot be written
            ([`check_output_path`][diffcam.io.writing.check_output_path]), before the block
            runs.
    """
    if not paths:
        raise DiffcamError("atomic_output needs at least one output path.")
    targets = [Path(os.path.realpath(check_output_path(p))) for p in paths]
    guard = _TermGuard.install()
    temps: list[Path] = []
    try:
        try:
            for target in targets:
                fd, temp = _create_temp(target)
                os.close(fd)
                temps.append(temp)
            yield temps[0] if len(temps) == 1 else tuple(temps)
            if guard is not None:
                guard.deferring = True  # a SIGTERM now waits until the files are in place
                if guard.received:  # the block swallowed Terminated: its output is partial
                    raise Terminated()
            for temp in temps:
                _fsync(temp)
            for temp, target in zip(temps, targets):
                os.replace(temp, target)
            for folder in dict.fromkeys(t.parent for t in targets):
                _fsync(folder)
        except BaseException:
            if guard is not None:
                guard.deferring = True
            for temp in temps:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(temp)
            raise
    finally:
        if guard is not None:
            guard.restore()


class Terminated(SystemExit):
    """SIGTERM arrived while [`atomic_output`][diffcam.io.writing.atomic_output] was
    writing.

    A ``SystemExit`` (exit status 143, as a shell reports SIGTERM), so ``except
    Exception`` does not swallow it. [`atomic_output`][diffcam.io.writing.atomic_output]
    re-raises the signal itself once its temporary files are gone, so this is seen only if
    that signal is blocked.
    """

    def __init__(self) -> None:
        super().__init__(128 + signal.SIGTERM)


class _TermGuard:
    """SIGTERM as `Terminated` for the duration of one `atomic_output`."""

    def __init__(self) -> None:
        self.deferring = False  # cleaning up or committing: record, do not raise
        self.received = False

    @classmethod
    def install(cls) -> "_TermGuard | None":
        if threading.current_thread() is not threading.main_thread():
            return None  # signal handlers can only be set from the main thread
        if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
            return None  # the caller (or an outer atomic_output) handles SIGTERM
        guard = cls()
        signal.signal(signal.SIGTERM, guard._handle)
        guard._dropped = _redeliver_dropped(Terminated, guard._again)
        guard._dropped.__enter__()
        return guard

    def _handle(self, signum, frame) -> None:
        first = not self.received
        self.received = True
        if first and not self.deferring:
            self.deferring = True
            raise Terminated()

    def _again(self) -> None:
        """Python dropped the `Terminated` raised by `_handle`: as if the
        signal had not come yet, and it comes again."""
        self.received = self.deferring = False
        _send_again(signal.SIGTERM)

    def restore(self) -> None:
        self._dropped.__exit__(None, None, None)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        if self.received:
            signal.raise_signal(signal.SIGTERM)  # now with its default action: exit


@contextlib.contextmanager
def interrupts_as_keyboard_interrupt() -> Iterator[None]:
    """SIGINT raises ``KeyboardInterrupt`` as Python's default handler does, and a
    ``KeyboardInterrupt`` that Python drops is delivered again (`_redeliver_dropped`).
    Installed only from the main thread and only over Python's default handler."""
    main = threading.current_thread() is threading.main_thread()
    if not main or signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    with _redeliver_dropped(KeyboardInterrupt, lambda: _send_again(signal.SIGINT)):
        yield


@contextlib.contextmanager
def _redeliver_dropped(kind: type[BaseException], again) -> Iterator[None]:
    """While the block runs, an exception of ``kind`` that Python prints as "Exception
    ignored" and drops calls ``again()`` instead of being printed.

    A signal handler's exception is dropped so when the signal lands in a garbage-
    collector callback (JAX registers one), a ``__del__`` or a weakref callback; the run
    would then go on as if no signal had come (seen in CI). ``again`` sends it anew.
    """
    previous = sys.unraisablehook

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, kind):
            again()
        else:
            previous(unraisable)

    sys.unraisablehook = hook
    try:
        yield
    finally:
        sys.unraisablehook = previous


def _send_again(signum: int) -> None:
    """Send ``signum`` to the main thread in 50 ms (after the code that dropped it).

    To the thread, not the process: the kernel may hand a process's signal to any of
    its threads (XLA's among them), and a blocking call in the main thread then runs to
    its end before Python's handler runs (a test's 2 s sleep, once in a full run)."""
    if hasattr(signal, "pthread_kill"):
        send = partial(signal.pthread_kill, threading.main_thread().ident, signum)
    else:  # Windows
        send = partial(os.kill, os.getpid(), signum)
    timer = threading.Timer(0.05, send)
    timer.daemon = True
    timer.start()


def _create_temp(target: Path, *, probe: bool = False) -> tuple[int, Path]:
    """Create an empty file beside ``target`` with mode ``0o666 & ~umask`` (unlike
    ``tempfile.mkstemp``'s 0o600). A probe is removed at once."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    for _ in range(100):
        kind = "probe" if probe else "tmp"
        temp = target.with_name(f".{target.stem}.{kind}-{secrets.token_hex(4)}{target.suffix}")
        try:
            fd = os.open(temp, flags, 0o666)
        except FileExistsError:
            continue
        if probe:
            os.unlink(temp)
        return fd, temp
    raise FileExistsError(f"no free temporary name beside {target}")


def temporary_files(target: str | os.PathLike) -> set[Path]:
    """The temporary files [`atomic_output`][diffcam.io.writing.atomic_output] has beside
    ``target`` now: a hard-killed writer leaves its own behind, and whoever ran it (a
    launcher of several processes) removes the ones that were not there before."""
    target = Path(os.path.realpath(target))
    hex8 = "[0-9a-f]" * 8  # secrets.token_hex(4), as _create_temp names them
    pattern = f".{glob.escape(target.stem)}.tmp-{hex8}{glob.escape(target.suffix)}"
    return set(target.parent.glob(pattern))


def _fsync(path: Path) -> None:
    """Flush a file's (or a folder's entries') data to the disk, where the OS allows."""
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_BINARY", 0))
    except OSError:  # folders cannot be opened on Windows
        return
    try:
        os.fsync(fd)
    except OSError:
        pass  # some file systems refuse fsync on a folder
    finally:
        os.close(fd)
