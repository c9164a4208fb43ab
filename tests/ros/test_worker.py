"""Worker: latest-wins mailbox, drop counting, survival of exceptions, synchronous mode."""

from __future__ import annotations

import threading
import time

import pytest

from vi3_ros.worker import Worker


def test_latest_wins_and_replaced_counted():
    gate = threading.Event()
    started = threading.Event()
    done, replaced = [], []

    def handle(job):
        started.set()
        gate.wait(5)
        done.append(job)

    w = Worker(handle, on_error=lambda j, e: None, on_replaced=replaced.append)
    w.submit(0)
    assert started.wait(5)  # job 0 is running; 1..4 queue up in the one-slot mailbox
    for k in range(1, 5):
        w.submit(k)
    gate.set()
    assert w.wait_idle(5)
    w.stop()
    assert done == [0, 4]
    assert replaced == [1, 2, 3] and w.replaced == 3
    assert (w.submitted, w.processed, w.errors) == (5, 2, 0)


def test_exception_reported_and_worker_keeps_running():
    errors, done = [], []

    def handle(job):
        if job == "bad":
            raise ValueError("broken clip")
        done.append(job)

    w = Worker(handle, on_error=lambda j, e: errors.append((j, str(e))))
    for job in ("a", "bad", "b"):
        w.submit(job)
        assert w.wait_idle(5)
    w.stop()
    assert errors == [("bad", "broken clip")]
    assert done == ["a", "b"] and w.errors == 1 and w.processed == 3
    assert not w._thread.is_alive()
    with pytest.raises(RuntimeError, match="after stop"):
        w.submit("c")


def test_synchronous_mode_processes_every_job_in_order_on_caller_thread():
    seen = []
    w = Worker(lambda j: seen.append((j, threading.current_thread().name)), on_error=lambda j, e: None,
               synchronous=True)
    for k in range(10):
        w.submit(k)
    assert [j for j, _ in seen] == list(range(10))
    assert {name for _, name in seen} == {threading.current_thread().name}
    assert w.replaced == 0 and w.processed == 10 and w._thread is None


def test_a_failing_error_report_does_not_kill_the_worker_and_stop_does_not_wait_out_a_long_job():
    """The node's shutdown: reporting an error raises too (publishing on a dead context); the worker goes on with
    the newer job; ``stop(timeout)`` returns after the timeout while a job is still running."""
    gate, started, done = threading.Event(), threading.Event(), []

    def handle(job):
        if job == "bad":
            raise RuntimeError("publish on a shut-down context")
        if job == "slow":
            started.set()
            gate.wait(10)
        done.append(job)

    def on_error(job, exc):
        raise RuntimeError("publish on a shut-down context")

    w = Worker(handle, on_error=on_error)
    w.submit("bad")
    assert w.wait_idle(5)
    w.submit("next")
    assert w.wait_idle(5) and done == ["next"] and (w.errors, w.unreported) == (1, 1)
    w.submit("slow")
    assert started.wait(5)
    t0 = time.monotonic()
    w.stop(timeout=0.2)
    assert time.monotonic() - t0 < 1.0 and w.alive
    gate.set()
    w._thread.join(5)
    assert not w.alive
