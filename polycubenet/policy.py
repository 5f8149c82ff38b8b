"""The polycube fallback policy, written once.

Which polycube sources a part tries and in what order, when a source is left for the
next one, and which mesh is kept.  Both drivers run it: :func:`polycubenet.pipeline.mesh_surface`
(one process, no orchestrator) and ``tasks.mesh.mesh_chain`` (every stage a cached,
retried Prefect task).  A driver only supplies ``attempt(source, seconds)``: run that
source's stages (polycube -> extract -> register -> pullback), add each stage's seconds
to ``seconds`` as it finishes, and return an :class:`Attempt`; the policy decides the rest.

The rules:

* **Order** (:func:`source_names`): ``auto`` = learned, then the classical chain;
  the learned source's first draw (at the run's DDIM steps: the checkpoint's default, 1 step
  on a CPU) is followed by further draws of the model, :data:`LEARNED_DRAWS` (``learned+1``,
  ``learned+2``, ...: more steps, other seeds; :func:`learned_draws`), each tried only when
  the one before is left: one step is best on synthetic pairs, more steps on real parts whose
  slanted or round features the one-step cloud blurs, and a draw is cheap (0.2-0.7 s at 4096
  points on one CPU core, with its extraction) beside the classical chain (6-9 s); see
  :data:`LEARNED_DRAWS` for the measurements;
  ``classical`` = surface flattening, then the voxel polycube (its last resort, which
  exists for every closed part); ``voxel`` alone; ``learned`` / ``oracle`` alone, or
  followed by the classical chain with ``fallback``.  The voxel polycube is followed by
  up to :data:`VOXEL_REFINEMENTS` finer ones (``voxel+K``: ``K * refine_cells`` more cells
  than the resolution the voxel polycube chose, :func:`polycubenet.voxel.voxel_polycube`),
  tried only while the one before gave a mesh that does not end the chain: a coarse voxel
  solid cuts thin features and curved faces (HexGen fertility 1.22 % off at 30 cells,
  0.84 % at 38; rockerarm not valid at 28 cells, min SJ 0.302 at 36).  The last source,
  ``voxel+3*``, partitions the finest of them into :data:`DENSER_HEXES` times the hexes
  (:func:`source_config`), tried like a refinement: whether a fine voxel polycube's pull-back
  untangles depends on its partition (seed-3 threaded rod, refinement 3: not valid at the
  default 5000 hexes, valid and 0.82 % off at 6000 to 10 000, not valid at 15 000).
* **Leaving a source** (:func:`leaves_source`): a rejected polycube
  (:class:`~polycubenet.errors.PolycubeError`, at any stage) always hands the part to
  the next source; for the learned source, so does *any* other error of its attempt
  (generation, registration, pullback), since the classical chain does not depend on it.
  A :class:`~polycubenet.errors.PartError` is final: a bad part is bad for every source.
  A source whose pulled-back mesh is not valid is also left, its mesh kept as a candidate;
  so is a valid mesh that does not follow the part (:func:`distance_to_part`: the sampled
  two-sided distance the pull-back measures, relative to the diagonal, above
  :data:`~polycubenet.tol.HAUSDORFF_REL_MAX`: a polycube that folds or cuts across the part
  can still be untangled into a valid mesh of the wrong shape), and a mesh that is valid
  but under ``min_sj`` (the project's quality bar, ``PipelineConfig.min_sj`` = 0.2): the
  next source is tried and the better mesh kept (HexGen rockerarm: the flattening's mesh
  has min SJ 0.187, the voxel polycube's 0.302).
* **A learned draw's rest**: a learned draw's pull-back is its registration map's mesh first; the rest (the exact
  realisation, the refined map, the mend, the denser pull-back) runs at once when that mesh is a near miss
  (:func:`near_miss`) or no later draw follows, otherwise after the later draws' own maps (:func:`defers`): a draw
  far off mostly has the wrong structure, and the next draw's map is cheaper than its realisation.  Of the waiting
  draws only :data:`FAR_RESTS` finish before the classical chain, the best mesh so far first (:func:`mesh_rank`);
  the others are left with their maps' meshes.
* **The kept mesh**: the first valid, faithful one that ends the chain, unless an earlier
  candidate ranks higher (:func:`mesh_rank`: valid first, then faithful, then not under the
  quality bar, then the higher minimum scaled Jacobian, or among meshes off the part the one
  closer to it); when none is valid, the candidate with the highest minimum scaled Jacobian,
  reported as not valid.

Every reason a source was left is one sentence in :attr:`Outcome.reasons`
(``"<source> polycube rejected at <stage>: <reason>"`` or
``"pullback: the <source> polycube's hex mesh is not valid (...)"``), and the seconds
spent on left sources are summed per stage in :attr:`Outcome.rejected_seconds`.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from . import tol
from .errors import PartError, PolycubeError

#: the values of ``--polycube`` / ``PipelineConfig.polycube``
MODES = ("auto", "learned", "classical", "voxel")
#: finer voxel polycubes after the first one (``voxel+1`` ... ``voxel+3``)
VOXEL_REFINEMENTS = 3
#: the model's further draws after its first, in order: ``(DDIM steps, seed offset, generator fallbacks, turn[,
#: anchor spread[, stretch exponent]])`` of
#: ``learned+1``, ``learned+2``, ...  (a draw never uses fewer steps than the first; one that would repeat the
#: first is skipped, :func:`learned_draws`; the fallbacks: :func:`extraction_config`).  Measured on never-seen
#: parts meshed valid, faithful and >= 0.2 through the learned source (of 16, ``benchmarks/unseen_parts.py
#: --mesh``): session 9, one 4-step draw after the first: blocks 9 -> 12, mixed 5 -> 7 and 5 -> 5.  Session 12,
#: two more 4-step draws (seeds +1, +2) with the 21.00 h file: mixed seed 11 6 -> 7, seed 41 (first 10 parts)
#: 3 -> 3: not kept.  Session 18, each draw alone on the dev sets (mixed 61 + 67, 32 parts, used for no reported
#: figure; the shipped file): 1 step at seeds +0/+1/+2 with the fallbacks 12/12/13, 4 steps without them at
#: seeds +0/+1/+2 13/6/9; in order, 1:+0 then 4:+0 15 (401 s learned-only), then 1 step at seed +1 with the
#: fallbacks 17 (575 s), then 4:+2 18 (647 s), nothing more from 4:+1 or 1:+2 (``benchmarks/results/
#: dev_draws_s18.json``): the third draw kept, the fourth not (+1 of 32 for 72 s).  The turn: None, or the canonical
#: axis the part is turned a half-turn about before the model sees it, the cloud turned back
#: (:data:`polycubenet.inference.TURNS`): another view of the part for a model that is not equivariant.  Session 36,
#: the third draw turned (``benchmarks/learned_meshes.py --draws``, ``benchmarks/unseen_parts.py --draws``): on the
#: dev sets (machined 61 + 67, the 71.93 h continue file) turned about z it meshes 2 of the 16 parts the unturned
#: draws leave (``benchmarks/results/dev_draws_s36.json``), but on the never-seen machined
#: sets 11, 31, 53, 103 (the shipped file) 34 of 64 against 35 (+0, -1) and on the examples 9 of 10 against 8
#: (bushing; ``benchmarks/results/turned_draws_s36.json``): no better than another seed, not kept.  The anchor
#: spread: ``uniform`` (independent area-uniform samples, the first draw's) or ``even`` (a Poisson-disk sample,
#: spread as the training pairs' anchors are; :data:`polycubenet.inference.ANCHOR_SPREADS`).  Session 38, a
#: fourth draw as the first but with evenly spread anchors (the 76.57 h continue file's session 37 finding,
#: ``benchmarks/anchor_sampling.py``): dev sets (machined 61 + 67, the shipped file) 20 of 32 against 18 (+2,
#: -0), the examples 10 of 10 against 8 (bushing, flange), the never-seen machined sets 11, 31, 53, 103 35 of
#: 64 as before (+0, -0; ``benchmarks/results/even_draw_s38.json``): kept, a later draw loses no part.
#: Sessions 74-75, two more with evenly spread anchors at seed +1, at 1 and at 4 steps (the shipped file, the
#: learned source alone, ``benchmarks/learned_meshes.py --draws default 4/0/n/-,1/1/y/-,1/0/y/-/even,1/1/y/-/even,
#: 4/1/y/-/even --misses-only``): the 40 misses of the session 66-73 fresh sets 8 against 2 (+6: three by each
#: of the two; ``benchmarks/results/s74_even2_old_misses.json``), then the sets never run before, 981-984 20 of
#: 24 either way and 991-994 22 of 24 against 21 (+1; ``s74_fresh_981_984.json``, ``s75_fresh_991_994.json``);
#: the examples all mesh by the first four draws, so these never run; a part the earlier draws leave costs about 150 s
#: more of learned source (the draws' maps and rests) before the classical chain: kept
LEARNED_DRAWS = ((4, 0, False, None), (1, 1, True, None), (1, 0, True, None, "even"),
                 (1, 1, True, None, "even"), (4, 1, True, None, "even"))
#: the very last source, ``voxel+3*``: the finest voxel polycube partitioned into this many times the hexes
DENSER_HEXES = 1.5


def _int_steps(steps) -> bool:
    return isinstance(steps, (int, np.integer)) and not isinstance(steps, bool)


def draw_steps(source: str, steps):
    """DDIM steps a learned source draws at after a first draw at ``steps`` (the run's setting):
    ``steps`` for ``learned``, for ``learned+K`` the steps of its :data:`LEARNED_DRAWS` entry, or
    ``steps`` when that is more."""
    k = refinement(source)[1]
    if not k:
        return steps
    want = LEARNED_DRAWS[k - 1][0]
    return max(want, int(steps)) if _int_steps(steps) else want


def draw_seed(source: str) -> int:
    """The seed offset of a learned source's draw: 0 for ``learned``, its :data:`LEARNED_DRAWS`
    entry's for ``learned+K``."""
    k = refinement(source)[1]
    return LEARNED_DRAWS[k - 1][1] if k else 0


def draw_turn(source: str) -> str | None:
    """The axis a learned source's draw turns the part a half-turn about before the model sees it
    (:data:`polycubenet.inference.TURNS`): None for ``learned`` and for a further draw whose
    :data:`LEARNED_DRAWS` entry has no turn."""
    k = refinement(source)[1]
    entry = LEARNED_DRAWS[k - 1] if k else ()
    return entry[3] if len(entry) > 3 else None


def draw_anchors(source: str) -> str:
    """How a learned source's draw spreads the model's anchors on the part
    (:data:`polycubenet.inference.ANCHOR_SPREADS`): ``uniform`` for ``learned`` and for a further draw
    whose :data:`LEARNED_DRAWS` entry names no spread."""
    k = refinement(source)[1]
    entry = LEARNED_DRAWS[k - 1] if k else ()
    return entry[4] if len(entry) > 4 else "uniform"


def draw_stretch(source: str) -> float | None:
    """The exponent of a learned source's stretched view of the part (:func:`polycubenet.inference.stretch_factors`):
    None for ``learned`` and for a further draw whose :data:`LEARNED_DRAWS` entry has no sixth field."""
    k = refinement(source)[1]
    entry = LEARNED_DRAWS[k - 1] if k else ()
    return (float(entry[5]) or None) if len(entry) > 5 and entry[5] is not None else None


def draw_fallbacks(source: str) -> bool:
    """Whether a learned source's draw is extracted with the generator fallbacks: always the first draw
    (``learned``), a further draw when its :data:`LEARNED_DRAWS` entry says so."""
    k = refinement(source)[1]
    return bool(LEARNED_DRAWS[k - 1][2]) if k else True


def learned_draws(steps, anchored: bool = True) -> tuple[int, ...]:
    """The further draws ``K`` (sources ``learned+K``) after a first draw at ``steps``: every entry
    of :data:`LEARNED_DRAWS` that would not repeat the first draw or an earlier further one (the same cloud:
    the same steps, seed offset, turn and anchor spread, the first's seed offset 0, no turn, uniform anchors;
    for a model that takes no anchors, ``anchored=False``, any spread is the first's), unless the earlier one
    was extracted without the generator fallbacks and this one with them (the first draw has them); none
    after a first draw at a schedule that is not a step count (the GPU's ``"stride4"``).  A run at more
    steps draws every entry at its own steps (:func:`draw_steps`), so entries that differ only in their
    steps can fall together: at 4 steps the table's 1-step and 4-step even draws at seed +1 are one draw."""
    if not _int_steps(steps):
        return ()
    tried = {(int(steps), 0, None, "uniform", None): True}  # cloud -> extracted with the fallbacks
    kept = []
    for k in range(1, len(LEARNED_DRAWS) + 1):
        src = f"learned+{k}"
        cloud = (draw_steps(src, steps), draw_seed(src), draw_turn(src), draw_anchors(src) if anchored else "uniform",
                 draw_stretch(src))
        if cloud in tried and (tried[cloud] or not draw_fallbacks(src)):
            continue
        tried[cloud] = draw_fallbacks(src)  # here: a new cloud, or one now with the fallbacks
        kept.append(k)
    return tuple(kept)


def refinement(source: str) -> tuple[str, int]:
    """``(base source, refinement step)`` of a source name: ``"voxel+2"`` -> ``("voxel", 2)``,
    ``"voxel+3*"`` -> ``("voxel", 3)``, ``"classical"`` -> ``("classical", 0)``."""
    base, plus, k = source.removesuffix("*").partition("+")
    if plus and k.isdigit() and int(k) > 0:
        return base, int(k)
    return source, 0


def denser(source: str) -> bool:
    """Whether ``source`` is partitioned into :data:`DENSER_HEXES` times the hexes (``voxel+3*``)."""
    return source.endswith("*")


def source_config(source: str, config):
    """The pipeline config ``source``'s partition uses: ``config`` itself, or for a denser source
    :func:`denser_config`."""
    return denser_config(config) if denser(source) else config


def denser_config(config):
    """``config`` with :data:`DENSER_HEXES` times its hexes (``target_hexes``, or ``target_size`` over the cube
    root): the partition of the ``voxel+3*`` source and of a learned polycube's near miss
    (:func:`polycubenet.pipeline.pull_back_learned`)."""
    if config.target_size is not None:
        return dataclasses.replace(config, target_size=config.target_size / DENSER_HEXES ** (1 / 3))
    return dataclasses.replace(config, target_hexes=int(round(config.target_hexes * DENSER_HEXES)))


def extraction_config(source: str, config):
    """The pipeline config ``source``'s cloud is extracted with: ``config`` itself, or for the model's
    further draws (``learned+K``) whose :data:`LEARNED_DRAWS` entry has no generator fallbacks
    (:func:`draw_fallbacks`) its extraction without them
    (:meth:`~polycubenet.structure.ExtractConfig.for_exact_clouds`).
    A 4-step draw that passes extraction only through them costs a pull-back and a realisation it rarely
    pays back: with them, `auto` on the examples rose from 1.00 to 1.44 x the classical wall time (bushing's
    and flange's second draws, 4.8 % and 1.1 % off the part, 19 s each), while on never-seen mixed seeds 61
    and 67 no part was meshed by a second draw that needed them (session 15).  A one-step draw at another
    seed is the first draw's kind of cloud and gets them, as the first draw does (session 18)."""
    kind, k = refinement(source)
    if kind == "learned" and k and not draw_fallbacks(source):
        return dataclasses.replace(config, extract=config.extract.for_exact_clouds())
    return config


def source_label(source: str) -> str:
    """How reasons name a source: ``voxel+2`` is "voxel (refinement 2)", ``voxel+3*``
    "voxel (refinement 3, 1.5x hexes)", ``learned+1`` "learned (draw 2, 4 steps)", a draw with another seed
    "learned (draw 3, 4 steps, seed +1)", a turned one "learned (draw 3, 1 step, seed +1, turned about z)", one
    with evenly spread anchors "learned (draw 4, 1 step, even anchors)", a stretched one "..., stretched +0.5" (the
    steps of :data:`LEARNED_DRAWS`; a run at more steps draws at its own)."""
    base, k = refinement(source)
    if base == "learned" and k:
        seed = f", seed +{draw_seed(source)}" if draw_seed(source) else ""
        turn = f", turned about {draw_turn(source)}" if draw_turn(source) else ""
        spread = f", {draw_anchors(source)} anchors" if draw_anchors(source) != "uniform" else ""
        stretch = f", stretched {draw_stretch(source):+g}" if draw_stretch(source) else ""
        n = LEARNED_DRAWS[k - 1][0]
        return f"learned (draw {k + 1}, {n} step{'s' if n != 1 else ''}{seed}{turn}{spread}{stretch})"
    if denser(source):
        return f"{base} (refinement {k}, {DENSER_HEXES:g}x hexes)"
    return f"{base} (refinement {k})" if k else source


def source_names(mode: str, fallback: bool = False, classical: bool = True, draws: tuple[int, ...] = ()) -> list[str]:
    """The sources a part tries, in order, for polycube mode ``mode``.

    ``fallback`` adds the classical chain after ``learned`` / ``oracle`` (``auto`` always has
    it); ``classical=False`` (the flattening construction unavailable) leaves the voxel
    polycube alone in the classical chain; ``draws`` (:func:`learned_draws` of the first draw's
    steps) adds the model's further draws ``learned+K`` after ``learned``.
    """
    voxel = ["voxel"] + [f"voxel+{k}" for k in range(1, VOXEL_REFINEMENTS + 1)] + [f"voxel+{VOXEL_REFINEMENTS}*"]
    if mode == "voxel":
        return voxel
    rest = (["classical"] if classical else []) + voxel
    if mode == "classical":
        return rest
    first = [mode if mode != "auto" else "learned"]
    if mode in ("auto", "learned"):
        first += [f"learned+{k}" for k in draws]
    return first + (rest if fallback or mode == "auto" else [])


def leaves_source(source: str, exc: BaseException) -> bool:
    """Whether ``exc``, raised by ``source``'s attempt, hands the part to the next source."""
    if isinstance(exc, PartError):
        return False
    if isinstance(exc, PolycubeError):
        return True
    # the learned attempt may fail in ways the classical chain never depends on (the model, CPD, ...)
    return refinement(source)[0] == "learned" and isinstance(exc, Exception)


def distance_to_part(meta: dict) -> float | None:
    """How far a pulled-back mesh is from the part, relative to the diagonal: its sampled
    ``hausdorff`` (the quality report's measure) when the pull-back measured it, else the
    cheaper ``deviation`` (a lower bound); None when neither is there."""
    d = meta.get("hausdorff")
    d = meta.get("deviation") if d is None else d
    return None if d is None else float(d)


def faithful(meta: dict) -> bool:
    """Whether a pulled-back mesh follows the part: :func:`distance_to_part` within the
    Hausdorff bar; a mesh without the measure counts as faithful."""
    d = distance_to_part(meta)
    return d is None or d <= tol.HAUSDORFF_REL_MAX


def under_bar(meta: dict, min_sj: float | None) -> bool:
    """Whether a pulled-back mesh's minimum scaled Jacobian is under the quality bar ``min_sj`` (never
    with no bar; always when the mesh has no measure)."""
    sj = meta.get("sj_min")
    return min_sj is not None and (sj is None or float(sj) < min_sj)


def mesh_rank(meta: dict, min_sj: float | None = None) -> tuple:
    """Order of pulled-back meshes (``HexMesh.meta`` or a quality dict): a valid one first, then a
    faithful one (:func:`faithful`), then one not under the quality bar ``min_sj``; among faithful (or
    invalid) meshes the higher minimum scaled Jacobian; among valid meshes off the part the one closer
    to it (:func:`distance_to_part`), then the higher minimum scaled Jacobian.  When no polycube gives a
    faithful mesh, the part gets the one whose surface is least wrong (never-seen mixed_61_000 under
    ``auto``, session 19: the learned mesh 2.34 % of the diagonal off at minimum SJ 0.302 used to be kept over
    a voxel polycube's 1.99 % off at 0.256)."""
    sj = meta.get("sj_min")
    sj = -np.inf if sj is None else float(sj)
    valid, true_to_part = bool(meta.get("valid")), faithful(meta)
    above = not under_bar(meta, min_sj)
    if valid and not true_to_part:
        return (True, False, above, -distance_to_part(meta), sj)
    return (valid, true_to_part, above, sj, 0.0)


#: the refined map (:func:`polycubenet.registration.refine`) is fitted and tried only after a near miss: a valid
#: mesh so far (the registration's, or a realised one) at most this many times the faithfulness bar
#: (:data:`polycubenet.tol.HAUSDORFF_REL_MAX`) off the part.  A finer field mends a local misfit; it does not
#: untangle a folded structure or find a missing feature.  Session 42, the learned source alone, ungated: the two
#: parts it meshed on the dev sets (machined_61_000, 67_011) were 1.75 and 1.66 % off through the registration
#: alone; where it was kept but failed, the registration's mesh was mostly not valid or 2.5-7 % off.  A learned
#: draw's further pull-back steps also run at once only after a near miss (:func:`run_chain`)
REFINE_NEAR_MISS = 2.0


def near_miss(quality: dict | None) -> bool:
    """Whether a pulled-back mesh (``HexMesh.meta`` or a quality dict) is valid and at most
    :data:`REFINE_NEAR_MISS` times the faithfulness bar off the part (:func:`distance_to_part`)."""
    if not quality or not quality.get("valid"):
        return False
    d = distance_to_part(quality)
    return d is not None and d <= REFINE_NEAR_MISS * tol.HAUSDORFF_REL_MAX


def ends_chain(quality: dict, min_sj: float | None) -> bool:
    """Whether a pulled-back mesh (``HexMesh.meta`` or a quality dict) ends the chain: valid, faithful
    (:func:`faithful`) and not under the quality bar ``min_sj``."""
    return bool(quality.get("valid")) and faithful(quality) and not under_bar(quality, min_sj)


def unfaithful_reason(label: str, meta: dict) -> str:
    """Why a valid mesh that does not follow the part made the chain try the next polycube."""
    return (f"the {label} polycube's hex mesh is valid but {100 * distance_to_part(meta):.2f} % of the diagonal "
            f"off the part (bar {100 * tol.HAUSDORFF_REL_MAX:g} %): the next polycube was tried and the better "
            "mesh kept")


def invalid_mesh_reason(label: str, meta: dict) -> str:
    """Why a pulled-back mesh made the chain try the next polycube (one sentence)."""
    sj = meta.get("sj_min")
    sj = "unknown" if sj is None else f"{float(sj):.3f}"
    return f"the {label} polycube's hex mesh is not valid (minimum scaled Jacobian {sj})"


def error_reason(exc: BaseException) -> str:
    """The sentence of an error: a PolycubeError's own reason, otherwise ``Type: message``."""
    if isinstance(exc, PolycubeError):
        return getattr(exc, "reason", None) or str(exc)
    return f"{type(exc).__name__}: {exc}"


@dataclasses.dataclass
class Attempt:
    """One source's pulled-back mesh: ``quality`` has at least ``valid`` and ``sj_min``;
    ``payload`` is whatever the driver needs to export it; ``label`` names it in reasons
    (default: the source).  ``rest``: for a learned draw whose mesh so far is its registration map's alone
    (:func:`polycubenet.pipeline.pull_back_learned`, ``phase="map"``), the call that runs the draw's further
    pull-back steps and returns the finished attempt (seconds added); :func:`run_chain` decides when."""

    source: str
    quality: dict
    payload: Any = None
    seconds: dict = dataclasses.field(default_factory=dict)
    label: str | None = None
    rest: Callable[[], "Attempt"] | None = None


@dataclasses.dataclass
class Outcome:
    """What :func:`run_chain` decided: the kept attempt (None when every source was
    rejected before a mesh; ``error`` is then the last source's error), the reasons the
    other sources were left and the seconds they cost per stage."""

    chosen: Attempt | None
    reasons: list[str]
    rejected_seconds: dict
    attempts: list[Attempt]
    error: BaseException | None = None
    error_source: str | None = None

    @property
    def fallback_reason(self) -> str | None:
        return "; ".join(self.reasons) or None


class StageTracker:
    """The ``seconds`` dict a driver fills, plus the stage it is in (for the reason of an error)."""

    def __init__(self):
        self.seconds: dict = {}
        self.stage = "polycube"


def below_bar_reason(label: str, meta: dict, bar: float) -> str:
    """Why a valid mesh under the quality bar did not end the chain (one sentence)."""
    sj = meta.get("sj_min")
    sj = "unknown" if sj is None else f"{float(sj):.3f}"
    return (f"the {label} polycube's hex mesh is valid but its minimum scaled Jacobian {sj} is under {bar:g}: "
            "the next polycube was tried and the better mesh kept")


def defers(quality: dict, later: list[str]) -> bool:
    """Whether a learned draw whose mesh so far (``quality``, its registration map's) does not end the chain
    leaves the rest of its pull-back (the exact realisation, the refined map, the mend, the denser pull-back:
    :func:`polycubenet.pipeline.pull_back_learned`) until the later learned draws among ``later`` (the sources
    after it) have their own mesh so far: when that mesh is not a near miss (:func:`near_miss`) and such a draw
    follows.  A near miss is where the rest pays (a local misfit, the partition's); a mesh farther off is mostly a
    structure the rest cannot mend, and another draw's registration map is cheaper than the realisation.
    Session 57, the examples with the 118.30 h continue file: stepped_shaft's first two draws 3.4 and 2.8 %
    off, their rests 43 s refused, the third draw's map within the bar in 4 s
    (``benchmarks/results/s57_bench_auto_cost_C118.json``); session 56's replay of the 114.15 h file's draws
    (``benchmarks/learned_order.py``, order ``defer-far``): learned seconds -4 and -9 % on the dev machined sets,
    -2 % on turned 5, the same on the examples, the same parts meshed."""
    return not near_miss(quality) and any(refinement(s)[0] == "learned" for s in later)


#: how many waiting learned draws (far off the part: :func:`defers`) finish their rest before the next kind of
#: source, the best mesh so far first (:func:`mesh_rank`); the others are left with their maps' meshes.  Session 86,
#: every draw's units timed on today's code and the orders replayed (``benchmarks/learned_order.py --replay``): a far
#: draw's rest cost 3-107 s (median 15) and ended the chain in 52 of 101; where several ran on a part no draw
#: meshed they mostly ended equally far off (blocks_1132_000: six rests, 400 s, each 4.79 % off: a wall thinner than
#: the hexes).  Learned seconds with every waiting rest / the closest one only: 2359 / 1653 on 19 never-seen parts
#: of sessions 83-85 (the rule chosen there; 12 meshed either way), 1056 / 833 on a check set recorded after (the
#: examples, machined 1141, mixed 1143: 22 parts, 19 meshed either way); with none (only near misses and the last
#: draw finish) 1433 and 632, two parts lost (``benchmarks/results/s86_learned_order_{fresh,check}.json``).
#: None: every waiting draw finishes, in draw order
FAR_RESTS: int | None = 1


def run_chain(sources: list[str], attempt: Callable[[str, StageTracker], Attempt],
              min_sj: float | None = None) -> Outcome:
    """Try ``sources`` in order with the policy of this module (see the module docstring).

    ``attempt(source, tracker)`` runs the source's stages, setting ``tracker.stage`` as it goes
    and adding stage seconds to ``tracker.seconds``; it returns an :class:`Attempt` or raises.
    A voxel refinement (``voxel+K``) is tried only when the source just before it gave a mesh;
    the model's further draws (``learned+K``) whenever the draw before is left.
    A learned draw's attempt may leave the rest of its pull-back for later (:attr:`Attempt.rest`): when its
    mesh so far does not end the chain, the rest runs at once after a near miss (:func:`near_miss`) and when no
    later learned draw follows; otherwise it waits until every later draw's own mesh so far is in, the waiting
    ones then, :data:`FAR_RESTS` of them, best mesh so far first, before the next kind of source (:func:`defers`);
    a draw still waiting when a later mesh ends the chain, or beyond :data:`FAR_RESTS`, is left with its mesh so
    far, as a candidate, its reason and seconds reported.
    An error that :func:`leaves_source` does not cover is raised as it is, with
    ``exc.stage`` and ``exc.source`` set, after ``exc.fallback_reason`` records the sources
    left before it.
    """
    if not sources:
        raise ValueError("no polycube source to try")
    reasons: list[str] = []
    rejected: dict = {}
    candidates: list[Attempt] = []
    attempts: list[Attempt] = []
    chosen: Attempt | None = None
    last_error: tuple | None = None
    waiting: list[Attempt] = []  # learned draws whose rest waits (draw order)

    def reject(seconds: dict) -> None:
        for k, v in seconds.items():
            rejected[k] = rejected.get(k, 0.0) + float(v or 0.0)

    def failed(src: str, stage: str, exc: BaseException, seconds: dict) -> None:
        """Leave a source whose attempt (or rest) raised, its ``seconds`` rejected; raise an error no source may
        be left by."""
        nonlocal last_error
        exc.stage = getattr(exc, "stage", None) or stage
        exc.source = src
        if not leaves_source(src, exc):
            exc.fallback_reason = "; ".join(reasons) or None
            raise exc
        reject(seconds)
        reasons.append(f"{source_label(src)} polycube rejected at {exc.stage}: {error_reason(exc)}")
        last_error = (exc, src)

    def finished(att: Attempt) -> Attempt | None:
        """``att`` with its rest run; None when the rest raised (the draw left as an attempt that raised is)."""
        try:
            return att.rest()
        except BaseException as exc:
            failed(att.source, "pullback", exc, att.seconds)
            return None

    def settle(att: Attempt, last: bool, note: str = "") -> bool:
        """Take a finished attempt in; True when it ends the chain."""
        nonlocal chosen
        attempts.append(att)
        if ends_chain(att.quality, min_sj) or last:
            chosen = att
            return True
        candidates.append(att)
        label = att.label or source_label(att.source)
        if not att.quality.get("valid"):
            why = invalid_mesh_reason(label, att.quality)
        elif not faithful(att.quality):
            why = unfaithful_reason(label, att.quality)
        else:
            why = below_bar_reason(label, att.quality, min_sj)
        reasons.append(f"pullback: {why}{note}")
        reject(att.seconds)
        return False

    def run_waiting() -> bool:
        if FAR_RESTS is not None:  # the best meshes so far first (a stable sort: ties in draw order)
            waiting.sort(key=lambda a: mesh_rank(a.quality, min_sj), reverse=True)
        runs = len(waiting) if FAR_RESTS is None else FAR_RESTS
        while waiting and runs > 0:
            runs -= 1
            att = finished(waiting.pop(0))
            if att is not None and settle(att, last=False):
                return True
        note = (" (its realisation not tried: only the closest far draw finishes)" if FAR_RESTS == 1 else
                f" (its realisation not tried: only the {FAR_RESTS} closest far draws finish)")
        while waiting:  # beyond FAR_RESTS: left with its mesh so far, a candidate
            settle(waiting.pop(0), last=False, note=note)
        return False

    meshed: set = set()  # the sources that gave a mesh
    for i, src in enumerate(sources):
        last = i == len(sources) - 1
        base, k = refinement(src)
        if waiting and base != "learned" and run_waiting():
            break
        if base == "voxel" and k and (i == 0 or sources[i - 1] not in meshed):
            continue  # its coarser voxel polycube gave no mesh: a finer one is no answer to that
        tracker = StageTracker()
        try:
            att = attempt(src, tracker)
        except BaseException as exc:
            failed(src, tracker.stage, exc, tracker.seconds)
            continue
        if not att.seconds:
            att.seconds = dict(tracker.seconds)
        meshed.add(src)
        if att.rest is not None and not ends_chain(att.quality, min_sj):
            if defers(att.quality, sources[i + 1:]):
                waiting.append(att)
                continue
            att = finished(att)
            if att is None:
                continue
        if settle(att, last and not waiting):
            break
    else:
        run_waiting()
    for att in waiting:  # left waiting when a later mesh ended the chain: its mesh so far is a candidate
        settle(att, last=False)
    pool = candidates + ([chosen] if chosen is not None and chosen not in candidates else [])
    if not pool:  # every source was rejected before it gave a mesh
        exc, src = last_error
        reasons.pop()  # the last source's own rejection is the error itself
        return Outcome(None, reasons, rejected, attempts, error=exc, error_source=src)
    best = max(pool, key=lambda a: mesh_rank(a.quality, min_sj))
    if chosen is not None and best is not chosen:  # the last source's mesh is worse than an earlier one
        label = chosen.label or source_label(chosen.source)
        if not chosen.quality.get("valid"):
            why = invalid_mesh_reason(label, chosen.quality)
        elif not faithful(chosen.quality) and (faithful(best.quality)
                                               or under_bar(chosen.quality, min_sj) == under_bar(best.quality, min_sj)):
            why = f"the {label} polycube's hex mesh is valid but does not follow the part as closely as an earlier one"
        elif not faithful(chosen.quality):
            why = (f"the {label} polycube's hex mesh is valid but {100 * distance_to_part(chosen.quality):.2f} % of "
                   f"the diagonal off the part and worse (minimum scaled Jacobian {float(chosen.quality.get('sj_min')):.3f})")
        else:
            why = (f"the {label} polycube's hex mesh is valid but worse (minimum scaled Jacobian "
                   f"{float(chosen.quality.get('sj_min')):.3f})")
        reasons.append(f"pullback: {why}")
        reject(chosen.seconds)
    if best in candidates:  # counted as rejected when it was left; kept now
        for k, v in best.seconds.items():
            rejected[k] = max(0.0, rejected.get(k, 0.0) - float(v or 0.0))
    if not best.quality.get("valid") and len(pool) > 1:
        reasons.append(f"no polycube gave a valid mesh: kept the {best.label or source_label(best.source)} one's "
                       "(the highest minimum scaled Jacobian)")
    return Outcome(best, reasons, {k: v for k, v in rejected.items() if v > 0}, attempts)
