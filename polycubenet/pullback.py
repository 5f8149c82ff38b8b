"""Pull a polycube-domain hex mesh back onto the part (the last geometric stage of the spine).

:func:`pull_back` takes the regular hex mesh of a polycube (:func:`polycubenet.hexmesh.partition`,
positions in the polycube domain), a map ``to_part`` from the polycube domain to the part
(the exact synthetic map in tests, later the registration's displacement field, which may be
a few percent of the diagonal off) and the part's true triangle surface ``(V, F)``, and
returns a hex mesh of the part with the same connectivity plus one pillow layer.

Steps (each timed and measured in ``meta``):

1. **Boundary.**  Boundary nodes are classified by the distinct outward normals of their
   incident boundary quads in the polycube domain (:func:`classify_boundary`: 1 = face node,
   2 = edge node, 3+ = corner).  Their images under ``to_part`` are projected onto ``(V, F)``.
   The part surface gets a chart labelling (polycube patch label ``(axis, sign)``, see
   :data:`LABELS`) transferred from the nearest mapped face nodes whose mapped normal agrees
   with the triangle's (:func:`chart_labels`); every node is projected onto the triangles of
   its own chart(s) only.  Edge nodes snap to a sharp feature curve of the part (dihedral angle
   above ``feature_angle_deg``) that is near and parallel to the mapped polycube edge, corners
   to a feature vertex.  A snap that flattens or folds a boundary quad corner is undone
   (:func:`quad_corner_quality`); a chart projection that lands much farther than the free
   closest point falls back to the free one.  Both are counted in ``meta["projection"]``.
   **Coverage** (step 1b, :func:`fit_coverage`): the projected nodes are then slid on the
   surface, under the same constraints, so that the boundary quads cover the part: a map a
   percent off leaves the polycube's edges beside the part's rounded edges and holes, where
   quads cut across the rounding (most of the Hausdorff distance); each iteration moves every
   node by the mean of the two-sided residuals (surface samples to the quads, quad samples to
   the surface) that its quads carry.
2. **Interior.**  A sparse graph-Laplacian (hex edges, uniform weights) solve with the boundary
   fixed (:func:`harmonic_extension`): by default of the *correction* ``projected - to_part(p)``,
   added to ``to_part`` of the interior nodes (the map is evaluable anywhere, and a smooth map
   is a far better interior than a harmonic one); ``interior="harmonic"`` solves for the
   positions themselves.
3. **Untangle + optimise** (:func:`optimise_quality`).  Adam on the vertex positions, with the
   analytic gradient (numpy; torch autograd was 25x slower on this CPU) of a smooth hinge
   ``softplus((t - s) / w) w`` over the nine verdict terms ``s`` of every hex's scaled Jacobian
   (8 corners + centre, normalised vectors, exactly what
   :func:`polycubenet.quality.scaled_jacobian` measures), a small push on the mean and a pull
   towards the start positions (weak for interior and face nodes, strong for edge and corner
   nodes, which sit where the part turns).  Boundary nodes are re-projected after every step
   onto their chart / feature curve (snapped corners stay fixed).  Only poor hexes and their
   surroundings move.  The best state (minimum SJ first, then the mean) is kept.  With
   pillowing this first run only untangles.
4. **Pillowing** (:func:`pillow`).  Every boundary quad gets a new hex between it and inward
   copies of its nodes; the old hexes use the inner copies.  No hex then has two faces on the
   boundary.  Step 3 runs again.  Then, if a hex corner is still poor (or the mesh is not
   valid), its boundary nodes are *released* (unpinned from features, weaker pull) and step 3
   runs once more; a release that moves a valid mesh away from the part is undone.
   Last, the coverage fit runs again on the whole mesh, guarded (:func:`guarded_coverage`): a
   surface node (with its inner pillow copy) keeps a move only if no incident hex falls below
   ``min(final_coverage_sj, its SJ before)``, so a valid mesh stays valid.  A result that is
   not valid is recomputed once without step 1b, and the valid one kept.
5. **Smoothing** (:func:`guarded_smooth`).  Quality-guarded Laplacian sweeps on the interior
   nodes: all nodes move at once, and moves that lower the minimum (or the sum) of the SJ of
   their incident hexes are undone, so the mesh minimum never drops.

6. **Mending uncovered spots** (:func:`mend_spots`, ``capture_spots``).  A valid mesh still farther
   from the part than the Hausdorff bar is mostly so at a few spots: a short sharp feature no polycube
   edge maps to (a knife edge where a slanted cut crosses a hole or notch, a corner of a pocket).  The
   coverage fit moves nodes by the mean residual, which leaves such a spot cut; here the nearest surface
   nodes move onto the farthest uncovered samples of the part, one node per spot and round, each move
   undone if a hex falls below ``min(capture_sj, its SJ before)`` (:func:`guarded_spot_capture`), the
   interior is smoothed again, and the result is kept only when it is within the bar.  A mesh more than
   ``capture_max`` (4 %) off misses a feature rather than a spot and is left as it is.

A result with an inverted or degenerate hex is still returned, with ``meta["valid"] = False``
and a sentence in ``meta["warnings"]``; it is never returned silently.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import factorized
from scipy.spatial import cKDTree

from . import tol
from .data import HexMesh
from .hexmesh import HEX_EDGES, boundary_quads, boundary_vertex_mask, quads_to_triangles
from .quality import CORNER_FRAMES, corner_sj_and_degenerate, scaled_jacobian_and_degenerate  # verdict's corner order

#: polycube patch labels: label ``2 * axis + (sign > 0)``
LABELS = ("-x", "+x", "-y", "+y", "-z", "+z")


# node kinds for the boundary constraint
_CHART, _CURVE, _FIXED, _FREE = 0, 1, 2, 3

#: "untangled" for the optimisation before pillowing: every hex's SJ above this
_UNTANGLED = 0.01

#: the optimiser's active set (poor hexes and their surroundings) is refreshed this often
_REFRESH = 20

#: the optimiser first raises the minimum SJ to this, then the mean (+ a quarter of the minimum)
_SJ_FLOOR = 0.3


@dataclasses.dataclass(frozen=True)
class PullbackConfig:
    """Parameters of :func:`pull_back` (frozen).  Lengths are relative to the local element
    size unless a field says otherwise.

    Attributes
    ----------
    pillow : bool
        Add one pillow layer (step 4).
    interior : str
        ``"correction"`` (harmonic extension of the boundary correction added to ``to_part``
        of the interior nodes) or ``"harmonic"`` (harmonic positions).
    chart_projection : bool
        Project boundary nodes onto their own chart(s) only (else the free closest point).
    snap_features : bool
        Snap edge / corner nodes to sharp feature curves / vertices of the part.
    feature_angle_deg : float
        A surface edge whose dihedral angle (between the face normals) exceeds this is a
        sharp feature.  50 rather than 30 degrees: at 30 the two lines of a 45-degree
        chamfer and the facets of a coarsely tessellated fillet count too, and neither is
        where the (rounded) polycube edge goes; a slanted face (ramp, up to 35 degrees)
        keeps a 90-degree edge above 55 degrees.
    snap_radius : float
        Snap only to features closer than this x the node's local edge length.
    snap_align_deg : float
        An edge node snaps only to feature segments within this angle of its mapped edge.
    snap_quad_quality : float
        A snap is undone when it leaves a corner of a boundary quad with a planar scaled
        Jacobian below this (and below its unsnapped value): e.g. a corner pinned to where a
        fillet starts, which flattens its quads.
    fallback_excess : float
        A constrained projection more than this x the local edge length farther than the
        free one falls back to the free one (counted in ``meta["projection"]``).
    label_normal_weight : float
        Weight of the normal disagreement ``1 - n_tri . n_node`` against the distance (in
        local edge lengths) when labelling triangles.
    optimise_iterations : int
        Maximum Adam steps per optimisation run.
    optimise_patience : int
        Stop after this many steps without improvement.
    learning_rate : float
        Adam step, x the mean edge length.
    sj_target : float
        The hinge acts on verdict terms below this.
    sj_softness : float
        Width of the softplus hinge.
    mean_weight : float
        Weight of ``mean(1 - sj)`` (raises the average).
    regularisation : float
        Weight of the pull of interior nodes towards their start positions (per squared
        edge length).
    boundary_regularisation : float
        The same for boundary nodes: they start where the map put them (projected), which is
        what keeps the boundary close to the part; sliding them only pays where quality needs it.
    edge_regularisation : float
        The same for edge and corner nodes that are not pinned to a feature curve: they sit
        where the part turns, so sliding them cuts the part (Hausdorff).
    untangle_only_before_pillow : bool
        With ``pillow``, the optimisation before pillowing stops as soon as no hex is inverted
        (the pillow layer changes the hexes the quality terms are about).
    pillow_thickness : float
        Inner copies go about this x the local edge length inward (see :func:`pillow`).
    pillow_fix_boundary : bool
        After pillowing, keep the surface nodes where the projection put them and let only
        the inner copies and the interior move: letting them slide to help the pillow hexes
        cuts corners at features (on held-out pairs the Hausdorff distance fell from 2.6 %
        to 1.0 % of the diagonal on the worst part, at a small cost in SJ).
    release_sj : float
        After the optimisation, the boundary nodes of every hex corner whose verdict term is
        below this (the corner and its three edge neighbours) are released: unpinned from a
        feature curve or vertex (counted in ``meta["projection"]["released"]``) and given the
        weaker ``release_regularisation``; then the optimisation runs again (at most
        ``release_rounds`` times).
    release_rounds : int
    release_regularisation : float
        Pull of a released node towards where it was (a released corner may cut the part's
        corner, which costs Hausdorff distance, but only where a hex would be poor otherwise).
    release_max_deviation : float
        When the mesh was already valid, the release is undone if, after the final coverage
        fit (step 4c, which wins back most of what a release costs), the boundary is farther
        from the part (:func:`boundary_deviation`, relative to the diagonal) than this and
        than 1.1 x before the release: validity first, then fidelity, then the minimum SJ.
        The undone state gets the final coverage fit instead.
    release_retry_regularisation : float
        When a release is undone, the release runs once more from the unreleased state with this (stronger)
        pull on the released nodes, and is kept when it is valid, better in minimum SJ than the undone state
        and within the same deviation bound (``meta["projection"]["re_released"]``).  The weak pull lets a
        released node leave the part's corner where a hex wants it; the strong one moves it only as far as
        the poor corner needs.  Measured on never-seen machined parts: machined_31_000's classical polycube
        (3,000 hexes) 0.084 -> 0.313 at 0.58 % of the diagonal; its realised learned polycube 0.000 -> 0.309
        at 0.4 %.  Not above ``release_regularisation``: off.
    smoothing_sweeps : int
        Guarded Laplacian sweeps (step 5).
    smoothing_step : float
        Fraction of the way to the neighbour average per sweep.
    coverage_iterations : int
        Iterations of the coverage fit after the projection (step 1b, :func:`fit_coverage`):
        each boundary node moves by the weighted mean of the residuals it is responsible for
        (surface samples to their closest point on the boundary quads, and sample points of the
        quads to their closest point on the surface), then is projected again under its
        constraint.  0 turns it off.  With the final guarded pass (``final_coverage_*``) it took
        the median Hausdorff distance of the 50 held-out pairs of ``benchmarks/bench_spine.py``
        (registered map) from 1.36 % to 0.69 % of the diagonal.
    coverage_samples : int
        Random surface samples the fit uses (plus the surface's vertices).
    coverage_step : float
        Fraction of the mean residual a node moves per iteration.
    coverage_damping : float
        A node's residual weight is divided by its own weight plus this x the median node
        weight, so a node touched by few samples moves less.
    coverage_max_move : float
        Largest move per iteration, x the local edge length.
    coverage_h2s_weight : float
        Weight of the quad-to-surface residuals against the surface-to-quad ones.
    final_coverage_iterations : int
        Iterations of the coverage fit on the finished mesh (step 4c, :func:`guarded_coverage`),
        where a move that would take a hex below ``min(final_coverage_sj, its SJ before)`` is
        undone: it wins back what the release of step 4 cost.  0 turns it off.
    final_coverage_sj : float
    final_coverage_follow : bool
        In the final fit, a surface node's inner pillow copy moves with it (keeps the pillow
        hex's shape, so fewer moves are undone).
    retry_min_sj : float
        An invalid result at least this good is pulled back once more without the coverage fit.
    snap_corners : bool
        After the final fit, bring a surface node onto each corner of the part (three or more sharp
        edges) that no node is near (:func:`guarded_corner_snap`, under the same quality guard).
    capture_spots : bool
        A valid mesh farther from the part than the Hausdorff bar (:data:`polycubenet.tol.HAUSDORFF_REL_MAX`,
        relative to the part's own diagonal) gets its surface nodes moved onto the spots of the part it leaves
        uncovered, then the interior smoothed again, and is kept so when that brings it within the bar
        (:func:`mend_spots`).  Meshes within the bar are left as they are.
    capture_target : float
        Spots farther than this (relative to the diagonal) are captured once the capture runs.
    capture_max : float
        A mesh farther off the part than this (relative to the diagonal) is not mended: so far off, the
        polycube misses a feature (structure, not a spot), and the capture would try thousands of moves in
        vain (session 46: 143 of 160 s on a never-seen block 8.9 % off).  Every never-seen part the mend brought
        within the bar (sessions 45-46) was at most 2.4 % off before; the tests' sheared L-block, 3.2 %.
    capture_tries : int
        At most this many surface nodes tried per capture round (the farthest spots first).
    capture_sj : float
        The capture's quality guard: no hex goes below ``min(capture_sj, its SJ before)``.  Lower than
        ``final_coverage_sj``: a mesh off the part fails, one at 0.22 is above the quality bar (0.2).
    ease_spots : bool
        Step 7 (:func:`ease_poor_hexes`): a mesh that is not valid, or valid under ``ease_below``, with at most
        ``ease_max_hexes`` hexes under ``ease_below + ease_margin``, is untangled once more around those hexes
        with the boundary nodes there allowed up to ``ease_slack`` off the part's surface; kept only when it is
        then valid (and, if it was valid before, better and no farther off the part than the bar or than before).
    ease_below : float
        A valid mesh whose minimum SJ is at least this is left as it is.  Inside the pipeline it is the
        pipeline's quality bar (``PipelineConfig`` sets it from ``min_sj`` when that is not None); this default
        is for the pull-back used alone.
    ease_margin : float
        The hexes to ease: those under ``ease_below + ease_margin`` (0.22 at the pipeline's default bar), with
        ``ease_rings`` rings of their neighbours.
    ease_rings : int
        Rings of neighbouring hexes whose nodes move with the poor hexes' own.
    ease_max_hexes : int
        More poor hexes than this is a fold of the map, not a spot: not eased.
    ease_slack : float
        How far (relative to the diagonal) an eased boundary node may stay off the part's surface.  Session 49,
        machined_103_012 (a 151-degree knife edge, 4 inverted hexes): held on the surface the easing reaches
        SJ 0.08; with 0.002 of slack 0.25, and the mesh 0.88 % off the part (0.76 % before).
    """

    pillow: bool = True
    interior: str = "correction"
    chart_projection: bool = True
    snap_features: bool = True
    feature_angle_deg: float = 50.0
    snap_radius: float = 0.5
    snap_align_deg: float = 35.0
    snap_quad_quality: float = 0.3
    fallback_excess: float = 1.0
    label_normal_weight: float = 2.0
    optimise_iterations: int = 400
    optimise_patience: int = 40
    learning_rate: float = 0.02
    sj_target: float = 0.6
    sj_softness: float = 0.05
    mean_weight: float = 0.05
    regularisation: float = 1e-3
    boundary_regularisation: float = 1e-2
    edge_regularisation: float = 0.3
    untangle_only_before_pillow: bool = True
    pillow_thickness: float = 0.35
    pillow_fix_boundary: bool = True
    release_sj: float = 0.35
    release_rounds: int = 3
    release_regularisation: float = 0.03
    release_max_deviation: float = 0.8 * tol.HAUSDORFF_REL_MAX
    release_retry_regularisation: float = 0.3
    smoothing_sweeps: int = 5
    smoothing_step: float = 0.5
    coverage_iterations: int = 25
    coverage_samples: int = 30000
    coverage_step: float = 1.0
    coverage_damping: float = 0.5
    coverage_max_move: float = 0.3
    coverage_h2s_weight: float = 1.0
    final_coverage_iterations: int = 10
    final_coverage_sj: float = 0.3
    final_coverage_follow: bool = True
    #: a result that is not valid is recomputed another way (without the coverage fit; with the other
    #: interior mode for the classical map) only when its minimum SJ is at least this: a few barely
    #: inverted hexes can tip; a folded map (-0.9 on the helical groove, -0.1 on HexGen mount2) never
    #: did in the 4 variants measured on those, which cost 36-62 s before the voxel polycube meshed them
    retry_min_sj: float = -0.05
    snap_corners: bool = True
    capture_spots: bool = True
    capture_target: float = 0.8 * tol.HAUSDORFF_REL_MAX
    capture_max: float = 4.0 * tol.HAUSDORFF_REL_MAX
    capture_tries: int = 200
    capture_sj: float = 0.22
    ease_spots: bool = True
    ease_below: float = 0.2
    ease_margin: float = 0.02
    ease_rings: int = 2
    ease_max_hexes: int = 64
    ease_slack: float = 0.2 * tol.HAUSDORFF_REL_MAX

    def __post_init__(self):
        if self.interior not in ("correction", "harmonic"):
            raise ValueError(f"interior must be 'correction' or 'harmonic'; got {self.interior!r}")
        for name in ("snap_radius", "learning_rate", "sj_softness", "fallback_excess"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive; got {getattr(self, name)}")
        if not 0 < self.pillow_thickness <= 0.5:
            raise ValueError(f"pillow_thickness must be in (0, 0.5]; got {self.pillow_thickness}")
        if not 0 < self.smoothing_step <= 1:
            raise ValueError(f"smoothing_step must be in (0, 1]; got {self.smoothing_step}")
        if not 0 <= self.release_sj < 1:
            raise ValueError(f"release_sj must be in [0, 1); got {self.release_sj}")
        if min(self.regularisation, self.boundary_regularisation, self.edge_regularisation,
               self.release_regularisation, self.release_retry_regularisation) < 0:
            raise ValueError("regularisation weights must be non-negative")
        if min(self.coverage_iterations, self.final_coverage_iterations) < 0:
            raise ValueError("coverage iteration counts must be non-negative")
        if self.coverage_samples < 1 or not self.coverage_step > 0 or not self.coverage_max_move > 0:
            raise ValueError("coverage_samples, coverage_step and coverage_max_move must be positive")
        if self.coverage_damping < 0 or self.coverage_h2s_weight < 0:
            raise ValueError("coverage_damping and coverage_h2s_weight must be non-negative")
        if min(self.optimise_iterations, self.smoothing_sweeps, self.release_rounds) < 0 or self.optimise_patience < 1:
            raise ValueError("iteration counts must be non-negative (patience >= 1)")


# --------------------------------------------------------------------------- topology helpers


def hex_edges(hexes: np.ndarray) -> np.ndarray:
    """Unique undirected edges of a hex mesh.

    Parameters
    ----------
    hexes : (H, 8) int

    Returns
    -------
    edges : (E, 2) int64, sorted pairs
    """
    e = np.sort(np.asarray(hexes, dtype=np.int64)[:, HEX_EDGES].reshape(-1, 2), axis=1)
    if not len(e):
        return e
    m = int(e.max()) + 1  # one int64 key per pair, in the pairs' lexicographic order (~5x np.unique(axis=0))
    key = np.unique(e[:, 0] * m + e[:, 1])
    return np.stack([key // m, key % m], axis=1)


def boundary_face_counts(hexes: np.ndarray) -> np.ndarray:
    """Number of boundary faces of each hex.

    Parameters
    ----------
    hexes : (H, 8) int

    Returns
    -------
    counts : (H,) int64
    """
    _, hid = boundary_quads(hexes, return_hex=True)
    return np.bincount(hid, minlength=len(hexes)).astype(np.int64)


def _laplacian(edges: np.ndarray, n: int) -> sp.csr_matrix:
    """Uniform graph Laplacian ``D - A`` (n, n) of ``edges``."""
    i, j = edges[:, 0], edges[:, 1]
    A = sp.coo_matrix((np.ones(2 * len(edges)), (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()


def harmonic_extension(edges: np.ndarray, n: int, fixed: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Harmonic (uniform graph Laplacian) extension of values given on ``fixed`` nodes.

    Parameters
    ----------
    edges : (E, 2) int, graph edges
    n : int, number of nodes
    fixed : (n,) bool, nodes whose value is given
    values : (n, k) float, used on ``fixed`` rows

    Returns
    -------
    out : (n, k) float64, equal to ``values`` on fixed rows, harmonic elsewhere
        (a free node in a component without fixed nodes keeps its value)
    """
    values = np.asarray(values, dtype=np.float64)
    out = values.copy()
    free = ~fixed
    if not free.any():
        return out
    L = _laplacian(edges, n)
    Lff = L[free][:, free].tocsc()
    # regularise nodes not connected to anything fixed (keeps the system non-singular)
    Lff = Lff + sp.identity(Lff.shape[0], format="csc") * 1e-12
    rhs = -(L[free][:, fixed] @ values[fixed])
    solve = factorized(Lff)
    for c in range(values.shape[1]):
        out[free, c] = solve(np.ascontiguousarray(rhs[:, c]))
    return out


def _quad_normals(X: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Area-weighted normals (Q, 3) of quads (cross product of the diagonals / 2)."""
    return 0.5 * np.cross(X[quads[:, 2]] - X[quads[:, 0]], X[quads[:, 3]] - X[quads[:, 1]])


def _vertex_normals(X: np.ndarray, quads: np.ndarray, n: int) -> np.ndarray:
    """Unit vertex normals (n, 3): sums of incident quad normals (zero rows for unused nodes)."""
    qn = _quad_normals(X, quads)
    acc = np.zeros((n, 3))
    for k in range(4):
        np.add.at(acc, quads[:, k], qn)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    return np.divide(acc, norm, out=np.zeros_like(acc), where=norm > 0)


def _mean_edge_length(X: np.ndarray, edges: np.ndarray, n: int) -> np.ndarray:
    """Mean length (n,) of the edges incident to each node (0 where none)."""
    ln = np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)
    s = np.bincount(edges.ravel(), weights=np.repeat(ln, 2), minlength=n)
    c = np.bincount(edges.ravel(), minlength=n)
    return np.divide(s, c, out=np.zeros(n), where=c > 0)


# --------------------------------------------------------------------------- the part surface


def _scene(V: np.ndarray, F: np.ndarray):
    from ._o3d import open3d as o3d

    s = o3d.t.geometry.RaycastingScene()
    s.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(V, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(F, dtype=np.uint32)),
    )
    return s


def _closest(scene, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points (n, 3), distances (n,), triangle ids (n,) of ``Q`` on an open3d scene."""
    from ._o3d import open3d as o3d

    if len(Q) == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    r = scene.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(Q, dtype=np.float32)))
    P = r["points"].numpy().astype(np.float64)
    return P, np.linalg.norm(P - Q, axis=1), r["primitive_ids"].numpy().astype(np.int64)


def _closest_on_segments(Q, A, B):
    """Closest points on segments ``A[i] B[i]`` to ``Q[i]`` (all (..., 3)); returns points, distances."""
    d = B - A
    t = np.einsum("...k,...k->...", Q - A, d) / np.maximum(np.einsum("...k,...k->...", d, d), 1e-300)
    t = np.clip(t, 0.0, 1.0)
    P = A + t[..., None] * d
    return P, np.linalg.norm(P - Q, axis=-1)


class PartSurface:
    """The part's triangle surface with projection queries: free, per chart, onto feature curves.

    Parameters
    ----------
    V : (nv, 3) float64
    F : (nf, 3) int64
    feature_angle_deg : float, dihedral angle above which an edge is a sharp feature
    turn_deg : float, a feature curve is split where it turns by more than this

    Attributes
    ----------
    normals : (nf, 3) unit triangle normals
    centroids : (nf, 3) triangle centroids
    seg : (S, 2) int64, sharp feature edges (vertex ids)
    seg_curve : (S,) int64, feature curve of each segment (curves split at feature vertices)
    feature_vertices : (K,) int64, vertex ids where curves end, branch or turn sharply
    branch_vertices : (B,) int64, the part's corners: vertex ids where three or more sharp edges meet
    labels : (nf,) int64 or None, chart label of each triangle (after :meth:`set_labels`)
    """

    _K_SEG = 16

    def __init__(self, V: np.ndarray, F: np.ndarray, feature_angle_deg: float = 50.0, turn_deg: float = 45.0):
        self.V = np.asarray(V, dtype=np.float64)
        self.F = np.asarray(F, dtype=np.int64)
        tri = self.V[self.F]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        self.centroids = tri.mean(axis=1)
        self.scene = _scene(self.V, self.F)
        self.labels = None
        self._label_scenes: list = [None] * 6
        self._find_features(feature_angle_deg, turn_deg)

    def _find_features(self, feature_angle_deg: float, turn_deg: float) -> None:
        F = self.F
        he = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        face = np.repeat(np.arange(len(F)), 3)
        key = he[:, 0] * (len(self.V) + 1) + he[:, 1]
        order = np.argsort(key, kind="stable")
        key, he, face = key[order], he[order], face[order]
        uniq, start, count = np.unique(key, return_index=True, return_counts=True)
        two = count == 2
        e = he[start[two]]
        f0, f1 = face[start[two]], face[start[two] + 1]
        cosang = np.einsum("ij,ij->i", self.normals[f0], self.normals[f1])
        sharp = cosang < np.cos(np.radians(feature_angle_deg))
        seg = e[sharp]
        self.seg = seg
        nseg = len(seg)
        if nseg == 0:
            self.seg_curve = np.zeros(0, dtype=np.int64)
            self.feature_vertices = np.zeros(0, dtype=np.int64)
            self.branch_vertices = np.zeros(0, dtype=np.int64)
            self._seg_tree = None
            self._fv_tree = None
            return
        deg = np.bincount(seg.ravel(), minlength=len(self.V))
        # join segments sharing a degree-2 vertex unless the curve turns sharply there
        inc = np.argsort(seg.ravel(), kind="stable")  # incidences grouped by vertex
        verts = seg.ravel()[inc]
        segs_of = inc // 2
        first = np.r_[True, verts[1:] != verts[:-1]]
        pair_start = np.flatnonzero(first)
        v_of_group = verts[pair_start]
        glen = np.diff(np.r_[pair_start, len(verts)])
        g2 = glen == 2
        s_a = segs_of[pair_start[g2]]
        s_b = segs_of[pair_start[g2] + 1]
        v = v_of_group[g2]
        # directions pointing away from the shared vertex
        oa = np.where(seg[s_a, 0] == v, seg[s_a, 1], seg[s_a, 0])
        ob = np.where(seg[s_b, 0] == v, seg[s_b, 1], seg[s_b, 0])
        da = self.V[oa] - self.V[v]
        db = self.V[ob] - self.V[v]
        c = np.einsum("ij,ij->i", da, db) / np.maximum(
            np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1), 1e-300
        )
        # straight continuation: angle between da and db near 180 degrees
        smooth = c < -np.cos(np.radians(turn_deg))
        from scipy.sparse.csgraph import connected_components

        G = sp.coo_matrix((np.ones(int(smooth.sum())), (s_a[smooth], s_b[smooth])), shape=(nseg, nseg))
        _, self.seg_curve = connected_components(G, directed=False)
        self.seg_curve = self.seg_curve.astype(np.int64)
        self.branch_vertices = np.flatnonzero(deg >= 3)  # where three or more sharp curves meet
        corner = deg.copy() > 0
        corner &= deg != 2
        corner[v[~smooth]] = True
        self.feature_vertices = np.flatnonzero(corner)
        A, B = self.V[seg[:, 0]], self.V[seg[:, 1]]
        self._seg_tree = cKDTree(0.5 * (A + B))
        self._fv_tree = cKDTree(self.V[self.feature_vertices]) if len(self.feature_vertices) else None

    # ---- queries

    def feature_distance(self, X: np.ndarray, k: int = 8) -> np.ndarray:
        """``(n,)`` distance of each point ``X`` to the nearest sharp feature edge (inf without any)."""
        X = np.asarray(X, dtype=np.float64)
        if len(X) == 0 or self._seg_tree is None:
            return np.full(len(X), np.inf)
        k = min(k, len(self.seg))
        _, idx = self._seg_tree.query(X, k=k)
        idx = np.asarray(idx).reshape(len(X), k)
        _, d = _closest_on_segments(X[:, None, :], self.V[self.seg[idx, 0]], self.V[self.seg[idx, 1]])
        return d.min(axis=1)

    def closest(self, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Free closest points ``(n, 3)``, distances ``(n,)`` and triangle ids ``(n,)``."""
        return _closest(self.scene, Q)

    def set_labels(self, labels: np.ndarray) -> None:
        """Give every triangle a chart label in ``0..5`` and build one scene per chart."""
        self.labels = np.asarray(labels, dtype=np.int64)
        for lab in range(6):
            sel = self.labels == lab
            self._label_scenes[lab] = _scene(self.V, self.F[sel]) if sel.any() else None

    def closest_in_charts(self, Q: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Closest point of each query on the union of its charts.

        Parameters
        ----------
        Q : (n, 3) float
        masks : (n, 6) bool, allowed chart labels per query

        Returns
        -------
        points : (n, 3); distances : (n,) (inf where no allowed chart exists)
        """
        best = np.full(len(Q), np.inf)
        P = Q.copy()
        for lab in range(6):
            sel = np.flatnonzero(masks[:, lab])
            if not len(sel) or self._label_scenes[lab] is None:
                continue
            p, d, _ = _closest(self._label_scenes[lab], Q[sel])
            better = d < best[sel]
            best[sel[better]] = d[better]
            P[sel[better]] = p[better]
        return P, best

    def closest_on_curves(self, Q: np.ndarray, curve: np.ndarray | None = None, k: int | None = None):
        """Closest point on the sharp feature segments (optionally of one curve per query).

        Parameters
        ----------
        Q : (n, 3) float
        curve : (n,) int or None, required curve id per query (-1 / None: any)
        k : int, candidate segments per query (nearest midpoints)

        Returns
        -------
        points : (n, 3); distances : (n,) (inf where no candidate); seg : (n,) segment id (-1)
        """
        n = len(Q)
        if self._seg_tree is None or n == 0:
            return Q.copy(), np.full(n, np.inf), np.full(n, -1, dtype=np.int64)
        k = min(k or self._K_SEG, len(self.seg))
        _, idx = self._seg_tree.query(Q, k=k)
        idx = idx.reshape(n, k)
        A, B = self.V[self.seg[idx, 0]], self.V[self.seg[idx, 1]]
        P, d = _closest_on_segments(Q[:, None, :], A, B)
        if curve is not None:
            curve = np.asarray(curve)
            d = np.where((curve[:, None] < 0) | (self.seg_curve[idx] == curve[:, None]), d, np.inf)
        j = np.argmin(d, axis=1)
        r = np.arange(n)
        dist = d[r, j]
        seg = np.where(np.isfinite(dist), idx[r, j], -1)
        return np.where(np.isfinite(dist)[:, None], P[r, j], Q), dist, seg

    def segment_directions(self, seg: np.ndarray) -> np.ndarray:
        """Unit directions ``(n, 3)`` of segments ``seg`` (n,)."""
        d = self.V[self.seg[seg, 1]] - self.V[self.seg[seg, 0]]
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


# --------------------------------------------------------------------------- boundary classification


@dataclasses.dataclass
class BoundaryStructure:
    """The polycube structure of a hex mesh's boundary.

    Attributes
    ----------
    nodes : (nb,) int64, boundary node ids
    quads : (Q, 4) int64, outward boundary quads (global ids)
    quad_label : (Q,) int64, patch label ``2 * axis + (sign > 0)`` of each quad
    label_mask : (nb, 6) bool, distinct labels of the incident quads
    kind : (nb,) int64, number of distinct labels (1 face, 2 edge, 3+ corner)
    tangent : (nb, 3) float64, polycube edge direction of edge nodes (zero otherwise)
    """

    nodes: np.ndarray
    quads: np.ndarray
    quad_label: np.ndarray
    label_mask: np.ndarray
    kind: np.ndarray
    tangent: np.ndarray


def classify_boundary(points: np.ndarray, hexes: np.ndarray) -> BoundaryStructure:
    """Label boundary quads by their axis-aligned outward normal and classify boundary nodes.

    Parameters
    ----------
    points : (P, 3) float, polycube-domain positions (boundary quads axis-aligned)
    hexes : (H, 8) int

    Returns
    -------
    BoundaryStructure
    """
    quads = boundary_quads(hexes)
    qn = _quad_normals(points, quads)
    axis = np.argmax(np.abs(qn), axis=1)
    sign = qn[np.arange(len(qn)), axis] > 0
    label = 2 * axis + sign
    nodes = np.unique(quads)
    loc = np.full(len(points), -1, dtype=np.int64)
    loc[nodes] = np.arange(len(nodes))
    mask = np.zeros((len(nodes), 6), dtype=bool)
    for k in range(4):
        mask[loc[quads[:, k]], label] = True
    kind = mask.sum(axis=1)
    tangent = np.zeros((len(nodes), 3))
    edge = np.flatnonzero(kind == 2)
    if len(edge):
        axes_present = np.zeros((len(edge), 3), dtype=bool)
        for lab in range(6):
            axes_present[:, lab // 2] |= mask[edge, lab]
        ok = axes_present.sum(axis=1) == 2
        tangent[edge[ok], np.argmin(axes_present[ok], axis=1)] = 1.0
        kind[edge[~ok]] = 3  # two opposite normals at one node: treat as a corner
    return BoundaryStructure(nodes, quads, label, mask, kind, tangent)


# --------------------------------------------------------------------------- boundary placement


def chart_labels(
    centroids: np.ndarray,
    tri_normals: np.ndarray,
    node_points: np.ndarray,
    node_normals: np.ndarray,
    node_labels: np.ndarray,
    node_h: np.ndarray,
    normal_weight: float = 2.0,
    k: int = 8,
) -> np.ndarray:
    """Transfer polycube patch labels from face nodes to the part's triangles.

    Each triangle takes the label of the one among its ``k`` nearest face nodes that minimises
    ``distance / h + normal_weight * (1 - n_tri . n_node)``: the nearest node, unless its
    (mapped) normal disagrees with the triangle's, which keeps labels from leaking around a
    sharp edge or across a thin wall.

    Parameters
    ----------
    centroids : (nf, 3) float, triangle centroids
    tri_normals : (nf, 3) float, unit triangle normals
    node_points : (n, 3) float, face-node positions on the part
    node_normals : (n, 3) float, their unit (mapped) normals
    node_labels : (n,) int, their patch labels in ``0..5``
    node_h : (n,) float, local element size at each node
    normal_weight : float
    k : int

    Returns
    -------
    labels : (nf,) int64
    """
    k = min(k, len(node_points))
    dist, idx = cKDTree(node_points).query(centroids, k=k)
    dist, idx = dist.reshape(len(centroids), k), idx.reshape(len(centroids), k)
    h = np.maximum(np.asarray(node_h)[idx], 1e-12)
    agree = np.einsum("tk,tjk->tj", tri_normals, node_normals[idx])
    score = dist / h + normal_weight * (1.0 - agree)
    j = np.argmin(score, axis=1)
    return np.asarray(node_labels, dtype=np.int64)[idx[np.arange(len(centroids)), j]]


@dataclasses.dataclass
class _Constraint:
    """How each boundary node is kept on the surface (indices into ``BoundaryStructure.nodes``)."""

    mode: np.ndarray  # (nb,) _CHART / _CURVE / _FIXED / _FREE
    curve: np.ndarray  # (nb,) curve id for _CURVE nodes (else -1)
    mask: np.ndarray  # (nb, 6) chart labels
    released: np.ndarray  # (nb,) bool, released from a feature after the optimisation


def _project(surf: PartSurface, X: np.ndarray, con: _Constraint, idx: np.ndarray | None = None) -> np.ndarray:
    """Project boundary positions ``X`` (n, 3) of boundary nodes ``idx`` (all when None)
    according to their constraints."""
    if idx is not None:
        con = _Constraint(con.mode[idx], con.curve[idx], con.mask[idx], con.released[idx])
    out = X.copy()
    m = con.mode
    sel = np.flatnonzero(m == _FREE)
    if len(sel):
        out[sel] = surf.closest(X[sel])[0]
    sel = np.flatnonzero(m == _CHART)
    if len(sel):
        P, d = surf.closest_in_charts(X[sel], con.mask[sel])
        ok = np.isfinite(d)
        out[sel[ok]] = P[ok]
        if not ok.all():
            out[sel[~ok]] = surf.closest(X[sel[~ok]])[0]
    sel = np.flatnonzero(m == _CURVE)
    if len(sel):
        P, d, _ = surf.closest_on_curves(X[sel], con.curve[sel])
        ok = np.isfinite(d)
        out[sel[ok]] = P[ok]
        if not ok.all():
            lost = sel[~ok]
            P2, d2 = surf.closest_in_charts(X[lost], con.mask[lost])
            out[lost] = np.where(np.isfinite(d2)[:, None], P2, X[lost])
    return out  # _FIXED nodes keep X (never moved by the optimiser)


def quad_corner_quality(X: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Planar scaled Jacobian of each quad corner, relative to the quad's own normal.

    Parameters
    ----------
    X : (n, 3) float
    quads : (Q, 4) int

    Returns
    -------
    q : (Q, 4) float64, ``(e1 x e2) . n / (|e1| |e2|)`` at every corner (``e1`` to the next
        corner, ``e2`` to the previous one, ``n`` the unit normal from the diagonals): 1 for a
        right angle, 0 for a flat (180 degree) or collapsed corner, negative where folded
    """
    P = X[quads]  # (Q, 4, 3)
    n = np.cross(P[:, 2] - P[:, 0], P[:, 3] - P[:, 1])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    e1 = np.roll(P, -1, axis=1) - P
    e2 = np.roll(P, 1, axis=1) - P
    c = np.einsum("qkj,qj->qk", np.cross(e1, e2), n)
    return c / np.maximum(np.linalg.norm(e1, axis=2) * np.linalg.norm(e2, axis=2), 1e-300)


def _guard_snaps(X, X0, mode, curve, bs: BoundaryStructure, bar: float):
    """Undo snaps (``X`` vs the unsnapped ``X0``) that leave a boundary quad corner below
    ``min(bar, its unsnapped quality)``; repeat until none does.  Returns X, mode, curve, count."""
    loc = np.full(int(bs.nodes.max()) + 1, -1, dtype=np.int64)
    loc[bs.nodes] = np.arange(len(bs.nodes))
    q = loc[bs.quads]  # (Q, 4) local ids
    snapped = (mode == _CURVE) | (mode == _FIXED)
    limit = np.minimum(bar, quad_corner_quality(X0, q)) - 1e-9
    undone = 0
    X = X.copy()
    for _ in range(100):
        bad = (quad_corner_quality(X, q) < limit).any(axis=1)
        nodes = np.unique(q[bad])
        nodes = nodes[snapped[nodes]]
        if not len(nodes):
            break
        X[nodes] = X0[nodes]
        mode[nodes] = _CHART
        curve[nodes] = -1
        snapped[nodes] = False
        undone += len(nodes)
    return X, mode, curve, undone


def boundary_deviation(points: np.ndarray, hexes: np.ndarray, surf: PartSurface) -> float:
    """A cheap two-sided distance between the hex boundary and the part surface.

    The maximum of (a) the distance of every surface vertex to the hex boundary (quads split
    into triangles) and (b) the distance of the boundary quad centres and edge midpoints to
    the surface.  A lower bound of the sampled Hausdorff distance of
    :func:`polycubenet.quality.surface_distance`, in the units of ``points``.

    Parameters
    ----------
    points : (P, 3) float
    hexes : (H, 8) int
    surf : PartSurface

    Returns
    -------
    float
    """
    q = boundary_quads(hexes)
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    _, d_sv, _ = _closest(_scene(points, tris), surf.V)
    Pq = points[q]
    probes = np.concatenate([Pq.mean(axis=1), 0.5 * (Pq + np.roll(Pq, -1, axis=1)).reshape(-1, 3)])
    _, d_hs, _ = surf.closest(probes)
    return float(max(d_sv.max(), d_hs.max()))


def _place_boundary(
    surf: PartSurface,
    bs: BoundaryStructure,
    Y: np.ndarray,
    Yt: np.ndarray,
    hloc: np.ndarray,
    normals: np.ndarray,
    cfg: PullbackConfig,
) -> tuple[np.ndarray, _Constraint, dict]:
    """Step 1: chart labelling, constrained projection, feature snapping.

    Parameters
    ----------
    surf : PartSurface
    bs : BoundaryStructure
    Y : (nb, 3) mapped boundary positions
    Yt : (nb, 3) mapped edge tangents (zero for non-edge nodes)
    hloc : (nb,) local edge lengths
    normals : (nb, 3) mapped vertex normals
    cfg : PullbackConfig

    Returns
    -------
    X : (nb, 3) positions on the surface; constraint; info dict
    """
    nb = len(bs.nodes)
    P_free, d_free, _ = surf.closest(Y)
    info: dict = {"free_distance_max": float(d_free.max()) if nb else 0.0}
    mode = np.full(nb, _FREE if not cfg.chart_projection else _CHART, dtype=np.int64)
    curve = np.full(nb, -1, dtype=np.int64)
    X = P_free.copy()
    fallback = {"face": 0, "edge": 0, "corner": 0, "snap_rejected": 0}

    # chart labelling of the part triangles from the face nodes (projected positions, mapped normals)
    face = np.flatnonzero(bs.kind == 1)
    if cfg.chart_projection and len(face):
        lab_face = np.argmax(bs.label_mask[face], axis=1)
        surf.set_labels(
            chart_labels(
                surf.centroids, surf.normals, P_free[face], normals[face], lab_face, hloc[face],
                cfg.label_normal_weight,
            )
        )
        P_chart, d_chart = surf.closest_in_charts(Y, bs.label_mask)
        bad = ~(d_chart - d_free <= cfg.fallback_excess * hloc)  # also catches inf
        for kind_id, name in ((1, "face"), (2, "edge"), (3, "corner")):
            sel = bs.kind == kind_id if kind_id < 3 else bs.kind >= 3
            fallback[name] = int((bad & sel).sum())
        X = np.where(bad[:, None], P_free, P_chart)
        mode[bad] = _FREE
        info["chart_triangles"] = np.bincount(surf.labels, minlength=6).tolist()
    info["fallbacks"] = fallback

    snapped = {"edge": 0, "corner": 0}
    X_unsnapped = X.copy()
    if cfg.snap_features and len(surf.seg):
        cos_align = np.cos(np.radians(cfg.snap_align_deg))
        # edge nodes: nearest parallel feature segment
        edge = np.flatnonzero(bs.kind == 2)
        if len(edge):
            k = min(PartSurface._K_SEG, len(surf.seg))
            _, idx = surf._seg_tree.query(X[edge], k=k)
            idx = idx.reshape(len(edge), k)
            A, B = surf.V[surf.seg[idx, 0]], surf.V[surf.seg[idx, 1]]
            P, d = _closest_on_segments(X[edge][:, None, :], A, B)
            dirs = B - A
            dirs /= np.maximum(np.linalg.norm(dirs, axis=2, keepdims=True), 1e-300)
            t = Yt[edge] / np.maximum(np.linalg.norm(Yt[edge], axis=1, keepdims=True), 1e-300)
            align = np.abs(np.einsum("njk,nk->nj", dirs, t))
            d = np.where(align >= cos_align, d, np.inf)
            j = np.argmin(d, axis=1)
            r = np.arange(len(edge))
            dj, Pj = d[r, j], P[r, j]
            ok = dj <= cfg.snap_radius * hloc[edge]
            # snapping must not be far worse than the free projection of the mapped point
            worse = np.linalg.norm(Pj - Y[edge], axis=1) > d_free[edge] + cfg.fallback_excess * hloc[edge]
            snapped_ok = ok & ~worse
            fallback["snap_rejected"] += int((ok & worse).sum())
            sel = edge[snapped_ok]
            X[sel] = Pj[snapped_ok]
            mode[sel] = _CURVE
            curve[sel] = surf.seg_curve[idx[r, j][snapped_ok]]
            snapped["edge"] = int(snapped_ok.sum())
        # corner nodes: a feature vertex (a corner on a smooth stretch of a curve stays free on
        # its charts: pinning it there would leave a flat 180-degree quad corner)
        corner = np.flatnonzero(bs.kind >= 3)
        if len(corner):
            done = np.zeros(len(corner), dtype=bool)
            if surf._fv_tree is not None:
                dv, iv = surf._fv_tree.query(X[corner])
                ok = dv <= cfg.snap_radius * hloc[corner]
                # one node per feature vertex: the nearest claims it
                order = np.argsort(dv, kind="stable")
                taken = set()
                for c in order:
                    if ok[c]:
                        fv = int(iv[c])
                        if fv in taken:
                            ok[c] = False
                        else:
                            taken.add(fv)
                sel = corner[ok]
                X[sel] = surf.V[surf.feature_vertices[iv[ok]]]
                mode[sel] = _FIXED
                done |= ok
                snapped["corner"] = int(ok.sum())
        # a snap that folds or flattens a boundary quad corner is a wrong feature: undo it
        X, mode, curve, undone = _guard_snaps(X, X_unsnapped, mode, curve, bs, cfg.snap_quad_quality)
        fallback["snap_rejected"] += undone
        snapped["edge"] = int(((mode == _CURVE) & (bs.kind == 2)).sum())
        snapped["corner"] = int(((mode == _FIXED) & (bs.kind >= 3)).sum())
    info["snapped"] = snapped
    return X, _Constraint(mode, curve, bs.label_mask.copy(), np.zeros(nb, dtype=bool)), info


class _Coverage:
    """Two-sided fitting of the boundary quads to the part surface.

    Holds the surface samples (the surface's vertices plus ``cfg.coverage_samples`` area-uniform
    random points, seeded) and the triangulated boundary quads (local node ids); lengths are in
    the surface's normalised frame.
    """

    #: sample points on each quad triangle: centroid and edge midpoints (barycentric weights)
    _BARY = np.array([[1 / 3, 1 / 3, 1 / 3], [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])

    def __init__(self, surf: PartSurface, bs: BoundaryStructure, cfg: PullbackConfig, seed: int = 0):
        self.surf, self.cfg = surf, cfg
        nb = len(bs.nodes)
        self.nb = nb
        loc = np.full(int(bs.nodes.max()) + 1, -1, dtype=np.int64)
        loc[bs.nodes] = np.arange(nb)
        q = loc[bs.quads]
        self.tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
        rng = np.random.default_rng(seed)
        tri = surf.V[surf.F]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        n = int(cfg.coverage_samples)
        idx = np.minimum(np.searchsorted(np.cumsum(area) / area.sum(), rng.random(n), side="right"), len(area) - 1)
        r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
        S = (1 - r1)[:, None] * tri[idx, 0] + (r1 * (1 - r2))[:, None] * tri[idx, 1] + (r1 * r2)[:, None] * tri[idx, 2]
        self.S = np.vstack([surf.V, S])
        self.hv = np.repeat(self.tris, len(self._BARY), axis=0)
        self.hw = np.tile(self._BARY, (len(self.tris), 1))

    def residuals(self, X: np.ndarray):
        """The fit's move of every boundary node and the two one-sided distances.

        Parameters
        ----------
        X : (nb, 3) float, boundary node positions

        Returns
        -------
        delta : (nb, 3) float64, the weighted mean of the residuals the node's triangles carry
            (barycentric weights): surface sample -> its closest point on the quads reversed, and
            quad sample point -> its closest point on the surface
        s2h : float, largest distance of a surface sample to the quads
        h2s : float, largest distance of a quad sample point to the surface
        """
        from ._o3d import open3d as o3d

        sc = _scene(X, self.tris)
        r = sc.compute_closest_points(o3d.core.Tensor(np.ascontiguousarray(self.S, dtype=np.float32)))
        C = r["points"].numpy().astype(np.float64)
        t = r["primitive_ids"].numpy().astype(np.int64)
        uv = r["primitive_uvs"].numpy().astype(np.float64)
        res = self.S - C
        d_s = np.linalg.norm(res, axis=1)
        Hp = np.einsum("nk,nkj->nj", self.hw, X[self.hv])
        hres = self.surf.closest(Hp)[0] - Hp
        d_h = np.linalg.norm(hres, axis=1)
        w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        vid = np.concatenate([self.tris[t], self.hv]).ravel()
        w = np.concatenate([w, self.cfg.coverage_h2s_weight * self.hw])
        res = np.concatenate([res, hres])
        wsum = np.bincount(vid, weights=w.ravel(), minlength=self.nb)
        force = np.stack([np.bincount(vid, weights=(w * res[:, k : k + 1]).ravel(), minlength=self.nb) for k in range(3)], 1)
        w0 = self.cfg.coverage_damping * float(np.median(wsum[wsum > 0]))
        delta = self.cfg.coverage_step * force / (wsum + w0)[:, None]
        return delta, float(d_s.max()), float(d_h.max())


def _cap(delta: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Shorten the rows of ``delta (n, 3)`` to at most ``limit (n,)``."""
    ln = np.linalg.norm(delta, axis=1)
    return delta * np.minimum(1.0, limit / np.maximum(ln, 1e-300))[:, None]


def fit_coverage(
    cov: _Coverage, X: np.ndarray, con: _Constraint, hloc: np.ndarray, iterations: int
) -> tuple[np.ndarray, dict]:
    """Step 1b: slide the boundary nodes so that the quads cover the part surface.

    ``iterations`` times: every node moves by :meth:`_Coverage.residuals` (at most
    ``coverage_max_move`` x ``hloc``) and is projected back under its constraint (chart,
    feature curve; fixed corners stay).

    Parameters
    ----------
    cov : _Coverage
    X : (nb, 3) float, projected boundary positions
    con : _Constraint
    hloc : (nb,) float, local edge lengths
    iterations : int

    Returns
    -------
    X : (nb, 3) float64
    info : dict, ``coverage_s2h`` / ``coverage_h2s``: the one-sided maxima before each iteration
        and at the end
    """
    movable = con.mode != _FIXED
    hist_s, hist_h = [], []
    for it in range(int(iterations) + 1):
        delta, ds, dh = cov.residuals(X)
        hist_s.append(ds)
        hist_h.append(dh)
        if it == int(iterations):
            break
        Xp = _project(cov.surf, X + _cap(delta, cov.cfg.coverage_max_move * hloc), con)
        X = np.where(movable[:, None], Xp, X)
    return X, {"coverage_s2h": hist_s, "coverage_h2s": hist_h}


def _hex_sj(hexes: np.ndarray, Y: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Scaled Jacobian of hexes ``rows`` at node positions ``Y``, ``-inf`` for a degenerate one."""
    sj, dg = scaled_jacobian_and_degenerate(Y, hexes[rows])
    return np.where(dg, -np.inf, sj)


def guarded_coverage(
    cov: _Coverage,
    X: np.ndarray,
    hexes: np.ndarray,
    nodes: np.ndarray,
    con: _Constraint,
    hloc: np.ndarray,
    iterations: int,
    sj_bar: float,
    follow: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """The coverage fit on a finished mesh, never taking a hex below ``min(sj_bar, its SJ before)``.

    Each iteration moves the surface nodes as :func:`fit_coverage` does (and, with ``follow``,
    each one's inner pillow copy by the same vector); then, repeatedly, the moved nodes of every
    hex that fell below ``min(sj_bar, its SJ before the iteration)`` are put back, until none
    does.  A valid mesh stays valid.

    Parameters
    ----------
    cov : _Coverage
    X : (P, 3) float, all node positions (normalised frame)
    hexes : (H, 8) int
    nodes : (nb,) int, the surface nodes, in the order of ``con`` and ``hloc``
    con : _Constraint
    hloc : (nb,) float
    iterations : int
    sj_bar : float
    follow : (P0,) int or None, node that moves with each node (-1: none), e.g. the inner
        copies from :func:`pillow`

    Returns
    -------
    X : (P, 3) float64
    info : dict, ``guarded_s2h``, ``guarded_h2s`` (per iteration), ``guarded_undone`` (moves
        put back per iteration)
    """
    X = X.copy()
    P, H = len(X), len(hexes)
    incident, node_min = _hex_incidence(hexes, P)

    sj = _hex_sj(hexes, X, np.arange(H))
    movable_b = con.mode != _FIXED
    if follow is not None:
        follow = np.concatenate([follow, np.full(P - len(follow), -1, dtype=np.int64)])
    hist_s, hist_h, undone = [], [], []
    for it in range(int(iterations) + 1):
        delta, ds, dh = cov.residuals(X[nodes])
        hist_s.append(ds)
        hist_h.append(dh)
        if it == int(iterations):
            break
        limit = np.minimum(node_min(sj), sj_bar) - 1e-9
        Xb = _project(cov.surf, X[nodes] + _cap(delta, cov.cfg.coverage_max_move * hloc), con)
        Xn = X.copy()
        moved = np.zeros(P, dtype=bool)
        sel = nodes[movable_b]
        Xn[sel] = Xb[movable_b]
        moved[sel] = True
        if follow is not None:
            f = follow[sel]
            ok = f >= 0
            Xn[f[ok]] = X[f[ok]] + (Xn[sel[ok]] - X[sel[ok]])
            moved[f[ok]] = True
        sj_new = sj.copy()
        rows = np.flatnonzero(np.asarray(incident @ moved))
        n_undone = 0
        for _ in range(100):
            sj_new[rows] = _hex_sj(hexes, Xn, rows)
            bad = moved & (node_min(sj_new) < limit)
            if not bad.any():
                break
            # undo the moved nodes of every hex that fell below its bar (else the flagged nodes)
            hb = np.asarray(incident @ bad).astype(bool) & (sj_new < np.minimum(sj, sj_bar) - 1e-9)
            culprits = np.zeros(P, dtype=bool)
            culprits[hexes[hb].ravel()] = True
            culprits &= moved
            if not culprits.any():
                culprits = bad
            if follow is not None:  # an undone surface node takes its inner copy back too
                f = follow[np.flatnonzero(culprits)]
                f = f[f >= 0]
                culprits[f] = True
            Xn[culprits] = X[culprits]
            moved &= ~culprits
            n_undone += int(culprits.sum())
            rows = np.flatnonzero(np.asarray(incident @ culprits))
        else:  # pragma: no cover - ``moved`` shrinks every round, so this is not reached
            Xn, sj_new = X.copy(), sj
        X, sj = Xn, sj_new
        undone.append(n_undone)
    return X, {"guarded_s2h": hist_s, "guarded_h2s": hist_h, "guarded_undone": undone}


def _node_quads(quads: np.ndarray, P: int) -> sp.csr_matrix:
    """The node -> boundary quad incidence (P x Q boolean CSR)."""
    return sp.csr_matrix((np.ones(quads.size, dtype=bool), (quads.ravel(), np.repeat(np.arange(len(quads)), 4))),
                         shape=(P, len(quads)))


def _quad_gap(surf: PartSurface, Y: np.ndarray, quads: np.ndarray) -> float:
    """How far boundary quads ``quads`` (``(k, 4)`` node ids) at positions ``Y`` are from the part: the largest
    distance of their centres and edge midpoints to the surface."""
    q = Y[quads]  # (k, 4, 3)
    pts = np.concatenate([q.mean(axis=1), 0.5 * (q + np.roll(q, -1, axis=1)).reshape(-1, 3)])
    return float(surf.closest(pts)[1].max())


def _guarded_move(X, hexes, inc, group, v, fractions, sj_bar, also) -> bool:
    """Move nodes ``group`` of ``X`` (in place) by the largest of ``fractions`` of ``v`` that leaves no hex around
    them below ``min(sj_bar, its SJ before)`` and passes ``also()``; True if one did (else ``X`` is unchanged).
    ``inc``: the node -> hex incidence as CSC (P x H).  The hexes' SJ at every fraction is taken in one pass (these
    moves are tried tens of thousands of times on a hard part); ``also()`` only where the SJ guard passes, in order."""
    rows = np.unique(np.concatenate([inc.indices[inc.indptr[m]:inc.indptr[m + 1]] for m in group]))
    H = hexes[rows]  # (r, 8) node ids
    fr = np.asarray(fractions, dtype=np.float64)
    # the hexes' corners as they are, then at each fraction: only the group's nodes move
    corners = np.broadcast_to(X[H], (1 + len(fr),) + H.shape + (3,)).copy()  # (1 + f, r, 8, 3)
    for m in group:
        hit = H == m
        corners[1:, hit] = (X[m] + fr[:, None] * v)[:, None, :]
    sj, dg = corner_sj_and_degenerate(corners.reshape(-1, 8, 3))
    sj = np.where(dg, -np.inf, sj).reshape(1 + len(fr), len(rows))
    ok = (sj[1:] >= np.minimum(sj[0], sj_bar) - 1e-9).all(axis=1)
    start = X[group].copy()
    for frac, good in zip(fr, ok):
        if not good:
            continue
        X[group] = start + frac * v
        if also():
            return True
    X[group] = start
    return False


def guarded_corner_snap(
    surf: PartSurface,
    X: np.ndarray,
    hexes: np.ndarray,
    nodes: np.ndarray,
    hloc: np.ndarray,
    sj_bar: float,
    follow: np.ndarray | None = None,
    min_gap: float = 0.25 * tol.HAUSDORFF_REL_MAX,
    radius: float = 2.0,
    fractions: tuple = (1.0, 0.75, 0.5, 0.25),
) -> tuple[np.ndarray, dict]:
    """Put a surface node on every corner of the part (``surf.branch_vertices``: three or more sharp
    edges meet there) that no node of the finished mesh is within ``min_gap`` of (diagonal units).

    The coverage fit pulls a node towards a corner only as much as the many samples around it
    allow, so a box corner cut by the mesh (one surface point, hence the Hausdorff distance) can
    stay 1 % of the diagonal off.  Nearest corners first, the nearest surface node within ``radius``
    x its local edge length moves onto the corner (with ``follow``, its inner pillow copy by the
    same vector), the largest of ``fractions`` of the way that passes, and only when (a) no hex around it falls below
    ``min(sj_bar, its SJ before)`` and (b) its boundary quads (centres and edge midpoints) end no
    farther from the part than before or than half the Hausdorff bar.  A valid mesh stays valid.

    Returns ``X`` and ``{"corner_snaps": moved, "corner_snaps_refused": left}``.
    """
    info = {"corner_snaps": 0, "corner_snaps_refused": 0}
    fv = surf.branch_vertices
    if not len(fv) or not len(nodes):
        return X, info
    C = surf.V[fv]
    d, j = cKDTree(X[nodes]).query(C)
    todo = np.flatnonzero((d > min_gap) & (d <= radius * hloc[j]))
    if not len(todo):
        return X, info
    X = X.copy()
    P = len(X)
    inc = sp.csc_matrix(_hex_incidence(hexes, P)[0])
    quads = boundary_quads(hexes)
    node_quads = _node_quads(quads, P)
    if follow is not None:
        follow = np.concatenate([follow, np.full(max(0, P - len(follow)), -1, dtype=np.int64)])

    def quad_gap(Y, qrows):
        return _quad_gap(surf, Y, quads[qrows])

    used: set = set()
    for ci in todo[np.argsort(d[todo])]:
        n = int(nodes[j[ci]])
        if n in used:
            continue
        used.add(n)
        group = [n] + ([int(follow[n])] if follow is not None and follow[n] >= 0 else [])
        qrows = node_quads.indices[node_quads.indptr[n]:node_quads.indptr[n + 1]]
        gap_bar = max(quad_gap(X, qrows), 0.5 * tol.HAUSDORFF_REL_MAX)
        if _guarded_move(X, hexes, inc, group, C[ci] - X[n], fractions, sj_bar,
                         lambda: quad_gap(X, qrows) <= gap_bar):
            info["corner_snaps"] += 1
        else:
            info["corner_snaps_refused"] += 1
    return X, info


def guarded_spot_capture(
    surf: PartSurface,
    X: np.ndarray,
    hexes: np.ndarray,
    nodes: np.ndarray,
    hloc: np.ndarray,
    sj_bar: float,
    trigger: float,
    target: float,
    samples: int = 100_000,
    rounds: int = 8,
    radius: float = 2.0,
    fractions: tuple = (1.0, 0.75, 0.5, 0.25),
    seed: int = 0,
    follow: np.ndarray | None = None,
    tries: int | None = None,
) -> tuple[np.ndarray, dict]:
    """Bring the boundary onto the spots of the part it leaves uncovered, when one is farther than ``trigger``.

    The coverage fit moves nodes by the *mean* of the residuals around them, so a short sharp feature that
    no polycube edge maps to (a knife edge where a slanted cut crosses a hole, the corner of a notch) stays
    cut by the quads: a few surface points, but the Hausdorff distance is their maximum.  Here, only
    when a sample of the part (its vertices plus ``samples`` area-uniform points) lies farther than
    ``trigger`` from the boundary quads, up to ``rounds`` rounds each take the samples farther than
    ``target``, worst first, and move one of the three nearest surface nodes (within ``radius`` x its local
    edge length, each node once a round) onto the sample: the largest of ``fractions`` of the way that
    passes the guard of :func:`guarded_corner_snap` (no hex around it below ``min(sj_bar, its SJ before)``,
    its quads no farther from the part than before or than half the Hausdorff bar), the node alone first,
    then, with ``follow`` (``(P,)``, the node that moves with each node, -1: none; e.g. its inner pillow
    copy), the two together: alone it shears its boundary hex, together they shear the hex behind it.  A valid
    mesh stays valid.  ``tries``: at most this many nodes tried a round (None: no limit).  Lengths are in the
    units of ``X`` (the pull-back's frame: diagonal 1).

    Returns ``X`` and ``{"spot_captures": moves kept, "spot_captures_refused": samples left,
    "spot_gap_before": the farthest sample's distance before, "spot_gap_after": after}``.
    """
    from .quality import _sample_triangles

    quads = boundary_quads(hexes)
    tris = quads_to_triangles(quads)
    S = _sample_triangles(surf.V, surf.F, int(samples), np.random.default_rng(seed))
    gap = _closest(_scene(X, tris), S)[1]
    info = {"spot_captures": 0, "spot_captures_refused": 0, "spot_gap_before": float(gap.max()),
            "spot_gap_after": float(gap.max())}
    if not gap.max() > trigger or not len(nodes):
        return X, info
    X = X.copy()
    P = len(X)
    inc = sp.csc_matrix(_hex_incidence(hexes, P)[0])
    node_quads = _node_quads(quads, P)
    h = np.zeros(P)
    h[nodes] = hloc

    def quad_gap(Y, qrows):
        return _quad_gap(surf, Y, quads[qrows])

    for _ in range(int(rounds)):
        far = np.flatnonzero(gap > target)
        if not len(far):
            break
        k = min(3, len(nodes))
        dist, idx = cKDTree(X[nodes]).query(S[far], k=k)
        dist, idx = dist.reshape(len(far), k), idx.reshape(len(far), k)
        used: set = set()
        moved = refused = tried = 0
        order = np.argsort(-gap[far])
        for i, r in enumerate(order):
            if tries is not None and tried >= tries:
                refused += len(order) - i  # the nearer spots this round leaves untried
                break
            s = S[far[r]]
            for dn, j in zip(dist[r], idx[r]):
                n = int(nodes[j])
                if n in used or dn > radius * h[n]:
                    continue
                tried += 1
                qrows = node_quads.indices[node_quads.indptr[n]:node_quads.indptr[n + 1]]
                gap_bar = max(quad_gap(X, qrows), 0.5 * tol.HAUSDORFF_REL_MAX)
                def passes(qrows=qrows, gap_bar=gap_bar):
                    return quad_gap(X, qrows) <= gap_bar

                groups = [[n]] + ([[n, int(follow[n])]] if follow is not None and follow[n] >= 0 else [])
                if not any(_guarded_move(X, hexes, inc, g, s - X[n], fractions, sj_bar, passes) for g in groups):
                    continue
                used.add(n)
                moved += 1
                break
            else:
                refused += 1
        info["spot_captures"] += moved
        info["spot_captures_refused"] = refused
        gap = _closest(_scene(X, tris), S)[1]
        if not moved:
            break
    info["spot_gap_after"] = float(gap.max())
    return X, info


# --------------------------------------------------------------------------- optimisation


#: signs of the 8 corners in the three centre principal axes (verdict's X1, X2, X3)
_CENTRE_SIGNS = np.array(
    [
        [-1, 1, 1, -1, -1, 1, 1, -1],
        [-1, -1, 1, 1, -1, -1, 1, 1],
        [-1, -1, -1, -1, 1, 1, 1, 1],
    ],
    dtype=np.float64,
)


def _term_operators() -> np.ndarray:
    """(3, 8, 9): for each of the three vectors of the nine verdict terms (:func:`sj_terms`), the
    linear map from a hex's 8 corner coordinates to it (the centre axes, then corner edges)."""
    ops = np.zeros((3, 8, 9))
    for v in range(3):
        ops[v, :, 0] = _CENTRE_SIGNS[v]
        ops[v, CORNER_FRAMES[:, v + 1], np.arange(1, 9)] += 1.0
        ops[v, CORNER_FRAMES[:, 0], np.arange(1, 9)] -= 1.0
    return ops


_TERM_OPS = _term_operators()
#: (27, 8): the three operators side by side, transposed (the gradient's way back to the corners)
_TERM_OPS_T = np.ascontiguousarray(np.concatenate(list(_TERM_OPS), axis=1).T)


def _cross3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cross product of component-first arrays ``(3, ...)``."""
    out = np.empty_like(u)
    np.multiply(u[1], v[2], out=out[0])
    out[0] -= u[2] * v[1]
    np.multiply(u[2], v[0], out=out[1])
    out[1] -= u[0] * v[2]
    np.multiply(u[0], v[1], out=out[2])
    out[2] -= u[1] * v[0]
    return out


def _dot3(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Dot product of component-first arrays ``(3, ...)``."""
    out = u[0] * v[0]
    out += u[1] * v[1]
    out += u[2] * v[2]
    return out


def sj_terms(points: np.ndarray, hexes: np.ndarray, dfds: Callable | None = None, eps: float = 1e-300):
    """The nine verdict terms of the scaled Jacobian of every hex, and optionally a gradient.

    Term 0 is the centre term (three principal axes), terms 1..8 the corners
    (:data:`CORNER_FRAMES`); each is ``det[a, b, c] / (|a| |b| |c|)``.  The verdict scaled
    Jacobian of a (non-degenerate) hex is the minimum of its nine terms.

    Parameters
    ----------
    points : (P, 3) float64
    hexes : (H, 8) int64
    dfds : callable or None
        ``(H, 9) terms -> (H, 9)`` derivative of a loss with respect to each term; when
        given, the gradient of that loss with respect to the points is returned too.
    eps : float
        Added to every squared vector length (keeps the gradient at a collapsed edge finite);
        a term with a zero-length vector is 0.

    Returns
    -------
    terms : (H, 9) float64
    grad : (P, 3) float64, only when ``dfds`` is given
    """
    # structure of arrays, component-first (3, H, 9): each vector of every term is one small
    # matmul of the corner coordinates with a fixed (8, 9) operator, and the gradient goes back
    # through the transposed operators (no per-frame gathers and scatters of corners)
    H = len(hexes)
    C = np.asarray(points, dtype=np.float64).T[:, hexes].reshape(3 * H, 8)
    a = (C @ _TERM_OPS[0]).reshape(3, H, 9)
    b = (C @ _TERM_OPS[1]).reshape(3, H, 9)
    c = (C @ _TERM_OPS[2]).reshape(3, H, 9)
    bxc = _cross3(b, c)
    det = _dot3(a, bxc)
    la = _dot3(a, a) + eps
    lb = _dot3(b, b) + eps
    lc = _dot3(c, c) + eps
    inv_scale = 1.0 / np.maximum(np.sqrt(la) * np.sqrt(lb) * np.sqrt(lc), 1e-300)  # 0 for a collapsed vector
    s = det * inv_scale
    if dfds is None:
        return s
    g = dfds(s)  # (H, 9)
    gi = g * inv_scale
    gs = g * s
    gabc = np.empty((3, H, 27))
    for k, (u, cr, ln) in enumerate(((a, bxc, la), (b, _cross3(c, a), lb), (c, _cross3(a, b), lc))):
        out = gabc[:, :, 9 * k: 9 * k + 9]
        np.multiply(gi, cr, out=out)
        out -= (gs / ln) * u
    gC = (gabc.reshape(3 * H, 27) @ _TERM_OPS_T).reshape(3, 8 * H)
    flat = np.asarray(hexes).ravel()
    n = len(points)
    return s, np.stack([np.bincount(flat, weights=gC[k], minlength=n) for k in range(3)], axis=1)


def optimise_quality(
    points: np.ndarray,
    hexes: np.ndarray,
    *,
    movable: np.ndarray | None = None,
    project: Callable[[np.ndarray], np.ndarray] | None = None,
    project_nodes: np.ndarray | None = None,
    config: PullbackConfig = PullbackConfig(),
    stop_when_valid: bool = False,
    regularisation: np.ndarray | None = None,
) -> tuple[np.ndarray, dict]:
    """Untangle and maximise the minimum scaled Jacobian, keeping the connectivity.

    Adam on the movable positions with the objective (over the 9 verdict terms ``s`` of the
    hexes, :func:`sj_terms`, divided by ``9 H``) ``sum softplus((t - s) / w) w + m (1 - s)``
    plus ``sum_i r_i |x_i - x0_i|^2 / (h^2 P)``; after each step the moved ``project_nodes``
    are put back by ``project``.  The gradient is analytic (numpy, checked against torch
    autograd in the tests).  Only an active set moves: the nodes of the hexes within one
    ring of a hex whose SJ is below ``t + 3 w`` (refreshed every ``_REFRESH`` steps); the
    others feel almost nothing of the hinge, and leaving them still keeps a big mesh fast.
    The best state is returned: the higher minimum SJ until it reaches ``_SJ_FLOOR``, then
    the higher ``mean + min / 4``; it stops after ``optimise_patience`` steps in which neither
    that nor the total deficit ``sum max(0, _SJ_FLOOR - sj)`` improved.

    Parameters
    ----------
    points : (P, 3) float, start positions
    hexes : (H, 8) int
    movable : (P,) bool or None, nodes allowed to move (default all)
    project : callable or None
        ``project(x, i)`` with ``x : (k, 3)`` the positions of ``project_nodes[i]`` (``i : (k,)``)
        returns their positions after the constraint (e.g. back onto the surface); applied
        after every step to the nodes that moved
    project_nodes : (n,) int or None, these nodes get ``boundary_regularisation``
    config : PullbackConfig
    stop_when_valid : bool, stop at the first state with every hex's SJ above 0.01
    regularisation : (P,) float or None, per-node weight of the pull to the start position
        (default ``config.regularisation``, ``config.boundary_regularisation`` on
        ``project_nodes``)

    Returns
    -------
    points : (P, 3) float64, the best state
    info : dict, ``iterations``, ``sj_min_start``, ``sj_avg_start``, ``sj_min``, ``sj_avg``,
        ``seconds``
    """
    t0 = time.perf_counter()
    X0 = np.asarray(points, dtype=np.float64)
    hexes = np.asarray(hexes, dtype=np.int64)
    P = len(X0)
    movable = np.ones(P, dtype=bool) if movable is None else np.asarray(movable, dtype=bool)
    edges = hex_edges(hexes)
    h = float(np.linalg.norm(X0[edges[:, 0]] - X0[edges[:, 1]], axis=1).mean())
    t, w, mw = config.sj_target, config.sj_softness, config.mean_weight
    n_terms = 9.0 * len(hexes)

    def dfds(s):
        z = np.clip((t - s) / w, -50.0, 50.0)
        return (-1.0 / (1.0 + np.exp(-z)) - mw) / n_terms

    lr = config.learning_rate * h
    if regularisation is not None:
        reg = np.asarray(regularisation, dtype=np.float64)
    else:
        reg = np.full(P, config.regularisation)
        if project_nodes is not None:
            reg[project_nodes] = config.boundary_regularisation
    b1, b2, eps = 0.9, 0.999, 1e-16
    pn = np.zeros(0, dtype=np.int64) if project is None or project_nodes is None else np.asarray(project_nodes)
    H = len(hexes)
    incident = sp.csr_matrix(
        (np.ones(8 * H, dtype=bool), (np.repeat(np.arange(H), 8), hexes.ravel())), shape=(H, P)
    )
    thr = t + 3.0 * w  # hexes above this feel almost nothing of the hinge

    def select(X):
        """Active set: nodes of poor hexes and their neighbours' hexes; the hexes they touch."""
        hmin = sj_terms(X, hexes).min(axis=1)
        near = np.zeros(P, dtype=bool)
        near[hexes[hmin < thr].ravel()] = True
        ring = np.asarray(incident @ near).astype(bool) if near.any() else np.zeros(H, dtype=bool)
        act = np.zeros(P, dtype=bool)
        act[hexes[ring].ravel()] = True
        act &= movable
        ev = np.asarray(incident @ act).astype(bool)
        return act, np.flatnonzero(ev), hmin

    X = X0.copy()
    m1 = np.zeros_like(X)
    m2 = np.zeros_like(X)
    best_key, best_X, since = None, X0.copy(), 0
    best_deficit = np.inf
    it = 0
    for it in range(config.optimise_iterations + 1):
        if it % _REFRESH == 0:
            act, ev, hmin = select(X)
            static = np.ones(H, dtype=bool)
            static[ev] = False
            static_min = float(hmin[static].min()) if static.any() else np.inf
            static_sum = float(hmin[static].sum())
            ev_hexes = hexes[ev]
            pa = np.flatnonzero(act[pn])  # projected nodes that move
        deficit = 0.0
        if len(ev):
            s, g = sj_terms(X, ev_hexes, dfds, eps=(1e-3 * h) ** 2)
            if not np.isfinite(g).all():
                break
            per_hex = s.min(axis=1)
            mn = min(float(per_hex.min()), static_min)
            avg = (float(per_hex.sum()) + static_sum) / H
            deficit = float(np.maximum(_SJ_FLOOR - per_hex, 0.0).sum())
        else:
            mn, avg = static_min, static_sum / H
        # lexicographic: reach a minimum of _SJ_FLOOR first, then trade for the mean
        key = (mn, 0.0) if mn < _SJ_FLOOR else (_SJ_FLOOR, avg + 0.25 * mn)
        since += 1
        if best_key is None or key[0] > best_key[0] + 1e-6 or (
            key[0] >= best_key[0] and key[1] > best_key[1] + 1e-5
        ):
            best_key, best_X, since = key, X.copy(), 0
        # the worst hex may be stuck while the other poor ones still improve: keep going
        if deficit < best_deficit * (1.0 - 1e-3):
            best_deficit, since = deficit, 0
        if since >= config.optimise_patience or it == config.optimise_iterations or not len(ev):
            break
        if stop_when_valid and mn > _UNTANGLED:
            break
        g += (2.0 / (h * h * P)) * reg[:, None] * (X - X0)
        g[~act] = 0.0
        m1 = b1 * m1 + (1 - b1) * g
        m2 = b2 * m2 + (1 - b2) * g * g
        step = (m1 / (1 - b1 ** (it + 1))) / (np.sqrt(m2 / (1 - b2 ** (it + 1))) + eps)
        X = X - lr * step
        if len(pa):
            X[pn[pa]] = project(X[pn[pa]], pa)
    sj, _ = scaled_jacobian_and_degenerate(best_X, hexes)
    sj0, _ = scaled_jacobian_and_degenerate(X0, hexes)
    info = {
        "iterations": it,
        "sj_min_start": float(sj0.min()) if len(sj0) else None,
        "sj_avg_start": float(sj0.mean()) if len(sj0) else None,
        "sj_min": float(sj.min()) if len(sj) else None,
        "sj_avg": float(sj.mean()) if len(sj) else None,
        "seconds": time.perf_counter() - t0,
    }
    return best_X, info


# --------------------------------------------------------------------------- pillowing and smoothing


def pillow(
    points: np.ndarray, hexes: np.ndarray, thickness: float = 0.35
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pillow layer: a new hex between every boundary quad and inward copies of its nodes.

    Parameters
    ----------
    points : (P, 3) float
    hexes : (H, 8) int, positively oriented (VTK order)
    thickness : float in (0, 0.5], inner copies go along the inward vertex normal (sum of
        the incident boundary quad normals), ``thickness`` x the local thickness of the boundary
        layer deep: twice the depth of the mean centroid of the node's hexes along the normal
        (an edge length for a regular layer), but no more than that of any node of its boundary
        quads.  Where the normal is unreliable (it makes more than about 72 degrees with the
        direction to that centroid), towards the centroid instead.

    Returns
    -------
    points : (P + nb, 3) float64, the old points then the inner copies
    hexes : (H + Q, 8) int64, the old hexes (boundary nodes replaced by the inner copies)
        then one pillow hex per boundary quad (inner quad at the bottom, the outer quad on top)
    inner : (P,) int64, index of each boundary node's inner copy (-1 elsewhere)
    """
    points = np.asarray(points, dtype=np.float64)
    hexes = np.asarray(hexes, dtype=np.int64)
    P = len(points)
    quads = boundary_quads(hexes)
    nodes = np.unique(quads)
    inner = np.full(P, -1, dtype=np.int64)
    inner[nodes] = P + np.arange(len(nodes))
    # towards the mean centroid of the incident hexes: inside the solid even at corners and
    # saddles, where an averaged normal can point along a face
    cen = points[hexes].mean(axis=1)  # (H, 3)
    acc = np.zeros((P, 3))
    cnt = np.bincount(hexes.ravel(), minlength=P).astype(np.float64)
    for k in range(3):
        acc[:, k] = np.bincount(hexes.ravel(), weights=np.repeat(cen[:, k], 8), minlength=P)
    v = acc[nodes] / cnt[nodes, None] - points[nodes]  # node -> mean centroid of its hexes
    n = -_vertex_normals(points, quads, P)[nodes]  # inward unit normals
    along = np.einsum("ij,ij->i", v, n)
    vlen = np.linalg.norm(v, axis=1)
    # along the normal, as deep as the boundary layer is thick (twice the centroid depth);
    # where the normal is unreliable (a saddle, or it points along the hexes), towards the centroid
    ok = along > 0.3 * vlen
    # the layer depth at a node: twice its centroid depth, but no deeper than at any node of its
    # boundary quads (neighbouring inner copies at very different depths fold the pillow hexes
    # where the boundary layer is squeezed)
    depth = np.where(ok, 2.0 * along, 2.0 * vlen)
    loc = np.full(P, -1, dtype=np.int64)
    loc[nodes] = np.arange(len(nodes))
    ql = loc[quads]
    qmin = depth[ql].min(axis=1)
    ring = np.full(len(nodes), np.inf)
    np.minimum.at(ring, ql.ravel(), np.repeat(qmin, 4))
    depth = np.minimum(depth, ring)
    d = np.where(ok[:, None], n, v / np.maximum(vlen, 1e-300)[:, None])
    step = (thickness * depth)[:, None] * d
    remap = np.arange(P)
    remap[nodes] = inner[nodes]
    H2 = np.vstack([remap[hexes], np.concatenate([inner[quads], quads], axis=1)])
    X2 = np.vstack([points, points[nodes] + step])
    return X2, H2, inner


def guarded_smooth(
    points: np.ndarray,
    hexes: np.ndarray,
    movable: np.ndarray,
    *,
    sweeps: int = 5,
    step: float = 0.5,
) -> tuple[np.ndarray, dict]:
    """Laplacian smoothing that never lowers the minimum SJ of the hexes around a moved node.

    Each sweep moves every movable node ``step`` of the way to the average of its edge
    neighbours, all at once; then, repeatedly, every moved node whose incident hexes got a
    lower minimum SJ (or a lower SJ sum) than before the sweep is put back, until none is.
    A hex that got worse has a moved node whose incident minimum did not drop, so the
    minimum SJ of the mesh never decreases.

    Parameters
    ----------
    points : (P, 3) float
    hexes : (H, 8) int
    movable : (P,) bool
    sweeps : int
    step : float in (0, 1]

    Returns
    -------
    points : (P, 3) float64
    info : dict, ``moved`` (nodes moved per sweep), ``sj_min``, ``sj_avg``
    """
    X = np.asarray(points, dtype=np.float64).copy()
    hexes = np.asarray(hexes, dtype=np.int64)
    P = len(X)
    edges = hex_edges(hexes)
    A = sp.coo_matrix(
        (np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(P, P)
    ).tocsr()
    deg = np.asarray(A.sum(axis=1)).ravel()
    H = len(hexes)
    flat = hexes.ravel()
    incident, node_min = _hex_incidence(hexes, P)

    def node_sum(v):
        return np.bincount(flat, weights=np.repeat(v, 8), minlength=P)

    sj = _hex_sj(hexes, X, np.arange(H))
    moved_counts = []
    for _ in range(sweeps):
        before, before_sum = node_min(sj), node_sum(sj)
        target = (A @ X) / np.maximum(deg, 1)[:, None]
        active = movable & (deg > 0)
        Xn = X.copy()
        Xn[active] += step * (target[active] - X[active])
        sj_new = sj.copy()
        rows = np.flatnonzero(np.asarray(incident @ active))
        for _ in range(100):
            sj_new[rows] = _hex_sj(hexes, Xn, rows)  # only hexes around nodes that moved
            bad = active & ((node_min(sj_new) < before) | (node_sum(sj_new) < before_sum - 1e-12))
            if not bad.any():
                break
            Xn[bad] = X[bad]
            active &= ~bad
            rows = np.flatnonzero(np.asarray(incident @ bad))
        else:  # pragma: no cover - ``active`` shrinks every round, so this is not reached
            Xn, active, sj_new = X.copy(), np.zeros(P, dtype=bool), sj
        X, sj = Xn, sj_new
        moved_counts.append(int(active.sum()))
        if not active.any():
            break
    sj = scaled_jacobian_and_degenerate(X, hexes)[0]
    return X, {"moved": moved_counts, "sj_min": float(sj.min()), "sj_avg": float(sj.mean())}


# --------------------------------------------------------------------------- the pipeline


def _stats(X: np.ndarray, hexes: np.ndarray) -> dict:
    sj, dg = scaled_jacobian_and_degenerate(X, hexes)
    return {
        "sj_min": float(sj.min()),
        "sj_avg": float(sj.mean()),
        "inverted": int(((sj < 0) & ~dg).sum()),
        "degenerate": int(dg.sum()),
    }


def worth_retry(meta: dict, config: PullbackConfig) -> bool:
    """Whether a pulled-back mesh that is not valid is close enough to valid to be recomputed
    another way (``config.retry_min_sj``)."""
    sj = meta.get("sj_min")
    return sj is not None and float(sj) >= config.retry_min_sj


def pull_back(
    mesh_pc: HexMesh,
    to_part: Callable[[np.ndarray], np.ndarray],
    V: np.ndarray,
    F: np.ndarray,
    config: PullbackConfig = PullbackConfig(),
    diagonal: float | None = None,
) -> HexMesh:
    """Map a polycube-domain hex mesh onto the part (see the module docstring for the steps).

    ``diagonal``: the length ``meta["hausdorff"]`` is relative to (default: the bounding-box
    diagonal of ``V``; the pipeline passes the part's own, as its quality report uses).

    When the result is not valid (but its minimum SJ is at least ``config.retry_min_sj``) and
    the coverage fit of step 1b ran, the pull-back runs once more without it (the fit slides
    boundary nodes, which can leave a pillow layer that cannot be untangled) and the valid one of the two is returned (``meta["coverage_retry"]`` is
    ``"kept"`` or ``"discarded"``): validity first, then fidelity.
    """
    res = _pull_back_once(mesh_pc, to_part, V, F, config)
    if res.meta["valid"] or not config.coverage_iterations or not worth_retry(res.meta, config):
        out = _with_hausdorff(res, V, F, diagonal)
    else:
        again = _pull_back_once(mesh_pc, to_part, V, F, dataclasses.replace(config, coverage_iterations=0))
        total = res.meta["timings"]["total"] + again.meta["timings"]["total"]
        out = again if again.meta["valid"] else res
        out.meta["coverage_retry"] = "kept" if out is again else "discarded"
        out.meta["timings"]["total"] = total
        out = _with_hausdorff(out, V, F, diagonal)
    if config.ease_spots:
        out = ease_poor_hexes(out, V, F, config, diagonal)
    return mend_spots(out, V, F, config, diagonal) if config.capture_spots else out


def ease_poor_hexes(mesh: HexMesh, V: np.ndarray, F: np.ndarray, config: PullbackConfig = PullbackConfig(),
                    diagonal: float | None = None) -> HexMesh:
    """A mesh that is not valid, or valid with its minimum scaled Jacobian under ``config.ease_below``, untangled
    once more around its few poor hexes with the boundary nodes there given some slack off the part's surface.

    Where a part has a knife edge (a slanted cut crossing a hole: faces meeting at 20-30 degrees) that no polycube
    edge maps to, the pull-back holds every surface node on the surface, and a handful of hexes at the edge stay
    inverted or flat.  Here the nodes of the hexes under ``config.ease_below + config.ease_margin`` and of
    ``config.ease_rings`` rings around them move again (:func:`optimise_quality`), the surface nodes among them kept
    within ``config.ease_slack`` of the surface instead of on it.  The result is kept only when it is valid and, for
    a mesh that was valid already, has a higher minimum SJ and stays within ``max(bar, distance before)`` of the
    part (:data:`polycubenet.tol.HAUSDORFF_REL_MAX`; a farther one gets its spots mended first, :func:`mend_spots`,
    when ``config.capture_spots``); a mesh with more than ``config.ease_max_hexes`` poor hexes (a folded map, not a
    spot) is left as it is.  ``meta["eased"]`` says what was tried: the hexes eased, the nodes free to move, the
    surface nodes moved and how far the farthest of them was left off the surface (relative to the diagonal), the
    minimum SJ and the distance before and after, and whether the result was kept.

    ``V``, ``F``, ``diagonal``: as for :func:`pull_back` (``mesh`` in the units of ``V``)."""
    sj_before = mesh.meta.get("sj_min")
    valid_before = bool(mesh.meta.get("valid"))
    if sj_before is None or (valid_before and sj_before >= config.ease_below):
        return mesh
    t0 = time.perf_counter()
    V, centre, diag, X = _unit_frame(V, mesh.points)
    hexes = np.asarray(mesh.hexes, dtype=np.int64)
    sj, _ = scaled_jacobian_and_degenerate(X, hexes)
    under = config.ease_below + config.ease_margin
    poor = sj < under
    info = {"kept": False, "hexes": int(poor.sum()), "sj_min_before": float(sj_before),
            "hausdorff_before": mesh.meta.get("hausdorff")}
    if not poor.any() or poor.sum() > config.ease_max_hexes:
        mesh.meta["eased"] = {**info, "skipped": f"{int(poor.sum())} hexes under SJ {under:g}"}
        return mesh
    P = len(X)
    inc, _ = _hex_incidence(hexes, P)
    region = np.zeros(P, dtype=bool)
    region[hexes[poor].ravel()] = True
    for _ in range(config.ease_rings):
        region[hexes[np.asarray(inc @ region.astype(np.int64)) > 0].ravel()] = True
    surf = PartSurface((V - centre) / diag, F, config.feature_angle_deg)
    on = np.zeros(P, dtype=bool)
    on[boundary_quads(hexes).ravel()] = True
    loose = np.flatnonzero(on & region)
    slack = config.ease_slack * (diagonal or diag) / diag  # relative to the part's own diagonal

    def within_slack(x, _idx):
        c = surf.closest(x)[0]
        d = np.linalg.norm(x - c, axis=1, keepdims=True)
        return np.where(d > slack, c + (x - c) * (slack / np.maximum(d, 1e-300)), x)

    Y, _ = optimise_quality(X, hexes, movable=region, project=within_slack, project_nodes=loose, config=config)
    # optimise_quality projects the nodes it moves at each step; Adam's momentum can still carry a node a little
    # after it left the active set: every loose node within the slack at the end (the stats are of this state)
    Y[loose] = within_slack(Y[loose], None)
    st = _stats(Y, hexes)
    shifted = loose[np.any(Y[loose] != X[loose], axis=1)]  # the surface nodes the easing moved
    off = float(surf.closest(Y[shifted])[1].max()) * diag / (diagonal or diag) if len(shifted) else 0.0
    info.update(nodes=int(region.sum()), surface_nodes=int(len(shifted)), sj_min=st["sj_min"], off_surface_max=off)
    meta = {**mesh.meta, "timings": dict(mesh.meta.get("timings", {}))}
    meta["timings"]["ease"] = time.perf_counter() - t0
    if st["inverted"] or st["degenerate"] or not st["sj_min"] > 0 or (valid_before and st["sj_min"] <= sj_before):
        mesh.meta["eased"] = info
        mesh.meta.setdefault("timings", {})["ease"] = meta["timings"]["ease"]
        return mesh
    meta.update(valid=True, sj_min=st["sj_min"], sj_avg=st["sj_avg"],
                deviation=float(boundary_deviation(Y, hexes, surf)), stages={**mesh.meta.get("stages", {}), "eased": st},
                warnings=[w for w in mesh.meta.get("warnings", [])
                          if not w.startswith("The pulled-back mesh is not valid")])
    eased = _with_hausdorff(HexMesh(points=Y * diag + centre, hexes=hexes, boundary=mesh.boundary, meta=meta),
                            V, F, diagonal)
    info["hausdorff"] = eased.meta["hausdorff"]
    allowed = max(tol.HAUSDORFF_REL_MAX, info["hausdorff_before"] or 0.0)
    if valid_before and eased.meta["hausdorff"] > allowed and config.capture_spots:
        # the slack can leave a knife edge's tip a little farther off: its spots mended (mend_spots' guard keeps
        # every hex at min(capture_sj, its SJ))
        mended = mend_spots(eased, V, F, config, diagonal)
        info["mended"] = mended is not eased
        eased = mended
    if valid_before and eased.meta["hausdorff"] > allowed:
        mesh.meta["eased"] = info
        return mesh
    eased.meta["eased"] = {**info, "kept": True}
    return eased


def _unit_frame(V: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """``(V, centre, diag, X)``: the surface as float64, the centre and diagonal of its bounding box, and
    ``points`` moved to that centre and divided by that diagonal (the units the pull-back works in)."""
    V = np.asarray(V, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre, diag = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    return V, centre, diag, (np.asarray(points, dtype=np.float64) - centre) / diag


def mend_spots(mesh: HexMesh, V: np.ndarray, F: np.ndarray, config: PullbackConfig = PullbackConfig(),
               diagonal: float | None = None) -> HexMesh:
    """A valid pulled-back mesh off the part (``meta["hausdorff"]`` above :data:`polycubenet.tol.HAUSDORFF_REL_MAX`)
    with its uncovered spots captured (:func:`guarded_spot_capture`, at ``config.capture_target`` and under
    ``config.capture_sj``), the interior smoothed again (:func:`guarded_smooth`), when that brings it within the
    bar; else ``mesh`` as it is.  Any other mesh, and one more than ``config.capture_max`` off, is returned as
    it is.  ``meta["spots"]`` says what was tried (moves kept, samples left, farthest sample before and after),
    also when the mend is not kept, or why none was tried.

    ``V``, ``F``, ``diagonal``: as for :func:`pull_back` (``mesh`` in the units of ``V``)."""
    d = mesh.meta.get("hausdorff")
    if not mesh.meta.get("valid") or d is None or not d > tol.HAUSDORFF_REL_MAX:
        return mesh
    if d > config.capture_max:
        mesh.meta["spots"] = {"kept": False, "skipped": f"{100 * d:.2f} % off the part, more than the "
                                                        f"{100 * config.capture_max:g} % a mend is tried at"}
        return mesh
    t0 = time.perf_counter()
    V, centre, diag, X = _unit_frame(V, mesh.points)
    hexes = mesh.hexes
    surf = PartSurface((V - centre) / diag, F, config.feature_angle_deg)
    nodes = np.unique(boundary_quads(hexes))
    edges = hex_edges(hexes)
    hloc = _mean_edge_length(X, edges, len(X))[nodes]
    # each surface node's one neighbour inside (its inner pillow copy, or the next layer's node), -1 if not one
    on = np.zeros(len(X), dtype=bool)
    on[nodes] = True
    a, b = np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([edges[:, 1], edges[:, 0]])
    inward = on[a] & ~on[b]
    count = np.bincount(a[inward], minlength=len(X))
    follow = np.full(len(X), -1, dtype=np.int64)
    follow[a[inward]] = b[inward]
    follow[count != 1] = -1
    target = config.capture_target * (diagonal or diag) / diag  # relative to the part's own diagonal
    X, info = guarded_spot_capture(surf, X, hexes, nodes, hloc, config.capture_sj, trigger=target, target=target,
                                   follow=follow, tries=config.capture_tries)
    mesh.meta["spots"] = {**info, "kept": False}
    if not info["spot_captures"]:
        return mesh
    if config.smoothing_sweeps:
        bmask = boundary_vertex_mask(hexes, len(X))
        X, _ = guarded_smooth(X, hexes, ~bmask, sweeps=config.smoothing_sweeps, step=config.smoothing_step)
    st = _stats(X, hexes)
    if st["inverted"] or st["degenerate"] or not st["sj_min"] > 0:  # pragma: no cover - the guard keeps it valid
        return mesh
    meta = {**mesh.meta, "sj_min": st["sj_min"], "sj_avg": st["sj_avg"],
            "deviation": float(boundary_deviation(X, hexes, surf)), "timings": dict(mesh.meta.get("timings", {}))}
    meta["timings"]["mend_spots"] = time.perf_counter() - t0
    meta["stages"] = {**mesh.meta.get("stages", {}), "spots_mended": st}
    mended = _with_hausdorff(HexMesh(points=X * diag + centre, hexes=hexes, boundary=mesh.boundary, meta=meta),
                             V, F, diagonal)
    if not mended.meta["hausdorff"] <= tol.HAUSDORFF_REL_MAX:
        mesh.meta["spots"]["after"] = mended.meta["hausdorff"]
        return mesh
    mended.meta["spots"] = {**info, "kept": True, "hausdorff_before": d, "sj_min_before": mesh.meta.get("sj_min")}
    return mended


def _with_hausdorff(mesh: HexMesh, V: np.ndarray, F: np.ndarray, diagonal: float | None = None) -> HexMesh:
    """``meta["hausdorff"]`` of a valid mesh: the quality report's sampled two-sided distance
    (:func:`polycubenet.quality.surface_distance`, relative to ``diagonal``, default that of ``V``), which
    the fallback policy checks against the bar.  ``deviation`` is a cheaper lower bound that
    reads up to ~12 % lower (threaded rod, 28-cell voxel polycube: 1.05 % against 1.18 %), too
    little for a decision at the bar.  ~0.4 s; not measured for a mesh that is not valid."""
    from .quality import surface_distance

    if mesh.meta.get("valid"):
        t0 = time.perf_counter()
        from .hexmesh import quads_to_triangles

        d = surface_distance(mesh.points, quads_to_triangles(boundary_quads(mesh.hexes)), V, F)  # the report's samples
        mesh.meta["hausdorff"] = float(d["hausdorff"] * d["diagonal"] / (diagonal or d["diagonal"]))
        mesh.meta["timings"]["hausdorff"] = time.perf_counter() - t0
    return mesh


def _pull_back_once(
    mesh_pc: HexMesh,
    to_part: Callable[[np.ndarray], np.ndarray],
    V: np.ndarray,
    F: np.ndarray,
    config: PullbackConfig = PullbackConfig(),
) -> HexMesh:
    """One run of the pull-back: the parameters and the result are those of :func:`pull_back`.

    Parameters
    ----------
    mesh_pc : HexMesh
        ``points (P, 3)`` in the polycube domain (boundary quads axis-aligned, e.g. from
        :func:`polycubenet.hexmesh.partition`), ``hexes (H, 8)`` positively oriented.
    to_part : callable
        ``(K, 3) -> (K, 3)``: polycube-domain points to (approximate) part positions;
        evaluated on every node.
    V : (nv, 3) float
        The part's true surface vertices.
    F : (nf, 3) int
        Its triangles (outward).
    config : PullbackConfig

    Returns
    -------
    HexMesh
        On the part: ``points (P', 3)``, ``hexes (H', 8)`` (``H' = H + boundary quads`` when
        pillowed), ``boundary (P',)``.  ``meta`` has ``timings`` (seconds per step),
        ``stages`` (SJ min/avg/inverted/degenerate after each step), ``pillowed``,
        ``multi_boundary_before`` / ``multi_boundary_after`` (hexes with >= 2 boundary
        faces), ``projection`` (fallbacks, snapped nodes, chart sizes), ``node_kinds``,
        ``valid``, ``deviation`` (:func:`boundary_deviation` relative to the diagonal),
        ``hausdorff`` (of :func:`pull_back`, valid meshes only: the sampled distance that the
        fallback policy checks against the bar), ``sj_min``, ``sj_avg`` and
        ``warnings`` (sentences).

    Raises
    ------
    ValueError
        Bad shapes, an empty mesh or surface, non-finite values from ``to_part``.
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise ValueError(f"V must be (nv, 3) with nv > 0; got shape {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise ValueError(f"F must be (nf, 3) triangles; got shape {F.shape}")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError("F indexes outside V")
    if not np.isfinite(V).all():
        raise ValueError("V has NaN or infinite coordinates")
    if len(mesh_pc.hexes) == 0:
        raise ValueError("the hex mesh has no hexes")
    timings: dict = {}
    stages: dict = {}
    warnings: list = []
    t_all = time.perf_counter()

    # work in the surface's normalised frame (centre 0, diagonal 1): float32 queries stay precise
    lo, hi = V.min(axis=0), V.max(axis=0)
    centre, diag = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    if not diag > 0:
        raise ValueError("the surface has a zero bounding box")

    def norm(x):
        return (x - centre) / diag

    def mapped(p):
        y = np.asarray(to_part(p), dtype=np.float64)
        if y.shape != p.shape:
            raise ValueError(f"to_part returned shape {y.shape} for input {p.shape}")
        if not np.isfinite(y).all():
            raise ValueError("to_part returned NaN or infinite positions")
        return norm(y)

    # ---- step 1: boundary
    t0 = time.perf_counter()
    Ppc = mesh_pc.points
    hexes = mesh_pc.hexes
    n_pts = len(Ppc)
    surf = PartSurface(norm(V), F, config.feature_angle_deg)
    bs = classify_boundary(Ppc, hexes)
    Y_all = mapped(Ppc)
    edges = hex_edges(hexes)
    Yb = Y_all[bs.nodes]
    h_all = _mean_edge_length(Y_all, edges, n_pts)
    hloc = h_all[bs.nodes]
    nrm = _vertex_normals(Y_all, bs.quads, n_pts)[bs.nodes]
    Yt = np.zeros_like(Yb)
    en = np.flatnonzero(bs.kind == 2)
    if len(en):
        eps = 0.25 * _mean_edge_length(Ppc, edges, n_pts)[bs.nodes[en]][:, None]
        p = Ppc[bs.nodes[en]]
        Yt[en] = mapped(p + eps * bs.tangent[en]) - mapped(p - eps * bs.tangent[en])
    Xb, con, proj_info = _place_boundary(surf, bs, Yb, Yt, hloc, nrm, config)
    cov = None
    if config.coverage_iterations or config.final_coverage_iterations:
        t1 = time.perf_counter()
        cov = _Coverage(surf, bs, config)
        Xb, cov_info = fit_coverage(cov, Xb, con, hloc, config.coverage_iterations)
        proj_info.update(cov_info)
        timings["coverage"] = time.perf_counter() - t1
    n_fb = sum(v for k, v in proj_info["fallbacks"].items() if k != "snap_rejected")
    if n_fb:
        warnings.append(
            f"{n_fb} boundary nodes were projected freely because their chart projection was more than "
            f"{config.fallback_excess:g} element sizes farther than the free closest point."
        )
    timings["boundary"] = time.perf_counter() - t0
    stages["mapped"] = _stats(Y_all, hexes)

    # ---- step 2: interior
    t0 = time.perf_counter()
    fixed = np.zeros(n_pts, dtype=bool)
    fixed[bs.nodes] = True
    if config.interior == "correction":
        corr = np.zeros((n_pts, 3))
        corr[bs.nodes] = Xb - Yb
        X = Y_all + harmonic_extension(edges, n_pts, fixed, corr)
    else:
        vals = np.zeros((n_pts, 3))
        vals[bs.nodes] = Xb
        X = harmonic_extension(edges, n_pts, fixed, vals)
    X[bs.nodes] = Xb
    timings["interior"] = time.perf_counter() - t0
    stages["interior"] = _stats(X, hexes)

    # ---- step 3: untangle + optimise
    def proj(xb, idx):
        return _project(surf, xb, con, idx)

    movable = np.ones(n_pts, dtype=bool)
    movable[bs.nodes[con.mode == _FIXED]] = False

    def regularisation(n_total):
        reg = np.full(n_total, config.regularisation)
        reg[bs.nodes] = np.where(
            (bs.kind >= 2) & (con.mode != _CURVE), config.edge_regularisation, config.boundary_regularisation
        )
        reg[bs.nodes[con.released]] = config.release_regularisation
        return reg

    t0 = time.perf_counter()
    X, opt_info = optimise_quality(
        X, hexes, movable=movable, project=proj, project_nodes=bs.nodes, config=config,
        stop_when_valid=config.pillow and config.untangle_only_before_pillow,
        regularisation=regularisation(n_pts),
    )
    timings["optimise"] = time.perf_counter() - t0
    stages["optimised"] = _stats(X, hexes)
    stages["optimised"]["iterations"] = opt_info["iterations"]

    # ---- step 4: pillowing
    multi_before = int((boundary_face_counts(hexes) >= 2).sum())
    multi_after = multi_before
    if config.pillow:
        t0 = time.perf_counter()
        X, hexes, inner = pillow(X, hexes, config.pillow_thickness)
        timings["pillow"] = time.perf_counter() - t0
        multi_after = int((boundary_face_counts(hexes) >= 2).sum())
        stages["pillowed"] = _stats(X, hexes)
        movable = np.concatenate([movable, np.ones(len(X) - n_pts, dtype=bool)])
        if config.pillow_fix_boundary:  # the surface nodes stay where projection put them
            movable = movable.copy()
            movable[bs.nodes] = False
        t0 = time.perf_counter()
        X, opt_info2 = optimise_quality(
            X, hexes, movable=movable, project=proj, project_nodes=bs.nodes, config=config,
            regularisation=regularisation(len(X)),
        )
        timings["optimise_pillow"] = time.perf_counter() - t0
        stages["pillow_optimised"] = _stats(X, hexes)
        stages["pillow_optimised"]["iterations"] = opt_info2["iterations"]

    # ---- feature constraints that keep a hex poor are released, then optimise again
    loc = np.full(len(X), -1, dtype=np.int64)
    loc[bs.nodes] = np.arange(len(bs.nodes))

    def copy_con(c):
        return dataclasses.replace(c, mode=c.mode.copy(), curve=c.curve.copy(), released=c.released.copy())

    def release(X, pull, stage):
        """The release rounds with ``pull`` as the released nodes' regularisation (``stages[stage]`` after each):
        ``(X, released, unreleased)``, ``unreleased`` the valid state before the first release (None when there
        was none)."""
        released, unreleased = 0, None
        for _ in range(config.release_rounds):
            sj_before = scaled_jacobian_and_degenerate(X, hexes)
            valid_before = bool(sj_before[0].min() > 0 and not sj_before[1].any())
            if valid_before and sj_before[0].min() >= config.release_sj:
                break
            if valid_before and unreleased is None and not con.released.any():
                unreleased = (X.copy(), copy_con(con), movable.copy(), boundary_deviation(X, hexes, surf))
            # the nodes of the poor corners (a corner term below the bar, with its three neighbours)
            terms = sj_terms(X, hexes)[:, 1:]  # (H, 8) corner terms
            hb, kb = np.nonzero(terms < config.release_sj)
            bad_nodes = np.unique(hexes[hb[:, None], CORNER_FRAMES[kb]])
            li = loc[bad_nodes]
            li = li[li >= 0]
            li = li[~con.released[li]]
            if not len(li):
                break
            pinned = (con.mode[li] == _CURVE) | (con.mode[li] == _FIXED)
            con.mode[li[pinned]] = _CHART
            con.curve[li[pinned]] = -1
            released += int(pinned.sum())
            movable[bs.nodes[li]] = True
            con.released[li] = True
            t0 = time.perf_counter()
            reg = regularisation(len(X))
            reg[bs.nodes[con.released]] = pull
            X, _ = optimise_quality(
                X, hexes, movable=movable, project=proj, project_nodes=bs.nodes, config=config, regularisation=reg,
            )
            timings["optimise_released"] = timings.get("optimise_released", 0.0) + time.perf_counter() - t0
            stages[stage] = _stats(X, hexes)
        return X, released, unreleased

    X, released, unreleased = release(X, config.release_regularisation, "released")
    reverted = False
    proj_info["re_released"] = False

    # ---- step 4c: the coverage fit again, guarded
    def final_coverage(X, con):
        if cov is None or not config.final_coverage_iterations:
            return X
        t0 = time.perf_counter()
        follow = inner if config.pillow and config.final_coverage_follow else None
        X, gi = guarded_coverage(
            cov, X, hexes, bs.nodes, con, hloc, config.final_coverage_iterations, config.final_coverage_sj,
            follow=follow,
        )
        proj_info.update(gi)
        if config.snap_corners:
            X, ci = guarded_corner_snap(surf, X, hexes, bs.nodes, hloc, config.final_coverage_sj, follow=follow)
            proj_info.update(ci)
        timings["coverage_final"] = timings.get("coverage_final", 0.0) + time.perf_counter() - t0
        stages["coverage_final"] = _stats(X, hexes)
        return X

    X = final_coverage(X, con)
    # the boundary is final from here (the smoothing moves interior nodes only): measured once
    deviation = boundary_deviation(X, hexes, surf)  # the diagonal is 1 here: relative to it
    if unreleased is not None and con.released.any():
        # a valid mesh is released only where it does not cost the surface fidelity
        X_un, con_un, movable_un, dev_un = unreleased
        allowed = max(1.1 * dev_un, config.release_max_deviation)
        if deviation > allowed:
            stages["release_undone"] = {"deviation": deviation, "deviation_before": dev_un, **_stats(X, hexes)}
            con = copy_con(con_un)
            X, released, reverted = final_coverage(X_un.copy(), con), 0, True
            deviation = boundary_deviation(X, hexes, surf)
            if config.release_retry_regularisation > config.release_regularisation:
                # once more from the unreleased state, the released nodes held closer to where they were
                kept = (X, con, deviation, _stats(X, hexes)["sj_min"])
                con, movable = copy_con(con_un), movable_un.copy()
                Xr, n_r, _ = release(X_un.copy(), config.release_retry_regularisation, "released_again")
                Xr = final_coverage(Xr, con)
                dev_r = boundary_deviation(Xr, hexes, surf)
                st = _stats(Xr, hexes)
                stages["re-released"] = {"deviation": dev_r, **st}
                ok = st["inverted"] == 0 and st["degenerate"] == 0 and st["sj_min"] > kept[3]
                if ok and dev_r <= allowed:
                    X, deviation, released, reverted = Xr, dev_r, n_r, False
                else:
                    X, con, deviation = kept[:3]
                    stages["coverage_final"] = _stats(X, hexes)
            proj_info["re_released"] = not reverted
    proj_info["released"] = int(released)
    proj_info["release_reverted"] = bool(reverted)
    modes = (("chart", _CHART), ("curve", _CURVE), ("fixed", _FIXED), ("free", _FREE))
    proj_info["final_modes"] = {name: int((con.mode == code).sum()) for name, code in modes}

    # ---- step 5: guarded smoothing of the interior
    bmask = boundary_vertex_mask(hexes, len(X))
    if config.smoothing_sweeps:
        t0 = time.perf_counter()
        X, sm = guarded_smooth(X, hexes, ~bmask, sweeps=config.smoothing_sweeps, step=config.smoothing_step)
        timings["smooth"] = time.perf_counter() - t0
        stages["smoothed"] = _stats(X, hexes)
        stages["smoothed"]["moved"] = sm["moved"]

    final = _stats(X, hexes)
    valid = final["inverted"] == 0 and final["degenerate"] == 0 and final["sj_min"] > 0
    if not valid:
        warnings.append(
            f"The pulled-back mesh is not valid: {final['inverted']} inverted and {final['degenerate']} "
            f"degenerate hexes, minimum scaled Jacobian {final['sj_min']:.4f}."
        )
    timings["total"] = time.perf_counter() - t_all
    kinds = {
        "face": int((bs.kind == 1).sum()),
        "edge": int((bs.kind == 2).sum()),
        "corner": int((bs.kind >= 3).sum()),
    }
    meta = {
        "timings": timings,
        "stages": stages,
        "pillowed": bool(config.pillow),
        "multi_boundary_before": multi_before,
        "multi_boundary_after": multi_after,
        "projection": proj_info,
        "node_kinds": kinds,
        "interior": config.interior,
        "valid": bool(valid),
        "deviation": float(deviation),
        "sj_min": final["sj_min"],
        "sj_avg": final["sj_avg"],
        "warnings": warnings,
        "config": dataclasses.asdict(config),
    }
    return HexMesh(points=X * diag + centre, hexes=hexes, boundary=bmask, meta=meta)


__all__ = [
    "LABELS",
    "PullbackConfig",
    "PartSurface",
    "BoundaryStructure",
    "classify_boundary",
    "chart_labels",
    "quad_corner_quality",
    "boundary_deviation",
    "harmonic_extension",
    "hex_edges",
    "boundary_face_counts",
    "optimise_quality",
    "sj_terms",
    "pillow",
    "guarded_smooth",
    "fit_coverage",
    "guarded_coverage",
    "pull_back",
    "mend_spots",
    "ease_poor_hexes",
    "guarded_spot_capture",
    "worth_retry",
]


def _hex_incidence(hexes: np.ndarray, P: int):
    """The hex -> node incidence (H x P boolean CSR) and ``node_min(v)``: for a value per hex,
    the minimum over the hexes around each node (inf at nodes no hex uses)."""
    H = len(hexes)
    flat = hexes.ravel()
    order = np.argsort(flat, kind="stable")
    used = np.unique(flat)
    starts = np.searchsorted(flat[order], used)
    incident = sp.csr_matrix((np.ones(8 * H, dtype=bool), (np.repeat(np.arange(H), 8), flat)), shape=(H, P))

    def node_min(v):
        m = np.full(P, np.inf)
        m[used] = np.minimum.reduceat(np.repeat(v, 8)[order], starts)
        return m

    return incident, node_min
