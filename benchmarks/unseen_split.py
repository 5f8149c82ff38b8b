"""Never-seen parts meshed through the learned source, split by the features that lose them, over many runs.

    python benchmarks/unseen_split.py RESULT.json [RESULT.json ...] [--arm NAME] [--json benchmarks/results/unseen_split.json]

Reads the JSON files ``benchmarks/learned_meshes.py`` writes (one arm each: ``--arm``, or the file's first, its
baseline), rebuilds every set's parts (``family:seed``, the file's ``count``; :func:`unseen_parts.make_parts`
draws them from their seed, so they are the parts that were meshed) only to read their descriptions and their
sharpest convex edge, and counts the parts meshed (valid, within the Hausdorff and quality bars, learned
provenance: what ``learned_meshes.py`` counts) in each class of ``unseen_losses.py``: by shape (no slanted end,
a slanted end, a slanted end and a round through-hole: :func:`unseen_losses.shape_class`) and by the sharpest
convex edge (:data:`unseen_losses.EDGE_BINS`), and by whether the part has walls or gaps thinner than the hexes of
a ``learned_meshes.py`` mesh (:data:`THIN_BINS`; :func:`polycubenet.quality.thin_features` at the edge of a cube of
the part's volume over :data:`HEXES`: features no mesh of that size follows, whatever its polycube), by how thin
they are against that hex edge (:data:`DEPTH_BINS`: the median thickness of the thinnest kind over the edge), and
into parts like the examples or not (:data:`LIKE_BINS`: no knife edge, nothing thinner than :data:`THIN_LIKE` of
a hex).  No model is run.  Prints one table per split, each row with the count per file and over all of them;
writes the JSON, with every part's sharpest edge, thickness ratio and whether it was meshed.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from unseen_losses import EDGE_BINS, SHAPES, edge_class, shape_class  # noqa: E402
from unseen_parts import make_parts  # noqa: E402

from polycubenet.atomic import write_json  # noqa: E402

#: the hexes of a learned_meshes.py mesh (unseen_parts.mesh_learned's target_hexes)
HEXES = 3000
THIN_BINS = ("no wall or gap thinner than a hex", "walls or gaps thinner than a hex")
#: a part like the examples has no convex edge sharper than 130 degrees (every example's is 90-111) and no wall or
#: gap thinner than this fraction of a hex.  Session 79 chose the fraction on the fresh sets of sessions 73-79
#: (the knife-edge-free parts' misses all had walls under 0.15 of a hex, none of their meshed parts did) and
#: then read it on the session 66-72 files, which it had not seen (MODEL_CARD.md, "Session 79")
THIN_LIKE = 0.15
LIKE_BINS = (f"like the examples (edges <= 130 deg, nothing under {THIN_LIKE:g} hex)",
             f"knife edge or features under {THIN_LIKE:g} hex")
#: the thinnest feature's median thickness over the hex edge, binned: the lower bound of each bin after the first
#: (none thinner than a hex), the last bin open below
DEPTH_FLOORS = (0.5, 0.3, THIN_LIKE)
DEPTH_BINS = ("none thinner than a hex", *(f"{lo:g}-{hi:g} hex" for lo, hi in zip(DEPTH_FLOORS, (1, *DEPTH_FLOORS))),
              f"under {DEPTH_FLOORS[-1]:g} hex")


def thin_class(ratio: float | None) -> str:
    """The :data:`THIN_BINS` bin of a part's thickness ratio (:func:`read_part`; None: no thin feature)."""
    return THIN_BINS[int(ratio is not None)]


def depth_class(ratio: float | None) -> str:
    """The :data:`DEPTH_BINS` bin of a part's thickness ratio (None: nothing thinner than a hex)."""
    if ratio is None:
        return DEPTH_BINS[0]
    return DEPTH_BINS[1 + sum(ratio < lo for lo in DEPTH_FLOORS)]


def like_class(deg: float | None, ratio: float | None) -> str | None:
    """The :data:`LIKE_BINS` bin of a part with sharpest convex edge ``deg`` and thickness ratio ``ratio``
    (None when the edge is not known)."""
    if deg is None:
        return None
    return LIKE_BINS[0] if edge_class(deg) == EDGE_BINS[0] and (ratio is None or ratio >= THIN_LIKE) else LIKE_BINS[1]


