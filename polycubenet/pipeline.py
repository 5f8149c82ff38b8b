"""The whole spine for one part: ``mesh_part(path, source, config) -> PartResult``.

load → canonical frame → Poisson-disk sample → polycube cloud (from an injected
*source*) → outlier filter → rigid + CPD registration → structure extraction →
regular partition → pullback (projection, harmonic interior, untangling and
optimisation, pillowing, smoothing) → back to the part's own coordinates → quality
report.  Runnable with no orchestrator; ``tasks/`` wraps the same stages one by one.

A *polycube source* is any callable ``source(sample, V, F, config) -> PolycubeCloud``
in the part's canonical frame:

* :class:`OracleSource` -- the ground-truth polycube of a synthetic pair, sampled and
  corrupted with noise and outliers (proves every stage before a model exists);
* the learned model (``polycubenet.inference``) plugs in the same way;
* the classical construction (:class:`polycubenet.classical.ClassicalSource`) builds the
  polycube from the surface itself; its cloud carries the exact map polycube -> part
  (``cloud.correspondence()``), which then replaces registration.

A generated (learned or oracle) polycube is pulled back through the registration's map; when that
mesh would not end the chain (not valid, off the part, under the quality bar), the same structure is
also realised exactly on the part (:mod:`polycubenet.realise`: labels transferred through the
registration, the classical deformation, the same cells or nothing) and the better mesh kept
(:func:`pull_back_learned`; ``meta["map"]`` and the manifest's ``map`` say which).  A valid mesh of any
source that is off the part only at a few spots gets them mended (:func:`polycubenet.pullback.mend_spots`,
``meta["spots"]``); a learned polycube's map mesh only after its realisation was tried, which is better where
it applies.

**Hybrid policy** (``PipelineConfig.polycube``): the sources of :func:`source_chain` are
tried in order.

* ``"learned"`` -- the injected source alone (a failed polycube is final for the part);
* ``"classical"`` -- the classical polycube (the injected source is not called), then, as a
  last resort, the voxel polycube (:mod:`polycubenet.voxel`: the cells of a grid inside the
  part, which exists for every closed part but follows its features less well);
* ``"voxel"`` -- the voxel polycube alone;
* ``"auto"`` -- the injected source first, then the classical chain.

A source is left for the next one when it raises
:class:`~polycubenet.errors.PolycubeError`, when its polycube fails validation at
extraction (not a closed manifold solid, genus different from the part's, cloud far
from the polycube, surface not covered), or when its pulled-back hex mesh is not valid
(an inverted or degenerate hex).  The first valid mesh is kept; when none is, the mesh
with the highest minimum scaled Jacobian (reported as not valid).
``PartResult.provenance`` says which polycube was used and ``PartResult.fallback_reason``
why the ones before it were left (``"<stage>: <reason>"``, joined by ``"; "``); both go to
the manifest row and ``quality.json``.

Errors: a :class:`~polycubenet.errors.PartError` (bad input) or
:class:`~polycubenet.errors.PolycubeError` (the polycube failed validation) propagates
with the stage recorded in ``exc.stage``; :func:`mesh_part_safe` turns them into a
failed :class:`PartResult` so a batch goes on.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from .atomic import write_json
from .classical import ClassicalConfig, ClassicalSource
from .cleanup import remove_outliers
from .data import HexMesh, Part, Polycube, PolycubeCloud, SurfaceSample
from .errors import PartError, PolycubeError
from .frame import Transform, canonicalize
from .hexmesh import partition
from .polycube import polycube_surface
from .policy import MODES as POLYCUBE_MODES
from .policy import near_miss as policy_near_miss
from .policy import DENSER_HEXES, Attempt, denser_config, distance_to_part, ends_chain, error_reason, extraction_config, invalid_mesh_reason, mesh_rank, refinement, run_chain, source_config, source_label, source_names  # noqa: F401
from .pullback import PullbackConfig, mend_spots, pull_back, worth_retry
from .quality import QualityReport, quality_report
from .realise import RealiseConfig, learned_map
from .realise import variants as realise_variants
from .registration import align
from .sampling import poisson_disk, uniform_sample
from .structure import ExtractConfig, check_genus, extract
from .threads import one_blas_thread
from .voxel import VoxelConfig


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Parameters of :func:`mesh_part`.

    Attributes
    ----------
    n_sample : points on the part (the model's condition and the registration target)
    n_polycube : points of the classical and voxel polycube clouds
    n_learned : points the model generates for the learned polycube (its cost is linear in
        them, benchmarks/bench_inference.py; 4096 resolve the structure of CAD-like parts)
    n_register : polycube points used by CPD (a random subset; the field is evaluable anywhere)
    target_hexes : approximate hex count (``target_size`` wins when set)
    target_size : element edge length relative to the part's bounding-box diagonal
    seed : every random choice of the run derives from it
    polycube : ``"learned"``, ``"classical"``, ``"voxel"`` or ``"auto"`` (see the module
        docstring); ``"learned"`` by default so an injected source is used exactly as given
    classical, voxel : the settings of the classical and voxel polycubes
    min_sj : a valid mesh with a lower minimum scaled Jacobian does not end the chain: the
        next polycube source is tried and the better mesh kept (:mod:`polycubenet.policy`;
        None: any valid mesh ends it)
    learned_maps : the steps a learned polycube is pulled back through, in order, each only while the meshes
        before do not end the chain (:func:`pull_back_learned`): the maps ``"registration"`` (rigid + CPD,
        :func:`polycubenet.registration.align`), ``"refined"`` (a second, finer CPD field after the
        registration's, :func:`polycubenet.registration.refine`) and ``"anchors"`` (an anchored model's own
        correspondences, :mod:`polycubenet.anchormap`), and ``"exact"``, the realisation (``realise``; last
        when not named).  The default is the registration, then the realisation, then the refined map
        (session 42, the learned source alone on the dev sets machined 61 + 67, which no reported figure
        uses: 21 -> 23 of 32, +2 -0, the examples 10 of 10 as before; before the realisation it meshes the
        same parts but takes a realised part's exact mesh, machined_61_009 min SJ 0.381 -> 0.308).  With the
        anchors as well, before or after the registration, the dev sets meshed the same 17 of 32 parts
        (session 26, MODEL_CARD "The model's own map"), so they are an option, not the default
    snap_planes : None (the default: never), or a learned cloud's points on each planar face of the part
        tilted at least this many degrees from its label's axis are moved onto one plane before the
        extraction (:func:`polycubenet.planesnap.snap_planes`; needs an anchored model that takes the part's
        normals).  The model leaves a slanted end as a ramp that the extraction cuts into a staircase; the
        snap removes the ramp but not the parts' other structure errors, and meshed no more never-seen
        parts (session 33, at 5 degrees, the learned source alone: dev machined seeds 61 and 67 with the
        65.27 h continue file 18 -> 20 of 32, +3 -1; machined 11, 31, 53, 103 with the shipped file 35 -> 35
        of 64, +3 -3; mixed 11 and 31 15 -> 15 of 32; at 0 degrees, the axis-aligned faces too, seed 67 alone
        11 -> 9), so it is an option, not the default
    """

    n_sample: int = 4096
    n_polycube: int = 16384
    n_learned: int = 4096
    n_register: int = 4096
    target_hexes: int | None = 5000
    target_size: float | None = None
    seed: int = 0
    extract: ExtractConfig = ExtractConfig()
    pullback: PullbackConfig = PullbackConfig()
    polycube: str = "learned"
    classical: ClassicalConfig = ClassicalConfig()
    voxel: VoxelConfig = VoxelConfig()
    min_sj: float | None = 0.2
    realise: RealiseConfig | None = RealiseConfig()
    learned_maps: tuple[str, ...] = ("registration", "exact", "refined")
    snap_planes: float | None = None

    def __post_init__(self):
        # the pull-back eases a mesh under the chain's own quality bar (pullback.ease_poor_hexes): a run with
        # another min_sj eases at that bar, not at the pull-back's standalone default; with min_sj None (any
        # valid mesh ends the chain) the pull-back's own ease_below stands
        if self.min_sj is not None and self.pullback.ease_below != self.min_sj:
            object.__setattr__(self, "pullback", dataclasses.replace(self.pullback, ease_below=float(self.min_sj)))


