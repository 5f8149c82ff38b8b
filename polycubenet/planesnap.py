"""One plane per planar face of the part, in an anchored model's cloud.

An anchored model (``ModelConfig.anchored``) makes each cloud point from one point of the part
(its anchor), so the cloud says which part face each of its points stands for.  A planar face of
a CAD part is one chart of its polycube map: the classical flattening gives all of it one label
and lays it onto one plane.  The model does not quite: it moves a slanted face only part of the
way onto its plane (``benchmarks/slant_moves.py``: about 0.7 of it), and the ramp left over is cut
by the structure extraction into a staircase of thin planes that the part does not have.

:func:`plane_patches` finds the planar faces among the anchors (connected, coplanar, same normal,
wide enough in both directions), and :func:`snap_planes` moves the cloud points of each such face
that carry its majority label onto one coordinate along that label's axis (their median): the
structure the model meant, without the slope it left.

It does remove the ramps, but on never-seen parts it meshed no more of them (session 33: the parts it is
meant for fail elsewhere too; ``PipelineConfig.snap_planes`` and the model card), so the pipeline runs it
only when asked (``PipelineConfig.snap_planes``, ``benchmarks/unseen_parts.py --snap-planes``).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .structure import axis_labels, point_spacing

#: anchors closer than this many median spacings (white-noise samples: well above their percolation
#: radius), with normals within ``NORMAL_DEG`` and on one plane, are one face
RADIUS_SPACINGS = 4.0
NORMAL_DEG = 3.0
#: a face needs this many cloud points and this many anchor spacings of extent in both of its directions
#: (a tessellated round face gives thin strips, which are left alone)
MIN_POINTS = 20
MIN_EXTENT_SPACINGS = 3.0
#: the face's majority label must hold at least this share of its points
MIN_LABEL_SHARE = 0.6
#: a patch is a facet of a tessellated round face, not a face, when more than ``SMOOTH_SHARE`` of the anchors
#: around it (not in it) turn less than ``SMOOTH_DEG`` from its normal: a CAD face meets its neighbours at an edge
SMOOTH_DEG = 15.0
SMOOTH_SHARE = 0.25


def plane_patches(anchors: np.ndarray, normals: np.ndarray, spacing: float | None = None, *,
                  normal_deg: float = NORMAL_DEG, radius_spacings: float = RADIUS_SPACINGS,
                  min_points: int = MIN_POINTS, min_extent_spacings: float = MIN_EXTENT_SPACINGS) -> np.ndarray:
    """``(M,) int`` planar-face id of each anchor (``-1``: on no planar face wide enough, or on a facet of
    a round face: one that meets its neighbours smoothly, ``SMOOTH_DEG``).

    ``anchors (M, 3)`` are part points with their (face) ``normals (M, 3)``; ``spacing`` defaults to
    their median nearest-neighbour distance."""
    A = np.asarray(anchors, np.float64)
    n = np.asarray(normals, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    out = np.full(len(A), -1, dtype=np.int64)
    if len(A) < min_points:
        return out
    h = point_spacing(A) if spacing is None else float(spacing)
    cos_n = np.cos(np.radians(normal_deg))
    tree = cKDTree(A)
    pairs = tree.query_pairs(radius_spacings * h, output_type="ndarray")
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        same = (np.einsum("ij,ij->i", n[i], n[j]) >= cos_n) & (np.abs(np.einsum("ij,ij->i", A[j] - A[i], n[i])) <= 0.25 * h)
        pairs = pairs[same]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(A), len(A)))
    _, comp = connected_components(graph, directed=False)
    next_id = 0
    for c in np.flatnonzero(np.bincount(comp) >= min_points):
        members = np.flatnonzero(comp == c)
        m = n[members].mean(axis=0)
        m /= max(np.linalg.norm(m), 1e-12)
        if np.min(n[members] @ m) < np.cos(np.radians(2.0 * normal_deg)):  # chained along a curved face
            continue
        R = A[members] - A[members].mean(axis=0)
        vt = np.linalg.svd(R, full_matrices=False)[2]
        span = [np.subtract(*np.percentile(R @ vt[k], [95, 5])) for k in (0, 1)]
        if min(span) < min_extent_spacings * h:
            continue
        # stragglers on the face's plane (small components at its corners and rims) join it, grown
        # through its neighbourhood until nothing more joins
        centre, face, new = A[members].mean(axis=0), members, members
        near = np.empty(0, dtype=np.int64)
        while True:  # only the points that joined last are queried again
            near = np.union1d(near, np.concatenate(tree.query_ball_point(A[new], radius_spacings * h)).astype(np.int64))
            ring = np.setdiff1d(near, face)
            on = (n[ring] @ m >= cos_n) & (np.abs((A[ring] - centre) @ m) <= 0.25 * h) & (out[ring] < 0)
            if not on.any():
                break
            new = ring[on]
            face = np.union1d(face, new)
        off = ring[n[ring] @ m < cos_n]
        if len(off) and np.mean(n[off] @ m >= np.cos(np.radians(SMOOTH_DEG))) > SMOOTH_SHARE:
            continue
        out[face] = next_id
        next_id += 1
    return out


def snap_planes(points: np.ndarray, normals: np.ndarray, anchors: np.ndarray, anchor_normals: np.ndarray, *,
                min_deg: float = 0.0, min_label_share: float = MIN_LABEL_SHARE) -> tuple[np.ndarray, dict]:
    """The cloud ``points (M, 3)`` (generated ``normals``) with each planar part face's points on one plane.

    ``anchors`` / ``anchor_normals`` ``(M, 3)``: the part point each cloud point was made from, and its
    normal.  A face (:func:`plane_patches`) is snapped when one label (axis and sign of the generated
    normals, :func:`~polycubenet.structure.axis_labels`) holds ``min_label_share`` of its points and the
    face is tilted at least ``min_deg`` degrees from that axis (0: every face, the axis-aligned ones
    too); its points with that label move along the axis to their median coordinate.

    Returns the moved copy and ``{"faces": snapped faces, "tilted": of them at least 5 degrees from
    their axis, "points": points moved}``."""
    P = np.array(points, dtype=np.float64, copy=True)
    patch = plane_patches(anchors, anchor_normals)
    axis, sign = axis_labels(normals)
    an = np.asarray(anchor_normals, np.float64)
    info = {"faces": 0, "tilted": 0, "points": 0}
    for r in range(int(patch.max()) + 1 if len(patch) else 0):
        idx = np.flatnonzero(patch == r)
        lab = axis[idx] * 2 + (sign[idx] > 0)
        lab = lab[axis[idx] >= 0]
        if len(lab) == 0:
            continue
        counts = np.bincount(lab, minlength=6)
        best = int(np.argmax(counts))
        if counts[best] < min_label_share * len(idx):
            continue
        a, s = best // 2, 1 if best % 2 else -1
        m = an[idx].mean(axis=0)
        tilt = np.degrees(np.arccos(min(1.0, abs(m[a]) / max(np.linalg.norm(m), 1e-12))))
        if tilt < min_deg:
            continue
        move = idx[(axis[idx] == a) & (sign[idx] == s)]
        P[move, a] = np.median(P[move, a])
        info["faces"] += 1
        info["tilted"] += int(tilt >= 5.0)
        info["points"] += len(move)
    return P, info
