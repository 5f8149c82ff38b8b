"""``scan_drops``: mesh what is new or changed in a drop folder.

Discovers the parts under ``drop``, hashes their content and compares with
``<out>/manifest.json``: a part whose path is not in the manifest, or whose content hash
differs from the recorded one, is meshed with :func:`flows.mesh_library.mesh_library`
(the rows of the others are kept).  A part that failed before and did not change is left
to ``retry_failed``.  Scheduled nightly by ``deployments/prefect.yaml``.
"""

from __future__ import annotations

from prefect import flow, get_run_logger

from polycubenet import library

from flows.mesh_library import mesh_library
from flows.runners import make_runner


def changed_parts(drop: list[str] | str, out: str) -> tuple[list[str], list[str]]:
    """``(new, changed)`` part paths of ``drop`` relative to ``<out>/manifest.json``."""
    drops = [drop] if isinstance(drop, str) else list(drop)
    known = {r["path"]: r.get("hash") for r in library.read_manifest(out)["parts"]}
    new, changed = [], []
    for p in library.discover(drops, exclude=[out]):
        if str(p) not in known:
            new.append(str(p))
        elif library.file_hash(p) != known[str(p)]:
            changed.append(str(p))
    return new, changed


@flow(name="scan-drops", log_prints=True)
def scan_drops(drop: str, out: str, polycube: str = "auto", formats: list[str] = ("vtu",),
               target_hexes: int | None = 5000, target_size: float | None = None, workers: int = 1,
               dask_address: str | None = None, runner: str = "dask", mesh_options: dict | None = None) -> dict:
    """Mesh the new and changed parts of ``drop`` into ``out`` (see the module docstring).

    ``mesh_options`` are further ``mesh_library`` arguments (``n_sample``, ``checkpoint``, ...).
    Returns ``new``, ``changed`` and, when something ran, the ``mesh_library`` summary.
    """
    logger = get_run_logger()
    new, changed = changed_parts(drop, out)
    logger.info(f"{drop}: {len(new)} new, {len(changed)} changed parts")
    if not new and not changed:
        return {"new": [], "changed": [], "out": str(out)}
    sub = mesh_library.with_options(task_runner=make_runner(workers, dask_address, runner))
    res = sub(inputs=new + changed, out=out, polycube=polycube, formats=list(formats), target_hexes=target_hexes,
              target_size=target_size, merge=True, **(mesh_options or {}))
    return {"new": new, "changed": changed, **res}
