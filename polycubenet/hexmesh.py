"""Topology helpers for all-hex meshes.

Hexes are in VTK_HEXAHEDRON order (see :class:`polycubenet.data.HexMesh`): the
bottom face 0-1-2-3 counter-clockwise seen from the top, then the top face
4-5-6-7 above it.  For a positively oriented hex the six faces listed in
:data:`HEX_FACES` have outward normals (right-hand rule).

Functions
---------
boundary_quads
    The faces used by exactly one hex, oriented outward.
boundary_vertex_mask
    Which points lie on those faces.
hex_volumes
    Exact (signed) volume of each trilinear hex.
partition
    Regular partition of a polycube (grid + occupancy) into conforming hexes.
"""

from __future__ import annotations

import numpy as np

from .data import HexMesh

#: The six faces of a VTK hexahedron, each listed so that its normal points out
#: of a positively oriented hex (same faces and orientation as ``vtkHexahedron``).
HEX_FACES = np.array(
    [
        [0, 4, 7, 3],  # xi = 0
        [1, 2, 6, 5],  # xi = 1
        [0, 1, 5, 4],  # eta = 0
        [3, 7, 6, 2],  # eta = 1
        [0, 3, 2, 1],  # zeta = 0 (bottom)
        [4, 5, 6, 7],  # zeta = 1 (top)
    ],
    dtype=np.int64,
)

#: The twelve edges of a VTK hexahedron as pairs of local corner indices.
HEX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]],
    dtype=np.int64,
)


def _as_hexes(hexes) -> np.ndarray:
    hexes = np.asarray(hexes, dtype=np.int64)
    if hexes.ndim != 2 or hexes.shape[1] != 8:
        raise ValueError(f"hexes must be (H, 8); got shape {hexes.shape}")
    return hexes


def all_faces(hexes) -> np.ndarray:
    """Every face of every hex, oriented outward from its hex.

    Parameters
    ----------
    hexes : (H, 8) int
        VTK hexahedron connectivity.

    Returns
    -------
    faces : (6*H, 4) int64
        Face ``6*h + k`` is face ``k`` of :data:`HEX_FACES` of hex ``h``.
    """
    hexes = _as_hexes(hexes)
    return hexes[:, HEX_FACES].reshape(-1, 4)


def boundary_quads(hexes, *, return_hex: bool = False):
    """Boundary faces of a hex mesh: the faces used by exactly one hex.

    A face is identified by its set of four vertex indices, so two hexes that
    share a face with different winding still make it interior.  Faces used by
    three or more hexes (non-manifold input) are not boundary.

    Parameters
    ----------
    hexes : (H, 8) int
        VTK hexahedron connectivity.
    return_hex : bool, optional
        Also return, for each boundary quad, the index of the hex it belongs to.

    Returns
    -------
    quads : (Q, 4) int64
        Boundary quads, each oriented outward from its hex (outward from the
        mesh when the hexes are positively oriented), in order of their hex.
    hex_ids : (Q,) int64
        Only when ``return_hex``; the owning hex of each quad.
    """
    hexes = _as_hexes(hexes)
    faces = all_faces(hexes)
    if len(faces) == 0:
        quads = np.zeros((0, 4), dtype=np.int64)
        return (quads, np.zeros(0, dtype=np.int64)) if return_hex else quads
    key = np.sort(faces, axis=1)
    # equal faces side by side (a lexicographic sort: ~3x np.unique(axis=0) on big meshes)
    order = np.lexsort(key.T[::-1])
    ks = key[order]
    group = np.cumsum(np.r_[True, (ks[1:] != ks[:-1]).any(axis=1)]) - 1
    once = np.empty(len(faces), dtype=bool)
    once[order] = np.bincount(group)[group] == 1
    quads = faces[once]
    if return_hex:
        return quads, np.nonzero(once)[0] // 6
    return quads


