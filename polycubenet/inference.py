"""Generate polycube clouds with a trained PolycubeNet: any N_in and N_out, batched, CPU or CUDA.

* :func:`load_model` reads a checkpoint (default: the shipped one, :data:`DEFAULT_CHECKPOINT`)
  once per (path, device) and keeps it.
* :func:`plan_batches` groups requests of equal resolution ``(N_in, N_out)`` and packs
  each group into batches whose total point count stays under a budget, so a mixed
  library runs in few passes and never runs out of memory; a request larger than the
  budget runs alone, its point side processed in chunks (memory linear in points).
* :func:`generate` runs DDIM for a list of conditions and returns ``(N_out, 6)`` clouds
  (xyz + unit normals, the conditions' canonical frame).  Every request draws its noise
  from its own generator seeded by ``(seed, the request's own condition points)``
  (:func:`request_seed`), so the output of a request depends on nothing else: not on its
  position in the list, nor on the batch it landed in.
* :class:`ModelSource` plugs the model into :func:`polycubenet.pipeline.mesh_part`.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .data import PolycubeCloud
from .model.checkpoint import Loaded, load_checkpoint
from .model.diffusion import anchored_from_network, anchored_to_network, from_network, to_network

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "checkpoints" / "polycubenet-cpu.pt"
DEFAULT_POINT_BUDGET = 1 << 19  # condition + output points per batch
DEFAULT_STEPS_CPU = 32  # DDIM steps when running on a CPU (stride 4 = 256 steps on a GPU)
#: point chunk at inference: past ~8k points a chunk's logits (heads x latents x chunk) fall out of
#: cache and the streaming read gets slower per point (measured by benchmarks/bench_inference.py)
MAX_CHUNK = 8192

#: the half-turns about the canonical axes (:mod:`polycubenet.frame`), which a further draw of the model may
#: apply to the part before generating (:attr:`ModelSource.turn`, :data:`polycubenet.policy.LEARNED_DRAWS`): each
#: keeps the axes, and with them the bounding-box extents' order, so the turned part is in a canonical frame up to
#: the frame's sign convention, and the cloud is turned back exactly
TURNS = {"x": np.diag([1.0, -1.0, -1.0]), "y": np.diag([-1.0, 1.0, -1.0]), "z": np.diag([-1.0, -1.0, 1.0])}


def stretch_factors(V: np.ndarray, exponent: float) -> np.ndarray:
    """The per-axis factors of a further draw's stretched view of a part in the canonical frame
    (:attr:`ModelSource.stretch`): axis ``i`` scaled by ``(e_max / e_i) ** exponent`` of the bounding-box
    extents ``e``, then all by one factor that gives the stretched box the unit diagonal again.  An exponent in
    (0, 1) takes the box part of the way to a cube, a negative one away from it; either keeps the extents' order,
    so the stretched part is in a canonical frame too, and an axis-aligned scaling maps a polycube to a polycube,
    so the cloud is stretched back exactly."""
    V = np.asarray(V, np.float64)
    e = np.maximum(V.max(axis=0) - V.min(axis=0), 1e-9)
    d = (e.max() / e) ** float(exponent)
    return d / np.linalg.norm(e * d) * np.linalg.norm(e)


def view_points(points: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Points seen through the diagonal map ``diag(d)`` (a turn's signs, a stretch's factors)."""
    return np.asarray(points, np.float64) * d


