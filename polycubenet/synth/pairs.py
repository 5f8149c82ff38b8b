"""One training pair: a deformed "CAD" shape and its exact polycube, with samples.

:func:`make_pair` (deterministic in its seed):

1. draws a valid polycube (:func:`~polycubenet.synth.polycube.random_polycube`,
   normalized: bounding box centred at 0, diagonal 1 -- the *generator frame*);
2. extracts its boundary on a refined grid (edges at most ``edge_length``, default 2 %
   of the diagonal) and checks that the surface's Euler genus equals the cubical
   complex's genus;
3. draws a deformation (:func:`~polycubenet.synth.deform.random_deformation`) and
   rejects it unless ``det J > MIN_DET`` at 4096 random points of the bounding box and
   at every surface vertex; shape vertex ``i`` is the image of polycube vertex ``i``
   and both meshes share the face list;
4. puts the shape in the frame :func:`polycubenet.frame.canonicalize` gives it.  The
   polycube gets the same centre and scale and the canonical rotation *snapped to the
   nearest proper signed permutation*, so it stays exactly axis-aligned (every face
   normal is exactly an axis).  A sample whose canonical rotation is more than
   ``max_snap_deg`` (30) degrees from every signed permutation is rejected;
5. samples ``n_cond`` points on the shape (Poisson disk, :mod:`polycubenet.sampling`)
   and puts the target points at the *same* face ids and barycentrics on the polycube
   (exact point-to-point ground truth).  When ``n_target != n_cond`` the target uses
   its own shape sample of ``n_target`` points.

Rejections re-draw from the same generator stream, so the result stays a function of
the seed alone.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import time
from pathlib import Path

import numpy as np

from ..atomic import load_npz, save_npz
from ..data import Polycube, SurfaceSample
from ..frame import Transform, canonicalize, face_normals_areas
from ..sampling import interpolate, poisson_disk, uniform_sample
from .deform import (DeformationMap, RoundHole, _other_axes, breakout_cut, check_invertible, empty_cells, gusset_cut,
                     random_deformation)
from ..tol import AREA_REL
from .polycube import (FLANGES, convex_edges, polycube_quads, random_polycube, surface_genus, transform_grid,
                       triangulate_quads, turned_polycube)

#: default target edge length of the refined surfaces (generator frame, diagonal 1)
EDGE_LENGTH = 0.02
#: samples whose canonical rotation is further than this from a signed permutation are rejected
MAX_SNAP_DEG = 30.0
SAMPLERS = ("poisson", "uniform")


def _proper_signed_permutations() -> np.ndarray:
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((-1.0, 1.0), repeat=3):
            P = np.zeros((3, 3))
            P[np.arange(3), perm] = signs
            if np.linalg.det(P) > 0:
                out.append(P)
    return np.array(out)


_PERMS = _proper_signed_permutations()  # (24, 3, 3)


def snap_rotation(R: np.ndarray) -> tuple[np.ndarray, float]:
    """The proper signed permutation nearest to rotation ``R`` and the angle between them.

    Parameters
    ----------
    R : (3, 3) proper rotation

    Returns
    -------
    P : (3, 3) float64, entries in {-1, 0, 1}, det +1
    angle_deg : float, rotation angle of ``R @ P.T``
    """
    R = np.asarray(R, dtype=np.float64)
    scores = np.einsum("kij,ij->k", _PERMS, R)  # trace(P^T R)
    k = int(np.argmax(scores))
    cos = np.clip((scores[k] - 1.0) / 2.0, -1.0, 1.0)
    return _PERMS[k].copy(), float(np.degrees(np.arccos(cos)))


@dataclasses.dataclass
class SynthPair:
    """A shape and its polycube, in the shape's canonical frame.

    Attributes
    ----------
    seed : int, ``make_pair(seed, ...)`` rebuilds this pair exactly
    shape_vertices : (V, 3) float64, the deformed shape (canonical frame)
    polycube_vertices : (V, 3) float64, the polycube surface; vertex ``i`` maps to
        ``shape_vertices[i]``
    faces : (F, 3) int64, shared by both surfaces, outward oriented
    polycube : Polycube, the grid (``xs, ys, zs``) and ``occupancy`` in the canonical
        frame; ``meta`` has ``genus`` and ``provenance == "synthetic"``
    genus : int
    deformation : DeformationMap, acts in the generator frame
    shape_transform : Transform, generator frame -> canonical frame of the shape
        (what ``canonicalize`` returned)
    polycube_transform : Transform, generator frame -> canonical frame of the polycube
        (same centre and scale, rotation snapped to a signed permutation)
    cond : SurfaceSample, ``n_cond`` points on the shape
    target : SurfaceSample, ``n_target`` points on the polycube (axis normals)
    cond_on_polycube : (n_cond, 3) float64, polycube location of each condition point
    target_on_shape : (n_target, 3) float64, shape location of each target point
    meta : dict, provenance (style, features, map kinds, attempts, snap angle, ...)
    """

    seed: int
    shape_vertices: np.ndarray
    polycube_vertices: np.ndarray
    faces: np.ndarray
    polycube: Polycube
    genus: int
    deformation: DeformationMap
    shape_transform: Transform
    polycube_transform: Transform
    cond: SurfaceSample
    target: SurfaceSample
    cond_on_polycube: np.ndarray
    target_on_shape: np.ndarray
    meta: dict = dataclasses.field(default_factory=dict)

    def polycube_to_shape(self, points: np.ndarray) -> np.ndarray:
        """The exact map: polycube (canonical) ``points : (N, 3)`` -> shape (canonical) ``(N, 3)``."""
        return self.shape_transform.forward(self.deformation(self.polycube_transform.inverse(points)))

    def save(self, path: str | Path) -> Path:
        """Write the whole pair to one ``.npz`` (atomic)."""
        meta = dict(self.meta)
        meta.update(
            seed=int(self.seed),
            genus=int(self.genus),
            deformation=self.deformation.to_dict(),
            shape_transform=self.shape_transform.to_dict(),
            polycube_transform=self.polycube_transform.to_dict(),
            polycube_meta=self.polycube.meta,
        )
        arrays = dict(
            shape_vertices=self.shape_vertices,
            polycube_vertices=self.polycube_vertices,
            faces=self.faces,
            xs=self.polycube.xs,
            ys=self.polycube.ys,
            zs=self.polycube.zs,
            occupancy=self.polycube.occupancy,
            cond_on_polycube=self.cond_on_polycube,
            target_on_shape=self.target_on_shape,
        )
        for name, s in (("cond", self.cond), ("target", self.target)):
            arrays.update({f"{name}_points": s.points, f"{name}_normals": s.normals,
                           f"{name}_face_ids": s.face_ids, f"{name}_barycentrics": s.barycentrics})
        arrays["__meta__"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
        return save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "SynthPair":
        a = load_npz(path)
        meta = json.loads(bytes(a.pop("__meta__")).decode())
        samples = {
            name: SurfaceSample(a[f"{name}_points"], a[f"{name}_normals"], a[f"{name}_face_ids"], a[f"{name}_barycentrics"])
            for name in ("cond", "target")
        }
        return cls(
            seed=int(meta.pop("seed")),
            shape_vertices=a["shape_vertices"],
            polycube_vertices=a["polycube_vertices"],
            faces=a["faces"],
            polycube=Polycube(a["xs"], a["ys"], a["zs"], a["occupancy"], meta.pop("polycube_meta")),
            genus=int(meta.pop("genus")),
            deformation=DeformationMap.from_dict(meta.pop("deformation")),
            shape_transform=Transform.from_dict(meta.pop("shape_transform")),
            polycube_transform=Transform.from_dict(meta.pop("polycube_transform")),
            cond=samples["cond"],
            target=samples["target"],
            cond_on_polycube=a["cond_on_polycube"],
            target_on_shape=a["target_on_shape"],
            meta=meta,
        )


def _sample(V: np.ndarray, F: np.ndarray, n: int, seed: int, sampler: str) -> SurfaceSample:
    if sampler == "poisson":
        return poisson_disk(V, F, n, seed)
    if sampler == "uniform":
        return uniform_sample(V, F, n, np.random.default_rng(seed))
    raise ValueError(f"unknown sampler {sampler!r}; expected one of {SAMPLERS}")


def _on_polycube(sample: SurfaceSample, Vp: np.ndarray, F: np.ndarray, normals_p: np.ndarray) -> SurfaceSample:
    return SurfaceSample(
        points=interpolate(Vp, F, sample.face_ids, sample.barycentrics),
        normals=normals_p[sample.face_ids],
        face_ids=sample.face_ids.copy(),
        barycentrics=sample.barycentrics.copy(),
        meta={"method": "same locations as the shape sample"},
    )


def _on_box(edge: dict, lo: np.ndarray, hi: np.ndarray, tol: float = 1e-9) -> bool:
    """Whether a convex edge's line (:func:`~polycubenet.polycube.convex_edges`) meets the closed box ``lo``-``hi``."""
    return all(lo[a] - tol <= x <= hi[a] + tol for a, x in zip(_other_axes(int(edge["axis"])), edge["corner"]))


