"""Checkpoints that rebuild the model from the file alone.

Two kinds, one format (a ``torch.save`` dict, written atomically):

* ``train`` -- everything to resume: configs, raw and EMA weights, optimizer and
  scheduler state, step, RNG state, the training log's last metrics;
* ``published`` -- what inference needs (configs, EMA weights, optionally in float16
  to halve the file) plus the evaluation metrics and provenance; this is what the
  repository ships.

``load_checkpoint(path)`` reads either and returns a :class:`Loaded` with the model
(EMA weights by default), the diffusion and the metadata.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from ..atomic import atomic_path
from .config import ModelConfig
from .diffusion import Diffusion
from .network import PolycubeNet

FORMAT = 1


@dataclasses.dataclass
class Loaded:
    model: PolycubeNet
    diffusion: Diffusion
    meta: dict
    path: Path | None = None

    @property
    def config(self) -> ModelConfig:
        return self.model.config


def save_checkpoint(path: str | Path, state: dict) -> Path:
    """Write ``state`` (a dict with at least ``model_config``, ``diffusion`` and ``ema``) atomically."""
    for key in ("model_config", "diffusion", "ema"):
        if key not in state:
            raise ValueError(f"checkpoint state needs {key!r}")
    state = {"format": FORMAT, **state}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return path


def publish(train_ckpt: str | Path, out: str | Path, metrics: dict | None = None, half: bool = True,
            extra: dict | None = None) -> Path:
    """Strip a training checkpoint to the shipped form (configs + EMA weights + metrics)."""
    s = torch.load(train_ckpt, map_location="cpu", weights_only=False)
    ema = s["ema"]
    if half:
        ema = {k: (v.half() if v.is_floating_point() else v) for k, v in ema.items()}
    out_state = {
        "kind": "published",
        "model_config": s["model_config"],
        "diffusion": s["diffusion"],
        "ema": ema,
        "step": s.get("step"),
        "train_config": s.get("train_config"),
        "train_metrics": s.get("metrics"),
        "metrics": dict(metrics or {}),
        # cumulative CPU-hours of training behind these weights and where they came from, so a
        # run started from the published file (``train --init``) continues the count
        "cpu_hours": s.get("cpu_hours"),
        "gpu_hours": s.get("gpu_hours") or 0.0,  # and GPU-hours (runs on an accelerator), which CPU-hours leave out
        "lineage": s.get("lineage", []),
        **(extra or {}),
    }
    return save_checkpoint(out, out_state)


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu", weights: str = "ema") -> Loaded:
    """Rebuild the model from a checkpoint file (``weights``: ``"ema"`` or ``"model"``)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    try:
        s = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # a truncated or foreign file
        raise ValueError(f"checkpoint {path} cannot be read: {exc}") from exc
    if not isinstance(s, dict) or s.get("format") != FORMAT:
        raise ValueError(f"checkpoint {path}: not a PolycubeNet checkpoint (format {FORMAT})")
    cfg = ModelConfig.from_dict(s["model_config"])
    model = PolycubeNet(cfg)
    sd = s[weights] if weights in s else s["ema"]
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in sd.items()})
    model.to(device).eval()
    meta = {k: v for k, v in s.items() if k not in ("ema", "model", "optimizer", "scheduler", "rng")}
    return Loaded(model=model, diffusion=Diffusion.from_dict(s["diffusion"]), meta=meta, path=path)
