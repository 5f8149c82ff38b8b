"""``train``: make data → train (torchrun / DDP over the GPUs of the worker) → evaluate → publish.

Each step is the library's own command run by a task (:mod:`tasks.train`), so the flow
runs on any worker that has the project installed; the deployment puts it on a GPU work
pool.  Data generation is cached on its parameters; training resumes from
``RUN/last.pt`` after an interruption; the published checkpoint (EMA weights, written by
``polycubenet.evaluate --publish``) and its metrics appear in ``publish`` together, with
``latest.pt`` / ``latest.json`` pointing at the newest.
"""

from __future__ import annotations

import time
from pathlib import Path

from prefect import flow, get_run_logger

from polycubenet import library
from tasks.train import gpu_count, make_data, module_command, publish, run_command


def train_steps(data: str, run: str, eval_data: str, *, steps: int, preset: str, batch: int | None,
                points: int | None, nproc: int, resume: bool, eval_count: int, eval_steps: int | None) -> dict:
    """The training and evaluation command lines (pure: tested without running them)."""
    run_p = Path(run)
    targs = ["--data", data, "--out", run, "--preset", preset, "--steps", str(steps), "--eval-data", eval_data,
             "--no-progress"]
    if batch is not None:
        targs += ["--batch", str(batch)]
    if points is not None:
        targs += ["--points", str(points)]
    if not resume:
        targs += ["--no-resume"]
    eargs = ["--checkpoint", str(run_p / "last.pt"), "--data", eval_data, "--count", str(eval_count),
             "--json", str(run_p / "metrics.json"), "--publish", str(run_p / "published.pt")]
    if eval_steps is not None:
        eargs += ["--steps", str(eval_steps)]
    return {"train": module_command("polycubenet.train", targs, nproc),
            "evaluate": module_command("polycubenet.evaluate", eargs)}


@flow(name="train", log_prints=True)
def train(data: str, run: str, publish_to: str = "checkpoints/published", count: int = 1000, seed: int = 0,
          eval_data: str | None = None, eval_count: int = 50, steps: int = 2000, preset: str = "cpu",
          batch: int | None = None, points: int | None = None, gpus: int | None = None, resume: bool = True,
          eval_steps: int | None = None, n_cond: int = 2048, n_target: int = 2048) -> dict:
    """Train and publish a checkpoint (see the module docstring).

    ``gpus``: processes for torchrun (default: the GPUs of the worker; 0 or 1 -> one process).
    ``eval_data`` defaults to ``<data>-heldout`` generated with ``seed + 1`` (pairs disjoint
    from the training set).
    """
    logger = get_run_logger()
    target = publish_to
    eval_data = eval_data or str(Path(data).with_name(Path(data).name + "-heldout"))
    key = lambda c, s: library.stable_hash({"count": c, "seed": s, "n_cond": n_cond, "n_target": n_target})[:24]  # noqa: E731
    d1 = make_data.submit(data, count, seed, key=key(count, seed), n_cond=n_cond, n_target=n_target, name="train")
    d2 = make_data.submit(eval_data, eval_count, seed + 1, key=key(eval_count, seed + 1), n_cond=n_cond,
                          n_target=n_target, name="heldout")
    n = gpus if gpus is not None else gpu_count.submit().result()
    nproc = max(1, int(n))
    cmds = train_steps(data, run, eval_data, steps=steps, preset=preset, batch=batch, points=points, nproc=nproc,
                       resume=resume, eval_count=eval_count, eval_steps=eval_steps)
    logger.info(f"training on {nproc} process(es): {' '.join(cmds['train'])}")
    d1.result(), d2.result()  # a failed step fails the flow with its own error
    run_command(cmds["train"], str(Path(run) / "train.log"), name="train")
    run_command(cmds["evaluate"], str(Path(run) / "evaluate.log"), name="evaluate")
    name = f"polycubenet-{preset}-{time.strftime('%Y%m%d-%H%M%S')}"
    res = publish(str(Path(run) / "published.pt"), str(Path(run) / "metrics.json"), target, name)
    logger.info(f"published {res['checkpoint']}")
    return {"checkpoint": res["checkpoint"], "metrics": res["summary"], "nproc": nproc}
