"""Train PolycubeNet on synthetic shards: one command, resumable, CPU or (multi-)GPU.

    python -m polycubenet.train --data DIR --out RUN --preset cpu --steps 20000
    torchrun --nproc_per_node 4 -m polycubenet.train --data DIR --out RUN --preset paper ...

* Data: the shards of :mod:`polycubenet.synth` (condition = the shape's samples, target
  = the polycube's samples with axis normals), both subsampled at random to the
  training resolution every time a pair is drawn.  Augmentation keeps the pair
  consistent: the same random anisotropic scaling of shape and polycube (axis normals
  stay axis normals), re-normalised to diagonal 1, and a small jitter on the condition; with
  ``--mirror-aug P`` each axis of a pair is also mirrored with chance P (the canonical frame
  fixes the signs of x and y by the part's third moments, so by default a pair is never mirrored).
* AdamW, cosine decay with linear warm-up, gradient clipping, EMA weights, bf16
  autocast on CUDA, the hybrid loss of :class:`~polycubenet.model.Diffusion`.
* ``RUN/last.pt`` (``--out RUN``) is written atomically every ``--ckpt-every`` steps and at the end;
  ``--resume`` (the default when ``RUN/last.pt`` exists) continues from it, so a kill
  costs at most ``--ckpt-every`` steps.  ``RUN/log.jsonl`` gets one line per
  ``--log-every`` steps (loss, lr, held-out loss, seconds).
* Under ``torchrun`` (``WORLD_SIZE > 1``) it runs DDP (NCCL on GPUs, gloo on CPU); each
  rank draws its own pairs and only rank 0 writes.

A pair index drawn at step ``s`` by rank ``r`` comes from ``default_rng([seed, s, r])``,
so a resumed run draws exactly what the uninterrupted run would have drawn.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from . import tol
from .model import Diffusion, PolycubeNet, count_parameters, preset, to_network
from .model.checkpoint import save_checkpoint
from .model.config import ModelConfig
from .model.network import grow_identity
from .synth.shards import list_shards, load_shard


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    preset: str = "cpu"
    steps: int = 20000
    batch: int = 16  # global batch (split over ranks)
    points: int = 512  # training resolution of condition and target (paper: 4096)
    cond_points: int = 0  # > 0: the condition's own resolution (the part is sampled at 2048-4096 at inference)
    lr: float = 1e-4
    weight_decay: float = 0.01
    warmup: int = 500
    min_lr_ratio: float = 0.05
    clip: float = 1.0
    ema: float = 0.999
    loss: str = "hybrid"
    seed: int = 0
    scale_aug: float = 0.15  # anisotropic scale factors in [1 - a, 1 + a]
    jitter: float = 0.002  # condition jitter (diagonal units)
    mirror_aug: float = 0.0  # > 0: each axis of a drawn pair mirrored (x -> -x for shape, polycube, normals) with this chance
    eval_pairs: int = 32
    ckpt_every: int = 200
    log_every: int = 20
    threads: int = 0  # torch CPU threads (0: leave torch's default)
    # the diffusion recipe (defaults: the paper's -- eps prediction, cosine schedule, random pairing)
    prediction: str = "eps"  # eps | v
    schedule: str = "cosine"  # cosine | cosine_ztsnr | linear
    min_snr: float = 0.0  # Min-SNR-gamma loss weighting (0: off)
    pairing: str = "random"  # random | ot (noise matched to the target points by assignment)
    anchor_gain: float = 0.0  # > 0: the anchored model's displacement gain (ModelConfig.anchor_gain; 0: the preset's)
    t_bias: float = 1.0  # > 1: timesteps drawn towards the noisy end (Diffusion.training_loss)
    t_uniform: float = 0.0  # this fraction of pairs draws its timestep uniformly instead (Diffusion.training_loss)
    recycle: float = 0.0  # a recycling model (ModelConfig.recycle): the share of batches trained on a second evaluation
    max_genus: int = -1  # curriculum: train only on pairs of genus <= this (-1: all)
    reload_every: int = 0  # re-read the shard folder every this many steps (0: never), for shards still being written
    fit_steps: bool = False  # with a time limit: re-fit `steps` to the measured pace, so the cosine ends with the time
    fresh_lr_mult: float = 1.0  # the learning rate of parameters an --init file does not have (a new module), times this
    face_weight: float = 0.0  # > 0: each target point's loss weighted by its plane's share of the points to -this (face_weights)
    normal_weight: float = 1.0  # a point's error along its target normal (across its plane) weighs this much (Diffusion.training_loss)
    slant_weight: float = 0.0  # > 0: a point on a slanted face of the part weighs 1 + this (slant_weights)
    genus_drop: float = 0.1  # a model told the genus (ModelConfig.genus_classes): the share of pairs told "unknown"


def _cond_points(cfg: "TrainConfig | None", points: int) -> int:
    """The condition's resolution of a draw: ``cfg.cond_points`` when set, else the targets' ``points``."""
    return cfg.cond_points if cfg is not None and cfg.cond_points else points


def _share(parts: list[dict], cat: dict) -> None:
    """Point each cached shard's arrays into the concatenated ones (``cat``, shards in order), so the
    pairs are held once: a copy per shard beside the concatenation doubled the memory (28 672 pairs:
    10 GB, and two runs side by side did not fit in 24 GB)."""
    start = 0
    for d in parts:
        n = len(d["genus"])
        for k, a in cat.items():
            d[k] = a[start:start + n]
        start += n


class PairData:
    """All pairs of a shard folder in memory (float32, each pair once), with per-draw subsampling."""

    def __init__(self, directory: str | Path, limit: int | None = None, max_genus: int = -1,
                 cache: dict | None = None):
        """``cache`` (a dict the caller keeps) holds each shard's arrays and anchor normals by path,
        so re-reading a growing folder (``reload_every``) loads and processes only the new shards."""
        shards = list_shards(directory)
        if not shards:
            raise FileNotFoundError(f"no shard-*.npz in {directory} (make them with python -m polycubenet.synth)")
        self._cache = {} if cache is None else cache
        names = ("cond_points", "cond_normals", "target_points", "target_normals", "target_on_shape", "genus", "seeds")
        parts: list[dict] = []
        self._shard_paths: list[Path] = []
        n = 0
        for path in shards:
            key = str(path.resolve())
            if key not in self._cache:
                s = load_shard(path)
                self._cache[key] = {k: s[k] for k in names}
            parts.append(self._cache[key])
            self._shard_paths.append(path)
            n += len(parts[-1]["genus"])
            if limit is not None and n >= limit:
                break
        cat = {k: np.concatenate([d[k] for d in parts])[:limit] for k in names}
        if limit is None and max_genus < 0:
            _share(parts, cat)
        self.cond = cat["cond_points"]
        self.target_points = cat["target_points"]
        self.target_normals = cat["target_normals"]
        self.target_on_shape = cat["target_on_shape"]  # the part's point of each target point
        self.cond_normals = cat["cond_normals"]
        self._anchor_normals: np.ndarray | None = None
        self._limit = limit
        self._keep: np.ndarray | None = None
        self.genus = cat["genus"]
        self.seeds = cat["seeds"]
        if max_genus >= 0:
            keep = self.genus <= max_genus
            if not keep.any():
                raise ValueError(f"no pair of genus <= {max_genus} in {directory}")
            self._keep = keep
            for name in ("cond", "cond_normals", "target_points", "target_normals", "target_on_shape", "genus", "seeds"):
                setattr(self, name, getattr(self, name)[keep])
        self.directory = Path(directory)
        self.shards = len(shards)

    def __len__(self) -> int:
        return len(self.cond)

    @property
    def anchor_normals(self) -> np.ndarray:
        """The part's unit normal at each target point's part point (``target_on_shape``): the
        normal of the nearest condition point (computed once per shard, on first use)."""
        if self._anchor_normals is None:
            from scipy.spatial import cKDTree

            per_shard = []
            for path in self._shard_paths:
                d = self._cache[str(path.resolve())]
                if "anchor_normals" not in d:
                    out = np.empty_like(d["target_on_shape"])
                    for i in range(len(out)):
                        _, j = cKDTree(d["cond_points"][i]).query(d["target_on_shape"][i])
                        out[i] = d["cond_normals"][i][j]
                    d["anchor_normals"] = out
                per_shard.append(d["anchor_normals"])
            an = np.concatenate(per_shard)[:self._limit]
            if self._limit is None and self._keep is None:
                _share([self._cache[str(p.resolve())] for p in self._shard_paths], {"anchor_normals": an})
            self._anchor_normals = an if self._keep is None else an[self._keep]
        return self._anchor_normals

    def batch(self, idx: np.ndarray, points: int, rng: np.random.Generator, cfg: TrainConfig | None = None,
              anchors: int = 0):
        """``(x0, cond)`` for pairs ``idx`` (target xyz + normals, condition xyz; the canonical frame's
        units), augmented when ``cfg`` is given; with ``anchors`` (3, or True: the part point of each
        target point; 6: that point and the part's normal there) also ``(x0, cond, anchor)``,
        augmented alike."""
        B = len(idx)
        N, M = self.cond.shape[1], self.target_points.shape[1]
        ci, ti = _subsample(rng, B, N, _cond_points(cfg, points)), _subsample(rng, B, M, points)
        g = np.take_along_axis(self.cond[idx], ci[..., None], axis=1).astype(np.float64)
        p = np.take_along_axis(self.target_points[idx], ti[..., None], axis=1).astype(np.float64)
        nrm = np.take_along_axis(self.target_normals[idx], ti[..., None], axis=1).astype(np.float32)
        a = np.take_along_axis(self.target_on_shape[idx], ti[..., None], axis=1).astype(np.float64)
        an = np.take_along_axis(self.anchor_normals[idx], ti[..., None], axis=1).astype(np.float64) if anchors == 6 else None
        if cfg is not None and cfg.scale_aug > 0:
            s = rng.uniform(1 - cfg.scale_aug, 1 + cfg.scale_aug, size=(B, 1, 3))
            g, p, a = g * s, p * s, a * s
            if an is not None:  # a normal transforms with the inverse scale
                an = an / s
                an /= np.maximum(np.linalg.norm(an, axis=-1, keepdims=True), 1e-12)
            # back to diagonal 1 (as frame.canonicalize would) using the full condition cloud
            full = self.cond[idx].astype(np.float64) * s
            diag = np.linalg.norm(full.max(axis=1) - full.min(axis=1), axis=-1)[:, None, None]
            g, p, a = g / diag, p / diag, a / diag
        if cfg is not None and cfg.jitter > 0:
            g = g + rng.normal(scale=cfg.jitter, size=g.shape)
        if cfg is not None and cfg.mirror_aug > 0:
            m = np.where(rng.random((B, 1, 3)) < cfg.mirror_aug, -1.0, 1.0)
            g, p, a, nrm = g * m, p * m, a * m, nrm * m.astype(np.float32)
            if an is not None:
                an = an * m
        out = (torch.from_numpy(np.concatenate([p.astype(np.float32), nrm], axis=-1)),
               torch.from_numpy(g.astype(np.float32)))
        if an is not None:
            a = np.concatenate([a, an], axis=-1)
        return out + (torch.from_numpy(a.astype(np.float32)),) if anchors else out


class DevicePairs:
    """The arrays of a :class:`PairData` on the training device, with :meth:`PairData.batch`'s draw
    (subsampling, anisotropic scaling, re-normalisation, jitter) done there in torch.

    On a GPU the numpy batch builder on one core bounds the step (session 7: ~5 steps/s of 128 with
    the GPU ~1 % busy); here a batch is a few gathers on the device.  The draw has the same law as
    :meth:`PairData.batch`, not the same numbers (torch's generator, float32 arithmetic)."""

    def __init__(self, data: PairData, dev: torch.device, anchors: int = 0):
        def put(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).to(dev)

        self.cond, self.target_points = put(data.cond), put(data.target_points)
        self.target_normals, self.target_on_shape = put(data.target_normals), put(data.target_on_shape)
        self.anchor_normals = put(data.anchor_normals) if anchors == 6 else None
        self.anchors, self.dev = anchors, dev

    def __len__(self) -> int:
        return int(self.cond.shape[0])

    def batch(self, idx: np.ndarray, points: int, gen: torch.Generator, cfg: TrainConfig | None = None):
        """``(x0, cond[, anchor])`` on the device for pairs ``idx``, as :meth:`PairData.batch` returns them."""
        i = torch.as_tensor(np.asarray(idx), device=self.dev, dtype=torch.long)
        B, N, M = len(i), self.cond.shape[1], self.target_points.shape[1]

        def pick(arr: torch.Tensor, sub: torch.Tensor) -> torch.Tensor:
            return torch.gather(arr[i], 1, sub[..., None].expand(-1, -1, arr.shape[-1]))

        ci, ti = self._subsample(B, N, _cond_points(cfg, points), gen), self._subsample(B, M, points, gen)
        g, p = pick(self.cond, ci), pick(self.target_points, ti)
        nrm, a = pick(self.target_normals, ti), pick(self.target_on_shape, ti)
        an = pick(self.anchor_normals, ti) if self.anchor_normals is not None else None
        if cfg is not None and cfg.scale_aug > 0:
            s = 1 - cfg.scale_aug + 2 * cfg.scale_aug * torch.rand((B, 1, 3), generator=gen, device=self.dev)
            g, p, a = g * s, p * s, a * s
            if an is not None:  # a normal transforms with the inverse scale
                an = an / s
                an = an / an.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            full = self.cond[i] * s  # back to diagonal 1 on the full condition cloud
            diag = (full.amax(dim=1) - full.amin(dim=1)).norm(dim=-1)[:, None, None]
            g, p, a = g / diag, p / diag, a / diag
        if cfg is not None and cfg.jitter > 0:
            g = g + cfg.jitter * torch.randn(g.shape, generator=gen, device=self.dev)
        if cfg is not None and cfg.mirror_aug > 0:
            flip = torch.rand((B, 1, 3), generator=gen, device=self.dev) < cfg.mirror_aug
            m = 1.0 - 2.0 * flip.to(g.dtype)
            g, p, a, nrm = g * m, p * m, a * m, nrm * m
            if an is not None:
                an = an * m
        out = (torch.cat([p, nrm], dim=-1), g)
        if an is not None:
            a = torch.cat([a, an], dim=-1)
        return out + (a,) if self.anchors else out

    def _subsample(self, B: int, N: int, points: int, gen: torch.Generator) -> torch.Tensor:
        if points > N:
            return torch.randint(0, N, (B, points), generator=gen, device=self.dev)
        return torch.rand((B, N), generator=gen, device=self.dev).topk(points, dim=1).indices


def draw_raw(data: PairData, on_device: DevicePairs | None, idx: np.ndarray, rng: np.random.Generator,
             cfg: TrainConfig, mcfg: ModelConfig, dev) -> tuple:
    """The batch of pairs ``idx`` in the canonical frame's units (target xyz + normals, condition,
    anchors): drawn on the device by ``on_device`` when given (its generator seeded from ``rng``),
    else by :meth:`PairData.batch` with ``rng``."""
    if on_device is not None:
        gen = torch.Generator(device=dev).manual_seed(int(rng.integers(2**62)))
        return on_device.batch(idx, cfg.points, gen, cfg)
    return data.batch(idx, cfg.points, rng, cfg, anchors=mcfg.anchor_dim)


def draw_batch(data: PairData, on_device: DevicePairs | None, idx: np.ndarray, rng: np.random.Generator,
               cfg: TrainConfig, mcfg: ModelConfig, dev) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``(x0, cond, anchor)`` in network units for pairs ``idx`` (:func:`draw_raw`)."""
    return _to_net(draw_raw(data, on_device, idx, rng, cfg, mcfg, dev), mcfg, dev)


def slant_weights(anchor: torch.Tensor, gain: float, deg: float = tol.SLANT_DEG) -> torch.Tensor:
    """``(B, N)`` loss weights from the anchors (``(B, N, 6)``: part xyz + the part's unit normals): ``1 + gain``
    on a point whose part normal is more than ``deg`` from every axis (a slanted face, chamfer or ramp),
    1 elsewhere, scaled to mean 1 over the batch.

    A slanted face's points must travel furthest (a whole slanted end onto its end plane) and are a small
    share of the points; the one-step model takes them only part of the way, 0.49 of it at 21 CPU-hours and 0.73 at
    64 (``benchmarks/slant_moves.py``): the weight gives them a larger share of the gradient, where a
    per-point weight does not move the optimum of a deterministic target, only how soon it is reached.
    Session 32, weight 4 against none at equal CPU time: no change (0.73 against 0.72; model card)."""
    n = anchor[..., 3:6].float()
    cos = n.abs().amax(dim=-1) / n.norm(dim=-1).clamp_min(1e-12)
    w = 1.0 + gain * (cos < float(np.cos(np.radians(deg)))).float()
    return w / w.mean()


def face_weights(x0: torch.Tensor, power: float, tol: float = 0.005, cap: float = 10.0) -> torch.Tensor:
    """``(B, N)`` loss weights of target points ``x0`` (``(B, N, 6)``: polycube xyz + axis normals, the
    canonical frame's units), each ``share ** -power`` with ``share`` the fraction of its pair's points
    on the same plane (same axis and side, coordinate within ``tol``), capped at ``cap`` times the
    pair's mean, then scaled to mean 1 per pair.

    The points sample the polycube's surface by area, so a thin slab's faces carry a few points of
    the 512 and an L2 loss over points hardly notices when they are put on a neighbouring plane;
    yet every plane counts alike for the structure (session 22: 75 % of the planes a held-out
    extraction missed had no generated point on them)."""
    p, n = x0[..., :3].float(), x0[..., 3:6].float()
    axis = n.abs().argmax(dim=-1, keepdim=True)
    side = torch.gather(n, -1, axis) > 0
    coord = torch.gather(p, -1, axis)
    same = ((axis == axis.transpose(1, 2)) & (side == side.transpose(1, 2))
            & ((coord - coord.transpose(1, 2)).abs() < tol))
    w = same.float().mean(dim=-1).pow(-power)
    w = w / w.mean(dim=-1, keepdim=True)
    w = w.clamp(max=cap)
    return w / w.mean(dim=-1, keepdim=True)


def _subsample(rng: np.random.Generator, B: int, N: int, points: int) -> np.ndarray:
    """``(B, points)`` indices into ``N`` points: distinct within a row when ``points <= N``."""
    if points > N:
        return rng.integers(0, N, size=(B, points))
    return np.argpartition(rng.random((B, N)), points - 1, axis=1)[:, :points]


def lr_at(step: int, cfg: TrainConfig) -> float:
    """Linear warm-up then cosine decay to ``min_lr_ratio * lr``."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    frac = min(1.0, (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
    return cfg.lr * (cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * frac)))


@torch.no_grad()
def ema_update(ema: torch.nn.Module, model: torch.nn.Module, decay: float) -> None:
    """``ema = decay * ema + (1 - decay) * model``, in two fused list operations (a GPU step of
    this small model is bound by kernel launches, one pair per tensor otherwise)."""
    pe = list(ema.parameters())
    torch._foreach_mul_(pe, decay)
    torch._foreach_add_(pe, [p.detach() for p in model.parameters()], alpha=1 - decay)


def _param_groups(model: torch.nn.Module, fresh: set[str], mult: float) -> list[dict]:
    """AdamW groups: the parameters named in ``fresh`` (not taken from an ``--init`` file) with
    learning rate times ``mult``, the rest times 1 (``lr_mult`` of each group)."""
    named = list(model.named_parameters())
    new = [p for n, p in named if n in fresh]
    groups = [{"params": [p for n, p in named if n not in fresh], "lr_mult": 1.0}]
    if new:
        groups.append({"params": new, "lr_mult": float(mult)})
    return groups


def _widen_anchor_embed(src: dict, own: dict, mcfg: ModelConfig) -> dict:
    """Starting an ``anchor_normals`` model from an anchored one without them: the denoiser's input
    projection gets zero columns for the anchor's normal and keeps every other column, so the new
    model starts as exactly the old function."""
    key = "denoiser.embed.proj.weight"
    old_cfg = ModelConfig.from_dict(src["model_config"]) if src.get("model_config") else None
    if (old_cfg is None or not mcfg.anchor_normals or not old_cfg.anchored or old_cfg.anchor_normals
            or key not in src["ema"] or key not in own):
        return {}
    w_old, w_new = src["ema"][key].float(), own[key]
    if w_new.shape[1] != w_old.shape[1] + 3:
        return {}
    w = torch.zeros_like(w_new)
    w[:, :3] = w_old[:, :3]  # anchor xyz
    w[:, 6:] = w_old[:, 3:]  # x_t and the Fourier features; columns 3..5 (the anchor's normal) start at 0
    return {key: w}


def _widen_hidden(src: dict, own: dict) -> dict:
    """Starting a model with wider feed-forward layers from one with narrower ones (a preset with a
    larger ``write_mlp_ratio``): each layer keeps the old hidden units as its first ones, the added
    units keep their fresh input weights and get zero output weights, so the new model starts as
    exactly the old function and the added units learn from the first step."""
    out = {}
    for key, w_new in own.items():
        if not key.endswith((".net.0.weight", ".net.0.bias", ".net.2.weight")) or key not in src:
            continue
        w_old = src[key].float()
        if w_old.shape == w_new.shape or w_old.dim() != w_new.dim():
            continue
        if key.endswith(".net.2.weight"):  # (dim, hidden): the added columns start at zero
            if w_old.shape[0] != w_new.shape[0] or w_old.shape[1] > w_new.shape[1]:
                continue
            w = torch.zeros_like(w_new)
            w[:, : w_old.shape[1]] = w_old
        else:  # (hidden, dim) or (hidden,): the added rows keep their fresh initialisation
            if w_old.shape[1:] != w_new.shape[1:] or w_old.shape[0] > w_new.shape[0]:
                continue
            w = w_new.detach().clone().float()
            w[: w_old.shape[0]] = w_old
        out[key] = w
    return out


@torch.no_grad()
def _to_net(batch, mcfg: ModelConfig, dev) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``(x0, cond, anchor)`` in network units on ``dev`` (anchor None for a free-point model)."""
    from .model.diffusion import anchored_to_network

    x0, cond = batch[0].to(dev), batch[1].to(dev)
    cond = to_network(cond, None, mcfg.xyz_scale)
    if mcfg.anchored:
        x0, anchor = anchored_to_network(batch[2].to(dev), x0[..., :3], x0[..., 3:], mcfg.xyz_scale, mcfg.anchor_gain)
        return x0, cond, anchor
    return to_network(x0[..., :3], x0[..., 3:], mcfg.xyz_scale), cond, None


def heldout_loss(model, diffusion: Diffusion, x0: torch.Tensor, cond: torch.Tensor, seed: int = 0,
                 anchor: torch.Tensor | None = None, genus: torch.Tensor | None = None) -> float:
    """Mean L2 error of the recipe's prediction target (noise, or v) at fixed timesteps and noise
    (comparable across the steps of one run, not across recipes: compare those with evaluate)."""
    g = torch.Generator(device=x0.device).manual_seed(seed)
    B = x0.shape[0]
    t = torch.linspace(0, diffusion.T - 1, B, device=x0.device).long()
    noise = torch.randn(x0.shape, generator=g, device=x0.device)
    extra = ({} if anchor is None else {"anchor": anchor}) | ({} if genus is None else {"genus": genus})
    out = model(diffusion.q_sample(x0, t, noise), t, cond, **extra)
    target = noise
    if diffusion.prediction == "v":
        ab = diffusion._ab(t, x0)
        target = ab.sqrt() * noise - (1 - ab).sqrt() * x0
    return float((out.float() - target).pow(2).mean())


def _dist_env() -> tuple[int, int, int]:
    return int(os.environ.get("RANK", 0)), int(os.environ.get("WORLD_SIZE", 1)), int(os.environ.get("LOCAL_RANK", 0))


def diffusion_of(cfg: TrainConfig) -> Diffusion:
    """The diffusion recipe of a training config."""
    return Diffusion(schedule=cfg.schedule, prediction=cfg.prediction, min_snr=cfg.min_snr or None,
                     pairing=cfg.pairing)


def train(data_dir: str | Path, run_dir: str | Path, cfg: TrainConfig, *, eval_dir: str | Path | None = None,
          resume: bool = True, device: str | None = None, progress: bool = True, max_seconds: float | None = None,
          model_config: ModelConfig | None = None, init: str | Path | None = None,
          max_cpu_seconds: float | None = None, prior_cpu_hours: float = 0.0) -> dict:
    """Train (or resume) into ``run_dir``; returns the final metrics dict.

    ``max_seconds`` (wall) and ``max_cpu_seconds`` (this process's CPU time, all threads)
    stop cleanly (checkpoint written), so a session-limited job can be continued later
    with the same command, and ablations can be run at equal CPU time.

    ``init`` starts a new run from another checkpoint's EMA weights (e.g. the published
    one the repository ships) with a fresh optimizer and warm-up; its cumulative CPU-hours
    (``cpu_hours`` in its metadata, plus ``prior_cpu_hours`` for training it does not record)
    carry over into this run's.
    """
    if cfg.recycle > 0 and not (model_config or preset(cfg.preset)).recycle:
        raise ValueError(f"--recycle {cfg.recycle} needs a model that takes its previous estimate: preset "
                         f"{cfg.preset!r} has ModelConfig.recycle False (e.g. --preset cpu-anchored-normals-recycle)")
    rank, world, local = _dist_env()
    if device is None:
        device = f"cuda:{local}" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda":
        torch.cuda.set_device(dev)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    ddp = world > 1
    if ddp:
        import torch.distributed as dist

        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo")
    run = Path(run_dir)
    if rank == 0:
        run.mkdir(parents=True, exist_ok=True)
    mcfg = model_config or preset(cfg.preset)
    if cfg.anchor_gain > 0:  # the scale displacements have in network units, next to unit normals and noise
        mcfg = dataclasses.replace(mcfg, anchor_gain=float(cfg.anchor_gain))
    diffusion = diffusion_of(cfg)
    torch.manual_seed(cfg.seed)
    model = PolycubeNet(mcfg).to(dev)
    cpu_before = float(prior_cpu_hours) * 3600.0  # CPU-seconds of training behind this run's weights
    gpu_before = 0.0  # GPU-seconds likewise (wall time of runs on an accelerator, which add no CPU-hours)
    lineage: list = []
    fresh: list[str] = []  # parameters not taken from --init (their own learning rate: cfg.fresh_lr_mult)
    ckpt = run / "last.pt"
    if init is not None and not (resume and ckpt.exists()):
        src = torch.load(init, map_location="cpu", weights_only=False)
        # every tensor of the same name and shape is taken (so a model that only adds an input, like
        # the anchored one, starts from the other's weights); the rest keeps its fresh initialisation
        own = model.state_dict()
        take = {k: (v.float() if v.is_floating_point() else v) for k, v in src["ema"].items()
                if k in own and own[k].shape == v.shape}
        take.update(_widen_anchor_embed(src, own, mcfg))
        take.update(_widen_hidden(src["ema"], own))
        model.load_state_dict(take, strict=False)
        fresh = sorted(set(own) - set(take))
        # latent layers the file does not have (a deeper preset) start as identities: the same function
        grown = grow_identity(model, set(fresh))
        if fresh and rank == 0:
            print(f"[train] --init {init}: {len(take)} tensors taken, {len(fresh)} kept fresh: {', '.join(fresh)}"
                  + (f"; {len(grown)} added latent layers start as identities" if grown else ""), flush=True)
        cpu_before = (float(src.get("cpu_hours") or 0.0) + float(prior_cpu_hours)) * 3600.0
        gpu_before = float(src.get("gpu_hours") or 0.0) * 3600.0
        lineage = list(src.get("lineage", [])) + [{"init": str(init), "step": src.get("step"),
                                                   "diffusion": src.get("diffusion")}]
    ema = copy.deepcopy(model).eval()
    for p in ema.parameters():
        p.requires_grad_(False)
    step = 0
    s = torch.load(ckpt, map_location="cpu", weights_only=False) if resume and ckpt.exists() else None
    if s is not None:
        fresh = list(s.get("fresh", []))
    opt = torch.optim.AdamW(_param_groups(model, set(fresh), cfg.fresh_lr_mult), lr=cfg.lr,
                            weight_decay=cfg.weight_decay)
    if s is not None:
        saved = ModelConfig.from_dict(s["model_config"])
        if dataclasses.replace(saved, chunk=mcfg.chunk) != mcfg:  # chunk is an inference setting
            raise ValueError(f"{ckpt} was trained with another model config; use a new --run folder")
        model.load_state_dict(s["model"])
        ema.load_state_dict(s["ema"])
        opt.load_state_dict(s["optimizer"])
        step = int(s["step"])
        cpu_before = float(s.get("cpu_hours", 0.0)) * 3600.0
        gpu_before = float(s.get("gpu_hours") or 0.0) * 3600.0
        lineage = list(s.get("lineage", []))
        if s.get("diffusion") and Diffusion.from_dict(s["diffusion"]).to_dict() != diffusion.to_dict():
            raise ValueError(f"{ckpt} was trained with diffusion {s['diffusion']}, not {diffusion.to_dict()}; "
                             f"use a new --out folder (with --init {ckpt} to start from it)")
    shard_cache: dict = {}  # each shard's arrays, loaded once however often the folder is re-read
    data = PairData(data_dir, max_genus=cfg.max_genus, cache=shard_cache)
    # on a GPU the batches are drawn there (DevicePairs); on a CPU by PairData.batch, the drawn numbers
    # reproducible across a resume
    on_device = DevicePairs(data, dev, mcfg.anchor_dim) if dev.type == "cuda" else None
    heldout = None
    heldout_genus = None
    if eval_dir is not None and rank == 0:
        ev = PairData(eval_dir, limit=cfg.eval_pairs)
        # no augmentation, the condition at the run's own resolution (cond_points)
        plain = dataclasses.replace(cfg, scale_aug=0.0, jitter=0.0, mirror_aug=0.0)
        heldout = _to_net(ev.batch(np.arange(len(ev)), cfg.points, np.random.default_rng(12345), plain,
                                   anchors=mcfg.anchor_dim), mcfg, dev)
        if mcfg.genus_classes:
            heldout_genus = torch.as_tensor(ev.genus, dtype=torch.long, device=dev)
    net = model
    if ddp:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if dev.type == "cuda" else None
    per_rank = max(1, cfg.batch // world)
    if rank == 0:
        print(f"[train] {count_parameters(model):,} parameters, preset {cfg.preset}, {len(data)} pairs, "
              f"{world} process(es) on {dev}, batch {per_rank * world} x {cfg.points} points, from step {step}",
              flush=True)
    t_start = time.time()
    c_start = time.process_time()
    window: list[float] = []
    fit_from: tuple[int, float] | None = None
    metrics: dict = {}
    log_path = run / "log.jsonl"
    bar = None
    if progress and rank == 0 and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=cfg.steps, initial=step, desc="train", unit="step")
    while step < cfg.steps:
        if cfg.reload_every and step % cfg.reload_every == 0 and len(list_shards(data_dir)) != data.shards:
            data = PairData(data_dir, max_genus=cfg.max_genus, cache=shard_cache)
            on_device = DevicePairs(data, dev, mcfg.anchor_dim) if on_device is not None else None
            if rank == 0:
                print(f"[train] step {step}: {len(data)} pairs from {data.shards} shards", flush=True)
        rng = np.random.default_rng([cfg.seed, step, rank])
        idx = rng.integers(0, len(data), size=per_rank)
        raw = draw_raw(data, on_device, idx, rng, cfg, mcfg, dev)
        x0, cond, anchor = _to_net(raw, mcfg, dev)
        weight = face_weights(raw[0].to(dev), cfg.face_weight) if cfg.face_weight > 0 else None
        if cfg.slant_weight > 0:
            if raw[2] is None or raw[2].shape[-1] < 6:
                raise ValueError("--slant-weight needs an anchored model with anchor normals")
            sw = slant_weights(raw[2].to(dev), cfg.slant_weight)
            weight = sw if weight is None else weight * sw
        for group in opt.param_groups:
            group["lr"] = lr_at(step, cfg) * group.get("lr_mult", 1.0)
        gen = torch.Generator(device=dev).manual_seed(int(rng.integers(2**62)))
        genus = None
        if mcfg.genus_classes:  # drawn after the rest, so a seed's pairs, noise and timesteps stay a plain run's
            g = np.where(rng.random(len(idx)) < cfg.genus_drop, -1, np.asarray(data.genus)[idx])
            genus = torch.as_tensor(g, dtype=torch.long, device=dev)
        model.train()
        loss, stats = diffusion.training_loss(net, x0, cond, loss=cfg.loss, generator=gen, autocast=autocast,
                                              anchor=anchor, t_bias=cfg.t_bias,
                                              t_uniform=cfg.t_uniform, recycle=cfg.recycle, point_weight=weight,
                                              normal_weight=cfg.normal_weight, genus=genus)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        gnorm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip))
        opt.step()
        ema_update(ema, model, cfg.ema if step >= cfg.warmup else 0.0 if step == 0 else min(cfg.ema, 0.99))
        step += 1
        window.append(stats["l2"])
        if bar is not None:
            bar.update(1)
            bar.set_postfix(l2=f"{np.mean(window[-20:]):.4f}")
        last = step == cfg.steps
        out_of_time = ((max_seconds is not None and time.time() - t_start > max_seconds)
                       or (max_cpu_seconds is not None and time.process_time() - c_start > max_cpu_seconds))
        on_gpu = dev.type == "cuda"
        cpu_hours = (cpu_before + (0.0 if on_gpu else time.process_time() - c_start)) / 3600.0
        gpu_hours = (gpu_before + (time.time() - t_start if on_gpu else 0.0)) / 3600.0
        if cfg.fit_steps and max_seconds is not None and step % cfg.log_every == 0:
            if fit_from is None:  # the pace is measured from the first log on (start-up excluded)
                fit_from = (step, time.time())
            elif time.time() > fit_from[1] + 1.0:
                pace = (step - fit_from[0]) / (time.time() - fit_from[1])
                left = max_seconds - (time.time() - t_start)
                cfg = dataclasses.replace(cfg, steps=max(step + 1, int(step + pace * left)))
        if ddp:  # every rank stops together when rank 0 runs out of time
            flag = torch.tensor([int(out_of_time)], device=dev)
            torch.distributed.broadcast(flag, 0)
            out_of_time = bool(flag.item())
        if rank == 0 and (step % cfg.log_every == 0 or last or out_of_time):
            metrics = {"step": step, "loss_l2": float(np.mean(window)), "lr": lr_at(step - 1, cfg), "grad_norm": gnorm,
                       "seconds": round(time.time() - t_start, 1), "cpu_hours": round(cpu_hours, 4),
                       "gpu_hours": round(gpu_hours, 4), "steps": cfg.steps,
                       "pairs": len(data), "loss": cfg.loss}
            window = []
            if heldout is not None:
                ema.eval()
                metrics["heldout_l2"] = heldout_loss(ema, diffusion, *heldout[:2], anchor=heldout[2], genus=heldout_genus)
            with open(log_path, "a") as fh:
                fh.write(json.dumps(metrics) + "\n")
            if bar is None and progress:
                print(f"[train] step {step}/{cfg.steps} " + " ".join(
                    f"{k}={v:.4g}" for k, v in metrics.items() if isinstance(v, float)), flush=True)
        if rank == 0 and (step % cfg.ckpt_every == 0 or last or out_of_time):
            save_checkpoint(ckpt, {
                "kind": "train", "model_config": mcfg.to_dict(), "diffusion": diffusion.to_dict(),
                "train_config": dataclasses.asdict(cfg), "data": str(data.directory), "pairs": len(data),
                "model": model.state_dict(), "ema": ema.state_dict(), "optimizer": opt.state_dict(),
                "step": step, "metrics": metrics, "world_size": world, "device": str(dev),
                "cpu_hours": cpu_hours, "gpu_hours": gpu_hours, "lineage": lineage, "fresh": fresh,
            })
        if out_of_time:
            break
    if bar is not None:
        bar.close()
    if ddp:
        torch.distributed.barrier()
        torch.distributed.destroy_process_group()
    return {"step": step, **metrics}


def recipe_flags(checkpoint: str | Path) -> list[str]:
    """The ``train`` flags of the recipe a checkpoint was trained with (preset, diffusion, points,
    condition points, batch, anchor gain, t bias and its uniform share, recycling share,
    face weight, normal weight, slant weight, genus drop, mirror share), so a run continues it
    (``scripts/train_session.sh``, ``scripts/device_train.sh``; a later ``--batch`` on the command line wins)."""
    s = torch.load(checkpoint, map_location="cpu", weights_only=False)
    d, tc = s.get("diffusion") or {}, s.get("train_config") or {}
    return ["--preset", tc.get("preset", "cpu"),
            "--prediction", d.get("prediction", "eps"), "--schedule", d.get("schedule", "cosine"),
            "--pairing", d.get("pairing", "random"), "--min-snr", str(d.get("min_snr") or 0),
            "--points", str(tc.get("points", 512)), "--cond-points", str(tc.get("cond_points", 0)),
            "--batch", str(tc.get("batch", 12)), "--anchor-gain", str((s.get("model_config") or {}).get("anchor_gain", 0.0)),
            "--t-bias", str(tc.get("t_bias", 1.0)), "--t-uniform", str(tc.get("t_uniform", 0.0)),
            "--recycle", str(tc.get("recycle", 0.0)), "--face-weight", str(tc.get("face_weight", 0.0)),
            "--normal-weight", str(tc.get("normal_weight", 1.0)), "--slant-weight", str(tc.get("slant_weight", 0.0)),
            "--genus-drop", str(tc.get("genus_drop", 0.1)), "--mirror-aug", str(tc.get("mirror_aug", 0.0))]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polycubenet.train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="shard folder (python -m polycubenet.synth)")
    ap.add_argument("--out", required=True, help="run folder (last.pt, log.jsonl)")
    ap.add_argument("--eval-data", help="held-out shard folder for the held-out loss")
    ap.add_argument("--no-resume", action="store_true", help="start over even if RUN/last.pt exists")
    ap.add_argument("--device", help="cpu, cuda, cuda:1 (default: cuda:LOCAL_RANK when available)")
    ap.add_argument("--max-minutes", type=float, help="stop cleanly (checkpoint written) after this long")
    ap.add_argument("--max-cpu-minutes", type=float,
                    help="stop cleanly after this much CPU time of this process (ablations at equal CPU time)")
    ap.add_argument("--init", help="start a new run from this checkpoint's EMA weights (e.g. the shipped one)")
    ap.add_argument("--prior-cpu-hours", type=float, default=0.0,
                    help="CPU-hours of training behind --init that its file does not record (added to what it does)")
    ap.add_argument("--no-progress", action="store_true")
    for f in dataclasses.fields(TrainConfig):
        kind = type(f.default)
        if kind is bool:  # --flag true|false (bool("false") would be True)
            kind = lambda v: str(v).lower() in ("1", "true", "yes", "on")  # noqa: E731
        ap.add_argument("--" + f.name.replace("_", "-"), type=kind, default=f.default)
    args = ap.parse_args(argv)
    cfg = TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})
    out = train(args.data, args.out, cfg, eval_dir=args.eval_data, resume=not args.no_resume, device=args.device,
                progress=not args.no_progress, max_seconds=None if args.max_minutes is None else 60 * args.max_minutes,
                init=args.init, max_cpu_seconds=None if args.max_cpu_minutes is None else 60 * args.max_cpu_minutes,
                prior_cpu_hours=args.prior_cpu_hours)
    if _dist_env()[0] == 0:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
