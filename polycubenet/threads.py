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

import functools
from typing import Callable, TypeVar

from threadpoolctl import threadpool_limits

#: BLAS threads of every CPU stage (:func:`one_blas_thread`); parts run in parallel across processes instead
STAGE_THREADS = 1

F = TypeVar("F", bound=Callable)


def one_blas_thread(fn: F) -> F:
    """``fn`` run with the BLAS pools (numpy's and scipy's OpenBLAS) held at :data:`STAGE_THREADS`
    threads and restored after it."""

    @functools.wraps(fn)
    def held(*args, **kwargs):
        with threadpool_limits(limits=STAGE_THREADS, user_api="blas"):
            return fn(*args, **kwargs)

    return held
