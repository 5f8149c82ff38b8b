"""In what order should the learned draws' pull-back steps run?  Every draw's units timed, orders simulated.

    python benchmarks/learned_order.py [--checkpoint C.pt] [--sets examples turned:5] [--count 16] \\
        [--only NAME ...] [--no-rf] [--json benchmarks/results/learned_order.json]
    python benchmarks/learned_order.py --replay RECORDS.json ...     (the orders on earlier records, no meshing)

A learned draw that passes extraction costs two units of pull-back work
(:func:`polycubenet.pipeline.pull_back_learned`'s ``phase``): **A**, its mesh through the registration's map,
and, when that mesh does not end the chain, **B**, the rest (the exact realisation, the refined map after a near
miss, the spot mend, the denser pull-back).  Session 56's policy ran A1 B1 A2 B2 ... (each draw to its end before
the next draw).  Because the first five orders run the same units until one ends the chain, they mesh the same
parts; only the seconds differ.  This script meshes each part through the learned source alone (``--polycube
learned``, 3000 hexes, as ``benchmarks/unseen_parts.py --mesh``), recording each draw's seconds before the
pull-back (generation, extraction, registration), A and B, and whether each ended the chain, then replays the
orders on the same records (each B also records its mesh's minimum scaled Jacobian and distance to the part,
``b_sj`` / ``b_off`` and ``b_rf_sj`` / ``b_rf_off``, to compare what the orders keep):

* ``now``: A1 B1 A2 B2 ... (the default until session 57);
* ``defer``: every draw's A first (A1 A2 ...), then the B of each draw that gave a mesh, in draw order;
* ``defer-far``: a draw's B right after its A when A's mesh is a near miss
  (:func:`polycubenet.pipeline.near_miss`: valid, at most twice the Hausdorff bar off), otherwise after every
  later draw's A (the default since session 57: :func:`polycubenet.policy.defers`);
* ``now-rf`` and ``defer-far-rf``: the same, a near miss's B with the refined map before the exact realisation
  (``learned_maps=("registration", "refined", "exact")``; recorded as ``b_rf`` for near misses only: elsewhere
  the refined map is not tried and B is the same; ``--no-rf`` records none and these two replay as the others);
* ``policy``: ``defer-far`` as :func:`polycubenet.policy.run_chain` ran it until session 86 (the last draw's B at
  once, since no draw follows it; then every waiting B in draw order);
* ``closest``: ``policy``, the waiting Bs closest first (their A mesh's distance to the part; an A mesh that is
  not valid last);
* ``capN``: ``closest``, but only the N closest waiting Bs run; ``cap1`` is today's policy
  (:data:`polycubenet.policy.FAR_RESTS`, session 86);
* ``capqN``: ``capN``, the last draw's B queued with the others when its A is far (not at once);
* ``same``: ``policy``, but the waiting Bs stop once two finished Bs gave valid meshes equally far off the part
  (within :data:`SAME_OFF`, relative): a misfit every structure shares is the part's (a wall thinner than the
  hexes), not the draw's (session 86);
* ``now-same``: ``now``, but a draw's B is left once two finished Bs gave valid meshes equally far off the part.
  These orders can mesh fewer parts than the others.

It stops recording a part at the first A that ends the chain (no order goes further); B units are recorded for
every draw before it.  Prints one row per part and a total per order and set; writes the JSON.  ``--sets``:
``examples`` (``examples/parts/*.step``), a folder of STEP files and never-seen ``family:seed`` sets of ``unseen_parts.py``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import sys
import tempfile
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

ORDERS = ("now", "defer", "defer-far", "now-rf", "defer-far-rf", "policy", "closest", "cap0", "cap1", "cap2", "same", "now-same", "capq1", "capq2")


def record_part(path: Path, checkpoint: str, steps: int, rf: bool = True) -> list[dict]:
    """One dict per learned draw of ``path``: ``pre`` seconds (generation to registration and partition), ``extract``
    (None, or why the polycube was rejected), ``a`` / ``b`` seconds, ``a_end`` / ``b_end`` (the unit's mesh ends the
    chain), ``near`` (A's mesh is a near miss), ``a_off`` / ``a_sj`` / ``a_valid`` (A's mesh), ``b_off`` / ``b_sj`` /
    ``b_map`` (B's); ``b`` None where it was not run."""
    from polycubenet.errors import PolycubeError
    from polycubenet.frame import canonicalize
    from polycubenet.inference import ModelSource
    from polycubenet.io import load_part
    from polycubenet.pipeline import (PipelineConfig, _polycube_stages, near_miss, own_diagonal, partition_polycube,
                                      pull_back_learned, register_cloud, source_chain)
    from polycubenet.policy import ends_chain, extraction_config, source_config
    from polycubenet.sampling import poisson_disk

    cfg = PipelineConfig(polycube="learned", target_hexes=3000)
    part = load_part(path)
    Vc, T = canonicalize(part.vertices, part.faces)
    F = part.faces
    sample = poisson_disk(Vc, F, cfg.n_sample, seed=cfg.seed)
    genus = part.meta.get("genus")
    clock = lambda name: contextlib.nullcontext()  # noqa: E731
    out = []
    for label, source in source_chain(ModelSource(checkpoint, steps=steps, device="cpu"), cfg):
        row = {"draw": label, "extract": None, "a": None, "b": None, "a_end": False, "b_end": False, "near": False}
        out.append(row)
        t0 = time.perf_counter()
        try:
            cloud, P, N, A, poly = _polycube_stages(source, sample, Vc, F, genus, extraction_config(label, cfg),
                                                    path.name, clock, types.SimpleNamespace())
        except PolycubeError as exc:
            row["pre"], row["extract"] = round(time.perf_counter() - t0, 2), str(exc)[:200]
            continue
        corr = register_cloud(sample, P, N, cfg)
        c = source_config(label, cfg)
        mesh_pc = partition_polycube(poly, c)
        row["pre"] = round(time.perf_counter() - t0, 2)
        kw = dict(diagonal=own_diagonal(Vc, T), part=path.name, partitioned=mesh_pc,
                  anchored=None if A is None else (P, N, A), part_points=sample.points)
        t0 = time.perf_counter()
        first, _ = pull_back_learned(poly, corr, Vc, F, c, phase="map", **kw)
        row["a"], row["a_end"], row["near"] = round(time.perf_counter() - t0, 2), ends_chain(first.meta, cfg.min_sj), \
            near_miss(first)
        row["a_off"], row["a_valid"], row["a_sj"] = first.meta.get("hausdorff"), bool(first.meta.get("valid")), \
            first.meta.get("sj_min")
        if row["a_end"]:
            break
        t0 = time.perf_counter()
        rest, _ = pull_back_learned(poly, corr, Vc, F, c, phase="rest", prior=first, **kw)
        row["b"], row["b_end"], row["b_map"] = round(time.perf_counter() - t0, 2), ends_chain(rest.meta, cfg.min_sj), \
            rest.meta.get("map")
        row["b_planar"] = (rest.meta.get("realised") or {}).get("planar_patches")  # which labelling realised it
        row["b_sj"], row["b_off"] = rest.meta.get("sj_min"), rest.meta.get("hausdorff")
        if rf and row["near"]:  # the refined map before the realisation (the only steps a near miss adds)
            rf_cfg = dataclasses.replace(c, learned_maps=("registration", "refined", "exact"))
            t0 = time.perf_counter()
            rest, _ = pull_back_learned(poly, corr, Vc, F, rf_cfg, phase="rest", prior=first, **kw)
            row["b_rf"], row["b_rf_end"], row["b_rf_map"] = round(time.perf_counter() - t0, 2), \
                ends_chain(rest.meta, cfg.min_sj), rest.meta.get("map")
            row["b_rf_sj"], row["b_rf_off"] = rest.meta.get("sj_min"), rest.meta.get("hausdorff")
    return out


def _far_key(d: dict) -> tuple:
    """Closest first: a waiting draw's A mesh distance to the part (an A mesh that is not valid or has no measure
    last, in draw order)."""
    off = d.get("a_off")
    return (off is None or not d.get("a_valid", True), float("inf") if off is None else off)


#: ``same``: two finished rests whose meshes are valid and this close off the part (relative) end the waiting rests
SAME_OFF = 0.02


def _same_off(done: list[dict]) -> bool:
    """Whether two of the finished rests ``done`` gave valid meshes equally far off the part (within
    :data:`SAME_OFF`, relative): the ``same`` order's stop."""
    offs = sorted(d["b_off"] for d in done if d.get("b_off") is not None and (d.get("b_sj") or -1.0) > 0)
    return any(b - a <= SAME_OFF * b for a, b in zip(offs, offs[1:]))


def replay(draws: list[dict], order: str) -> tuple[float, str | None]:
    """Seconds the learned source costs under ``order`` and the unit that ended the chain (None: none did)."""
    spent = 0.0
    later: list[dict] = []
    rf = order.endswith("-rf")  # a near miss's rest with the refined map before the realisation
    order = order.removesuffix("-rf")
    policy = order in ("policy", "closest", "same") or (order.startswith("cap") and not order.startswith("capq"))
    done: list[dict] = []  # the finished rests
    for i, d in enumerate(draws):
        spent += d["pre"]
        if d["a"] is None:
            continue
        spent += d["a"]
        if d["a_end"]:
            return spent, f"A {d['draw']}"
        last = i == len(draws) - 1  # a part none of whose As ends the chain: every draw of the chain is recorded
        if order == "now-same" and _same_off(done):
            continue  # this draw's B left: two finished ones ended equally far off
        if order in ("now", "now-same") or (order == "defer-far" and d["near"]) or (policy and (d["near"] or last)):
            with_rf = rf and d["near"] and "b_rf" in d
            b, end = (d["b_rf"], d["b_rf_end"]) if with_rf else (d["b"], d["b_end"])
            spent += b
            done.append(d)
            if end:
                return spent, f"B{'rf' if with_rf else ''} {d['draw']}"
        else:
            later.append(d)
    if order == "closest" or order.startswith("cap"):
        later = sorted(later, key=_far_key)
    if order.startswith("cap"):
        later = later[:int(order.lstrip("capq"))]
    for d in later:
        if order == "same" and _same_off(done):
            break
        spent += d["b"]
        done.append(d)
        if d["b_end"]:
            return spent, f"B {d['draw']}"
    return spent, None


def replay_files(files: list[str]) -> int:
    """Every order replayed on the recorded draws of ``files`` (this script's JSON): per file and in all, the
    learned source's seconds and the parts meshed under each order, the seconds as a ratio to ``policy``'s."""
    import json

    total = {o: [0.0, 0] for o in ORDERS}
    print(f"{'records':<44} " + " ".join(f"{o:>12}" for o in ORDERS) + "   (seconds / parts meshed)")
    for f in files:
        res = {o: [0.0, 0] for o in ORDERS}
        for spec in json.load(open(f))["sets"].values():
            for row in spec["parts"]:
                for o in ORDERS:
                    sec, end = replay(row["draws"], o)
                    res[o][0] += sec
                    res[o][1] += end is not None
        for o in ORDERS:
            total[o][0] += res[o][0]
            total[o][1] += res[o][1]
        print(f"{Path(f).name[:44]:<44} " + " ".join(f"{res[o][0]:>7.0f}/{res[o][1]:<4d}" for o in ORDERS))
    base = total["policy"][0] or 1.0
    print(f"{'all':<44} " + " ".join(f"{total[o][0]:>7.0f}/{total[o][1]:<4d}" for o in ORDERS))
    print(f"{'seconds / policy':<44} " + " ".join(f"{total[o][0] / base:>12.2f}" for o in ORDERS))
    return 0


def main(argv=None) -> int:
    from unseen_parts import set_paths

    from polycubenet.atomic import write_json
    from polycubenet.inference import DEFAULT_CHECKPOINT, resolve_steps

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    ap.add_argument("--sets", nargs="+", default=["examples"])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--rf", action=argparse.BooleanOptionalAction, default=True,
                    help="also record a near miss's rest with the refined map first (the -rf orders); --no-rf: not")
    ap.add_argument("--only", nargs="+", default=None, help="only these parts of the sets (names without .step)")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/learned_order.json"))
    ap.add_argument("--replay", nargs="+", default=None, metavar="JSON",
                    help="replay every order on the records of earlier runs (no meshing) and print the totals")
    args = ap.parse_args(argv)
    if args.replay:
        return replay_files(args.replay)
    import torch

    torch.set_num_threads(1)
    steps = int(resolve_steps(None, "cpu", args.checkpoint)[1])
    tmp = Path(tempfile.mkdtemp(prefix="learned-order-"))
    result = {"checkpoint": args.checkpoint, "steps": steps, "orders": ORDERS, "sets": {}}
    for spec in args.sets:
        paths = [p for p in set_paths(spec, tmp, args.count) if args.only is None or p.stem in args.only]
        rows = []
        print(f"\n{spec}: {len(paths)} parts\n{'part':<22} {'meshed':>6} " + " ".join(f"{o:>10}" for o in ORDERS)
              + "  ended by (now / defer-far)", flush=True)
        for p in paths:
            draws = record_part(p, args.checkpoint, steps, rf=args.rf)
            sims = {o: replay(draws, o) for o in ORDERS}
            rows.append({"part": p.stem, "draws": draws, **{o: {"seconds": round(s, 1), "ended_by": e}
                                                              for o, (s, e) in sims.items()}})
            print(f"{p.stem:<22} {'yes' if sims['now'][1] else 'no':>6} "
                  + " ".join(f"{sims[o][0]:>10.1f}" for o in ORDERS)
                  + f"  {sims['now'][1]} / {sims['defer-far'][1]}", flush=True)
        totals = {o: round(sum(r[o]["seconds"] for r in rows), 1) for o in ORDERS}
        meshed = sum(r["now"]["ended_by"] is not None for r in rows)
        print(f"{'total':<22} {meshed:>6} " + " ".join(f"{totals[o]:>10.1f}" for o in ORDERS), flush=True)
        result["sets"][spec] = {"parts": rows, "meshed": meshed, "seconds": totals}
        write_json(args.json, result)
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
