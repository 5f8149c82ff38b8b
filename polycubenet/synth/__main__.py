"""Command line: ``python -m polycubenet.synth --out DIR --count K --seed S``.

Writes ``DIR/shard-*.npz`` and ``DIR/dataset.json`` (see :mod:`polycubenet.synth.shards`);
re-running the same command resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import sys
import time

from .pairs import EDGE_LENGTH, SAMPLERS
from .polycube import FLANGES
from .shards import write_dataset


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m polycubenet.synth",
        description="Generate synthetic (shape, polycube) training pairs into .npz shards.",
    )
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--count", type=int, required=True, help="number of pairs")
    p.add_argument("--seed", type=int, required=True, help="dataset seed (pair i uses SeedSequence(seed, spawn_key=(i,)))")
    p.add_argument("--per-shard", type=int, default=256, help="pairs per shard (default 256)")
    p.add_argument("--n-cond", type=int, default=4096, help="condition points on the shape (default 4096)")
    p.add_argument("--n-target", type=int, default=4096, help="target points on the polycube (default 4096)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (default 1; output does not depend on it)")
    p.add_argument("--sampler", choices=SAMPLERS, default="poisson", help="surface sampler (default poisson)")
    p.add_argument("--edge-length", type=float, default=EDGE_LENGTH, help=f"surface refinement (default {EDGE_LENGTH})")
    p.add_argument("--full", action="store_true", help="also store meshes, face ids and barycentrics")
    p.add_argument("--cad-features", action="store_true",
                   help="also round bosses and cut slanted ends (features of machined parts; see make_pair)")
    p.add_argument("--whole-slants", action="store_true",
                   help="also cut whole ends by slanted planes (20-45 degrees) in half the pairs (see make_pair)")
    p.add_argument("--max-strength", type=float, default=None,
                   help="cap on the random strength of the global maps (0.35: the mild bends, tapers and shears "
                        "of machined parts; default: no cap)")
    p.add_argument("--tall-bosses", action="store_true",
                   help="more and taller bosses (posts up to about the stock's height); with --cad-features most "
                        "are rounded (see make_pair)")
    p.add_argument("--full-slants", type=float, default=0.0, metavar="P",
                   help="with --whole-slants: the share P of those cuts that run across the whole end, leaving none "
                        "of its face, as a saw cut does (default 0; see make_pair)")
    p.add_argument("--cut-slants", action="store_true",
                   help="with --whole-slants: each slanted end a plane cut that leaves the walls near it straight, "
                        "placed away from holes and steps (see make_pair)")
    p.add_argument("--turned", type=float, default=0.0, metavar="P",
                   help="the share P of pairs that are turned parts (shafts, bushings, flanges: coaxial steps rounded "
                        "about their axis, bores, bolt circles, cross holes; default 0; see make_pair)")
    p.add_argument("--bolt-circles", type=float, default=0.0, metavar="P",
                   help="with --turned: the share P of bolted flanges drilled on a circle of 3-8 holes instead of four "
                        "on the cross axes (default 0; see make_pair)")
    p.add_argument("--flanges", type=float, default=FLANGES, metavar="P",
                   help=f"with --turned: the share P of turned parts with a flange at one end (default {FLANGES:g}; "
                        "see make_pair)")
    p.add_argument("--min-holes", type=int, default=0, metavar="K",
                   help="the non-turned pairs attempt at least K through-holes: genus 2 and more, as drilled machined "
                        "parts are (default 0; see make_pair)")
    p.add_argument("--breakouts", type=float, default=0.0, metavar="P",
                   help="the share P of non-turned pairs with a hole that breaks out through a slanted end "
                        "(default 0; see make_pair)")
    p.add_argument("--gussets", type=float, default=0.0, metavar="P",
                   help="the share P of non-turned pairs with triangular ribs in concave corners, as brackets have "
                        "(default 0; see make_pair)")
    p.add_argument("--overwrite", action="store_true", help="regenerate existing shards / replace another dataset")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    t0 = time.perf_counter()
    try:
        paths = write_dataset(
            args.out, args.count, args.seed, per_shard=args.per_shard, n_cond=args.n_cond,
            n_target=args.n_target, workers=args.workers, sampler=args.sampler,
            edge_length=args.edge_length, full=args.full, overwrite=args.overwrite, cad_features=args.cad_features,
            whole_slants=args.whole_slants, max_strength=args.max_strength, tall_bosses=args.tall_bosses,
            full_slants=args.full_slants, cut_slants=args.cut_slants, turned=args.turned,
            bolt_circles=args.bolt_circles, flanges=args.flanges, min_holes=args.min_holes, breakouts=args.breakouts,
            gussets=args.gussets, progress=not args.no_progress,
        )
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    dt = time.perf_counter() - t0
    print(f"{args.count} pairs in {len(paths)} shard(s) under {args.out} ({dt:.1f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
