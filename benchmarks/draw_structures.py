"""Would skipping a learned draw whose structure repeats an earlier draw's save time without losing parts?

    python benchmarks/draw_structures.py RECORD.json ... [--checkpoint C.pt] [--json OUT.json]
    python benchmarks/draw_structures.py --replay OUT.json           (the count again, no model)

RECORD.json files are ``benchmarks/learned_meshes.py`` results (one arm): their sets are rebuilt
(``unseen_parts.make_parts``, the same seeds) and, for every part that was not meshed by its first draw,
each learned draw of the policy (``policy.LEARNED_DRAWS``, as ``--polycube learned`` runs them at 3000
hexes) is generated and its structure extracted, with no registration and no pull-back.  A draw's
structure is the extracted polycube's occupied cells (the grid's shape and which cells; not where its
planes lie).  The record says which draw meshed the part, or that none did.

The replay counts, for the rule "a draw whose cells equal an earlier draw's of the same part is left
before its registration": the draws it would leave on parts no draw meshed (the time saved), those it
would leave before the draw that meshed (saved too), and the parts whose meshing draw it would leave
(lost).  It also counts a second rule, "stop the learned source when its first K draws were all rejected at
extraction" (K = 2, 3, 4): the parts it loses and the parts no draw meshed that it stops early.  Prints the
parts with a repeated structure and the totals; writes the JSON (per part: the record's outcome and each
draw's signature, grid shape and cell count, or its extraction error).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def signature(occupancy) -> str:
    """The occupied cells as a short hash (the grid's shape and which cells)."""
    occ = np.asarray(occupancy, bool)
    return hashlib.sha1(str(occ.shape).encode() + np.packbits(occ).tobytes()).hexdigest()[:12]


def record(files: list[str], checkpoint: str, out: Path, parts_dir: Path) -> dict:
    from unseen_parts import make_parts

    from polycubenet import pipeline
    from polycubenet.errors import PolycubeError
    from polycubenet.inference import ModelSource
    from polycubenet.pipeline import PipelineConfig, mesh_part

    rec = json.loads(out.read_text()) if out.exists() else {}
    draws: list = []
    stages = pipeline._polycube_stages

    def watched(source, sample, Vc, F, genus, config, name, clock, res):
        try:
            got = stages(source, sample, Vc, F, genus, config, name, clock, res)
        except PolycubeError as exc:
            draws.append({"sig": None, "error": str(exc)[-160:]})
            raise
        occ = np.asarray(got[-1].occupancy, bool)
        draws.append({"sig": signature(occ), "shape": list(occ.shape), "cells": int(occ.sum())})
        return got

    def stop(*args, **kw):
        raise PolycubeError("left before registration (draw_structures.py records the structures only)")

    saved = pipeline._polycube_stages, pipeline.register_cloud
    pipeline._polycube_stages, pipeline.register_cloud = watched, stop
    cfg = PipelineConfig(polycube="learned", target_hexes=3000)
    try:
        for f in files:
            d = json.loads(Path(f).read_text())
            rows = next(iter(d["rows"].values()))
            for spec in d["sets"]:
                family, seed = spec.split(":")
                todo = [p for p, r in rows.items() if p.startswith(f"{family}_{seed}_") and not (r[0] and r[2] == 1)
                        and p not in rec]
                if not todo:
                    continue
                folder = parts_dir / f"{family}{seed}"
                if not all(any(folder.glob(p + ".*")) for p in todo):  # not built yet, or a build cut short
                    folder.mkdir(parents=True, exist_ok=True)
                    make_parts(folder, d["count"], int(seed), family)
                for p in todo:
                    draws.clear()
                    t0 = time.perf_counter()
                    try:
                        mesh_part(next(folder.glob(p + ".*")),
                                  ModelSource(checkpoint, steps=1, seed=0, device="cpu", anchors="uniform"), cfg)
                    except Exception:  # noqa: BLE001 - every draw is left on purpose
                        pass
                    r = rows[p]
                    rec[p] = {"record": Path(f).name, "meshed": bool(r[0]), "draw": r[2], "seconds": r[3],
                              "draws": list(draws), "seconds_here": round(time.perf_counter() - t0, 1)}
                    out.write_text(json.dumps(rec, indent=1))
                    print(p, rec[p]["meshed"], rec[p]["draw"], [x["sig"] for x in draws], flush=True)
    finally:
        pipeline._polycube_stages, pipeline.register_cloud = saved
    return rec


def replay(rec: dict) -> dict:
    """The rule's count on the records (see the module docstring)."""
    tot = {"parts": len(rec), "repeated": 0, "left_on_misses": 0, "left_before_the_hit": 0, "lost": []}
    print(f"{'part':<22} {'meshed':<7} {'draw':<5} structures (draw order; - : rejected at extraction)")
    for p, r in rec.items():
        sigs = [x["sig"] for x in r["draws"]]
        seen: set = set()
        left = []
        for s in sigs:
            left.append(s is not None and s in seen)
            if s is not None:
                seen.add(s)
        if not any(left):
            continue
        tot["repeated"] += 1
        if r["meshed"]:
            k = r["draw"] or 0
            tot["left_before_the_hit"] += sum(left[:k - 1])
            if 0 < k <= len(left) and left[k - 1]:
                tot["lost"].append(p)
        else:
            tot["left_on_misses"] += sum(left)
        print(f"{p:<22} {str(r['meshed']):<7} {str(r['draw']):<5} {' '.join((s or '-')[:4] for s in sigs)}")
    print(f"\n{tot['parts']} parts not meshed by their first draw; {tot['repeated']} with a repeated structure; "
          f"draws left on parts no draw meshed: {tot['left_on_misses']}; before the meshing draw: "
          f"{tot['left_before_the_hit']}; parts lost: {len(tot['lost'])} {tot['lost']}")
    for k in (2, 3, 4):
        first = {p: r for p, r in rec.items() if len(r["draws"]) > k and all(x["sig"] is None for x in r["draws"][:k])}
        lost = [p for p, r in first.items() if r["meshed"]]
        stopped = len(first) - len(lost)
        tot[f"stop_after_{k}_rejected"] = {"lost": lost, "stopped": stopped}
        print(f"stop after the first {k} draws all rejected at extraction: parts lost {len(lost)} {lost}; parts no "
              f"draw meshed stopped early {stopped}")
    return tot


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("records", nargs="*", help="learned_meshes.py result files")
    ap.add_argument("--checkpoint", default=str(ROOT / "polycubenet/checkpoints/polycubenet-cpu.pt"))
    ap.add_argument("--parts", default="/tmp/draw_structures_parts", help="where the sets are rebuilt")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/draw_structures.json"))
    ap.add_argument("--replay", default=None, help="count on an earlier output, no model")
    args = ap.parse_args()
    if args.replay:
        replay(json.loads(Path(args.replay).read_text()))
        return 0
    if not args.records:
        ap.error("name learned_meshes.py records, or --replay")
    out = Path(args.json)
    replay(record(args.records, args.checkpoint, out, Path(args.parts)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
