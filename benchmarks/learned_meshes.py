"""Checkpoints compared where it counts: never-seen parts meshed through the learned polycube.

    python benchmarks/learned_meshes.py --checkpoints A.pt B.pt [--names a b] [--sets mixed:61 mixed:67] \\
        [--count 16] [--workers 2] [--draws default default] [--json benchmarks/results/learned_meshes.json]

Builds the never-seen parts of ``benchmarks/unseen_parts.py`` (``family:seed``, ``--count`` each) once,
then meshes every part with every checkpoint through the learned source alone, exactly as
``unseen_parts.py --mesh`` does (:func:`unseen_parts.mesh_learned`: every draw of
``polycubenet.policy.LEARNED_DRAWS``, no classical fallback).  A part counts when its mesh is valid,
within the Hausdorff bar and at least the quality bar, with a learned provenance.  The first checkpoint
is the baseline: the table gives each checkpoint's count, the parts it gains and loses against the
baseline, and its seconds (same run, same machine).  ``--workers`` runs the (checkpoint, part) jobs in
that many processes (one thread each).  The held-out figure (``python -m polycubenet.evaluate``) is read
on synthetic pairs; this one is read on machined-style parts the model never saw, the issue's target.

``--draws`` gives each arm (one per ``--checkpoints`` entry; repeat a checkpoint to compare tables) its own table
of the model's further draws instead of ``polycubenet.policy.LEARNED_DRAWS`` (``default``): entries
``STEPS/SEED/FALLBACKS/TURN[/ANCHORS]`` joined by commas, FALLBACKS ``y``/``n``, TURN ``x``, ``y``, ``z`` or ``-``
(none), ANCHORS ``uniform`` (the default) or ``even``, e.g. ``default`` against ``4/0/n/-,1/1/y/z`` (the
policy's first two further draws, the second turned about z; session 36).

``--mend-moves`` gives each arm the extraction's ``ExtractConfig.mend_moves`` (``default``: the config's, 0: no
topology mends; session 64 measured 3), to compare the code with and without them on one checkpoint;
the mends are a last resort, so ``--misses-only`` (the later arms only on the parts the first did not mesh) reads
the same gains in a fraction of the time.

``--own-structure`` gives each arm ``RealiseConfig.own_structure`` (``on``, ``off`` or ``default``): whether a
realisation that finds the part flattened on the learned labels bounds another valid polycube of the same genus
keeps that one (session 65) or falls back to the registration's map.  It too only adds to what a failed map does,
so ``--misses-only`` reads its gains; the ``part str.`` column counts the meshes made on the part's own structure.

``--sheets`` gives each arm ``ExtractConfig.sheet_bandwidths`` (``on``: the default, ``off``: None, close planes
that face opposite ways merged as before session 70); it can lose parts as well as gain them, so compare it on
whole sets.  ``--strips`` gives each arm the realisation's thin-strip rule (``on``: a chart under the minimum area
that borders both faces of another axis is kept, and close planes facing opposite ways across each other are not
merged: ``ClassicalConfig.keep_strips``, ``RealiseConfig.keep_sheets``, the default since session 82; ``repair``:
the first alone; ``off``: both off, the code before session 81); compare it on whole
sets too.  ``--only NAME ...`` keeps only the named parts of the sets (e.g. an earlier run's misses).
``--files PATH ...`` adds mesh files of any kind the product reads (the hard models' seeded variants, a customer's
parts), each named by its file stem; with it and no ``--sets`` only the files are run.
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


def _job(args: tuple[int, str, str, int, tuple | None, int | None, bool | None, bool | None, bool | None, int]
         ) -> tuple[int, str, list]:
    arm, checkpoint, path, steps, draws, mend_moves, own, sheets, strips, hexes = args
    import torch

    torch.set_num_threads(1)
    from unseen_parts import mesh_learned

    ((name, row),) = mesh_learned([Path(path)], checkpoint, steps, draws=draws,
                                     mend_moves=mend_moves, own_structure=own, sheets=sheets,
                                     strips=strips, hexes=hexes).items()
    return arm, name, list(row)


def compare(checkpoints: list[str], parts: list[Path], workers: int = 1,
            draws: list[tuple | None] | None = None, mends: list[int | None] | None = None,
            misses_only: bool = False, owns: list[bool | None] | None = None,
            sheets: list[bool | None] | None = None,
            strips: list[bool | str | None] | None = None, hexes: int = 3000) -> list[dict[str, list]]:
    """Per arm (a checkpoint, with its table of further draws from ``draws``: None for the policy's) part
    name -> :func:`unseen_parts.mesh_learned`'s row, every checkpoint at its own default steps.  With
    ``misses_only`` the arms after the first run only on the parts the first did not mesh, and take the first's
    row (marked ``"baseline"`` at its end) for the others: for an arm that can only add a last resort to what
    the first does (``--mend-moves``, ``--own-structure``), not for another checkpoint.  ``owns``: each arm's
    ``RealiseConfig.own_structure`` (None: the config's); ``sheets``: each arm's opposite-faces rule
    (``ExtractConfig.sheet_bandwidths``: None the config's, False off); ``strips``: each arm's thin-strip rule of
    the realisation (``ClassicalConfig.keep_strips`` and ``RealiseConfig.keep_sheets``; None the configs').
    ``hexes``: every arm's ``PipelineConfig.target_hexes``."""
    from polycubenet.inference import resolve_steps

    draws = draws or [None] * len(checkpoints)
    mends = mends or [None] * len(checkpoints)
    owns = owns or [None] * len(checkpoints)
    sheets = sheets or [None] * len(checkpoints)
    strips = strips or [None] * len(checkpoints)

    def jobs(arms, which):
        return [(i, checkpoints[i], str(p), int(resolve_steps(None, "cpu", checkpoints[i])[1]), draws[i], mends[i],
                 owns[i], sheets[i], strips[i], int(hexes))
                for i in arms for p in which]

    out: list[dict[str, list]] = [{} for _ in checkpoints]
    done = 0

    def run(todo) -> None:
        nonlocal done
        with ProcessPoolExecutor(max(1, workers)) as pool:
            for arm, name, row in (pool.map(_job, todo) if workers > 1 else map(_job, todo)):
                done += 1
                out[arm][name] = row
                print(f"[{done}] {Path(checkpoints[arm]).name} (arm {arm + 1}) {name}: "
                      f"{'meshed' if row[0] else 'not meshed'} ({row[3]} s)", flush=True)

    if not misses_only:
        run(jobs(range(len(checkpoints)), parts))
        return out
    run(jobs([0], parts))
    for arm in range(1, len(checkpoints)):
        out[arm] = {k: list(v) + ["baseline"] for k, v in out[0].items() if v[0]}
    run(jobs(range(1, len(checkpoints)), [p for p in parts if not out[0][p.stem][0]]))
    return out


def summary(names: list[str], checkpoints: list[str], result: list[dict[str, list]],
            draws: list[str] | None = None, mends: list[int | None] | None = None,
            owns: list[bool | None] | None = None, sheets: list[bool | None] | None = None,
            strips: list[bool | str | None] | None = None) -> list[dict]:
    """One row per arm: meshed count (and how many of them on the part's own structure, not the learned one:
    :func:`unseen_parts.map_name`), gained / lost parts against the first, seconds."""
    base = {k for k, v in result[0].items() if v[0]}
    rows = []
    for i, (name, ck) in enumerate(zip(names, checkpoints)):
        ok = {k for k, v in result[i].items() if v[0]}
        rows.append({"name": name, "checkpoint": ck, "draws": (draws or ["default"] * len(names))[i],
                     "mend_moves": (mends or [None] * len(names))[i],
                     "own_structure": (owns or [None] * len(names))[i],
                     "sheets": (sheets or [None] * len(names))[i],
                     "strips": (strips or [None] * len(names))[i],
                     "meshed": len(ok), "parts": len(result[i]),
                     "part_structure": sum(1 for k in ok if result[i][k][6] == "exact, part's structure"),
                     "gained": sorted(ok - base), "lost": sorted(base - ok),
                     "seconds": round(sum(v[3] for v in result[i].values()), 1)})
    return rows


def main(argv=None) -> int:
    from unseen_parts import make_parts, parse_draws

    from polycubenet.atomic import write_json

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoints", nargs="+", required=True, help="the first is the baseline")
    ap.add_argument("--names", nargs="+", default=None, help="one name per checkpoint (default: file names)")
    ap.add_argument("--sets", nargs="*", default=None,
                    help="family:seed of benchmarks/unseen_parts.py (default: the dev sets mixed:61 mixed:67, used for "
                         "no reported figure; none when --files is given)")
    ap.add_argument("--files", nargs="+", type=Path, default=[],
                    help="mesh files to run as well (STEP, STL, ...; e.g. the hard models' variants), named by their "
                         "stems, which must differ")
    ap.add_argument("--count", type=int, default=16, help="parts per set")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--draws", nargs="+", default=None,
                    help="one table of further draws per checkpoint (see above; default: the policy's)")
    ap.add_argument("--mend-moves", nargs="+", default=None,
                    help="the extraction's mend_moves per checkpoint (an integer or default; see above)")
    ap.add_argument("--own-structure", nargs="+", default=None, choices=["on", "off", "default"],
                    help="RealiseConfig.own_structure per checkpoint (see above)")
    ap.add_argument("--sheets", nargs="+", default=None, choices=["on", "off", "default"],
                    help="ExtractConfig.sheet_bandwidths per checkpoint: on (default) or off (None; see above)")
    ap.add_argument("--strips", nargs="+", default=None, choices=["on", "repair", "off", "default"],
                    help="the realisation's thin-strip rule per checkpoint (see above)")
    ap.add_argument("--hexes", type=int, default=3000,
                    help="target hexes of every mesh (default 3000, the figures of sessions 66-89; the product's "
                         "default is 5000)")
    ap.add_argument("--only", nargs="+", default=None, help="only these parts of the sets (names without .step)")
    ap.add_argument("--misses-only", action="store_true",
                    help="the arms after the first only on the parts the first did not mesh (see compare)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/learned_meshes.json"))
    args = ap.parse_args(argv)
    names = args.names or [Path(c).stem for c in args.checkpoints]
    if len(names) != len(args.checkpoints) or len(set(names)) != len(names):
        ap.error("--names needs one distinct name per checkpoint")
    if args.draws is not None and len(args.draws) != len(args.checkpoints):
        ap.error("--draws needs one table per checkpoint")
    try:
        tables = [parse_draws(d) for d in args.draws] if args.draws else None
    except ValueError as exc:
        ap.error(str(exc))
    if args.mend_moves is not None and len(args.mend_moves) != len(args.checkpoints):
        ap.error("--mend-moves needs one value per checkpoint")
    try:
        mends = [None if m == "default" else int(m) for m in args.mend_moves] if args.mend_moves else None
    except ValueError:
        ap.error("--mend-moves takes integers or default")
    if args.own_structure is not None and len(args.own_structure) != len(args.checkpoints):
        ap.error("--own-structure needs one value per checkpoint")
    owns = [None if o == "default" else o == "on" for o in args.own_structure] if args.own_structure else None
    if args.sheets is not None and len(args.sheets) != len(args.checkpoints):
        ap.error("--sheets needs one value per checkpoint")
    sheets = [None if o == "default" else o == "on" for o in args.sheets] if args.sheets else None
    if args.strips is not None and len(args.strips) != len(args.checkpoints):
        ap.error("--strips needs one value per checkpoint")
    strips = [{"default": None, "on": True, "off": False, "repair": "repair"}[o] for o in args.strips] if args.strips else None
    if args.sets is None:
        args.sets = [] if args.files else ["mixed:61", "mixed:67"]
    missing = [str(f) for f in args.files if not f.is_file()]
    if missing:
        ap.error(f"--files: no such file: {' '.join(missing)}")
    t0 = time.perf_counter()
    folder = Path(tempfile.mkdtemp(prefix="learned-meshes-"))
    parts = [f.resolve() for f in args.files]
    for s in args.sets:
        family, seed = s.split(":")
        parts += [p for p, _ in make_parts(folder, args.count, int(seed), family)]
    if len({p.stem for p in parts}) != len(parts):
        ap.error("the parts' names (file stems) must differ: rename the --files that share one")
    if args.only:
        missing = set(args.only) - {p.stem for p in parts}
        if missing:
            ap.error(f"--only names parts the sets do not make: {' '.join(sorted(missing))}")
        parts = [p for p in parts if p.stem in set(args.only)]
    result = compare(args.checkpoints, parts, args.workers, tables, mends, args.misses_only, owns, sheets, strips,
                     hexes=args.hexes)
    rows = summary(names, args.checkpoints, result, args.draws, mends, owns, sheets, strips)
    print(f"\n{'arm':<16} {'meshed':>9} {'part str.':>9} {'seconds':>8}  gained / lost against {names[0]}")
    for r in rows:
        print(f"{r['name']:<16} {r['meshed']:>4} / {r['parts']:<3} {r['part_structure']:>9} {r['seconds']:>8}  "
              f"+{len(r['gained'])} "
              f"{' '.join(r['gained'])} / -{len(r['lost'])} {' '.join(r['lost'])}")
    write_json(args.json, {"sets": args.sets, "files": [str(f) for f in args.files], "count": args.count, "hexes": args.hexes, "only": args.only,
                           "misses_only": args.misses_only, "summary": rows,
                           "rows": dict(zip(names, result)),
                           "seconds": round(time.perf_counter() - t0, 1)})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
