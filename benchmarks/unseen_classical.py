"""The classical polycube on the never-seen parts: is a part the learned path misses one that has a coarse polycube?

    python benchmarks/unseen_classical.py [--count 16] [--seed 53] [--family mixed] \\
        [--json benchmarks/results/unseen_classical_mixed53.json] [--strips on|off|default]
    python benchmarks/unseen_classical.py --examples      # the 10 example parts, for the same comparison

Builds the same parts as ``benchmarks/unseen_parts.py`` (same ``--count``, ``--seed`` and ``--family`` give the
same STEP files) and meshes each through the classical chain alone (``--polycube classical``: the surface
flattening, then the voxel polycubes), as ``mesh_part`` runs it.  A part counts when its mesh is valid, within
the Hausdorff bar and at least the quality bar: the test ``unseen_parts.meets_bars`` that ``unseen_parts.py
--mesh`` applies to the learned source.  The row also says which polycube made the kept mesh: ``classical``
(the flattening: a coarse polycube, what the learned polycube is compared with) or ``voxel``, ``voxel+K`` (a
grid of cells that follows the part without a coarse structure).

``--strips on|off`` sets the flattening's thin-strip rule (``ClassicalConfig.keep_strips``: a chart under the
minimum area that borders both faces of another axis keeps its own label; on by default since session 84, in the
learned path's realisation since session 82), to compare the two on one set.

``benchmarks/unseen_losses.py`` reads these files beside the learned ones and splits the learned misses by what
the classical chain gives for the same part.
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


def result_file(family: str, seed) -> Path:
    """Where this script writes a set's rows by default (and where ``unseen_losses.py`` looks for them):
    ``benchmarks/results/unseen_classical_<family><seed>.json``, ``..._examples.json`` for the examples."""
    name = "examples" if family == "examples" else f"{family}{seed}"
    return ROOT / "benchmarks/results" / f"unseen_classical_{name}.json"


def mesh_classical(paths: list[Path], keep_strips: bool | None = None) -> dict:
    """name -> (meets the bars, SJ min or the exception's name, the source whose mesh was kept, seconds,
    Hausdorff / diagonal); ``--polycube classical`` at the benchmark's 3000 hexes.  ``keep_strips`` sets the
    flattening's ``ClassicalConfig.keep_strips`` (None: the config's default)."""
    from bench_classical import with_strips
    from unseen_parts import meets_bars

    from polycubenet.pipeline import PipelineConfig, mesh_part

    cfg = with_strips(PipelineConfig(polycube="classical", target_hexes=3000), keep_strips)
    res = {}
    for p in paths:
        t0 = time.perf_counter()
        try:
            r = mesh_part(p, None, cfg)
            q = r.report
            ok = meets_bars(r, cfg)
            dist = r.row()["hausdorff"]
            res[p.stem] = (ok, None if q is None else q.sj_min, r.source, round(time.perf_counter() - t0, 1),
                           None if dist is None else round(float(dist), 4))
        except Exception as exc:  # noqa: BLE001 - report the failure in the row
            res[p.stem] = (False, type(exc).__name__, None, round(time.perf_counter() - t0, 1), None)
        print(f"{p.stem:<18} {'meets the bars' if res[p.stem][0] else 'misses':<15} {res[p.stem][2]!s:<10} "
              f"SJ {res[p.stem][1]}  Hausdorff {res[p.stem][4]}  {res[p.stem][3]} s", flush=True)
    return res


def main(argv=None) -> int:
    from unseen_parts import FAMILIES, make_parts

    from polycubenet.atomic import write_json

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--seed", type=int, default=53)
    ap.add_argument("--family", choices=FAMILIES, default="mixed")
    ap.add_argument("--examples", action="store_true", help="mesh the 10 example parts (examples/parts) instead")
    ap.add_argument("--json", default=None, help="default: benchmarks/results/unseen_classical_<family><seed>.json "
                    "(with --examples: unseen_classical_examples.json)")
    ap.add_argument("--strips", choices=("on", "off", "default"), default="default",
                    help="the flattening's thin-strip rule (ClassicalConfig.keep_strips; default: the config's)")
    args = ap.parse_args(argv)
    if args.examples:
        args.family, args.seed = "examples", None
    name = "examples" if args.examples else f"{args.family}{args.seed}"
    out = args.json or str(result_file(args.family, args.seed))
    t0 = time.perf_counter()
    if args.examples:
        made = [(p, "example") for p in sorted((ROOT / "examples/parts").glob("*.step"))]
    else:
        made = make_parts(Path(tempfile.mkdtemp(prefix="unseen-parts-")), args.count, args.seed, args.family)
    from bench_classical import STRIPS

    rows = mesh_classical([p for p, _ in made], STRIPS[args.strips])
    flat = sum(ok and src == "classical" for ok, _, src, _, _ in rows.values())
    any_ok = sum(bool(v[0]) for v in rows.values())
    print(f"\n{name}: the classical chain meets the bars on {any_ok}/{len(rows)} parts, "
          f"{flat} of them by the flattening (a coarse polycube)")
    write_json(out, {"seed": args.seed, "family": args.family, "strips": args.strips, "count": len(rows),
                     "met": any_ok,
                     "met_by_flattening": flat, "mesh": {k: list(v) for k, v in rows.items()},
                     "shapes": {p.stem: d for p, d in made}, "seconds": round(time.perf_counter() - t0, 1)})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
