"""Worker: latest-wins mailbox, drop counting, survival of exceptions, synchronous mode."""

from __future__ import annotations

import threading

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
