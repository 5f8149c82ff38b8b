"""The training line behind the continue file, re-measured: every committed version of
``polycubenet/checkpoints/polycubenet-cpu-continue.pt`` read on the held-out pairs with today's code.

    python benchmarks/continue_curve.py --data HELDOUT [--count 100] \\
        [--out benchmarks/results/learning_curve_continue.jsonl] [--min-gap 0.5]

The shipped file is published rarely (the curve's points in ``learning_curve.jsonl`` stop where it was last
published), while training goes on every session into the continue file, committed at least every hour.
This script walks the git history of that file (oldest first), takes a version when its cumulative
CPU-hours are at least ``--min-gap`` past the last point taken, evaluates it exactly as the curve's points
are (``python -m polycubenet.evaluate --count 100 --n-out 4096 --steps 1 --seed 0``) and appends one JSON
line per version to ``--out``.  Versions already in ``--out`` (by commit) are skipped, so each session
adds only its own points.  ``python benchmarks/plot_learning_curve.py`` draws them beside the shipped
file's points.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
CONTINUE = "polycubenet/checkpoints/polycubenet-cpu-continue.pt"


def versions(path: str = CONTINUE, repo: Path = ROOT) -> list[str]:
    """Commits that changed ``path``, oldest first."""
    out = subprocess.run(["git", "-C", str(repo), "log", "--format=%H", "--", path], check=True,
                         capture_output=True, text=True).stdout.split()
    return out[::-1]


def committed_versions(tmp: str | Path) -> list[dict]:
    """Every committed version of the continue file, oldest first, written into the folder ``tmp``: one dict
    each with its commit, file, step, cumulative CPU-hours and GPU-hours."""
    import torch

    metas = []
    for i, rev in enumerate(versions()):
        blob = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{CONTINUE}"], capture_output=True).stdout
        if not blob:
            continue
        f = Path(tmp) / f"{i:03d}.pt"
        f.write_bytes(blob)
        ck = torch.load(f, map_location="cpu", weights_only=False)
        metas.append({"commit": rev, "file": f, "step": ck.get("step"), "cpu_hours": float(ck.get("cpu_hours") or 0.0),
                      "gpu_hours": float(ck.get("gpu_hours") or 0.0)})
    return metas


def pending(out: Path, tmp: str | Path, min_gap: float) -> tuple[list[dict], set[str], list[dict]]:
    """``(versions, done, todo)``: the continue file's committed versions (:func:`committed_versions`, written
    into ``tmp``), the commits already in the curve file ``out``, and the versions still to read there
    (:func:`select`)."""
    from plot_learning_curve import read_points

    done = {p["commit"] for p in read_points(out)} if Path(out).exists() else set()
    metas = committed_versions(tmp)
    return metas, done, select(metas, done, min_gap)


def select(metas: list[dict], done: set[str], min_gap: float) -> list[dict]:
    """The versions to evaluate: in order, each at least ``min_gap`` CPU-hours past the last one kept
    (points already in the curve, ``done``, count as kept), and not in ``done``."""
    picked, last = [], None
    for m in metas:
        if last is not None and m["cpu_hours"] - last < min_gap:
            continue
        last = m["cpu_hours"]
        if m["commit"] not in done:
            picked.append(m)
    return picked


def point(meta: dict, result: dict) -> dict:
    """One curve point from a version's meta and its :func:`polycubenet.evaluate.evaluate` result (its
    summary fields), with the columns of the shipped file's points."""
    rows = result["rows"]
    return {
        "commit": meta["commit"], "checkpoint": Path(CONTINUE).name, "step": meta["step"],
        "cpu_hours": meta["cpu_hours"], "gpu_hours": meta["gpu_hours"], "pairs": len(rows),
        "steps": result.get("steps"), "n_out": result.get("n_out"),
        "chamfer_median": result["chamfer_median"], "chamfer_identity": result["chamfer_identity_median"],
        "label_accuracy": result.get("label_accuracy_median"),
        "exact": result["exact_structure_rate"],
        "genus_match_genus_le2": result.get("genus_match_rate_genus_le2"),
        **({"exact_by_feature": result["exact_by_feature"]} if "exact_by_feature" in result else {}),
    }


def main(argv=None) -> int:
    import torch

    from polycubenet.evaluate import evaluate

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="held-out shard folder (the seed-2 pairs)")
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--min-gap", type=float, default=0.5, help="CPU-hours between two points taken")
    ap.add_argument("--out", default=str(ROOT / "benchmarks/results/learning_curve_continue.jsonl"))
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    with tempfile.TemporaryDirectory() as tmp:
        metas, done, todo = pending(out, tmp, args.min_gap)
        print(f"{len(metas)} versions of {CONTINUE}, {len(done)} already in {out.name}, {len(todo)} to evaluate",
              flush=True)
        print(f"{'commit':>8} {'CPU-h':>6} {'GPU-h':>5} {'Chamfer':>8} {'exact':>6} {'genus<=2':>8}")
        for m in todo:
            res = evaluate(m["file"], args.data, args.count, n_out=4096, steps=1, seed=0, progress=False)
            p = point(m, res)
            with out.open("a") as fh:  # one complete line per version: an interrupted run keeps the lines before
                fh.write(json.dumps(p) + "\n")
            print(f"{m['commit'][:8]} {p['cpu_hours']:>6.2f} {p['gpu_hours']:>5.2f} {p['chamfer_median']:>8.4f} "
                  f"{p['exact']:>6.0%} {p['genus_match_genus_le2'] or 0:>8.0%}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
