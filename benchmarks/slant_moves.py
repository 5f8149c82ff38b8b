"""How far the model takes a part's slanted faces toward their polycube planes (a share of the way), by feature.

    python benchmarks/slant_moves.py --data FEATURES [--count 256] [--checkpoints F ...] [--names N ...]
        [--steps 1 [8 ...]] [--json benchmarks/results/slant_moves.json]

FEATURES: held-out pairs with the training mix's machined features, from a seed never trained on
(``python -m polycubenet.synth --out FEATURES --count 256 --seed 9001 --n-cond 2048 --n-target 2048
--cad-features --whole-slants``).  Each checkpoint generates one-step clouds from the training's anchors (each
target point's preimage, :func:`polycubenet.evaluate.slant_moves`), so every output point has a known target:
``moved`` 1.00 puts a slanted face onto its plane, 0.75 leaves a ramp a quarter as steep as the part's, which the
extraction reads as a staircase.  Default checkpoints: the shipped file and the continue file.  ``--steps``
reads each checkpoint at each of these DDIM step counts (default 1, the policy's first draw; one
arm per checkpoint and step count).

With ``--curve OUT.jsonl`` it reads instead every committed version of the continue file at least ``--min-gap``
CPU-hours apart (as ``benchmarks/continue_curve.py`` does) and appends one line per version not yet in OUT:
``python benchmarks/slant_moves.py --data FEATURES --curve benchmarks/results/learning_curve_slant_moves.jsonl``.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

DEFAULTS = ["polycubenet/checkpoints/polycubenet-cpu.pt", "polycubenet/checkpoints/polycubenet-cpu-continue.pt"]


def main(argv=None) -> int:
    import torch

    from polycubenet.atomic import write_json
    from polycubenet.evaluate import SHARE_BINS, slant_moves

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="held-out shard folder with machined features (seed 9001)")
    ap.add_argument("--count", type=int, default=256)
    ap.add_argument("--checkpoints", nargs="+", default=DEFAULTS)
    ap.add_argument("--names", nargs="+", help="one short name per checkpoint (default: file stems)")
    ap.add_argument("--steps", type=int, nargs="+", default=[1], help="DDIM step counts, each read (default 1)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", help="write every checkpoint's summary and rows here")
    ap.add_argument("--curve", help="append a line per committed version of the continue file to this .jsonl")
    ap.add_argument("--min-gap", type=float, default=4.0, help="with --curve: CPU-hours between two versions")
    args = ap.parse_args(argv)
    if args.curve:
        return curve(args)
    names = args.names or [Path(c).stem for c in args.checkpoints]
    if len(names) != len(args.checkpoints):
        ap.error("--names needs one name per checkpoint")
    if len(args.steps) > 1:  # one arm per (checkpoint, steps)
        names = [f"{n} @{s} steps" for n in names for s in args.steps]
    arms = [(ck, s) for ck in args.checkpoints for s in args.steps]
    torch.set_num_threads(args.threads)
    results = {}
    print(f"{'checkpoint':<34} {'CPU-h':>6} {'feature':<12} {'pairs':>5} {'moved':>6} {'short':>6} "
          f"{'err slanted':>11} {'err flat':>8}")
    for name, (ck, steps) in zip(names, arms):
        r = slant_moves(ck, args.data, args.count, progress=False, steps=steps)
        results[name] = r
        for cls, v in [*r["by_feature"].items(), ("all", r["all"])]:
            if v["moved_median"] is None:
                continue
            print(f"{name:<34} {r['cpu_hours'] or 0:>6.2f} {cls:<12} {v['pairs_with_slanted_points']:>5} "
                  f"{v['moved_median']:>6.2f} {v['short_rate']:>6.0%} {v['err_slanted_median']:>11.4f} "
                  f"{v['err_flat_median']:>8.4f}", flush=True)
    print(f"\nslanted ends, moved by the point's displacement as a share of the face's largest (0: by the pivot)")
    print(f"{'checkpoint':<34}" + "".join(f"{b:>9}" for b in SHARE_BINS))
    for name, r in results.items():
        v = r["by_feature"].get("slanted end", {}).get("moved_by_share") or {}
        print(f"{name:<34}" + "".join(f"{v[b]:>9.2f}" if v.get(b) is not None else f"{'-':>9}" for b in SHARE_BINS))
    if args.json:
        write_json(args.json, {"data": args.data, "count": args.count, "checkpoints": dict(zip(names, [c for c, _ in arms])),
                               "results": results})
    return 0


def curve(args) -> int:
    """One line per committed version of the continue file (``--min-gap`` apart) not yet in ``args.curve``."""
    import json
    import tempfile

    import torch
    from continue_curve import CONTINUE, pending

    from polycubenet.evaluate import slant_moves

    torch.set_num_threads(args.threads)
    out = Path(args.curve)
    with tempfile.TemporaryDirectory() as tmp:
        metas, done, todo = pending(out, tmp, args.min_gap)
        print(f"{len(metas)} versions of {CONTINUE}, {len(done)} already in {out.name}, {len(todo)} to read", flush=True)
        print(f"{'commit':>8} {'CPU-h':>6} {'moved: slanted end':>18} {'chamfer':>8} {'err slanted':>11}")
        for m in todo:
            r = slant_moves(m["file"], args.data, args.count, progress=False)
            line = {"commit": m["commit"], "cpu_hours": m["cpu_hours"], "gpu_hours": m["gpu_hours"],
                    "pairs": r["pairs"], "all": r["all"], "by_feature": r["by_feature"]}
            with out.open("a") as fh:  # one complete line per version
                fh.write(json.dumps(line) + "\n")
            bf = r["by_feature"]
            print(f"{m['commit'][:8]} {m['cpu_hours']:>6.2f} {bf.get('slanted end', {}).get('moved_median') or 0:>18.2f} "
                  f"{bf.get('chamfer', {}).get('moved_median') or 0:>8.2f} {r['all']['err_slanted_median']:>11.4f}",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
