"""Meshing a whole library of parts: the per-stage file contract that the orchestration runs.

The Prefect tasks (``tasks/``) and flows (``flows/``) are thin; everything they do to
a part lives here, as plain functions over paths, so it runs (and is tested) without
an orchestrator:

* discovery (:func:`discover`): folders, globs and files of every supported format;
* content hashing and cache keys (:func:`file_hash`, :func:`stage_key`): a stage's key
  is the hash of its upstream key, its parameters and its version string, and the
  first key is the hash of the part file's bytes, so a re-run reuses exactly the
  stages whose inputs and parameters did not change;
* the stages, each writing its result atomically under ``<work>/<part-hash>/`` as
  ``<stage>-<key>.npz`` and returning the path (:func:`load_sample`,
  :func:`polycube_cloud`, :func:`write_generated`, :func:`cleanup_extract`,
  :func:`register`, :func:`partition_pullback`, :func:`report_export`) -- the same
  order as :func:`polycubenet.pipeline.mesh_surface` (extraction before registration:
  an invalid polycube is found before CPD is paid for, and the classical fallback
  then starts from the part, not from a registration it would throw away);
* polycube sources by name (:func:`make_source`): ``oracle`` (a synthetic part's
  ground-truth sidecar ``X.polycube.npz``), ``classical`` (``polycubenet.classical``,
  when present); the learned model is run in batches by the flow
  (``polycubenet.inference``);
* the manifest (``manifest.json``, one row per part) and ``report.html``.

Nothing here imports Prefect or Dask.
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import html
import json
import os
import time
from pathlib import Path
from typing import Iterable

import numpy as np

from .atomic import load_npz, save_npz, write_json, write_text
from .data import HexMesh, Part, Polycube, PolycubeCloud, SurfaceSample
from .errors import PolycubeError
from .pipeline import OracleSource, PartResult, PipelineConfig, register_cloud
from .threads import one_blas_thread
from . import tol
from .policy import (draw_anchors, draw_seed, draw_steps, draw_turn, extraction_config, faithful, refinement,
                     source_config, under_bar)

#: part files the library reads (``polycubenet.io.load_part``)
CAD_SUFFIXES = (".step", ".stp", ".iges", ".igs")
MESH_SUFFIXES = (".stl", ".obj", ".ply", ".off", ".glb")
#: volume meshes (tets, hexes, ...): the part is their boundary
VOLUME_SUFFIXES = (".mesh", ".vtu", ".vtk", ".msh")
PART_SUFFIXES = CAD_SUFFIXES + MESH_SUFFIXES + VOLUME_SUFFIXES
#: hex mesh formats ``polycubenet.io.write_hex`` writes
HEX_FORMATS = ("vtu", "vtk", "mesh", "inp", "msh", "bdf")
#: the sidecar next to a synthetic part ``X.stl`` holding its ground-truth polycube
SIDECAR_SUFFIX = ".polycube.npz"

#: bump a stage's version when its code changes what it writes: every key downstream changes
STAGE_VERSIONS = {
    # 2: CAD solids healed before meshing, zero-area caps split, sharpest_edge_deg; 3: a heal that changes the
    # surface's area or that gmsh cannot mesh is undone
    "load_sample": "3",
    "polycube": "1",
    "extract": "4",  # 2: carries the classical exact map; 3: the voxel solid taken as built; 4: no plane refit
    "register": "2",  # 2: the classical exact map replaces CPD
    # 2: classical pullback as in pipeline.mesh_surface; 3: sj_terms by operators; 4: realise.py;
    # 5: no-pillow retry; 6: uncovered spots mended (pullback.mend_spots); 7: no mend past capture_max (4 %)
    # 8: a few poor hexes eased with surface slack (pullback.ease_poor_hexes); 9: no second labelling after a
    # realisation whose flattened part does not bound the learned structure; 10: a learned draw's file is its
    # registration map's mesh alone, the rest of its pull-back a second file (policy.run_chain decides when);
    # 11: a realisation may keep the part's own structure on the learned labels (RealiseConfig.own_structure)
    "pullback": "11",
    "export": "1",
}
#: stage names in pipeline order (what ``stage reached`` in the manifest refers to)
STAGES = ("load_sample", "polycube", "extract", "register", "pullback", "export")
MANIFEST = "manifest.json"
#: default wall-clock limit of one part in a batch (seconds): generous, a part takes ~10-60 s
DEFAULT_PART_TIMEOUT = 1800.0
REPORT = "report.html"


# --------------------------------------------------------------------------- discovery


def discover(inputs: Iterable[str | os.PathLike], *, prefer_cad: bool = True,
             exclude: Iterable[str | os.PathLike] = ()) -> list[Path]:
    """Part files named by ``inputs``: files, folders (searched recursively) and glob patterns.

    Only the suffixes in :data:`PART_SUFFIXES` are kept from folders and globs (a file named
    explicitly is always kept, whatever its suffix, so that ``load_part`` reports it); nothing under
    an ``exclude`` folder is kept from a folder or glob (a run's own output folder inside its
    input: its hex meshes are volume meshes too).  With ``prefer_cad``, when one stem exists in
    several forms in the same folder (found through a folder or a glob) only the most exact is meshed: CAD (STEP/IGES), then a
    surface mesh, then a volume mesh.  Sorted, without duplicates.  Raises
    ``FileNotFoundError`` for an input that is neither a file, a folder nor a pattern that
    matches something.
    """
    skip = [Path(e).resolve() for e in exclude]

    def kept(q: Path) -> bool:
        if not (q.is_file() and q.suffix.lower() in PART_SUFFIXES):
            return False
        r = q.resolve()
        return not any(r == e or e in r.parents for e in skip)

    found: list[Path] = []
    named: list[Path] = []  # files named explicitly: always kept
    for item in inputs:
        s = str(item)
        p = Path(s)
        if p.is_dir():
            found += [q for q in sorted(p.rglob("*")) if kept(q)]
        elif p.is_file():
            named.append(p)
        elif glob.has_magic(s):
            matches = [Path(m) for m in sorted(glob.glob(s, recursive=True))]
            found += [q for q in matches if kept(q)]
            found += [r for q in matches if q.is_dir() for r in discover([q], prefer_cad=False, exclude=skip)]
        else:
            raise FileNotFoundError(f"{s}: no such file, folder or matching pattern")
    if prefer_cad:
        def rank(q: Path) -> int:
            x = q.suffix.lower()
            return 0 if x in CAD_SUFFIXES else 2 if x in VOLUME_SUFFIXES else 1

        best: dict = {}
        for q in found:
            k = (q.parent, q.stem)
            best[k] = min(best.get(k, 3), rank(q))
        found = [q for q in found if rank(q) == best[(q.parent, q.stem)]]
    return sorted(dict.fromkeys(q.resolve() for q in found + named))


def part_names(paths: list[Path], hashes: list[str]) -> list[str]:
    """Output folder name of each part, one per path: its stem; where two paths share a stem, with 8 hash
    characters added (``bracket.step`` and ``sub/bracket.stl``), then the extension where the contents are
    the same too (four empty files ``x.stl``, ``x.obj``, ...), then a counter."""
    names = [p.stem for p in paths]

    def clashes(ns):
        seen: dict = {}
        for n in ns:
            seen[n] = seen.get(n, 0) + 1
        return {n for n, c in seen.items() if c > 1}

    for extend in (lambda i: f"{names[i]}-{hashes[i][:8]}", lambda i: f"{names[i]}-{paths[i].suffix.lstrip('.').lower()}"):
        dup = clashes(names)
        if not dup:
            break
        names = [extend(i) if n in dup else n for i, n in enumerate(names)]
    dup = clashes(names)
    count: dict = {}
    for i, n in enumerate(names):
        if n in dup:
            count[n] = count.get(n, 0) + 1
            names[i] = f"{n}-{count[n]}"
    return names


# --------------------------------------------------------------------------- hashing and keys


def file_hash(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def _plain(obj):
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {k: _plain(v) for k, v in dataclasses.asdict(obj).items()}
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def stable_hash(obj) -> str:
    """SHA-256 of a JSON rendering of ``obj`` (dataclasses, dicts, lists, numbers, strings)."""
    return hashlib.sha256(json.dumps(_plain(obj), sort_keys=True, default=repr).encode()).hexdigest()


def stage_key(stage: str, upstream: str, params) -> str:
    """Cache key of ``stage``: hash of its version, its parameters and the upstream key
    (for the first stage, the part file's content hash).  24 hex characters."""
    if stage not in STAGE_VERSIONS:
        raise ValueError(f"unknown stage {stage!r}; expected one of {STAGES}")
    return stable_hash({"stage": stage, "version": STAGE_VERSIONS[stage], "upstream": upstream, "params": params})[:24]


def stage_params(config: PipelineConfig, *, polycube: str = "oracle", polycube_extra=None,
                 load_kw: dict | None = None, formats=("vtu",), out_dir: str | None = None) -> dict:
    """The parameters each stage's key depends on (only those: changing the hex size
    re-runs partition and later, never sampling or generation)."""
    hexes = source_config(polycube, config)  # a denser source partitions into more hexes
    return {
        "load_sample": {"n_sample": config.n_sample, "seed": config.seed, "load": dict(load_kw or {})},
        "polycube": {"source": polycube, "seed": config.seed, "extra": polycube_extra,
                     "n_points": config.n_learned if refinement(polycube)[0] == "learned" else config.n_polycube},
        "extract": {"extract": extraction_config(polycube, config).extract},  # a further draw: no fallbacks
        "register": {"n_register": config.n_register, "seed": config.seed},
        "pullback": {"target_hexes": hexes.target_hexes, "target_size": hexes.target_size, "pullback": config.pullback,
                     "realise": config.realise, "min_sj": config.min_sj},
        "export": {"formats": sorted(formats), "out": out_dir},
    }


def chain_keys(part_hash: str, params: dict, *, source: str | None = None) -> dict[str, str]:
    """Keys of every stage for one part; ``source`` overrides the polycube source name
    (the fallback chain: the classical cloud has its own keys from ``polycube`` on)."""
    keys: dict[str, str] = {}
    up = part_hash
    for stage in STAGES:
        p = params[stage]
        if stage == "polycube" and source is not None:
            p = {**p, "source": source}
        up = keys[stage] = stage_key(stage, up, p)
    return keys


def stage_path(work: str | os.PathLike, part_hash: str, stage: str, key: str, suffix: str = ".npz") -> Path:
    """Where a stage's result lives: ``<work>/<part-hash[:16]>/<stage>-<key>.npz``."""
    return Path(work) / part_hash[:16] / f"{stage}-{key}{suffix}"


def sweep_partials(*folders: str | os.PathLike, before: float | None = None) -> int:
    """Remove the ``.tmp-*`` files a killed run left behind (``atomic.atomic_path``) that were last
    written before ``before`` (a ``time.time()``; default now); return how many.  Meant for a
    folder that one run writes at a time (what the deployments' concurrency limits ensure)."""
    before = time.time() if before is None else before
    n = 0
    for folder in folders:
        folder = Path(folder)
        if folder.is_dir():
            for tmp in folder.rglob(".tmp-*"):
                try:
                    if tmp.is_file() and tmp.stat().st_mtime < before:
                        tmp.unlink()
                        n += 1
                except FileNotFoundError:  # renamed or removed meanwhile by its writer
                    pass
    return n


# --------------------------------------------------------------------------- polycube sources


def sidecar_path(part: str | os.PathLike) -> Path:
    """``X.polycube.npz`` next to ``X.<ext>``."""
    p = Path(part)
    return p.with_name(p.stem + SIDECAR_SUFFIX)


def polycube_to_frame(poly: Polycube, transform) -> Polycube:
    """A polycube given in a part's file coordinates, in the part's canonical frame.

    ``transform`` (:class:`polycubenet.frame.Transform`) must rotate by a signed axis
    permutation (an axis-aligned polycube stays axis-aligned); anything else raises
    :class:`PolycubeError`.
    """
    R = np.asarray(transform.rotation, float)
    perm = np.abs(R).argmax(axis=1)  # canonical axis i <- file axis perm[i]
    signs = np.sign(R[np.arange(3), perm])
    if sorted(perm.tolist()) != [0, 1, 2] or np.abs(np.abs(R[np.arange(3), perm]) - 1).max() > 1e-6:
        raise PolycubeError("the oracle polycube is not axis-aligned in the part's canonical frame")
    grids_file = [np.asarray(poly.xs, float), np.asarray(poly.ys, float), np.asarray(poly.zs, float)]
    occ = np.asarray(poly.occupancy, bool).transpose(perm)
    grids = []
    for i in range(3):
        g = signs[i] * (grids_file[perm[i]] - transform.center[perm[i]]) * transform.scale
        if signs[i] < 0:
            g = g[::-1]
            occ = np.flip(occ, axis=i)
        grids.append(g)
    return Polycube(*grids, np.ascontiguousarray(occ), meta=dict(poly.meta))


@dataclasses.dataclass
class SidecarOracle:
    """Polycube source for a synthetic part: its sidecar's polycube (file coordinates) moved
    into the canonical frame, sampled with noise and outliers by :class:`OracleSource`."""

    sidecar: Path
    transform: object
    noise: float = 0.005
    outliers: float = 0.02

    def __call__(self, sample, V, F, config):
        if not Path(self.sidecar).is_file():
            raise PolycubeError(f"no oracle polycube: {self.sidecar} does not exist")
        poly = polycube_to_frame(Polycube.load(self.sidecar), self.transform)
        return OracleSource(poly, noise=self.noise, outliers=self.outliers)(sample, V, F, config)


def classical_available() -> bool:
    """Whether the classical polycube construction (``polycubenet.classical``) is installed."""
    import importlib.util

    return importlib.util.find_spec("polycubenet.classical") is not None


def make_source(kind: str, part_path: str | os.PathLike, transform, *, checkpoint: str | os.PathLike | None = None,
                device: str | None = None, steps: int | None = None):
    """A per-part polycube source by name: ``oracle``, ``classical``, ``voxel`` or ``voxel+K``
    (the voxel polycube ``K`` refinement steps finer, :func:`polycubenet.policy.source_names`;
    ``voxel+K*`` is the same polycube, partitioned denser),
    or ``learned+K``: the model of ``checkpoint`` (on ``device``) drawn again (the further draw ``K`` of
    :data:`polycubenet.policy.LEARNED_DRAWS` after a first draw at ``steps``), one part at a time.

    (``learned`` is not made here: the flow runs the model's first draw in batches across parts.)
    This is the one place the classical fallbacks plug in.
    """
    if kind == "oracle":
        return SidecarOracle(sidecar_path(part_path), transform)
    if kind == "classical":
        try:
            from .classical import ClassicalSource
        except ImportError as exc:
            raise PolycubeError(f"the classical polycube construction is not available ({exc})") from exc
        return ClassicalSource()
    base, refine = refinement(kind)
    if base == "voxel":
        from .voxel import VoxelSource

        return VoxelSource(refine=refine)
    if base == "learned" and refine:
        from .inference import ModelSource

        return ModelSource(checkpoint, steps=steps, device=device).draw_source(refine)
    raise ValueError(f"unknown per-part polycube source {kind!r}; expected 'oracle', 'classical', 'voxel', 'voxel+K' "
                     "or 'learned+K'")


def source_extra(kind: str, part_path: str | os.PathLike, checkpoint: str | os.PathLike | None = None, *,
                 steps: int | None = None, device: str | None = None) -> dict:
    """What, besides the part, a polycube source's output depends on (for its cache key).

    For the model: the checkpoint's content, the DDIM steps actually used and the device
    type (``steps=None`` means a device-dependent default, resolved here).  The batch and
    the point budget are not in it: a request's cloud does not depend on them
    (:func:`polycubenet.inference.generate`)."""
    if kind == "oracle":
        sc = sidecar_path(part_path)
        return {"sidecar": file_hash(sc) if sc.is_file() else None}
    if refinement(kind)[0] == "learned":
        from .inference import resolve_steps

        dev_type, used = resolve_steps(steps, device, checkpoint)
        used = draw_steps(kind, used)
        extra = {"checkpoint": file_hash(checkpoint) if checkpoint and Path(checkpoint).is_file() else str(checkpoint),
                 "steps": used, "device": dev_type}
        if refinement(kind)[1]:  # a further draw: its seed offset too, its turn and anchor spread where it has them
            extra["seed"] = draw_seed(kind)
            if draw_turn(kind):
                extra["turn"] = draw_turn(kind)
            if draw_anchors(kind) != "uniform":
                extra["anchors"] = draw_anchors(kind)
        return extra
    if kind == "classical" and classical_available():
        # the construction's settings and version: a cached classical cloud made by older code is not reused
        from .classical import VERSION, ClassicalConfig

        return {"classical": ClassicalConfig(), "version": VERSION}
    if refinement(kind)[0] == "voxel":
        from .voxel import VERSION as VOXEL_VERSION
        from .voxel import VoxelConfig

        return {"voxel": VoxelConfig(), "version": VOXEL_VERSION, "refine": refinement(kind)[1]}
    return {}


# --------------------------------------------------------------------------- the stages


@one_blas_thread
def load_sample(path: str | os.PathLike, dest: str | os.PathLike, config: PipelineConfig, load_kw: dict | None = None) -> Path:
    """Load and validate the part, put it in its canonical frame, Poisson-disk sample it.

    Writes one ``.npz`` at ``dest``: the canonical surface (``vertices``, ``faces``), the
    sample (``points``, ``normals``, ``face_ids``, ``barycentrics``) and JSON metadata
    (the part's ``meta`` and the ``transform`` back to file coordinates).  Raises PartError.
    """
    from .frame import canonicalize
    from .io import load_part
    from .sampling import poisson_disk

    part = load_part(path, **(load_kw or {}))
    Vc, T = canonicalize(part.vertices, part.faces)
    sample = poisson_disk(Vc, part.faces, config.n_sample, seed=config.seed)
    meta = {"part": part.meta, "transform": T.to_dict(), "name": Path(path).name}
    return _save_arrays(dest, meta, vertices=Vc, faces=part.faces, points=sample.points, normals=sample.normals,
                        face_ids=sample.face_ids, barycentrics=sample.barycentrics)


def read_loaded(path: str | os.PathLike):
    """``(Part in the canonical frame, SurfaceSample, Transform, meta)`` from a :func:`load_sample` file."""
    from .frame import Transform

    arrays, meta = _load_arrays(path)
    part = Part(arrays["vertices"], arrays["faces"], meta=meta["part"])
    sample = SurfaceSample(arrays["points"], arrays["normals"], arrays["face_ids"], arrays["barycentrics"])
    return part, sample, Transform.from_dict(meta["transform"]), meta


@one_blas_thread
def polycube_cloud(kind: str, part_path: str | os.PathLike, loaded: str | os.PathLike, dest: str | os.PathLike,
                   config: PipelineConfig, *, checkpoint: str | os.PathLike | None = None,
                   device: str | None = None, steps: int | None = None) -> Path:
    """Run a per-part polycube source (:func:`make_source`; ``checkpoint``, ``device`` and the first
    draw's ``steps`` for the model's further draws) on a loaded part; save the cloud."""
    part, sample, T, _ = read_loaded(loaded)
    source = make_source(kind, part_path, T, checkpoint=checkpoint, device=device, steps=steps)
    cloud = source(sample, part.vertices, part.faces, config)
    cloud.meta.setdefault("provenance", kind)
    return cloud.save(dest)


def write_generated(generated: np.ndarray, dest: str | os.PathLike, meta: dict,
                    anchors: np.ndarray | None = None) -> Path:
    """Save one part's generated cloud ``(M, 6)`` (xyz + normals) as a PolycubeCloud, with the part points
    ``anchors (M, 3)`` it was generated from (an anchored model; ``(M, 6)`` with the part's normals there)."""
    g = np.asarray(generated, dtype=np.float64)
    if g.ndim != 2 or g.shape[1] != 6 or not np.isfinite(g).all():
        raise PolycubeError(f"the model returned an unusable cloud (shape {g.shape}, finite {bool(np.isfinite(g).all())})")
    n = np.linalg.norm(g[:, 3:], axis=1, keepdims=True)
    normals = np.divide(g[:, 3:], n, out=np.zeros_like(g[:, 3:]), where=n > 0)
    a = None if anchors is None else np.asarray(anchors, dtype=np.float64)
    an = None if a is None or a.shape[1] < 6 else a[:, 3:6]
    return PolycubeCloud(g[:, :3], normals, meta={"provenance": "learned", **meta}, anchors=None if a is None else a[:, :3],
                         anchor_normals=an).save(dest)


@one_blas_thread
def cleanup_extract(cloud_path: str | os.PathLike, loaded: str | os.PathLike, dest: str | os.PathLike,
                    config: PipelineConfig) -> Path:
    """Outlier filter, then the explicit polycube (:func:`polycubenet.pipeline.cloud_polycube`:
    the voxel solid as built, any other cloud's structure extracted; validated against the
    part's genus).

    Writes the cleaned cloud and the polycube in one ``.npz``; raises PolycubeError when
    the polycube fails validation.
    """
    from .classical import ClassicalCloud
    from .pipeline import clean_cloud, cloud_polycube

    cloud = ClassicalCloud.load(cloud_path)  # a plain cloud loads with the classical fields None
    _, _, _, meta = read_loaded(loaded)
    P, N, keep = clean_cloud(cloud, config)
    poly = cloud_polycube(cloud, P, N, meta["part"].get("genus"), config, meta["name"])
    exact = _exact_map_arrays(cloud_path)
    if cloud.anchors is not None:  # a generated cloud's anchors (its own map to the part), row by row with P
        exact["anchors"] = cloud.anchors[keep]
    return _save_arrays(dest, {"polycube": poly.meta, "cloud": cloud.meta}, points=P, normals=N,
                        xs=poly.xs, ys=poly.ys, zs=poly.zs, occupancy=poly.occupancy, **exact)


_EXACT_MAP = ("polycube_vertices", "surface_vertices", "surface_faces")


def _exact_map_arrays(path) -> dict:
    """The exact polycube -> part map a classical cloud file carries (empty for other clouds)."""
    arrays = load_npz(path, _EXACT_MAP)
    return arrays if len(arrays) == len(_EXACT_MAP) else {}


def _surface_map(arrays: dict):
    from .classical import SurfaceMap

    return SurfaceMap(np.asarray(arrays["polycube_vertices"], float), np.asarray(arrays["surface_faces"], np.int64),
                      np.asarray(arrays["surface_vertices"], float))


def read_extracted(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, Polycube, dict]:
    arrays, meta = _load_arrays(path)
    return arrays["points"], arrays["normals"], _extracted_polycube(arrays, meta), meta["cloud"]


def _extracted_polycube(arrays: dict, meta: dict) -> Polycube:
    """The polycube of a :func:`cleanup_extract` file's arrays and meta."""
    return Polycube(arrays["xs"], arrays["ys"], arrays["zs"], arrays["occupancy"], meta=meta["polycube"])


@one_blas_thread
def register(extracted: str | os.PathLike, loaded: str | os.PathLike, dest: str | os.PathLike, config: PipelineConfig) -> Path:
    """Rigid + CPD registration of the cleaned cloud to the part sample (:func:`polycubenet.pipeline.register_cloud`)."""
    arrays, _ = _load_arrays(extracted)
    if all(k in arrays for k in _EXACT_MAP):
        # the classical polycube knows its map to the part exactly: no registration
        return _save_arrays(dest, {"method": "classical exact map"}, **{k: arrays[k] for k in _EXACT_MAP})
    P, N, _, _ = read_extracted(extracted)
    _, sample, _, _ = read_loaded(loaded)
    return register_cloud(sample, P, N, config).save(dest)


@one_blas_thread
def partition_pullback(extracted: str | os.PathLike, corr: str | os.PathLike, loaded: str | os.PathLike,
                       dest: str | os.PathLike, config: PipelineConfig, phase: str = "all",
                       prior: str | os.PathLike | None = None) -> Path:
    """Partition the polycube into hexes (at ``config``'s size: the source's own,
    :func:`polycubenet.policy.source_config`) and pull them back onto the part (canonical frame); a learned
    polycube as :func:`polycubenet.pipeline.pull_back_learned` does (the steps of ``config.learned_maps``: realised
    exactly, or through the refined map, when the registration's mesh would not end the chain; a realised mesh's
    file carries the realised polycube in its meta).  ``phase`` and ``prior`` (a ``"map"`` phase's file, for
    ``"rest"``): :func:`~polycubenet.pipeline.pull_back_learned`'s, for a learned polycube only."""
    from .registration import Correspondence

    from .pipeline import _pull_back_classical, own_diagonal, partition_polycube, pull_back_learned

    ext, ext_meta = _load_arrays(extracted)  # one read: the polycube, and the cleaned cloud with its anchors
    poly = _extracted_polycube(ext, ext_meta)
    anchored = (ext["points"], ext["normals"], ext["anchors"]) if "anchors" in ext else None
    part, sample, T, lmeta = read_loaded(loaded)
    diagonal = own_diagonal(part.vertices, T)
    arrays, _ = _load_arrays(corr)
    if all(k in arrays for k in _EXACT_MAP):  # classical: the same pullback as pipeline.mesh_surface
        return _pull_back_classical(partition_polycube(poly, config), _surface_map(arrays), part.vertices, part.faces,
                                    config, diagonal).save(dest)
    mesh, _ = pull_back_learned(poly, Correspondence.load(corr), part.vertices, part.faces, config, diagonal,
                                lmeta.get("name"), anchored=anchored, part_points=sample.points, phase=phase,
                                prior=None if prior is None else HexMesh.load(prior))
    return mesh.save(dest)


def meshed_polycube(hexc: str | os.PathLike, extracted: str | os.PathLike) -> Polycube:
    """The polycube a pull-back file was meshed on: the extracted one, or the one it was realised as (a
    learned polycube realised exactly, its thin slabs collapsed or the part's put back:
    :func:`polycubenet.pipeline.pull_back_learned`)."""
    m = HexMesh.load(hexc).meta
    if "realised_polycube" in m:
        return Polycube.from_meta(m["realised_polycube"])
    return read_extracted(extracted)[2]


def pullback_quality(path: str | os.PathLike) -> dict:
    """``valid``, ``sj_min``, ``deviation`` and ``hausdorff`` of a :func:`partition_pullback` file (what decides
    whether the flow tries the next polycube source), read from its metadata."""
    m = HexMesh.load(path).meta
    out = {"valid": bool(m.get("valid"))}
    for k in ("sj_min", "deviation", "hausdorff"):
        out[k] = None if m.get(k) is None else float(m[k])
    return out


@one_blas_thread
def report_export(hexc: str | os.PathLike, extracted: str | os.PathLike, loaded: str | os.PathLike,
                  out_dir: str | os.PathLike, formats=("vtu",), *, key: str | None = None, name: str | None = None) -> Path:
    """Mesh back to the part's own coordinates, quality report against the input surface,
    and the output files (``hex.<fmt>``, ``quality.json``/``.png``, ``preview.png``, ``deviation.png`` off the part,
    ``polycube.npz``, ``result.json`` last).  ``name`` names the part in ``result.json`` (default:
    the file name the loaded stage was made from; identical files share that stage).  Returns ``out_dir``."""
    from .quality import quality_report

    part, _, T, meta = read_loaded(loaded)
    _, _, _, cloud_meta = read_extracted(extracted)
    poly = meshed_polycube(hexc, extracted)
    mc = HexMesh.load(hexc)
    mesh = HexMesh(T.inverse(mc.points), mc.hexes, mc.boundary, meta=dict(mc.meta))
    Vo = T.inverse(part.vertices)
    res = PartResult(name=name or meta["name"], status="meshed", stage="export", part_meta=meta["part"], mesh=mesh,
                     polycube=poly, cloud=PolycubeCloud(np.zeros((0, 3)), np.zeros((0, 3)), meta=cloud_meta),
                     report=quality_report(mesh, surface=(Vo, part.faces)))
    out = Path(out_dir)
    # result.json is written last, once, with the stage key in it (PartResult.write): its presence
    # with this key marks a complete output; a kill before it leaves the stage to be redone
    (out / "result.json").unlink(missing_ok=True)
    res.write(out, formats=tuple(formats), extra={"key": key})
    return out


def _save_arrays(dest, meta: dict, **arrays) -> Path:
    meta_bytes = np.frombuffer(json.dumps(_plain(meta), sort_keys=True).encode(), dtype=np.uint8)
    return save_npz(dest, __meta__=meta_bytes, **arrays)


def _load_arrays(path) -> tuple[dict, dict]:
    arrays = load_npz(path)
    meta = arrays.pop("__meta__", None)
    return arrays, (json.loads(bytes(meta).decode()) if meta is not None else {})


# --------------------------------------------------------------------------- synthetic libraries


def write_synthetic_parts(out: str | os.PathLike, seeds: Iterable[int], *, scale: float = 100.0,
                          offset=(40.0, -15.0, 5.0), suffix: str = ".stl") -> list[Path]:
    """Write synthetic parts ``synth-<seed><suffix>`` (in mm: canonical shape × ``scale`` +
    ``offset``) with their ground-truth sidecars ``synth-<seed>.polycube.npz`` in the same
    file coordinates (:func:`polycubenet.synth.make_pair`; seeds >= 9000 are held out from
    training).  Existing files are kept.  Returns the part paths."""
    from .io import write_surface
    from .synth import make_pair

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    off = np.asarray(offset, float)
    paths = []
    for seed in seeds:
        path = out / f"synth-{seed}{suffix}"
        if not (path.is_file() and sidecar_path(path).is_file()):
            pair = make_pair(int(seed), n_cond=64, n_target=64)
            p = pair.polycube
            Polycube(p.xs * scale + off[0], p.ys * scale + off[1], p.zs * scale + off[2], p.occupancy,
                     meta={**p.meta, "seed": int(seed), "scale": scale, "offset": off.tolist()}).save(sidecar_path(path))
            write_surface(pair.shape_vertices * scale + off, pair.faces, path)
        paths.append(path)
    return paths


# --------------------------------------------------------------------------- manifest and report


def load_json(path: str | os.PathLike) -> dict:
    """A JSON file as a dict; ``{}`` when it does not exist."""
    p = Path(path)
    return json.loads(p.read_text()) if p.is_file() else {}


def read_manifest(out: str | os.PathLike) -> dict:
    """``<out>/manifest.json`` as a dict (``{"parts": [], ...}`` when there is none)."""
    p = Path(out) / MANIFEST
    if not p.is_file():
        return {"parts": []}
    return json.loads(p.read_text())


def merge_rows(old: list[dict], new: list[dict]) -> list[dict]:
    """Rows of ``old`` replaced by the rows of ``new`` for the same part path (new ones appended)."""
    by_path = {r["path"]: r for r in old}
    for r in new:
        by_path[r["path"]] = r
    return sorted(by_path.values(), key=lambda r: r["name"])


def write_manifest(out: str | os.PathLike, rows: list[dict], *, parameters: dict | None = None,
                   extra: dict | None = None) -> Path:
    """Write ``manifest.json``: the run's parameters, counts and one row per part."""
    counts = {s: sum(r["status"] == s for r in rows) for s in ("meshed", "failed")}
    body = {"updated": time.strftime("%Y-%m-%dT%H:%M:%S"), "counts": counts, "parameters": _plain(parameters or {}),
            **(extra or {}), "parts": rows}
    return write_json(Path(out) / MANIFEST, body)


def summary_rows(rows: list[dict]) -> list[dict]:
    """The summary table: one flat row per part, plain Python types (Prefect table artifacts)."""
    out = []
    for r in rows:
        q = r.get("quality") or {}
        out.append({
            "part": r["name"],
            "status": r["status"],
            "stage": r["stage"],
            "polycube": r.get("provenance") or "",
            "hexes": q.get("hexes") or 0,
            "sj_min": _round(q.get("sj_min")),
            "sj_avg": _round(q.get("sj_avg")),
            "hausdorff_pct": _round(None if q.get("hausdorff") is None else 100 * q["hausdorff"]),
            "valid": bool(q.get("valid")) if q else False,
            "seconds": round(float(sum((r.get("timings") or {}).values())), 2),
            "error": r.get("error") or "",
        })
    return out


def format_table(rows: list[dict]) -> str:
    """A plain-text table of :func:`summary_rows` (the CLI's final summary)."""
    if not rows:
        return "(no parts)"
    cols = ["part", "status", "stage", "polycube", "hexes", "sj_min", "sj_avg", "hausdorff_pct", "valid", "seconds", "error"]
    cells = [[("" if r[c] is None else str(r[c])) for c in cols] for r in rows]
    widths = [min(60, max(len(c), *(len(x[i]) for x in cells))) for i, c in enumerate(cols)]
    line = lambda xs: "  ".join(x[:w].ljust(w) for x, w in zip(xs, widths)).rstrip()  # noqa: E731
    return "\n".join([line(cols), line(["-" * w for w in widths])] + [line(x) for x in cells])


def quality_bar(manifest: dict) -> float | None:
    """The quality bar (``PipelineConfig.min_sj``) a manifest's run meshed at (None: none recorded)."""
    return ((manifest.get("parameters") or {}).get("config") or {}).get("min_sj")


def under_quality_bar(summary: dict, min_sj: float | None) -> bool:
    """Whether a :func:`summary_rows` row is a part meshed valid but under the quality bar ``min_sj``
    (:func:`polycubenet.policy.under_bar`; never with ``min_sj`` None)."""
    return summary["status"] == "meshed" and summary["valid"] and under_bar(summary, min_sj)


def off_part(summary: dict) -> bool:
    """Whether a :func:`summary_rows` row is a part meshed valid whose mesh is farther from the part than the
    Hausdorff bar (:func:`polycubenet.policy.faithful`, :data:`polycubenet.tol.HAUSDORFF_REL_MAX` of the diagonal):
    the best mesh any source gave, kept, but not the part's shape.  A row without the measure is not marked."""
    pct = summary.get("hausdorff_pct")
    return (summary["status"] == "meshed" and summary["valid"] and pct is not None
            and not faithful({"hausdorff": pct / 100.0}))


def flagged_counts(summary: list[dict], min_sj: float | None) -> str:
    """The parts meshed valid but short of a bar, as the report and the command line say them: those under the
    quality bar ``min_sj`` (:func:`under_quality_bar`) and those off the part (:func:`off_part`); "" when none."""
    n_under = sum(under_quality_bar(s, min_sj) for s in summary)
    n_off = sum(off_part(s) for s in summary)
    said = []
    if n_under:
        said.append(f"{n_under} valid but under the quality bar (SJ min < {min_sj:g})")
    if n_off:
        said.append(f"{n_off} valid but off the part (Hausdorff > {100 * tol.HAUSDORFF_REL_MAX:g} % of the diagonal)")
    return ", ".join(said)


def write_report_html(out: str | os.PathLike, rows: list[dict], *, title: str = "PolycubeNet meshing report",
                      min_sj: float | None = None) -> Path:
    """``<out>/report.html``: counts, a table (status, polycube, quality, time, error) and the
    pictures of every meshed part (relative links to ``<part>/preview.png``, ``quality.png``, and ``deviation.png``
    for a mesh off the part).  A part meshed
    valid but under the quality bar ``min_sj`` or off the part (:func:`flagged_counts`) is marked as a meshed part
    not valid is, and counted; each part's quality warnings (``quality.json``) head its section."""
    out = Path(out)
    esc = html.escape
    n_ok = sum(r["status"] == "meshed" for r in rows)
    summary = summary_rows(rows)
    flagged = flagged_counts(summary, min_sj)
    under = f" Meshed short of a bar: {flagged}." if flagged else ""
    head = ("<th>part</th><th>status</th><th>stage</th><th>polycube</th><th>hexes</th><th>SJ min</th><th>SJ avg</th>"
            "<th>Hausdorff %</th><th>valid</th><th>time s</th><th>error</th>")
    body = []
    for s in summary:
        good = s["status"] == "meshed" and s["valid"] and not under_quality_bar(s, min_sj) and not off_part(s)
        cls = "ok" if good else ("warn" if s["status"] == "meshed" else "bad")
        body.append(
            f"<tr class='{cls}'><td><a href='#{esc(s['part'])}'>{esc(s['part'])}</a></td><td>{esc(s['status'])}</td>"
            f"<td>{esc(s['stage'])}</td><td>{esc(s['polycube'])}</td><td>{s['hexes']}</td><td>{_fmt(s['sj_min'])}</td>"
            f"<td>{_fmt(s['sj_avg'])}</td><td>{_fmt(s['hausdorff_pct'])}</td><td>{'yes' if s['valid'] else 'no'}</td>"
            f"<td>{s['seconds']}</td><td>{esc(s['error'])}</td></tr>")
    cards = []
    for r in rows:
        if r["status"] != "meshed":
            continue
        d = r["name"]
        pics = "".join(f"<img src='{esc(d)}/{p}' alt='{p}'>" for p in ("preview.png", "quality.png", "deviation.png")
                       if (out / d / p).is_file())
        files = " ".join(f"<a href='{esc(d)}/{esc(f)}'>{esc(f)}</a>" for f in r.get("files", []))
        said = "".join(f"<li>{esc(w)}</li>" for w in ((r.get("quality") or {}).get("warnings") or []))
        said = f"<ul class='warn'>{said}</ul>" if said else ""
        cards.append(f"<section id='{esc(d)}'><h3>{esc(d)}</h3>{said}<p>{files}</p>{pics}</section>")
    doc = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>{esc(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; }} table {{ border-collapse: collapse; }}
td, th {{ border: 1px solid #ccc; padding: 3px 8px; font-size: 13px; }} tr.bad {{ background: #fdd; }}
tr.warn {{ background: #ffd; }} ul.warn {{ background: #ffd; }} section img {{ max-width: 480px; margin-right: 1em; }}
</style></head><body>
<h1>{esc(title)}</h1>
<p>{len(rows)} parts: {n_ok} meshed, {len(rows) - n_ok} failed.{under} Generated {time.strftime('%Y-%m-%d %H:%M:%S')}.</p>
<table><tr>{head}</tr>
{chr(10).join(body)}
</table>
<h2>Parts</h2>
{chr(10).join(cards)}
</body></html>
"""
    return write_text(out / REPORT, doc)


def _round(x, nd: int = 4):
    return None if x is None else round(float(x), nd)


def _fmt(x) -> str:
    return "" if x is None else f"{x:.3f}"


def thumbnail_data_uri(png: str | os.PathLike, width: int = 360) -> str | None:
    """A small JPEG of a picture as a ``data:`` URI (to embed in a markdown artifact), or None."""
    try:
        import base64
        import io

        from PIL import Image

        with Image.open(png) as im:
            im = im.convert("RGB")
            im.thumbnail((width, width))
            buf = io.BytesIO()
            im.save(buf, format="JPEG", quality=70)
        return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode()
    except (OSError, ImportError, ValueError):
        return None


__all__ = [
    "PART_SUFFIXES", "HEX_FORMATS", "STAGES", "discover", "part_names", "file_hash", "stable_hash", "stage_key",
    "stage_params", "chain_keys", "stage_path", "sweep_partials", "sidecar_path", "polycube_to_frame",
    "SidecarOracle", "classical_available", "make_source", "source_extra", "load_sample", "read_loaded",
    "polycube_cloud", "write_generated", "cleanup_extract", "read_extracted", "register", "partition_pullback",
    "pullback_quality", "report_export", "write_synthetic_parts", "read_manifest", "merge_rows", "write_manifest", "summary_rows",
    "format_table", "load_json", "write_report_html", "quality_bar", "under_quality_bar", "thumbnail_data_uri",
]
