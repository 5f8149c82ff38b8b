"""``mesh_library``: mesh every part under some folders into ``<out>/``, overnight-safe.

discover (folders, globs, every supported format) → load + sample per part → the polycube
cloud (the diffusion model in batches packed by resolution under a point budget, routed to
a GPU worker when the Dask cluster has one; or a per-part source: ``oracle`` sidecars,
``classical``, ``voxel``) → cleanup + extraction → registration → partition + pullback →
report + export, per part on the flow's task runner (a local Dask cluster by default, a
scheduler address for a real one) → the classical chain (surface flattening, then the voxel
polycube) for a part whose polycube fails validation or whose hex mesh is not valid →
``manifest.json``, ``report.html`` and Prefect artifacts (a markdown artifact per part, a
summary table, a progress bar updated as parts finish).

Every stage is a cached task (:mod:`tasks.mesh`) keyed on the part's content hash, the
stage's parameters and its version, with Prefect's records kept in
``<work>/.prefect-results``: a re-run (the same folder, ``retry_failed``, ``scan_drops``, a
run after a crash) recomputes only what changed or never finished.  The flow submits two
tasks per part to the task runner -- ``load_sample`` and ``mesh_chain``, which calls the
stage tasks from polycube to export itself (each still its own cached, retried task run)
-- plus the batched generation tasks: a task submitted to a Dask worker costs about 0.3 s
of CPU in Prefect's context set-up, a task called inside one about 0.02 s.  A part that
fails with a ``PartError`` / ``PolycubeError`` is recorded as failed (stage and error in the
manifest); the batch goes on and the flow completes.
"""

from __future__ import annotations

import dataclasses
import queue
import re
import time
from pathlib import Path
from typing import Callable

from prefect import flow, get_run_logger
from prefect.context import FlowRunContext
from prefect_dask import DaskTaskRunner

from polycubenet import library
from polycubenet.errors import PartError, PolycubeError
from polycubenet.pipeline import PipelineConfig
from polycubenet.policy import leaves_source, source_names
from tasks import mesh as T
from tasks.common import results_dir

from flows.runners import dask_runner, gpu_workers, prepare_dask

#: callables ``hook(event: dict)`` called in the flow's process as parts finish (the CLI's progress bar)
PROGRESS_HOOKS: list[Callable[[dict], None]] = []

@dataclasses.dataclass
class _Part:
    path: Path
    name: str
    hash: str
    keys: dict
    sources: list
    records: dict = dataclasses.field(default_factory=dict)
    status: str = "pending"
    stage: str = "load_sample"
    error: str | None = None
    fallback: str | None = None
    #: cache keys of every source's chain (``chain_keys[source][stage]``)
    chain_keys: dict = dataclasses.field(default_factory=dict)
    #: seconds spent on the polycube sources that were left (per stage)
    rejected_seconds: dict = dataclasses.field(default_factory=dict)

    @property
    def source(self) -> str:
        return self.sources[0]


