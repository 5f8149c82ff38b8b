"""Training shards: many pairs per ``.npz`` with fixed point counts, reproducible by seed.

Pair ``i`` of a dataset with seed ``S`` is ``make_pair(pair_seed(S, i))`` where
:func:`pair_seed` derives the pair's seed from ``np.random.SeedSequence(S,
spawn_key=(i,))``; a shard is therefore a pure function of ``(S, first index, count,
parameters)``, byte for byte, whatever the number of worker processes.

Shard ``shard-KKKKK.npz`` holds pairs ``K * per_shard ...`` as stacked arrays
(``K`` pairs, ``N = n_cond``, ``M = n_target``):

==========================  =================  ==========================================
array                       shape, dtype       meaning
==========================  =================  ==========================================
index                       (K,) int64         global pair index
seeds                       (K,) int64         ``make_pair(seeds[k])`` rebuilds pair k
genus                       (K,) int32
cond_points, cond_normals   (K, N, 3) float32  shape samples (canonical frame)
target_points, ..._normals  (K, M, 3) float32  polycube samples; normals exactly axes
target_on_shape             (K, M, 3) float32  the shape point of each target point
grid_sizes                  (K, 3) int32       ``(nx, ny, nz)`` of each polycube
grid_offsets                (K + 1,) int64     pair k's planes: ``grid_coords[o[k]:o[k+1]]``
grid_coords                 (G,) float64       ``xs, ys, zs`` concatenated per pair
occupancy_offsets           (K + 1,) int64
occupancy                   (C,) bool          ``occupancy[o[k]:o[k+1]].reshape(grid_sizes[k])``
__meta__                    uint8              JSON: parameters, per-pair provenance,
                                               deformation parameters and frame transforms
==========================  =================  ==========================================

With ``full=True`` also: ``cond_face_ids, target_face_ids (K, ., ) int32``,
``cond_barycentrics, target_barycentrics (K, ., 3) float32``, ``cond_on_polycube
(K, N, 3) float32`` and both meshes as ragged arrays (``vertex_offsets, face_offsets,
shape_vertices, polycube_vertices (float64), faces (int32, local indices)``).
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import sys
from pathlib import Path
from typing import Iterator

import numpy as np

from ..atomic import load_npz, save_npz, write_json
from ..data import Polycube
from .pairs import EDGE_LENGTH, SynthPair, make_pair
from .polycube import FLANGES

FORMAT = 1
MANIFEST = "dataset.json"


def pair_seed(dataset_seed: int, index: int) -> int:
    """The seed of pair ``index`` of the dataset ``dataset_seed`` (63-bit, non-negative).

    Parameters
    ----------
    dataset_seed : int, >= 0
    index : int, >= 0

    Returns
    -------
    int
    """
    ss = np.random.SeedSequence(entropy=int(dataset_seed), spawn_key=(int(index),))
    return int(ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


@dataclasses.dataclass(frozen=True)
class ShardParams:
    """The parameters every pair of a dataset shares (recorded in each shard and the manifest)."""

    n_cond: int = 4096
    n_target: int = 4096
    sampler: str = "poisson"
    edge_length: float = EDGE_LENGTH
    full: bool = False
    cad_features: bool = False
    whole_slants: bool = False
    max_strength: float | None = None
    tall_bosses: bool = False
    full_slants: float = 0.0
    cut_slants: bool = False
    turned: float = 0.0
    bolt_circles: float = 0.0
    flanges: float = FLANGES
    min_holes: int = 0
    breakouts: float = 0.0
    gussets: float = 0.0


def pair_record(pair: SynthPair, index: int, full: bool = False) -> dict:
    """The compact, shard-ready form of one pair: ``{"arrays": {...}, "meta": {...}}``."""
    pc = pair.polycube
    arrays = {
        "index": np.int64(index),
        "seeds": np.int64(pair.seed),
        "genus": np.int32(pair.genus),
        "cond_points": pair.cond.points.astype(np.float32),
        "cond_normals": pair.cond.normals.astype(np.float32),
        "target_points": pair.target.points.astype(np.float32),
        "target_normals": pair.target.normals.astype(np.float32),
        "target_on_shape": pair.target_on_shape.astype(np.float32),
        "grid_sizes": np.asarray(pc.occupancy.shape, dtype=np.int32),
        "grid_coords": np.concatenate([pc.xs, pc.ys, pc.zs]).astype(np.float64),
        "occupancy": np.ascontiguousarray(pc.occupancy, dtype=bool).ravel(),
    }
    if full:
        arrays.update(
            cond_face_ids=pair.cond.face_ids.astype(np.int32),
            cond_barycentrics=pair.cond.barycentrics.astype(np.float32),
            target_face_ids=pair.target.face_ids.astype(np.int32),
            target_barycentrics=pair.target.barycentrics.astype(np.float32),
            cond_on_polycube=pair.cond_on_polycube.astype(np.float32),
            shape_vertices=pair.shape_vertices,
            polycube_vertices=pair.polycube_vertices,
            faces=pair.faces.astype(np.int32),
        )
    meta = {
        "index": int(index),
        "seed": int(pair.seed),
        "genus": int(pair.genus),
        "deformation": pair.deformation.to_dict(),
        "shape_transform": pair.shape_transform.to_dict(),
        "polycube_transform": pair.polycube_transform.to_dict(),
        **{k: pair.meta[k] for k in ("style", "features", "map_kinds", "attempts", "min_jacobian", "snap_deg")},
    }
    return {"arrays": arrays, "meta": meta}


_STACKED = ("index", "seeds", "genus", "cond_points", "cond_normals", "target_points", "target_normals",
            "target_on_shape", "grid_sizes", "cond_face_ids", "cond_barycentrics", "target_face_ids",
            "target_barycentrics", "cond_on_polycube")
_RAGGED = {"grid_coords": "grid_offsets", "occupancy": "occupancy_offsets"}


def _offsets(parts: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([[0], np.cumsum([len(p) for p in parts])]).astype(np.int64)


def write_shard(path: str | Path, records: list[dict], params: ShardParams, dataset_seed: int | None = None) -> Path:
    """Stack ``records`` (from :func:`pair_record`) into one shard, written atomically.

    Parameters
    ----------
    path : str or Path, ``.npz``
    records : list of dict
    params : ShardParams
    dataset_seed : int or None, recorded in the metadata

    Returns
    -------
    Path
    """
    if not records:
        raise ValueError("a shard needs at least one pair")
    out: dict[str, np.ndarray] = {}
    A = [r["arrays"] for r in records]
    for name in _STACKED:
        if name in A[0]:
            out[name] = np.stack([a[name] for a in A])
    for name, off in _RAGGED.items():
        parts = [a[name] for a in A]
        out[name] = np.concatenate(parts)
        out[off] = _offsets(parts)
    if "faces" in A[0]:
        out["vertex_offsets"] = _offsets([a["shape_vertices"] for a in A])
        out["face_offsets"] = _offsets([a["faces"] for a in A])
        out["shape_vertices"] = np.concatenate([a["shape_vertices"] for a in A])
        out["polycube_vertices"] = np.concatenate([a["polycube_vertices"] for a in A])
        out["faces"] = np.concatenate([a["faces"] for a in A])
    meta = {
        "format": FORMAT,
        "dataset_seed": None if dataset_seed is None else int(dataset_seed),
        "params": dataclasses.asdict(params),
        "pairs": [r["meta"] for r in records],
    }
    out["__meta__"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    return save_npz(path, **out)


class Shard:
    """A loaded shard (all arrays in memory); index it to get one pair's view.

    Attributes
    ----------
    path : Path
    arrays : dict of name -> ndarray (see the module docstring)
    meta : dict, the decoded ``__meta__``
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.arrays = load_npz(self.path)
        self.meta = json.loads(bytes(self.arrays.pop("__meta__")).decode())
        if self.meta.get("format") != FORMAT:
            raise ValueError(f"{self.path}: shard format {self.meta.get('format')} != {FORMAT}")

    def __len__(self) -> int:
        return len(self.arrays["index"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def polycube(self, k: int) -> Polycube:
        """The grid and occupancy of pair ``k`` (canonical frame)."""
        a = self.arrays
        nx, ny, nz = (int(v) for v in a["grid_sizes"][k])
        g = a["grid_coords"][a["grid_offsets"][k] : a["grid_offsets"][k + 1]]
        occ = a["occupancy"][a["occupancy_offsets"][k] : a["occupancy_offsets"][k + 1]].reshape(nx, ny, nz)
        return Polycube(
            g[: nx + 1].copy(), g[nx + 1 : nx + ny + 2].copy(), g[nx + ny + 2 :].copy(), occ.copy(),
            meta={"provenance": "synthetic", "genus": int(a["genus"][k])},
        )

    def mesh(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(shape_vertices, polycube_vertices, faces)`` of pair ``k`` (shards written with ``full``)."""
        a = self.arrays
        if "faces" not in a:
            raise KeyError(f"{self.path} has no meshes (written without full=True); use regenerate()")
        v0, v1 = a["vertex_offsets"][k], a["vertex_offsets"][k + 1]
        f0, f1 = a["face_offsets"][k], a["face_offsets"][k + 1]
        return a["shape_vertices"][v0:v1], a["polycube_vertices"][v0:v1], a["faces"][f0:f1].astype(np.int64)

    def pair(self, k: int) -> dict:
        """Pair ``k`` as a dict: every per-pair array, ``polycube`` and ``meta``."""
        out = {name: self.arrays[name][k] for name in _STACKED if name in self.arrays}
        out["polycube"] = self.polycube(k)
        out["meta"] = self.meta["pairs"][k]
        return out

    def __iter__(self) -> Iterator[dict]:
        for k in range(len(self)):
            yield self.pair(k)

    def feature(self, k: int) -> str | None:
        """The machined feature of pair ``k`` a polycube finds hardest to follow, from its recorded
        deformation (:func:`feature_class`); None when the shard records none."""
        pairs = self.meta.get("pairs") or []
        return feature_class(pairs[k].get("deformation")) if k < len(pairs) else None

    def ribs(self, k: int) -> int | None:
        """How many gussets (``synth --gussets``: ribs in concave corners) pair ``k`` carries, from its recorded
        features; None when the shard records none."""
        pairs = self.meta.get("pairs") or []
        if k >= len(pairs) or pairs[k].get("features") is None:
            return None
        return sum(f.get("kind") == "gusset" for f in pairs[k]["features"])

    def regenerate(self, k: int) -> SynthPair:
        """Rebuild the full pair ``k`` (meshes, map, float64 samples) from its seed."""
        # a shard written before a parameter existed has that parameter's default
        params = ShardParams(**{**dataclasses.asdict(ShardParams()), **self.meta["params"]})
        return _generate(int(self.arrays["seeds"][k]), params)


#: the classes of :func:`feature_class`, hardest first
FEATURE_CLASSES = ("slanted end", "chamfer", "neither")


def feature_class(deformation: dict | None) -> str | None:
    """``"slanted end"`` when a pair's deformation (its recorded ``DeformationMap`` dict) cuts a whole end by a
    slanted plane (``slant_end``, ``--whole-slants``), else ``"chamfer"`` when it cuts a convex edge by a plane
    (``round_edge`` in the chamfer style, 45 degrees or a long slanted one, ``--cad-features``), else
    ``"neither"``; None without a deformation.  A polycube meets such a face at an axis plane the slant lies
    between, so these pairs ask the model to commit a slanted face to one side."""
    if not deformation:
        return None
    maps = deformation.get("maps") or []
    if any(m.get("kind") == "slant_end" for m in maps):
        return FEATURE_CLASSES[0]
    if any(m.get("kind") == "round_edge" and m.get("style") == "chamfer" for m in maps):
        return FEATURE_CLASSES[1]
    return FEATURE_CLASSES[2]


def load_shard(path: str | Path) -> Shard:
    """Load one shard written by :func:`write_dataset` / :func:`write_shard`."""
    return Shard(path)


def list_shards(directory: str | Path) -> list[Path]:
    """The shard files of a dataset folder, in order."""
    return sorted(Path(directory).glob("shard-*.npz"))


def iter_pairs(directory: str | Path) -> Iterator[dict]:
    """Every pair of a dataset folder, in index order (see :meth:`Shard.pair`)."""
    for path in list_shards(directory):
        yield from load_shard(path)


# --------------------------------------------------------------------------- writing


def _generate(seed: int, params: ShardParams) -> SynthPair:
    """The pair of ``seed`` made with a dataset's shared parameters (writing and :meth:`Shard.regenerate`)."""
    return make_pair(seed, n_cond=params.n_cond, n_target=params.n_target, sampler=params.sampler,
                     edge_length=params.edge_length, cad_features=params.cad_features,
                     whole_slants=params.whole_slants, max_strength=params.max_strength,
                     tall_bosses=params.tall_bosses, full_slants=params.full_slants, cut_slants=params.cut_slants,
                     turned=params.turned, bolt_circles=params.bolt_circles, flanges=params.flanges,
                     min_holes=params.min_holes, breakouts=params.breakouts, gussets=params.gussets)


def _make_record(task: tuple[int, int, ShardParams]) -> dict:
    dataset_seed, index, params = task
    return pair_record(_generate(pair_seed(dataset_seed, index), params), index, full=params.full)


def _init_worker() -> None:  # pragma: no cover - runs in child processes
    import threadpoolctl  # a dependency since session 88 (polycubenet.threads)

    threadpoolctl.threadpool_limits(1)


def write_dataset(
    out: str | Path,
    count: int,
    seed: int,
    *,
    per_shard: int = 256,
    n_cond: int = 4096,
    n_target: int = 4096,
    workers: int = 1,
    sampler: str = "poisson",
    edge_length: float = EDGE_LENGTH,
    full: bool = False,
    overwrite: bool = False,
    progress: bool = True,
    cad_features: bool = False,
    whole_slants: bool = False,
    max_strength: float | None = None,
    tall_bosses: bool = False,
    full_slants: float = 0.0,
    cut_slants: bool = False,
    turned: float = 0.0,
    bolt_circles: float = 0.0,
    flanges: float = FLANGES,
    min_holes: int = 0,
    breakouts: float = 0.0,
    gussets: float = 0.0,
) -> list[Path]:
    """Generate ``count`` pairs into ``out/shard-*.npz`` plus ``out/dataset.json``.

    Shards already present (from an interrupted run with the same parameters) are kept
    and skipped, so re-running the same command resumes.

    Parameters
    ----------
    out : str or Path, folder (created)
    count : int, number of pairs
    seed : int, the dataset seed
    per_shard : int, pairs per shard (the last shard may hold fewer)
    n_cond, n_target : int, points per pair
    workers : int, processes (1 = in this process); the output does not depend on it
    sampler : ``"poisson"`` or ``"uniform"``
    edge_length : float, surface refinement
    full : bool, also store face ids, barycentrics and both meshes
    overwrite : bool, regenerate shards that exist; required when the parameters differ
        from an existing manifest in ``out``
    progress : bool, tqdm progress bar on stderr
    cad_features : bool, round bosses and slanted ends too (:func:`~polycubenet.synth.pairs.make_pair`)
    whole_slants : bool, whole ends cut by slanted planes too (:func:`~polycubenet.synth.pairs.make_pair`)
    max_strength : float or None, cap on the strength of the global maps (:func:`~polycubenet.synth.pairs.make_pair`)
    tall_bosses : bool, more and taller bosses (:func:`~polycubenet.synth.pairs.make_pair`)
    full_slants : float, the share of whole-end slants across the whole end (:func:`~polycubenet.synth.pairs.make_pair`)
    cut_slants : bool, whole-end slants as plane cuts that shear nothing near them (:func:`~polycubenet.synth.pairs.make_pair`)
    turned : float, the share of turned parts: shafts, bushings, flanges (:func:`~polycubenet.synth.pairs.make_pair`)
    bolt_circles : float, the share of bolted flanges drilled on a circle (:func:`~polycubenet.synth.pairs.make_pair`)
    flanges : float, the share of turned parts with a flange (:func:`~polycubenet.synth.pairs.make_pair`)
    min_holes : int, the fewest through-holes a non-turned pair attempts (:func:`~polycubenet.synth.pairs.make_pair`)
    breakouts : float, the share of pairs with a hole breaking out through a slanted end (:func:`~polycubenet.synth.pairs.make_pair`)
    gussets : float, the share of pairs with triangular ribs in concave corners (:func:`~polycubenet.synth.pairs.make_pair`)

    Returns
    -------
    list of Path, every shard of the dataset
    """
    if count < 1 or per_shard < 1:
        raise ValueError(f"count and per_shard must be positive; got {count}, {per_shard}")
    if seed < 0:
        raise ValueError(f"seed must be non-negative; got {seed}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    params = ShardParams(int(n_cond), int(n_target), str(sampler), float(edge_length), bool(full), bool(cad_features),
                         bool(whole_slants), None if max_strength is None else float(max_strength),
                         bool(tall_bosses), float(full_slants), bool(cut_slants), float(turned),
                         float(bolt_circles), float(flanges), int(min_holes), float(breakouts),
                         float(gussets))
    n_shards = (count + per_shard - 1) // per_shard
    shards = [
        {"name": f"shard-{k:05d}.npz", "first": k * per_shard, "count": min(per_shard, count - k * per_shard)}
        for k in range(n_shards)
    ]
    manifest = {"format": FORMAT, "seed": int(seed), "count": int(count), "per_shard": int(per_shard),
                "params": dataclasses.asdict(params), "shards": shards}
    mpath = out / MANIFEST
    if mpath.exists() and not overwrite:
        old = json.loads(mpath.read_text())
        # a manifest written before a parameter existed has that parameter's default
        old["params"] = {**dataclasses.asdict(ShardParams()), **old.get("params", {})}
        same = all(old.get(k) == manifest[k] for k in ("format", "seed", "per_shard", "params"))
        if not same:
            raise ValueError(f"{out} holds a dataset with other parameters ({mpath}); pass overwrite=True")
    write_json(mpath, manifest)

    todo = [s for s in shards if overwrite or not _shard_ok(out / s["name"], s)]
    total = sum(s["count"] for s in todo)
    tasks = [(int(seed), s["first"] + j, params) for s in todo for j in range(s["count"])]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, file=sys.stderr, unit="pair", desc="synth", dynamic_ncols=True)
    pool = None
    try:
        if workers > 1 and total > 1:
            pool = multiprocessing.get_context("spawn").Pool(min(workers, total), initializer=_init_worker)
            results = pool.imap(_make_record, tasks, chunksize=1)
        else:
            results = map(_make_record, tasks)
        for s in todo:
            records = []
            for _ in range(s["count"]):
                records.append(next(results))
                if bar is not None:
                    bar.update(1)
            write_shard(out / s["name"], records, params, dataset_seed=seed)
    finally:
        if pool is not None:
            pool.terminate()
            pool.join()
        if bar is not None:
            bar.close()
    return [out / s["name"] for s in shards]


def _shard_ok(path: Path, spec: dict) -> bool:
    if not path.exists():
        return False
    try:
        index = load_npz(path, ["index"])["index"]
        return len(index) == spec["count"] and int(index[0]) == spec["first"]
    except Exception:  # a damaged file is regenerated
        return False
