"""One writer per directory: an exclusive OS lock on a file in it, `RUN_DIR/.lock` while a run trains,
`EXP/.sweep.lock` while a sweep runs on an experiment directory (the package's one lock implementation).

`mcrl train`, `mcrl train --resume`, a vmapped group and every sweep backend take a run's lock for each run they
write (`mcrl.run.member.open_member`, and the sweep driver for the files a remote worker ships back), before
anything is written; `eval`, `render`, `plot` and `report` only read and take none. It is `flock` on an open file:
the kernel drops it when the process ends, however it ends (kill -9 too), so it is never stale. The file holds the
holder's pid and command line for the message a second writer gets (`Locked.holder`); it stays behind after the
run, unlocked (removing it would let two writers lock two different files).
"""
from __future__ import annotations

import fcntl
import os
import sys
from pathlib import Path

from mcrl.errors import MCRLError
from mcrl.run import rundir

_holder: str | None = None  # what this process says it is, in the lock file (default: its command line)


def describe_holder(text: str) -> None:
    """Name this process in the locks it takes (a sweep worker: which sweep it belongs to)."""
    global _holder
    _holder = text


def _command_line() -> str:
    argv = [os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python", *sys.argv[1:]]
    return " ".join(argv)[:160]


class Locked(MCRLError):
    """Another process holds the lock; `holder` is what it wrote into the lock file ("pid 123 (mcrl train ...)")."""

    def __init__(self, message: str, directory: Path, holder: str):
        super().__init__(message)
        self.directory, self.holder = directory, holder


class RunLock:
    """A held lock; `release` (or the end of the process) frees it."""

    def __init__(self, run_dir: Path, fd: int):
        self.run_dir, self._fd = run_dir, fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the last descriptor of the open file drops the flock
            self._fd = None

    def __enter__(self) -> "RunLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def holder_of(directory: Path | str, file: str = rundir.LOCK) -> str:
    """The holder's line from the lock file ('' when none was written)."""
    try:
        return (Path(directory) / file).read_text().strip()
    except OSError:
        return ""


def _refused(directory: Path, file: str) -> Locked:
    holder = holder_of(directory, file) or "another process"
    if file == rundir.LOCK:
        msg = (f"{directory} is being written by {holder}: one writer per run; wait for it to end or stop it "
               "(`mcrl eval`, `render`, `plot` and `report` may read the run meanwhile)")
    else:
        msg = f"{directory / file} is held by {holder}: wait for it to end or stop it"
    return Locked(msg, directory, holder)


def check_free(directory: Path | str, file: str = rundir.LOCK) -> None:
    """Raise the `Locked` error `acquire` would if another process holds the lock; creates nothing (a group checks
    all its runs before it writes into any, a sweep before it starts a run)."""
    try:
        fd = os.open(Path(directory) / file, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return  # no lock file: no holder
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        raise _refused(Path(directory), file) from None
    finally:
        os.close(fd)


def acquire(directory: Path | str, file: str = rundir.LOCK) -> RunLock:
    """Lock `directory` (made if missing) through `file` in it for this process, or raise `Locked` naming the
    process that holds it."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    fd = os.open(directory / file, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)  # opened, not truncated
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        raise _refused(directory, file) from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"pid {os.getpid()} ({_holder or _command_line()})\n".encode(), 0)
    return RunLock(directory, fd)
