"""One thin ``@task`` per meshing stage.

Each calls one function of :mod:`polycubenet.library`, which writes the stage's result
atomically under ``<work>/<part-hash>/<stage>-<key>.npz`` (or the output files), and
returns a :func:`tasks.common.stage_record`.  ``key`` is the stage's cache key
(:func:`polycubenet.library.chain_keys`); ``name`` only names the task run.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import task
from prefect.cache_policies import NO_CACHE

from polycubenet import library
from polycubenet.pipeline import PipelineConfig

from .common import RETRIES, retry_transient, stage_record, task_options


@task(**task_options("load-sample"))
def load_sample(path: str, dest: str, key: str, config: PipelineConfig, name: str = "", load_kw: dict | None = None) -> dict:
    """Load + validate, canonical frame, Poisson-disk sample (PartError is final)."""
    return _record("load_sample", dest, lambda: library.load_sample(path, dest, config, load_kw))


@task(**task_options("polycube"))
def polycube_cloud(kind: str, path: str, loaded: str, dest: str, key: str, config: PipelineConfig, name: str = "",
                   checkpoint: str | None = None, device: str | None = None, steps: int | None = None) -> dict:
    """A per-part polycube cloud (``oracle`` sidecar, ``classical`` construction, voxel polycube, the
    model's further draws ``learned+K`` from ``checkpoint`` on ``device`` after a first at ``steps``)."""
    return _record("polycube", dest, lambda: library.polycube_cloud(kind, path, loaded, dest, config,
                                                                     checkpoint=checkpoint, device=device, steps=steps))


@task(name="generate", cache_policy=NO_CACHE, retries=RETRIES, retry_delay_seconds=[5, 30],
      retry_condition_fn=retry_transient, task_run_name="generate-{name}")
def generate_batch(loaded: list[str], dests: list[str], n_out: list[int], key: str, checkpoint: str | None = None,
                   steps: int | None = None, seed: int = 0, device: str | None = None,
                   point_budget: int | None = None, name: str = "") -> list[dict]:
    """The diffusion model on one batch of parts (packed by the flow under a point budget):
    one cloud ``.npz`` per part.  Not cached as a batch: the flow skips the parts whose
    cloud already exists, so a batch is never recomputed for parts it already did."""
    from polycubenet import inference  # lazily: the model is optional for every other stage

    parts = [library.read_loaded(p) for p in loaded]
    records = []

    def run():
        model = inference.load_model(checkpoint, device)
        anchors = None
        if model.model.config.anchored:  # each part's own points, moved onto its polycube by the model
            anchors = [inference.model_anchors(model, p[0].vertices, p[0].faces, n, seed) for p, n in zip(parts, n_out)]
        clouds = inference.generate([p[1].points for p in parts], n_out, model=model, steps=steps,
                                    seed=seed, device=device, point_budget=point_budget, anchors=anchors)
        meta = {"checkpoint": None if checkpoint is None else str(checkpoint), "steps": steps, "seed": seed}
        return [library.write_generated(np.asarray(c), d, meta, anchors=None if anchors is None else anchors[i])
                for i, (c, d) in enumerate(zip(clouds, dests))]

    rec = stage_record("polycube", run)
    for d in dests:
        records.append({**rec, "path": str(d), "seconds": rec["seconds"] / max(1, len(dests))})
    return records


@task(**task_options("extract"))
def cleanup_extract(cloud: str, loaded: str, dest: str, key: str, config: PipelineConfig, name: str = "") -> dict:
    """Outlier filter + structure extraction and validation (PolycubeError is final)."""
    return _record("extract", dest, lambda: library.cleanup_extract(cloud, loaded, dest, config))


@task(**task_options("register"))
def register(extracted: str, loaded: str, dest: str, key: str, config: PipelineConfig, name: str = "") -> dict:
    """Rigid + CPD registration of the cleaned polycube cloud to the part."""
    return _record("register", dest, lambda: library.register(extracted, loaded, dest, config))


@task(**task_options("pullback"))
def partition_pullback(extracted: str, corr: str, loaded: str, dest: str, key: str, config: PipelineConfig,
                       name: str = "", phase: str = "all", prior: str | None = None) -> dict:
    """Regular partition of the polycube, pulled back onto the part (a learned draw's in two phases:
    :func:`polycubenet.library.partition_pullback`)."""
    return _record("pullback", dest, lambda: library.partition_pullback(extracted, corr, loaded, dest, config,
                                                                        phase=phase, prior=prior))


@task(**task_options("export"))
def report_export(hexc: str, extracted: str, loaded: str, out_dir: str, key: str, formats: list[str],
                  name: str = "") -> dict:
    """Quality report against the input surface and the output files."""
    rec = stage_record("export", lambda: library.report_export(hexc, extracted, loaded, out_dir, formats, key=key, name=name or None),
                       done=lambda: library.load_json(Path(out_dir) / "result.json").get("key") == key)
    return {**rec, "path": str(out_dir)}


def _record(stage: str, dest: str, fn) -> dict:
    """:func:`stage_record` that reuses ``dest`` when an earlier run left it complete (atomic writes:
    a file with the final name is whole), and returns ``dest`` as the path either way."""
    rec = stage_record(stage, fn, done=lambda: Path(dest).is_file())
    return {**rec, "path": str(dest)}


# --------------------------------------------------------------------------- one part, polycube to export


@task(name="part", cache_policy=NO_CACHE, persist_result=False, task_run_name="part-{name}")
def mesh_chain(name: str, path: str, loaded: str, sources: list[str], keys: dict, paths: dict, config: PipelineConfig,
               formats: list[str], out_dir: str, result_storage: str, learned: dict | None = None,
               model: dict | None = None) -> dict:
    """Everything after ``load_sample`` for one part: for each polycube source in ``sources``
    (in order) the stage tasks polycube -> extract -> register -> pullback, then export.

    The stage tasks are called from here, inside this task, so each stays its own cached
    (committed as soon as it finishes), retried Prefect task run with its own file, but the
    part costs the task runner one submission instead of five.  On a Dask worker a submitted task pays Prefect's context
    hydration (its settings re-validated, two API clients built): about 0.3 s of CPU per task
    measured here, against 0.02 s for a task called inside another one.

    ``keys[source][stage]`` and ``paths[source][stage]`` are the cache keys and files of each
    source's chain (:func:`polycubenet.library.chain_keys`); ``learned`` is ``{"record": ...}``
    (the batched generation's cloud) or ``{"error": ...}`` (generation was rejected) when the
    first source is the model; ``model`` (``checkpoint``, ``device``, ``steps``) is for its further
    draws ``learned+K``, made here one part at a time.  A source is left for the next one when its polycube is
    rejected (``PolycubeError`` at polycube or extract) or its pulled-back mesh is not valid;
    the first valid mesh is exported, or when none is, the one with the highest minimum scaled
    Jacobian (``pipeline.mesh_rank``).  A ``PartError`` / ``PolycubeError`` elsewhere is final
    for the part.  Anything else (a bug) is raised with ``exc.stage`` set.

    Returns ``status`` (meshed / failed), ``stage`` reached, ``error``, ``source`` and ``keys``
    of the kept chain, ``records`` (stage -> :func:`stage_record`), ``rejected_seconds`` (per
    stage, of the sources left) and ``fallback`` (why each source was left, ``"; "``-joined).
    """
    from prefect.transactions import CommitMode, transaction

    state = {"stage": "polycube"}
    try:
        # each stage's cache record is written as that stage finishes: with Prefect's default (lazy) commit,
        # the stage tasks called here would only be committed with this task, and not at all when a later
        # stage fails, so a retry would recompute them
        with transaction(commit_mode=CommitMode.EAGER):
            return _chain(state, name, path, loaded, sources, keys, paths, config, formats, out_dir,
                          result_storage, learned, model or {})
    except Exception as exc:  # a bug: fail this task run, and say where
        exc.stage = state["stage"]
        raise


def _chain(state, name, path, loaded, sources, keys, paths, config, formats, out_dir, result_storage, learned, model):
    """The body of :func:`mesh_chain` (``state["stage"]`` follows the stage reached): each source's
    stages as tasks, the choice between sources by :func:`polycubenet.policy.run_chain`."""
    from polycubenet.errors import PolycubeError
    from polycubenet.pipeline import learned_phases
    from polycubenet.policy import Attempt, StageTracker, extraction_config, run_chain, source_config, source_label

    from .common import FINAL_ERRORS

    storage = Path(result_storage)
    records: dict = {}  # source -> stage -> record, also for a source whose attempt raised

    def run(stage: str, fn, src: str, tracker, key_suffix: str = "", **kw) -> dict:
        """One stage task of ``src`` (``key_suffix``: a second task of the stage, its seconds added to the first's)."""
        state["stage"] = tracker.stage = stage
        key = keys[src][stage] + key_suffix
        if stage == "export":
            fresh = library.load_json(Path(kw["out_dir"]) / "result.json").get("key") == key
        else:
            fresh = Path(kw["dest"]).exists()
        t = fn.with_options(result_storage=storage, refresh_cache=not fresh)  # a stale record is refreshed
        rec = t(key=key, name=name, **kw)
        records[src][stage] = rec
        tracker.seconds[stage] = tracker.seconds.get(stage, 0.0) + float(rec.get("seconds") or 0.0)
        return rec

    def attempt(src: str, tracker) -> Attempt:
        p = paths[src]
        att = records[src] = {}
        state["stage"] = tracker.stage = "polycube"
        if src == "learned":
            if learned is None or "error" in learned:
                raise PolycubeError((learned or {}).get("error") or "no generated cloud")
            att["polycube"] = learned["record"]
            tracker.seconds["polycube"] = float(learned["record"].get("seconds") or 0.0)
        else:
            run("polycube", polycube_cloud, src, tracker, kind=src, path=path, loaded=loaded, dest=p["polycube"],
                config=config, **(model if src.startswith("learned+") else {}))
        run("extract", cleanup_extract, src, tracker, cloud=att["polycube"]["path"], loaded=loaded, dest=p["extract"],
            config=extraction_config(src, config))
        run("register", register, src, tracker, extracted=att["extract"]["path"], loaded=loaded, dest=p["register"],
            config=config)
        cfg = source_config(src, config)
        split = src.startswith("learned") and learned_phases(cfg)
        run("pullback", partition_pullback, src, tracker, extracted=att["extract"]["path"],
            corr=att["register"]["path"], loaded=loaded, dest=p["pullback"], config=cfg,
            phase="map" if split else "all")
        out = Attempt(src, library.pullback_quality(att["pullback"]["path"]), payload=att,
                      seconds=dict(tracker.seconds), label=source_label(src))
        if split:  # the draw's further pull-back steps, when the policy says (policy.run_chain)
            out.rest = lambda: rest_of(src, out, cfg)
        return out

    def rest_of(src: str, first: Attempt, cfg) -> Attempt:
        """The rest of a learned draw's pull-back, from its map's file: a second pull-back task and file."""
        tracker = StageTracker()
        tracker.seconds = dict(first.seconds)
        prior, dest = first.payload["pullback"]["path"], Path(paths[src]["pullback"])
        rec = run("pullback", partition_pullback, src, tracker, key_suffix="-rest",
                  extracted=first.payload["extract"]["path"], corr=first.payload["register"]["path"], loaded=loaded,
                  dest=str(dest.with_name(f"{dest.stem}-rest{dest.suffix}")), config=cfg, phase="rest", prior=prior)
        return Attempt(src, library.pullback_quality(rec["path"]), payload=records[src], seconds=dict(tracker.seconds),
                       label=source_label(src))

    def failed(stage: str, exc: BaseException, source: str, reasons) -> dict:
        return {"status": "failed", "stage": stage, "error": f"{type(exc).__name__}: {exc}", "source": source,
                "keys": keys[source], "records": dict(records.get(source) or {}), "rejected_seconds": rejected,
                "fallback": "; ".join(reasons) or None}

    rejected: dict = {}
    try:
        outcome = run_chain(list(sources), attempt, min_sj=config.min_sj)
    except FINAL_ERRORS as exc:  # a bad part: final whatever the source
        reason = getattr(exc, "fallback_reason", None)
        return failed(exc.stage, exc, exc.source, [reason] if reason else [])
    rejected = {s: round(v, 4) for s, v in outcome.rejected_seconds.items()}
    if outcome.chosen is None:
        exc = outcome.error
        if not isinstance(exc, FINAL_ERRORS):  # the learned source alone, failing otherwise than by its polycube
            exc = PolycubeError(f"learned polycube failed at {exc.stage}: {type(exc).__name__}: {exc}", name)
        return failed(outcome.error.stage, exc, outcome.error_source, outcome.reasons)
    src, att = outcome.chosen.source, dict(outcome.chosen.payload)
    records[src] = att
    try:
        att["export"] = run("export", report_export, src, _NoTracker(), hexc=att["pullback"]["path"],
                            extracted=att["extract"]["path"], loaded=loaded, out_dir=out_dir, formats=formats)
    except FINAL_ERRORS as exc:
        return failed("export", exc, src, outcome.reasons)
    return {"status": "meshed", "stage": "export", "error": None, "source": src, "keys": keys[src], "records": att,
            "rejected_seconds": rejected, "fallback": outcome.fallback_reason}


class _NoTracker:
    """A stage tracker for the export, which is after the source choice."""

    def __init__(self):
        self.stage, self.seconds = "export", {}
