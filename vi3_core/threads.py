"""Thread limits for small dense numerical work.

The estimators solve many small least-squares problems (tens to a few hundred unknowns). OpenBLAS splits even those
across its threads, which on a busy 2-core machine (a backbone, the flight stack) turns a 1 ms solve into tens of
milliseconds of waiting; one thread is both faster and kinder to the rest of the machine.
"""

from __future__ import annotations

from contextlib import AbstractContextManager

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None


def single_blas_thread() -> AbstractContextManager:
    """A context in which BLAS (numpy's and scipy's) runs on one thread; the libraries are found on first use."""
    global _controller
    if _controller is None:
        _controller = ThreadpoolController()
    return _controller.limit(limits=1, user_api="blas")
