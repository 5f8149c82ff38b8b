"""What ``--polycube auto`` costs over ``--polycube classical``, and what the learned attempt costs.

    python benchmarks/bench_auto_cost.py [--parts examples/parts] [--hexes 3000] \\
        [--checkpoint CANDIDATE.pt] [--rounds 1] [--json benchmarks/results/bench_auto_cost.json]

Runs the CLI twice on the same folder, each into a fresh output and work folder (nothing
cached), in this order: ``--polycube classical`` then ``--polycube auto`` (the shipped
checkpoint or ``--checkpoint``'s, default steps and learned points), and reports the wall time of each, the
ratio auto / classical (target <= 1.3), and from the manifests: per part, which polycube
was kept, its stage seconds and the seconds that went to rejected polycubes (the learned attempt when it
was rejected).  The same machine and the same run: the ratio is what to compare.  ``--rounds N`` runs the
pair N times, alternating which goes first (classical, auto; auto, classical; ...), so that a machine whose load
drifts during the run weighs on both sides; the ratio is then total auto over total classical wall time, and
each round's ratio is printed and kept in the JSON (the table and the manifests' figures are the last round's).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_cli(mode: str, parts: str, hexes: int, extra: list[str]) -> tuple[float, dict]:
    out = Path(tempfile.mkdtemp(prefix=f"auto-cost-{mode}-"))
    cmd = [str(ROOT / ".venv/bin/polycubenet"), "mesh", parts, "-o", str(out / "out"), "--work", str(out / "work"),
           "--polycube", mode, "--hexes", str(hexes), "--formats", "vtu"] + extra
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**os.environ})
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        print(proc.stdout[-3000:], proc.stderr[-3000:])
        raise SystemExit(f"{mode}: exit {proc.returncode}")
    return wall, json.loads((out / "out" / "manifest.json").read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--parts", default=str(ROOT / "examples/parts"))
    ap.add_argument("--hexes", type=int, default=3000)
    ap.add_argument("--extra", nargs="*", default=["--polycube-points", "8192"],
                    help="more CLI flags for both runs (default: those of make demo)")
    ap.add_argument("--checkpoint", default=None,
                    help="the auto run's checkpoint (default: the shipped one), e.g. a candidate before it is shipped")
    ap.add_argument("--rounds", type=int, default=1, help="run the pair this many times, alternating the order")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/bench_auto_cost.json"))
    args = ap.parse_args(argv)
    res = {}
    walls: dict = {"classical": [], "auto": []}
    for i in range(max(1, args.rounds)):
        for mode in (("classical", "auto") if i % 2 == 0 else ("auto", "classical")):
            run_mode(mode, args, res, walls)
        if args.rounds > 1:
            print(f"round {i + 1}: auto / classical {walls['auto'][-1] / walls['classical'][-1]:.2f}", flush=True)
    for mode in res:
        res[mode]["wall_s"] = round(sum(walls[mode]), 1)
        res[mode]["round_walls_s"] = [round(w, 1) for w in walls[mode]]
    ratio = res["auto"]["wall_s"] / res["classical"]["wall_s"]
    report(args, res, ratio)
    return 0


def run_mode(mode: str, args, res: dict, walls: dict) -> None:
    """One CLI run of ``mode``: its wall time appended to ``walls[mode]``, its manifest's rows in ``res[mode]``."""
    extra = args.extra + (["--checkpoint", args.checkpoint] if args.checkpoint and mode == "auto" else [])
    wall, m = run_cli(mode, args.parts, args.hexes, extra)
    walls[mode].append(wall)
    rows = m["parts"]
    res[mode] = {"meshed": sum(r["status"] == "meshed" for r in rows),
                 "valid": sum(bool((r.get("quality") or {}).get("valid")) for r in rows),
                 "rejected_polycube_s": m["last_run"].get("rejected_polycube_seconds"),
                 "rows": [{"name": r["name"], "status": r["status"], "provenance": r.get("provenance"),
                           "sj_min": (r.get("quality") or {}).get("sj_min"),
                           "hausdorff": (r.get("quality") or {}).get("hausdorff"),
                           "seconds": round(sum(v for v in r["timings"].values()), 1),
                           "rejected_s": round(sum(v for k, v in r["timings"].items() if k.startswith("rejected_")), 2),
                           "fallback": r.get("fallback")} for r in rows]}
    print(f"{mode:>9}: {wall:7.1f} s wall, {res[mode]['meshed']} meshed, {res[mode]['valid']} valid, "
          f"{res[mode]['rejected_polycube_s'] or 0:.1f} s of stage time on rejected polycubes", flush=True)


def report(args, res: dict, ratio: float) -> None:
    """The summary line, the per-part table and the JSON."""
    learned = sum(r["provenance"] == "learned" for r in res["auto"]["rows"])
    from polycubenet import tol

    def within(r):
        return r.get("hausdorff") is not None and r["hausdorff"] <= tol.HAUSDORFF_REL_MAX

    learned_within = sum(r["provenance"] == "learned" and within(r) for r in res["auto"]["rows"])
    print(f"\nauto / classical wall time: {ratio:.2f} (target <= 1.3); parts meshed through the learned polycube: "
          f"{learned}/{len(res['auto']['rows'])}, {learned_within} of them within the {100 * tol.HAUSDORFF_REL_MAX:g} % "
          f"bar; within the bar: auto {sum(map(within, res['auto']['rows']))}, classical "
          f"{sum(map(within, res['classical']['rows']))}")
    print(f"\n{'part':<20} {'auto polycube':<14} {'auto SJmin':>10} {'classical SJmin':>15} {'auto off %':>10} "
          f"{'classical off %':>15} {'rejected s':>10} {'auto s':>7} {'classical s':>11}")
    cl = {r["name"]: r for r in res["classical"]["rows"]}
    for r in res["auto"]["rows"]:
        c = cl.get(r["name"], {})
        off = [100 * x["hausdorff"] if x.get("hausdorff") is not None else float("nan") for x in (r, c)]
        print(f"{r['name']:<20} {str(r['provenance']):<14} {r['sj_min'] or float('nan'):>10.3f} "
              f"{c.get('sj_min') or float('nan'):>15.3f} {off[0]:>10.2f} {off[1]:>15.2f} {r['rejected_s']:>10.1f} "
              f"{r['seconds']:>7.1f} {c.get('seconds', float('nan')):>11.1f}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"ratio": ratio, "learned": learned, "learned_within_bar": learned_within,
                                           "hexes": args.hexes, "checkpoint": args.checkpoint, "rounds": args.rounds,
                                           "cpus": os.cpu_count(), **res}, indent=1))


if __name__ == "__main__":
    sys.exit(main())
