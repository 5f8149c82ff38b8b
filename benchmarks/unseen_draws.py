"""Never-seen parts, several noise draws each: which features does the model still fail on?

    python benchmarks/unseen_draws.py --checkpoints A.pt B.pt [--names a b] [--sets mixed:11 mixed:41 ...] \\
        [--count 16] [--draws 4] [--json benchmarks/results/unseen_draws.json]

Builds the never-seen parts of ``benchmarks/unseen_parts.py`` (``family:seed``, ``--count`` each) and,
for every checkpoint, generates ``--draws`` clouds per part (noise seeds 0 .. draws-1, the checkpoint's
default DDIM steps, 4096 points, anchors as ``ModelSource`` draws them), filters outliers and extracts
the structure with the part's genus, as the pipeline's learned source does.  A draw counts when the
extraction accepts it.  Many draws per part make a checkpoint comparison far less noisy than one first
draw per part (16 parts: one part is 6 points), and the features split shows what fails: the ``mixed``
parts carry round bosses, round holes and slanted ends.  Prints per checkpoint the accepted draws and the
parts with at least one per set, then the accepted fraction per feature; writes the JSON.  Unlike
``unseen_parts.py --mesh`` it does not mesh: acceptance at extraction, not a valid mesh.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

FEATURES = ("round boss", "round hole", "slanted")


def draw_parts(checkpoint: str, parts: list[tuple[Path, str]], draws: int, config=None) -> list[dict]:
    """One row per part: ``part``, ``shape`` (its description) and ``accepted`` (one bool per draw)."""
    from model_failures import extract_cloud, learned_cloud
    from polycubenet.errors import PolycubeError
    from polycubenet.frame import canonicalize
    from polycubenet.inference import load_model, resolve_steps
    from polycubenet.io import load_part
    from polycubenet.sampling import poisson_disk

    loaded = load_model(checkpoint, "cpu")
    steps = resolve_steps(None, "cpu", loaded)[1]
    rows = []
    for path, shape in parts:
        part = load_part(path)
        V, _ = canonicalize(part.vertices, part.faces)
        sample = poisson_disk(V, part.faces, 4096, seed=0)
        ok = []
        for s in range(draws):
            cloud = learned_cloud(loaded, V, part.faces, sample, 4096, steps, seed=s)
            try:
                extract_cloud(cloud, int(part.meta["genus"]), path.stem, config)
                ok.append(True)
            except PolycubeError:
                ok.append(False)
        rows.append({"part": path.stem, "shape": shape, "accepted": ok})
    return rows


def by_feature(rows: list[dict]) -> dict:
    """Accepted draws / draws of the parts with and without each feature (and with none of them)."""
    out = {}
    for f in FEATURES:
        for has in (True, False):
            sel = [r for r in rows if (f in r["shape"]) == has]
            out[("with " if has else "without ") + f] = (sum(sum(r["accepted"]) for r in sel),
                                                         sum(len(r["accepted"]) for r in sel))
    sel = [r for r in rows if not any(f in r["shape"] for f in FEATURES)]
    out["none of them"] = (sum(sum(r["accepted"]) for r in sel), sum(len(r["accepted"]) for r in sel))
    return out


def main(argv=None) -> int:
    from polycubenet.atomic import write_json
    from unseen_parts import make_parts

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=[str(ROOT / "polycubenet/checkpoints/polycubenet-cpu.pt")])
    ap.add_argument("--names", nargs="+", default=None, help="one name per checkpoint (default: file names)")
    ap.add_argument("--sets", nargs="+", default=["mixed:11", "mixed:41", "mixed:31", "blocks:7"],
                    help="family:seed of each never-seen set")
    ap.add_argument("--count", type=int, default=16, help="parts per set")
    ap.add_argument("--draws", type=int, default=4, help="noise draws per part")
    ap.add_argument("--fallbacks", action="store_true",
                    help="extract with the generator fallbacks (structure.GENERATOR_FALLBACKS: flattened ramps, "
                         "a wider kernel; the pipeline's first draw has them since session 15); without: bare")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/unseen_draws.json"))
    args = ap.parse_args(argv)
    from polycubenet.structure import ExtractConfig

    config = ExtractConfig() if args.fallbacks else ExtractConfig().for_exact_clouds()  # the defaults carry them
    names = args.names or [Path(c).stem for c in args.checkpoints]
    if len(names) != len(args.checkpoints):
        ap.error("--names needs one name per checkpoint")
    folder = Path(tempfile.mkdtemp(prefix="unseen-draws-"))
    sets = {}
    for spec in args.sets:
        family, _, seed = spec.partition(":")
        if family not in ("blocks", "mixed") or not seed.isdigit():
            ap.error(f"--sets takes family:seed with family blocks or mixed; got {spec!r}")
        sub = folder / spec.replace(":", "_")
        sub.mkdir(parents=True)
        sets[spec] = make_parts(sub, args.count, int(seed), family)
    result = {"draws": args.draws, "count": args.count, "sets": list(sets), "fallbacks": bool(args.fallbacks),
              "checkpoints": {}}
    for name, ck in zip(names, args.checkpoints):
        t0 = time.perf_counter()
        per_set = {spec: draw_parts(ck, parts, args.draws, config) for spec, parts in sets.items()}
        every = [r for rows in per_set.values() for r in rows]
        result["checkpoints"][name] = {"checkpoint": ck, "seconds": round(time.perf_counter() - t0, 1),
                                       "sets": per_set, "features": by_feature(every)}
        print(f"[unseen_draws] {name}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)

    head = f"{'checkpoint':18s}" + "".join(f"{s + ' draws':>16s}{'parts':>7s}" for s in sets)
    print(f"\naccepted at extraction, {args.draws} draws per part, {args.count} parts per set\n{head}")
    for name, res in result["checkpoints"].items():
        cells = ""
        for spec in sets:
            rows = res["sets"][spec]
            cells += f"{sum(sum(r['accepted']) for r in rows):>9d} / {len(rows) * args.draws:<4d}"
            cells += f"{sum(any(r['accepted']) for r in rows):>7d}"
        print(f"{name:18s}{cells}")
    keys = list(next(iter(result["checkpoints"].values()))["features"])
    print(f"\n{'by feature (all sets)':24s}" + "".join(f"{n:>18s}" for n in result["checkpoints"]))
    for k in keys:
        cells = "".join(f"{a}/{b} {a / max(b, 1):.2f}".rjust(18)
                        for a, b in (res["features"][k] for res in result["checkpoints"].values()))
        print(f"{k:24s}{cells}")
    write_json(args.json, result)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
