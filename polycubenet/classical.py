"""A polycube built from the part's own surface (the classical path, no model).

The surface (canonical frame, diagonal 1) is turned into a polycube in four steps,
in the spirit of Gregson et al. 2011 (*All-hex mesh generation via volumetric
polycube deformation*) and Fu et al. 2016, written here from the ideas, not from
their code:

1. **Labelling** (:func:`label_faces`).  Every triangle gets one of the six labels
   ``2 * axis + (sign > 0)`` (the order of :data:`polycubenet.pullback.LABELS`).  The
   start is the axis closest to its normal; the labels are then smoothed by minimising
   an energy of the graph-cut kind -- fidelity ``area * (1 - n . d_label)`` plus a Potts
   term ``compactness * edge length`` on every edge between two labels, cheaper across
   sharp edges, and prohibitive between opposite labels (+x next to -x) -- by iterated
   conditional modes (each sweep moves a random half of the faces that want to change,
   so the synchronous update cannot oscillate).
2. **Validity and repair** (:func:`label_issues`, :func:`repair_labels`).  Charts are
   the connected groups of triangles with one label.  A chart of a polycube is a
   rectilinear polygon, so it needs neighbours of *both* other axes and a minimum
   area; charts that fail are merged into the neighbour they share the longest border
   with (one that no other neighbour contradicts).  Opposite labels that touch are
   relabelled.  The remaining checks are reported: corners where more than three
   charts meet, vertices that would have to sit on two planes of one axis, and
   turning points (a chart border that reverses direction along the axis it must
   follow).
3. **Refinement** (:func:`split_constrained_edges`).  An edge inside a chart whose two
   ends both lie on the border with charts of another axis would collapse when the
   chart is flattened (its triangle then has three collinear corners); such edges are
   split at their midpoint (a point of the original surface, so the map stays exact).
4. **Deformation** (:func:`deform_to_polycube`).  An as-rigid-as-possible iteration:
   each triangle's best rotation from its rest shape (local step) is corrected by the
   smallest rotation that turns its normal onto its label's axis; the rotated rest
   edges are the targets of a sparse least-squares solve per coordinate (global step)
   in which, for each triangle of a chart with axis ``a``, the ``a``-component of its
   edges gets an extra weight that grows every iteration (flatness).  The result is
   then made exact: every chart's vertices take the chart's mean coordinate along its
   axis (charts of one axis sharing a vertex share the plane).  Flipped or degenerate
   triangles are counted (``meta["flipped"]``): the map is injective when there are
   none.

5. **Structure check** (:func:`flat_structure`).  The polycube the flattened surface
   bounds is read off directly (the distinct chart planes as grid, the generalised
   winding number at every cell centre as occupancy).  When it is not a valid polycube
   of the part's genus -- a handle closed because the labelling of its hole's walls let
   them collapse -- steps 1-4 are repeated on the part turned by a few fixed rotations
   (:func:`_orientations`); the first orientation that gives the right genus is kept.
6. **Plane spacing** (:func:`space_planes`, in :class:`ClassicalSource`).  When the
   structure extraction rejects the cloud (it merges planes it cannot resolve), distinct
   chart planes of one axis are moved at least a few cloud point spacings apart by a
   monotone map per axis (which changes neither the structure nor any flip), so the
   structure extraction, which merges planes it cannot resolve, recovers that polycube.

The output (:class:`ClassicalSource`) is a :class:`ClassicalCloud`: a
:class:`~polycubenet.data.PolycubeCloud` (points on the flattened surface with their
chart's axis as normal, ``provenance = "classical"``) that also carries the flattened
mesh and the original vertices, so its :meth:`ClassicalCloud.correspondence` gives the
exact map polycube -> part (:class:`SurfaceMap`) that the pipeline uses instead of
registration.  ``structure.extract`` and everything after it are shared with the
learned path.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import factorized
from scipy.spatial import cKDTree

from .data import PolycubeCloud
from .errors import PolycubeError
from .frame import face_normals_areas
from .sampling import interpolate, poisson_disk

#: unit direction of each label ``2 * axis + (sign > 0)``: -x, +x, -y, +y, -z, +z
DIRECTIONS = np.array(
    [[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64
)


#: version of the construction, part of the flow's cache key for classical clouds: bump it when a
#: change to this module changes its output for the same settings
VERSION = "4"  # 2: orientations, plane spacing, decimation above 16000 triangles only; 3: orientation budget; 4: weight blocks

@dataclasses.dataclass(frozen=True)
class ClassicalConfig:
    """Parameters of the classical polycube (lengths relative to the canonical diagonal 1).

    Attributes
    ----------
    compactness : float
        Weight of the Potts term per mean edge length against the fidelity per mean
        triangle area.  Larger gives fewer, more compact charts.
    sharp_angle_deg : float
        Across an edge whose dihedral angle exceeds this, a label change costs
        ``sharp_discount`` times less.
    sharp_discount : float
    smooth_sweeps : int
        Sweeps of iterated conditional modes.
    min_chart_area : float
        A chart smaller than this fraction of the total area is merged into a neighbour.
    keep_strips : bool
        A chart under ``min_chart_area`` that borders both labels of another axis (the rim of a thin
        plate, the floor or end of a thin slot: a strip between two opposite faces) is kept: merged into
        either neighbour it would put the two opposite faces on one plane and fill the slot or cut the plate.
        On by default since session 84: in the realisation since session 82; in the classical chain,
        measured both ways on 76 never-seen parts (the classical chain alone, ``benchmarks/unseen_classical.py
        --strips``), 72 against 71 meet the bars and 65 against 59 by the flattening rather than a voxel
        polycube, none lost, the examples unchanged; on HexGen and the hard models
        (``benchmarks/bench_classical.py --strips``) 23 of 23 either way, the 12-hole plate by the flattening
        where a voxel polycube was needed before (min SJ 0.30 -> 0.48), joint 0.22 -> 0.27, tube elbow
        0.314 -> 0.306.
    repair_rounds : int
        Rounds of merge / relabel / smooth.
    deform_iterations : int
        Local/global iterations of the deformation.
    flat_weight_start, flat_weight_end : float
        Flatness weight of the first and last iteration (geometric schedule).
    weight_blocks : int
        The weight is held for blocks of this many iterations (each block at the schedule's
        value of its last iteration), so each axis' sparse system is factorized once per block
        rather than once per iteration (15 LU factorizations per flattening instead of 75: they
        were ~45 % of the construction's time).  Measured against 1 (the plain geometric
        schedule), same labelling and orientation: HexGen joint 11.3 -> 6.6 s, 4 -> 4 flipped
        triangles; rockerarm 23.1 -> 14.7 s, 964 -> 959; ant 19.0 -> 12.2 s, 2196 -> 2207;
        mount2 3.1 -> 1.9 s, 10 -> 10; bracket 2.4 -> 1.2 s, 0 -> 0.
    max_faces : int
        A surface with more triangles is first decimated to this many (quadric error,
        open3d), kept only if it stays a closed manifold of the same genus without
        self-intersections; the pullback still projects onto the full surface.  Decimating a
        CAD tessellation (long thin triangles) costs more than it saves: at 6000, the
        ``flange.step`` (10872 triangles) and ``pocket_housing.step`` (12908) examples came
        out inverted at 3000 hexes (min SJ -0.50, -0.33; 167 s and 93 s) and valid without
        decimation (0.181, 0.406; 24 s and 20 s).
    interior : str
        The pullback's interior mode tried first for this map (``"harmonic"``: the map is
        exact on the surface only, so interior nodes are placed harmonically); when that
        mesh is not valid the pipeline also tries the other mode and keeps the better.
    fix_rounds : int
        Rounds of relabelling flipped triangles and flattening again.
    retries : int
        When the flattened surface has flipped triangles, the labelling is redone with
        ``compactness`` doubled, up to this many times; the attempt with the fewest
        flips is kept.
    orientations : int
        When the solid bounded by the flattened surface (:func:`flat_structure`) does not
        have the part's genus (a handle closed by the flattening: its hole's walls were
        labelled so that they cannot stay apart), the whole construction is repeated on
        the part turned by up to this many further fixed rotations
        (:func:`_orientations`), which gives the labelling other chart layouts; the
        attempt of the right genus with the fewest flips is kept.
    orientation_budget : int
        At most ``max(1, orientation_budget // faces)`` orientations are flattened (``faces``
        after decimation): a deterministic bound on the search, which on a part that no
        orientation flattens to its genus (a plate with 12 holes: 9 orientations, 270-400 s)
        is most of the time spent.  On the 8 HexGen models, 10 example parts, 15 hard models
        and the 2 synthetic test parts the most any needed was 3 orientations of 10692 faces
        (32 076); the default is twice that.
    min_plane_gap, plane_gap_spacings : float
        When the extraction rejects the cloud, distinct chart planes of one axis are moved at least ``max(min_plane_gap,
        plane_gap_spacings * s)`` apart (:func:`space_planes`), ``s`` being the point
        spacing of the polycube cloud, so the structure extraction resolves them.
    """

    compactness: float = 1.5
    sharp_angle_deg: float = 50.0
    sharp_discount: float = 4.0
    smooth_sweeps: int = 40
    min_chart_area: float = 0.002
    keep_strips: bool = True
    repair_rounds: int = 30
    deform_iterations: int = 25
    flat_weight_start: float = 1.0
    flat_weight_end: float = 1e4
    weight_blocks: int = 5
    retries: int = 2
    fix_rounds: int = 4
    max_faces: int = 16000
    interior: str = "harmonic"
    orientations: int = 8
    orientation_budget: int = 64000
    min_plane_gap: float = 0.01
    plane_gap_spacings: float = 2.5


# --------------------------------------------------------------------------- topology


def edge_topology(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges ``(E, 2)`` and their two faces ``(E, 2)`` of a closed 2-manifold.

    Raises
    ------
    PolycubeError
        When an edge does not have exactly two faces.
    """
    F = np.asarray(F, dtype=np.int64)
    nf = len(F)
    he = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    key = np.sort(he, axis=1)
    edges, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    if np.any(counts != 2):
        raise PolycubeError(f"surface is not a closed 2-manifold ({int((counts != 2).sum())} bad edges)")
    order = np.argsort(inv.ravel(), kind="stable")
    faces = np.tile(np.arange(nf), 3)[order].reshape(-1, 2)
    return edges, faces


