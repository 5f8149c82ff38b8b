"""How many neighbours does CPD's truncated E-step need?  The registration of generated clouds at several ``k``.

    python benchmarks/cpd_neighbours.py [--checkpoint C.pt] [--sets examples turned:5] [--count 16] \\
        [--ks 32 16 8] [--json benchmarks/results/cpd_neighbours.json]

The registration (:func:`polycubenet.pipeline.register_cloud`: rigid, then the low-rank CPD of
:func:`polycubenet.registration.cpd_nonrigid`) compares each part sample with its ``k`` nearest moving cloud
points in every E-step (:data:`polycubenet.registration.CPD_K`); the KD-tree query of those neighbours is most of
its time, and the registration runs once for every learned draw that passes extraction, in ``auto`` only.  For
each part this script takes the first learned draw that passes extraction (the checkpoint's draws, as
``mesh_part`` runs them), registers it once at every ``--ks`` value (the same cloud, the same points), and
reports per ``k``: the registration's seconds and iterations (coarse + fine), how far its map moves the
polycube partition's nodes from the first ``k``'s map (largest and 99th percentile, % of the part's diagonal),
and the mesh through that map (:func:`polycubenet.pipeline.pull_back_learned`, ``phase="map"``: the step that
ends the chain on most parts): valid, minimum scaled Jacobian, distance to the part, and whether it ends the
chain.  Totals per set and ``k``: seconds (and their ratio to the first ``k``'s), meshes that end the chain.
``--sets``: ``examples``, a folder of STEP files, or never-seen ``family:seed`` sets of ``unseen_parts.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def record_part(path: Path, checkpoint: str, steps: int, ks: list[int]) -> dict:
    """``{"draw", "rows": [per k: seconds, iterations, moved_max/p99 (% diagonal), valid, sj, off, ends]}`` of
    ``path``'s first learned draw that passes extraction; ``draw`` None (and no rows) when none does."""
    from polycubenet.errors import PolycubeError
    from polycubenet.frame import canonicalize
    from polycubenet.inference import ModelSource
    from polycubenet.io import load_part
    from polycubenet.pipeline import (PipelineConfig, _polycube_stages, own_diagonal, partition_polycube,
                                      pull_back_learned, source_chain)
    from polycubenet.policy import ends_chain, extraction_config, source_config
    from polycubenet.registration import align
    from polycubenet.sampling import poisson_disk

    cfg = PipelineConfig(polycube="learned", target_hexes=3000)
    part = load_part(path)
    Vc, T = canonicalize(part.vertices, part.faces)
    F = part.faces
    diagonal = own_diagonal(Vc, T)
    sample = poisson_disk(Vc, F, cfg.n_sample, seed=cfg.seed)
    clock = lambda name: contextlib.nullcontext()  # noqa: E731
    for label, source in source_chain(ModelSource(checkpoint, steps=steps, device="cpu"), cfg):
        try:
            _, P, N, A, poly = _polycube_stages(source, sample, Vc, F, part.meta.get("genus"),
                                                extraction_config(label, cfg), path.name, clock,
                                                types.SimpleNamespace())
        except PolycubeError:
            continue
        c = source_config(label, cfg)
        mesh_pc = partition_polycube(poly, c)
        # the points register_cloud registers (the same subsample for every k)
        sub = np.random.default_rng(cfg.seed + 5).choice(len(P), size=min(cfg.n_register, len(P)), replace=False)
        rows, ref = [], None
        for k in ks:
            t0 = time.perf_counter()
            corr = align(sample, P[sub], N[sub], k=k)
            seconds = time.perf_counter() - t0
            mapped = corr.map_points(mesh_pc.points)
            ref = mapped if ref is None else ref
            moved = np.linalg.norm(mapped - ref, axis=1) / diagonal
            mesh, _ = pull_back_learned(poly, corr, Vc, F, c, phase="map", diagonal=diagonal, part=path.name,
                                        partitioned=mesh_pc, anchored=None if A is None else (P, N, A),
                                        part_points=sample.points)
            m = mesh.meta
            rows.append({"k": k, "seconds": round(seconds, 2),
                         "iterations": int(sum(m_ for m_ in corr.meta.get("coarse_iterations", []))
                                           + corr.meta.get("fine_iterations", corr.meta["iterations"])),
                         "moved_max": 100 * float(moved.max()), "moved_p99": 100 * float(np.quantile(moved, 0.99)),
                         "valid": bool(m.get("valid")), "sj": m.get("sj_min"), "off": m.get("hausdorff"),
                         "ends": bool(ends_chain(m, cfg.min_sj))})
        return {"draw": label, "rows": rows}
    return {"draw": None, "rows": []}


def main(argv=None) -> int:
    from unseen_parts import set_paths

    from polycubenet.atomic import write_json
    from polycubenet.inference import DEFAULT_CHECKPOINT, resolve_steps

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    ap.add_argument("--sets", nargs="+", default=["examples"])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--ks", nargs="+", type=int, default=[32, 16, 8])
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/cpd_neighbours.json"))
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    steps = int(resolve_steps(None, "cpu", args.checkpoint)[1])
    tmp = Path(tempfile.mkdtemp(prefix="cpd-neighbours-"))
    result = {"checkpoint": args.checkpoint, "steps": steps, "ks": args.ks, "sets": {}}
    for spec in args.sets:
        paths = set_paths(spec, tmp, args.count)
        print(f"\n{spec}: {len(paths)} parts\n{'part':<22} {'k':>3} {'reg s':>6} {'iters':>5} {'moved max':>9} "
              f"{'p99':>6} {'valid':>5} {'min SJ':>6} {'off %':>6} {'ends':>4}", flush=True)
        parts = []
        for p in paths:
            rec = record_part(p, args.checkpoint, steps, args.ks)
            parts.append({"part": p.stem, **rec})
            for r in rec["rows"]:
                print(f"{p.stem:<22} {r['k']:>3} {r['seconds']:>6.2f} {r['iterations']:>5} {r['moved_max']:>8.3f}% "
                      f"{r['moved_p99']:>5.3f}% {'yes' if r['valid'] else 'no':>5} "
                      f"{(r['sj'] if r['sj'] is not None else float('nan')):>6.3f} "
                      f"{100 * (r['off'] if r['off'] is not None else float('nan')):>6.2f} "
                      f"{'yes' if r['ends'] else 'no':>4}", flush=True)
            if not rec["rows"]:
                print(f"{p.stem:<22} no draw passed extraction", flush=True)
        totals = {}
        for i, k in enumerate(args.ks):
            rows = [q["rows"][i] for q in parts if q["rows"]]
            totals[k] = {"seconds": round(sum(r["seconds"] for r in rows), 2), "ends": sum(r["ends"] for r in rows),
                         "valid": sum(r["valid"] for r in rows),
                         "moved_max": round(max((r["moved_max"] for r in rows), default=0.0), 4)}
        base = totals[args.ks[0]]["seconds"] or 1.0
        for k, t in totals.items():
            t["ratio"] = round(t["seconds"] / base, 3)
            print(f"{'total k=' + str(k):<22} registration {t['seconds']:7.1f} s (x{t['ratio']:.2f} of k={args.ks[0]}), "
                  f"valid {t['valid']}, ends the chain {t['ends']}, largest move {t['moved_max']:.3f} %", flush=True)
        result["sets"][spec] = {"parts": parts, "totals": totals}
        write_json(args.json, result)
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
