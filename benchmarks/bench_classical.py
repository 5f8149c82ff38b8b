"""The classical polycube (and the hybrid policy) on the HexGen models, the example parts and the hard models.

For each model: ``mesh_part`` with ``--polycube classical`` (and ``auto`` when a learned
source exists: ``polycubenet.inference`` with a shipped checkpoint), then min / avg scaled
Jacobian, hex count, Hausdorff (relative to the bounding-box diagonal), time, which polycube
was used and why, next to the published reference numbers (``reference.json``) for the
HexGen models.  Prints a table, writes ``benchmarks/results/bench_classical.json`` (updated
after every model, so a partial run keeps what it measured) and the quality report with
pictures of every result under ``benchmarks/results/classical/<mode>/<model>/``.

    OMP_NUM_THREADS=1 python benchmarks/bench_classical.py [--hexgen DIR] [--parts DIR]
        [--modes classical auto] [--models mount1 rod ...] [--hexes 5000]
        [--sets hexgen examples hard] [--hard] [--hard-dir DIR] [--hard-seed N] [--part-timeout 600]
        [--strips on|off|default] [--out FILE]

``--sets`` picks the model sets (default ``hexgen examples``); ``hard`` (or ``--hard``) adds the
hard CAD models of ``benchmarks/hard_models.py``, generated into ``--hard-dir`` (default
``benchmarks/results/hard_models/``, ignored by git) before the run.  ``--hard-seed N`` builds
instead the seeded variants of those models (other dimensions, never tuned on) into
``benchmarks/results/hard_models_seed<N>/`` (or ``--hard-dir``); their set is named
``hard_seed<N>`` (rows keyed ``hard_seed<N>/<model>``, pictures under ``<mode>/hard_seed<N>/``),
so they do not overwrite the fixed set's results (the flag adds the hard set to ``--sets``).  ``mesh_part`` has no
time limit of its own, so ``--part-timeout S`` (> 0) runs each part in a subprocess killed
after S seconds (status ``"timeout"``; a subprocess that dies is status ``"crashed"``).
``--strips on|off`` sets the flattening's thin-strip rule
(``ClassicalConfig.keep_strips``) to compare the chain with and without it (pictures then under
``benchmarks/results/classical-strips-<on|off>/``; give each its own ``--out``).
The summary prints one table per mode and set, with the median time and the counts of valid
meshes, min SJ >= 0.2 and Hausdorff <= 1% of the diagonal.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from polycubenet.atomic import write_json
from polycubenet.library import discover
from polycubenet.errors import PartError, PolycubeError
from polycubenet.pipeline import PipelineConfig, mesh_part

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
HEXGEN = ROOT / ".." / "shared" / "benchmark" / "hexgen"
PARTS = ROOT / "examples" / "parts"
HARD = RESULTS / "hard_models"
SETS = ("hexgen", "examples", "hard")
#: ``--strips``: ``ClassicalConfig.keep_strips`` (None: the config's default)
STRIPS = {"on": True, "off": False, "default": None}


def with_strips(cfg: PipelineConfig, keep_strips: bool | None) -> PipelineConfig:
    """``cfg`` with the flattening's thin-strip rule set (``ClassicalConfig.keep_strips``; None: unchanged)."""
    if keep_strips is None:
        return cfg
    return dataclasses.replace(cfg, classical=dataclasses.replace(cfg.classical, keep_strips=keep_strips))
SJ_BAR = 0.2  # the project's quality bar on the minimum scaled Jacobian
H_BAR = 0.01  # Hausdorff bar, relative to the bounding-box diagonal


def learned_source():
    """The learned polycube source, or None while no model is shipped."""
    try:
        from polycubenet import inference  # noqa: F401  (written by another issue)
    except ImportError:
        return None, "polycubenet.inference does not exist yet"
    make = getattr(inference, "default_source", None) or getattr(inference, "ModelSource", None)
    if make is None:
        return None, "polycubenet.inference has no default_source / ModelSource"
    try:
        src = make()
        load = getattr(inference, "load_model", None)
        if load is not None:  # no shipped checkpoint: auto is not measurable
            load(getattr(src, "model", None), getattr(src, "device", None))
        return src, None
    except Exception as exc:
        return None, f"learned source unavailable: {type(exc).__name__}: {exc}"


