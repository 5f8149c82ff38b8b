"""Checkpoints compared where it counts: never-seen parts meshed through the learned polycube.

    python benchmarks/learned_meshes.py --checkpoints A.pt B.pt [--names a b] [--sets mixed:61 mixed:67] \\
        [--count 16] [--workers 2] [--json benchmarks/results/learned_meshes.json]

Builds the never-seen parts of ``benchmarks/unseen_parts.py`` (``family:seed``, ``--count`` each) once,
then meshes every part with every checkpoint through the learned source alone, exactly as
``unseen_parts.py --mesh`` does (:func:`unseen_parts.mesh_learned`: every draw of
``polycubenet.policy.LEARNED_DRAWS``, no classical fallback).  A part counts when its mesh is valid,
within the Hausdorff bar and at least the quality bar, with a learned provenance.  The first checkpoint
is the baseline: the table gives each checkpoint's count, the parts it gains and loses against the
baseline, and its seconds (same run, same machine).  ``--workers`` runs the (checkpoint, part) jobs in
that many processes (one thread each).  The held-out figure (``python -m polycubenet.evaluate``) is read
on synthetic pairs; this one is read on machined-style parts the model never saw, the issue's target.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _job(args: tuple[str, str, int]) -> tuple[str, str, list]:
    checkpoint, path, steps = args
    import torch

    torch.set_num_threads(1)
    from unseen_parts import mesh_learned

    ((name, row),) = mesh_learned([Path(path)], checkpoint, steps).items()
    return checkpoint, name, list(row)


def compare(checkpoints: list[str], parts: list[Path], workers: int = 1) -> dict[str, dict[str, list]]:
    """checkpoint -> part name -> :func:`unseen_parts.mesh_learned`'s row, every checkpoint at its own
    default steps."""
    from polycubenet.inference import resolve_steps

    jobs = [(ck, str(p), int(resolve_steps(None, "cpu", ck)[1])) for ck in checkpoints for p in parts]
    out: dict[str, dict[str, list]] = {ck: {} for ck in checkpoints}
    with ProcessPoolExecutor(max(1, workers)) as pool:
        results = pool.map(_job, jobs) if workers > 1 else map(_job, jobs)
        for done, (ck, name, row) in enumerate(results, 1):
            out[ck][name] = row
            print(f"[{done}/{len(jobs)}] {Path(ck).name} {name}: {'meshed' if row[0] else 'not meshed'} "
                  f"({row[3]} s)", flush=True)
    return out


def summary(names: list[str], checkpoints: list[str], result: dict[str, dict[str, list]]) -> list[dict]:
    """One row per checkpoint: meshed count, gained / lost parts against the first, seconds."""
    base = {k for k, v in result[checkpoints[0]].items() if v[0]}
    rows = []
    for name, ck in zip(names, checkpoints):
        ok = {k for k, v in result[ck].items() if v[0]}
        rows.append({"name": name, "checkpoint": ck, "meshed": len(ok), "parts": len(result[ck]),
                     "gained": sorted(ok - base), "lost": sorted(base - ok),
                     "seconds": round(sum(v[3] for v in result[ck].values()), 1)})
    return rows


def main(argv=None) -> int:
    from unseen_parts import make_parts

    from polycubenet.atomic import write_json

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", nargs="+", required=True, help="the first is the baseline")
    ap.add_argument("--names", nargs="+", default=None, help="one name per checkpoint (default: file names)")
    ap.add_argument("--sets", nargs="+", default=["mixed:61", "mixed:67"],
                    help="family:seed of benchmarks/unseen_parts.py (default: the dev sets, used for no reported figure)")
    ap.add_argument("--count", type=int, default=16, help="parts per set")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/learned_meshes.json"))
    args = ap.parse_args(argv)
    names = args.names or [Path(c).stem for c in args.checkpoints]
    if len(names) != len(args.checkpoints):
        ap.error("--names needs one name per checkpoint")
    t0 = time.perf_counter()
    folder = Path(tempfile.mkdtemp(prefix="learned-meshes-"))
    parts = []
    for s in args.sets:
        family, seed = s.split(":")
        parts += [p for p, _ in make_parts(folder, args.count, int(seed), family)]
    result = compare(args.checkpoints, parts, args.workers)
    rows = summary(names, args.checkpoints, result)
    print(f"\n{'checkpoint':<16} {'meshed':>9} {'seconds':>8}  gained / lost against {names[0]}")
    for r in rows:
        print(f"{r['name']:<16} {r['meshed']:>4} / {r['parts']:<3} {r['seconds']:>8}  +{len(r['gained'])} "
              f"{' '.join(r['gained'])} / -{len(r['lost'])} {' '.join(r['lost'])}")
    write_json(args.json, {"sets": args.sets, "count": args.count, "summary": rows,
                           "rows": {n: result[ck] for n, ck in zip(names, args.checkpoints)},
                           "seconds": round(time.perf_counter() - t0, 1)})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
