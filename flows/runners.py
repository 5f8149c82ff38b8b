"""Task runners for the flows: a Dask cluster (local by default, or a scheduler address).

A local cluster's worker processes must talk to the same Prefect API as the flow: with
the embedded (ephemeral) server nothing tells them where it is, and each would start its
own (PLATFORM.md).  :func:`prepare_dask` passes the flow's API URL (and the thread
limits) into the workers' environment just before the cluster starts.

It also stops Dask from starting its worker processes with ``MALLOC_TRIM_THRESHOLD_=65536``
(its ``distributed.nanny.pre-spawn-environ`` default, meant to hand freed memory back to
the OS).  Setting that variable switches off glibc's adaptive mmap threshold, so every
numpy temporary over 128 KiB becomes a fresh ``mmap`` whose pages fault in again: measured
here on one synthetic part at 5000 hexes, the pullback took 36.0 s in a Dask worker (19.7 s
of it system time) against 12.5 s (0.8 s system) without the variable, and the whole flow
ran 2-2.5x slower than a plain loop.  The stages free their arrays when a part is done,
so the worker's memory stays flat without the trim.

Every local worker process loads open3d (and gmsh) in its main thread as it starts
(:func:`dask_setup`, Dask's preload hook).  Without that, open3d was first loaded in the task
thread, and a worker whose task had raycast and then rendered a VTK preview (every part does)
aborted in libEGL's destructor as the cluster closed: ``malloc_consolidate(): unaligned fastbin
chunk detected`` on the user's terminal after every ``polycubenet mesh`` run, though the results
were complete.
"""

from __future__ import annotations

import os

from prefect.task_runners import ThreadPoolTaskRunner
from prefect_dask import DaskTaskRunner

#: environment the local Dask workers inherit from the flow's process when set there
_PASS_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "PREFECT_HOME",
             "PREFECT_SERVER_ANALYTICS_ENABLED", "DO_NOT_TRACK", "VTK_DEFAULT_OPENGL_WINDOW")


def dask_runner(workers: int | None = None, address: str | None = None, threads_per_worker: int = 1,
                memory: str | None = None) -> DaskTaskRunner:
    """A DaskTaskRunner on ``address`` (a running scheduler: its workers must import this
    project; GPU workers started with ``--resources GPU=1``) or on a new local cluster of
    ``workers`` single-threaded processes (default 1), each capped at ``memory`` (e.g. ``"4GiB"``;
    default Dask's: the machine's memory shared between the workers).  A worker past its cap is
    restarted by its nanny; a part whose worker dies twice fails (``allowed-failures`` is 1,
    set in :func:`prepare_dask`) and the batch goes on."""
    if address:
        return DaskTaskRunner(address=address)
    kw = {"n_workers": int(workers or 1), "threads_per_worker": threads_per_worker, "processes": True,
          "dashboard_address": ":0", "preload": [WORKER_PRELOAD]}
    if memory:
        kw["memory_limit"] = memory
    return DaskTaskRunner(cluster_kwargs=kw)


#: the module each local worker process imports as it starts (its :func:`dask_setup` runs there)
WORKER_PRELOAD = __name__


def dask_setup(worker=None) -> None:
    """Dask's preload hook, run by every local worker process as it starts, in its main thread: load
    gmsh, and pymeshlab then open3d (:mod:`polycubenet._o3d`'s order), before a task thread does.

    open3d first loaded in a task thread, then VTK rendering (or gmsh first loaded in another
    thread) makes the process abort at its normal exit, in libEGL's destructor.  ``flows.cli.leave``
    skips those destructors in the command line's own process; a worker process exits normally when
    the cluster closes, so it loads them here first
    (``tests/test_flows.py::test_local_dask_workers_leave_without_aborting_in_native_destructors``)."""
    import importlib

    for name in ("gmsh", "polycubenet._o3d"):
        try:
            importlib.import_module(name)
        except ImportError:  # the stage that needs it says so; a worker that does not start says nothing useful
            pass


def make_runner(workers: int | None = None, address: str | None = None, kind: str = "dask", memory: str | None = None):
    """``kind="dask"`` (:func:`dask_runner`) or ``"threads"`` (a thread pool, for tests)."""
    if kind == "threads":
        return ThreadPoolTaskRunner(max_workers=int(workers or 1))
    if kind != "dask":
        raise ValueError(f"unknown task runner kind {kind!r}; expected 'dask' or 'threads'")
    return dask_runner(workers, address, memory=memory)


def current_api_url() -> str | None:
    """The Prefect API this process talks to: ``PREFECT_API_URL`` or the running embedded server."""
    from prefect.settings import get_current_settings

    url = get_current_settings().api.url
    if url:
        return str(url)
    try:
        from prefect.server.api.server import SubprocessASGIServer

        server = SubprocessASGIServer._instances.get(None)
        if server is not None and server.running:
            return server.api_url
    except ImportError:  # pragma: no cover
        pass
    return None


def prepare_dask(runner) -> None:
    """Before a local Dask cluster starts (first submit), give its workers the flow's API URL
    and thread limits.  No-op for other runners, a scheduler address or a started cluster."""
    if not isinstance(runner, DaskTaskRunner) or runner.address or runner._client is not None:
        return
    keep_glibc_malloc_defaults()
    import dask

    # a task whose worker dies is retried once elsewhere (a killed worker), not three times (a part that
    # exhausts every worker's memory would take the whole cluster down three times over)
    dask.config.set({"distributed.scheduler.allowed-failures": 1})
    env = dict(runner.cluster_kwargs.get("env") or {})
    url = current_api_url()
    if url:
        env.setdefault("PREFECT_API_URL", url)
    for k in _PASS_ENV:
        if k in os.environ:
            env.setdefault(k, os.environ[k])
    env.setdefault("OMP_NUM_THREADS", "1")
    runner.cluster_kwargs["env"] = env


def keep_glibc_malloc_defaults() -> None:
    """Start local Dask workers without ``MALLOC_TRIM_THRESHOLD_`` (see the module docstring).

    Dask reads ``distributed.nanny.pre-spawn-environ`` when a nanny starts; ``None`` drops
    the variable.  A value the user set in this process's environment is left alone."""
    import dask

    dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None})


def gpu_workers(runner) -> int:
    """How many workers of the runner's Dask cluster advertise a ``GPU`` resource (0 otherwise)."""
    if not isinstance(runner, DaskTaskRunner):
        return 0
    try:
        try:
            info = runner.client.scheduler_info(n_workers=-1)
        except TypeError:  # older distributed
            info = runner.client.scheduler_info()
    except Exception:  # noqa: BLE001 - no cluster reachable: no GPU routing
        return 0
    return sum(1 for w in info.get("workers", {}).values() if (w.get("resources") or {}).get("GPU", 0) > 0)
