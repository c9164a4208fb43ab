"""A background worker with a latest-wins mailbox (one slot), so that heavy per-clip work never blocks the
callbacks that feed it and a slow worker always processes the newest clip.

``Worker(handle, on_error=...)`` runs ``handle(job)`` on its own thread. ``submit`` puts a job in the mailbox;
a job still waiting there is replaced and counted in ``replaced`` (``on_replaced(old_job)`` is told). An exception
in ``handle`` is passed to ``on_error(job, exc)`` and the thread goes on with the next job.

``synchronous=True`` runs ``handle`` inside ``submit`` instead (no thread, nothing replaced): replay uses it so
that every clip is processed, deterministically, in bag time.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

_EMPTY = object()


class Worker:
    """Latest-wins worker. Counters: ``submitted``, ``processed``, ``replaced``, ``errors``, ``unreported`` (errors
    whose ``on_error`` raised too) (ints, read any time)."""

    def __init__(self, handle: Callable[[Any], None], *, on_error: Callable[[Any, BaseException], None],
                 on_replaced: Callable[[Any], None] | None = None, synchronous: bool = False,
                 name: str = "vi3-worker") -> None:
        self._handle = handle
        self._on_error = on_error
        self._on_replaced = on_replaced
        self.synchronous = synchronous
        self.submitted = self.processed = self.replaced = self.errors = self.unreported = 0
        self._slot: Any = _EMPTY
        self._cond = threading.Condition()
        self._stopping = False
        self._busy = False
        self._thread: threading.Thread | None = None
        if not synchronous:
            self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
            self._thread.start()

    def submit(self, job: Any) -> None:
        """Hand over a job; in threaded mode returns at once, replacing a job that is still waiting."""
        if self.synchronous:
            self.submitted += 1
            self._run(job)
            return
        old = _EMPTY
        with self._cond:
            if self._stopping:
                raise RuntimeError("Worker.submit after stop()")
            self.submitted += 1
            if self._slot is not _EMPTY:
                old = self._slot
                self.replaced += 1
            self._slot = job
            self._cond.notify_all()
        if old is not _EMPTY and self._on_replaced is not None:
            self._on_replaced(old)

    def wait_idle(self, timeout: float | None = None) -> bool:
        """Block until the mailbox is empty and no job is running; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._slot is _EMPTY and not self._busy, timeout)

    @property
    def alive(self) -> bool:
        """Whether the thread is still running (a job outlived ``stop``'s timeout)."""
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout: float | None = 5.0) -> None:
        """Discard a waiting job and end the thread once the running job is done, waiting for that at most
        ``timeout`` s (None: as long as it takes); the thread is a daemon and does not hold up the process."""
        with self._cond:
            self._stopping = True
            self._slot = _EMPTY
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self, job: Any) -> None:
        try:
            self._handle(job)
        except Exception as exc:  # the worker must survive any failure of one job
            self.errors += 1
            try:
                self._on_error(job, exc)
            except Exception:  # reporting failed too (e.g. publishing after the node shut down): nowhere to report
                self.unreported += 1
        finally:
            self.processed += 1

    def _loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._slot is not _EMPTY or self._stopping)
                if self._stopping:
                    return
                job, self._slot, self._busy = self._slot, _EMPTY, True
            try:
                self._run(job)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()
