"""Benchmark of synthetic pair generation (``polycubenet.synth``).

Generates ``--count`` pairs in this process (1 worker), then the same number through
``write_dataset`` with 2 worker processes, prints a table (pairs/s, s/pair, stage
times, genus histogram) and the extrapolated time for 30K pairs, and writes
``benchmarks/results/bench_synth.json``.

    python benchmarks/bench_synth.py [--count 40] [--n-cond 4096] [--n-target 4096]
"""

from __future__ import annotations

import argparse
import collections
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from polycubenet.atomic import write_json  # noqa: E402
from polycubenet.synth import make_pair, pair_seed, write_dataset  # noqa: E402

TARGET = 30_000


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--n-cond", type=int, default=4096)
    ap.add_argument("--n-target", type=int, default=4096)
    ap.add_argument("--sampler", default="poisson")
    ap.add_argument("--skip-workers", action="store_true", help="only the 1-worker run")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_synth.json"))
    args = ap.parse_args(argv)

    make_pair(pair_seed(args.seed, 10**6), n_cond=64, n_target=64, sampler=args.sampler)  # warm-up (imports)
    per_pair, genus, styles, stages, attempts, faces = [], collections.Counter(), collections.Counter(), collections.Counter(), [], []
    kinds = collections.Counter()
    t_all = time.perf_counter()
    for i in range(args.count):
        t0 = time.perf_counter()
        p = make_pair(pair_seed(args.seed, i), n_cond=args.n_cond, n_target=args.n_target, sampler=args.sampler)
        per_pair.append(time.perf_counter() - t0)
        genus[p.genus] += 1
        styles[p.meta["style"]] += 1
        stages.update(p.meta["timings"])
        attempts.append(p.meta["attempts"])
        faces.append(p.meta["n_faces"])
        kinds.update(set(p.deformation.kinds))
    t1w = time.perf_counter() - t_all
    rate1 = args.count / t1w

    rate2 = t2w = None
    if not args.skip_workers:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_dataset(tmp, args.count, args.seed, per_shard=args.count, n_cond=args.n_cond,
                          n_target=args.n_target, workers=2, sampler=args.sampler, progress=False)
            t2w = time.perf_counter() - t0
        rate2 = args.count / t2w

    per_pair = np.array(per_pair)
    result = {
        "count": args.count,
        "n_cond": args.n_cond,
        "n_target": args.n_target,
        "sampler": args.sampler,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform()},
        "one_worker": {"seconds": t1w, "pairs_per_s": rate1, "s_per_pair_mean": float(per_pair.mean()),
                       "s_per_pair_median": float(np.median(per_pair)), "s_per_pair_max": float(per_pair.max())},
        "two_workers": None if rate2 is None else {"seconds": t2w, "pairs_per_s": rate2,
                                                    "note": "write_dataset incl. process start-up and shard write"},
        "stage_s_per_pair": {k: v / args.count for k, v in stages.items()},
        "attempts_mean": float(np.mean(attempts)),
        "faces_median": float(np.median(faces)),
        "genus_histogram": {str(k): genus[k] for k in sorted(genus)},
        "style_histogram": dict(sorted(styles.items())),
        "map_kind_fraction": {k: kinds[k] / args.count for k in sorted(kinds)},
        "extrapolated_30k_hours": {"1_worker": TARGET / rate1 / 3600,
                                   "2_workers": None if rate2 is None else TARGET / rate2 / 3600},
    }
    write_json(args.out, result)

    print(f"synth benchmark: {args.count} pairs, {args.n_cond}/{args.n_target} points, sampler={args.sampler}, "
          f"{os.cpu_count()} CPUs")
    print(f"{'workers':>8} {'pairs/s':>9} {'s/pair':>8} {'30K pairs (h)':>14}")
    print(f"{1:>8} {rate1:>9.2f} {1 / rate1:>8.3f} {TARGET / rate1 / 3600:>14.2f}")
    if rate2 is not None:
        print(f"{2:>8} {rate2:>9.2f} {1 / rate2:>8.3f} {TARGET / rate2 / 3600:>14.2f}")
    print("stage s/pair: " + ", ".join(f"{k} {v:.3f}" for k, v in result["stage_s_per_pair"].items()))
    print(f"s/pair median {np.median(per_pair):.3f}, max {per_pair.max():.3f}; attempts mean {np.mean(attempts):.2f}; "
          f"faces median {np.median(faces):.0f}")
    print("genus histogram: " + "  ".join(f"{k}:{genus[k]}" for k in sorted(genus)))
    print("styles: " + "  ".join(f"{k}:{v}" for k, v in sorted(styles.items())))
    print("maps (fraction of pairs): " + "  ".join(f"{k}:{v:.2f}" for k, v in result["map_kind_fraction"].items()))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