def view_normals(normals: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Unit normals seen through ``diag(d)``: the inverse transpose, renormalised."""
    n = np.asarray(normals, np.float64) / d
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)

_CACHE: dict = {}


def default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def load_model(checkpoint: str | Path | Loaded | None = None, device: str | None = None) -> Loaded:
    """The model of ``checkpoint`` (a path, an already loaded model, or None for the shipped one)."""
    if isinstance(checkpoint, Loaded):
        return checkpoint
    path = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
    device = device or default_device()
    if not path.is_file():
        raise FileNotFoundError(
            f"model checkpoint {path} not found (train one: python -m polycubenet.train, then "
            f"python -m polycubenet.evaluate --publish)")
    key = (str(path.resolve()), path.stat().st_mtime_ns, device)
    if key not in _CACHE:
        _CACHE.clear()
        _CACHE[key] = load_checkpoint(path, device=device)
    return _CACHE[key]


def resolve_steps(steps: int | None, device: str | None, model: str | Path | Loaded | None = None) -> tuple[str, int | str]:
    """``(device type, DDIM steps)`` that :func:`generate` will use for these arguments.

    Without ``steps`` on a CPU: the checkpoint's own ``default_steps`` (chosen by measurement
    when it was published), else :data:`DEFAULT_STEPS_CPU`; on CUDA stride 4."""
    dev_type = torch.device(device or default_device()).type
    if steps is not None:
        return dev_type, int(steps)
    if dev_type != "cpu":
        return dev_type, "stride4"
    try:
        meta = load_model(model, "cpu").meta
    except (FileNotFoundError, ValueError):
        meta = {}
    return dev_type, int(meta.get("default_steps") or DEFAULT_STEPS_CPU)


def request_seed(seed: int, condition: np.ndarray) -> int:
    """The noise seed of one request: a hash of ``seed`` and the condition's float32 bytes (63 bits)."""
    import hashlib

    h = hashlib.blake2b(digest_size=8)
    h.update(int(seed).to_bytes(8, "little", signed=True))
    c = np.ascontiguousarray(condition, dtype=np.float32)
    h.update(np.asarray(c.shape, np.int64).tobytes())
    h.update(c.tobytes())
    return int.from_bytes(h.digest(), "little") >> 1


