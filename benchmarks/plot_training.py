"""Training curve of a run (``RUN/log.jsonl``) and held-out Chamfer of its snapshots.

    python benchmarks/plot_training.py --log benchmarks/results/train_cpu1_log.jsonl \\
        --eval benchmarks/results/model_eval_step*.json --out benchmarks/results/train_cpu1.png

Prints the loss averaged over windows of steps and the Chamfer per evaluated step
(what more training bought so far), writes the picture and ``train_cpu1.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--log", required=True)
    ap.add_argument("--eval", nargs="*", default=[])
    ap.add_argument("--out", required=True)
    ap.add_argument("--window", type=int, default=250)
    args = ap.parse_args(argv)
    rows = [json.loads(line) for line in Path(args.log).read_text().splitlines() if line.strip()]
    steps = np.array([r["step"] for r in rows])
    loss = np.array([r["loss_l2"] for r in rows])
    print(f"{'steps':>11} {'train L2':>9} {'hours':>6}")
    table = []
    for a in range(0, int(steps.max()), args.window):
        m = (steps > a) & (steps <= a + args.window)
        if m.any():
            sec = max(r["seconds"] for r, k in zip(rows, m) if k)
            table.append({"steps": f"{a + 1}-{a + args.window}", "loss_l2": float(loss[m].mean()), "hours": sec / 3600})
            print(f"{table[-1]['steps']:>11} {table[-1]['loss_l2']:9.4f} {table[-1]['hours']:6.2f}")
    evals = []
    for p in sorted(args.eval):
        e = json.loads(Path(p).read_text())
        evals.append({k: e.get(k) for k in ("step", "pairs", "n_out", "steps", "chamfer_median", "chamfer_mean",
                                             "exact_structure_rate", "genus_match_rate")})
    evals.sort(key=lambda e: e["step"] or 0)
    if evals:
        print(f"\n{'step':>6} {'pairs':>5} {'Chamfer median':>15} {'exact':>6} {'genus':>6}")
        for e in evals:
            print(f"{e['step']:>6} {e['pairs']:>5} {e['chamfer_median']:15.4f} {e.get('exact_structure_rate') or 0:6.2f} "
                  f"{e.get('genus_match_rate') or 0:6.2f}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 if evals else 1, figsize=(11 if evals else 6, 4), squeeze=False)
    ax = axes[0, 0]
    ax.plot(steps, loss, lw=0.5, alpha=0.4, label="train L2 (per log line)")
    k = max(1, len(loss) // 40)
    ax.plot(steps[k - 1 :], np.convolve(loss, np.ones(k) / k, mode="valid"), lw=2, label=f"moving mean ({k})")
    ax.set_xlabel("step")
    ax.set_ylabel("noise-prediction L2")
    ax.set_ylim(0, min(1.0, float(loss.max())))
    ax.legend()
    ax.set_title(Path(args.log).stem)
    if evals:
        ax = axes[0, 1]
        ax.plot([e["step"] for e in evals], [100 * e["chamfer_median"] for e in evals], "o-")
        ax.axhline(1.5, color="r", ls="--", label="target 1.5 %")
        ax.set_xlabel("step")
        ax.set_ylabel("held-out Chamfer, % of diagonal (median)")
        ax.legend()
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    out.with_suffix(".json").write_text(json.dumps({"train": table, "evals": evals}, indent=1) + "\n")
    print(f"\nwrote {out} and {out.with_suffix('.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