def run_one(path: Path, source, mode: str, hexes: int, pictures: Path, keep_strips: bool | None = None) -> dict:
    cfg = with_strips(PipelineConfig(polycube=mode, target_hexes=hexes), keep_strips)
    t0 = time.perf_counter()
    try:
        res = mesh_part(path, source, cfg)
    except (PartError, PolycubeError) as exc:
        return {"model": path.stem, "mode": mode, "status": "failed", "stage": getattr(exc, "stage", None),
                "error": f"{type(exc).__name__}: {exc}", "time": time.perf_counter() - t0}
    except Exception as exc:  # noqa: BLE001 - a bug on one part: record it, measure the others
        return {"model": path.stem, "mode": mode, "status": "crashed", "stage": None,
                "error": f"{type(exc).__name__}: {exc}", "time": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    res.write(pictures / path.stem)
    row = res.row()
    cm = res.cloud.meta if res.cloud is not None else {}
    return {
        "model": path.stem, "mode": mode, "status": row["status"], "valid": row["valid"],
        "hexes": row["hexes"], "sj_min": row["sj_min"], "sj_avg": row["sj_avg"],
        "hausdorff": row["hausdorff"], "time": wall, "timings": row["timings"],
        "provenance": row["provenance"], "fallback_reason": row["fallback_reason"],
        "genus": row["genus"], "polycube_grid": list(res.polycube.occupancy.shape),
        "flipped": cm.get("flipped"), "charts": cm.get("charts"), "turning_points": cm.get("turning_points"),
        "decimated": cm.get("decimated"), "voxel_resolution": cm.get("resolution"),
    }


def run_one_limited(path: Path, mode: str, hexes: int, pictures: Path, timeout: float,
                    strips: str = "default") -> dict:
    """:func:`run_one` in a subprocess (this script with ``--one``) killed after ``timeout`` s."""
    with tempfile.TemporaryDirectory(prefix="bench-classical-") as tmp:
        res_json = Path(tmp) / "row.json"
        cmd = [sys.executable, str(Path(__file__).resolve()), "--one", str(path), "--one-json", str(res_json),
               "--modes", mode, "--hexes", str(hexes), "--pictures", str(pictures), "--strips", strips]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            _, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)  # the child's own session: it and what it started
            proc.communicate()
            return {"model": path.stem, "mode": mode, "status": "timeout", "stage": None,
                    "error": f"over the per-part limit of {timeout:g} s", "time": time.perf_counter() - t0}
        if proc.returncode == 0 and res_json.exists():
            return json.loads(res_json.read_text())
        tail = " | ".join((err or "").strip().splitlines()[-3:])
        return {"model": path.stem, "mode": mode, "status": "crashed", "stage": None,
                "error": f"subprocess exit {proc.returncode}: {tail}"[:500], "time": time.perf_counter() - t0}


def fmt(x, nd=3):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def set_summary(rows: list[dict]) -> dict:
    """Counts and median time of one set's rows."""
    times = [r["time"] for r in rows if r.get("time") is not None]
    return {
        "total": len(rows),
        "valid": sum(1 for r in rows if r.get("valid")),
        "sj_min_ok": sum(1 for r in rows if r.get("valid") and (r.get("sj_min") or -1) >= SJ_BAR),
        "hausdorff_ok": sum(1 for r in rows if r.get("hausdorff") is not None and r["hausdorff"] <= H_BAR),
        "failed": sum(1 for r in rows if r.get("status") not in ("meshed",)),
        "median_time": statistics.median(times) if times else None,
    }