#: the values of ``PipelineConfig.polycube`` (and of the command-line ``--polycube``): ``policy.MODES``


def source_chain(source, config: PipelineConfig) -> list[tuple[str, Callable]]:
    """The polycube sources :func:`mesh_surface` tries in order, as ``(name, source)``
    (the order is :func:`polycubenet.policy.source_names`'s).

    ``learned``: the injected source alone (the classical chain when it is None);
    ``classical``: the surface-flattening construction, then the voxel polycube;
    ``voxel``: the voxel polycube alone; ``auto``: the injected source, then the classical chain;
    the voxel polycube is followed by its refinements (``voxel+1``, ...), and an injected source
    with ``further_draws()`` / ``draw_source(k)`` (:class:`polycubenet.inference.ModelSource`) by
    those draws (``learned+1``, ...).
    """
    from .voxel import VoxelSource

    if config.polycube not in POLYCUBE_MODES:
        raise ValueError(f"polycube must be one of {POLYCUBE_MODES}; got {config.polycube!r}")
    mode = "classical" if source is None and config.polycube in ("learned", "auto") else config.polycube
    # the model's further draws, when the injected source has them (policy.learned_draws)
    further = getattr(source, "further_draws", None)
    draws = tuple(further()) if callable(further) and mode in ("learned", "auto") else ()

    def make(name: str):
        base, k = refinement(name)
        if base == "voxel":
            return VoxelSource(config.voxel, refine=k)
        if base == "learned" and k:
            return source.draw_source(k)
        return {"learned": source, "classical": ClassicalSource(config.classical)}[name]

    return [(name, make(name)) for name in source_names(mode, draws=draws)]


