"""The polycube → hex spine on held-out synthetic pairs, with the ground-truth polycube as the
"generated" cloud (noise sigma = 0.5% of the diagonal, 2% outliers).

For every pair: structure recovered exactly (same minimal grid topology and occupancy
as the ground truth, planes within 3 sigma), valid hex mesh (min SJ > 0), min / avg SJ,
two-sided Hausdorff to the shape (relative to its diagonal), time per stage.  Prints
a table per part and the summary against the issue's targets, writes
``benchmarks/results/bench_spine.json`` and a picture of a few results
(``benchmarks/results/bench_spine.png``: part, polycube, hex mesh coloured by SJ).

    python benchmarks/bench_spine.py [--count 50] [--first-seed 9000] [--hexes 5000]

Seeds 9000+ are never used by the tests (they use < 2000).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from polycubenet.errors import PartError, PolycubeError
from polycubenet.pipeline import OracleSource, PipelineConfig, mesh_surface
from polycubenet.polycube import compress
from polycubenet.synth import make_pair

RESULTS = Path(__file__).parent / "results"


def same_structure(got, truth, atol: float) -> bool:
    ga, oa = compress([got.xs, got.ys, got.zs], got.occupancy)
    gb, ob = compress([truth.xs, truth.ys, truth.zs], truth.occupancy)
    return oa.shape == ob.shape and bool((oa == ob).all()) and all(np.allclose(a, b, atol=atol) for a, b in zip(ga, gb))


def picture(results: list, path: Path) -> None:
    """Rows of (part, polycube, hex boundary coloured by SJ) with matplotlib."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from polycubenet.hexmesh import boundary_quads
    from polycubenet.polycube import polycube_surface

    rows = [r for r in results if r["res"] is not None and r["res"].mesh is not None][:4]
    if not rows:
        return
    fig = plt.figure(figsize=(12, 3.6 * len(rows)), dpi=90)
    cmap = plt.get_cmap("viridis")
    for i, r in enumerate(rows):
        res, pair = r["res"], r["pair"]
        panels = []
        panels.append(("part (genus %d)" % pair.genus, pair.shape_vertices[pair.faces], None))
        Vp, Fp = polycube_surface(res.polycube.xs, res.polycube.ys, res.polycube.zs, res.polycube.occupancy)
        panels.append(("extracted polycube", Vp[Fp], None))
        q, owner = boundary_quads(res.mesh.hexes, return_hex=True)
        sj = res.report.sj[owner]
        panels.append((f"hex: {len(res.mesh.hexes)} hexes, SJ min {res.report.sj_min:.2f} avg {res.report.sj_avg:.2f}", res.mesh.points[q], sj))
        for j, (title, polys, val) in enumerate(panels):
            ax = fig.add_subplot(len(rows), 3, 3 * i + j + 1, projection="3d")
            colour = cmap(np.clip(val, 0, 1)) if val is not None else ("#4878a8" if j == 0 else "#d08a3c")
            pc = Poly3DCollection(polys, facecolors=colour, edgecolors="k" if val is not None else "none", linewidths=0.1)
            ax.add_collection3d(pc)
            lo, hi = polys.reshape(-1, 3).min(0), polys.reshape(-1, 3).max(0)
            ax.set_xlim(lo[0], hi[0]); ax.set_ylim(lo[1], hi[1]); ax.set_zlim(lo[2], hi[2])
            ax.set_box_aspect(hi - lo)
            ax.set_axis_off()
            ax.set_title(f"seed {r['seed']}: {title}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--count", type=int, default=50)
    ap.add_argument("--first-seed", type=int, default=9000)
    ap.add_argument("--hexes", type=int, default=5000)
    ap.add_argument("--noise", type=float, default=0.005)
    ap.add_argument("--outliers", type=float, default=0.02)
    args = ap.parse_args()
    cfg = PipelineConfig(target_hexes=args.hexes)
    results, rows = [], []
    hdr = f"{'seed':>5} {'g':>2} {'exact':>5} {'valid':>5} {'hexes':>6} {'SJmin':>6} {'SJavg':>6} {'Haus%':>6} {'time s':>7} {'cpu s':>6}  stage / error"
    print(hdr)
    for seed in range(args.first_seed, args.first_seed + args.count):
        pair = make_pair(seed, n_cond=256, n_target=256)
        src = OracleSource(pair.polycube, noise=args.noise, outliers=args.outliers)
        t0, c0 = time.perf_counter(), time.process_time()
        res, err = None, None
        try:
            res = mesh_surface(pair.shape_vertices, pair.faces, src, cfg, name=f"synth-{seed}",
                               part_meta={"genus": pair.genus}, canonical=True)
        except (PartError, PolycubeError) as exc:
            err = f"{getattr(exc, 'stage', '?')}: {type(exc).__name__}: {exc}"
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        row = {"seed": seed, "genus": pair.genus, "time_s": dt, "cpu_s": cpu, "error": err}
        if res is not None:
            q = res.report.to_dict()
            row.update(exact=same_structure(res.polycube, pair.polycube, atol=3 * args.noise + 2e-3),
                       valid=bool(q["valid"]), hexes=q["hex_count"], sj_min=q["sj_min"], sj_avg=q["sj_avg"],
                       hausdorff=q["surface"]["hausdorff"], timings=res.timings)
        else:
            row.update(exact=False, valid=False)
        rows.append(row)
        results.append({"seed": seed, "pair": pair, "res": res})
        if res is not None:
            print(f"{seed:>5} {pair.genus:>2} {str(row['exact']):>5} {str(row['valid']):>5} {row['hexes']:>6} "
                  f"{row['sj_min']:>6.3f} {row['sj_avg']:>6.3f} {100 * row['hausdorff']:>6.2f} {dt:>7.1f} {cpu:>6.1f}", flush=True)
        else:
            print(f"{seed:>5} {pair.genus:>2} {'-':>5} {'-':>5} {'':>6} {'':>6} {'':>6} {'':>6} {dt:>7.1f} {cpu:>6.1f}  {err}", flush=True)

    n = len(rows)
    ok = [r for r in rows if r.get("hexes")]
    med = lambda k: float(np.median([r[k] for r in ok])) if ok else float("nan")  # noqa: E731
    summary = {
        "pairs": n,
        "structure_exact_rate": sum(r["exact"] for r in rows) / n,
        "valid_rate": sum(r["valid"] for r in rows) / n,
        "median_sj_avg": med("sj_avg"),
        "median_hausdorff": med("hausdorff"),
        "median_time_s": float(np.median([r["time_s"] for r in rows])),
        # CPU seconds of this process: on a shared machine the wall time also counts other jobs
        "median_cpu_s": float(np.median([r["cpu_s"] for r in rows])),
        "load_average_1min_at_end": float(os.getloadavg()[0]) if hasattr(os, "getloadavg") else None,
        "median_stage_s": {k: float(np.median([r["timings"][k] for r in ok])) for k in (ok[0]["timings"] if ok else {})},
    }
    targets = {"structure_exact_rate": (">=", 0.95), "valid_rate": (">=", 0.95), "median_sj_avg": (">=", 0.85),
               "median_hausdorff": ("<=", 0.01), "median_time_s": ("<=", 20.0)}
    print("\nsummary (target):")
    for k, (op, t) in targets.items():
        v = summary[k]
        good = v >= t if op == ">=" else v <= t
        print(f"  {k:<22} {v:8.4f}   ({op} {t})  {'met' if good else 'NOT met'}")
    print(f"  median_cpu_s           {summary['median_cpu_s']:8.4f}   (CPU seconds of this process; wall time above)")
    print("  median stage seconds:", {k: round(v, 2) for k, v in summary["median_stage_s"].items()})
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_spine.json").write_text(json.dumps({"args": vars(args), "summary": summary, "rows": rows}, indent=2, default=str))
    picture(results, RESULTS / "bench_spine.png")
    print(f"wrote {RESULTS / 'bench_spine.json'} and bench_spine.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
