"""One run at a time per output: an exclusive lock that a ``vi3`` command holds on its output from before it checks
it until the output is final, so that two runs onto one output never replace each other's work silently; the
second fails at once, naming the first.

The lock is ``fcntl.flock`` on a hidden file beside the output (``.NAME.vi3-lock``) that holds the owner's pid and
start time; the kernel drops the lock when its process ends, however it ends, so a killed run never blocks a later one.
The file is removed on release while still locked, and a run that locked a file that was removed meanwhile locks
the new one instead. (``filelock`` keeps its lock files in place and cannot name the holder.)
"""

from __future__ import annotations

import fcntl
import os
import time
from pathlib import Path
from types import TracebackType

from vi3_core.errors import DataError


class OutputBusy(DataError):
    """Another run holds the lock on the output; the message names it."""


def lock_path(output: str | Path) -> Path:
    """The lock file of ``output``: ``.NAME.vi3-lock`` in the same folder."""
    output = Path(output)
    return output.with_name(f".{output.name}.vi3-lock")


class OutputLock:
    """``with OutputLock(path, what="replay output"):`` holds the lock of ``path`` for the block; entering raises
    OutputBusy when another run holds it, OSError (its filename ``path``) when the lock file cannot be created."""

    def __init__(self, output: str | Path, *, what: str) -> None:
        self.output, self.what = Path(output), what
        self.path = lock_path(self.output)
        self._fd: int | None = None

    def __enter__(self) -> OutputLock:
        self.acquire()
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.release()

    def acquire(self) -> None:
        """Take the lock (see the class)."""
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as err:
                raise OSError(err.errno, err.strerror, str(self.output)) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 4096).decode(errors="replace").strip() or "another run"
                os.close(fd)
                raise OutputBusy(f"{self.what} {self.output} is being written by another run ({holder}); wait for "
                                 "it to end or choose another output") from None
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:  # its holder removed it between our open and our lock
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()}, started {time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode())
        self._fd = fd

    def release(self) -> None:
        """Remove the lock file and let the lock go (nothing when it is not held)."""
        if self._fd is None:
            return
        try:
            self.path.unlink()  # while locked: a run that opened it meanwhile sees it gone and takes a new one
        except FileNotFoundError:
            pass
        os.close(self._fd)  # unlocks
        self._fd = None