class PolycubeSource(Protocol):
    def __call__(self, sample: SurfaceSample, V: np.ndarray, F: np.ndarray, config: PipelineConfig) -> PolycubeCloud: ...


@dataclasses.dataclass
class OracleSource:
    """A known polycube (grid + occupancy, canonical frame) as a noisy cloud: the stand-in
    for the model on synthetic pairs.

    ``noise`` is the Gaussian sigma and ``outliers`` the fraction of uniform outliers in
    the bounding box (with random normals), both relative to the diagonal (1).
    """

    polycube: Polycube
    noise: float = 0.005
    outliers: float = 0.02

    def __call__(self, sample, V, F, config: PipelineConfig) -> PolycubeCloud:
        p = self.polycube
        Vp, Fp = polycube_surface(p.xs, p.ys, p.zs, p.occupancy)
        s = poisson_disk(Vp, Fp, config.n_polycube, seed=config.seed + 17)
        rng = np.random.default_rng(config.seed + 23)
        P = s.points + rng.normal(scale=self.noise, size=s.points.shape)
        N = s.normals.copy()
        k = int(round(self.outliers * len(P)))
        if k:
            lo, hi = P.min(axis=0), P.max(axis=0)
            N_out = rng.normal(size=(k, 3))
            P = np.vstack([P, rng.uniform(lo, hi, size=(k, 3))])
            N = np.vstack([N, N_out / np.linalg.norm(N_out, axis=1, keepdims=True)])
        return PolycubeCloud(P, N, meta={"provenance": "oracle", "noise": self.noise, "outliers": self.outliers})


@dataclasses.dataclass
class PartResult:
    """What :func:`mesh_part` produced for one part (``status`` is ``"meshed"`` or ``"failed"``)."""

    name: str
    status: str
    stage: str
    error: str | None = None
    timings: dict = dataclasses.field(default_factory=dict)
    part_meta: dict = dataclasses.field(default_factory=dict)
    mesh: HexMesh | None = None
    polycube: Polycube | None = None
    cloud: PolycubeCloud | None = None
    transform: Transform | None = None
    report: QualityReport | None = None
    surface: tuple[np.ndarray, np.ndarray] | None = None
    provenance: str | None = None
    fallback_reason: str | None = None
    #: the source whose mesh was kept (``"learned"``, ``"learned+2"``, ``"voxel+1"``, ...: policy.source_names)
    source: str | None = None

    def row(self) -> dict:
        """One manifest row (plain types)."""
        q = self.report.to_dict() if self.report is not None else {}
        return {
            "part": self.name,
            "status": self.status,
            "stage": self.stage,
            "error": self.error,
            "timings": {k: round(v, 4) for k, v in self.timings.items()},
            "genus": self.part_meta.get("genus"),
            # a knife edge (far above 90) is where polycube hex meshes struggle: io.sharpest_convex_edge_deg
            "sharpest_edge_deg": None if (e := self.part_meta.get("sharpest_edge_deg")) is None else round(float(e), 1),
            "provenance": self.provenance or (self.cloud.meta.get("provenance") if self.cloud is not None else None),
            "fallback_reason": self.fallback_reason,
            # a learned polycube: pulled back by its exact realisation or by the registration (polycubenet.realise)
            "map": self.mesh.meta.get("map") if self.mesh is not None else None,
            "hexes": q.get("hex_count"),
            "sj_min": q.get("sj_min"),
            "sj_avg": q.get("sj_avg"),
            "valid": q.get("valid"),
            "hausdorff": (q.get("surface") or {}).get("hausdorff"),
            # poor hexes untangled with some surface nodes left off the surface (pullback.ease_poor_hexes)
            "eased": _eased_summary(self.mesh.meta.get("eased") if self.mesh is not None else None),
        }

    def write(self, out_dir: str | Path, formats: tuple[str, ...] = ("vtu",), extra: dict | None = None) -> Path:
        """Write the mesh in ``formats``, ``polycube.npz``, ``quality.*`` and ``result.json`` under ``out_dir``.

        ``result.json`` is written last and once (``extra`` merged into its row), so its presence
        with a given content marks an output that is complete with that content."""
        from .io import write_hex

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        if self.mesh is not None:
            for fmt in formats:
                fmt = fmt.lstrip(".")
                keeps_cells = fmt in ("vtu", "vtk", "msh") and self.report is not None
                cell = {"scaled_jacobian": self.report.sj} if keeps_cells else None
                write_hex(self.mesh, out / f"hex.{fmt}", cell_data=cell)
        if self.polycube is not None:
            self.polycube.save(out / "polycube.npz")
        if self.report is not None:
            self.report.write(out)
            _add_provenance(out / "quality.json", self.row())
        write_json(out / "result.json", {**self.row(), **(extra or {})})
        return out


