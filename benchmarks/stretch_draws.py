"""Does the model see a part's thin walls better when the part is stretched along a canonical axis?

    python benchmarks/stretch_draws.py --out benchmarks/results/s48_stretch.jsonl PART.step ... [--factors 1.5,2] [--seeds 0,1]
    python benchmarks/stretch_draws.py --table benchmarks/results/s48_stretch.jsonl

A polycube stays a polycube under a scaling along the axes, so a part stretched along one axis of its
canonical frame (then scaled back to a unit diagonal, as the model's training pairs are after their
+-15 % anisotropic augmentation) is another view of the same part in which walls across that axis are
thicker.  For each part, each stretch (none, then x, y, z by each factor) and each noise seed, the model's
one-step cloud (4096 points, the pipeline's anchors on the stretched part) is scaled back, normals
alike, and put through the pipeline's outlier filter and structure extraction with the part's genus
(``model_failures.extract_cloud``); one JSON line per draw says whether it was accepted.  ``--table``
prints, per part and stretch, the draws accepted, and the totals per family.
"""
from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def stretched_draw(loaded, Vc, F, scale, seed: int, n: int = 4096) -> np.ndarray:
    """The model's cloud ``(n, 6)`` for the canonical part ``(Vc, F)`` stretched by ``scale`` (3 factors) and
    re-normalised to a unit diagonal, mapped back to the unstretched frame (points divided, normals multiplied
    by the stretch, then normalised)."""
    from model_failures import learned_cloud

    from polycubenet.sampling import poisson_disk

    s = np.asarray(scale, dtype=float)
    Vs = Vc * s
    k = 1.0 / np.linalg.norm(Vs.max(0) - Vs.min(0))
    Vs = Vs * k
    cloud = learned_cloud(loaded, Vs, F, poisson_disk(Vs, F, 4096, seed=0), n, 1, seed)
    P = cloud[:, :3] / (s * k)
    N = cloud[:, 3:6] * s
    return np.hstack([P, N / np.linalg.norm(N, axis=1, keepdims=True)])


def table(rows: list[dict]) -> None:
    names = list(dict.fromkeys(r["variant"] for r in rows))
    hits = collections.Counter((r["part"], r["variant"]) for r in rows if r["ok"])
    fam = collections.defaultdict(collections.Counter)
    print(f"{'part':<20}" + "".join(f"{v:>7}" for v in names))
    for p in dict.fromkeys(r["part"] for r in rows):
        print(f"{p:<20}" + "".join(f"{hits[(p, v)]:>7}" for v in names))
        family = p.split("_")[0] if p.split("_")[0] in ("machined", "mixed", "blocks", "finished") else "examples"
        for v in names:
            fam[family][v] += hits[(p, v)]
    for f, c in fam.items():
        print(f"{'total ' + f:<20}" + "".join(f"{c[v]:>7}" for v in names))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("parts", nargs="*", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--factors", default="1.5,2")
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--table", type=Path, help="only print the table of a JSONL file written before")
    args = ap.parse_args(argv)
    if args.table:
        table([json.loads(line) for line in args.table.read_text().splitlines() if line.strip()])
        return 0
    if not args.out or not args.parts:
        ap.error("give --out and the parts (or --table FILE)")
    from model_failures import extract_cloud

    from polycubenet.errors import PolycubeError
    from polycubenet.frame import canonicalize
    from polycubenet.inference import load_model
    from polycubenet.io import load_part

    factors = [float(x) for x in args.factors.split(",")]
    variants = [("id", (1.0, 1.0, 1.0))] + [(f"{'xyz'[a]}{f:g}", tuple(f if i == a else 1.0 for i in range(3)))
                                            for f in factors for a in range(3)]
    loaded = load_model(None, "cpu")
    rows = []
    with args.out.open("w") as out:
        for path in args.parts:
            part = load_part(path)
            genus = int(part.meta["genus"])
            Vc, _ = canonicalize(part.vertices, part.faces)
            for name, scale in variants:
                for seed in (int(x) for x in args.seeds.split(",")):
                    row = {"part": path.stem, "variant": name, "seed": seed, "genus": genus}
                    try:
                        extract_cloud(stretched_draw(loaded, Vc, part.faces, scale, seed), genus, path.stem)
                        row["ok"] = True
                    except PolycubeError as exc:
                        row.update(ok=False, error=str(exc)[:120])
                    out.write(json.dumps(row) + "\n")
                    rows.append(row)
            print(f"[stretch] {path.stem}: " + " ".join(
                f"{n}={sum(r['ok'] for r in rows if r['part'] == path.stem and r['variant'] == n)}" for n, _ in variants),
                flush=True)
    table(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
