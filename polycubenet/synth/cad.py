"""Training pairs from machined-style CAD parts and their classical polycubes.

The synthetic pairs of :mod:`polycubenet.synth.pairs` deform a random polycube into a shape, so their
shapes are bent, swollen polycubes; machined parts are something else (flat faces, round holes and
bosses, slots, slanted cuts), and a model trained on the first does not carry the second as often
(session 20: held-out pairs 58.6 → 62 % exact while never-seen CAD parts stayed where they were).
The paper trains on CAD models (ABC) paired with polycubes built by classical methods and kept where
their map is foldover-free.  This module does the same at our scale:

1. :func:`build_cad_part` draws a machined-style solid with gmsh's OpenCASCADE kernel (a base block or
   an L / T of two blocks; bosses, round posts and ribs fused on; through and blind holes along any
   axis, pockets, slots, notches and slanted cuts taken off; sometimes turned about a random axis);
2. the part is read back as the pipeline reads a CAD file (:func:`polycubenet.io.load_part`) and put
   in its canonical frame;
3. :func:`polycubenet.classical.classical_polycube` flattens it; the pair is kept only when the
   flattening needed no turn (its polycube is axis-aligned in the frame the model sees), flipped at
   most 0.2 % of its triangles, bounds a valid polycube of the part's genus, and the extraction recovers that
   polycube from a dense sample of it;
4. the condition is a Poisson sample of the part, the target a Poisson sample of the flattened surface,
   and each target point's place on the part is the same barycentric point of the same triangle.

Records have the fields of :func:`polycubenet.synth.shards.pair_record` (no deformation: ``meta`` says
``style == "cad-classical"``), so shards of these pairs train and evaluate like the synthetic ones.

    python -m polycubenet.synth.cad --out DIR --count 512 --seed 100 [--workers 1]

The part generator is not the one of ``benchmarks/unseen_parts.py`` (the never-seen sets): it has its
own shapes and ranges, and that script's sets are never trained on.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ..classical import DIRECTIONS, ClassicalConfig, classical_polycube
from ..errors import PartError, PolycubeError
from ..frame import canonicalize
from ..sampling import interpolate, poisson_disk

STYLE = "cad-classical"


def _fuse(occ, solid, tool):
    out, _ = occ.fuse(solid, [(3, tool)])
    return out


def build_cad_part(occ, rng: np.random.Generator) -> list[str]:
    """One random machined-style solid in the current gmsh model (mm); returns what it is made of."""
    L, W, H = rng.uniform(30, 100), rng.uniform(20, 70), rng.uniform(8, 40)
    what = [f"block {L:.0f}x{W:.0f}x{H:.0f}"]
    solid = [(3, occ.addBox(0, 0, 0, L, W, H))]
    shape = rng.random()
    if shape < 0.2:  # an L: a second block standing on one end
        l2, h2 = rng.uniform(0.2, 0.5) * L, rng.uniform(0.6, 1.5) * H
        solid = _fuse(occ, solid, occ.addBox(0, 0, H - 1e-3, l2, W, h2))
        what.append("L")
    elif shape < 0.35:  # a T: a flange wider than the base
        w2 = rng.uniform(1.2, 1.6) * W
        h2 = rng.uniform(0.2, 0.5) * H
        solid = _fuse(occ, solid, occ.addBox(0, -(w2 - W) / 2, -h2 + 1e-3, L, w2, h2))
        what.append("flange")
    for _ in range(rng.integers(0, 4)):  # fused on the top face
        kind = rng.choice(["boss", "post", "rib"], p=[0.4, 0.35, 0.25])
        h = rng.uniform(0.15, 1.0) * H
        if kind == "post":
            r = rng.uniform(0.08, 0.25) * min(L, W)
            x, y = rng.uniform(r, L - r), rng.uniform(r, W - r)
            tool = occ.addCylinder(x, y, H - 1e-3, 0, 0, h, r)
        elif kind == "rib":
            t = rng.uniform(0.05, 0.12) * min(L, W)
            if rng.random() < 0.5:
                tool = occ.addBox(0, rng.uniform(0, W - t), H - 1e-3, L, t, h)
            else:
                tool = occ.addBox(rng.uniform(0, L - t), 0, H - 1e-3, t, W, h)
        else:
            l, w = rng.uniform(0.15, 0.6) * L, rng.uniform(0.15, 0.9) * W
            tool = occ.addBox(rng.uniform(0, L - l), rng.uniform(0, W - w), H - 1e-3, l, w, h)
        solid = _fuse(occ, solid, tool)
        what.append(str(kind))
    occ.synchronize()
    tools = []
    dims = np.array([L, W, H])
    for _ in range(rng.integers(0, 3)):  # holes along a random axis, through or blind
        ax = int(rng.choice(3, p=[0.2, 0.2, 0.6]))
        u, v = [a for a in range(3) if a != ax]
        r = rng.uniform(0.05, 0.15) * min(dims[u], dims[v])
        c = np.zeros(3)
        c[u], c[v] = rng.uniform(r + 2, dims[u] - r - 2), rng.uniform(r + 2, dims[v] - r - 2)
        through = rng.random() < 0.7
        depth = 3 * dims[ax] + 10 if through else rng.uniform(0.3, 0.7) * dims[ax]
        c[ax] = -5 if through else dims[ax] - depth
        d = np.zeros(3)
        d[ax] = depth + (0 if through else 5)
        if rng.random() < 0.65:
            tools.append((3, occ.addCylinder(*c, *d, r)))
            what.append("round hole" if through else "blind round hole")
        else:
            lo = c.copy()
            lo[u] -= r
            lo[v] -= r
            size = np.full(3, 2 * r)
            size[ax] = d[ax]
            tools.append((3, occ.addBox(*lo, *size)))
            what.append("square hole" if through else "square recess")
    if rng.random() < 0.35:  # a pocket from the top
        l, w = rng.uniform(0.15, 0.45) * L, rng.uniform(0.15, 0.5) * W
        tools.append((3, occ.addBox(rng.uniform(2, L - l - 2), rng.uniform(2, W - w - 2),
                                    rng.uniform(0.3, 0.8) * H, l, w, 3 * H)))
        what.append("pocket")
    if rng.random() < 0.25:  # a slot across, along x or y
        if rng.random() < 0.5:
            w = rng.uniform(0.08, 0.25) * W
            tools.append((3, occ.addBox(-5, rng.uniform(2, W - w - 2), rng.uniform(0.4, 0.85) * H, L + 10, w, 3 * H)))
        else:
            w = rng.uniform(0.08, 0.25) * L
            tools.append((3, occ.addBox(rng.uniform(2, L - w - 2), -5, rng.uniform(0.4, 0.85) * H, w, W + 10, 3 * H)))
        what.append("slot")
    if rng.random() < 0.2:  # a notch off a vertical corner edge
        a, b = rng.uniform(0.1, 0.3) * L, rng.uniform(0.1, 0.3) * W
        x = 0 if rng.random() < 0.5 else L - a
        y = 0 if rng.random() < 0.5 else W - b
        tools.append((3, occ.addBox(x - 1e-3 if x == 0 else x, y - 1e-3 if y == 0 else y, -5, a + 1e-3, b + 1e-3, 3 * H + 10)))
        what.append("notch")
    if rng.random() < 0.4:  # a slanted cut across an end (a chamfer when small)
        ang = rng.uniform(15, 50)
        wedge = occ.addBox(-L, -5, -5, L, W + 10, 4 * H)
        occ.rotate([(3, wedge)], 0, 0, H * rng.uniform(0.1, 0.8), 0, 1, 0, -np.radians(ang))
        occ.translate([(3, wedge)], rng.uniform(0.03, 0.25) * L, 0, 0)
        if rng.random() < 0.5:  # the other end
            occ.rotate([(3, wedge)], L / 2, W / 2, 0, 0, 0, 1, np.pi)
        tools.append((3, wedge))
        what.append(f"slanted cut {ang:.0f} deg")
    if tools:
        solid, _ = occ.cut(solid, tools)
    occ.synchronize()
    if rng.random() < 0.5:
        axis = rng.normal(size=3)
        occ.rotate(occ.getEntities(3), 0, 0, 0, *axis, rng.uniform(0, np.pi))
        occ.synchronize()
        what.append("rotated")
    if len(occ.getEntities(3)) != 1:
        raise ValueError(f"{len(occ.getEntities(3))} volumes")
    return what


def cad_pair(seed: int, *, n_cond: int = 2048, n_target: int = 2048, n_check: int = 16384,
             workdir: str | Path | None = None, why: dict | None = None,
             max_flipped: float = 0.002) -> dict | None:
    """One pair record (:func:`~polycubenet.synth.shards.pair_record`'s fields) from ``seed``, or None
    when the part cannot be built or its classical polycube is not kept (module docstring); ``why``
    (a dict) counts the reasons of the pairs not kept."""
    why = {} if why is None else why

    def drop(reason: str) -> None:
        why[reason] = why.get(reason, 0) + 1

    from ..cleanup import remove_outliers
    from ..io import gmsh_session, load_part, quiet_stdout
    from ..polycube import surface_genus
    from ..structure import ExtractConfig, extract

    rng = np.random.default_rng([seed, 7919])
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        path = Path(tmp) / f"cad_{seed}.step"
        with gmsh_session() as gmsh:
            gmsh.model.add(path.stem)
            try:
                what = build_cad_part(gmsh.model.occ, rng)
                with quiet_stdout():
                    gmsh.write(str(path))
            except Exception:  # noqa: BLE001 - a draw OCC refuses (or that falls apart): no pair
                return drop("build")
            finally:
                gmsh.model.remove()
        try:
            part = load_part(path)
        except PartError:
            return drop("load")
    Vc, _ = canonicalize(part.vertices, part.faces)
    F = np.asarray(part.faces, np.int64)
    try:
        genus = surface_genus(F)
        # one orientation: a turned flattening is not kept (its polycube is not axis-aligned in this frame)
        Vp, Vs, Fs, labels, info = classical_polycube(Vc, F, ClassicalConfig(orientations=1), seed=0)
    except PolycubeError:
        return drop("classical")
    if info.get("orientation", 0) != 0:
        return drop("turned")
    if info.get("flipped", 0) > max_flipped * len(Fs):
        return drop("flipped")
    if info.get("structure_reason") is not None or info.get("structure_genus") != genus:
        return drop("structure")
    dense = poisson_disk(Vp, Fs, n_check, seed=seed % (2**31))
    P, N, _ = remove_outliers(dense.points, DIRECTIONS[labels[dense.face_ids]])
    try:
        poly = extract(P, N, genus=genus, config=ExtractConfig().for_exact_clouds())
    except PolycubeError:
        return drop("extraction")
    cond = poisson_disk(Vc, F, n_cond, seed=(seed + 1) % (2**31))
    target = poisson_disk(Vp, Fs, n_target, seed=(seed + 2) % (2**31))
    on_shape = interpolate(Vs, Fs, target.face_ids, target.barycentrics)
    arrays = {
        "index": np.int64(0),
        "seeds": np.int64(seed),
        "genus": np.int32(genus),
        "cond_points": cond.points.astype(np.float32),
        "cond_normals": cond.normals.astype(np.float32),
        "target_points": target.points.astype(np.float32),
        "target_normals": DIRECTIONS[labels[target.face_ids]].astype(np.float32),
        "target_on_shape": on_shape.astype(np.float32),
        "grid_sizes": np.asarray(poly.occupancy.shape, dtype=np.int32),
        "grid_coords": np.concatenate([poly.xs, poly.ys, poly.zs]).astype(np.float64),
        "occupancy": np.ascontiguousarray(poly.occupancy, dtype=bool).ravel(),
    }
    meta = {"index": 0, "seed": int(seed), "genus": int(genus), "style": STYLE, "features": what,
            "deformation": None, "shape_transform": None, "polycube_transform": None, "map_kinds": ["classical"],
            "attempts": len(info.get("attempts", [])), "flipped": int(info.get("flipped", 0)), "min_jacobian": None, "snap_deg": None,
            "seconds": round(time.perf_counter() - t0, 2)}
    return {"arrays": arrays, "meta": meta}


def write_cad_shards(out: str | Path, count: int, seed: int, *, per_shard: int = 64, n_cond: int = 2048,
                     n_target: int = 2048, progress: bool = True) -> list[Path]:
    """``count`` kept pairs from part seeds ``seed * 1_000_000 + k`` (k = 0, 1, ...) into shards of
    ``per_shard`` under ``out`` (resumable: a finished shard is kept and its seeds skipped)."""
    from .shards import ShardParams, write_shard

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    params = ShardParams(n_cond=n_cond, n_target=n_target, sampler="poisson")
    written = sorted(out.glob("shard-*.npz"))
    state = out / "progress.json"
    k = json.loads(state.read_text())["next_k"] if state.exists() and written else 0
    done = len(written) * per_shard
    records: list[dict] = []
    tried = kept = 0
    dropped: dict = {}
    t0 = time.perf_counter()
    while done + len(records) < count:
        s = seed * 1_000_000 + k
        k += 1
        tried += 1
        rec = cad_pair(s, n_cond=n_cond, n_target=n_target, why=dropped)
        if rec is None:
            continue
        kept += 1
        rec["arrays"]["index"] = np.int64(done + len(records))
        rec["meta"]["index"] = done + len(records)
        records.append(rec)
        if len(records) == per_shard or done + len(records) == count:
            path = write_shard(out / f"shard-{len(written):05d}.npz", records, params, dataset_seed=seed)
            written.append(path)
            done += len(records)
            records = []
            state.write_text(json.dumps({"next_k": k, "dropped_this_run": dropped}))
        if progress:
            el = time.perf_counter() - t0
            print(f"[cad] {done + len(records)}/{count} pairs kept of {tried} parts tried, {el:.0f} s "
                  f"({el / max(kept, 1):.1f} s a kept pair; dropped: {dropped or 'none'})", flush=True)
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polycubenet.synth.cad", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="shard folder")
    ap.add_argument("--count", type=int, default=512, help="pairs kept")
    ap.add_argument("--seed", type=int, default=100, help="the dataset's seed (part seeds seed*1e6 + k)")
    ap.add_argument("--per-shard", type=int, default=64)
    ap.add_argument("--n-cond", type=int, default=2048)
    ap.add_argument("--n-target", type=int, default=2048)
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    paths = write_cad_shards(args.out, args.count, args.seed, per_shard=args.per_shard, n_cond=args.n_cond,
                             n_target=args.n_target, progress=not args.no_progress)
    print(f"{len(paths)} shard(s) under {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