def boundary_vertex_mask(hexes, n_points: int | None = None) -> np.ndarray:
    """Which points lie on the boundary of the hex mesh.

    Parameters
    ----------
    hexes : (H, 8) int
        VTK hexahedron connectivity.
    n_points : int, optional
        Number of points ``P``; defaults to ``hexes.max() + 1``.

    Returns
    -------
    mask : (P,) bool
        True for vertices of :func:`boundary_quads`.
    """
    hexes = _as_hexes(hexes)
    if n_points is None:
        n_points = int(hexes.max()) + 1 if hexes.size else 0
    mask = np.zeros(n_points, dtype=bool)
    mask[boundary_quads(hexes).ravel()] = True
    return mask


# 2-point Gauss-Legendre on [0, 1]: det J of a trilinear map has degree <= 2 in
# each parametric variable, so the 2x2x2 rule integrates it exactly.
_G = np.array([0.5 - 0.5 / np.sqrt(3.0), 0.5 + 0.5 / np.sqrt(3.0)])
# parametric coordinates of the 8 corners in VTK order
_CORNER_UVW = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64
)


def _shape_gradients(uvw: np.ndarray) -> np.ndarray:
    """Gradients of the 8 trilinear shape functions at points ``uvw`` (K, 3) -> (K, 8, 3)."""
    c = _CORNER_UVW[None, :, :]  # (1, 8, 3)
    t = uvw[:, None, :]  # (K, 1, 3)
    # 1-D factors: (1 - t) for corner coordinate 0, t for 1; derivative -1 / +1
    f = np.where(c == 1, t, 1.0 - t)  # (K, 8, 3)
    df = np.where(c == 1, 1.0, -1.0) * np.ones_like(f)
    g = np.empty_like(f)
    g[..., 0] = df[..., 0] * f[..., 1] * f[..., 2]
    g[..., 1] = f[..., 0] * df[..., 1] * f[..., 2]
    g[..., 2] = f[..., 0] * f[..., 1] * df[..., 2]
    return g


_GAUSS_UVW = np.array([[a, b, c] for a in _G for b in _G for c in _G])
_GAUSS_GRAD = _shape_gradients(_GAUSS_UVW)  # (8, 8, 3)


def hex_volumes(points, hexes, *, chunk: int = 200_000) -> np.ndarray:
    """Exact signed volume of each hex (trilinear map), by 2x2x2 Gauss quadrature.

    Parameters
    ----------
    points : (P, 3) float
    hexes : (H, 8) int
        VTK hexahedron connectivity.
    chunk : int, optional
        Hexes processed at a time (bounds memory).

    Returns
    -------
    volumes : (H,) float64
        Positive for a positively oriented hex (VTK order), negative when inverted.
        Exact for the trilinear map, so a unit cube gives 1.
    """
    points = np.asarray(points, dtype=np.float64)
    hexes = _as_hexes(hexes)
    out = np.empty(len(hexes), dtype=np.float64)
    for s in range(0, len(hexes), chunk):
        X = points[hexes[s : s + chunk]]  # (h, 8, 3)
        # J[h, q, i, j] = d x_i / d u_j at Gauss point q
        J = np.einsum("hki,qkj->hqij", X, _GAUSS_GRAD)
        out[s : s + chunk] = np.linalg.det(J).sum(axis=1) / 8.0
    return out


def quads_to_triangles(quads) -> np.ndarray:
    """Split each quad (a, b, c, d) into triangles (a, b, c) and (a, c, d).

    Parameters
    ----------
    quads : (Q, 4) int

    Returns
    -------
    triangles : (2*Q, 3) int64
        Same orientation as the quads; triangles ``2q`` and ``2q+1`` come from quad ``q``.
    """
    quads = np.asarray(quads, dtype=np.int64).reshape(-1, 4)
    return np.stack([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]], axis=1).reshape(-1, 3)


def enclosed_volume(points, triangles) -> float:
    """Signed volume enclosed by a closed triangle surface (divergence theorem).

    Parameters
    ----------
    points : (P, 3) float
    triangles : (T, 3) int

    Returns
    -------
    volume : float
        Positive when the triangles are oriented outward.
    """
    points = np.asarray(points, dtype=np.float64)
    v = points[np.asarray(triangles, dtype=np.int64)]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


