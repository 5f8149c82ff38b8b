"""The CPU stages run with one BLAS thread, so that a part's mesh does not depend on the machine.

OpenBLAS divides a matrix product among its threads differently for each thread count, and the sums
then differ in their last bits.  In the registration's M-step, ``C.T @ (P1 * C)`` is a (64 x M) by (M x 64)
product. For M = 4080 (a learned cloud after its outliers are removed) it differs between one and two
threads; for M = 4096 it does not.  CPD iterates about 150 times on that product, so the difference grows.
A part at the edge of a bar can then be meshed on one machine and missed on another.
Session 88: never-seen finished_1154_008's first draw gave a valid registration mesh 4.15 % off the part with
one BLAS thread and an inverted one with two.  The learned-source run then ended 2.22 % off with one thread
and 0.75 % off with two.

The drivers' Dask workers already start with ``OMP_NUM_THREADS=1`` (``flows.runners``), unless the environment
says otherwise.  :func:`one_blas_thread` holds the BLAS pools at :data:`STAGE_THREADS` for a stage, whatever
the process or its environment set.  The same part then gives the same mesh in a worker, in the thread
runner, in a benchmark and in a direct call.  Only BLAS is held.  The model's torch pool is left alone;
its clouds were identical at one and two threads.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from typing import Callable, Iterator, TypeVar

from threadpoolctl import threadpool_limits

#: BLAS threads of every CPU stage (:func:`one_blas_thread`); parts run in parallel across processes instead
STAGE_THREADS = 1

F = TypeVar("F", bound=Callable)


_lock = threading.Lock()
_depth = 0  # stages inside the hold, in every thread of this process (the pools are the process's, not a thread's)
_limiter = None


@contextlib.contextmanager
def blas_held() -> Iterator[None]:
    """The BLAS pools (numpy's and scipy's OpenBLAS) at :data:`STAGE_THREADS` threads while any stage of this
    process is inside, restored when the last one leaves.  The pools belong to the process, and the thread runner
    runs parts side by side.  A plain ``threadpool_limits`` per stage would put one part's stage back at the old
    count when another part's stage finished first.  Seen here with OpenBLAS 0.3.30/0.3.31: when the last stage
    to leave runs in another thread than the first one in, the old count does not come back for the first
    thread. Its later products then run at one thread too, which changes no result of this library."""
    global _depth, _limiter
    with _lock:
        if _depth == 0:
            _limiter = threadpool_limits(limits=STAGE_THREADS, user_api="blas")
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _limiter.restore_original_limits()
                _limiter = None


def one_blas_thread(fn: F) -> F:
    """``fn`` run inside :func:`blas_held`."""

    @functools.wraps(fn)
    def held(*args, **kwargs):
        with blas_held():
            return fn(*args, **kwargs)

    return held