def _dihedral(normals: np.ndarray, edge_faces: np.ndarray) -> np.ndarray:
    c = np.einsum("ij,ij->i", normals[edge_faces[:, 0]], normals[edge_faces[:, 1]])
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def charts_of(labels: np.ndarray, edge_faces: np.ndarray) -> tuple[int, np.ndarray]:
    """Connected groups of faces with one label: ``(count, chart id per face (F,))``."""
    same = labels[edge_faces[:, 0]] == labels[edge_faces[:, 1]]
    ef = edge_faces[same]
    n = len(labels)
    g = sp.coo_matrix((np.ones(len(ef)), (ef[:, 0], ef[:, 1])), shape=(n, n))
    return connected_components(g, directed=False)


# --------------------------------------------------------------------------- labelling


def _pair_cost(compactness_big: float) -> np.ndarray:
    """Potts cost between labels: 0 same, 1 different, ``compactness_big`` opposite."""
    P = 1.0 - np.eye(6)
    for l in range(6):
        P[l, l ^ 1] = compactness_big
    return P


def smooth_labels(
    labels: np.ndarray,
    normals: np.ndarray,
    areas: np.ndarray,
    edge_faces: np.ndarray,
    edge_w: np.ndarray,
    sweeps: int,
    rng: np.random.Generator,
    data: np.ndarray | None = None,
) -> np.ndarray:
    """Iterated conditional modes on fidelity + Potts (see the module docstring).

    ``data`` ``(F, 6)``: the fidelity cost of each label on each face, when it is not the
    normal's (:func:`normal_fidelity`; e.g. labels transferred from a learned polycube)."""
    labels = labels.copy()
    if data is None:
        data = normal_fidelity(normals, areas)
    P = _pair_cost(25.0)
    f0, f1 = edge_faces[:, 0], edge_faces[:, 1]
    n = len(labels)
    for _ in range(sweeps):
        cost = data.copy()
        np.add.at(cost, f0, edge_w[:, None] * P[labels[f1]])
        np.add.at(cost, f1, edge_w[:, None] * P[labels[f0]])
        best = np.argmin(cost, axis=1)
        want = np.flatnonzero(best != labels)
        if len(want) == 0:
            break
        move = want[rng.random(len(want)) < 0.5] if len(want) > 8 else want
        labels[move] = best[move]
    return labels


