"""The classical polycube (and the hybrid policy) on the HexGen models and the example parts.

For each model: ``mesh_part`` with ``--polycube classical`` (and ``auto`` when a learned
source exists: ``polycubenet.inference`` with a shipped checkpoint), then min / avg scaled
Jacobian, hex count, Hausdorff (relative to the bounding-box diagonal), time, which polycube
was used and why, next to the published reference numbers (``reference.json``) for the
HexGen models.  Prints a table, writes ``benchmarks/results/bench_classical.json`` (updated
after every model, so a partial run keeps what it measured) and the quality report with
pictures of every result under ``benchmarks/results/classical/<mode>/<model>/``.

    OMP_NUM_THREADS=1 python benchmarks/bench_classical.py [--hexgen DIR] [--parts DIR]
        [--modes classical auto] [--models mount1 rod ...] [--hexes 5000]
"""

from __future__ import annotations

import argparse
import json
import sys
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


def run_one(path: Path, source, mode: str, hexes: int, pictures: Path) -> dict:
    cfg = PipelineConfig(polycube=mode, target_hexes=hexes)
    t0 = time.perf_counter()
    try:
        res = mesh_part(path, source, cfg)
    except (PartError, PolycubeError) as exc:
        return {"model": path.stem, "mode": mode, "status": "failed", "stage": getattr(exc, "stage", None),
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


def fmt(x, nd=3):
    return "-" if x is None else (f"{x:.{nd}f}" if isinstance(x, float) else str(x))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hexgen", type=Path, default=HEXGEN)
    ap.add_argument("--parts", type=Path, default=PARTS)
    ap.add_argument("--modes", nargs="+", default=["classical", "auto"])
    ap.add_argument("--models", nargs="*", default=None, help="model stems (default: all)")
    ap.add_argument("--hexes", type=int, default=5000)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_classical.json")
    args = ap.parse_args(argv)

    ref_path = args.hexgen / "reference.json"
    reference = json.loads(ref_path.read_text()) if ref_path.exists() else {}
    # the example parts as the flow finds them (a STEP file wins over an STL of the same stem)
    files = sorted(args.hexgen.glob("*.obj")) + discover([args.parts])
    if args.models:
        files = [f for f in files if f.stem in args.models]
    src, why_not = learned_source()
    out = {"hexes_target": args.hexes, "modes": {}, "auto_note": why_not}
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
        for f in files:
            r = run_one(f, src, mode, args.hexes, RESULTS / "classical" / mode)
            if f.stem in reference:
                r["reference"] = reference[f.stem]
                ref = reference[f.stem]
                r["beats_reference"] = bool(
                    r.get("valid") and r["sj_min"] > ref["ref_min_sj"] and r["sj_avg"] > ref["ref_avg_sj"]
                    and r["hausdorff"] is not None and r["hausdorff"] <= 0.01
                )
                r["set"] = "hexgen"
            else:
                r["set"] = "examples"
            rows[f.stem] = r
            print(f"{mode:9s} {f.stem:16s} {r['status']:7s} valid={fmt(r.get('valid'))} min={fmt(r.get('sj_min'))} "
                  f"avg={fmt(r.get('sj_avg'))} hexes={fmt(r.get('hexes'))} H={fmt(r.get('hausdorff'), 4)} "
                  f"t={r['time']:.1f}s flips={fmt(r.get('flipped'))} polycube={r.get('provenance')} "
                  f"{r.get('error') or r.get('fallback_reason') or ''}", flush=True)
            write_json(args.out, out)

    # summary tables
    for mode, rows in out["modes"].items():
        if "measured" in rows:
            continue
        print(f"\n## {mode}\n")
        print("| model | valid | min SJ (ref) | avg SJ (ref) | hexes (ref) | Hausdorff | time s | polycube |")
        print("|---|---|---|---|---|---|---|---|")
        for name, r in rows.items():
            ref = r.get("reference", {})
            print(f"| {name} | {fmt(r.get('valid'))} | {fmt(r.get('sj_min'))} ({fmt(ref.get('ref_min_sj'))}) | "
                  f"{fmt(r.get('sj_avg'))} ({fmt(ref.get('ref_avg_sj'))}) | {fmt(r.get('hexes'))} ({fmt(ref.get('ref_hexes'))}) | "
                  f"{fmt(r.get('hausdorff'), 4)} | {r['time']:.1f} | {r.get('provenance') or r.get('error', '')} |")
        hg = [r for r in rows.values() if r.get("set") == "hexgen"]
        valid = sum(1 for r in hg if r.get("valid"))
        summary = {"hexgen_valid": valid, "hexgen_total": len(hg),
                   "examples_valid": sum(1 for r in rows.values() if r.get("set") == "examples" and r.get("valid")),
                   "examples_total": sum(1 for r in rows.values() if r.get("set") == "examples")}
        out.setdefault("summary", {})[mode] = summary
        print(f"\n{mode}: valid on {valid}/{len(hg)} HexGen models, "
              f"{summary['examples_valid']}/{summary['examples_total']} example parts")
    write_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
