"""Held-out evaluation of a checkpoint, and publishing it.

    python -m polycubenet.evaluate --checkpoint RUN/last.pt --data HELDOUT --count 500 \\
        --n-out 8192 --steps 64 --json benchmarks/results/model_eval.json [--publish OUT.pt]

For every held-out pair (seeds never trained on): generate the polycube cloud from the
shape's samples and measure

* Chamfer distance to the ground-truth polycube samples (mean of the two directed mean
  nearest-neighbour distances; the canonical frame has diagonal 1, so it reads as a
  fraction of the diagonal), beside the trivial reference of the part's own samples taken
  as the polycube cloud (``chamfer_identity``: a model must beat it to have learned anything);
* structure: the outlier filter and :func:`polycubenet.structure.extract` on the
  generated cloud, compared with the ground-truth grid and occupancy (exact match of
  the minimal grid topology and occupancy, planes within a tolerance) and its genus
  against the pair's genus (given to the extraction, as the pipeline gives the part's).

With ``--publish`` the checkpoint is stripped to the shipped form (EMA weights in
float16) with these metrics inside.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from . import tol
from .atomic import write_json
from .cleanup import remove_outliers
from .errors import PolycubeError
from .inference import generate, load_model
from .polycube import compress, plane_offset, same_structure
from .structure import ExtractConfig, extract
from .synth.shards import list_shards, load_shard


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance: ``(mean_a d(a, B) + mean_b d(b, A)) / 2``."""
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return float(0.5 * (da.mean() + db.mean()))


#: refusal categories of a polycube cloud, in the order they are tested (first match wins)
REJECTION_CATEGORIES = (
    ("genus differs", ("genus",)),
    ("edge/vertex-only contacts", ("edge-only", "vertex-only", "edge only", "vertex only")),
    ("enclosed cavity", ("cavit",)),
    ("several solid components", ("component",)),
    ("too few planes on an axis", ("plane(s) normal",)),
    ("cloud far from its polycube", ("far from",)),
    ("surface not covered", ("covers only",)),
    ("too few points", ("too few points",)),
    ("no occupied cell", ("empty occ",)),
)


def label_accuracy(cloud: np.ndarray, anchors: np.ndarray, on_shape: np.ndarray, truth_normals: np.ndarray) -> float:
    """Fraction of generated points whose normal has the ground truth's dominant axis and sign, the truth
    being the target normal of the target point whose part point is nearest the generated point's anchor
    (an anchored model's output point ``i`` is anchor ``i`` moved onto the polycube)."""
    from scipy.spatial import cKDTree

    from .structure import axis_labels

    _, j = cKDTree(np.asarray(on_shape, float)).query(np.asarray(anchors, float))
    ga, gs = axis_labels(np.asarray(cloud[:, 3:6], float), 90.0)
    ta, ts = axis_labels(np.asarray(truth_normals, float)[j], 90.0)
    return float(np.mean((ga == ta) & (gs == ts)))


def rejection_category(message: str) -> str:
    """The category of a :class:`~polycubenet.errors.PolycubeError` message (``"other"`` when none fits)."""
    m = message.lower()
    for name, keys in REJECTION_CATEGORIES:
        if any(k in m for k in keys):
            return name
    return "other"


def row_category(row: dict) -> str:
    """One held-out row's outcome: ``exact``, ``right genus, other structure``, or why it failed."""
    if row.get("error"):
        return rejection_category(row["error"])
    if not row.get("genus_match"):
        return "genus differs"
    return "exact" if row.get("exact") else "right genus, other structure"


#: bin edges of the ground truth's thinnest slab (fraction of the diagonal) for :func:`by_thinnest_slab`; the
#: generator's floor is 0.025, and 512 training points lie ~0.05 apart on a part of diagonal 1
SLAB_BINS = (0.03, 0.05)


def thinnest_slab(poly) -> float:
    """The thinnest slab of ``poly``'s minimal grid (:func:`polycubenet.polycube.compress`), in the
    canonical frame's units (a fraction of the diagonal)."""
    grid, _ = compress([poly.xs, poly.ys, poly.zs], poly.occupancy)
    return float(min(np.diff(g).min() for g in grid))


