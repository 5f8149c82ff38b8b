"""The learned polycube's structure, realised exactly on the part through the classical deformation.

The learned path maps its polycube onto the part by registration (rigid, then CPD): a smooth
field that is close on the surface, not exact.  Where the part has a feature the polycube
draws differently -- a slanted end (the polycube's end face is axis-aligned), a round boss --
the field leaves the polycube's face where the cloud had it, and the pulled-back mesh misses
the part by 1-4 % of its diagonal although the structure is right.

:func:`realise` keeps the learned structure and replaces the map:

1. **Labels from the learned polycube** (:func:`transfer_votes`).  The extracted polycube's
   surface is sampled, every sample carries the label of its face (``2 * axis + (sign > 0)``)
   and goes through the registration's map onto the part; every part triangle then holds the
   share of each label among the mapped samples near it.  The labelling's fidelity cost
   (:func:`label_cost`) is mostly that share; the triangle's normal only settles the borders
   and forbids a label that faces away from it.
2. **Clean-up and flattening**, the classical construction's own steps
   (:mod:`polycubenet.classical`): Potts smoothing and chart repair with that cost, then the
   as-rigid-as-possible flattening onto the labels' planes (:func:`classical.flatten_labelled`).
   With ``ClassicalConfig.keep_strips`` (on in ``RealiseConfig.classical``) the repair keeps a small chart that
   borders both faces of another axis: the floor of a thin slot or the rim of a thin plate, which merged into a
   neighbour puts the two opposite faces on one plane and fills the slot (sessions 81-82).
3. **The same structure, else the part's own.**  The solid that the flattened surface bounds
   (:func:`classical.flat_structure`, planes closer than :data:`MERGE_REL` of the learned
   polycube's smallest cell merged, but not two that face opposite ways across each other:
   ``RealiseConfig.keep_sheets``) is
   compared with the learned polycube's minimal grid and
   occupancy, up to slabs thinner than :data:`THIN_SLAB` on either side (:func:`match_structure`:
   a learned slab collapsed where the part has one plane, a thin slab of the part put back where the
   learned polycube has one plane).  When it matches, each axis goes through the monotone
   piecewise-linear map that sends the flattened planes onto the learned ones, so the flattened
   surface *is* the learned polycube's surface, and :class:`~polycubenet.classical.SurfaceMap`
   maps it exactly (barycentric) onto the part.  When it does not, but is a valid polycube of the
   learned one's genus (``RealiseConfig.own_structure``, on by default), that solid is kept: the
   learned labels with a boss or step the generated cloud left out, whose faces the normals label
   (session 65: never-seen machined 812_011, 812_015 and blocks 813_006,
   whose realisations were all refused for another structure, meshed within the bars).  Otherwise
   :class:`~polycubenet.errors.PolycubeError` says how it differs and the registration's map is used
   as before.

Provenance stays honest: the structure (cells, planes, genus) is the generated cloud's, up to the thin
slabs :func:`match_structure` collapses or puts back (counted in the map's ``meta``: ``collapsed_slabs``,
``inserted_slabs``), or, where the map's ``meta["structure"]`` says ``the part's (...)``, the part's own solid on
the learned labels; the map onto the part is computed by the classical deformation; neither the classical
labelling (the normals' own labels, without the learned votes) nor the voxel grid enters.
"""

from __future__ import annotations

import dataclasses
import itertools
import time

import numpy as np
from scipy.spatial import cKDTree

from .classical import (
    DIRECTIONS,
    ClassicalConfig,
    SurfaceMap,
    _edge_weights,
    decimate,
    edge_topology,
    flat_structure,
    flatten_labelled,
    normal_fidelity,
    repair_labels,
    smooth_labels,
)
from .data import Polycube
from .errors import PolycubeError
from .frame import face_normals_areas
from .polycube import compress, polycube_surface, solid_genus
from .sampling import poisson_disk

