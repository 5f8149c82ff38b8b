"""Where a training step's time goes, per batch size: building the batch, forward + backward,
optimizer, EMA (the shipped checkpoint's model and recipe).

    python benchmarks/bench_train_step.py --data SHARDS [--device cuda:0] [--batches 12 128 512] [--builders numpy device] \\
        [--steps 20] [--json benchmarks/results/bench_train_step.json]

Session 7 trained on a lent H100 at ~5 steps/s of batch 128 with the GPU about 1 % busy: run this first
on such a machine (it takes well under a minute) to see whether the step is bound by building batches
on the CPU or by kernel launches, and so which batch size buys the most pairs per second. The baseline
is the first batch size in the same run: the table gives each row's pairs per second as a ratio to it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from polycubenet.model import PolycubeNet  # noqa: E402
from polycubenet.model.config import ModelConfig  # noqa: E402
from polycubenet.train import DevicePairs, PairData, TrainConfig, diffusion_of, draw_batch, ema_update  # noqa: E402


def _sync(dev: torch.device) -> None:
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)


def measure(data: PairData, mcfg: ModelConfig, cfg: TrainConfig, dev: torch.device, steps: int,
            on_device: DevicePairs | None = None) -> dict:
    """Mean seconds per step of each phase over ``steps`` steps (after two warm-up steps); batches
    drawn by ``on_device`` (the training's builder on a GPU) when given, else by numpy."""
    model = PolycubeNet(mcfg).to(dev)
    ema = PolycubeNet(mcfg).to(dev).eval()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-5)
    diffusion = diffusion_of(cfg)
    autocast = (lambda: torch.autocast("cuda", dtype=torch.bfloat16)) if dev.type == "cuda" else None
    rng = np.random.default_rng(0)
    times = {"build": 0.0, "forward_backward": 0.0, "optimizer": 0.0, "ema": 0.0}
    for i in range(steps + 2):
        t0 = time.perf_counter()
        idx = rng.integers(0, len(data), size=cfg.batch)
        x0, cond, anchor = draw_batch(data, on_device, idx, rng, cfg, mcfg, dev)
        _sync(dev)
        t1 = time.perf_counter()
        loss, _ = diffusion.training_loss(model, x0, cond, loss=cfg.loss, autocast=autocast, anchor=anchor,
                                          t_bias=cfg.t_bias)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip))
        _sync(dev)
        t2 = time.perf_counter()
        opt.step()
        _sync(dev)
        t3 = time.perf_counter()
        ema_update(ema, model, 0.999)
        _sync(dev)
        t4 = time.perf_counter()
        if i >= 2:
            for k, dt in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
                times[k] += dt / steps
    times["step"] = sum(times.values())
    return times


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="a shard folder (python -m polycubenet.synth)")
    ap.add_argument("--checkpoint", default=str(ROOT / "polycubenet/checkpoints/polycubenet-cpu.pt"))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--batches", type=int, nargs="+", default=[12, 128])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--pairs", type=int, default=1024, help="pairs loaded (the first shards)")
    ap.add_argument("--builders", nargs="+", default=["numpy"], choices=["numpy", "device"],
                    help="who draws the batches: numpy on one core, or DevicePairs on --device (the GPU training's)")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/bench_train_step.json"))
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    dev = torch.device(args.device)
    s = torch.load(args.checkpoint, map_location="cpu", weights_only=False)
    mcfg = ModelConfig.from_dict(s["model_config"])
    d, tc = s.get("diffusion") or {}, s.get("train_config") or {}
    data = PairData(args.data, limit=args.pairs)
    _ = data.anchor_normals if mcfg.anchor_dim == 6 else None  # computed once, outside the timing
    rows = []
    on_device = DevicePairs(data, dev, mcfg.anchor_dim) if "device" in args.builders else None
    for builder, b in [(w, b) for w in args.builders for b in args.batches]:
        cfg = TrainConfig(preset=tc.get("preset", "cpu"), batch=b, points=int(tc.get("points", 512)),
                          prediction=d.get("prediction", "eps"), schedule=d.get("schedule", "cosine"),
                          pairing=d.get("pairing", "random"), t_bias=float(tc.get("t_bias", 1.0)))
        t = measure(data, mcfg, cfg, dev, args.steps, on_device if builder == "device" else None)
        rows.append({"builder": builder, "batch": b, **{k: round(v, 5) for k, v in t.items()}, "pairs_per_s": round(b / t["step"], 1)})
    base = rows[0]["pairs_per_s"]
    print(f"device {dev}, {len(data)} pairs, {args.steps} timed steps per row (ms per step)")
    print(f"{'builder':>8} {'batch':>6} {'build':>9} {'fwd+bwd':>8} {'optim':>7} {'ema':>6} {'step':>7} {'pairs/s':>8} {'ratio':>6}")
    for r in rows:
        print(f"{r['builder']:>8} {r['batch']:>6} {1e3 * r['build']:>9.1f} {1e3 * r['forward_backward']:>8.1f} {1e3 * r['optimizer']:>7.1f} "
              f"{1e3 * r['ema']:>6.1f} {1e3 * r['step']:>7.1f} {r['pairs_per_s']:>8.1f} {r['pairs_per_s'] / base:>6.2f}")
    out = {"device": str(dev), "pairs": len(data), "steps": args.steps, "baseline_batch": rows[0]["batch"], "rows": rows}
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