def by_thinnest_slab(rows: list[dict], bins: tuple[float, ...] = SLAB_BINS) -> dict:
    """Exact structure per bin of the ground truth's thinnest slab (``row["gt_thinnest_slab"]``):
    ``{"< 0.03": {"pairs": n, "exact": rate}, "0.03-0.05": ..., ">= 0.05": ...}`` (``exact`` None for an
    empty bin).  Says whether a model's misses are the fine features (a slab under the training
    points' spacing) or the coarse ones."""
    edges = (-np.inf, *bins, np.inf)
    out = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        name = f"< {hi:g}" if lo == -np.inf else f">= {lo:g}" if hi == np.inf else f"{lo:g}-{hi:g}"
        sel = [r for r in rows if lo <= r["gt_thinnest_slab"] < hi]
        out[name] = {"pairs": len(sel), "exact": float(np.mean([r["exact"] for r in sel])) if sel else None}
    return out


def by_feature(rows: list[dict]) -> dict:
    """Pairs, exact structure and extraction accepted per machined feature class (the rows' ``feature``,
    :func:`polycubenet.synth.shards.feature_class`), classes with no pair left out."""
    from .synth.shards import FEATURE_CLASSES

    out = {}
    for name in FEATURE_CLASSES:
        sel = [r for r in rows if r.get("feature") == name]
        if sel:
            out[name] = _exact_extracted(sel)
    return out


def _exact_extracted(sel: list[dict]) -> dict:
    """Pairs, exact structure and extraction accepted over the rows ``sel`` (one class of a split)."""
    return {"pairs": len(sel), "exact": float(np.mean([r["exact"] for r in sel])),
            "extracted": float(np.mean([r["error"] is None for r in sel]))}


def by_ribs(rows: list[dict]) -> dict:
    """Pairs, exact structure and extraction accepted by how many gussets a pair carries (the rows' ``ribs``,
    :meth:`polycubenet.synth.shards.Shard.ribs`; keys the count as a string, ascending, rows without one left out):
    whether a model follows a rib cut to a triangle or drops it."""
    out = {}
    for n in sorted({int(r["ribs"]) for r in rows if r.get("ribs") is not None}):
        out[str(n)] = _exact_extracted([r for r in rows if r.get("ribs") == n])
    return out


def by_genus(rows: list[dict]) -> dict:
    """Pairs, exact structure, genus matched and extraction accepted per ground-truth genus (keys are the
    genus as a string, ascending): where a model's misses sit, e.g. a bolted flange's many holes."""
    out = {}
    for g in sorted({int(r["genus"]) for r in rows}):
        sel = [r for r in rows if int(r["genus"]) == g]
        out[str(g)] = {"pairs": len(sel), "exact": float(np.mean([r["exact"] for r in sel])),
                       "genus_match": float(np.mean([r["genus_match"] for r in sel])),
                       "extracted": float(np.mean([r["error"] is None for r in sel]))}
    return out


def _pairs(directory: str | Path, count: int):
    n = 0
    for path in list_shards(directory):
        s = load_shard(path)
        for k in range(len(s)):
            if n >= count:
                return
            yield s, k
            n += 1


def _structure(P: np.ndarray, N: np.ndarray, gt, genus: int, part: str, config: ExtractConfig = ExtractConfig()) -> dict:
    """Outlier filter + extraction of a cloud, compared with the ground-truth polycube ``gt``."""
    try:
        P, N, _ = remove_outliers(P, N)
        # the pair's genus is given, as the pipeline gives the part's: a polycube of another genus is
        # rejected (and the extraction retries without its plane filter, see ExtractConfig)
        poly = extract(P, N, genus=genus, part=part, config=config)
    except PolycubeError as exc:
        return {"genus_got": None, "genus_match": False, "exact": False, "plane_offset": None, "planes_added": None,
                "planes_missed": None, "error": str(exc)}
    got = int(poly.meta["genus"])
    added, missed = plane_errors(poly, gt)
    # plane_offset: the same cells with planes further than 0.02 away, or (None) other cells
    return {"genus_got": got, "genus_match": got == genus, "exact": got == genus and same_structure(poly, gt, atol=0.02),
            "plane_offset": plane_offset(poly, gt), "planes_added": added, "planes_missed": missed, "error": None}


