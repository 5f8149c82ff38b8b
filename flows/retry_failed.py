"""``retry_failed``: re-run only the failed parts of an output folder.

Reads ``<out>/manifest.json``, takes the parts whose status is ``failed`` and runs
:func:`flows.mesh_library.mesh_library` on them with the parameters the folder was made
with (recorded in the manifest); every stage that finished before comes from the cache,
so only the stage that failed (and what follows it) is computed.  The manifest rows of
the retried parts are replaced; the others are kept.
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger

from polycubenet import library

from flows.mesh_library import mesh_library
from flows.runners import make_runner

#: manifest parameters that are mesh_library arguments
_PASSED = ("formats", "polycube", "fallback", "checkpoint", "steps", "work", "load_kw")
_CONFIG = ("n_sample", "n_polycube", "n_learned", "n_register", "target_hexes", "target_size", "seed", "min_sj")


def mesh_arguments(manifest: dict) -> dict:
    """The ``mesh_library`` keyword arguments recorded in a manifest's ``parameters``."""
    p = manifest.get("parameters") or {}
    kw = {k: p[k] for k in _PASSED if k in p}
    kw.update({k: p["config"][k] for k in _CONFIG if k in (p.get("config") or {})})
    return kw


@flow(name="retry-failed", log_prints=True)
def retry_failed(out: str, workers: int = 1, dask_address: str | None = None, runner: str = "dask",
                 overrides: dict | None = None) -> dict:
    """Re-mesh the failed parts of ``out`` (see the module docstring).

    ``overrides`` replace recorded parameters (e.g. ``{"polycube": "classical"}``).
    Returns the ``mesh_library`` summary, or ``{"retried": 0}`` when nothing failed.
    """
    logger = get_run_logger()
    manifest = library.read_manifest(out)
    failed = [r["path"] for r in manifest["parts"] if r["status"] == "failed"]
    missing = [p for p in failed if not Path(p).is_file()]
    failed = [p for p in failed if Path(p).is_file()]
    if missing:
        logger.warning(f"{len(missing)} failed parts no longer exist and are not retried: {missing[:5]}")
    if not failed:
        logger.info(f"{out}: nothing to retry")
        return {"retried": 0, "out": str(out)}
    logger.info(f"{out}: retrying {len(failed)} failed parts")
    kw = {**mesh_arguments(manifest), **(overrides or {})}
    sub = mesh_library.with_options(task_runner=make_runner(workers, dask_address, runner))
    res = sub(inputs=failed, out=out, merge=True, **kw)
    return {"retried": len(failed), **res}