def make_pair(
    seed: int,
    *,
    n_cond: int = 4096,
    n_target: int = 4096,
    edge_length: float = EDGE_LENGTH,
    sampler: str = "poisson",
    max_attempts: int = 100,
    max_snap_deg: float = MAX_SNAP_DEG,
    style: str | None = None,
    n_holes: int | None = None,
    strength: float | None = None,
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
) -> SynthPair:
    """Generate one pair from ``seed`` (see the module docstring for the steps).

    Parameters
    ----------
    seed : int, >= 0
    n_cond, n_target : int, sample sizes on the shape / on the polycube
    edge_length : float, refinement of both surfaces (generator frame, diagonal 1)
    sampler : ``"poisson"`` (blue noise, :func:`polycubenet.sampling.poisson_disk`) or
        ``"uniform"`` (area-uniform white noise, faster)
    max_attempts : int, polycube + deformation draws before giving up
    max_snap_deg : float, rejection bound on the canonical rotation (module docstring)
    style, n_holes : forwarded to :func:`random_polycube` (None = random)
    strength : forwarded to :func:`random_deformation` (None = random)
    cad_features : bool, also round bosses into cylinders (like holes) and cut slanted ends
        (``random_deformation(slanted_ends=True)``): features of machined parts the base
        generator lacks.  Off, a seed gives the pair it gave before this option existed.
    whole_slants : bool, also cut a whole end by a slanted plane in half the pairs
        (``random_deformation(whole_ends=True)``, :class:`~polycubenet.synth.deform.SlantEnd`).  Off,
        a seed gives the pair it gave before this option existed.
    max_strength : float or None, cap on the random strength of the global maps
        (``random_deformation(max_strength=...)``: 0.35 for machined-like parts); None: no cap.
    tall_bosses : bool, more and taller bosses (:func:`~polycubenet.synth.polycube.random_polycube`); with
        ``cad_features`` most are rounded into posts.  Off, a seed gives the pair it gave before.
    full_slants : float in [0, 1], with ``whole_slants``: the share of those cuts that run across the whole
        end, leaving none of its face (``random_deformation(full_ends=...)``).  0: a seed gives the pair it
        gave before.
    cut_slants : bool, with ``whole_slants``: each cut a plane cut that leaves the part's other faces where they
        are (``random_deformation(cut_ends=True)``, placed away from the polycube's empty cells) instead of a
        smooth fade that shears the walls near it.  Off, a seed gives the pair it gave before.
    turned : float in [0, 1], the share of pairs that are turned parts: the polycube of coaxial square steps of
        :func:`~polycubenet.synth.polycube.turned_polycube`, its bolt and cross holes rounded, the fillets and
        chamfers of its shoulders, no global map or slant, then every square about the axis rounded into a
        circle by one radial map (:class:`~polycubenet.synth.deform.RoundHole` about the axis, fading nowhere):
        shafts, bushings and flanges, which the other pairs never show whole.  0: a seed gives the pair it gave
        before.
    bolt_circles : float in [0, 1], with ``turned``: the share of bolted flanges drilled on a circle of 3-8 holes
        rather than four on the cross axes (:func:`~polycubenet.synth.polycube.turned_polycube`).  0: a seed gives
        the pair it gave before.
    flanges : float in [0, 1], with ``turned``: the share of turned parts with a flange at one end
        (:func:`~polycubenet.synth.polycube.turned_polycube`).  The default
        (:data:`~polycubenet.synth.polycube.FLANGES`): a seed gives the pair it gave before.
    min_holes : int, the pairs that are not turned parts attempt at least this many through-holes
        (:func:`~polycubenet.synth.polycube.random_polycube`): genus 2 and more, as drilled machined parts are.
        0: a seed gives the pair it gave before.
    breakouts : float in [0, 1], the share of the pairs that are not turned parts and have a through-hole where one
        hole is opened into the nearer end over some of its layers and that end cut by a slanted plane across them
        (:func:`~polycubenet.synth.deform.breakout_cut`, instead of ``whole_slants``' cut): the hole breaks out
        through the slanted face, as drilled holes near a machined part's slanted end do.  0: a seed gives the
        pair it gave before.
    gussets : float in [0, 1], the share of the pairs that are not turned parts given one or two ribs in concave
        corners (:func:`~polycubenet.synth.polycube.random_polycube`), each cut across its free edge into a
        bracket's triangular rib (:func:`~polycubenet.synth.deform.gusset_cut`, before the other maps; the rib's
        edges are not rounded).  0: a seed gives the pair it gave before.

    Returns
    -------
    SynthPair
    """
    if sampler not in SAMPLERS:
        raise ValueError(f"unknown sampler {sampler!r}; expected one of {SAMPLERS}")
    if n_cond < 1 or n_target < 1:
        raise ValueError(f"n_cond and n_target must be positive; got {n_cond}, {n_target}")
    rng = np.random.default_rng(seed)
    rejected = {"jacobian": 0, "rotation": 0, "orientation": 0}
    timings = {"polycube": 0.0, "deformation": 0.0, "frame": 0.0, "sampling": 0.0}
    for attempt in range(1, max_attempts + 1):
        t0 = time.perf_counter()
        if turned > 0 and rng.random() < turned:
            pc = turned_polycube(rng, bolt_circles=bolt_circles, flanges=flanges)
        else:
            pc = random_polycube(rng, style=style, n_holes=n_holes, tall_bosses=tall_bosses, min_holes=min_holes,
                                 breakouts=breakouts, gussets=gussets)
        body = next((f for f in pc.features if f.kind == "turned"), None)
        V0, Q = polycube_quads(pc.xs, pc.ys, pc.zs, pc.occupancy, h=edge_length)
        lo, hi = pc.bounds
        rounded = ("through_hole", "pocket", "boss") if cad_features else ("through_hole", "pocket")
        holes = [(f.axis, f.lo, f.hi) for f in pc.features if f.kind in rounded]
        t1 = time.perf_counter()
        timings["polycube"] += t1 - t0
        edges = convex_edges(pc.xs, pc.ys, pc.zs, pc.occupancy)
        if body is not None:  # the shoulders' fillets and chamfers, not the edges along the axis (rounded next)
            edges = [e for e in edges if int(e["axis"]) != body.axis]
            dmap = random_deformation(rng, lo, hi, holes, edges, strength=0.0)
            dmap.maps.append(RoundHole(body.axis, 0.5 * (body.lo + body.hi), np.ones(2),
                                       float(rng.choice([16.0, 64.0], p=[0.25, 0.75])), float(rng.uniform(0.85, 1.0)),
                                       1e6))
        else:
            ribs = [f for f in pc.features if f.kind == "gusset"]
            if ribs:  # a rib's edges are left sharp: its cut (below) is the one rounding it gets
                edges = [e for e in edges if not any(_on_box(e, f.lo, f.hi) for f in ribs)]
            out = next((f for f in pc.features if f.kind == "breakout"), None)
            cut = None if out is None else breakout_cut(rng, lo, hi, out.lo, out.hi, out.axis)
            dmap = random_deformation(rng, lo, hi, holes, edges, strength=strength, slanted_ends=cad_features,
                                       whole_ends=whole_slants and cut is None, max_strength=max_strength,
                                       full_ends=full_slants, cut_ends=cut_slants,
                                       keep_out=empty_cells(pc.xs, pc.ys, pc.zs, pc.occupancy) if cut_slants else ())
            if cut is not None:  # after the roundings, before the global maps, as random_deformation's own cut
                at = next((i for i, m in enumerate(dmap.maps) if m.kind not in ("round_hole", "round_edge")),
                          len(dmap.maps))
                dmap.maps.insert(at, cut)
            if ribs:
                cuts = [gusset_cut(rng, pc.xs, pc.ys, pc.zs, pc.occupancy, f.lo, f.hi, f.axis, f.signs) for f in ribs]
                dmap.maps[0:0] = [m for m in cuts if m is not None]
        ok, min_det = check_invertible(dmap, lo, hi, rng, extra=V0)
        timings["deformation"] += time.perf_counter() - t1
        if not ok:
            rejected["jacobian"] += 1
            continue
        t1 = time.perf_counter()
        Vs = dmap(V0)
        F = triangulate_quads(Q, Vs)  # the better diagonal of each quad on the shape
        g_surface = surface_genus(F)
        if g_surface != pc.genus:  # two independent computations disagree: a bug, never data
            raise RuntimeError(f"seed {seed}: surface genus {g_surface} != cubical genus {pc.genus}")
        _, areas_s = face_normals_areas(Vs, F)
        volume = float(np.einsum("ij,ij->i", Vs[F[:, 0]], np.cross(Vs[F[:, 1]], Vs[F[:, 2]])).sum() / 6.0)
        if volume <= 0 or areas_s.min() <= AREA_REL:  # the generator-frame diagonal is 1
            rejected["orientation"] += 1  # inside-out or a collapsed triangle
            timings["frame"] += time.perf_counter() - t1
            continue
        Vc, T = canonicalize(Vs, F)
        P, snap_deg = snap_rotation(T.rotation)
        timings["frame"] += time.perf_counter() - t1
        if snap_deg > max_snap_deg:
            rejected["rotation"] += 1
            continue
        break
    else:
        raise RuntimeError(f"seed {seed}: no acceptable pair in {max_attempts} attempts ({rejected})")

    Tp = Transform(center=T.center.copy(), scale=float(T.scale), rotation=P)
    Vp = Tp.forward(V0)
    xs, ys, zs, occ = transform_grid(pc.xs, pc.ys, pc.zs, pc.occupancy, Tp.center, Tp.scale, P)
    normals_p, _ = face_normals_areas(Vp, F)
    normals_c, _ = face_normals_areas(Vc, F)

    t1 = time.perf_counter()
    seeds = rng.integers(0, 2**31 - 1, size=2)
    cond = _sample(Vc, F, n_cond, int(seeds[0]), sampler)
    cond.normals = normals_c[cond.face_ids]
    if n_target == n_cond:
        shape_for_target = cond
    else:
        shape_for_target = _sample(Vc, F, n_target, int(seeds[1]), sampler)
        shape_for_target.normals = normals_c[shape_for_target.face_ids]
    target = _on_polycube(shape_for_target, Vp, F, normals_p)
    cond_on_polycube = interpolate(Vp, F, cond.face_ids, cond.barycentrics)
    timings["sampling"] += time.perf_counter() - t1

    polycube = Polycube(xs, ys, zs, occ, meta={"provenance": "synthetic", "genus": int(pc.genus)})
    meta = {
        "style": pc.style,
        "features": [f.to_dict() for f in pc.features],
        "map_kinds": dmap.kinds,
        "attempts": attempt,
        "rejected": rejected,
        "min_jacobian": min_det,
        "snap_deg": snap_deg,
        "sampler": sampler,
        "edge_length": float(edge_length),
        "n_vertices": int(len(V0)),
        "n_faces": int(len(F)),
        "timings": timings,  # seconds per stage, summed over attempts (not stored in shards)
    }
    return SynthPair(
        seed=int(seed),
        shape_vertices=Vc,
        polycube_vertices=Vp,
        faces=F,
        polycube=polycube,
        genus=int(pc.genus),
        deformation=dmap,
        shape_transform=T,
        polycube_transform=Tp,
        cond=cond,
        target=target,
        cond_on_polycube=cond_on_polycube,
        target_on_shape=shape_for_target.points.copy(),
        meta=meta,
    )