def plane_errors(poly, gt, tol: float = 0.02) -> tuple[int, int]:
    """``(added, missed)``: planes of ``poly``'s minimal grid with no plane of ``gt``'s (same axis)
    within ``tol``, and planes of ``gt``'s with none of ``poly``'s (the tolerance of the exact match)."""
    a, _ = compress([poly.xs, poly.ys, poly.zs], poly.occupancy)
    b, _ = compress([gt.xs, gt.ys, gt.zs], gt.occupancy)

    def unmatched(p, q):
        return int((np.abs(p[:, None] - q[None, :]).min(axis=1) > tol).sum())

    return sum(unmatched(a[i], b[i]) for i in range(3)), sum(unmatched(b[i], a[i]) for i in range(3))


def evaluate(checkpoint, data: str | Path, count: int = 100, *, n_out: int = 8192, n_in: int | None = None,
             steps: int | None = 64, seed: int = 0, structure: bool = True, batch: int = 8, device: str | None = None,
             progress: bool = True, keep_clouds: int = 0, identity: bool = False, recycles: int | None = None,
             generator=None, extract_config: ExtractConfig = ExtractConfig()) -> dict:
    """Metrics of ``checkpoint`` on the first ``count`` pairs of the held-out shards ``data``.

    ``keep_clouds`` > 0 also returns ``clouds``: (condition, generated cloud, ground-truth
    points + normals) of the first that many pairs, for pictures.  ``generator``: a stand-in for
    :func:`~polycubenet.inference.generate` with its signature (default: it), e.g. a mean of several draws.
    ``extract_config``: the structure extraction's (default: the pipeline's)."""
    gen = generate if generator is None else generator
    loaded = load_model(checkpoint, device)
    items = list(_pairs(data, count))
    if not items:
        raise FileNotFoundError(f"no held-out pairs in {data}")
    rows = []
    kept: list = []
    t0 = time.perf_counter()
    for b in range(0, len(items), batch):
        chunk = items[b : b + batch]
        conds = []
        for s, k in chunk:
            c = s["cond_points"][k]
            if n_in is not None and n_in < len(c):
                c = c[np.random.default_rng(k).choice(len(c), n_in, replace=False)]
            conds.append(c)
        tg = time.perf_counter()
        anchors = None
        cfg = loaded.model.config
        n_gen = n_out
        if cfg.anchored:
            # the shard has no mesh: the anchors are the part's condition points (with their normals), each
            # at most once -- a repeated anchor gives near-duplicate output points, which the extraction
            # reads as a denser cloud than there is
            anchors = []
            n_gen = min(n_out, min(len(s["cond_points"][k]) for s, k in chunk))
            for (s, k), c in zip(chunk, conds):
                cp = np.asarray(s["cond_points"][k], np.float32)
                if cfg.anchor_normals:
                    cp = np.hstack([cp, np.asarray(s["cond_normals"][k], np.float32)])
                anchors.append(cp[np.random.default_rng(k).permutation(len(cp))[:n_gen]])
        # a model told the genus gets the pair's, as the pipeline gives it the part's
        told = {"genus": [int(s["genus"][k]) for s, k in chunk]} if cfg.genus_classes else {}
        clouds = gen(conds, n_gen, model=loaded, steps=steps, seed=seed + b, device=device, anchors=anchors,
                     recycles=recycles, **told)
        t_gen = (time.perf_counter() - tg) / len(chunk)
        for i, ((s, k), cloud, c) in enumerate(zip(chunk, clouds, conds)):
            truth = np.asarray(s["target_points"][k], float)
            if len(rows) < keep_clouds:
                kept.append((c, cloud, np.hstack([truth, np.asarray(s["target_normals"][k], float)])))
            row = {"seed": int(s["seeds"][k]), "genus": int(s["genus"][k]), "feature": s.feature(k),
                   "ribs": s.ribs(k),
                   "chamfer": chamfer(cloud[:, :3].astype(float), truth), "gen_seconds": round(t_gen, 3),
                   # the trivial reference: the part's own samples taken as the polycube cloud
                   "chamfer_identity": chamfer(np.asarray(c, float), truth)}
            # the trivial reference for labels: the part's own normal at each point, snapped to its axis
            cp_all = np.asarray(s["cond_points"][k], float)
            row["label_accuracy_part_normals"] = label_accuracy(np.hstack([cp_all, np.asarray(s["cond_normals"][k], float)]),
                                                                cp_all, s["target_on_shape"][k], s["target_normals"][k])
            if anchors is not None:
                row["label_accuracy"] = label_accuracy(cloud, anchors[i][:, :3], s["target_on_shape"][k],
                                                       s["target_normals"][k])
            if structure:
                gt = s.polycube(k)
                row["gt_thinnest_slab"] = thinnest_slab(gt)
                row.update(_structure(cloud[:, :3].astype(float), cloud[:, 3:].astype(float), gt, row["genus"],
                                      f"pair {row['seed']}", extract_config))
                if identity:  # the trivial reference: the part's own samples and normals as the cloud (no model)
                    ref = _structure(cp_all, np.asarray(s["cond_normals"][k], float), gt, row["genus"], "identity")
                    row.update(exact_identity=ref["exact"], plane_offset_identity=ref["plane_offset"])
            rows.append(row)
        if progress:
            done = len(rows)
            el = time.perf_counter() - t0
            print(f"[evaluate] {done}/{len(items)} pairs, {el:.0f} s, ETA {el / done * (len(items) - done):.0f} s, "
                  f"median Chamfer so far {np.median([r['chamfer'] for r in rows]):.4f}", flush=True)
    ch = np.array([r["chamfer"] for r in rows])
    out = {
        "checkpoint": str(loaded.path) if loaded.path else None,
        "step": loaded.meta.get("step"),
        "pairs": len(rows),
        "data": str(data),
        "n_out": n_out,
        "n_in": n_in,
        "steps": steps,
        "recycles": recycles,
        "chamfer_mean": float(ch.mean()),
        "chamfer_median": float(np.median(ch)),
        "chamfer_p90": float(np.quantile(ch, 0.9)),
        "chamfer_identity_median": float(np.median([r["chamfer_identity"] for r in rows])),
        "n_generated": int(len(clouds[0])),
        "gen_seconds_per_pair": float(np.mean([r["gen_seconds"] for r in rows])),
    }
    if structure:
        out["exact_structure_rate"] = float(np.mean([r["exact"] for r in rows]))
        out["genus_match_rate"] = float(np.mean([r["genus_match"] for r in rows]))
        out["extract_failed_rate"] = float(np.mean([r["error"] is not None for r in rows]))
        low = [r for r in rows if r["genus"] <= 2]
        if low:  # the targets are stated for parts of genus <= 2
            out["genus_le2_pairs"] = len(low)
            out["exact_structure_rate_genus_le2"] = float(np.mean([r["exact"] for r in low]))
            out["genus_match_rate_genus_le2"] = float(np.mean([r["genus_match"] for r in low]))
        offs = [r.get("plane_offset") for r in rows]
        out["same_cells_rate"] = float(np.mean([o is not None for o in offs]))
        out["plane_offset_median"] = (float(np.median([o for o in offs if o is not None]))
                                      if any(o is not None for o in offs) else None)
        if identity:
            out["exact_structure_rate_identity"] = float(np.mean([r["exact_identity"] for r in rows]))
            out["same_cells_rate_identity"] = float(np.mean([r["plane_offset_identity"] is not None for r in rows]))
        out["exact_by_thinnest_slab"] = by_thinnest_slab(rows)
        out["by_genus"] = by_genus(rows)
        if any(r.get("feature") for r in rows):
            out["exact_by_feature"] = by_feature(rows)
        if any(r.get("ribs") for r in rows):
            out["exact_by_ribs"] = by_ribs(rows)
        # over the extracted clouds: planes with no ground-truth plane within 0.02, and the reverse
        out["planes_added"] = int(sum(r["planes_added"] for r in rows if r["planes_added"] is not None))
        out["planes_missed"] = int(sum(r["planes_missed"] for r in rows if r["planes_missed"] is not None))
        cats: dict = {}
        for r in rows:
            r["category"] = c = row_category(r)
            cats[c] = cats.get(c, 0) + 1
        out["categories"] = cats
    out["label_accuracy_part_normals_median"] = float(np.median([r["label_accuracy_part_normals"] for r in rows]))
    if rows and "label_accuracy" in rows[0]:
        out["label_accuracy_median"] = float(np.median([r["label_accuracy"] for r in rows]))
    out["rows"] = rows
    if keep_clouds:
        out["clouds"] = kept
    return out