def _slug(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")[:60] or "part"


@flow(name="mesh-library", task_runner=dask_runner(), log_prints=True)
def mesh_library(
    inputs: list[str],
    out: str,
    formats: list[str] = ("vtu",),
    polycube: str = "learned",
    fallback: bool = True,
    n_sample: int = 4096,
    n_polycube: int = 16384,
    n_learned: int = 4096,
    n_register: int = 4096,
    target_hexes: int | None = 5000,
    target_size: float | None = None,
    seed: int = 0,
    min_sj: float | None = PipelineConfig.min_sj,
    checkpoint: str | None = None,
    steps: int | None = None,
    point_budget: int | None = None,
    device: str | None = None,
    work: str | None = None,
    load_kw: dict | None = None,
    artifacts: bool = True,
    merge: bool = True,
    part_timeout: float | None = library.DEFAULT_PART_TIMEOUT,
) -> dict:
    """Mesh the parts named by ``inputs`` into ``out`` (see the module docstring).

    Parameters
    ----------
    inputs : files, folders or glob patterns
    out : output folder (``<out>/<part>/hex.<fmt>``, ``manifest.json``, ``report.html``)
    formats : hex formats among vtu, vtk, mesh, inp, msh, bdf
    polycube : ``auto`` (the model, then the classical chain for a part whose learned polycube
        fails validation or gives an invalid mesh: ``learned`` with ``fallback=True``),
        ``learned`` (the model), ``oracle`` (synthetic parts' sidecars), ``classical`` (the
        surface-flattening polycube, then the voxel polycube as a last resort), ``voxel``
    fallback : after a ``learned`` / ``oracle`` polycube that fails validation or whose hex mesh
        is not valid, try the classical chain (``auto`` always does)
    n_sample, n_polycube, n_learned, n_register, target_hexes, target_size, seed : :class:`PipelineConfig`
    min_sj : the quality bar (:class:`PipelineConfig`, 0.2 by default): a valid mesh whose minimum scaled
        Jacobian is under it does not end a part's chain of polycube sources (the next is tried and the better
        mesh kept), the pull-back eases meshes under it, and the report marks a part meshed under it (None: any
        valid mesh ends the chain)
    checkpoint, steps, point_budget, device : the model (``polycube="learned"``; budget: condition +
        output points of one generation batch, default ``inference.DEFAULT_POINT_BUDGET``)
    work : stage files and cache records (default ``<out>/.work``)
    merge : keep the manifest rows of parts not in this run
    part_timeout : wall-clock seconds one part's task may run (its loading, or its chain of polycube
        sources to the export); past it the part becomes a failed row saying so, its task is
        cancelled and -- on Dask -- the worker process running it is restarted, and the batch goes
        on.  None: no limit.  (A part's memory is capped by the Dask worker's ``memory_limit``:
        a worker past it is restarted by its nanny and the part fails after one retry.)

    Returns
    -------
    dict : ``out``, ``manifest``, ``report``, ``counts`` and ``computed`` / ``reused`` stage counts
    """
    logger = get_run_logger()
    t_start = time.perf_counter()
    out_p = Path(out).resolve()
    work_p = Path(work).resolve() if work else out_p / ".work"
    formats = [f.lstrip(".").lower() for f in formats]
    bad = [f for f in formats if f not in library.HEX_FORMATS]
    if bad:
        raise ValueError(f"unknown hex formats {bad}; expected some of {library.HEX_FORMATS}")
    if polycube not in ("auto", "learned", "oracle", "classical", "voxel"):
        raise ValueError(f"unknown polycube source {polycube!r}; expected auto, learned, oracle, classical or voxel")
    if polycube == "auto":
        polycube, fallback = "learned", True
    config = PipelineConfig(n_sample=n_sample, n_polycube=n_polycube, n_learned=n_learned, n_register=n_register,
                            target_hexes=target_hexes, target_size=target_size, seed=seed, min_sj=min_sj)
    swept = library.sweep_partials(out_p, work_p, before=time.time())
    if swept:
        logger.info(f"removed {swept} partial files left by an interrupted run")

    if polycube == "learned" and checkpoint is None:
        from polycubenet.inference import DEFAULT_CHECKPOINT

        checkpoint = str(DEFAULT_CHECKPOINT)
    if polycube == "learned" and not Path(checkpoint).is_file():
        raise FileNotFoundError(f"model checkpoint {checkpoint} not found: pass checkpoint=..., or polycube='classical'")
    paths = library.discover(inputs, exclude=[out_p, work_p])
    hashes = [library.file_hash(p) for p in paths]
    names = library.part_names(paths, hashes)
    draws: tuple[int, ...] = ()
    if polycube == "learned":  # the model's further draws after its first (the policy)
        from polycubenet.inference import ModelSource

        draws = ModelSource(checkpoint, steps=steps, device=device).further_draws()
    sources = source_names(polycube, fallback, classical=library.classical_available(), draws=draws)
    parts: list[_Part] = []
    for p, h, n in zip(paths, hashes, names):
        keys = {}
        for src in sources:
            params = library.stage_params(config, polycube=src,
                                          polycube_extra=library.source_extra(src, p, checkpoint, steps=steps,
                                                                                device=device),
                                          load_kw=load_kw, formats=formats, out_dir=str(out_p / n))
            keys[src] = library.chain_keys(h, params)
        part = _Part(p, n, h, keys[sources[0]], list(sources))
        part.chain_keys = keys
        parts.append(part)
    logger.info(f"{len(parts)} parts under {list(inputs)}; polycube source {' -> '.join(sources)}; out {out_p}")

    ctx = FlowRunContext.get()
    runner = ctx.task_runner if ctx else None
    prepare_dask(runner)
    on_dask = isinstance(runner, DaskTaskRunner)
    run_id = str(ctx.flow_run.id) if ctx and ctx.flow_run else None
    result_storage = results_dir(work_p)
    result_storage.mkdir(parents=True, exist_ok=True)
    load_task = T.load_sample.with_options(result_storage=result_storage)
    done_q: "queue.Queue" = queue.Queue()
    pending: dict = {}
    progress = _Progress(len(parts), artifacts)
    gen_pool: list[_Part] = []
    loads_left = len(parts)

    def path_of(part: _Part, stage: str, source: str | None = None) -> str:
        return str(library.stage_path(work_p, part.hash, stage, part.chain_keys[source or part.source][stage]))

    def submit(part, what: str, task, priority: int, **kw):
        if on_dask:  # the most advanced part first: parts finish one after another, not all at the end
            import dask

            with dask.annotate(priority=priority):
                fut = task.submit(**kw)
        else:
            fut = task.submit(**kw)
        pending[fut] = (part, what)
        fut.add_done_callback(done_q.put)

    def submit_load(part: _Part):
        dest = path_of(part, "load_sample")
        task = load_task if Path(dest).exists() else load_task.with_options(refresh_cache=True)
        submit(part, "load_sample", task, 0, path=str(part.path), dest=dest, key=part.keys["load_sample"],
               name=part.name, load_kw=load_kw, config=config)

    def submit_chain(part: _Part, learned: dict | None = None):
        """The rest of the part (every source's chain, then export) as one task that calls the stage tasks."""
        part.stage = "polycube"
        srcs = part.sources
        submit(part, "chain", T.mesh_chain, 1, name=part.name, path=str(part.path),
               loaded=part.records["load_sample"]["path"], sources=list(srcs),
               keys={s: part.chain_keys[s] for s in srcs},
               paths={s: {st: path_of(part, st, s) for st in library.STAGES[1:5]} for s in srcs},
               config=config, formats=formats, out_dir=str(out_p / part.name),
               result_storage=str(result_storage), learned=learned,
               model={"checkpoint": None if checkpoint is None else str(checkpoint), "device": device, "steps": steps})

    def start_polycube(part: _Part):
        if part.source == "learned":
            if Path(path_of(part, "polycube")).exists():
                submit_chain(part, {"record": {"stage": "polycube", "path": path_of(part, "polycube"), "seconds": 0.0,
                                               "flow_run": "earlier", "finished": time.time()}})
            else:
                gen_pool.append(part)
        else:
            submit_chain(part)

    def flush_generation(final: bool):
        nonlocal gen_pool
        if not gen_pool:
            return
        from polycubenet import inference

        budget = point_budget or inference.DEFAULT_POINT_BUDGET
        if not final and len(gen_pool) * (config.n_sample + config.n_learned) < budget:
            return
        batches = inference.plan_batches([config.n_sample] * len(gen_pool), [config.n_learned] * len(gen_pool),
                                         budget)
        annotate = gpu_workers(runner) > 0
        for i, idx in enumerate(batches):
            members = [gen_pool[j] for j in idx]
            kw = dict(loaded=[m.records["load_sample"]["path"] for m in members],
                      dests=[path_of(m, "polycube") for m in members], n_out=[config.n_learned] * len(members),
                      key="+".join(m.keys["polycube"] for m in members), checkpoint=checkpoint, steps=steps,
                      seed=seed, device=device, point_budget=budget,
                      name=f"{members[0].name}+{len(members) - 1}")
            if annotate:
                import dask

                with dask.annotate(resources={"GPU": 1}, priority=1):
                    fut = T.generate_batch.submit(**kw)
            else:
                fut = T.generate_batch.submit(**kw)
            for m in members:
                m.stage = "polycube"
            pending[fut] = (members, "generate")
            fut.add_done_callback(done_q.put)
        gen_pool = []

    rows_by_name: dict = {}

    parameters = {"inputs": [str(i) for i in inputs], "formats": formats, "polycube": polycube, "fallback": fallback,
                  "config": config, "checkpoint": checkpoint, "steps": steps, "work": str(work_p),
                  "load_kw": load_kw or {}}
    old_rows = library.read_manifest(out_p)["parts"] if merge else []

    def write_manifest(final: bool) -> Path:
        """The manifest as it stands (rewritten atomically as each part finishes, so a killed run leaves
        a true one): the earlier runs' rows merged with this run's finished parts."""
        rows = [rows_by_name[p.name] for p in parts if p.name in rows_by_name]
        computed = sum(len(r["computed"]) for r in rows)
        reused = sum(len(r["reused"]) for r in rows)
        rejected = round(sum(v for r in rows for k, v in r["timings"].items() if k.startswith("rejected_")), 2)
        last = {"flow_run": run_id, "parts": len(parts), "finished": len(rows), "complete": final,
                "seconds": round(time.perf_counter() - t_start, 2), "computed_stages": computed,
                "reused_stages": reused, "rejected_polycube_seconds": rejected}
        return library.write_manifest(out_p, library.merge_rows(old_rows, rows), parameters=parameters,
                                      extra={"last_run": last})

    def finish(part: _Part, status: str, error: str | None = None):
        part.status, part.error = status, error
        rows_by_name[part.name] = row = _row(part, out_p, run_id)
        write_manifest(final=False)
        if artifacts:
            _part_artifact(row, out_p)
        progress.step(part)
        for hook in PROGRESS_HOOKS:
            hook({"part": part.name, "status": status, "stage": part.stage, "error": error,
                  "done": progress.done, "failed": progress.failed, "total": progress.total})

    def unexpected(part: _Part, stage: str, exc: BaseException):
        msg = f"{type(exc).__name__}: {exc}"
        if type(exc).__name__ == "KilledWorker":  # the nanny restarted the worker twice while it ran this part
            msg = (f"WorkerDied: the worker process died twice while meshing this part (over the worker memory "
                   f"limit, --worker-memory, or a crash); the batch went on ({exc})")
        if not isinstance(exc, (PartError, PolycubeError)):
            logger.error(f"{part.name}: unexpected failure at {stage}: {msg}")
        part.stage = stage
        finish(part, "failed", msg)

    for part in parts:
        submit_load(part)

    watch = _Watch(runner, part_timeout)
    while pending:
        try:
            fut = done_q.get(timeout=watch.poll)
        except queue.Empty:
            for f, part, seconds in watch.overdue(pending):
                del pending[f]
                reached = [st for st in library.STAGES[1:5] if any(Path(path_of(part, st, s)).exists()
                                                                    for s in part.sources)]
                at = library.STAGES[library.STAGES.index(reached[-1]) + 1] if reached else part.stage
                what = watch.abandon(f)
                logger.error(f"{part.name}: over the per-part time limit ({seconds:.0f} s > {part_timeout:g} s) "
                             f"at {at}; {what}")
                part.stage = at
                finish(part, "failed", f"PartTimeout: the part ran {seconds:.0f} s, over the per-part limit of "
                                       f"{part_timeout:g} s (--part-timeout), during {at}; {what}")
            continue
        if fut not in pending:
            continue
        who, what = pending.pop(fut)
        value = fut.result(raise_on_failure=False)
        if what == "generate":
            for m in who:
                if isinstance(value, BaseException):
                    if len(m.sources) > 1 and leaves_source("learned", value):  # the policy: the next source
                        msg = str(value) if isinstance(value, PolycubeError) else f"{type(value).__name__}: {value}"
                        submit_chain(m, {"error": msg})
                    else:
                        unexpected(m, "polycube", value)
                else:
                    rec = next(r for r in value if Path(r["path"]) == Path(path_of(m, "polycube")))
                    submit_chain(m, {"record": rec})
        elif what == "load_sample":
            part = who
            loads_left -= 1
            if isinstance(value, BaseException):
                unexpected(part, "load_sample", value)
            else:
                part.records["load_sample"] = value
                start_polycube(part)
        else:  # the part's chain
            part = who
            if isinstance(value, BaseException):
                unexpected(part, getattr(value, "stage", "polycube"), value)
            else:
                part.records.update(value["records"])
                part.sources = [value["source"]]
                part.keys = value["keys"]
                part.fallback = value["fallback"]
                part.rejected_seconds = value["rejected_seconds"]
                if value["fallback"]:
                    logger.warning(f"{part.name}: {value['fallback']}")
                part.stage = value["stage"]
                finish(part, value["status"], value["error"])
        if any(p.source == "learned" for p in gen_pool):
            flush_generation(final=loads_left == 0)

    for p in parts:  # every part has finished; a part that never did is a row too
        rows_by_name.setdefault(p.name, _row(p, out_p, run_id))
    rows = [rows_by_name[p.name] for p in parts]
    computed = sum(len(r["computed"]) for r in rows)
    reused = sum(len(r["reused"]) for r in rows)
    rejected = sum(v for r in rows for k, v in r["timings"].items() if k.startswith("rejected_"))
    manifest = write_manifest(final=True)
    all_rows = library.merge_rows(old_rows, rows)
    report = library.write_report_html(out_p, all_rows, min_sj=min_sj)
    if artifacts:
        from prefect.artifacts import create_table_artifact

        create_table_artifact(table=library.summary_rows(all_rows), key="mesh-library-summary",
                              description=f"{out_p}: one row per part")
    counts = {s: sum(r["status"] == s for r in rows) for s in ("meshed", "failed")}
    logger.info(f"done: {counts['meshed']} meshed, {counts['failed']} failed; stages computed {computed}, "
                f"reused {reused}; {rejected:.1f} s went to rejected polycubes; manifest {manifest}")
    return {"out": str(out_p), "manifest": str(manifest), "report": str(report), "counts": counts,
            "computed": computed, "reused": reused, "rows": rows}


class _Watch:
    """The per-part time limit: which running tasks are past it, and how to let one go.

    A task's clock starts when it is first seen running (on Dask: in the scheduler's
    ``processing``; in a thread pool: ``Future.running()``), not when it was queued."""

    def __init__(self, runner, limit: float | None):
        self.limit = limit
        self.runner = runner
        self.started: dict = {}
        self.poll = None if limit is None else min(1.0, max(0.05, limit / 10))

    def _dask(self):
        return self.runner.client if isinstance(self.runner, DaskTaskRunner) else None

    def overdue(self, pending: dict) -> list:
        if self.limit is None:
            return []
        now = time.monotonic()
        client = self._dask()
        busy = None
        if client is not None:
            busy = {k for keys in client.processing().values() for k in keys}
        out = []
        for fut, (who, what) in list(pending.items()):
            wf = fut.wrapped_future
            running = (wf.key in busy) if busy is not None else getattr(wf, "running", lambda: False)()
            if running:
                t0 = self.started.setdefault(fut, now)
                if now - t0 > self.limit and what != "generate":
                    out.append((fut, who, now - t0))
        return out

    def abandon(self, fut) -> str:
        """Cancel ``fut``'s task and free its worker; says what was done."""
        wf = fut.wrapped_future
        client = self._dask()
        if client is None:
            wf.cancel()
            return "a thread pool cannot stop a running task: it finishes in the background, unused"
        where = [addr for addr, keys in client.processing().items() if wf.key in keys]
        client.cancel(wf)
        if not where:
            return "its task was cancelled"
        try:
            client.restart_workers(where, timeout=60)
            return f"its worker {where[0]} was restarted"
        except Exception as exc:  # noqa: BLE001 - a worker without a nanny cannot be restarted
            return f"its task was cancelled, but the worker {where[0]} could not be restarted ({exc})"


def _row(part: _Part, out: Path, run_id: str | None) -> dict:
    """One manifest row (plain types)."""
    row = {
        "name": part.name, "path": str(part.path), "hash": part.hash, "status": part.status,
        "stage": "export" if part.status == "meshed" else part.stage, "error": part.error,
        "provenance": None, "fallback": part.fallback,
        "timings": {**{s: r["seconds"] for s, r in part.records.items()},
                    **{f"rejected_{s}": round(v, 4) for s, v in part.rejected_seconds.items()}},
        "computed": [s for s, r in part.records.items() if r.get("flow_run") == run_id],
        "reused": [s for s, r in part.records.items() if r.get("flow_run") != run_id],
        "quality": None, "files": [], "keys": dict(part.keys), "out": part.name,
    }
    if part.status == "meshed":
        d = out / part.name
        res = library.load_json(d / "result.json")
        q = library.load_json(d / "quality.json")
        row["provenance"] = res.get("provenance")
        row["quality"] = {"hexes": q.get("hex_count"), "sj_min": q.get("sj_min"), "sj_avg": q.get("sj_avg"),
                          "sj_p01": q.get("sj_p01"), "inverted": q.get("inverted_count"),
                          "degenerate": q.get("degenerate_count"), "valid": q.get("valid"),
                          "hausdorff": (q.get("surface") or {}).get("hausdorff"), "warnings": q.get("warnings")}
        row["files"] = sorted(f.name for f in d.iterdir() if f.is_file() and not f.name.startswith("."))
    elif "polycube" in part.records:
        row["provenance"] = part.source
    return row


class _Progress:
    """The progress artifact, updated as parts finish."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.done, self.failed = total, 0, 0
        self.artifact_id = None
        if enabled:
            from prefect.artifacts import create_progress_artifact

            self.artifact_id = create_progress_artifact(progress=0.0, key="mesh-library-progress",
                                                        description=f"parts finished of {total}")

    def step(self, part: _Part):
        self.done += 1
        self.failed += part.status == "failed"
        if self.artifact_id is not None:
            from prefect.artifacts import update_progress_artifact

            update_progress_artifact(self.artifact_id, progress=100.0 * self.done / max(1, self.total),
                                     description=f"{self.done}/{self.total} parts finished, {self.failed} failed")


def _part_artifact(r: dict, out: Path) -> None:
    """The markdown artifact of one finished part: its quality table and a picture (two for a mesh off the part)."""
    from prefect.artifacts import create_markdown_artifact

    q = r.get("quality") or {}
    lines = [f"# {r['name']}: {r['status']}", "", f"`{r['path']}`", "",
             "| field | value |", "|---|---|",
             f"| status | {r['status']} |", f"| stage reached | {r['stage']} |",
             f"| polycube | {r.get('provenance') or ''} |"]
    if r.get("fallback"):
        lines.append(f"| fallback | {r['fallback'].replace('|', '/')} |")
    if r.get("error"):
        lines.append(f"| error | {r['error'].replace('|', '/')} |")
    for k in ("hexes", "sj_min", "sj_avg", "sj_p01", "inverted", "degenerate", "valid", "hausdorff"):
        if k in q:
            lines.append(f"| {k} | {q[k]} |")
    lines.append(f"| time s | {round(sum(r['timings'].values()), 2)} (reused: {', '.join(r['reused']) or 'none'}) |")
    uri = library.thumbnail_data_uri(out / r["name"] / "preview.png") if r["status"] == "meshed" else None
    if uri:
        lines += ["", f"![preview]({uri})"]
    where = out / r["name"] / "deviation.png"  # a mesh off the part: where it leaves it
    uri = library.thumbnail_data_uri(where, width=480) if r["status"] == "meshed" and where.is_file() else None
    if uri:
        lines += ["", f"![where the mesh leaves the part]({uri})"]
    create_markdown_artifact(markdown="\n".join(lines), key=f"part-{_slug(r['name'])}",
                             description=f"{r['name']}: {r['status']}")