#: samples of the learned polycube's surface sent through the registration's map
N_TRANSFER = 16384
#: mapped samples consulted per part triangle
K_TRANSFER = 12
#: a slab of the learned polycube thinner than this (canonical frame, diagonal 1) may be collapsed to
#: match the flattened part (:func:`match_structure`)
THIN_SLAB = 0.03
#: a planar patch of the part: triangles joined across edges bending less than FLAT_DEG, all normals within
#: PLANAR_DEV_DEG of the patch's mean (:func:`planar_patches`); each takes one label (:func:`patch_cost`)
FLAT_DEG = 2.0
PLANAR_DEV_DEG = 3.0
#: weight of the normal's fidelity beside the transferred labels' share (which has weight 1)
NORMAL_WEIGHT = 0.35
#: flattened planes of one axis closer than this fraction of the learned polycube's smallest
#: cell width are merged before the structures are compared
MERGE_REL = 0.25


@dataclasses.dataclass(frozen=True)
class RealiseConfig:
    """Parameters of :func:`realise` (the flattening's are ``classical``'s)."""

    n_transfer: int = N_TRANSFER
    k: int = K_TRANSFER
    normal_weight: float = NORMAL_WEIGHT
    merge_rel: float = MERGE_REL
    thin_slab: float = THIN_SLAB
    planar_patches: bool = True
    own_structure: bool = True
    #: the thin-strip rule (sessions 81-82): close planes facing opposite ways across each other (their faces
    #: overlap seen along the axis) are not merged (:func:`_merge_close`: they bound a thin plate or slot), and the
    #: labelling's repair keeps the small charts that border both faces of another axis
    #: (``classical.keep_strips``).  Session 81 had the first half unguarded (every close opposite pair kept): the
    #: synthetic genus-2 oracle pair of ``tests/test_pipeline.py`` was then realised with 3 thin slabs its
    #: flattening staggered side by side.  Guarded, on the 84 parts of the session 74-81 fresh sets it can change:
    #: 63 meshed against 55 with the rule off (+8, -0), one fewer than unguarded; examples 10 / 10
    #: (``benchmarks/results/s82_strips.json``)
    keep_sheets: bool = True
    #: the realisation's labelling and flattening (its repair keeps thin strips: ``ClassicalConfig.keep_strips``,
    #: on by default, in the classical chain too since session 84)
    classical: ClassicalConfig = ClassicalConfig()


@dataclasses.dataclass
class Realised:
    """:func:`realise`'s result: the exact map (``map_points`` like registration's) and the polycube it maps
    from (the learned one, its thin slabs collapsed where the part has one plane and the part's thin slabs
    put back where the learned one has one plane)."""

    map: SurfaceMap
    polycube: Polycube

    def map_points(self, points):
        return self.map.map_points(points)


def variants(config: RealiseConfig) -> list[RealiseConfig]:
    """The labellings a realisation tries in turn: with each planar face of the part one label, then (where
    that mesh does not end the chain) triangle by triangle.  Measured on never-seen mixed seed 11 (16 parts,
    the 26.35 h file): triangle labels alone 8 meshed (mixed_11_007 0.216, 11_002 0.304), planar faces alone
    7 (11_007 0.250 at the first draw, 11_002 0.038: under the bar), both in turn keep each part's better one.
    The second is tried only after the first realised the structure (:func:`polycubenet.pipeline.pull_back_learned`)."""
    out = [config]
    if config.planar_patches:
        out.append(dataclasses.replace(config, planar_patches=False))
    return out


def transfer_votes(V: np.ndarray, F: np.ndarray, poly, map_points, n: int = N_TRANSFER, k: int = K_TRANSFER,
                   seed: int = 0) -> np.ndarray:
    """``(F, 6)``: the share of each label among the learned polycube's surface samples that the
    map (polycube domain -> part, e.g. ``Correspondence.map_points``) sends near each part triangle
    (Gaussian weights at the samples' spacing; rows sum to 1)."""
    Vq, Fq = polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy)
    s = poisson_disk(Vq, Fq, n, seed=seed)
    nq, _ = face_normals_areas(Vq, Fq)
    lab = np.argmax(nq[s.face_ids] @ DIRECTIONS.T, axis=1)
    mapped = np.asarray(map_points(s.points), dtype=np.float64)
    centroids = np.asarray(V, float)[np.asarray(F)].mean(axis=1)
    kk = min(k, len(mapped))
    d, idx = cKDTree(mapped).query(centroids, k=kk)
    d, idx = d.reshape(len(centroids), kk), idx.reshape(len(centroids), kk)
    h = max(float(np.median(d[:, 0])), 1e-9) * 2.0 + 1e-12
    w = np.exp(-((d - d[:, :1]) / h) ** 2)  # relative to the nearest: a triangle far from every sample still votes
    votes = np.zeros((len(centroids), 6))
    np.add.at(votes, (np.repeat(np.arange(len(centroids)), kk), lab[idx].ravel()), w.ravel())
    return votes / votes.sum(axis=1, keepdims=True)