__all__ = [
    "HEX_FACES",
    "HEX_EDGES",
    "all_faces",
    "boundary_quads",
    "boundary_vertex_mask",
    "hex_volumes",
    "quads_to_triangles",
    "enclosed_volume",
]


# --------------------------------------------------------------------------- partition


def element_size(poly, *, target_size: float | None = None, target_hexes: int | None = None) -> float:
    """Edge length for :func:`partition`: ``target_size`` as given, or the cube root of the
    polycube volume over ``target_hexes``; default 4% of the polycube's bounding-box diagonal."""
    if target_size is not None and target_hexes is not None:
        raise ValueError("give target_size or target_hexes, not both")
    xs, ys, zs = poly.xs, poly.ys, poly.zs
    if target_hexes is not None:
        if target_hexes < 1:
            raise ValueError(f"target_hexes must be >= 1; got {target_hexes}")
        cell = np.multiply.outer(np.multiply.outer(np.diff(xs), np.diff(ys)), np.diff(zs))
        volume = float(cell[np.asarray(poly.occupancy, bool)].sum())
        return (volume / target_hexes) ** (1.0 / 3.0)
    if target_size is None:
        target_size = 0.04 * float(np.linalg.norm([xs[-1] - xs[0], ys[-1] - ys[0], zs[-1] - zs[0]]))
    if not target_size > 0:
        raise ValueError(f"target_size must be positive; got {target_size}")
    return float(target_size)


def partition(poly, *, target_size: float | None = None, target_hexes: int | None = None) -> HexMesh:
    """Regular partition of a polycube into conforming hexes, in the polycube domain.

    Every grid interval of length ``L`` is split into ``max(1, round(L / h))`` equal pieces
    (``h`` from :func:`element_size`); each fine cell inside an occupied polycube cell
    becomes one hex.  Nodes are shared, so the mesh is conforming.

    Parameters
    ----------
    poly : polycubenet.data.Polycube
    target_size : float or None, element edge length (same units as the grid)
    target_hexes : int or None, approximate hex count instead of a size

    Returns
    -------
    HexMesh
        ``points (P, 3)`` polycube-domain positions, ``hexes (H, 8)`` in VTK order with
        positive volume, ``boundary (P,)``; ``meta`` has ``h``, the fine grid sizes and
        ``pieces`` (fine intervals per coarse interval, per axis).
    """
    h = element_size(poly, target_size=target_size, target_hexes=target_hexes)
    occ = np.asarray(poly.occupancy, dtype=bool)
    fine, counts = [], []
    for g in (poly.xs, poly.ys, poly.zs):
        g = np.asarray(g, dtype=np.float64)
        n = np.maximum(1, np.rint(np.diff(g) / h)).astype(np.int64)
        t = [np.linspace(g[i], g[i + 1], n[i] + 1)[:-1] for i in range(len(n))]
        fine.append(np.concatenate(t + [g[-1:]]))
        counts.append(n)
    # occupancy of the fine cells: repeat each coarse cell along each axis by its piece count
    focc = occ
    for a in range(3):
        focc = np.repeat(focc, counts[a], axis=a)
    cells = np.argwhere(focc)  # (H, 3) fine-cell indices
    corner = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    node_ijk = cells[:, None, :] + corner[None]  # (H, 8, 3)
    shape = np.array([len(f) for f in fine])
    flat = np.ravel_multi_index(node_ijk.reshape(-1, 3).T, shape)
    used, inverse = np.unique(flat, return_inverse=True)
    hexes = inverse.reshape(-1, 8).astype(np.int64)
    ijk = np.stack(np.unravel_index(used, shape), axis=1)
    points = np.stack([fine[a][ijk[:, a]] for a in range(3)], axis=1)
    return HexMesh(
        points=points,
        hexes=hexes,
        boundary=boundary_vertex_mask(hexes, len(points)),
        meta={"h": float(h), "fine_shape": shape.tolist(), "pieces": [c.tolist() for c in counts]},
    )
