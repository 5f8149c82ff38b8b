"""Where never-seen parts are lost on the learned path: extraction, validity, faithfulness or quality.

    python benchmarks/unseen_losses.py [RESULT.json ...] [--json benchmarks/results/unseen_losses.json] [--extraction-only]

Reads the JSON files ``benchmarks/unseen_parts.py --mesh`` writes (default: the seven sets whose figures the
model card reports) and sorts every part meshed through the learned source alone into one bucket:

* ``meshed``: valid, within the Hausdorff bar of the part and at least the quality bar (what the figure counts);
* ``rejected at extraction``: every draw's cloud gave no acceptable polycube (no mesh at all);
* ``not valid``: a polycube was accepted but its best mesh has an inverted hex;
* ``off the part``: valid, but farther from the part than the bar (:data:`polycubenet.tol.HAUSDORFF_REL_MAX`),
  split by how far (a polycube whose structure misses or adds a feature lands here);
* ``under the quality bar``: valid and faithful, minimum scaled Jacobian under ``PipelineConfig.min_sj``.

No model is run: it reads what the meshing runs recorded, so it costs nothing and says which stage a change
should aim at.

Where ``benchmarks/unseen_classical.py`` has meshed the same set through the classical chain
(``benchmarks/results/unseen_classical_<family><seed>.json``, and ``unseen_classical_examples.json`` for the
examples), every part is also sorted by what the classical chain gives for it (:func:`classical_class`): the
flattening meets the bars (the part has a coarse polycube that the learned one can be held to), only a voxel
polycube does, or nothing does; the second table counts the learned path's meshed parts in each class.
A third table splits the parts by the features their descriptions name (:func:`shape_class`: no slanted end,
a slanted end, a slanted end and a round through-hole) and counts in each the first draws accepted at
extraction, the learned path's meshes and the classical chain's.
A fourth splits them, the learned path's meshes and the classical chain's, by the part's sharpest convex edge
(``unseen_parts.py``'s ``knife_edge_deg``: the largest angle between the normals of two faces meeting on a convex
edge, 90 on a box; :data:`EDGE_BINS`), and the examples alike (computed from ``examples/parts``): where a slanted
cut crosses a hole, pocket or slot, or a hole grazes an edge, it leaves a knife edge that no example has.
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DEFAULT = ["unseen_parts.json", "unseen_parts_mixed.json", "unseen_parts_mixed31.json",
           "unseen_parts_mixed53.json", "unseen_parts_mixed71.json", "unseen_parts_blocks97.json",
           "unseen_parts_mixed89.json"]
BUCKETS = ("meshed", "rejected at extraction", "not valid", "off the part <= 1.5 %", "off the part 1.5-3 %",
           "off the part > 3 %", "under the quality bar")


def bucket(row: list, min_sj: float, bar: float) -> str:
    """The bucket of one ``mesh`` row of ``unseen_parts.py`` (ok, SJ min or the exception's name, draw,
    seconds, Hausdorff / diagonal, why the first draw was left, map)."""
    ok, sj, _draw, _s, dist = row[:5]
    if ok:
        return "meshed"
    if sj is None or isinstance(sj, str):
        return "rejected at extraction"
    if sj <= 0:
        return "not valid"
    if dist is not None and dist > bar:
        return ("off the part <= 1.5 %" if dist <= 0.015 else "off the part 1.5-3 %" if dist <= 0.03
                else "off the part > 3 %")
    if sj < min_sj:
        return "under the quality bar"
    return "not valid"  # pragma: no cover - a row the meshing run marked failed for another reason


#: the bins of the sharpest convex edge (degrees between the two faces' normals): up to 130 (the faces meet at 50
#: degrees or more), 130-150, above 150 (a knife edge under 30 degrees)
EDGE_BINS = ("sharpest edge <= 130 deg", "sharpest edge 130-150 deg", "sharpest edge > 150 deg")


def edge_class(deg: float | None) -> str | None:
    """The :data:`EDGE_BINS` bin of a sharpest convex edge of ``deg`` degrees (None: not known)."""
    if deg is None:
        return None
    return EDGE_BINS[0] if deg <= 130 else EDGE_BINS[1] if deg <= 150 else EDGE_BINS[2]


def edge_table(rows: list[dict], learned: dict, edges: dict | None = None, classical: dict | None = None) -> dict:
    """``{bin: [meshed, parts, classical meets the bars, parts with a classical row]}`` of the learned path's
    ``learned`` mesh rows (and ``classical``'s, :func:`classical_rows`, when given), by each part's sharpest
    convex edge: ``edges[name]`` when given, else the row's ``knife_edge_deg``; parts with neither are left out."""
    deg = {r["part"]: r.get("knife_edge_deg") for r in rows}
    deg.update(edges or {})
    out: dict = {}
    for name, row in learned.items():
        b = edge_class(deg.get(name))
        if b is not None:
            cell = out.setdefault(b, [0, 0, 0, 0])
            cell[0] += bool(row[0])
            cell[1] += 1
            if classical is not None and name in classical:
                cell[2] += classical_class(classical[name]) != CLASSICAL[2]
                cell[3] += 1
    return out


def example_edges(names) -> dict:
    """The sharpest convex edge of each example part named in ``names`` (``examples/parts/<name>.step``; a
    name without a file is left out)."""
    from unseen_parts import knife_edge_deg

    files = [ROOT / "examples/parts" / f"{n}.step" for n in sorted(names)]
    return {p.stem: knife_edge_deg(p) for p in files if p.is_file()}


CLASSICAL = ("flattening meets the bars", "only a voxel polycube does", "nothing meets the bars")


def classical_class(row: list) -> str:
    """The class of one ``mesh`` row of ``unseen_classical.py`` (meets the bars, SJ min, kept source, ...)."""
    ok, _sj, source = row[:3]
    if not ok:
        return CLASSICAL[2]
    return CLASSICAL[0] if source == "classical" else CLASSICAL[1]


def classical_rows(family: str, seed, results: Path) -> dict | None:
    """The classical chain's rows of one set (``unseen_classical.py``'s file for it, in the folder ``results``),
    or None when not run."""
    from unseen_classical import result_file

    f = results / result_file(family, seed).name
    return json.loads(f.read_text())["mesh"] if f.exists() else None


SHAPES = ("no slanted end", "slanted end, no round hole", "slanted end and round hole")


def shape_class(desc: str | None) -> str | None:
    """The class of a never-seen part by the features its description (``unseen_parts.py``'s ``shape``) names:
    whether it has a slanted end (a profile's mitred end is one), and with it a round through-hole (the
    combination the model fails most); None without a description (the examples)."""
    if not desc:
        return None
    feats = [f.strip() for f in desc.split(",")]
    if not any(f.startswith(("slanted end", "mitred end")) for f in feats):
        return SHAPES[0]
    return SHAPES[2] if "round hole" in feats else SHAPES[1]


def shape_table(rows: list[dict], learned: dict | None, classical: dict | None) -> dict:
    """``{class: {parts, accepted (first draw, at extraction), meshed (learned path, within the bars; None
    for a run without ``--mesh``), classical (the classical chain meets the bars; None when not run)}}`` over
    ``unseen_parts.py``'s ``rows``."""
    out = {}
    for r in rows:
        cls = shape_class(r.get("shape"))
        if cls is None:
            continue
        cell = out.setdefault(cls, {"parts": 0, "accepted": 0, "meshed": None if learned is None else 0,
                                    "classical": None if classical is None else 0})
        cell["parts"] += 1
        cell["accepted"] += bool(r.get("accepted"))
        if learned is not None:
            cell["meshed"] += bool(learned.get(r["part"], [False])[0])
        if classical is not None and r["part"] in classical:
            cell["classical"] += classical_class(classical[r["part"]]) != CLASSICAL[2]
    return out


def add_shapes(total: dict, table: dict) -> None:
    """Add one set's :func:`shape_table` into ``total`` (a count that is None in either stays None)."""
    for cls, cell in table.items():
        acc = total.setdefault(cls, {"parts": 0, "accepted": 0, "meshed": 0, "classical": 0})
        for k, v in cell.items():
            acc[k] = None if v is None or acc[k] is None else acc[k] + v


def cross_table(learned: dict, classical: dict) -> dict:
    """``{classical class: [learned path meshed, parts]}`` over the parts both runs have."""
    out = {c: [0, 0] for c in CLASSICAL}
    for name, row in learned.items():
        if name in classical:
            cell = out[classical_class(classical[name])]
            cell[0] += bool(row[0])
            cell[1] += 1
    return out


def either(cross: dict) -> int:
    """Parts that the learned path or the classical chain meets the bars on (``cross_table``'s counts): every part
    the classical chain meets them on, and those the learned path alone does."""
    return cross[CLASSICAL[0]][1] + cross[CLASSICAL[1]][1] + cross[CLASSICAL[2]][0]


def main(argv=None) -> int:
    from polycubenet import tol
    from polycubenet.atomic import write_json
    from polycubenet.pipeline import PipelineConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="*", help="unseen_parts.py --mesh JSON files (default: the model card's seven)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/unseen_losses.json"))
    ap.add_argument("--extraction-only", action="store_true",
                    help="read runs made without --mesh: only the first draws accepted at extraction, by the "
                         "part's features (the third table)")
    args = ap.parse_args(argv)
    files = [Path(f) for f in args.results] or [ROOT / "benchmarks/results" / f for f in DEFAULT]
    min_sj, bar = PipelineConfig().min_sj, tol.HAUSDORFF_REL_MAX
    table, total, ex_total = {}, Counter(), Counter()
    cross, ex_cross = {c: [0, 0] for c in CLASSICAL}, None
    shapes: dict = {}
    edges: dict = {}
    ex_edges = None
    for f in files:
        d = json.loads(f.read_text())
        if args.extraction_only:
            add_shapes(shapes, shape_table(d.get("rows", []), None, None))
            continue
        if not d.get("mesh"):
            print(f"{f}: no meshing rows (run unseen_parts.py with --mesh)", file=sys.stderr)
            return 2
        c = Counter(bucket(r, min_sj, bar) for r in d["mesh"].values())
        table[f"{d['family']}:{d['seed']}"] = dict(c)
        total.update(c)
        classical = classical_rows(d["family"], d["seed"], f.parent)
        if classical is not None:
            for cls, (m, k) in cross_table(d["mesh"], classical).items():
                cross[cls][0] += m
                cross[cls][1] += k
        add_shapes(shapes, shape_table(d.get("rows", []), d["mesh"], classical))
        for b, counts in edge_table(d.get("rows", []), d["mesh"], classical=classical).items():
            cell = edges.setdefault(b, [0, 0, 0, 0])
            for i, v in enumerate(counts):
                cell[i] += v
        if not ex_total:  # the examples are the same ten parts in every file: count them once
            ex_total.update(bucket(r, min_sj, bar) for r in d.get("example_mesh", {}).values())
            ex_classical = classical_rows("examples", None, f.parent)
            if d.get("example_mesh"):
                ex_edges = edge_table([], d["example_mesh"], example_edges(d["example_mesh"]), ex_classical)
            if ex_classical is not None:
                ex_cross = cross_table(d.get("example_mesh", {}), ex_classical)
    if args.extraction_only:
        print(f"{'features':<30}{'parts':>6}{'accepted':>10}   (first draws, at extraction)")
        for cls in SHAPES:
            if cls in shapes:
                print(f"{cls:<30}{shapes[cls]['parts']:>6}{shapes[cls]['accepted']:>10}")
        write_json(args.json, {"files": [str(f.relative_to(ROOT)) if f.is_relative_to(ROOT) else str(f) for f in files],
                               "by_shape": {cls: shapes[cls] for cls in SHAPES if cls in shapes}})
        print(f"wrote {args.json}")
        return 0
    cols = list(table) + ["all", "examples"]
    print(f"{'bucket':<26}" + "".join(f"{c:>11}" for c in cols))
    for b in BUCKETS:
        cells = [table[c].get(b, 0) for c in table] + [total.get(b, 0), ex_total.get(b, 0)]
        print(f"{b:<26}" + "".join(f"{v:>11d}" for v in cells))
    n, ne = sum(total.values()), sum(ex_total.values())
    print(f"{'parts':<26}" + "".join(f"{sum(table[c].values()):>11d}" for c in table) + f"{n:>11d}{ne:>11d}")
    compared = sum(k for _, k in cross.values())  # parts with a classical row
    if compared:
        print(f"\nlearned path meshed / parts, by what the classical chain gives for the same part "
              f"(benchmarks/unseen_classical.py):\n{'classical chain':<30}{'never-seen':>12}{'examples':>12}")
        for c in CLASSICAL:
            ex = "-" if ex_cross is None else f"{ex_cross[c][0]}/{ex_cross[c][1]}"
            print(f"{c:<30}{cross[c][0]:>7d}/{cross[c][1]:<4d}{ex:>12}")
        ex = "-" if ex_cross is None else f"{either(ex_cross)}/{sum(k for _, k in ex_cross.values())}"
        print(f"{'either path meets the bars':<30}{either(cross):>7d}/{compared:<4d}{ex:>12}")
    if shapes:
        print(f"\nby the part's features (unseen_parts.py's shape descriptions):\n{'features':<30}{'parts':>6}"
              f"{'accepted':>10}{'meshed':>8}{'classical':>10}")
        for cls in SHAPES:
            if cls in shapes:
                c = shapes[cls]
                cl = "-" if c["classical"] is None else c["classical"]
                print(f"{cls:<30}{c['parts']:>6}{c['accepted']:>10}{c['meshed']:>8}{cl:>10}")
    if edges:
        print(f"\nmeshed / parts by the part's sharpest convex edge (degrees between its faces' normals), the learned "
              f"path and the classical chain:\n{'sharpest convex edge':<30}{'learned':>10}{'classical':>11}"
              f"{'examples':>10}{'classical':>11}")
        for b in EDGE_BINS:
            m, k, c, kc = edges.get(b, [0, 0, 0, 0])
            em, ek, ec, ekc = (ex_edges or {}).get(b, [0, 0, 0, 0])
            ex = "-" if ex_edges is None else f"{em}/{ek}"
            exc = "-" if ex_edges is None or not ekc else f"{ec}/{ekc}"
            print(f"{b:<30}{f'{m}/{k}':>10}{(f'{c}/{kc}' if kc else '-'):>11}{ex:>10}{exc:>11}")
    write_json(args.json, {"files": [str(f.relative_to(ROOT)) if f.is_relative_to(ROOT) else str(f) for f in files],
                           "by_edge": {b: edges[b] for b in EDGE_BINS if b in edges} or None,
                           "examples_by_edge": ex_edges,
                           "min_sj": min_sj, "hausdorff_bar": bar, "sets": table, "all": dict(total),
                           "examples": dict(ex_total),
                           "by_classical": {cls: v for cls, v in cross.items() if v[1]} or None,
                           "either": either(cross) if compared else None,
                           "examples_by_classical": ex_cross,
                           "by_shape": {cls: shapes[cls] for cls in SHAPES if cls in shapes} or None})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