def _eased_summary(eased: dict | None) -> dict | None:
    """What the manifest says of a kept easing (:func:`polycubenet.pullback.ease_poor_hexes`): the hexes eased,
    the surface nodes among the moved ones, and how far the farthest was left off the surface (relative to the
    part's diagonal); None when none was kept."""
    if not eased or not eased.get("kept"):
        return None
    return {"hexes": eased["hexes"], "surface_nodes": eased["surface_nodes"],
            "off_surface_max": round(float(eased["off_surface_max"]), 6)}


class _Clock:
    def __init__(self, timings: dict):
        self.timings = timings
        self.tracker = None  # a policy.StageTracker to keep informed of the stage

    def __call__(self, name: str):
        clock = self

        class _Ctx:
            def __enter__(self):
                self.t0 = time.perf_counter()
                clock.stage = name
                if clock.tracker is not None:
                    clock.tracker.stage = name

            def __exit__(self, *exc):
                clock.timings[name] = time.perf_counter() - self.t0
                return False

        return _Ctx()


@one_blas_thread
def mesh_surface(
    V: np.ndarray,
    F: np.ndarray,
    source: PolycubeSource | Callable,
    config: PipelineConfig = PipelineConfig(),
    *,
    name: str = "part",
    part_meta: dict | None = None,
    canonical: bool = False,
) -> PartResult:
    """The spine on a validated surface ``(V, F)`` (see the module docstring).

    ``canonical=True`` says ``V`` is already in the canonical frame (synthetic pairs),
    so the frame stage is the identity.  Raises PartError / PolycubeError with
    ``exc.stage`` set.
    """
    timings: dict = {}
    clock = _Clock(timings)
    res = PartResult(name=name, status="failed", stage="frame", timings=timings, part_meta=dict(part_meta or {}))
    try:
        with clock("frame"):
            if canonical:
                Vc, T = np.asarray(V, float), Transform.identity()
            else:
                Vc, T = canonicalize(V, F)
        res.transform = T
        genus = res.part_meta.get("genus")
        with clock("sample"):
            sample = poisson_disk(Vc, F, config.n_sample, seed=config.seed)
        chain = dict(source_chain(source, config))

        def attempt(label: str, tracker) -> Attempt:
            clock.timings, clock.tracker = tracker.seconds, tracker
            cloud, P, N, A, poly = _polycube_stages(chain[label], sample, Vc, F, genus, extraction_config(label, config),
                                                    name, clock, res)
            with clock("register"):
                if hasattr(cloud, "correspondence"):  # classical and voxel polycubes know their map exactly
                    corr = cloud.correspondence()
                else:
                    corr = register_cloud(sample, P, N, config)
            cfg = source_config(label, config)
            with clock("partition"):
                mesh_pc = partition_polycube(poly, cfg)
            learned = not hasattr(cloud, "correspondence")
            split = learned and learned_phases(cfg)
            diagonal = own_diagonal(Vc, T)
            kw = dict(anchored=None if A is None else (P, N, A), part_points=sample.points)
            with clock("pullback"):
                if not learned:
                    mesh_c = _pull_back_classical(mesh_pc, corr, Vc, F, config, diagonal)
                else:
                    mesh_c, poly = pull_back_learned(poly, corr, Vc, F, cfg, diagonal, name, mesh_pc,
                                                     phase="map" if split else "all", **kw)
            att = Attempt(label, dict(mesh_c.meta), payload=(cloud, poly, mesh_c), seconds=dict(tracker.seconds),
                          label=source_label(label))
            if split:  # the policy decides when the draw's further pull-back steps run (policy.run_chain)
                def rest(prior=mesh_c, poly=poly) -> Attempt:
                    t0 = time.perf_counter()
                    m, used = pull_back_learned(poly, corr, Vc, F, cfg, diagonal, name, mesh_pc, phase="rest",
                                                prior=prior, **kw)
                    seconds = {**att.seconds, "pullback": att.seconds.get("pullback", 0.0) + time.perf_counter() - t0}
                    return Attempt(label, dict(m.meta), payload=(cloud, used, m), seconds=seconds,
                                   label=source_label(label))

                att.rest = rest
            return att

        outcome = run_chain(list(chain), attempt, min_sj=config.min_sj)
        clock.timings, clock.tracker = timings, None
        if outcome.chosen is None:
            exc = outcome.error
            exc.fallback_reason = outcome.fallback_reason
            clock.stage = exc.stage
            if not isinstance(exc, (PartError, PolycubeError)):  # the learned source alone failed otherwise
                err = PolycubeError(f"{exc.source} polycube failed at {exc.stage}: {error_reason(exc)}", name)
                err.fallback_reason = outcome.fallback_reason
                raise err from exc
            raise exc
        cloud, poly, mesh_c = outcome.chosen.payload
        # the kept attempt's timings under their own names, the others' as rejected_<stage>
        for k, v in outcome.chosen.seconds.items():
            timings[k] = timings.get(k, 0.0) + v
        for k, v in outcome.rejected_seconds.items():
            timings["rejected_" + k] = timings.get("rejected_" + k, 0.0) + v
        res.cloud, res.polycube = cloud, poly
        res.provenance = cloud.meta.get("provenance")
        res.fallback_reason = outcome.fallback_reason
        res.source = outcome.chosen.source
        with clock("report"):
            mesh = HexMesh(T.inverse(mesh_c.points), mesh_c.hexes, mesh_c.boundary, meta=dict(mesh_c.meta))
            Vo = np.asarray(V, float) if not canonical else Vc
            res.report = quality_report(mesh, surface=(Vo, F))
        res.mesh = mesh
        res.surface = (Vo, np.asarray(F))
        res.status, res.stage = "meshed", "report"
    except (PartError, PolycubeError) as exc:
        exc.stage = getattr(clock, "stage", "frame")
        res.stage = exc.stage
        raise
    return res


