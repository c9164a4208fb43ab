"""Thread limits: BLAS for small dense solves, torch's intra-op pool for the backbone and test-time refinement.

The estimators solve many small least-squares problems (tens to a few hundred unknowns). OpenBLAS splits even those
across its threads, which on a busy 2-core machine (a backbone, the flight stack) turns a 1 ms solve into tens of
milliseconds of waiting; one thread is both faster and kinder to the rest of the machine.

torch's intra-op pool (OpenMP) and OpenCV's thread pool are set once per process by ``use_threads`` where a command
or the node starts (the ``threads`` parameter), before the worker thread first runs torch: torch copies the process
setting into each thread the first time that thread runs a parallel operator. How the pool's idle workers wait is
an environment variable read when torch loads (``OMP_WAIT_POLICY``, which ``vi3_ros`` sets to passive; see its
``__init__``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None


def single_blas_thread() -> AbstractContextManager:
    """A context in which BLAS (numpy's and scipy's) runs on one thread; the libraries are found on first use."""
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")


def default_threads() -> int:
    """Two where this process may use two or more CPUs, else one: the default of ``use_threads``."""
    return min(2, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)


def use_threads(n: int) -> int:
    """Set torch's intra-op thread count and OpenCV's thread pool of the process to ``n`` (0: ``default_threads()``)
    and return it: with ``threads`` 1 the node's image work (tracking, the plane sweep) stays on one core.

    Call it once where work starts, on the thread that starts the workers, before they run torch; a thread that has
    already run a parallel torch operator keeps the count it had then. ValueError for a negative ``n``.
    """
    import cv2  # not at the top: the estimators use this module and never need torch or OpenCV
    import torch

    if n < 0:
        raise ValueError(f"threads must be >= 0 (0: automatic), got {n}")
    n = n or default_threads()
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    return n


def torch_thread_settings() -> dict:
    """What benchmarks report: ``threads`` (torch's intra-op count on this thread) and ``omp_wait_policy`` (the
    environment's ``OMP_WAIT_POLICY``; None when unset: spin, then sleep)."""
    import torch

    return {"threads": torch.get_num_threads(), "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY")}


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op thread count set to ``n`` for the block, then restored."""
    import torch

    old = torch.get_num_threads()
    if old != n:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        if old != n:
            torch.set_num_threads(old)
