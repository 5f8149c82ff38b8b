"""Tasks of the training flow: run one command of the library (data, training, evaluation)
as a subprocess, count the GPUs of the worker, publish a checkpoint.

The commands are the library's own entry points (``python -m polycubenet.synth``,
``polycubenet.train`` -- under ``torchrun`` for several GPUs --, ``polycubenet.evaluate``);
their output goes to a log file next to the run.  A command killed by a signal (the OOM
killer, a pre-empted node) is retried; training resumes from ``RUN/last.pt``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from prefect import task
from prefect.cache_policies import NO_CACHE

from polycubenet.atomic import atomic_path, write_json

from .common import STAGE_CACHE


class CommandError(RuntimeError):
    """A command exited non-zero; ``returncode < 0`` means it was killed by a signal."""

    def __init__(self, cmd: list[str], returncode: int, log: str):
        self.cmd, self.returncode, self.log = cmd, returncode, log
        super().__init__(f"{' '.join(cmd)} exited with {returncode} (log: {log})")

    def __reduce__(self):
        return (type(self), (self.cmd, self.returncode, self.log))


def _killed(task, task_run, state) -> bool:
    exc = state.result(raise_on_failure=False)
    return isinstance(exc, CommandError) and exc.returncode < 0


def module_command(module: str, args: list[str], nproc: int = 1) -> list[str]:
    """``python -m module args`` or, for ``nproc > 1``, ``torchrun --nproc_per_node nproc -m module args``."""
    if nproc > 1:
        return [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={nproc}",
                "-m", module, *args]
    return [sys.executable, "-m", module, *args]


@task(name="command", cache_policy=NO_CACHE, retries=1, retry_delay_seconds=30, retry_condition_fn=_killed,
      task_run_name="{name}")
def run_command(cmd: list[str], log: str, name: str = "command", env: dict | None = None) -> dict:
    """Run ``cmd``; stdout and stderr go to ``log``.  Raises CommandError on failure."""
    Path(log).parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "a") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n")
        fh.flush()
        rc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, env={**os.environ, **(env or {})}).returncode
    if rc != 0:
        raise CommandError(cmd, rc, log)
    return {"cmd": cmd, "seconds": round(time.perf_counter() - t0, 2), "log": log}


@task(name="make-data", cache_policy=STAGE_CACHE, persist_result=True, retries=1, retry_condition_fn=_killed,
      task_run_name="make-data-{name}")
def make_data(out: str, count: int, seed: int, key: str, n_cond: int = 2048, n_target: int = 2048,
              name: str = "") -> dict:
    """Synthetic shards (``python -m polycubenet.synth``); cached on (count, seed, sizes)."""
    cmd = module_command("polycubenet.synth", ["--out", out, "--count", str(count), "--seed", str(seed),
                                               "--n-cond", str(n_cond), "--n-target", str(n_target), "--no-progress"])
    return run_command.fn(cmd, str(Path(out) / "synth.log"), name)


@task(name="gpu-count", cache_policy=NO_CACHE)
def gpu_count() -> int:
    """GPUs visible to the worker that runs this task."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


@task(name="publish", cache_policy=NO_CACHE, retries=2, retry_delay_seconds=5)
def publish(checkpoint: str, metrics: str, target: str, name: str) -> dict:
    """Copy ``checkpoint`` and its ``metrics`` JSON into ``target`` as ``<name>.pt`` / ``<name>.json``
    and point ``latest.pt`` / ``latest.json`` at them; every file appears whole (atomic rename)."""
    t = Path(target)
    t.mkdir(parents=True, exist_ok=True)
    m = json.loads(Path(metrics).read_text())
    summary = {k: v for k, v in m.items() if k != "rows"} if isinstance(m, dict) else m
    body = {"name": name, "checkpoint": f"{name}.pt", "published": time.strftime("%Y-%m-%dT%H:%M:%S"), "metrics": summary}
    for stem in (name, "latest"):
        with atomic_path(t / f"{stem}.pt") as tmp:
            shutil.copyfile(checkpoint, tmp)
        write_json(t / f"{stem}.json", body)
    return {"checkpoint": str(t / f"{name}.pt"), "metrics": str(t / f"{name}.json"), "summary": summary}