#: a part point stands on a flat face when its normal is less than FLAT_DEG from an axis (on a slanted one: more
#: than :data:`polycubenet.tol.SLANT_DEG` from every axis); a slanted point counts when its target lies at least
#: MIN_MOVE (of the canonical frame's diagonal) across its plane from it
FLAT_DEG, MIN_MOVE = 5.0, 0.01
#: the bins of ``point_moves``'s ``moved_by_share`` (a slanted point's displacement over the pair's largest)
SHARE_BINS = ("0-0.2", "0.2-0.4", "0.4-0.6", "0.6-0.8", "0.8-1")


def point_moves(anchors: np.ndarray, normals: np.ndarray, cloud: np.ndarray, targets: np.ndarray,
                target_normals: np.ndarray) -> dict:
    """How far a generated cloud takes each part point across its target's plane, where the target of output
    point ``i`` is known (``anchors[i]``, the part point it was made from, is ``targets[i]``'s preimage).

    Across the target's plane (the axis of its normal): ``moved`` is the share of the way from the part point to
    that plane the output point went (1: onto it, 0: left where it was, 0.75: a ramp a quarter as steep), its
    median over the slanted points (the part's normal > :data:`polycubenet.tol.SLANT_DEG` from every axis, target at least
    :data:`MIN_MOVE` away); ``err_slanted`` and ``err_flat`` the median distances left to the plane on slanted
    and on flat points (normal < :data:`FLAT_DEG` from an axis); ``moved_by_share`` the median ``moved`` per bin
    of the displacement's share of the pair's largest (:data:`SHARE_BINS`).  None where fewer than 5 points."""
    idx = np.arange(len(targets))
    ax = np.abs(target_normals).argmax(axis=1)
    disp = (targets - anchors)[idx, ax]
    err = (cloud[:, :3] - targets)[idx, ax]
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True).clip(1e-12)
    tilt = np.degrees(np.arccos(np.clip(np.abs(n).max(axis=1), 0.0, 1.0)))
    slanted = (tilt > tol.SLANT_DEG) & (np.abs(disp) >= MIN_MOVE)
    flat = tilt < FLAT_DEG

    def med(x, m):
        return float(np.median(x[m])) if m.sum() >= 5 else None

    moved = 1.0 + err / np.where(slanted, disp, 1.0)
    # along the face: the slanted points binned by their displacement as a share of the pair's largest (a whole
    # slanted end: 0 at the pivot, where the flat rest of the end turns into the slant, 1 at its far edge)
    share = np.abs(disp) / max(float(np.abs(disp[slanted]).max()), 1e-12) if slanted.any() else np.zeros(len(disp))
    bin_of = np.minimum((share * len(SHARE_BINS)).astype(int), len(SHARE_BINS) - 1)  # share 1 in the last bin
    by_share = [med(moved, slanted & (bin_of == i)) for i in range(len(SHARE_BINS))]
    return {"slanted_points": int(slanted.sum()), "moved": med(moved, slanted), "moved_by_share": by_share,
            "err_slanted": med(np.abs(err), slanted), "err_flat": med(np.abs(err), flat)}


