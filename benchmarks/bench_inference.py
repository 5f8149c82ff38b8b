"""Inference cost against output resolution, and batching of a mixed library.

1. Resolution sweep: one request, a fixed condition (``--n-in`` points), ``--steps`` DDIM
   steps, output resolutions from 1k to 1M points.  Every resolution runs in a fresh
   child process, so its numbers do not depend on what ran before: wall time of
   :func:`polycubenet.inference.generate` (best of ``--repeats`` while a run is short),
   time per DDIM step (the total over the steps: it includes the one-off encoding of the
   condition), and peak memory -- on a CPU the growth of the child's peak RSS
   (``ru_maxrss``) over a small warm-up, on CUDA ``torch.cuda.max_memory_allocated``
   above the loaded model (on a CPU the warm-up, which encodes the condition, sets a
   floor: a small output whose memory stays under it shows ~0).  The sweep stops before a resolution that its own
   extrapolation says would overrun ``--budget-s``, and says so.  Memory and time should
   grow linearly (the point side is processed in chunks of ``model.config.chunk``):
   the check is time(64k) / time(4k) <= 20 for 16x the points.
2. Mixed batch: ``--requests`` requests with output resolutions drawn from {2048, 4096,
   8192} and conditions from {1024, 2048} points: one :func:`generate` call (batched by
   resolution under the default point budget) against a loop of :func:`generate` calls
   with one request each; parts per second for both.  Equality: the batched call against
   the same requests each run alone in its own batch (``point_budget=1``: same request
   indices, so the same noise seeds) -- every result must match (allclose), and the
   first request also against its result from the one-request loop.

Timing does not depend on the weights: ``--random`` uses a freshly initialised ``cpu``
preset model written to a temporary checkpoint (the output says which was used); its
zero-initialised output layer gets random weights so that the equality check compares
outputs that depend on the condition.
Results go to ``benchmarks/results/bench_inference.json`` (one entry per device kind and
chunk size, e.g. ``"cpu, chunk 32768"``; a run keeps the other entries) and
``bench_inference.png``.  ``--chunk`` overrides the model's ``config.chunk`` (the number of
points processed at once; it changes speed and memory, not the result).

    OMP_NUM_THREADS=1 python benchmarks/bench_inference.py --checkpoint RUN/last.pt --steps 4 --threads 1
    OMP_NUM_THREADS=1 python benchmarks/bench_inference.py --random --steps 4 --threads 1
    python benchmarks/bench_inference.py --random --device cuda --steps 4          # on a GPU
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
SIZES = [1024, 4096, 16384, 65536, 262144, 1048576]


def box_cloud(n: int, seed: int) -> np.ndarray:
    """``n`` points on the surface of a box of diagonal 1, centred (a stand-in condition)."""
    rng = np.random.default_rng(seed)
    ext = np.array([0.75, 0.5, 0.3])
    ext = ext / np.linalg.norm(ext)
    p = (rng.random((n, 3)) - 0.5) * ext
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -0.5, 0.5) * ext[axis]
    return p.astype(np.float32)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kilobytes


# ----------------------------------------------------------------------------- one resolution (child)
def child(args) -> None:
    """Time and peak memory of one resolution; prints one JSON line."""
    import torch

    torch.set_num_threads(args.threads)
    from polycubenet.inference import generate, load_model

    loaded = load_model(args.checkpoint, args.device)
    cuda = args.device.startswith("cuda")
    cond = box_cloud(args.n_in, 0)
    generate([cond], 256, model=loaded, steps=1, device=args.device)  # warm-up: allocator, kernels, caches
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
        base_cuda = torch.cuda.memory_allocated()
    rss0 = peak_rss_mb()
    times = []
    for r in range(args.repeats):
        t0 = time.perf_counter()
        (out,) = generate([cond], args.n_out, model=loaded, steps=args.steps, seed=r, device=args.device,
                          chunk=args.chunk)
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
        if times[-1] > args.repeat_below_s:
            break
    row = {"n_out": args.n_out, "n_in": args.n_in, "steps": args.steps, "seconds": min(times), "runs": len(times),
           "per_step_s": min(times) / args.steps, "peak_rss_growth_mb": peak_rss_mb() - rss0,
           "finite": bool(np.isfinite(out).all()), "shape": list(out.shape)}
    if cuda:
        row["cuda_peak_mb"] = (torch.cuda.max_memory_allocated() - base_cuda) / 2**20
    print("RESULT " + json.dumps(row), flush=True)


def run_child(args, n_out: int, timeout: float) -> dict:
    cmd = [sys.executable, __file__, "--child", "--checkpoint", str(args.checkpoint), "--device", args.device,
           "--n-out", str(n_out), "--n-in", str(args.n_in), "--steps", str(args.steps), "--threads", str(args.threads),
           "--repeats", str(args.repeats), "--repeat-below-s", str(args.repeat_below_s)]
    if args.chunk:
        cmd += ["--chunk", str(args.chunk)]
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        raise RuntimeError(f"child for n_out={n_out} failed (rc {p.returncode}):\n{p.stderr[-2000:]}")
    return json.loads(lines[-1][len("RESULT "):])


# ----------------------------------------------------------------------------- sweep
def sweep(args) -> dict:
    rows, stopped = [], None
    t_start = time.perf_counter()
    print(f"\nresolution sweep on {args.device}: condition {args.n_in} points, {args.steps} DDIM steps, "
          f"a fresh process per resolution")
    print(f"{'n_out':>9} {'seconds':>9} {'s/step':>9} {'us/pt/step':>11} {'peak MB':>9} {'B/point':>9}")
    for n in args.sizes:
        spent = time.perf_counter() - t_start
        if rows:  # extrapolate linearly from the largest run so far (+ the child's start-up)
            prev = rows[-1]
            predicted = prev["seconds"] * n / prev["n_out"] + prev["startup_s"]
            if spent + predicted > args.budget_s:
                stopped = (f"stopped before n_out={n}: predicted {predicted:.0f} s would pass the "
                           f"{args.budget_s:.0f} s budget ({spent:.0f} s spent)")
                print(stopped)
                break
        t0 = time.perf_counter()
        try:
            row = run_child(args, n, timeout=max(60.0, args.budget_s - spent + 60))
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            stopped = f"n_out={n} did not complete: {str(exc).splitlines()[0]}"
            print(stopped)
            break
        row["startup_s"] = max(0.0, time.perf_counter() - t0 - row["seconds"] * row["runs"])
        mem = row.get("cuda_peak_mb", row["peak_rss_growth_mb"])
        row["bytes_per_point"] = mem * 2**20 / n
        row["us_per_point_step"] = 1e6 * row["per_step_s"] / n
        rows.append(row)
        print(f"{n:>9} {row['seconds']:>9.3f} {row['per_step_s']:>9.3f} {row['us_per_point_step']:>11.3f} "
              f"{mem:>9.1f} {row['bytes_per_point']:>9.0f}")
    by_n = {r["n_out"]: r for r in rows}
    out = {"rows": rows, "stopped": stopped, "memory": "cuda_peak_mb" if args.device.startswith("cuda")
           else "peak_rss_growth_mb", "largest_n_out": max(by_n) if by_n else None}
    if 4096 in by_n and 65536 in by_n:
        ratio = by_n[65536]["seconds"] / by_n[4096]["seconds"]
        out["time_ratio_64k_4k"] = ratio
        out["linear_check"] = ratio <= 20
        print(f"time(64k) / time(4k) = {ratio:.2f} for 16x the points (<= 20: {'yes' if ratio <= 20 else 'NO'})")
    big = [r for r in rows if r["n_out"] >= 16384]
    if len(big) >= 2:  # log-log slope of time and memory over the large resolutions (1 = linear)
        n = np.log([r["n_out"] for r in big])
        out["time_slope"] = float(np.polyfit(n, np.log([r["seconds"] for r in big]), 1)[0])
        mem = [max(r.get("cuda_peak_mb", r["peak_rss_growth_mb"]), 1e-3) for r in big]
        out["memory_slope"] = float(np.polyfit(n, np.log(mem), 1)[0])
        print(f"log-log slope for n_out >= 16384: time {out['time_slope']:.2f}, memory {out['memory_slope']:.2f} "
              f"(1 = linear)")
    return out


# ----------------------------------------------------------------------------- mixed batch
def mixed(args) -> dict:
    import torch

    torch.set_num_threads(args.threads)
    from polycubenet.inference import DEFAULT_POINT_BUDGET, generate, load_model, plan_batches

    rng = np.random.default_rng(args.seed)
    n_out = [int(x) for x in rng.choice([2048, 4096, 8192], size=args.requests)]
    n_in = [int(x) for x in rng.choice([1024, 2048], size=args.requests)]
    conds = [box_cloud(m, 100 + i) for i, m in enumerate(n_in)]
    loaded = load_model(args.checkpoint, args.device)
    kw = dict(model=loaded, steps=args.steps, seed=args.seed, device=args.device, chunk=args.chunk)
    generate([conds[0]], 256, model=loaded, steps=1, device=args.device)  # warm-up
    sync = torch.cuda.synchronize if args.device.startswith("cuda") else (lambda: None)
    batches = plan_batches(n_in, n_out, DEFAULT_POINT_BUDGET)

    def timed(fn):
        sync()
        t0 = time.perf_counter()
        res = fn()
        sync()
        return res, time.perf_counter() - t0

    batched, t_batched = timed(lambda: generate(conds, n_out, **kw))
    loop, t_loop = timed(lambda: [generate([c], [m], **kw)[0] for c, m in zip(conds, n_out)])
    alone, t_alone = timed(lambda: generate(conds, n_out, point_budget=1, **kw))
    diffs = [float(np.abs(a - b).max()) for a, b in zip(batched, alone)]
    moved = np.concatenate([np.linalg.norm(a[:, :3] - b[:, :3], axis=1) for a, b in zip(batched, alone)])
    widest = max(batches, key=len)
    eps_diff = first_step_eps_diff(loaded, [conds[i] for i in widest], n_out[widest[0]], args.device)
    equal = all(np.allclose(a, b, atol=1e-4, rtol=1e-4) for a, b in zip(batched, alone))
    first_equal = bool(np.allclose(batched[0], loop[0], atol=1e-4, rtol=1e-4))
    k = args.requests
    out = {
        "requests": k, "n_out": n_out, "n_in": n_in, "steps": args.steps, "point_budget": DEFAULT_POINT_BUDGET,
        "batches": len(batches), "batch_sizes": [len(b) for b in batches],
        "total_points": int(sum(n_in) + sum(n_out)),
        "batched_s": t_batched, "loop_s": t_loop, "alone_in_one_call_s": t_alone,
        "parts_per_s_batched": k / t_batched, "parts_per_s_loop": k / t_loop,
        "parts_per_s_alone_in_one_call": k / t_alone, "speedup_vs_loop": t_loop / t_batched,
        "batched_equals_alone": bool(equal), "max_abs_diff_batched_vs_alone": max(diffs),
        "mean_abs_diff_batched_vs_alone": float(np.mean([np.abs(a - b).mean() for a, b in zip(batched, alone)])),
        "fraction_points_moved_over_1e-3": float((moved > 1e-3).mean()),
        "first_step_eps_max_diff": eps_diff,
        "first_request_equals_loop": first_equal,
        "max_abs_diff_first_request_vs_loop": float(np.abs(batched[0] - loop[0]).max()),
        "shapes_ok": all(b.shape == (m, 6) for b, m in zip(batched, n_out)),
    }
    print(f"\nmixed batch on {args.device}: {k} requests, n_out in {{2048, 4096, 8192}}, n_in in {{1024, 2048}}, "
          f"{args.steps} DDIM steps -> {len(batches)} batches of sizes {out['batch_sizes']}")
    print(f"{'mode':<38} {'seconds':>8} {'parts/s':>8}")
    print(f"{'batched (one generate call)':<38} {t_batched:>8.2f} {k / t_batched:>8.3f}")
    print(f"{'one at a time (loop of generate)':<38} {t_loop:>8.2f} {k / t_loop:>8.3f}")
    print(f"{'one per batch in one call (budget=1)':<38} {t_alone:>8.2f} {k / t_alone:>8.3f}")
    print(f"batched / one-at-a-time throughput: {out['speedup_vs_loop']:.2f}x")
    print(f"batched == alone for every request (allclose 1e-4): {equal} (max |diff| {max(diffs):.2e}); "
          f"request 0 batched == its loop result: {first_equal}")
    print(f"  mean |diff| {out['mean_abs_diff_batched_vs_alone']:.2e}, points moved > 1e-3 of the diagonal: "
          f"{100 * out['fraction_points_moved_over_1e-3']:.2f} %; first denoiser call (t = T-1), batch of "
          f"{len(widest)} vs alone: max |eps diff| {eps_diff:.2e}")
    return out


def first_step_eps_diff(loaded, conds: list[np.ndarray], n_out: int, device: str) -> float:
    """Max difference of the network's first-step output for a batch against each request alone
    (same inputs): separates float rounding of batched kernels from anything in the sampler."""
    import torch

    from polycubenet.model.diffusion import to_network

    m, T = loaded.model, loaded.diffusion.T
    dev = torch.device(device)
    cond = to_network(torch.as_tensor(np.stack(conds), device=dev), None, m.config.xyz_scale)
    x = torch.randn((len(conds), n_out, m.config.point_dim), generator=torch.Generator().manual_seed(0)).to(dev)
    t = torch.full((len(conds),), T - 1, device=dev, dtype=torch.long)
    with torch.no_grad():
        both = m.denoise(x, t, m.encode(cond, chunk=m.config.chunk), chunk=m.config.chunk)
        worst = 0.0
        for i in range(len(conds)):
            one = m.denoise(x[i:i + 1], t[:1], m.encode(cond[i:i + 1], chunk=m.config.chunk), chunk=m.config.chunk)
            worst = max(worst, float((both[i:i + 1] - one).abs().max()))
    return worst


# ----------------------------------------------------------------------------- picture
def picture(runs: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4.2))
    for dev, run in runs.items():
        rows = run["sweep"]["rows"]
        if not rows:
            continue
        n = np.array([r["n_out"] for r in rows], float)
        t = np.array([r["per_step_s"] for r in rows])
        m = np.array([r.get("cuda_peak_mb", r["peak_rss_growth_mb"]) for r in rows])
        mem_label = "CUDA peak allocated" if dev.startswith("cuda") else "peak RSS growth"
        axes[0].loglog(n, t, "o-", label=f"{dev}")
        axes[0].loglog(n, t[-1] * n / n[-1], "k:", lw=0.8)
        axes[1].loglog(n, np.maximum(m, 1e-1), "o-", label=f"{dev}: {mem_label}")
        axes[1].loglog(n, max(m[-1], 1e-1) * n / n[-1], "k:", lw=0.8)
        mx = run.get("mixed")
        if mx:
            xs = np.arange(2) + (0.4 if dev.startswith("cuda") else 0.0)
            axes[2].bar(xs, [mx["parts_per_s_batched"], mx["parts_per_s_loop"]], width=0.35, label=dev)
    axes[0].set(xlabel="output points", ylabel="seconds per DDIM step", title="time (dotted: linear)")
    axes[1].set(xlabel="output points", ylabel="MB", title="peak memory (dotted: linear)")
    axes[2].set_xticks([0.2, 1.2], ["batched", "one at a time"])
    k = next((r["mixed"]["requests"] for r in runs.values() if r.get("mixed")), 0)
    axes[2].set(ylabel="parts / s", title=f"mixed resolutions ({k} requests)")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, help="default: polycubenet.inference.DEFAULT_CHECKPOINT")
    ap.add_argument("--random", action="store_true", help="a fresh random `cpu` preset model (timing only)")
    ap.add_argument("--device", help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    ap.add_argument("--n-in", type=int, default=2048, help="condition points in the resolution sweep")
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--chunk", type=int, help="points per chunk (default: the model's config.chunk)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--repeat-below-s", type=float, default=10.0, help="repeat a run only while it takes less")
    ap.add_argument("--budget-s", type=float, default=420.0, help="wall time allowed for the sweep")
    ap.add_argument("--requests", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--skip-mixed", action="store_true")
    ap.add_argument("--json", type=Path, default=RESULTS / "bench_inference.json")
    ap.add_argument("--png", type=Path, default=RESULTS / "bench_inference.png")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--n-out", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    import torch

    if args.device is None:
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.child:
        return child(args)

    from polycubenet.inference import DEFAULT_CHECKPOINT

    tmp = None
    if args.random:
        from polycubenet.model import Diffusion, PolycubeNet, preset
        from polycubenet.model.checkpoint import save_checkpoint

        torch.manual_seed(args.seed)
        net = PolycubeNet(preset("cpu"))
        with torch.no_grad():  # the output layer starts at zero: without this every output would be the
            torch.nn.init.normal_(net.denoiser.out.weight, std=0.05)  # noise alone and the equality check vacuous
        tmp = tempfile.TemporaryDirectory(prefix="bench_inference_")
        args.checkpoint = Path(tmp.name) / "random-cpu.pt"
        save_checkpoint(args.checkpoint, {"kind": "published", "model_config": net.config.to_dict(),
                                          "diffusion": Diffusion().to_dict(), "ema": net.state_dict()})
        weights = "random (fresh `cpu` preset, timing only)"
    else:
        args.checkpoint = args.checkpoint or DEFAULT_CHECKPOINT
        if not args.checkpoint.is_file():
            raise SystemExit(f"checkpoint {args.checkpoint} not found: pass --checkpoint PATH, or --random "
                             f"(timing does not depend on the weights)")
        weights = f"checkpoint {args.checkpoint}"
    from polycubenet.inference import load_model

    loaded = load_model(args.checkpoint, args.device)
    cfg = loaded.config
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    chunk = args.chunk or cfg.chunk
    key = f"{kind}, chunk {chunk}"
    print(f"weights: {weights}; model {cfg.denoiser.blocks}x{cfg.denoiser.layers} d={cfg.denoiser.dim}, "
          f"chunk {chunk}{'' if args.chunk else ' (config)'}; device {args.device}, torch threads {args.threads}")
    run = {"device": args.device, "device_name": torch.cuda.get_device_name() if kind == "cuda" else platform.processor()
           or platform.machine(), "machine": platform.node(), "cpu_count": os.cpu_count(), "threads": args.threads,
           "weights": weights, "model_config": cfg.to_dict(), "chunk": chunk, "date": time.strftime("%Y-%m-%d %H:%M:%S"),
           "load_average_at_start": list(os.getloadavg())}
    run["sweep"] = sweep(args)
    if not args.skip_mixed:
        run["mixed"] = mixed(args)
    run["load_average_at_end"] = list(os.getloadavg())
    if tmp is not None:
        tmp.cleanup()

    from polycubenet.atomic import write_json

    runs = {}
    if args.json.exists():
        try:
            runs = json.loads(args.json.read_text()).get("runs", {})
        except (json.JSONDecodeError, AttributeError):
            runs = {}
    runs[key] = run
    write_json(args.json, {"benchmark": "inference time and memory against resolution; mixed batching",
                           "runs": runs})
    picture(runs, args.png)
    print(f"wrote {args.json} and {args.png}")


if __name__ == "__main__":
    main()
