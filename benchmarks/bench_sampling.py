"""Poisson-disk sampling: time and blue-noise quality against area-uniform sampling (the baseline).

Prints a table and writes ``benchmarks/results/bench_sampling.json``.  Ratios are
taken within the same run (the machines are shared and noisy).

    python benchmarks/bench_sampling.py [--sizes 1024 4096 16384 65536] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import trimesh

from polycubenet.sampling import min_spacing, poisson_disk, uniform_sample


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 16384, 65536])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "bench_sampling.json")
    args = ap.parse_args()

    mesh = trimesh.creation.torus(1.0, 0.35, major_sections=96, minor_sections=48)
    V, F = mesh.vertices, mesh.faces
    rows = []
    print(f"{'n':>7} {'poisson s':>10} {'uniform s':>10} {'time ratio':>11} {'min gap P':>10} {'min gap U':>10} {'gap ratio':>10}")
    for n in args.sizes:
        tp, tu = [], []
        for r in range(args.repeats):
            t0 = time.perf_counter()
            s = poisson_disk(V, F, n, seed=r)
            tp.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            u = uniform_sample(V, F, n, np.random.default_rng(r))
            tu.append(time.perf_counter() - t0)
        gp, gu = min_spacing(s.points), min_spacing(u.points)
        row = dict(n=n, poisson_s=min(tp), uniform_s=min(tu), time_ratio=min(tp) / min(tu), min_gap_poisson=gp, min_gap_uniform=gu, gap_ratio=gp / gu)
        rows.append(row)
        print(f"{n:>7} {row['poisson_s']:>10.3f} {row['uniform_s']:>10.4f} {row['time_ratio']:>11.1f} {gp:>10.4g} {gu:>10.4g} {row['gap_ratio']:>10.1f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": platform.node(), "faces": int(len(F)), "rows": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