def label_cost(votes: np.ndarray, normals: np.ndarray, areas: np.ndarray, normal_weight: float = NORMAL_WEIGHT) -> np.ndarray:
    """``(F, 6)`` fidelity cost: ``area * ((1 - share) + normal_weight * (1 - n . d))`` (areas relative
    to their mean), and a label facing away from the triangle's normal (``n . d < 0``) costs 4 more."""
    a = (areas / areas.mean())[:, None]
    nd = normals @ DIRECTIONS.T
    return a * ((1.0 - votes) + 4.0 * (nd < 0.0)) + normal_weight * normal_fidelity(normals, areas)


def planar_patches(normals: np.ndarray, edge_faces: np.ndarray, flat_deg: float = FLAT_DEG,
                   max_dev_deg: float = PLANAR_DEV_DEG) -> np.ndarray:
    """``(F,)`` the planar patch of each triangle, ``-1`` where it is on none: the groups of triangles joined
    across edges that bend less than ``flat_deg`` whose normals all stay within ``max_dev_deg`` of their mean
    (a CAD part's planar faces; a finely tessellated cylinder bends little per edge but fails the second test)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(normals)
    c = np.einsum("ij,ij->i", normals[edge_faces[:, 0]], normals[edge_faces[:, 1]])
    flat = c > np.cos(np.radians(flat_deg))
    ef = edge_faces[flat]
    k, comp = connected_components(coo_matrix((np.ones(len(ef)), (ef[:, 0], ef[:, 1])), shape=(n, n)), directed=False)
    mean = np.zeros((k, 3))
    np.add.at(mean, comp, normals)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
    dev = np.einsum("ij,ij->i", normals, mean[comp])
    worst = np.ones(k)
    np.minimum.at(worst, comp, dev)
    size = np.bincount(comp, minlength=k)
    planar = (worst > np.cos(np.radians(max_dev_deg))) & (size > 1)
    return np.where(planar[comp], comp, -1)


def patch_cost(data: np.ndarray, areas: np.ndarray, patch: np.ndarray) -> np.ndarray:
    """``data`` with every planar patch's rows replaced by the patch's cost per area times the row's area, so
    a planar face of the part takes one label (the learned share over the whole face) and the charts' borders
    follow the part's edges instead of cutting across a face where the registration left its samples."""
    out = data.copy()
    on = patch >= 0
    if not on.any():
        return out
    a = areas / areas.mean()
    k = int(patch.max()) + 1
    tot = np.zeros((k, data.shape[1]))
    np.add.at(tot, patch[on], data[on])
    area = np.bincount(patch[on], weights=a[on], minlength=k)
    out[on] = a[on, None] * tot[patch[on]] / np.maximum(area[patch[on], None], 1e-300)
    return out