def plan_batches(n_in: Sequence[int], n_out: Sequence[int], point_budget: int = DEFAULT_POINT_BUDGET) -> list[list[int]]:
    """Request indices grouped into batches: equal ``(n_in, n_out)`` in a batch, total points
    ``sum(n_in + n_out) <= point_budget`` (a single larger request gets a batch of its own).

    Batches come largest resolution first; within a group the original order is kept.
    """
    if len(n_in) != len(n_out):
        raise ValueError(f"n_in has {len(n_in)} entries, n_out {len(n_out)}")
    if point_budget < 1:
        raise ValueError("point_budget must be >= 1")
    groups: dict[tuple[int, int], list[int]] = {}
    for i, key in enumerate(zip(map(int, n_in), map(int, n_out))):
        groups.setdefault(key, []).append(i)
    batches: list[list[int]] = []
    for (a, b), idx in sorted(groups.items(), key=lambda kv: -(kv[0][0] + kv[0][1])):
        per = max(1, point_budget // (a + b))
        batches.extend(idx[s : s + per] for s in range(0, len(idx), per))
    return batches


#: how a draw spreads the model's anchors on the part: ``uniform``, independent area-uniform samples (the
#: first draw's); ``even``, a Poisson-disk sample (blue noise, as the training pairs' anchors are spread)
ANCHOR_SPREADS = ("uniform", "even")


def part_anchors(V: np.ndarray, F: np.ndarray, n: int, seed: int = 0, normals: bool = False,
                 spread: str = "uniform") -> np.ndarray:
    """``(n, 3)`` anchor points for an anchored model: samples of the part ``(V, F)`` (canonical
    frame) spread as ``spread`` says (:data:`ANCHOR_SPREADS`), a function of the part and ``seed``
    only; with ``normals`` ``(n, 6)``: each point and the unit normal of its triangle (for a model
    with ``anchor_normals``)."""
    from .sampling import poisson_disk, uniform_sample

    V, F = np.asarray(V, float), np.asarray(F)
    if spread == "uniform":
        s = uniform_sample(V, F, int(n), np.random.default_rng(seed))
    elif spread == "even":
        s = poisson_disk(V, F, int(n), seed=seed)
    else:
        raise ValueError(f"unknown anchor spread {spread!r}; expected one of {ANCHOR_SPREADS}")
    out = np.hstack([s.points, s.normals]) if normals else s.points
    return out.astype(np.float32)


def model_anchors(loaded: "Loaded", V: np.ndarray, F: np.ndarray, n: int, seed: int = 0,
                  spread: str = "uniform") -> np.ndarray | None:
    """The anchors ``loaded`` needs for a part ``(V, F)`` (canonical frame): None for a free-point
    model, else :func:`part_anchors` (spread as ``spread`` says) with the part's normals when the
    model takes them."""
    cfg = loaded.model.config
    return part_anchors(V, F, n, seed, normals=cfg.anchor_normals, spread=spread) if cfg.anchored else None


def _sample_batch(loaded: Loaded, conds: list[np.ndarray], n_out: int, seeds: list[int], *, steps, stride, eta,
                  device: str, chunk: int | None, progress: Callable | None,
                  anchors: list[np.ndarray] | None = None, recycles: int | None = None,
                  genus: list[int] | None = None) -> list[np.ndarray]:
    model, diffusion = loaded.model, loaded.diffusion
    cfg = model.config
    scale = cfg.xyz_scale
    dev = torch.device(device)
    cond = to_network(torch.as_tensor(np.stack(conds), dtype=torch.float32, device=dev), None, scale)
    gens = [torch.Generator(device=dev).manual_seed(int(s)) for s in seeds]
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if dev.type == "cuda" else None
    anchor = None
    if cfg.anchored:
        _, anchor = anchored_to_network(torch.as_tensor(np.stack(anchors), dtype=torch.float32, device=dev), None, None,
                                        scale, cfg.anchor_gain)
    x = diffusion.sample(model, cond, n_out, steps=steps, stride=stride, eta=eta, generator=gens,
                         chunk=chunk or min(cfg.chunk, MAX_CHUNK), autocast=autocast, progress=progress, anchor=anchor,
                         recycles=(1 if cfg.recycle else 0) if recycles is None else recycles,
                         genus=None if genus is None or not cfg.genus_classes else genus)
    if cfg.anchored:
        out = anchored_from_network(x, anchor, scale, cfg.anchor_gain)
    else:
        out = from_network(x, scale)
    return list(out.cpu().numpy().astype(np.float32))


def generate(
    conditions: Sequence[np.ndarray],
    n_out: int | Sequence[int],
    *,
    model: str | Path | Loaded | None = None,
    steps: int | None = None,
    stride: int = 4,
    eta: float = 0.0,
    seed: int = 0,
    device: str | None = None,
    point_budget: int | None = None,
    chunk: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    anchors: Sequence[np.ndarray] | None = None,
    recycles: int | None = None,
    genus: Sequence[int | None] | None = None,
) -> list[np.ndarray]:
    """Polycube clouds for ``conditions`` (each ``(N_i, 3)``, canonical frame).

    An anchored model (``ModelConfig.anchored``) also needs ``anchors``: per request the
    ``(n_out_i, 3)`` points of the part whose places on the polycube it generates, ``(n_out_i, 6)``
    with the part's normals for ``anchor_normals`` (:func:`part_anchors`); each output point is
    its anchor moved onto the polycube.

    Parameters
    ----------
    n_out : output points per request (one int for all, or one per request)
    model : checkpoint path or loaded model (default: the shipped checkpoint)
    steps : DDIM steps (default: stride 4 on CUDA; on a CPU the checkpoint's ``default_steps``,
        else :data:`DEFAULT_STEPS_CPU`)
    stride : DDIM stride when ``steps`` is None on CUDA
    eta : 0 = deterministic DDIM, 1 = DDPM-like ancestral noise
    seed : request ``i`` uses generator seed ``request_seed(seed, conditions[i])``
    point_budget : points (condition + output) per batch
    progress : called with ``(batches done, batches)``
    recycles : a recycling model's (``ModelConfig.recycle``) further evaluations per step, each given
        the last one's clean estimate (default: 1 for such a model, else 0)
    genus : per request the part's genus (None: unknown), for a model that takes it
        (``ModelConfig.genus_classes``); a model that does not ignores it

    Returns
    -------
    list of ``(n_out_i, 6)`` float32 arrays: xyz and unit normals.
    """
    device = device or default_device()
    loaded = load_model(model, device)
    if loaded.model.parameters().__next__().device != torch.device(device):
        loaded.model.to(device)
    conds = [np.asarray(c, dtype=np.float32) for c in conditions]
    for i, c in enumerate(conds):
        if c.ndim != 2 or c.shape[1] != 3 or len(c) < 1 or not np.isfinite(c).all():
            raise ValueError(f"condition {i}: expected a finite (N, 3) point array, got shape {c.shape}")
    outs = [int(n_out)] * len(conds) if np.isscalar(n_out) else [int(n) for n in n_out]
    if len(outs) != len(conds):
        raise ValueError(f"{len(conds)} conditions but {len(outs)} output sizes")
    if any(n < 1 for n in outs):
        raise ValueError("every n_out must be >= 1")
    if steps is None and torch.device(device).type == "cpu":
        steps = resolve_steps(None, device, loaded)[1]
    anch = None
    if loaded.model.config.anchored:
        k = loaded.model.config.anchor_dim
        what = "points" if k == 3 else "points and unit normals"
        if anchors is None or len(anchors) != len(conds):
            raise ValueError(f"this model is anchored: pass anchors, one (n_out, {k}) array of {what} on each part "
                             "(polycubenet.inference.part_anchors)")
        anch = [np.asarray(a, dtype=np.float32) for a in anchors]
        for i, (a, n) in enumerate(zip(anch, outs)):
            if a.shape != (n, k) or not np.isfinite(a).all():
                raise ValueError(f"anchors {i}: expected a finite ({n}, {k}) array of {what}, got shape {a.shape}")
    if genus is not None and len(genus) != len(conds):
        raise ValueError(f"{len(conds)} conditions but {len(genus)} genus values")
    gen_of = [-1 if genus is None or genus[i] is None else int(genus[i]) for i in range(len(conds))]
    batches = plan_batches([len(c) for c in conds], outs, point_budget or DEFAULT_POINT_BUDGET)
    results: list[np.ndarray | None] = [None] * len(conds)
    for b, idx in enumerate(batches):
        clouds = _sample_batch(loaded, [conds[i] for i in idx], outs[idx[0]], [request_seed(seed, conds[i]) for i in idx],
                               steps=steps, stride=stride, eta=eta, device=device, chunk=chunk, progress=None,
                               anchors=None if anch is None else [anch[i] for i in idx], recycles=recycles,
                               genus=[gen_of[i] for i in idx])
        for i, cloud in zip(idx, clouds):
            results[i] = cloud
        if progress is not None:
            progress(b + 1, len(batches))
    return results  # type: ignore[return-value]


def part_genus(F: np.ndarray) -> int | None:
    """The genus of a part's closed surface ``F`` (the part's own, the one extraction checks the polycube
    against), or None where the surface is not one closed manifold (the model is then told "unknown")."""
    from .errors import PolycubeError
    from .polycube import surface_genus

    try:
        return int(surface_genus(F))
    except PolycubeError:
        return None


class ModelSource:
    """The learned polycube source for :func:`polycubenet.pipeline.mesh_part`.

    ``source(sample, V, F, config)`` generates ``config.n_learned`` points conditioned on the
    part's sample and returns a :class:`PolycubeCloud` with ``meta["provenance"] == "learned"``.
    With ``turn`` (a key of :data:`TURNS`) the model sees the part (samples and anchors) turned a
    half-turn about that axis, and the generated cloud is turned back: another view of the same part.
    With ``stretch`` (an exponent, :func:`stretch_factors`; 0 or None: none) it sees the part scaled along the
    axes, and the cloud is scaled back.  ``anchors`` spreads the model's anchors on the part
    (:data:`ANCHOR_SPREADS`).
    """

    def __init__(self, model: str | Path | Loaded | None = None, steps: int | None = None, seed: int = 0,
                 device: str | None = None, turn: str | None = None, anchors: str = "uniform",
                 stretch: float | None = None):
        if turn is not None and turn not in TURNS:
            raise ValueError(f"unknown turn {turn!r}; expected one of {sorted(TURNS)} or None")
        if anchors not in ANCHOR_SPREADS:
            raise ValueError(f"unknown anchor spread {anchors!r}; expected one of {ANCHOR_SPREADS}")
        if stretch is not None and not (np.isfinite(stretch) and -1.0 < stretch < 1.0):
            raise ValueError(f"stretch exponent {stretch!r} out of range: expected a number in (-1, 1) or None")
        self.model, self.steps, self.seed, self.device, self.turn = model, steps, seed, device, turn
        self.anchors, self.stretch = anchors, (float(stretch) if stretch else None)

    def further_draws(self) -> tuple[int, ...]:
        """The ``K`` of the model's further draws ``learned+K`` after this source's own
        (:func:`polycubenet.policy.learned_draws` of its resolved steps; a model that takes no anchors
        skips a draw that differs from the first only in how its anchors are spread)."""
        from .policy import learned_draws

        steps = resolve_steps(self.steps, self.device, self.model)[1]
        if not learned_draws(steps):  # none at all (a GPU's stride schedule): no need to read the model
            return ()
        try:
            anchored = bool(load_model(self.model, self.device).model.config.anchored)
        except (FileNotFoundError, ValueError):  # no readable model: the table as it is (the source fails when it runs)
            anchored = True
        return learned_draws(steps, anchored=anchored)

    def draw_source(self, k: int) -> "ModelSource":
        """The source of the further draw ``learned+k``: the same model and device, at that draw's
        steps, seed offset, turn and anchor spread (:data:`polycubenet.policy.LEARNED_DRAWS`) from this
        source's."""
        from .policy import draw_anchors, draw_seed, draw_steps, draw_stretch, draw_turn

        name = f"learned+{int(k)}"
        steps = draw_steps(name, resolve_steps(self.steps, self.device, self.model)[1])
        return ModelSource(self.model, steps=steps, seed=self.seed + draw_seed(name), device=self.device,
                           turn=draw_turn(name), anchors=draw_anchors(name), stretch=draw_stretch(name))

    def __call__(self, sample, V, F, config) -> PolycubeCloud:
        loaded = load_model(self.model, self.device)
        t0 = time.perf_counter()
        seed = self.seed + config.seed
        n = int(getattr(config, "n_learned", None) or config.n_polycube)
        a = model_anchors(loaded, V, F, n, seed, spread=self.anchors)
        cond, anchors = sample.points, None if a is None else [a]
        d = np.ones(3)  # the view: a turn's signs times a stretch's factors, both diagonal
        if self.turn:
            d = d * np.diag(TURNS[self.turn])
        if self.stretch:
            d = d * stretch_factors(V, self.stretch)
        viewed = not np.array_equal(d, np.ones(3))
        if viewed:  # the part seen through diag(d) (points, and normals by the inverse transpose), the cloud back
            cond = view_points(cond, d)
            if a is not None:  # the anchors: xyz, then the normals when the model takes them
                blocks = [view_points(a[:, :3], d)] + [view_normals(a[:, i:i + 3], d) for i in range(3, a.shape[1], 3)]
                anchors = [np.hstack(blocks).astype(np.float32)]
        genus = part_genus(F) if loaded.model.config.genus_classes else None
        (cloud,) = generate([cond], n, model=loaded, steps=self.steps,
                            seed=seed, device=self.device, anchors=anchors, genus=[genus])
        if viewed:
            cloud = np.hstack([view_points(cloud[:, :3], 1.0 / d), view_normals(cloud[:, 3:6], 1.0 / d)])
        meta = {
            "provenance": "learned",
            "checkpoint": str(loaded.path.name if loaded.path else "memory"),
            "steps": resolve_steps(self.steps, self.device, loaded)[1],
            "seconds": round(time.perf_counter() - t0, 3),
        }
        if self.turn:
            meta["turn"] = self.turn
        if self.stretch:
            meta["stretch"] = self.stretch
        if loaded.model.config.genus_classes:
            meta["genus_given"] = genus
        if self.anchors != "uniform" and a is not None:
            meta["anchors"] = self.anchors
        return PolycubeCloud(cloud[:, :3].astype(np.float64), cloud[:, 3:].astype(np.float64), meta=meta,
                             anchors=None if a is None else a[:, :3].astype(np.float64),
                             anchor_normals=None if a is None or a.shape[1] < 6 else a[:, 3:6].astype(np.float64))
