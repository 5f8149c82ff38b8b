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

from .common import RETRIES, retry_transient, stage_record, task_options, warm_render_imports


@task(**task_options("load-sample"))
def load_sample(path: str, dest: str, key: str, config: PipelineConfig, name: str = "", load_kw: dict | None = None) -> dict:
    """Load + validate, canonical frame, Poisson-disk sample (PartError is final)."""
    return _record("load_sample", dest, lambda: library.load_sample(path, dest, config, load_kw))


@task(**task_options("polycube"))
def polycube_cloud(kind: str, path: str, loaded: str, dest: str, key: str, config: PipelineConfig, name: str = "") -> dict:
    """A per-part polycube cloud (``oracle`` sidecar, ``classical`` construction)."""
    return _record("polycube", dest, lambda: library.polycube_cloud(kind, path, loaded, dest, config))


@task(name="generate", cache_policy=NO_CACHE, retries=RETRIES, retry_delay_seconds=[5, 30],
      retry_condition_fn=retry_transient, task_run_name="generate-{name}")
def generate_batch(loaded: list[str], dests: list[str], n_out: list[int], key: str, checkpoint: str | None = None,
                   steps: int | None = None, seed: int = 0, device: str | None = None,
                   point_budget: int | None = None, name: str = "") -> list[dict]:
    """The diffusion model on one batch of parts (packed by the flow under a point budget):
    one cloud ``.npz`` per part.  Not cached as a batch: the flow skips the parts whose
    cloud already exists, so a batch is never recomputed for parts it already did."""
    from polycubenet import inference  # lazily: the model is optional for every other stage

    samples = [library.read_loaded(p)[1] for p in loaded]
    records = []

    def run():
        clouds = inference.generate([s.points for s in samples], n_out, model=checkpoint, steps=steps,
                                    seed=seed, device=device, point_budget=point_budget)
        meta = {"checkpoint": None if checkpoint is None else str(checkpoint), "steps": steps, "seed": seed}
        return [library.write_generated(np.asarray(c), d, meta) for c, d in zip(clouds, dests)]

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
                       name: str = "") -> dict:
    """Regular partition of the polycube, pulled back onto the part."""
    return _record("pullback", dest, lambda: library.partition_pullback(extracted, corr, loaded, dest, config))


@task(**task_options("export"))
def report_export(hexc: str, extracted: str, loaded: str, out_dir: str, key: str, formats: list[str],
                  name: str = "") -> dict:
    """Quality report against the input surface and the output files."""
    warm_render_imports()
    rec = stage_record("export", lambda: library.report_export(hexc, extracted, loaded, out_dir, formats, key=key, name=name or None),
                       done=lambda: library.load_json(Path(out_dir) / "result.json").get("key") == key)
    return {**rec, "path": str(out_dir)}


def _record(stage: str, dest: str, fn) -> dict:
    """:func:`stage_record` that reuses ``dest`` when an earlier run left it complete (atomic writes:
    a file with the final name is whole), and returns ``dest`` as the path either way."""
    rec = stage_record(stage, fn, done=lambda: Path(dest).is_file())
    return {**rec, "path": str(dest)}