def print_table(rows: dict) -> None:
    print("| model | valid | min SJ (ref) | avg SJ (ref) | hexes (ref) | Hausdorff | time s | polycube | error |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        ref = r.get("reference", {})
        err = (r.get("error") or "").replace("|", "/")
        if len(err) > 90:
            err = err[:87] + "..."
        print(f"| {name} | {fmt(r.get('valid'))} | {fmt(r.get('sj_min'))} ({fmt(ref.get('ref_min_sj'))}) | "
              f"{fmt(r.get('sj_avg'))} ({fmt(ref.get('ref_avg_sj'))}) | {fmt(r.get('hexes'))} ({fmt(ref.get('ref_hexes'))}) | "
              f"{fmt(r.get('hausdorff'), 4)} | {r['time']:.1f} | {r.get('provenance') or '-'} | {err or '-'} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hexgen", type=Path, default=HEXGEN)
    ap.add_argument("--parts", type=Path, default=PARTS)
    ap.add_argument("--modes", nargs="+", default=["classical", "auto"])
    ap.add_argument("--models", nargs="*", default=None, help="model stems (default: all)")
    ap.add_argument("--hexes", type=int, default=5000)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_classical.json")
    ap.add_argument("--sets", nargs="+", choices=SETS, default=["hexgen", "examples"],
                    help="model sets to run (default: hexgen examples)")
    ap.add_argument("--hard", action="store_true", help="add the hard set (same as naming it in --sets)")
    ap.add_argument("--hard-dir", type=Path, default=None,
                    help="where the hard models are generated (default benchmarks/results/hard_models/, "
                         "or hard_models_seed<N>/ with --hard-seed)")
    ap.add_argument("--hard-seed", type=int, default=None,
                    help="build the hard set's seeded variants (set name hard_seed<N>) instead of the fixed models")
    ap.add_argument("--part-timeout", type=float, default=0.0,
                    help="wall seconds per part, each part in a subprocess (default 0: in process, no limit)")
    ap.add_argument("--strips", choices=("on", "off", "default"), default="default",
                    help="the flattening's thin-strip rule, ClassicalConfig.keep_strips (default: the config's); "
                         "with on / off the pictures go to benchmarks/results/classical-strips-<on|off>/")
    ap.add_argument("--one", type=Path, help=argparse.SUPPRESS)  # child of --part-timeout: one part
    ap.add_argument("--one-json", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--pictures", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.one is not None:  # one part, row to --one-json (the parent applies the time limit)
        mode = args.modes[0]
        src = learned_source()[0] if mode in ("auto", "learned") else None
        write_json(args.one_json, run_one(args.one, src, mode, args.hexes, args.pictures, STRIPS[args.strips]))
        return 0

    sets = list(dict.fromkeys(args.sets + (["hard"] if args.hard or args.hard_seed is not None else [])))
    ref_path = args.hexgen / "reference.json"
    reference = json.loads(ref_path.read_text()) if ref_path.exists() else {}
    files: list[tuple[Path, str]] = []
    if "hexgen" in sets:
        files += [(f, "hexgen") for f in sorted(args.hexgen.glob("*.obj"))]
    if "examples" in sets:  # the example parts as the flow finds them (a STEP file wins over an STL of the same stem)
        files += [(f, "examples") for f in discover([args.parts])]
    hard_set = "hard" if args.hard_seed is None else f"hard_seed{args.hard_seed}"
    if "hard" in sets:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from hard_models import default_folder, make_all

        names = args.models or None
        hard_dir = args.hard_dir or (HARD if args.hard_seed is None else default_folder(args.hard_seed))
        files += [(f, hard_set) for f in make_all(hard_dir, names=names, seed=args.hard_seed, keep_going=True)]
    if args.models:
        files = [(f, s) for f, s in files if f.stem in args.models]
    need_learned = any(m in ("auto", "learned") for m in args.modes)
    src, why_not = learned_source() if need_learned else (None, "not asked for (no auto / learned mode)")
    out = {"hexes_target": args.hexes, "strips": args.strips, "modes": {}, "auto_note": why_not,
           "sets": [hard_set if s == "hard" else s for s in sets],
           "part_timeout": args.part_timeout or None}
    if args.out.exists():  # keep models measured by an earlier (partial) run
        try:
            old = json.loads(args.out.read_text())
            out["modes"] = old.get("modes", {})
        except (ValueError, OSError):
            pass
    for mode in args.modes:
        if mode == "auto" and src is None:
            print(f"auto: not measurable ({why_not})")
            out["modes"]["auto"] = {"measured": False, "reason": why_not}
            continue
        rows = out["modes"].setdefault(mode, {})
        if "measured" in rows:
            rows.clear()
        pictures = RESULTS / ("classical" if args.strips == "default" else f"classical-strips-{args.strips}") / mode
        for f, set_name in files:
            key, pics = f.stem, pictures  # a variant set: its own keys and pictures, the fixed set's stay
            if set_name not in SETS:
                key, pics = f"{set_name}/{f.stem}", pictures / set_name
            if args.part_timeout and args.part_timeout > 0:
                r = run_one_limited(f, mode, args.hexes, pics, args.part_timeout, args.strips)
            else:
                r = run_one(f, src, mode, args.hexes, pics, STRIPS[args.strips])
            if set_name == "hexgen" and f.stem in reference:
                r["reference"] = reference[f.stem]
                ref = reference[f.stem]
                r["beats_reference"] = bool(
                    r.get("valid") and r["sj_min"] > ref["ref_min_sj"] and r["sj_avg"] > ref["ref_avg_sj"]
                    and r["hausdorff"] is not None and r["hausdorff"] <= 0.01
                )
            r["set"] = set_name
            r["path"] = str(f)
            rows[key] = r
            print(f"{mode:9s} {key:16s} {r['status']:7s} valid={fmt(r.get('valid'))} min={fmt(r.get('sj_min'))} "
                  f"avg={fmt(r.get('sj_avg'))} hexes={fmt(r.get('hexes'))} H={fmt(r.get('hausdorff'), 4)} "
                  f"t={r['time']:.1f}s flips={fmt(r.get('flipped'))} polycube={r.get('provenance')} "
                  f"{r.get('error') or r.get('fallback_reason') or ''}", flush=True)
            write_json(args.out, out)

    # summary tables: one per mode and set
    for mode, rows in out["modes"].items():
        if "measured" in rows:
            continue
        by_set: dict[str, dict] = {}
        for name, r in rows.items():
            by_set.setdefault(r.get("set", "examples"), {})[name] = r
        per_set = {}
        for set_name in [s for s in SETS if s in by_set] + [s for s in by_set if s not in SETS]:
            srows = by_set[set_name]
            print(f"\n## {mode} / {set_name}\n")
            print_table(srows)
            sm = per_set[set_name] = set_summary(list(srows.values()))
            med = "-" if sm["median_time"] is None else f"{sm['median_time']:.1f} s"
            print(f"\n{mode} / {set_name}: median time {med}; valid {sm['valid']}/{sm['total']}, "
                  f"min SJ >= {SJ_BAR} {sm['sj_min_ok']}/{sm['total']}, Hausdorff <= {H_BAR:.0%} "
                  f"{sm['hausdorff_ok']}/{sm['total']}, not meshed {sm['failed']}/{sm['total']}")
        summary = {f"{k}_{w}": per_set.get(k, {}).get(v, 0)
                   for k in ("hexgen", "examples") for w, v in (("valid", "valid"), ("total", "total"))}
        summary["sets"] = per_set
        out.setdefault("summary", {})[mode] = summary
        if "hexgen" in per_set or "examples" in per_set:
            print(f"\n{mode}: valid on {summary['hexgen_valid']}/{summary['hexgen_total']} HexGen models, "
                  f"{summary['examples_valid']}/{summary['examples_total']} example parts")
    write_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