def read_part(path: Path) -> tuple[float, float | None]:
    """A part's sharpest convex edge (degrees; :func:`polycubenet.io.sharpest_convex_edge_deg`) and how thin its
    thinnest walls or gaps are: of the kinds thinner than the edge ``h`` of a cube of its volume over :data:`HEXES`
    (over at least 0.1 % of its surface: :func:`polycubenet.quality.thin_features`), the smallest median thickness
    over ``h``; None when it has none."""
    from polycubenet.io import load_part
    from polycubenet.quality import thin_features

    part = load_part(path)
    h = (abs(float(part.meta["volume"])) / HEXES) ** (1 / 3)
    thin = thin_features(part.vertices, part.faces, h)
    ratios = [v["median"] / h for v in thin.values() if v is not None]
    return float(part.meta["sharpest_edge_deg"]), (round(min(ratios), 3) if ratios else None)


def read_arm(path: Path, arm: str | None) -> tuple[str, dict[str, bool], list[str], int]:
    """``(arm name, {part: meshed}, sets, count)`` of one ``learned_meshes.py`` JSON."""
    d = json.loads(path.read_text())
    names = [s["name"] for s in d["summary"]]
    name = names[0] if arm is None else arm
    if name not in d["rows"]:
        raise SystemExit(f"{path}: no arm {name!r} (arms: {', '.join(names)})")
    return name, {part: bool(row[0]) for part, row in d["rows"][name].items()}, list(d["sets"]), int(d["count"])


def describe(sets: list[str], count: int, tmp: Path) -> dict[str, tuple[str, float, float | None]]:
    """``{part: (description, sharpest convex edge in degrees, thickness ratio)}`` of the never-seen sets, rebuilt from
    their seeds (:func:`read_part`)."""
    out = {}
    for spec in sets:
        family, seed = spec.split(":")
        folder = tmp / spec.replace(":", "_")
        folder.mkdir(parents=True, exist_ok=True)
        for p, desc in make_parts(folder, count, int(seed), family):
            out[p.stem] = (desc, *read_part(p))
            p.unlink()
    return out


SPLITS = ("shape", "edge", "thin", "depth", "like")


def split(meshed: dict[str, bool], info: dict[str, tuple[str, float, float | None]],
          out: dict[str, dict[str, list[int]]] | None = None) -> dict[str, dict[str, list[int]]]:
    """``{split: {class: [meshed, parts]}}`` for every split of :data:`SPLITS` (shape, sharpest edge, thin
    features, how thin, like the examples), added to ``out`` when given; a part whose build is not found again
    (an OpenCASCADE build that differs between machines) is counted under ``unknown``."""
    out = {k: {} for k in SPLITS} if out is None else out
    for part, ok in meshed.items():
        known = part in info
        desc, deg, ratio = info.get(part, (None, None, None))
        classes = (shape_class(desc), edge_class(deg), thin_class(ratio) if known else None,
                   depth_class(ratio) if known else None, like_class(deg, ratio))
        for key, cls in zip(SPLITS, classes):
            cell = out[key].setdefault(cls or "unknown", [0, 0])
            cell[0] += int(ok)
            cell[1] += 1
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", nargs="+", type=Path, help="learned_meshes.py JSON files")
    ap.add_argument("--arm", default=None, help="the arm to read in every file (default: each file's first)")
    ap.add_argument("--json", type=Path, default=ROOT / "benchmarks/results/unseen_split.json")
    args = ap.parse_args(argv)

    per_file, total = {}, {k: {} for k in SPLITS}
    with tempfile.TemporaryDirectory() as tmp:
        for f in args.results:
            arm, meshed, sets, count = read_arm(f, args.arm)
            info = describe(sets, count, Path(tmp) / f.stem)
            per_file[f.stem] = {"arm": arm, "sets": sets, "meshed": sum(meshed.values()), "parts": len(meshed),
                                "split": split(meshed, info),
                                "parts_missed": {p: info.get(p, (None,))[0] for p, ok in meshed.items() if not ok},
                                "parts": {p: dict(zip(("meshed", "edge_deg", "thin_ratio"),
                                                      (ok, *info.get(p, (None, None, None))[1:])))
                                          for p, ok in meshed.items()}}
            split(meshed, info, total)
            print(f"{f.stem}: {per_file[f.stem]['meshed']} / {len(meshed)} (arm {arm})", flush=True)
    for key, order in zip(SPLITS, (SHAPES, EDGE_BINS, THIN_BINS, DEPTH_BINS, LIKE_BINS)):
        classes = [c for c in (*order, "unknown") if c in total[key]]
        print(f"\n{'by ' + key:<44}" + "".join(f"{c[:22]:>24}" for c in classes))
        for name, r in per_file.items():
            print(f"{name:<44}" + "".join(f"{'%d / %d' % tuple(r['split'][key].get(c, [0, 0])):>24}" for c in classes))
        print(f"{'all':<44}" + "".join(f"{'%d / %d' % tuple(total[key][c]):>24}" for c in classes))
    write_json(args.json, {"files": [str(f) for f in args.results], "arm": args.arm, "per_file": per_file, "all": total})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