def _polycube_stages(source, sample, Vc, F, genus, config, name, clock, res):
    """Polycube cloud -> outlier filter -> structure extraction (validated) for one source."""
    with clock("polycube"):
        cloud = source(sample, Vc, F, config)
    res.cloud = cloud
    with clock("cleanup"):
        P, N, keep = clean_cloud(cloud, config)
    with clock("extract"):
        poly = cloud_polycube(cloud, P, N, genus, config, name)
    res.polycube = poly
    A = None if getattr(cloud, "anchors", None) is None else np.asarray(cloud.anchors, float)[keep]
    return cloud, P, N, A, poly


def register_cloud(sample: SurfaceSample, P: np.ndarray, N: np.ndarray, config: PipelineConfig):
    """The registration of a generated cloud's filtered points ``(P, N)`` onto the part's samples (both drivers
    call this): rigid + CPD (:func:`polycubenet.registration.align`) on ``config.n_register`` of the points,
    drawn with the run's seed."""
    rng = np.random.default_rng(config.seed + 5)
    sub = rng.choice(len(P), size=min(config.n_register, len(P)), replace=False)
    return align(sample, P[sub], N[sub])


def clean_cloud(cloud: PolycubeCloud, config: PipelineConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A source's cloud as it goes to the extraction (both drivers call this): the outlier filter
    (:func:`~polycubenet.cleanup.remove_outliers`: points, normals, keep mask), then for a learned cloud
    that carries its anchors' normals and with ``config.snap_planes`` set, each tilted planar face of the
    part on one plane (:func:`polycubenet.planesnap.snap_planes`; counts in ``cloud.meta["snapped"]``)."""
    P, N, keep = remove_outliers(cloud.points, cloud.normals)
    an = getattr(cloud, "anchor_normals", None)
    if config.snap_planes is not None and an is not None and cloud.meta.get("provenance") == "learned":
        from .planesnap import snap_planes

        P, cloud.meta["snapped"] = snap_planes(P, N, np.asarray(cloud.anchors, float)[keep],
                                               np.asarray(an, float)[keep], min_deg=config.snap_planes)
    return P, N, keep


def partition_polycube(poly: Polycube, config: PipelineConfig):
    """The polycube's regular hex partition at ``config``'s hex size or count (both drivers call this)."""
    if config.target_size is not None:
        return partition(poly, target_size=config.target_size)
    return partition(poly, target_hexes=config.target_hexes)


def cloud_polycube(cloud: PolycubeCloud, P: np.ndarray, N: np.ndarray, genus: int | None, config: PipelineConfig,
                   name: str | None = None) -> Polycube:
    """The explicit polycube of a source's cloud (both drivers call this): the solid the source
    built it from when the cloud carries it (the voxel polycube, ``ClassicalCloud.exact_polycube``),
    checked to be a valid polycube of the part's genus; otherwise the structure extraction of the
    filtered cloud ``(P, N)``.  A generated (learned) cloud is always extracted, and only it with the
    extraction's fallbacks for generated clouds.  Raises
    :class:`~polycubenet.errors.PolycubeError`."""
    from .polycube import check_occupancy, compress, solid_genus

    exact = cloud.exact_polycube() if hasattr(cloud, "exact_polycube") else None
    if cloud.meta.get("provenance") == "learned":
        poly = extract(P, N, genus=genus, config=config.extract, part=name)
    elif exact is None:  # the classical flattening's cloud: no generator fallbacks (ExtractConfig.for_exact_clouds)
        poly = extract(P, N, genus=genus, config=config.extract.for_exact_clouds(), part=name)
    else:
        grid, occ = compress([exact.xs, exact.ys, exact.zs], exact.occupancy)
        reason = check_occupancy(occ)
        if reason is not None:
            raise PolycubeError(f"the {cloud.meta.get('provenance')} solid is not a valid polycube: {reason}", name)
        g = int(solid_genus(occ))
        check_genus(g, genus, name)
        poly = Polycube(grid[0], grid[1], grid[2], occ, meta={"genus": g, "grid_shape": list(occ.shape), "exact": True})
    poly.meta["provenance"] = cloud.meta.get("provenance")
    return poly


def pull_back_learned(poly: Polycube, corr, Vc: np.ndarray, F: np.ndarray, config: PipelineConfig,
                      diagonal: float | None = None, part: str | None = None,
                      partitioned: HexMesh | None = None,
                      anchored: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                      part_points: np.ndarray | None = None, phase: str = "all",
                      prior: HexMesh | None = None) -> tuple[HexMesh, Polycube]:
    """A learned polycube's partition and pull-back (both drivers call this): through the steps of
    ``config.learned_maps`` in turn until one mesh ends the chain (:func:`polycubenet.policy.ends_chain`: valid,
    on the part, not under the bar), the best mesh (:func:`polycubenet.policy.mesh_rank`) and its polycube kept.
    A step is a map of the learned polycube onto the part (the registration's, ``corr``; ``refined``, a finer
    field after it; the model's own, from ``anchored`` = the cleaned cloud's points, normals and anchors), or
    ``exact``: the polycube realised exactly on the part (:func:`polycubenet.realise.learned_map`: the same
    structure, the classical deformation's exact map), with each labelling of
    :func:`polycubenet.realise.variants` in turn until a mesh ends the chain, the next labelling only after one
    that realised the structure (its mesh under the bar or off the part: session 15's mixed_11_002), never after one
    whose flattened part does not bound it (session 56, the 114.15 h file on the examples and the never-seen turned 5
    and machined 103 parts: in all 24 realisations where the first labelling did not bound it, the second did not
    either, at 5-7 s each; ``benchmarks/results/s56_learned_order_C114_*.json``);
    ``exact`` runs last when
    ``learned_maps`` does not name it, never when ``config.realise`` is None.  ``refined`` is fitted only after a
    near miss (:func:`near_miss`), any mesh so far, not only the best one.  A best mesh that is then still a
    near miss off the part (:func:`denser_worth`), also after its spots are mended
    (:func:`polycubenet.pullback.mend_spots`), is pulled back once more through the same map at
    :data:`~polycubenet.policy.DENSER_HEXES` times the hexes (``map``: ``"<map>, <DENSER_HEXES>x hexes"``).  ``meta["map"]`` says which step
    made the mesh (and why the realisation did not).  ``partitioned``: ``poly``'s partition when the caller
    made it already; ``part_points``: the part's samples the registration was fitted to (the refined map's
    target; drawn again as the pipeline draws them when not given).

    ``phase`` splits the same work in two calls (a policy may put other work between them): ``"map"`` runs the
    first step alone (a map: the registration by default), as it is, without mending its spots; ``"rest"``, given
    that mesh as ``prior``, runs every later step and the mend and denser pull-back after them.  The two calls give
    exactly what one call (``"all"``) gives: the first step's mesh when it ends the chain, else the rest's."""
    if phase not in ("all", "map", "rest"):
        raise ValueError(f"phase must be 'all', 'map' or 'rest'; got {phase!r}")
    if (phase == "rest") != (prior is not None):
        raise ValueError("a prior mesh goes with phase 'rest', and only with it")
    mesh_pc = partition_polycube(poly, config) if partitioned is None else partitioned
    steps = [n for n in config.learned_maps if n != "exact" or config.realise is not None]
    if config.realise is not None and "exact" not in steps:
        steps.append("exact")
    maps = dict(_learned_maps(poly, corr, anchored, [n for n in config.learned_maps if n != "exact"],
                              part_points=lambda: part_points if part_points is not None else
                              poisson_disk(Vc, F, config.n_sample, seed=config.seed).points))
    if not any(n in maps for n in steps):  # only the anchors asked for, and the cloud has none: the registration
        first = next(i for i, n in enumerate(steps) if n != "exact")
        steps[first] = "registration"
    best, used, why_not, cache = None, poly, [], {}
    unmended = dataclasses.replace(config.pullback, capture_spots=False)
    # any mesh so far a near miss, not only the best: a realised mesh far off the part but above the quality bar
    # outranks a closer map's mesh under it, and must not close the refined map's gate (never-seen mixed_1163_002,
    # session 87: the registration's mesh 1.00 % off at SJ 0.09, the realised one 4.45 % off at 0.30, the refined
    # map's 0.84 % off at 0.24)
    near = False

    def keep(m: HexMesh, polycube: Polycube, tie_wins: bool = False) -> bool:
        """Keep ``m`` when it ranks above the best so far; True when it ends the chain."""
        nonlocal best, used, near
        near = near or near_miss(m)
        if best is None:
            best, used = m, polycube
        else:
            rank, kept = mesh_rank(m.meta, config.min_sj), mesh_rank(best.meta, config.min_sj)
            if rank > kept or (tie_wins and rank == kept):
                best, used = m, polycube
        return ends_chain(m.meta, config.min_sj)

    if phase != "all" and (steps[0] in ("exact", "refined") or steps[0] not in maps):
        raise ValueError(f"phase {phase!r} needs a map as the first of learned_maps; got {steps[0]!r}")
    if phase == "map":
        steps = steps[:1]
    elif phase == "rest":
        keep(prior, poly)
        steps = steps[1:]
    for step in steps:
        if step != "exact":
            if step not in maps:  # a map this polycube does not have (anchors of a cloud without them)
                continue
            if step == "refined" and not near:
                continue
            # its spots are mended only when no later step ends the chain (below): a realised mesh is better
            m = pull_back(mesh_pc, maps[step], Vc, F, unmended, diagonal)
            m.meta["map"] = step
            if keep(m, poly) or phase == "map":
                return m, poly
            continue
        for rc in realise_variants(config.realise):
            exact, why = learned_map(Vc, F, poly, corr, rc, seed=config.seed, part=part, cache=cache)
            if exact is None:  # the part does not flatten onto this structure: another labelling of it is not tried
                why_not.append(why)
                break
            realised = _pull_back_classical(partition_polycube(exact.polycube, config), exact.map, Vc, F, config,
                                            diagonal, retry_below=config.min_sj)
            own = exact.map.meta.get("structure", "learned") != "learned"
            realised.meta["map"] = "exact (realised, the part's structure)" if own else "exact (realised)"
            realised.meta["realised"] = {k: v for k, v in exact.map.meta.items() if k != "method"}
            realised.meta["realised"]["planar_patches"] = rc.planar_patches
            realised.meta["realised_polycube"] = exact.polycube.to_meta()
            # a tie with a map's mesh: the exact map
            if keep(realised, exact.polycube, tie_wins=best is not None and "realised" not in best.meta):
                return realised, exact.polycube
    if config.pullback.capture_spots and "realised" not in best.meta:  # a realised mesh was mended already
        best = mend_spots(best, Vc, F, config.pullback, diagonal)
    if denser_worth(best, maps):
        # still off after the mend: the same polycube and map, a finer partition (on round parts the near miss is
        # the partition's), its spots mended too
        step = best.meta["map"]
        m = pull_back(partition_polycube(used, denser_config(config)), maps[step], Vc, F, unmended, diagonal)
        m.meta["map"] = f"{step}, {DENSER_HEXES:g}x hexes"
        if config.pullback.capture_spots:
            m = mend_spots(m, Vc, F, config.pullback, diagonal)
        if keep(m, used):
            return m, used
    if "realised" not in best.meta and "exact" in steps:
        why = "; ".join(why_not) if why_not else "its mesh ranks above the realised ones"
        best.meta["map"] = f"{best.meta['map']} ({why})"
    return best, used


def learned_phases(config: PipelineConfig) -> bool:
    """Whether a learned draw's pull-back runs as two calls, its registration map's mesh first and the rest when
    the policy says (:func:`pull_back_learned`'s ``phase``; :func:`polycubenet.policy.run_chain`): when
    ``config.learned_maps`` starts with the registration's map (the default)."""
    return config.learned_maps[0] == "registration"


def denser_worth(mesh: HexMesh | None, maps: dict) -> bool:
    """Whether the best learned mesh so far is pulled back once more through :data:`~polycubenet.policy.DENSER_HEXES`
    times the hexes (:func:`pull_back_learned`): a near miss (:func:`near_miss`) that is off the part, not under the
    quality bar alone, made by a map (not realised: that one is exact).  Session 53, never-seen turned parts at the
    benchmark's 3000 hexes: valid learned meshes 1.0-1.7 % off where the classical polycube's are 0.3-0.9 %
    (``benchmarks/unseen_classical.py --family turned --seed 5``); turned_5_012 through the same draw and map 1.01 %
    off at 3000 hexes, 0.72 % at 5000."""
    from . import tol

    return (near_miss(mesh) and "realised" not in mesh.meta and mesh.meta.get("map") in maps
            and distance_to_part(mesh.meta) > tol.HAUSDORFF_REL_MAX)


def near_miss(mesh: HexMesh | None) -> bool:
    """Whether ``mesh`` (the best learned mesh so far) is a near miss (:func:`polycubenet.policy.near_miss`: valid,
    at most :data:`~polycubenet.policy.REFINE_NEAR_MISS` times the faithfulness bar off the part): the refined map
    is worth its fit only then."""
    return mesh is not None and policy_near_miss(mesh.meta)


#: the maps ``PipelineConfig.learned_maps`` may name
LEARNED_MAPS = ("registration", "refined", "anchors")


class _LazyRefined:
    """The ``refined`` map (:func:`polycubenet.registration.refine`), fitted on its first use only: a map
    that comes after one that ends the chain costs nothing."""

    def __init__(self, corr, part_points: Callable[[], np.ndarray]):
        self.corr, self.part_points, self.refined = corr, part_points, None

    def map_points(self, points: np.ndarray) -> np.ndarray:
        from .registration import refine

        if self.refined is None:
            self.refined = refine(self.corr, self.part_points())
        return self.refined.map_points(points)


def _learned_maps(poly: Polycube, corr, anchored, names,
                  part_points: Callable[[], np.ndarray] | None = None) -> list[tuple[str, Callable]]:
    """``(name, to_part)`` of the maps ``names`` (``PipelineConfig.learned_maps``) this polycube has:
    ``anchors`` needs the cleaned cloud's points, normals and anchors (``anchored``; an anchored model's
    cloud) and at least one point near a face of its direction; ``refined`` the part's samples
    (``part_points()``, called when the map is first used); the registration is always there."""
    from .anchormap import anchor_map

    unknown = [n for n in names if n not in LEARNED_MAPS]
    if unknown or not names:
        raise ValueError(f"learned_maps must name some of {LEARNED_MAPS}; got {tuple(names)}")
    out = []
    for name in names:
        if name == "registration":
            out.append((name, corr.map_points))
        elif name == "refined":
            if part_points is not None:
                out.append((name, _LazyRefined(corr, part_points).map_points))
        elif anchored is not None:
            try:
                out.append((name, anchor_map(poly, *anchored).map_points))
            except ValueError:
                continue
    if not out:  # only the anchors asked for, and the cloud has none: the registration
        out.append(("registration", corr.map_points))
    return out


def own_diagonal(Vc: np.ndarray, T: Transform) -> float:
    """The bounding-box diagonal of the part in its own coordinates, in canonical units (what its
    quality report's Hausdorff distance is relative to; the canonical box is the rotated part's)."""
    return float(np.linalg.norm(np.ptp(np.asarray(Vc, float) @ np.asarray(T.rotation, float), axis=0)))


#: a realised learned polycube's mesh under the quality bar is pulled back once more without the pillow layer
#: (both interior modes): at a slanted end the pillow hexes can be the worst ones.  Measured on never-seen
#: mixed parts (seeds 61 and 67, not used for any reported figure): mixed_67_009 0.178 -> 0.319, mixed_61_002
#: 0.061 -> 0.301, both still within 1 % of the part
NO_PILLOW_RETRY = True


def _pull_back_classical(mesh_pc, corr, Vc, F, config: PipelineConfig, diagonal: float | None = None,
                         retry_below: float | None = None) -> HexMesh:
    """Pullback with the classical (exact on the surface) map: the interior mode of
    ``config.classical.interior`` first; when that mesh is not valid (or valid but under ``retry_below``),
    the other mode too, and with ``retry_below`` given also both modes without the pillow layer
    (:data:`NO_PILLOW_RETRY`), keeping the best mesh (:func:`polycubenet.policy.mesh_rank`; ``meta["interior"]``
    and ``meta["pillowed"]`` say which); not when the first mesh is far from valid
    (:func:`polycubenet.pullback.worth_retry`)."""
    modes = [config.classical.interior] + [m for m in ("harmonic", "correction") if m != config.classical.interior]
    tries = [(m, config.pullback.pillow) for m in modes]
    if retry_below is not None and config.pullback.pillow and NO_PILLOW_RETRY:
        tries += [(m, False) for m in modes]
    best = None
    for mode, pillow in tries:
        mesh = pull_back(mesh_pc, corr.map_points, Vc, F,
                         dataclasses.replace(config.pullback, interior=mode, pillow=pillow), diagonal)
        mesh.meta["interior"] = mode
        if best is None or mesh_rank(mesh.meta, config.min_sj) > mesh_rank(best.meta, config.min_sj):
            best = mesh
        good = best.meta.get("valid") and (retry_below is None or ends_chain(best.meta, retry_below))
        if good or not worth_retry(best.meta, config.pullback):
            break
    return best


def _add_provenance(path: Path, row: dict) -> None:
    """Record which polycube was used (and why), and the part's sharpest convex edge, in an existing
    ``quality.json``."""
    import json

    d = json.loads(Path(path).read_text())
    d["provenance"] = row.get("provenance")
    d["fallback_reason"] = row.get("fallback_reason")
    d["sharpest_edge_deg"] = row.get("sharpest_edge_deg")
    write_json(path, d)


def mesh_part(path: str | Path, source: PolycubeSource | Callable, config: PipelineConfig = PipelineConfig(), **load_kw) -> PartResult:
    """Load ``path`` (:func:`polycubenet.io.load_part`) and run :func:`mesh_surface` on it."""
    from .io import load_part

    t0 = time.perf_counter()
    try:
        part: Part = load_part(path, **load_kw)
    except PartError as exc:
        exc.stage = "load"
        raise
    t_load = time.perf_counter() - t0
    res = mesh_surface(part.vertices, part.faces, source, config, name=Path(path).name, part_meta=part.meta)
    res.timings = {"load": t_load, **res.timings}
    return res


def mesh_part_safe(path: str | Path, source, config: PipelineConfig = PipelineConfig(), **kw) -> PartResult:
    """:func:`mesh_part` that returns a failed :class:`PartResult` instead of raising for a bad
    part or an invalid polycube (anything else is a bug and still raises)."""
    try:
        return mesh_part(path, source, config, **kw)
    except (PartError, PolycubeError) as exc:
        return PartResult(
            name=Path(path).name, status="failed", stage=getattr(exc, "stage", "load"), error=f"{type(exc).__name__}: {exc}"
        )