def _merge_close(Xp: np.ndarray, F: np.ndarray, labels: np.ndarray, tol: float,
                 keep_sheets: bool = False) -> np.ndarray:
    """Chart planes of one axis closer than ``tol`` moved onto their group's mean (a thin slab the
    flattening left between two faces that the learned polycube has on one plane).  ``keep_sheets``: two
    neighbouring planes whose faces look opposite ways (one down the axis, the other up) stay apart however
    close: they bound a thin plate or a thin slot of the part, which merging would cut or fill
    (``RealiseConfig.keep_sheets``), but only where the two faces lie across each other (their projections
    along the axis overlap by more than ``tol`` both ways): opposite faces side by side are a flattening's
    stagger, not a sheet, and merge; so do planes that face one way (a low step)."""
    X = np.array(Xp, dtype=np.float64, copy=True)
    for a in range(3):
        on = np.flatnonzero(labels // 2 == a)
        p, inv = np.unique(X[F[on, 0], a], return_inverse=True)
        if len(p) < 2:
            continue
        join = np.diff(p) <= tol
        if keep_sheets:
            up = labels[on] % 2 == 1
            for i in np.flatnonzero(join):
                m0, m1 = inv == i, inv == i + 1
                lo, hi, lo_up, hi_up = on[m0], on[m1], up[m0], up[m1]
                if (_across(X, F, lo[lo_up], hi[~hi_up], a, tol)
                        or _across(X, F, lo[~lo_up], hi[hi_up], a, tol)):
                    join[i] = False
        group = np.concatenate([[0], np.cumsum(~join)])
        q = np.array([p[group == g].mean() for g in range(group[-1] + 1)])[group]
        if np.allclose(p, q):
            continue
        X[:, a] = np.interp(X[:, a], p, q)
    return X


def _across(X: np.ndarray, F: np.ndarray, f: np.ndarray, g: np.ndarray, axis: int, margin: float,
            chunk: int = 1 << 22) -> bool:
    """Whether some face of ``f`` and some face of ``g`` overlap when seen along ``axis``: their bounding
    rectangles in the other two coordinates share more than ``margin`` both ways."""
    if len(f) == 0 or len(g) == 0:
        return False
    other = [b for b in range(3) if b != axis]
    P, Q = X[F[f]][:, :, other], X[F[g]][:, :, other]
    plo, phi, qlo, qhi = P.min(1), P.max(1), Q.min(1), Q.max(1)
    step = max(1, chunk // len(g))
    for s in range(0, len(f), step):
        w = np.minimum(phi[s:s + step, None], qhi[None]) - np.maximum(plo[s:s + step, None], qlo[None])
        if ((w > margin).all(-1)).any():
            return True
    return False


def _collapses(a_planes: np.ndarray, b_planes: np.ndarray, thin: float, keep: int = 3) -> list[tuple[int, ...]]:
    """Up to ``keep`` sets of slabs of ``b_planes`` thinner than ``thin`` whose collapse leaves as many
    planes as ``a_planes``, the best aligned with them first (empty when none)."""
    k = len(b_planes) - len(a_planes)
    if k < 0:
        return []
    if k == 0:
        return [()]
    thin_slabs = np.flatnonzero(np.diff(b_planes) < thin)
    if len(thin_slabs) < k or len(thin_slabs) > 12:
        return []
    scored = []
    for sub in itertools.combinations(thin_slabs.tolist(), k):
        q = _collapsed_planes(b_planes, sub)
        scored.append((float(np.abs(q - a_planes).max()), sub))
    scored.sort()
    return [sub for _, sub in scored[:keep]]


def _collapsed_planes(planes: np.ndarray, slabs) -> np.ndarray:
    """The planes with each listed slab shrunk to one plane at its middle (adjacent ones chain)."""
    q = np.asarray(planes, dtype=np.float64).copy()
    for i in sorted(slabs):
        q[i + 1] = q[i] = 0.5 * (q[i] + q[i + 1])
    return np.delete(q, [i + 1 for i in sorted(slabs)])


def _expanded_planes(planes: np.ndarray, got: np.ndarray, slabs) -> np.ndarray:
    """``planes`` (one fewer per listed slab than ``got``) with each of ``got``'s collapsed slabs put back:
    the learned plane it collapsed onto split into two, ``got``'s thickness apart (at most 0.4 of either
    neighbouring cell, so the planes stay in order)."""
    q = np.asarray(planes, dtype=np.float64)
    out, i, j, slabs = [], 0, 0, set(slabs)
    while i < len(got):
        if i in slabs:  # got's slab (i, i + 1) is the learned plane q[j]
            w = float(got[i + 1] - got[i])
            lo = q[j] - q[j - 1] if j > 0 else np.inf
            hi = q[j + 1] - q[j] if j + 1 < len(q) else np.inf
            h = min(0.5 * w, 0.4 * lo, 0.4 * hi)
            out += [q[j] - h, q[j] + h]
            i += 2
        else:
            out.append(q[j])
            i += 1
        j += 1
    return np.asarray(out)


def match_structure(got_grid, got_occ, poly, thin: float = THIN_SLAB):
    """The learned polycube ``poly``'s planes in the order of the solid ``(got_grid, got_occ)``'s minimal
    grid, when the two are one structure: identical minimal grids and occupancies, or identical once
    some slabs thinner than ``thin`` are collapsed: of the learned polycube (a face the generated cloud
    drew a little thick, cut in two planes, which the part has as one), or, along an axis where the
    part has more planes, of the flattened part (two close part planes, a thin step or lip, that the
    generated cloud drew as one; that slab is put back around the learned plane, the part's thickness
    wide).  Returns ``(got planes, learned planes, collapsed slab count, inserted slab count)``; raises
    :class:`~polycubenet.errors.PolycubeError` saying how they differ otherwise."""
    ga, oa = compress(list(got_grid), got_occ)
    gb, ob = compress([poly.xs, poly.ys, poly.zs], poly.occupancy)
    # per axis: (slabs collapsed in the learned grid, slabs collapsed in the part's)
    options = [[(sub, ()) for sub in _collapses(ga[a], gb[a], thin)]
               + [((), sub) for sub in _collapses(gb[a], ga[a], thin) if sub and np.diff(sub).min(initial=2) > 1]
               for a in range(3)]
    if not all(options):
        raise PolycubeError(f"the flattened part bounds a {'x'.join(map(str, oa.shape))} grid, the learned polycube "
                            f"{'x'.join(map(str, ob.shape))}")
    worst = None
    for subs in itertools.product(*options):
        occ_b, occ_a = ob, oa
        for a in range(3):
            occ_b = np.delete(occ_b, list(subs[a][0]), axis=a)
            occ_a = np.delete(occ_a, list(subs[a][1]), axis=a)
        if occ_b.shape == occ_a.shape and bool((occ_b == occ_a).all()):
            planes = [_expanded_planes(_collapsed_planes(gb[a], subs[a][0]), ga[a], subs[a][1]) for a in range(3)]
            return (ga, planes, int(sum(len(s[0]) for s in subs)), int(sum(len(s[1]) for s in subs)))
        if occ_b.shape == occ_a.shape:
            worst = int((occ_b != occ_a).sum()) if worst is None else min(worst, int((occ_b != occ_a).sum()))
    raise PolycubeError(f"{worst if worst is not None else 'the'} cells differ from the learned polycube's")


def realise(V: np.ndarray, F: np.ndarray, poly, map_points, config: RealiseConfig = RealiseConfig(), seed: int = 0,
            part: str | None = None, cache: dict | None = None) -> Realised:
    """The exact map from the learned polycube ``poly`` onto the part ``(V, F)`` (canonical frame), its
    labels taken through ``map_points`` (the registration's map); see the module docstring.

    Returns a :class:`Realised`: the polycube (``poly``, its thin slabs collapsed where the part has one
    plane: :func:`match_structure`) and a :class:`~polycubenet.classical.SurfaceMap` whose flattened
    surface lies on that polycube's surface (``meta``: labels, flips, collapsed slabs, seconds).  Raises
    :class:`~polycubenet.errors.PolycubeError` when the flattened part does not bound the learned structure,
    nor (``config.own_structure``) another valid polycube of its genus, which is then returned on its own
    planes (``meta["structure"]``: ``the part's (how it differs)``; the polycube's meta: ``own_structure``,
    ``learned_grid_shape``).
    ``cache``: a dict shared by the calls for one polycube and map (the labelling :func:`variants`), which
    then decimate, measure and transfer the labels once.
    """
    t0 = time.perf_counter()
    cc = config.classical
    cache = {} if cache is None else cache
    if "votes" not in cache:
        V = np.asarray(V, dtype=np.float64)
        F = np.asarray(F, dtype=np.int64)
        if len(F) > cc.max_faces:
            dec = decimate(V, F, cc.max_faces)
            if dec is not None:
                V, F = dec
        cache.update(V=V, F=F, geometry=face_normals_areas(V, F), topology=edge_topology(F),
                     votes=transfer_votes(V, F, poly, map_points, config.n_transfer, config.k, seed=seed + 41))
    V, F, votes = cache["V"], cache["F"], cache["votes"]
    (normals, areas), (edges, edge_faces) = cache["geometry"], cache["topology"]
    rng = np.random.default_rng(seed)
    data = label_cost(votes, normals, areas, config.normal_weight)
    if config.planar_patches:
        data = patch_cost(data, areas, planar_patches(normals, edge_faces))
    labels = np.argmin(data, axis=1)
    w = _edge_weights(V, F, edges, edge_faces, normals, cc)
    labels = smooth_labels(labels, normals, areas, edge_faces, w, cc.smooth_sweeps, rng, data)
    labels, rep = repair_labels(labels, V, F, normals, areas, edges, edge_faces, w, cc, rng, data)
    t1 = time.perf_counter()
    Xp, Vs, Fs, ls, dmeta, fix, _, _ = flatten_labelled(V, F, labels, cc)
    cells = min(float(np.diff(g).min()) for g in (poly.xs, poly.ys, poly.zs))
    Xp = _merge_close(Xp, Fs, ls, config.merge_rel * cells, config.keep_sheets)
    st = flat_structure(Xp, Fs, ls)
    meta = {"merged_charts": rep["merged_charts"], "relabelled_faces": rep["relabelled_faces"],
            "flipped": dmeta["flipped"], "fix_rounds": fix, "faces": int(len(Fs)),
            "time_label": t1 - t0, "time_flatten": time.perf_counter() - t1}
    if st["reason"] is not None:
        raise PolycubeError(f"the part flattened on the learned labels is not a polycube ({st['reason']})", part)
    grid, occ = compress(list(st["grid"]), st["occupancy"])
    pmeta = {**poly.meta, "realised": True}
    try:
        ga, gb, collapsed, inserted = match_structure(st["grid"], st["occupancy"], poly, config.thin_slab)
        structure = "learned"
    except PolycubeError as exc:
        differs = f"the part flattened on the learned labels differs from the learned polycube: {exc.args[0]}"
        learned_genus = poly.meta.get("genus")
        learned_genus = int(solid_genus(poly.occupancy)) if learned_genus is None else int(learned_genus)
        if not config.own_structure:
            raise PolycubeError(differs + " (the part's own structure is off)", part) from None
        if st["genus"] != learned_genus:
            # the flattening closed or opened a tunnel (a hole wall labelled like its neighbour, a breakout
            # through a slanted end): say so, it is a different miss from another cell layout
            raise PolycubeError(f"{differs}; it is of genus {int(st['genus'])}, the learned polycube of genus "
                                f"{learned_genus}", part) from None
        # RealiseConfig.own_structure: the flattened part's own solid, on its own planes (the flattened surface
        # lies on its faces as it is); the labels that shaped it are still the learned polycube's
        ga = gb = grid
        collapsed, inserted, structure = 0, 0, f"the part's ({exc.args[0]})"
        pmeta.update(own_structure=True, genus=int(st["genus"]), grid_shape=list(occ.shape),
                     learned_grid_shape=list(poly.occupancy.shape))
    # each axis: the flattened planes onto the learned ones (same count and order: the grids matched)
    Y = np.array(Xp, copy=True)
    if structure == "learned":
        for a in range(3):
            Y[:, a] = np.interp(Xp[:, a], ga[a], gb[a])
    meta.update(collapsed_slabs=collapsed, inserted_slabs=inserted, structure=structure,
                seconds=time.perf_counter() - t0)
    realised = Polycube(gb[0], gb[1], gb[2], occ,
                        meta={**pmeta, "collapsed_slabs": collapsed, "inserted_slabs": inserted})
    method = ("learned polycube" if structure == "learned" else "the part's structure on the learned labels")
    return Realised(SurfaceMap(Y, Fs, Vs, meta={"method": f"{method}, exact map by the classical deformation",
                                                **meta}), realised)


def learned_map(V: np.ndarray, F: np.ndarray, poly, corr, config: RealiseConfig | None, seed: int = 0,
                part: str | None = None, cache: dict | None = None) -> tuple[Realised | None, str | None]:
    """The map a learned polycube is pulled back with: :func:`realise`'s exact one when ``config`` is set
    and the flattened part bounds the learned structure, else None and why (then the registration's
    ``corr`` maps the polycube, as without realisation)."""
    if config is None:
        return None, "off"
    try:
        return realise(V, F, poly, corr.map_points, config, seed=seed, part=part, cache=cache), None
    except PolycubeError as exc:
        return None, str(exc.args[0] if exc.args else exc)