def normal_fidelity(normals: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """``(F, 6)``: the labelling's fidelity cost, ``area * (1 - n . d_label)`` (areas relative to their mean)."""
    return (areas / areas.mean())[:, None] * (1.0 - normals @ DIRECTIONS.T)


def _edge_weights(V, F, edges, edge_faces, normals, config: ClassicalConfig) -> np.ndarray:
    length = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    w = config.compactness * length / max(length.mean(), 1e-12)
    sharp = _dihedral(normals, edge_faces) > config.sharp_angle_deg
    w[sharp] /= config.sharp_discount
    return w


def _chart_graph(labels, edge_faces, edge_len, chart):
    """Border length between every pair of adjacent charts: dict ``(c, d) -> length``."""
    a, b = chart[edge_faces[:, 0]], chart[edge_faces[:, 1]]
    diff = a != b
    n = int(chart.max()) + 1
    M = sp.coo_matrix((edge_len[diff], (a[diff], b[diff])), shape=(n, n)).tocsr()
    M = M + M.T
    return M


def repair_labels(
    labels: np.ndarray,
    V: np.ndarray,
    F: np.ndarray,
    normals: np.ndarray,
    areas: np.ndarray,
    edges: np.ndarray,
    edge_faces: np.ndarray,
    edge_w: np.ndarray,
    config: ClassicalConfig,
    rng: np.random.Generator,
    data: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Merge charts that cannot be polycube faces and separate opposite labels.

    ``data``: the fidelity cost of :func:`smooth_labels` (None: the normals').  Returns the
    repaired labels and counts of what was done.
    """
    labels = labels.copy()
    edge_len = np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)
    total = areas.sum()
    merged = relabelled = 0
    for _ in range(config.repair_rounds):
        changed = False
        # opposite labels touching: the face with the worse fidelity takes its best third axis
        opp = np.flatnonzero(labels[edge_faces[:, 0]] == (labels[edge_faces[:, 1]] ^ 1))
        if len(opp):
            for e in opp:
                f, g = edge_faces[e]
                fit_f = normals[f] @ DIRECTIONS[labels[f]]
                fit_g = normals[g] @ DIRECTIONS[labels[g]]
                h = f if fit_f < fit_g else g
                ax = labels[h] // 2
                cand = [l for l in range(6) if l // 2 != ax]
                labels[h] = cand[int(np.argmax(normals[h] @ DIRECTIONS[cand].T))]
                relabelled += 1
            changed = True
        n_ch, chart = charts_of(labels, edge_faces)
        ch_area = np.bincount(chart, weights=areas, minlength=n_ch)
        ch_label = np.zeros(n_ch, dtype=np.int64)
        ch_label[chart] = labels
        M = _chart_graph(labels, edge_faces, edge_len, chart)
        bad = []
        for c in range(n_ch):
            nb = M.indices[M.indptr[c] : M.indptr[c + 1]]
            other_axes = {int(ch_label[d] // 2) for d in nb} - {int(ch_label[c] // 2)}
            small = ch_area[c] < config.min_chart_area * total
            if small and config.keep_strips:
                nbl = {int(ch_label[d]) for d in nb}
                small = not any(2 * a in nbl and 2 * a + 1 in nbl for a in other_axes)
            if small or len(other_axes) < 2:
                bad.append(c)
        # smallest first; a chart merges only if none of its neighbours merged this round
        bad.sort(key=lambda c: ch_area[c])
        touched = np.zeros(n_ch, dtype=bool)
        new_label = {}
        for c in bad:
            nb = M.indices[M.indptr[c] : M.indptr[c + 1]]
            ln = np.asarray(M.data[M.indptr[c] : M.indptr[c + 1]])
            if touched[c] or len(nb) == 0 or touched[nb].any():
                continue
            nb_labels = ch_label[nb]
            by_label: dict[int, float] = {}
            for d_label, length in zip(nb_labels, ln):
                by_label[int(d_label)] = by_label.get(int(d_label), 0.0) + float(length)
            ok = [l for l in by_label if (l ^ 1) not in by_label]
            pool = ok if ok else list(by_label)
            target = max(pool, key=lambda l: by_label[l])
            new_label[c] = target
            touched[c] = True
            touched[nb] = True
        if new_label:
            for c, l in new_label.items():
                labels[chart == c] = l
            merged += len(new_label)
            changed = True
        if not changed:
            break
        labels = smooth_labels(labels, normals, areas, edge_faces, edge_w, 3, rng, data)
    return labels, {"merged_charts": merged, "relabelled_faces": relabelled}


def label_faces(V: np.ndarray, F: np.ndarray, config: ClassicalConfig = ClassicalConfig(), seed: int = 0):
    """Polycube labels ``(F,) int`` of the surface ``(V, F)`` (canonical frame) and a report dict."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    rng = np.random.default_rng(seed)
    normals, areas = face_normals_areas(V, F)
    edges, edge_faces = edge_topology(F)
    labels = np.argmax(normals @ DIRECTIONS.T, axis=1)
    w = _edge_weights(V, F, edges, edge_faces, normals, config)
    labels = smooth_labels(labels, normals, areas, edge_faces, w, config.smooth_sweeps, rng)
    labels, rep = repair_labels(labels, V, F, normals, areas, edges, edge_faces, w, config, rng)
    return labels, rep


# --------------------------------------------------------------------------- checks


def vertex_axes(F: np.ndarray, labels: np.ndarray, n_vertices: int) -> np.ndarray:
    """``(nv, 3) bool``: vertex touches a face whose label has that axis."""
    out = np.zeros((n_vertices, 3), dtype=bool)
    for k in range(3):
        out[F[:, k], labels // 2] = True
    return out


def label_issues(V: np.ndarray, F: np.ndarray, labels: np.ndarray) -> dict:
    """Validity checks of a labelling (counts; all zero for a clean polycube labelling).

    ``opposite_edges``: edges between opposite labels.  ``bad_charts``: charts without
    neighbours of both other axes.  ``high_valence_corners``: vertices where more than
    three charts meet.  ``turning_points``: vertices inside a border between an
    ``a``-chart and a ``b``-chart where the border reverses its direction along the third
    axis ``c`` (measured on ``V``; meaningful on the flattened surface).
    """
    F = np.asarray(F, dtype=np.int64)
    edges, edge_faces = edge_topology(F)
    n_ch, chart = charts_of(labels, edge_faces)
    la, lb = labels[edge_faces[:, 0]], labels[edge_faces[:, 1]]
    opposite = int((la == (lb ^ 1)).sum())
    ch_label = np.zeros(n_ch, dtype=np.int64)
    ch_label[chart] = labels
    ca, cb = chart[edge_faces[:, 0]], chart[edge_faces[:, 1]]
    border = ca != cb
    nb_axes = [set() for _ in range(n_ch)]
    for c, d in zip(ca[border], cb[border]):
        nb_axes[c].add(int(ch_label[d] // 2))
        nb_axes[d].add(int(ch_label[c] // 2))
    bad_charts = sum(1 for c in range(n_ch) if len(nb_axes[c] - {int(ch_label[c] // 2)}) < 2)
    # corner valence: distinct charts around each vertex
    nv = len(V)
    vc = np.unique(np.column_stack([F.ravel(), np.repeat(chart, 3)]), axis=0)
    valence = np.bincount(vc[:, 0], minlength=nv)
    high = int((valence > 3).sum())
    # turning points along borders
    turning = 0
    be = edges[border]
    bl = np.sort(np.column_stack([la[border] // 2, lb[border] // 2]), axis=1)
    for a, b in ((0, 1), (0, 2), (1, 2)):
        c = 3 - a - b
        sel = (bl[:, 0] == a) & (bl[:, 1] == b)
        if not sel.any():
            continue
        E = be[sel]
        d = V[E[:, 1], c] - V[E[:, 0], c]
        # at each border vertex of degree 2 along this border type: the two edges must move
        # the same way along c (one in, one out), i.e. the signed directions away from the
        # vertex have opposite signs
        away = np.concatenate([d, -d])
        verts = np.concatenate([E[:, 0], E[:, 1]])
        deg = np.bincount(verts, minlength=nv)
        s_pos = np.bincount(verts, weights=(away > 0).astype(float), minlength=nv)
        inner = (deg == 2) & (valence <= 2)
        turning += int((inner & ((s_pos == 2) | (s_pos == 0))).sum())
    # vertices that touch two different charts of one axis (would need two planes)
    vc_axis = np.column_stack([vc[:, 0], ch_label[vc[:, 1]] // 2])
    _, cnt = np.unique(vc_axis, axis=0, return_counts=True)
    two_planes = int((cnt > 1).sum())
    return {
        "charts": int(n_ch),
        "opposite_edges": opposite,
        "bad_charts": int(bad_charts),
        "high_valence_corners": high,
        "turning_points": int(turning),
        "two_plane_vertices": two_planes,
    }


# --------------------------------------------------------------------------- refinement


def split_constrained_edges(V: np.ndarray, F: np.ndarray, labels: np.ndarray, max_rounds: int = 8):
    """Split chart-interior edges whose ends both lie on borders with one other axis.

    Returns ``(V', F', labels', parent)`` where ``parent (nv', 2)`` gives, for each
    vertex, the two original-or-earlier vertices it is the midpoint of (a vertex of
    ``V`` is its own parent twice).
    """
    V = np.asarray(V, dtype=np.float64).copy()
    F = np.asarray(F, dtype=np.int64).copy()
    labels = labels.copy()
    parent = np.repeat(np.arange(len(V))[:, None], 2, axis=1)
    for _ in range(max_rounds):
        edges, edge_faces = edge_topology(F)
        la, lb = labels[edge_faces[:, 0]], labels[edge_faces[:, 1]]
        inside = la == lb
        ax = vertex_axes(F, labels, len(V))
        own = la // 2
        both = ax[edges[:, 0]] & ax[edges[:, 1]]
        both[np.arange(len(edges)), own] = False
        cand = np.flatnonzero(inside & both.any(axis=1))
        if len(cand) == 0:
            break
        # one split per face per round
        used = np.zeros(len(F), dtype=bool)
        chosen = []
        for e in cand:
            f, g = edge_faces[e]
            if used[f] or used[g]:
                continue
            used[f] = used[g] = True
            chosen.append(e)
        chosen = np.asarray(chosen, dtype=np.int64)
        m = len(V) + np.arange(len(chosen))
        i, j = edges[chosen, 0], edges[chosen, 1]
        V = np.vstack([V, 0.5 * (V[i] + V[j])])
        parent = np.vstack([parent, np.column_stack([i, j])])
        newF, newL = [], []
        drop = np.zeros(len(F), dtype=bool)
        for k, e in enumerate(chosen):
            a, b = edges[e]
            for f in edge_faces[e]:
                tri = F[f]
                # rotate so that the split edge is (tri[0], tri[1]) in face order
                for r in range(3):
                    t = np.roll(tri, -r)
                    if {t[0], t[1]} == {a, b}:
                        break
                p, q, s = t
                newF += [[p, m[k], s], [m[k], q, s]]
                newL += [labels[f], labels[f]]
                drop[f] = True
        F = np.vstack([F[~drop], np.asarray(newF, dtype=np.int64)])
        labels = np.concatenate([labels[~drop], np.asarray(newL, dtype=np.int64)])
    return V, F, labels, parent


# --------------------------------------------------------------------------- deformation


def _rotation_between(n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Smallest rotations ``(K, 3, 3)`` taking unit ``n`` onto unit ``d`` (row-wise)."""
    v = np.cross(n, d)
    c = np.einsum("ij,ij->i", n, d)
    s = np.linalg.norm(v, axis=1)
    K = np.zeros((len(n), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    I = np.broadcast_to(np.eye(3), K.shape)
    coef = np.where(s > 1e-12, (1.0 - c) / np.maximum(s, 1e-12) ** 2, 0.5)
    R = I + K + coef[:, None, None] * (K @ K)
    # antiparallel: rotate by pi about an axis perpendicular to d
    anti = (c < -1.0 + 1e-9) & (s < 1e-6)
    if anti.any():
        dd = d[anti]
        perp = np.cross(dd, np.where(np.abs(dd[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        perp /= np.linalg.norm(perp, axis=1, keepdims=True)
        R[anti] = 2.0 * np.einsum("ki,kj->kij", perp, perp) - np.eye(3)
    return R


def _best_rotations(E0: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Per face, the rotation ``R`` minimising ``sum_k |R e0_k - e_k|^2`` (``E0, E: (F, 3, 3)``, rows = edges)."""
    S = np.einsum("fki,fkj->fij", E, E0)  # sum_k e_k e0_k^T
    U, _, Vt = np.linalg.svd(S)
    det = np.linalg.det(U @ Vt)
    D = np.ones((len(S), 3))
    D[:, 2] = np.sign(det)
    D[D[:, 2] == 0, 2] = 1.0
    return (U * D[:, None, :]) @ Vt


def _incidence(F: np.ndarray, nv: int) -> sp.csr_matrix:
    """``(3F, nv)``: row ``k * nF + f`` is edge ``F[f, k+1] - F[f, k]``."""
    nf = len(F)
    rows = np.arange(3 * nf)
    heads = np.concatenate([F[:, 1], F[:, 2], F[:, 0]])
    tails = np.concatenate([F[:, 0], F[:, 1], F[:, 2]])
    data = np.concatenate([np.ones(3 * nf), -np.ones(3 * nf)])
    return sp.csr_matrix((data, (np.concatenate([rows, rows]), np.concatenate([heads, tails]))), shape=(3 * nf, nv))


def _face_edges(X: np.ndarray, F: np.ndarray) -> np.ndarray:
    """``(F, 3, 3)``: the three edge vectors of each face (rows), in the order of :func:`_incidence`."""
    return np.stack([X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 1]], X[F[:, 0]] - X[F[:, 2]]], axis=1)


def snap_charts(X: np.ndarray, F: np.ndarray, labels: np.ndarray, areas: np.ndarray | None = None) -> np.ndarray:
    """Make every chart exactly planar at its (area-weighted) mean coordinate along its axis.

    Charts of one axis that share a vertex are put on one plane.
    """
    X = X.copy()
    _, edge_faces = edge_topology(F)
    n_ch, chart = charts_of(labels, edge_faces)
    if areas is None:
        _, areas = face_normals_areas(X, F)
    areas = np.maximum(areas, 1e-16)
    ch_axis = np.zeros(n_ch, dtype=np.int64)
    ch_axis[chart] = labels // 2
    # union charts of one axis that share a vertex
    vc = np.unique(np.column_stack([F.ravel(), np.repeat(chart, 3)]), axis=0)
    rows, cols = [], []
    for a in range(3):
        sel = vc[ch_axis[vc[:, 1]] == a]
        if len(sel) == 0:
            continue
        order = np.argsort(sel[:, 0], kind="stable")
        s = sel[order]
        same = s[1:, 0] == s[:-1, 0]
        rows.append(s[1:, 1][same])
        cols.append(s[:-1, 1][same])
    if rows:
        r, c = np.concatenate(rows), np.concatenate(cols)
        g = sp.coo_matrix((np.ones(len(r)), (r, c)), shape=(n_ch, n_ch))
        _, group = connected_components(g, directed=False)
    else:
        group = np.arange(n_ch)
    fgroup = group[chart]
    ng = int(group.max()) + 1
    faxis = labels // 2
    fcoord = X[F, faxis[:, None]].mean(axis=1)
    num = np.bincount(fgroup, weights=areas * fcoord, minlength=ng)
    den = np.bincount(fgroup, weights=areas, minlength=ng)
    plane = num / np.maximum(den, 1e-300)
    for k in range(3):
        X[F[:, k], faxis] = plane[fgroup]
    return X


def flipped_faces(X: np.ndarray, F: np.ndarray, labels: np.ndarray, rel_area: float = 1e-10) -> np.ndarray:
    """``(F,) bool``: triangle whose normal disagrees with its label or whose area is ~0."""
    cross = np.cross(X[F[:, 1]] - X[F[:, 0]], X[F[:, 2]] - X[F[:, 0]])
    along = np.einsum("ij,ij->i", cross, DIRECTIONS[labels])
    scale = np.linalg.norm(X.max(0) - X.min(0)) ** 2
    return along <= rel_area * scale


def deform_to_polycube(
    V: np.ndarray,
    F: np.ndarray,
    labels: np.ndarray,
    config: ClassicalConfig = ClassicalConfig(),
) -> tuple[np.ndarray, dict]:
    """Flatten every chart onto a plane of its axis (see the module docstring, step 4).

    Returns the flattened vertices ``(nv, 3)`` and ``meta`` (iterations, flipped, residual).
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    nv, nf = len(V), len(F)
    D = _incidence(F, nv)
    E0 = _face_edges(V, F)
    target_dir = DIRECTIONS[labels]
    faxis = labels // 2
    X = V.copy()
    n_it = max(1, config.deform_iterations)
    weights = np.geomspace(config.flat_weight_start, config.flat_weight_end, n_it)
    block = max(1, int(config.weight_blocks))  # each block at the weight of its last iteration
    weights = weights[np.minimum((np.arange(n_it) // block + 1) * block - 1, n_it - 1)]
    mu = 1e-6
    centre = V.mean(axis=0)
    solve: dict = {}  # axis -> (weight, factorized system)
    for it in range(n_it):
        E = _face_edges(X, F)
        R = _best_rotations(E0, E)
        # normal of the rest face rotated by R, then turned onto the target axis
        n0 = np.cross(E0[:, 0], -E0[:, 2])
        n0 /= np.maximum(np.linalg.norm(n0, axis=1, keepdims=True), 1e-300)
        nr = np.einsum("fij,fj->fi", R, n0)
        Rt = _rotation_between(nr, target_dir) @ R
        T = np.einsum("fij,fkj->fki", Rt, E0)  # rotated rest edges (F, 3 edges, 3)
        for a in range(3):
            w = np.ones(nf)
            w[faxis == a] += weights[it]
            W = np.tile(w, 3)
            t = T[:, :, a].T.ravel()  # row k * nF + f
            if a not in solve or solve[a][0] != weights[it]:
                solve[a] = (weights[it], factorized((D.T @ sp.diags(W) @ D + mu * sp.identity(nv)).tocsc()))
            b = D.T @ (W * t) + mu * X[:, a]
            X[:, a] = solve[a][1](b)
        X -= X.mean(axis=0) - centre
    Xs = snap_charts(X, F, labels)
    resid = float(np.abs(Xs - X).max())
    before = int(flipped_faces(Xs, F, labels).sum())
    Xs = untangle_flat(Xs, F, labels)
    flips = flipped_faces(Xs, F, labels)
    return Xs, {"iterations": n_it, "flipped_before_untangle": before, "flipped": int(flips.sum()), "snap_residual": resid}


def untangle_flat(X: np.ndarray, F: np.ndarray, labels: np.ndarray, rounds: int = 200) -> np.ndarray:
    """Unfold the few flipped triangles a flattening leaves (zig-zag borders, turning points).

    The vertices of flipped triangles and their neighbours move, in their free
    coordinates only (those not fixed by a chart plane), to the mean of their
    neighbours; chart planes stay exact.  Stops when nothing is flipped.
    """
    X = X.copy()
    nv = len(X)
    fixed = vertex_axes(F, labels, nv)
    free = ~fixed
    edges, _ = edge_topology(F)
    src, dst = np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]]
    # a border vertex averages over the neighbours on its own border (or corners of it),
    # which straightens the border's order along its free axis; others over all neighbours
    along = (fixed[dst] | ~fixed[src]).all(axis=1) & fixed[src].any(axis=1)
    has_along = np.bincount(src[along], minlength=nv) >= 2
    use = along | ~has_along[src]
    A = sp.coo_matrix((np.ones(int(use.sum())), (src[use], dst[use])), shape=(nv, nv)).tocsr()
    deg = np.asarray(A.sum(1)).ravel()
    Aall = sp.coo_matrix((np.ones(len(src)), (src, dst)), shape=(nv, nv)).tocsr()
    best, best_n = X, int(flipped_faces(X, F, labels).sum())
    for _ in range(rounds):
        bad = flipped_faces(X, F, labels)
        if bad.sum() < best_n:
            best, best_n = X, int(bad.sum())
        if not bad.any():
            break
        act = np.zeros(nv, dtype=bool)
        act[F[bad].ravel()] = True
        act = act | (Aall @ act.astype(float) > 0)  # and their neighbours
        mean = (A @ X) / np.maximum(deg, 1)[:, None]
        move = act[:, None] & free
        X = np.where(move, 0.5 * X + 0.5 * mean, X)
    if int(flipped_faces(X, F, labels).sum()) < best_n:
        best = X
    return best


# --------------------------------------------------------------------------- the map and the source


@dataclasses.dataclass
class SurfaceMap:
    """Exact map from the polycube (the flattened surface ``(Vp, F)``) to the part ``(V, F)``.

    A point on the polycube surface (closer than ``surface_tol``) goes to the same
    barycentric position on the same triangle of the part; a point inside goes by the
    inverse-distance-weighted displacement of the nearest flattened vertices (a smooth
    volumetric extension for interior hex nodes).
    """

    Vp: np.ndarray
    F: np.ndarray
    V: np.ndarray
    surface_tol: float = 1e-3
    k: int = 16
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self._tree = cKDTree(self.Vp)
        self._disp = self.V - self.Vp

    def project(self, points: np.ndarray):
        """Closest point on the polycube mesh: ``(face_ids, barycentrics, distance)``."""
        import trimesh

        mesh = trimesh.Trimesh(self.Vp, self.F, process=False)
        closest, dist, tri = trimesh.proximity.closest_point(mesh, points)
        tri = np.asarray(tri, dtype=np.int64)
        bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
        bary = np.clip(np.nan_to_num(bary), 0.0, None)
        s = bary.sum(1, keepdims=True)
        bary = np.where(s > 0, bary / np.where(s > 0, s, 1), 1.0 / 3.0)
        return tri, bary, np.asarray(dist)

    def map_points(self, points: np.ndarray) -> np.ndarray:
        P = np.asarray(points, dtype=np.float64)
        out = np.empty_like(P)
        if len(P) == 0:
            return out
        d, idx = self._tree.query(P, k=min(self.k, len(self.Vp)))
        w = 1.0 / np.maximum(d, 1e-9) ** 2
        out[:] = P + np.einsum("kn,knd->kd", w, self._disp[idx]) / w.sum(1, keepdims=True)
        near = d[:, 0] < 0.25  # only points that can be near the surface are projected
        if near.any():
            sel = np.flatnonzero(near)
            tri, bary, dist = self.project(P[sel])
            on = dist <= self.surface_tol
            out[sel[on]] = interpolate(self.V, self.F, tri[on], bary[on])
        return out


@dataclasses.dataclass
class ClassicalCloud(PolycubeCloud):
    """A :class:`PolycubeCloud` that also carries the flattened surface and the exact map.

    Extra attributes (saved with the cloud): ``polycube_vertices (nv, 3)`` (flattened
    surface), ``surface_vertices (nv, 3)`` (the same vertices on the part, canonical
    frame), ``surface_faces (nf, 3)`` and ``face_labels (nf,)``; a source that knows its
    solid exactly (the voxel polycube) also gives ``grid_x, grid_y, grid_z`` (plane
    coordinates) and ``occupancy``: :meth:`exact_polycube`.
    """

    polycube_vertices: np.ndarray | None = None
    surface_vertices: np.ndarray | None = None
    surface_faces: np.ndarray | None = None
    face_labels: np.ndarray | None = None
    grid_x: np.ndarray | None = None
    grid_y: np.ndarray | None = None
    grid_z: np.ndarray | None = None
    occupancy: np.ndarray | None = None

    def exact_polycube(self):
        """The solid the cloud was sampled from (:class:`~polycubenet.data.Polycube`), or None
        when the source does not give it (the flattening: its solid is recovered by extraction)."""
        from .data import Polycube

        if any(a is None for a in (self.grid_x, self.grid_y, self.grid_z, self.occupancy)):
            return None
        return Polycube(np.asarray(self.grid_x, float), np.asarray(self.grid_y, float), np.asarray(self.grid_z, float),
                        np.asarray(self.occupancy, bool), meta={})

    def correspondence(self) -> SurfaceMap:
        """The exact polycube -> part map (``map_points`` like registration's Correspondence)."""
        return SurfaceMap(
            np.asarray(self.polycube_vertices, float),
            np.asarray(self.surface_faces, np.int64),
            np.asarray(self.surface_vertices, float),
            meta={"method": f"{self.meta.get('provenance', 'classical')} (exact, barycentric on the flattened surface)"},
        )


def relabel_flipped(V: np.ndarray, F: np.ndarray, labels: np.ndarray, flipped: np.ndarray) -> np.ndarray:
    """Give each flipped triangle the label of an edge neighbour (the one whose axis best
    fits the triangle's normal on the part), which removes the fold of a turning point
    or a zig-zag border; neighbours whose label is opposite to another neighbour's are
    avoided."""
    labels = labels.copy()
    normals, _ = face_normals_areas(V, F)
    _, edge_faces = edge_topology(F)
    nbrs = [[] for _ in range(len(F))]
    for f, g in edge_faces[np.isin(edge_faces, np.flatnonzero(flipped)).any(1)]:
        nbrs[f].append(g)
        nbrs[g].append(f)
    new = labels.copy()
    for f in np.flatnonzero(flipped):
        nl = {int(labels[g]) for g in nbrs[f]} - {int(labels[f])}
        ok = [l for l in nl if (l ^ 1) not in {int(labels[g]) for g in nbrs[f]}]
        pool = ok or list(nl)
        if pool:
            new[f] = max(pool, key=lambda l: float(normals[f] @ DIRECTIONS[l]))
    return new


def decimate(V: np.ndarray, F: np.ndarray, n_faces: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Quadric decimation of ``(V, F)`` to about ``n_faces`` triangles, or None when the result
    is not a closed, self-intersection-free manifold of the same genus."""
    from ._o3d import open3d as o3d

    from .polycube import surface_genus

    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F.astype(np.int32)))
    d = mesh.simplify_quadric_decimation(int(n_faces))
    d.remove_unreferenced_vertices()
    Vd, Fd = np.asarray(d.vertices, dtype=np.float64), np.asarray(d.triangles, dtype=np.int64)
    try:
        same = surface_genus(Fd) == surface_genus(F)
    except PolycubeError:
        return None
    if not same or not d.is_vertex_manifold() or d.is_self_intersecting():
        return None
    _, areas = face_normals_areas(Vd, Fd)
    if (areas <= 1e-14).any():
        return None
    return Vd, Fd


def winding_numbers(X: np.ndarray, F: np.ndarray, Q: np.ndarray, chunk: int = 128) -> np.ndarray:
    """Generalised winding number ``(K,)`` of the closed triangle surface ``(X, F)`` at the
    points ``Q (K, 3)`` (sum of signed solid angles / 4 pi; robust to a few folds)."""
    T = np.asarray(X, dtype=np.float64)[np.asarray(F, dtype=np.int64)]
    out = np.zeros(len(Q))
    for i in range(0, len(Q), chunk):
        q = Q[i : i + chunk, None, :]
        A, B, C = T[None, :, 0] - q, T[None, :, 1] - q, T[None, :, 2] - q
        a, b, c = (np.linalg.norm(M, axis=2) for M in (A, B, C))
        det = np.einsum("qfi,qfi->qf", A, np.cross(B, C))
        den = (a * b * c + np.einsum("qfi,qfi->qf", A, B) * c + np.einsum("qfi,qfi->qf", B, C) * a
               + np.einsum("qfi,qfi->qf", C, A) * b)
        out[i : i + chunk] = np.arctan2(det, den).sum(axis=1) / (2.0 * np.pi)
    return out


def flat_structure(Xp: np.ndarray, F: np.ndarray, labels: np.ndarray) -> dict:
    """The polycube that the flattened surface ``(Xp, F)`` bounds, read off directly.

    The grid is the distinct chart planes of each axis; a cell is solid when the
    surface's winding number at its centre exceeds 1/2.  Returns ``grid``, ``occupancy``,
    ``reason`` (why it is not a valid polycube, or None) and ``genus`` (None when invalid).
    """
    from .polycube import check_occupancy, solid_genus

    grid = []
    for a in range(3):
        c = np.unique(Xp[F[labels // 2 == a, 0], a])
        if len(c) < 2:
            return {"grid": None, "occupancy": None, "reason": f"fewer than 2 planes on axis {'xyz'[a]}", "genus": None}
        grid.append(c)
    cen = np.meshgrid(*[0.5 * (g[1:] + g[:-1]) for g in grid], indexing="ij")
    Q = np.stack([x.ravel() for x in cen], axis=1)
    occ = (winding_numbers(Xp, F, Q) > 0.5).reshape(cen[0].shape)
    reason = check_occupancy(occ)
    genus = int(solid_genus(occ)) if reason is None else None
    return {"grid": grid, "occupancy": occ, "reason": reason, "genus": genus}


def space_planes(Xp: np.ndarray, F: np.ndarray, labels: np.ndarray, gap: float) -> np.ndarray:
    """Move the distinct chart planes of every axis at least ``gap`` apart.

    Each coordinate goes through a monotone piecewise-linear map that sends the sorted
    planes ``p_0 < p_1 < ...`` to ``q_0 = p_0, q_{i+1} = q_i + max(p_{i+1} - p_i, gap)``
    (slope 1 outside).  A map ``(x, y, z) -> (f(x), g(y), h(z))`` with increasing ``f, g,
    h`` is an orientation-preserving homeomorphism that keeps every chart on a plane of
    its axis, so the flattened surface stays exactly as (in)jective as it was and bounds
    the same polycube -- but two planes of different charts can no longer be so close
    that the structure extraction, which cannot resolve planes closer than the cloud's
    point spacing, merges them (closing a handle or a thin slot).
    """
    X = np.array(Xp, dtype=np.float64, copy=True)
    F = np.asarray(F, dtype=np.int64)
    for a in range(3):
        p = np.unique(X[F[labels // 2 == a, 0], a])
        if len(p) < 2:
            continue
        q = p[0] + np.concatenate([[0.0], np.cumsum(np.maximum(np.diff(p), gap))])
        x = X[:, a]
        y = np.interp(x, p, q)
        y = np.where(x < p[0], x, y)
        y = np.where(x > p[-1], x - p[-1] + q[-1], y)
        X[:, a] = y
    return X


def _orientations(n: int) -> list[np.ndarray]:
    """The identity, then ``n`` fixed rotations (turns about the axes, then seeded random ones)."""
    from scipy.spatial.transform import Rotation

    rots = [np.eye(3)]
    turns = [("z", 22.5), ("y", 22.5), ("x", 22.5), ("z", 45.0), ("y", 45.0), ("x", 45.0)]
    for ax, deg in turns[:n]:
        rots.append(Rotation.from_euler(ax, deg, degrees=True).as_matrix())
    k = 0
    while len(rots) < n + 1:
        rots.append(Rotation.random(random_state=1000 + k).as_matrix())
        k += 1
    return rots


def _flatten(V: np.ndarray, F: np.ndarray, config: ClassicalConfig, seed: int):
    """Label, repair, refine and flatten ``(V, F)`` once per compactness retry; returns the
    attempt with the fewest flipped triangles ``(Vp, Vs, Fs, labels, info)`` and all reports."""
    attempts = []
    best = None
    cfg = config
    seen: list = []  # (labels, attempt index) of every labelling flattened so far
    for attempt in range(config.retries + 1):
        t0 = time.perf_counter()
        labels, rep = label_faces(V, F, cfg, seed=seed + attempt)
        t1 = time.perf_counter()
        same = next((i for lab, i in seen if np.array_equal(lab, labels)), None)
        if same is not None:
            # a higher compactness that gives the same labels: everything after the labelling ignores the
            # compactness, so this flattening would be the same one (pyramid blocks: 2 of every 3 attempts)
            attempts.append({**attempts[same], "compactness": cfg.compactness, "same_labels_as": same,
                             "time_label": t1 - t0, "time_refine": 0.0, "time_deform": 0.0})
            cfg = dataclasses.replace(cfg, compactness=cfg.compactness * 2.0)
            continue
        seen.append((labels, len(attempts)))
        Vp, Vs, Fs, ls, dmeta, fix, t_ref, t_def = flatten_labelled(V, F, labels, cfg)
        issues = label_issues(Vs, Fs, ls)
        info = {
            "compactness": cfg.compactness, **rep, **issues, **dmeta, "fix_rounds": fix,
            "faces_refined": int(len(Fs)),
            "time_label": t1 - t0, "time_refine": t_ref, "time_deform": t_def,
        }
        attempts.append(info)
        if best is None or dmeta["flipped"] < best[-1]["flipped"]:
            best = (Vp, Vs, Fs, ls, info)
        if dmeta["flipped"] == 0:
            break
        cfg = dataclasses.replace(cfg, compactness=cfg.compactness * 2.0)
    return best, attempts


def flatten_labelled(V: np.ndarray, F: np.ndarray, labels: np.ndarray, config: ClassicalConfig):
    """Refine and flatten a labelled surface (steps 3-4): flipped triangles are relabelled
    (:func:`relabel_flipped`) and the surface flattened again, up to ``config.fix_rounds`` times,
    while that lowers the flips.  Returns ``(Vp, Vs, Fs, labels, deform meta, fix rounds,
    seconds refining, seconds deforming)``."""
    Vs, Fs, ls = V, F, labels
    t_ref = t_def = 0.0
    kept = None
    for fix in range(config.fix_rounds + 1):
        ta = time.perf_counter()
        Vs, Fs, ls, _ = split_constrained_edges(Vs, Fs, ls)
        tb = time.perf_counter()
        Vp, dmeta = deform_to_polycube(Vs, Fs, ls, config)
        tc = time.perf_counter()
        t_ref += tb - ta
        t_def += tc - tb
        if kept is not None and dmeta["flipped"] >= kept[4]["flipped"]:
            break  # the relabelling did not help: keep the previous flattening
        kept = (Vp, Vs, Fs, ls, dmeta, fix)
        if dmeta["flipped"] == 0 or fix == config.fix_rounds:
            break
        ls = relabel_flipped(Vs, Fs, ls, flipped_faces(Vp, Fs, ls))
    return (*kept, t_ref, t_def)


def classical_polycube(V: np.ndarray, F: np.ndarray, config: ClassicalConfig = ClassicalConfig(), seed: int = 0):
    """Label, repair, refine and flatten ``(V, F)`` (canonical frame).

    Flipped triangles of a flattening are relabelled (:func:`relabel_flipped`) and the
    surface flattened again, up to ``config.fix_rounds`` times; if flips remain, the
    labelling restarts with doubled compactness (``config.retries`` times).  When the
    solid the flattened surface bounds (:func:`flat_structure`) is not a valid polycube
    of the part's genus, all of this is repeated on the part turned by the rotations of
    :func:`_orientations` (up to ``config.orientations``, within ``config.orientation_budget``),
    until one is.

    Returns ``(Vp, Vs, Fs, labels, meta)``: the flattened vertices (polycube domain), the
    refined surface's vertices on the part (in the frame of ``V``, whatever the rotation),
    its faces and labels, and a report (per attempt: labelling checks, flips, times;
    ``orientation``: the index of the rotation used, ``structure_genus``).  Among the
    orientations tried, a valid polycube of the right genus wins, then fewer flips.
    """
    from .polycube import surface_genus

    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    decimated = None
    if len(F) > config.max_faces:
        dec = decimate(V, F, config.max_faces)
        if dec is not None:
            decimated = [int(len(F)), int(len(dec[1]))]
            V, F = dec
    try:
        genus = surface_genus(F)
    except PolycubeError:
        genus = None
    attempts = []
    chosen = None
    tried = []
    max_tries = max(1, int(config.orientation_budget) // max(1, len(F)))
    for k, R in enumerate(_orientations(max(0, config.orientations))):
        if k >= max_tries:
            break
        (Vp, Vs, Fs, ls, info), att = _flatten(V @ R.T, F, config, seed)
        st = flat_structure(Vp, Fs, ls)
        ok = st["reason"] is None and (genus is None or st["genus"] == genus)
        info = {**info, "orientation": k, "structure_genus": st["genus"], "structure_reason": st["reason"]}
        for a in att:
            a["orientation"] = k
        attempts += att
        tried.append({"orientation": k, "flipped": info["flipped"], "structure_genus": st["genus"],
                      "structure_reason": st["reason"]})
        cand = (not ok, info["flipped"], k)
        if chosen is None or cand < chosen[0]:
            chosen = (cand, (Vp, Vs @ R, Fs, ls, info))
        if ok:
            break
    Vp, Vs, Fs, ls, info = chosen[1]
    return Vp, Vs, Fs, ls, {"attempts": attempts, "orientations_tried": tried, "orientations_allowed": max_tries,
                            "decimated": decimated,
                            "part_genus": genus, **info}


@dataclasses.dataclass
class ClassicalSource:
    """Polycube source (``source(sample, V, F, config) -> PolycubeCloud``) built from the
    surface itself; the returned :class:`ClassicalCloud` carries the exact map."""

    config: ClassicalConfig = ClassicalConfig()

    def __call__(self, sample, V, F, config) -> ClassicalCloud:
        seed = int(getattr(config, "seed", 0))
        n = int(getattr(config, "n_polycube", 16384))
        Vp, Vs, Fs, ls, meta = classical_polycube(V, F, self.config, seed=seed)
        s = poisson_disk(Vp, Fs, n, seed=seed + 31)
        meta["plane_gap"] = None
        if not self._extracts(s.points, DIRECTIONS[ls[s.face_ids]], meta.get("part_genus"), config):
            # planes too close for the extraction to resolve: space them apart
            _, areas = face_normals_areas(Vp, Fs)
            spacing = float(np.sqrt(areas.sum() / (n * np.sqrt(3.0) / 2.0)))
            gap = max(self.config.min_plane_gap, self.config.plane_gap_spacings * spacing)
            Vp = space_planes(Vp, Fs, ls, gap)
            meta["plane_gap"] = gap
            s = poisson_disk(Vp, Fs, n, seed=seed + 31)
        normals = DIRECTIONS[ls[s.face_ids]]
        meta = {"provenance": "classical", **_plain(meta)}
        return ClassicalCloud(
            s.points, normals, meta=meta,
            polycube_vertices=Vp, surface_vertices=Vs, surface_faces=Fs, face_labels=ls,
        )


    @staticmethod
    def _extracts(points, normals, genus, config) -> bool:
        """Whether the pipeline's cleanup + structure extraction accept this cloud, without the
        fallbacks meant for generated clouds (flattened ramps, a wider kernel): where only those would
        accept it, the planes are too close and get spaced apart, as before they existed."""
        from .cleanup import remove_outliers
        from .structure import ExtractConfig, extract

        P, N, _ = remove_outliers(points, normals)
        cfg = getattr(config, "extract", ExtractConfig()).for_exact_clouds()
        try:
            extract(P, N, genus=genus, config=cfg)
        except PolycubeError:
            return False
        return True


def _plain(d):
    if isinstance(d, dict):
        return {str(k): _plain(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_plain(v) for v in d]
    if isinstance(d, (np.integer,)):
        return int(d)
    if isinstance(d, (np.floating,)):
        return float(d)
    return d