def slant_moves(checkpoint, data: str | Path, count: int = 256, *, seed: int = 0, batch: int = 8,
                device: str | None = None, generator=None, progress: bool = True, steps: int = 1) -> dict:
    """:func:`point_moves` of ``checkpoint``'s ``steps``-step clouds (one by default: the policy's first draw) on
    the first ``count`` held-out pairs, summarised per machined feature class (:func:`polycubenet.synth.shards.feature_class`).

    Unlike :func:`evaluate` the anchors are the training's: each target point's preimage on the part with the
    normal of the nearest condition point, so every output point has a known target and the error of a slanted
    face can be read as a share of the way (a cloud that stops short of the plane leaves a ramp, which the
    extraction reads as a staircase).  ``generator``: a
    stand-in for :func:`~polycubenet.inference.generate` (then ``checkpoint`` may be None)."""
    from .synth.shards import FEATURE_CLASSES

    gen = generate if generator is None else generator
    loaded = load_model(checkpoint, device) if generator is None or checkpoint is not None else None
    items = list(_pairs(data, count))
    if not items:
        raise FileNotFoundError(f"no held-out pairs in {data}")
    rows = []
    for b in range(0, len(items), batch):
        chunk = items[b : b + batch]
        conds, anchors, truths = [], [], []
        for s, k in chunk:
            cp = np.asarray(s["cond_points"][k], np.float32)
            pre = np.asarray(s["target_on_shape"][k], np.float32)
            _, j = cKDTree(cp).query(pre)
            conds.append(cp)
            anchors.append(np.hstack([pre, np.asarray(s["cond_normals"][k], np.float32)[j]]))
            truths.append((np.asarray(s["target_points"][k], float), np.asarray(s["target_normals"][k], float)))
        clouds = gen(conds, [len(a) for a in anchors], model=loaded, steps=steps, seed=seed + b, device=device,
                     anchors=anchors)
        for (s, k), a, (tp, tn), cloud in zip(chunk, anchors, truths, clouds):
            rows.append({"seed": int(s["seeds"][k]), "feature": s.feature(k),
                         **point_moves(a[:, :3].astype(float), a[:, 3:].astype(float), np.asarray(cloud, float), tp, tn)})
        if progress:
            print(f"[slant_moves] {len(rows)}/{len(items)} pairs", flush=True)

    def summary(sel):
        mv = [r["moved"] for r in sel if r["moved"] is not None]
        es = [r["err_slanted"] for r in sel if r["err_slanted"] is not None]
        ef = [r["err_flat"] for r in sel if r["err_flat"] is not None]
        return {"pairs": len(sel), "pairs_with_slanted_points": len(mv),
                "moved_median": float(np.median(mv)) if mv else None,
                "short_rate": float(np.mean(np.array(mv) < 0.9)) if mv else None,  # pairs stopping > 10 % short
                "err_slanted_median": float(np.median(es)) if es else None,
                "err_flat_median": float(np.median(ef)) if ef else None,
                "moved_by_share": {name: (float(np.median(v)) if v else None) for name, v in
                                   ((name, [r["moved_by_share"][i] for r in sel if r["moved_by_share"][i] is not None])
                                    for i, name in enumerate(SHARE_BINS))}}

    classes = [c for c in FEATURE_CLASSES if any(r["feature"] == c for r in rows)]
    return {"checkpoint": str(loaded.path) if loaded is not None and loaded.path else None,
            "cpu_hours": loaded.meta.get("cpu_hours") if loaded is not None else None,
            "data": str(data), "steps": steps, "pairs": len(rows), "all": summary(rows),
            "by_feature": {c: summary([r for r in rows if r["feature"] == c]) for c in classes}, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polycubenet.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True, help="held-out shard folder")
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--n-out", type=int, default=8192)
    ap.add_argument("--n-in", type=int, help="subsample the condition to this many points")
    ap.add_argument("--steps", type=int, default=64, help="DDIM steps (0: stride 4)")
    ap.add_argument("--timesteps", help="explicit DDIM timesteps instead of --steps, e.g. 1023,64: the one-step "
                                        "jump, then a refining step from t = 64")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--recycles", type=int, help="a recycling model's further evaluations per step (default: 1 for one)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-structure", action="store_true")
    ap.add_argument("--identity", action="store_true",
                    help="also extract each pair's own samples (the no-model reference for exact structure)")
    ap.add_argument("--device")
    ap.add_argument("--mend-moves", type=int, default=ExtractConfig.mend_moves,
                    help="the extraction's topology mends (ExtractConfig.mend_moves; default: its default, none)")
    ap.add_argument("--no-sheets", action="store_true",
                    help="the extraction merges close planes that face opposite ways, as before session 70 "
                         "(ExtractConfig.sheet_bandwidths=None)")
    ap.add_argument("--json", help="write the metrics here")
    ap.add_argument("--publish", help="also write the shipped checkpoint (EMA, float16, metrics) here")
    args = ap.parse_args(argv)
    res = evaluate(args.checkpoint, args.data, args.count, n_out=args.n_out, n_in=args.n_in,
                   steps=(tuple(int(t) for t in args.timesteps.split(",")) if args.timesteps else args.steps or None),
                   seed=args.seed, structure=not args.no_structure, batch=args.batch,
                   device=args.device, identity=args.identity, recycles=args.recycles,
                   extract_config=ExtractConfig(mend_moves=args.mend_moves,
                                                **({"sheet_bandwidths": None} if args.no_sheets else {})))
    summary = {k: v for k, v in res.items() if k != "rows"}
    print(json.dumps(summary, indent=1))
    if args.json:
        write_json(args.json, res)
    if args.publish:
        from .model.checkpoint import publish

        publish(args.checkpoint, args.publish, metrics=summary)
        print(f"[evaluate] published {args.publish}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
