"""What every stage task shares: the cache policy, the retry rule and the result record.

* :class:`StageKey` -- the cache key is the ``key`` argument the flow computes with
  :func:`polycubenet.library.chain_keys` (content hash of the part file + the stage's
  parameters + its version string, chained through the upstream stages).  Prefect's
  default policy includes the run id, so nothing would be reused across runs; this one
  reuses a stage whenever its key is unchanged, in any run, on any machine that sees the
  same result storage.
* :func:`retry_transient` -- retries only what may succeed on a second try (I/O,
  connections, timeouts, memory, a CUDA out-of-memory).  A ``PartError`` or
  ``PolycubeError`` is final for its part (and a bug is not retried either).
* :func:`stage_record` -- what a task returns: the path it wrote, how long it took and the
  flow run that computed it (a cached result carries the run that first computed it,
  which is how the flow counts reuse).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, Callable

from prefect.cache_policies import CachePolicy
from prefect.context import TaskRunContext

from polycubenet.errors import PartError, PolycubeError

#: final for the part: never retried, never fail the batch
FINAL_ERRORS = (PartError, PolycubeError)
#: what a retry may fix
TRANSIENT_ERRORS = (OSError, TimeoutError, ConnectionError, MemoryError)
RETRIES = 2
RETRY_DELAYS = [2, 10]


@dataclasses.dataclass
class StageKey(CachePolicy):
    """Cache key = the task's ``key`` argument (None -> no caching)."""

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any],
                    **kwargs: Any) -> str | None:
        key = inputs.get("key")
        return None if key is None else f"stage-{key}"


STAGE_CACHE = StageKey()


def is_transient(exc: BaseException) -> bool:
    """Whether a retry may help: never for a PartError / PolycubeError."""
    if isinstance(exc, FINAL_ERRORS):
        return False
    if isinstance(exc, FileNotFoundError):  # a missing upstream file will still be missing
        return False
    if isinstance(exc, TRANSIENT_ERRORS):
        return True
    return isinstance(exc, RuntimeError) and "out of memory" in str(exc).lower()


def retry_transient(task, task_run, state) -> bool:
    """``retry_condition_fn`` for every stage task (see :func:`is_transient`)."""
    try:
        exc = state.result(raise_on_failure=False)
    except Exception as err:  # the state's data could not be read: treat that as transient
        exc = err
    return isinstance(exc, BaseException) and is_transient(exc)


def stage_record(stage: str, fn: Callable[[], Any], done: Callable[[], bool] | None = None) -> dict:
    """Run ``fn`` (which writes the stage's file and returns its path); return the record.

    ``done()`` says the stage's keyed output is already complete on disk (written whole by
    an earlier run whose cache record was lost, e.g. killed between the rename and the
    record): then nothing is recomputed and the record says ``flow_run: "file"``.
    """
    ctx = TaskRunContext.get()
    t0 = time.perf_counter()
    run = str(ctx.task_run.flow_run_id) if ctx and ctx.task_run else None
    if done is not None and done():
        path, run = None, "file"
    else:
        path = fn()
    return {
        "stage": stage,
        "path": None if path is None else str(path),
        "seconds": round(time.perf_counter() - t0, 4),
        "flow_run": run,
        "finished": time.time(),
    }


def task_options(name: str) -> dict:
    """The options every stage task is declared with."""
    return dict(
        name=name,
        cache_policy=STAGE_CACHE,
        persist_result=True,
        retries=RETRIES,
        retry_delay_seconds=RETRY_DELAYS,
        retry_condition_fn=retry_transient,
        task_run_name=name + "-{name}",
    )


def results_dir(work: str | Path) -> Path:
    """Where the flows keep Prefect's cached stage records: next to the stage files, so
    that a work folder on shared storage carries its cache with it."""
    return Path(work) / ".prefect-results"
