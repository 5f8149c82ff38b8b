"""Benchmark of the pull-back (``polycubenet.pullback.pull_back``) on synthetic pairs.

For each seed: the pair's polycube is partitioned (``--hexes`` target), pulled back onto the
part with the pair's exact polycube -> part map (optionally plus a smooth perturbation of
``--perturb`` x the diagonal, to mimic registration error), and measured with
``quality_report`` (scaled Jacobian, Hausdorff to the part).  Prints a per-part table and the
medians against the targets, and writes ``benchmarks/results/bench_pullback.json``.

    python benchmarks/bench_pullback.py [--seeds 5000:5020] [--hexes 6000] [--perturb 0.0]
        [--preview DIR]

Timings are wall-clock seconds of ``pull_back`` alone (the pair generation and the quality
report are not counted).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from polycubenet.atomic import write_json  # noqa: E402
from polycubenet.hexmesh import partition  # noqa: E402
from polycubenet.pullback import PullbackConfig, pull_back  # noqa: E402
from polycubenet.quality import quality_report  # noqa: E402
from polycubenet.synth import make_pair  # noqa: E402

TARGETS = {"valid_fraction": 0.95, "median_sj_avg": 0.85, "median_hausdorff": 0.01, "median_seconds": 20.0}


def smooth_perturbation(amplitude: float, seed: int, scale: float = 0.35):
    """A smooth displacement field ``(K, 3) -> (K, 3)`` with max magnitude about ``amplitude``.

    A sum of a few random low-frequency sines per axis (wavelength ~ ``scale`` x 2 pi,
    canonical frame, diagonal 1).
    """
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(3, 3, 3)) / scale  # (axis, term, xyz)
    phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
    weight = rng.uniform(0.5, 1.0, size=(3, 3))
    weight /= weight.sum(axis=1, keepdims=True)

    def field(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64)
        out = np.empty_like(p)
        for a in range(3):
            out[:, a] = (weight[a] * np.sin(p @ k[a].T + phase[a])).sum(axis=1)
        return amplitude * out / np.sqrt(3.0)

    return field


def parse_seeds(text: str) -> list[int]:
    if ":" in text:
        a, b = text.split(":")
        return list(range(int(a), int(b)))
    return [int(s) for s in text.split(",")]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="5000:5020")
    ap.add_argument("--hexes", type=int, default=6000, help="target hex count of the partition")
    ap.add_argument("--perturb", type=float, default=0.0, help="smooth map error, x the diagonal")
    ap.add_argument("--no-pillow", action="store_true")
    ap.add_argument("--preview", default=None, help="write quality.json/png + preview.png per part here")
    ap.add_argument("--samples", type=int, default=100_000, help="surface samples for the Hausdorff distance")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "bench_pullback.json"))
    args = ap.parse_args(argv)
    cfg = PullbackConfig(pillow=not args.no_pillow)
    seeds = parse_seeds(args.seeds)

    rows = []
    header = f"{'seed':>6} {'genus':>5} {'hexes':>6} {'minSJ':>7} {'avgSJ':>6} {'Haus%':>6} {'time_s':>6}  valid"
    print(header)
    print("-" * len(header))
    for seed in seeds:
        pair = make_pair(seed, n_cond=64, n_target=64, sampler="uniform")
        mesh_pc = partition(pair.polycube, target_hexes=args.hexes)
        to_part = pair.polycube_to_shape
        if args.perturb > 0:
            field = smooth_perturbation(args.perturb, seed)

            def to_part(p, _f=pair.polycube_to_shape, _g=field):
                return _f(p) + _g(p)

        t0 = time.perf_counter()
        mesh = pull_back(mesh_pc, to_part, pair.shape_vertices, pair.faces, cfg)
        seconds = time.perf_counter() - t0
        rep = quality_report(mesh, surface=(pair.shape_vertices, pair.faces), n_samples=args.samples)
        if args.preview:
            rep.write(Path(args.preview) / f"seed{seed}")
        row = {
            "seed": seed,
            "genus": int(pair.genus),
            "style": pair.meta["style"],
            "hexes": int(len(mesh.hexes)),
            "hexes_polycube": int(len(mesh_pc.hexes)),
            "sj_min": rep.sj_min,
            "sj_avg": rep.sj_avg,
            "hausdorff": rep.surface["hausdorff"],
            "seconds": seconds,
            "valid": bool(rep.valid),
            "meta_valid": bool(mesh.meta["valid"]),
            "timings": mesh.meta["timings"],
            "multi_boundary_before": mesh.meta["multi_boundary_before"],
            "multi_boundary_after": mesh.meta["multi_boundary_after"],
            "projection": {k: v for k, v in mesh.meta["projection"].items() if k != "chart_triangles"},
        }
        rows.append(row)
        print(
            f"{seed:>6} {row['genus']:>5} {row['hexes']:>6} {row['sj_min']:>7.3f} {row['sj_avg']:>6.3f} "
            f"{100 * row['hausdorff']:>6.3f} {seconds:>6.2f}  {'yes' if row['valid'] else 'NO'}",
            flush=True,
        )

    valid_fraction = sum(r["valid"] for r in rows) / len(rows)
    summary = {
        "parts": len(rows),
        "valid_fraction": valid_fraction,
        "median_sj_min": statistics.median(r["sj_min"] for r in rows),
        "median_sj_avg": statistics.median(r["sj_avg"] for r in rows),
        "median_hausdorff": statistics.median(r["hausdorff"] for r in rows),
        "max_hausdorff": max(r["hausdorff"] for r in rows),
        "median_seconds": statistics.median(r["seconds"] for r in rows),
        "median_hexes": statistics.median(r["hexes"] for r in rows),
    }
    met = {
        "valid_fraction": summary["valid_fraction"] >= TARGETS["valid_fraction"],
        "median_sj_avg": summary["median_sj_avg"] >= TARGETS["median_sj_avg"],
        "median_hausdorff": summary["median_hausdorff"] <= TARGETS["median_hausdorff"],
        "median_seconds": summary["median_seconds"] <= TARGETS["median_seconds"],
    }
    print("-" * len(header))
    print(
        f"median: hexes {summary['median_hexes']:.0f}, min SJ {summary['median_sj_min']:.3f}, "
        f"avg SJ {summary['median_sj_avg']:.3f}, Hausdorff {100 * summary['median_hausdorff']:.3f}% "
        f"(max {100 * summary['max_hausdorff']:.3f}%), time {summary['median_seconds']:.2f} s; "
        f"valid {100 * valid_fraction:.0f}%"
    )
    print("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}" for k, v in met.items()))
    write_json(
        args.out,
        {
            "benchmark": "pullback",
            "command": " ".join(["python benchmarks/bench_pullback.py", *(argv if argv is not None else sys.argv[1:])]),
            "config": dataclasses.asdict(cfg),
            "hex_target": args.hexes,
            "perturb": args.perturb,
            "machine": {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count()},
            "targets": TARGETS,
            "targets_met": met,
            "summary": summary,
            "rows": rows,
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
