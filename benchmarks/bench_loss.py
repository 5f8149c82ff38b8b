"""Hybrid loss against plain L2: does the hybrid objective converge faster? (paper's claim)

Trains the same model twice, one run after the other, with everything equal but the
loss: same seed (same initial weights, same pairs, same timesteps and noise at every
step), same data, preset, steps, batch, resolution and learning-rate schedule.  Both
runs log, every ``--log-every`` steps, the training L2 noise-prediction error (the
quantity plain L2 optimises; the hybrid run optimises ``w L2 + (1 - w) L1`` but logs
the same L2) and the held-out L2 of the EMA weights on a fixed set of held-out pairs,
fixed timesteps and fixed noise (``polycubenet.train.heldout_loss``), so the two curves
are measured on identical inputs.

The EMA decay defaults to 0.95 here (not the 0.999 of real training): over a few
hundred steps a 0.999 average would still be mostly the initial weights and the
held-out curve would show the EMA's lag instead of the training.

Prints the held-out L2 of both runs at equal steps and the first step at which each
reaches a few levels, writes ``benchmarks/results/bench_loss.json`` and plots both
curves in ``benchmarks/results/bench_loss.png`` (left: the curves; right: the ratio
hybrid / l2 of the held-out L2 at equal steps, which shows differences the log scale hides).

    nice -n 10 python benchmarks/bench_loss.py --data /work/data/train --eval-data /work/data/heldout \\
        --preset cpu --steps 300 --batch 8 --points 256 --lr 5e-4 --warmup 50 --threads 1 \\
        --seed 0 1 --work /tmp/bench_loss_runs

``--seed`` takes several seeds (one hybrid/l2 pair each, reported per seed and averaged);
with ``--work`` a finished run of the same configuration is reused, so adding a seed
trains only the new pair.  A seed on a small budget is one sample of a noisy process:
read the gap against the step-to-step wiggle of each curve and across seeds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def read_log(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def first_step_below(steps: list[int], values: list[float], level: float) -> int | None:
    """First logged step whose value is <= level (None when never)."""
    for s, v in zip(steps, values):
        if v <= level:
            return int(s)
    return None


def wait_for_shards(directory: Path, minutes: float) -> None:
    from polycubenet.synth.shards import list_shards

    deadline = time.time() + 60 * minutes
    while not (directory.is_dir() and list_shards(directory)):
        if time.time() > deadline:
            raise SystemExit(f"no shard-*.npz in {directory} after {minutes} min")
        print(f"waiting for held-out shards in {directory} ...", flush=True)
        time.sleep(20)


def finished_run(run: Path, cfg) -> dict | None:
    """The curves of a completed run in ``run`` trained with exactly ``cfg`` (else None)."""
    import dataclasses

    import torch

    log, ckpt = run / "log.jsonl", run / "last.pt"
    if not (log.exists() and ckpt.exists()):
        return None
    s = torch.load(ckpt, map_location="cpu", weights_only=False)
    rows = read_log(log)
    if s.get("train_config") != dataclasses.asdict(cfg) or not rows or rows[-1]["step"] != cfg.steps:
        return None
    return {k: [row[k] for row in rows] for k in ("step", "loss_l2", "heldout_l2")}


def compare(h: dict, l: dict, log_every: int, verbose: bool = True) -> dict:
    """Equal-step table, steps to reach levels and summary numbers of one (hybrid, l2) pair."""
    if h["step"] != l["step"]:
        raise SystemExit("the two runs logged different steps")
    steps = h["step"]
    table = []
    if verbose:
        print(f"{'step':>6} {'held-out hybrid':>16} {'held-out l2':>12} {'hybrid/l2':>10} {'train hybrid':>13} "
              f"{'train l2':>9}")
    for i, s in enumerate(steps):
        r = dict(step=s, heldout_hybrid=h["heldout_l2"][i], heldout_l2=l["heldout_l2"][i],
                 train_hybrid=h["loss_l2"][i], train_l2=l["loss_l2"][i])
        r["ratio"] = r["heldout_hybrid"] / r["heldout_l2"]
        table.append(r)
        if verbose and (s % (5 * log_every) == 0 or i == len(steps) - 1):
            print(f"{s:>6} {r['heldout_hybrid']:>16.4f} {r['heldout_l2']:>12.4f} {r['ratio']:>10.3f} "
                  f"{r['train_hybrid']:>13.4f} {r['train_l2']:>9.4f}")

    # levels spaced geometrically from the initial held-out L2 down to the lowest either run reached
    # (the last level is reached by at most one run), plus the worse of the two final values
    start = max(h["heldout_l2"][0], l["heldout_l2"][0])
    lowest = min(min(h["heldout_l2"]), min(l["heldout_l2"]))
    worse_final = max(h["heldout_l2"][-1], l["heldout_l2"][-1])
    levels = sorted({float(start * (lowest / start) ** (k / 6)) for k in range(1, 7)} | {float(worse_final)},
                    reverse=True)
    reach = []
    if verbose:
        print(f"\n{'held-out level':>15} {'hybrid first step':>18} {'l2 first step':>14}")
    for lev in levels:
        a, b = first_step_below(steps, h["heldout_l2"], lev), first_step_below(steps, l["heldout_l2"], lev)
        reach.append(dict(level=lev, hybrid_step=a, l2_step=b))
        if verbose:
            print(f"{lev:>15.4f} {str(a):>18} {str(b):>14}")

    def wiggle(v):  # typical step-to-step change of a curve over its last half (its noise level)
        v = np.asarray(v[len(v) // 2:])
        return float(np.median(np.abs(np.diff(v)))) if len(v) > 2 else float("nan")

    tail = max(1, len(steps) // 5)  # the last fifth of the logged points
    ratios = np.array([r["ratio"] for r in table])
    summary = {
        "final_heldout_hybrid": h["heldout_l2"][-1],
        "final_heldout_l2": l["heldout_l2"][-1],
        "min_heldout_hybrid": min(h["heldout_l2"]),
        "min_heldout_l2": min(l["heldout_l2"]),
        "mean_last_fifth_heldout_hybrid": float(np.mean(h["heldout_l2"][-tail:])),
        "mean_last_fifth_heldout_l2": float(np.mean(l["heldout_l2"][-tail:])),
        "mean_last_fifth_train_hybrid": float(np.mean(h["loss_l2"][-tail:])),
        "mean_last_fifth_train_l2": float(np.mean(l["loss_l2"][-tail:])),
        "heldout_wiggle_hybrid": wiggle(h["heldout_l2"]),
        "heldout_wiggle_l2": wiggle(l["heldout_l2"]),
        "median_ratio_hybrid_over_l2": float(np.median(ratios)),
        "steps_hybrid_lower": int((ratios < 1).sum()),
        "steps_compared": len(table),
    }
    if verbose:
        print(f"\nmean held-out L2 over the last fifth: hybrid {summary['mean_last_fifth_heldout_hybrid']:.4f}, "
              f"l2 {summary['mean_last_fifth_heldout_l2']:.4f}; step-to-step wiggle: hybrid "
              f"{summary['heldout_wiggle_hybrid']:.4f}, l2 {summary['heldout_wiggle_l2']:.4f}")
        print(f"hybrid below l2 at {summary['steps_hybrid_lower']} of {summary['steps_compared']} logged steps; "
              f"median held-out ratio hybrid / l2 {summary['median_ratio_hybrid_over_l2']:.3f}")
    return {"equal_steps": table, "levels": reach, "summary": summary}


def plot(curves: dict, out: Path, title: str) -> None:
    """Left: both losses' training and held-out L2 against step (every seed); right: held-out hybrid / l2."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12.5, 4.6), gridspec_kw={"width_ratios": [3, 2]})
    colours = {"hybrid": "tab:red", "l2": "tab:blue"}
    styles = ["-", "--", "-.", (0, (5, 1))]
    for k, (seed, pair) in enumerate(curves.items()):
        ls = styles[k % len(styles)]
        for loss, c in pair.items():
            ax.plot(c["step"], c["heldout_l2"], linestyle=ls, color=colours[loss], lw=2,
                    label=f"{loss}, seed {seed}: held-out L2 (EMA)")
            ax.plot(c["step"], c["loss_l2"], ":", color=colours[loss], lw=1.0, alpha=0.8,
                    label=f"{loss}, seed {seed}: training L2 (batch mean)")
        ratio = np.array(pair["hybrid"]["heldout_l2"]) / np.array(pair["l2"]["heldout_l2"])
        ax2.plot(pair["hybrid"]["step"], ratio, linestyle=ls, color="k", lw=1.5, label=f"seed {seed}")
    ax.set_xlabel("step")
    ax.set_ylabel("L2 noise-prediction error")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=9)
    ax2.axhline(1.0, color="grey", lw=1)
    ax2.set_xlabel("step")
    ax2.set_ylabel("held-out L2: hybrid / l2 (< 1: hybrid better)")
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=8)
    ax2.set_title("same seed, same batches, same noise: ratio at equal steps", fontsize=9)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("/work/data/train"))
    ap.add_argument("--eval-data", type=Path, default=Path("/work/data/heldout"))
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--points", type=int, default=256)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--ema", type=float, default=0.95)
    ap.add_argument("--seed", type=int, nargs="+", default=[0], help="one or more seeds (a pair of runs each)")
    ap.add_argument("--log-every", type=int, default=10)
    ap.add_argument("--eval-pairs", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--wait-minutes", type=float, default=30.0, help="wait this long for held-out shards")
    ap.add_argument("--work", type=Path, help="run folders WORK/seedS/LOSS; a finished run there with the same "
                                              "config is reused (default: a temporary folder, deleted)")
    ap.add_argument("--json", type=Path, default=RESULTS / "bench_loss.json")
    ap.add_argument("--png", type=Path, default=RESULTS / "bench_loss.png")
    args = ap.parse_args()

    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    torch.set_num_threads(args.threads)
    from polycubenet.train import TrainConfig, train

    wait_for_shards(args.eval_data, args.wait_minutes)
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_loss_")
        work = Path(tmp.name)
    else:
        work = args.work
    curves: dict[int, dict[str, dict]] = {}
    wall: dict[str, float | None] = {}
    for seed in args.seed:
        curves[seed] = {}
        for loss in ("hybrid", "l2"):
            cfg = TrainConfig(preset=args.preset, steps=args.steps, batch=args.batch, points=args.points,
                              lr=args.lr, warmup=args.warmup, ema=args.ema, loss=loss, seed=seed,
                              log_every=args.log_every, eval_pairs=args.eval_pairs, ckpt_every=10**9,
                              threads=args.threads)
            run = work / f"seed{seed}" / loss
            done = finished_run(run, cfg)
            if done is not None:
                print(f"--- seed {seed}, loss={loss}: reusing the finished run in {run} ---", flush=True)
                curves[seed][loss] = done
                wall[f"seed{seed}/{loss}"] = None
                continue
            if (run / "log.jsonl").exists():
                (run / "log.jsonl").unlink()
            print(f"--- seed {seed}, loss={loss}: training {args.steps} steps ---", flush=True)
            t0 = time.perf_counter()
            train(args.data, run, cfg, eval_dir=args.eval_data, resume=False, device="cpu", progress=False)
            wall[f"seed{seed}/{loss}"] = round(time.perf_counter() - t0, 1)
            curves[seed][loss] = finished_run(run, cfg)
    if tmp is not None:
        tmp.cleanup()

    per_seed = {}
    for seed, pair in curves.items():
        print(f"\n=== seed {seed} ===")
        per_seed[seed] = compare(pair["hybrid"], pair["l2"], args.log_every)
    if len(curves) > 1:
        both = {loss: {k: np.mean([curves[s][loss][k] for s in curves], axis=0).tolist()
                       for k in ("loss_l2", "heldout_l2")} for loss in ("hybrid", "l2")}
        for loss in both:
            both[loss]["step"] = curves[args.seed[0]][loss]["step"]
        print(f"\n=== mean over seeds {args.seed} ===")
        mean = compare(both["hybrid"], both["l2"], args.log_every)
    else:
        mean = None
    print(f"\nwall time per run (s; None = reused): {wall}")

    import dataclasses

    from polycubenet.atomic import write_json

    config = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("loss", "seed")}
    out = {
        "benchmark": "hybrid vs l2 loss, same seed and budget",
        "machine": platform.node(),
        "torch_threads": args.threads,
        "data": str(args.data),
        "eval_data": str(args.eval_data),
        "train_config": config,
        "seeds": args.seed,
        "curves": {str(s): c for s, c in curves.items()},
        "per_seed": {str(s): r for s, r in per_seed.items()},
        "mean_over_seeds": mean,
        "wall_s": wall,
    }
    write_json(args.json, out)
    title = (f"hybrid vs L2 loss: preset {args.preset}, {args.steps} steps, batch {args.batch} x {args.points} "
             f"points, lr {args.lr:g}, EMA {args.ema:g}")
    plot(curves, args.png, title)
    print(f"wrote {args.json} and {args.png}")


if __name__ == "__main__":
    main()
