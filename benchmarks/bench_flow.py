"""Orchestration overhead: ``mesh_library`` against ``mesh_part`` in a loop, and 1 vs 2 Dask workers.

On ``--count`` held-out synthetic parts (seeds 9000+, written as STL with their
ground-truth polycube sidecars, ``polycube="oracle"`` so the model's quality plays no
part), in one process:

1. a plain loop: ``mesh_part_safe`` + ``PartResult.write`` for every part (the work
   the flow does, with no orchestration);
2. the flow on a local Dask cluster of 1 worker process (fresh work folder: nothing cached);
3. the flow on 2 worker processes (fresh work folder);
4. the flow again on the folder of 3: every stage comes from the cache.

The Prefect server is started before any timing; the Dask cluster's start is part of the
flow's time.  Overhead = flow(1 worker) / loop - 1.  The machine is shared, so each run
also records the load average and its *compute* seconds (the loop: the sum of
``mesh_part`` + write per part; the flow: the sum of its stage tasks' own seconds, from the
manifest): ``wall / compute`` (per worker) separates orchestration from a slower machine.
Each run also records the CPU seconds of every process it used (this one, the Dask
workers, the embedded Prefect server): on a shared machine the wall clock moves with
other people's jobs, the CPU seconds much less, so ``cpu overhead`` = flow CPU / loop
CPU - 1 is the steadier figure beside the wall-clock one.  The all-cached re-run gives
the orchestration cost per task (no stage computes there).  The defaults are the flow's
own (``PipelineConfig()``: 4096 sample points, 16384 polycube points, 5000 hexes), since
orchestration costs a fixed time per task and its share depends on the work per part.
Prints a table, writes JSON.

    python benchmarks/bench_flow.py --count 50 [--workers 1,2] [--hexes 5000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
if "PREFECT_HOME" not in os.environ:  # (Dask's spawned workers re-import this module: no mkdtemp there)
    os.environ["PREFECT_HOME"] = tempfile.mkdtemp(prefix="bench-flow-prefect-")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")

ROOT = Path(__file__).resolve().parents[1]


def cpu_seconds() -> float:
    """User + system CPU seconds of this process, its reaped children (finished Dask
    workers) and every live descendant (the Prefect server, running workers)."""
    import psutil

    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    for child in psutil.Process().children(recursive=True):
        try:
            c = child.cpu_times()
            total += c.user + c.system
        except psutil.Error:  # exited meanwhile: counted once reaped
            pass
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=50)
    ap.add_argument("--seed", type=int, default=9000)
    ap.add_argument("--workers", default="1,2")
    from polycubenet.pipeline import PipelineConfig

    d = PipelineConfig()
    ap.add_argument("--hexes", type=int, default=d.target_hexes)
    ap.add_argument("--n-sample", type=int, default=d.n_sample)
    ap.add_argument("--n-polycube", type=int, default=d.n_polycube)
    ap.add_argument("--n-register", type=int, default=d.n_register)
    ap.add_argument("--formats", default="vtu")
    ap.add_argument("--keep", type=Path, default=None, help="work here instead of a temporary folder (kept)")
    ap.add_argument("--json", type=Path, default=ROOT / "benchmarks" / "results" / "bench_flow.json")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)
    from prefect.client.orchestration import get_client

    from flows.mesh_library import mesh_library
    from flows.runners import dask_runner
    from polycubenet import library
    from polycubenet.frame import canonicalize
    from polycubenet.io import load_part
    from polycubenet.pipeline import PipelineConfig, mesh_part_safe

    base = args.keep or Path(tempfile.mkdtemp(prefix="bench-flow-"))
    base.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    parts = library.write_synthetic_parts(base / "parts", range(args.seed, args.seed + args.count))
    print(f"{len(parts)} parts in {base / 'parts'} ({time.perf_counter() - t0:.1f} s)")
    cfg = PipelineConfig(n_sample=args.n_sample, n_polycube=args.n_polycube, n_register=args.n_register,
                         target_hexes=args.hexes)
    formats = args.formats.split(",")
    flow_kw = dict(polycube="oracle", fallback=False, n_sample=cfg.n_sample, n_polycube=cfg.n_polycube,
                   n_register=cfg.n_register, target_hexes=cfg.target_hexes, formats=formats)

    with get_client(sync_client=True) as client:  # start the embedded server before any timing
        client.hello()

    # 1. the loop (the oracle sources are prepared outside the timing)
    sources = []
    for p in parts:
        part = load_part(p)
        sources.append(library.SidecarOracle(library.sidecar_path(p), canonicalize(part.vertices, part.faces)[1]))
    loop_out = base / "loop"
    shutil.rmtree(loop_out, ignore_errors=True)
    load0 = os.getloadavg()[0]
    c0 = cpu_seconds()
    t0 = time.perf_counter()
    ok = 0
    for p, src in zip(parts, sources):
        res = mesh_part_safe(p, src, cfg)
        if res.status == "meshed":
            res.write(loop_out / p.stem, formats=tuple(formats))
            ok += 1
    t_loop = time.perf_counter() - t0
    cpu_loop = cpu_seconds() - c0
    runs = [{"run": "mesh_part loop", "workers": 1, "seconds": round(t_loop, 2), "cpu_seconds": round(cpu_loop, 2),
             "meshed": ok,
             "failed": len(parts) - ok, "computed": None, "reused": None, "compute_seconds": round(t_loop, 2),
             "load_avg": [round(load0, 2), round(os.getloadavg()[0], 2)]}]
    print(f"loop: {t_loop:.1f} s, {ok}/{len(parts)} meshed")

    # 2, 3. the flow, fresh, per worker count; 4. cached re-run of the last one
    last_out = None
    for w in [int(x) for x in args.workers.split(",")]:
        out = base / f"flow-{w}"
        shutil.rmtree(out, ignore_errors=True)
        load0 = os.getloadavg()[0]
        c0 = cpu_seconds()
        t0 = time.perf_counter()
        r = mesh_library.with_options(task_runner=dask_runner(w))(inputs=[str(base / "parts")], out=str(out), **flow_kw)
        t = time.perf_counter() - t0
        cpu = cpu_seconds() - c0
        compute = sum(sum(row["timings"].values()) for row in r["rows"])
        runs.append({"run": f"flow, {w} Dask worker{'s' * (w > 1)}", "workers": w, "seconds": round(t, 2),
                     "cpu_seconds": round(cpu, 2),
                     "meshed": r["counts"]["meshed"], "failed": r["counts"]["failed"], "computed": r["computed"],
                     "reused": r["reused"], "compute_seconds": round(compute, 2),
                     "load_avg": [round(load0, 2), round(os.getloadavg()[0], 2)]})
        print(f"flow {w} workers: {t:.1f} s, {r['counts']}")
        last_out = out
    c0 = cpu_seconds()
    t0 = time.perf_counter()
    r = mesh_library.with_options(task_runner=dask_runner(1))(inputs=[str(base / "parts")], out=str(last_out), **flow_kw)
    t = time.perf_counter() - t0
    cpu = cpu_seconds() - c0
    n_tasks = r["computed"] + r["reused"]
    per_task = t / max(1, n_tasks)
    runs.append({"run": "flow re-run, all cached, 1 worker", "workers": 1, "seconds": round(t, 2),
                 "cpu_seconds": round(cpu, 2),
                 "meshed": r["counts"]["meshed"], "failed": r["counts"]["failed"], "computed": r["computed"],
                 "reused": r["reused"]})

    flow1 = next((x for x in runs if x["run"].startswith("flow, 1 ")), None)
    overhead = None if flow1 is None else flow1["seconds"] / t_loop - 1
    cpu_overhead = None if flow1 is None else flow1["cpu_seconds"] / cpu_loop - 1
    by_w = {x["workers"]: x["seconds"] for x in runs if x["run"].startswith("flow, ")}
    speedup = by_w[1] / by_w[2] if 1 in by_w and 2 in by_w else None

    print(f"\n{'run':<38}{'seconds':>9}{'cpu s':>9}{'s/part':>8}{'meshed':>8}{'failed':>8}{'computed':>10}{'reused':>8}"
          f"{'compute s':>11}{'wall/compute':>14}{'load avg':>14}")
    for x in runs:
        c = x.get("compute_seconds")
        ratio = "" if not c else f"{x['seconds'] * x['workers'] / c:.3f}"
        la = "" if "load_avg" not in x else f"{x['load_avg'][0]:.1f}->{x['load_avg'][1]:.1f}"
        print(f"{x['run']:<38}{x['seconds']:>9.1f}{x.get('cpu_seconds', 0):>9.1f}{x['seconds'] / len(parts):>8.2f}{x['meshed']:>8}{x['failed']:>8}"
              f"{'' if x['computed'] is None else x['computed']:>10}{'' if x['reused'] is None else x['reused']:>8}"
              f"{'' if c is None else f'{c:.1f}':>11}{ratio:>14}{la:>14}")
    if overhead is not None:
        print(f"orchestration overhead (flow 1 worker vs loop): wall {100 * overhead:+.1f}%, "
              f"CPU {100 * cpu_overhead:+.1f}%")
    print(f"all-cached re-run: {per_task:.3f} s per stage task ({n_tasks} tasks, flow start and manifest included)")
    if speedup is not None:
        print(f"1 -> 2 workers speed-up: {speedup:.2f}x (on {os.cpu_count()} CPU cores shared with other jobs)")
    result = {
        "benchmark": "bench_flow", "parts": len(parts), "seeds": [args.seed, args.seed + args.count - 1],
        "config": {"n_sample": cfg.n_sample, "n_polycube": cfg.n_polycube, "n_register": cfg.n_register,
                   "target_hexes": cfg.target_hexes, "formats": formats, "polycube": "oracle (sidecar, 0.5% noise, 2% outliers)"},
        "runs": runs, "overhead_flow1_vs_loop": None if overhead is None else round(overhead, 4),
        "cpu_overhead_flow1_vs_loop": None if cpu_overhead is None else round(cpu_overhead, 4),
        "cached_seconds_per_task": round(per_task, 4),
        "speedup_2_vs_1_workers": None if speedup is None else round(speedup, 3),
        "machine": {"cpu_count": os.cpu_count(), "python": platform.python_version(), "omp_threads": os.environ["OMP_NUM_THREADS"]},
        "date": time.strftime("%Y-%m-%d %H:%M"),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")
    if args.keep is None:
        shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
