"""The anchored model's own map from its polycube to the part.

An anchored model (``ModelConfig.anchored``) generates each cloud point by moving one
point of the part (its *anchor*) onto the polycube, so a generated cloud already says,
point by point, which part point each polycube point stands for.  Registration
(:func:`polycubenet.registration.align`) ignores that and fits a smooth field (CPD,
``beta = 0.5`` of the diagonal) that moves the cloud onto the part samples; such a field
is near the identity and cannot stretch a box's end face over a slanted end, or a box
over a round boss, which the model's correspondences do by construction.

:func:`anchor_map` turns the correspondences into a map of the polycube domain:

1. each cleaned cloud point is snapped onto the extracted polycube's surface, onto the
   nearest face whose outward normal is the point's own (generated) normal axis; points
   farther than ``max_snap`` from any such face carry a structure the polycube does not
   have and are dropped;
2. ``map_points(z) = z + sum_i w_i (a_i - p_i) / sum_i w_i`` over the ``k`` nearest
   snapped points ``p_i``, ``w_i = exp(-|z - p_i|^2 / (2 sigma^2))`` with ``sigma`` a
   multiple of the snapped points' spacing: a local average of the model's
   displacements, which smooths their noise over a few neighbours and no further.

The pull-back then projects the mapped boundary onto the part as for any other map.
The map uses nothing but the generated cloud and its anchors, so a mesh pulled back
through it is still the learned polycube's (the structure is the extraction's, the
map the model's).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from .data import Polycube

#: Gaussian width of the displacement average, in multiples of the snapped points' median spacing
SIGMA_SPACINGS = 1.5
#: neighbours in the displacement average
K_NEIGHBOURS = 16
#: a cloud point farther than this from every polycube face of its normal's direction (in multiples of
#: the median spacing) is not used
MAX_SNAP_SPACINGS = 4.0


@dataclasses.dataclass
class AnchorMap:
    """Polycube domain -> part, from the model's own correspondences (see the module docstring).

    Attributes
    ----------
    points : (M, 3) float64, cloud points snapped onto the polycube's surface
    anchors : (M, 3) float64, the part point each was generated from
    sigma : float, Gaussian width of the displacement average (canonical frame)
    k : int, neighbours averaged
    meta : dict, ``method``, ``used`` / ``dropped`` point counts, ``spacing``, ``sigma``
    """

    points: np.ndarray
    anchors: np.ndarray
    sigma: float
    k: int = K_NEIGHBOURS
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self.points = np.asarray(self.points, np.float64)
        self.anchors = np.asarray(self.anchors, np.float64)
        if self.points.shape != self.anchors.shape or self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points and anchors must both be (M, 3); got {self.points.shape} and {self.anchors.shape}")
        if len(self.points) == 0:
            raise ValueError("an anchor map needs at least one point")
        self._tree = cKDTree(self.points)
        self._disp = self.anchors - self.points

    def map_points(self, points: np.ndarray) -> np.ndarray:
        """``(K, 3)`` polycube-domain points -> ``(K, 3)`` approximate part positions."""
        Z = np.asarray(points, np.float64)
        if len(Z) == 0:
            return Z.copy()
        k = min(self.k, len(self.points))
        d, idx = self._tree.query(Z, k=k)
        if k == 1:
            d, idx = d[:, None], idx[:, None]
        # relative to each query's nearest neighbour, so that a node far from every point still gets the
        # average of its nearest ones instead of 0 / 0
        w = np.exp(-(d**2 - d[:, :1] ** 2) / (2.0 * self.sigma**2))
        return Z + np.einsum("kn,knd->kd", w, self._disp[idx]) / w.sum(1, keepdims=True)


def snap_to_polycube(poly: Polycube, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point's closest point on a face of ``poly`` whose outward normal is the point's normal's
    dominant axis and sign: ``(snapped (M, 3), distance (M,))``; ``inf`` where ``poly`` has no face
    of that direction."""
    import trimesh

    from .polycube import polycube_surface

    V, F = polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy)
    tri_n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    tri_lab = _direction(tri_n)
    P = np.asarray(points, np.float64)
    lab = _direction(np.asarray(normals, np.float64))
    out = P.copy()
    dist = np.full(len(P), np.inf)
    for lbl in np.unique(lab):
        faces = np.flatnonzero(tri_lab == lbl)
        sel = np.flatnonzero(lab == lbl)
        if len(faces) == 0 or len(sel) == 0:
            continue
        mesh = trimesh.Trimesh(V, F[faces], process=False)
        closest, dd, _ = trimesh.proximity.closest_point(mesh, P[sel])
        out[sel], dist[sel] = closest, dd
    return out, dist


def _direction(n: np.ndarray) -> np.ndarray:
    """0..5: +x, -x, +y, -y, +z, -z of each row's dominant component (:func:`polycubenet.structure.axis_labels`
    with no cone: every normal has one)."""
    from .structure import axis_labels

    axis, sign = axis_labels(n, cone_deg=90.0)
    return 2 * axis + (sign < 0).astype(int)


def anchor_map(poly: Polycube, points: np.ndarray, normals: np.ndarray, anchors: np.ndarray, *,
               sigma_spacings: float = SIGMA_SPACINGS, max_snap_spacings: float = MAX_SNAP_SPACINGS,
               k: int = K_NEIGHBOURS) -> AnchorMap:
    """The :class:`AnchorMap` of a generated cloud ``(points, normals)`` (cleaned, canonical frame), the part
    points ``anchors`` it was generated from (row by row) and the polycube ``poly`` extracted from it.

    Raises ValueError when the shapes disagree or no point lies near a face of its direction."""
    P = np.asarray(points, np.float64)
    A = np.asarray(anchors, np.float64)
    if P.shape != A.shape or P.ndim != 2 or P.shape[1] != 3 or np.shape(normals) != P.shape:
        raise ValueError(f"points, normals and anchors must all be (M, 3); got {P.shape}, {np.shape(normals)}, {A.shape}")
    snapped, dist = snap_to_polycube(poly, P, normals)
    nn = cKDTree(snapped).query(snapped, k=2)[0][:, 1] if len(snapped) > 1 else np.ones(1)
    spacing = float(np.median(nn[nn > 0])) if np.any(nn > 0) else 1e-3
    keep = dist <= max_snap_spacings * spacing
    if not keep.any():
        raise ValueError("no generated point lies near a polycube face of its own direction")
    sigma = sigma_spacings * spacing
    return AnchorMap(snapped[keep], A[keep], sigma, k, meta={
        "method": "anchors (the model's own correspondences)", "used": int(keep.sum()),
        "dropped": int((~keep).sum()), "spacing": spacing, "sigma": sigma})
