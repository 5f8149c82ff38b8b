"""Explicit polycubes: validity, genus, boundary surface, minimal grid.

A polycube is a rectilinear grid (plane coordinates ``xs, ys, zs``, strictly
increasing) and a boolean occupancy of its cells (:class:`polycubenet.data.Polycube`).
Shared by the synthetic-data generator (:mod:`polycubenet.synth`), structure
extraction (:mod:`polycubenet.structure`) and hex partitioning.

* **valid** -- no two occupied (or two empty) cells touch only along an edge or only
  at a vertex (checked per lattice vertex with a 256-entry table: the boundary is a
  disk around a vertex iff the occupied and the empty cells among its 8 are both
  face-connected inside the 2x2x2 block, :func:`nonmanifold_vertices`); one
  face-connected solid; every empty component reaches the outside (no enclosed
  cavity: the boundary would be several surfaces).
* **genus**, computed two independent ways: :func:`solid_genus` from the cubical cell
  complex (``1 - chi`` over the closed cells), :func:`surface_genus` from the
  triangulated boundary (``V - E + F = 2 - 2g``).
* **surface** -- :func:`polycube_surface`: boundary quads between occupied and empty
  cells (optionally on a refined grid), triangulated, shared vertices, outward; every
  normal is exactly an axis.
* **minimal grid** -- :func:`compress`: crop to the solid and drop planes across which
  nothing changes; two polycubes are the same solid iff their compressed forms are equal.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .errors import PolycubeError

# --------------------------------------------------------------------------- validation

_FACE6 = ndimage.generate_binary_structure(3, 1)


def _vertex_table() -> np.ndarray:
    """Bad-vertex lookup ``(256,) bool``: bit ``dx + 2 dy + 4 dz`` is cell ``(dx, dy, dz)``.

    A configuration is bad when both the occupied and the empty cells are present and
    one of the two sets is not face-connected inside the 2x2x2 block.
    """
    cells = [(b & 1, (b >> 1) & 1, (b >> 2) & 1) for b in range(8)]
    adj = [[sum(abs(p - q) for p, q in zip(cells[a], cells[b])) == 1 for b in range(8)] for a in range(8)]

    def connected(members: list[int]) -> bool:
        if not members:
            return True
        seen, stack = {members[0]}, [members[0]]
        while stack:
            a = stack.pop()
            for b in members:
                if b not in seen and adj[a][b]:
                    seen.add(b)
                    stack.append(b)
        return len(seen) == len(members)

    table = np.zeros(256, dtype=bool)
    for code in range(256):
        occ = [b for b in range(8) if code >> b & 1]
        emp = [b for b in range(8) if not code >> b & 1]
        if occ and emp:
            table[code] = not (connected(occ) and connected(emp))
    return table


_BAD_VERTEX = _vertex_table()


def _as_occupancy(occ: np.ndarray) -> np.ndarray:
    occ = np.asarray(occ)
    if occ.ndim != 3:
        raise ValueError(f"occupancy must be a 3-d array; got shape {occ.shape}")
    return occ.astype(bool, copy=False)


def nonmanifold_vertices(occ: np.ndarray) -> np.ndarray:
    """Lattice vertices around which the boundary is not a disk.

    Parameters
    ----------
    occ : (nx, ny, nz) bool

    Returns
    -------
    (K, 3) int64, vertex indices in ``[0, n]`` per axis (vertex ``(i, j, k)`` is the
    corner shared by cells ``(i-1..i, j-1..j, k-1..k)``); empty when manifold.
    """
    occ = _as_occupancy(occ)
    P = np.pad(occ, 1).astype(np.uint8)
    code = np.zeros(tuple(s - 1 for s in P.shape), dtype=np.uint8)
    for b in range(8):
        dx, dy, dz = b & 1, (b >> 1) & 1, (b >> 2) & 1
        code |= P[dx : dx + code.shape[0], dy : dy + code.shape[1], dz : dz + code.shape[2]] << b
    return np.argwhere(_BAD_VERTEX[code])


def edge_contacts(occ: np.ndarray) -> np.ndarray:
    """Lattice edges where two cells (occupied or empty) meet only along the edge.

    Parameters
    ----------
    occ : (nx, ny, nz) bool

    Returns
    -------
    (K, 4) int64 rows ``(axis, i, j, k)``: the edge along ``axis`` starting at lattice
    vertex ``(i, j, k)`` whose 4 surrounding cells form a diagonal 2x2 pattern.
    """
    occ = _as_occupancy(occ)
    P = np.pad(occ, 1)
    out = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        Q = np.moveaxis(P, (axis, b, c), (0, 1, 2))
        a00, a10 = Q[:, :-1, :-1], Q[:, 1:, :-1]
        a01, a11 = Q[:, :-1, 1:], Q[:, 1:, 1:]
        diag = (a00 == a11) & (a10 == a01) & (a00 != a10)
        idx = np.argwhere(diag[1:-1])  # cells along the edge axis inside the grid
        if len(idx):
            verts = np.zeros((len(idx), 3), dtype=np.int64)
            verts[:, axis] = idx[:, 0]
            verts[:, b] = idx[:, 1]
            verts[:, c] = idx[:, 2]
            out.append(np.column_stack([np.full(len(idx), axis), verts]))
    return np.concatenate(out) if out else np.zeros((0, 4), dtype=np.int64)


def cell_contacts(padded: np.ndarray, cell) -> int:
    """How many of the 12 edges of ``cell`` are edge-only contacts (:func:`edge_contacts`) plus how many of
    its 8 corners are non-manifold vertices (:func:`nonmanifold_vertices`); ``padded`` is the occupancy
    with one empty layer around it (``np.pad(occ, 1)``).  Flipping one cell changes only these, so the
    grid's count ``len(edge_contacts) + len(nonmanifold_vertices)`` can be kept up to date flip by flip."""
    x, y, z = (int(i) for i in cell)
    W = padded[x : x + 3, y : y + 3, z : z + 3].tolist()  # the cell and its 26 neighbours (plain Python: 27 cells)
    n = 0
    for ox in (0, 1):
        for oy in (0, 1):
            for oz in (0, 1):
                code = 0
                for dx in (0, 1):
                    for dy in (0, 1):
                        for dz in (0, 1):
                            if W[ox + dx][oy + dy][oz + dz]:
                                code |= 1 << (dx + 2 * dy + 4 * dz)
                n += bool(_BAD_VERTEX[code])
    for ob in (0, 1):  # the 12 edges: a 2x2 diagonal pattern in the layer through the cell across each axis
        for oc in (0, 1):
            for q00, q10, q01, q11 in (
                    (W[1][ob][oc], W[1][ob + 1][oc], W[1][ob][oc + 1], W[1][ob + 1][oc + 1]),  # along x
                    (W[oc][1][ob], W[oc][1][ob + 1], W[oc + 1][1][ob], W[oc + 1][1][ob + 1]),  # along y
                    (W[ob][oc][1], W[ob + 1][oc][1], W[ob][oc + 1][1], W[ob + 1][oc + 1][1])):  # along z
                n += q00 == q11 and q10 == q01 and q00 != q10
    return n


def one_solid_without_cavity(occ: np.ndarray) -> bool:
    """The last checks of :func:`check_occupancy`: not empty, one face-connected solid, no enclosed cavity."""
    occ = _as_occupancy(occ)
    return bool(occ.any()) and _solid_reason(occ) is None


def edge_cells(axis: int, i: int, j: int, k: int) -> list[tuple[int, int, int]]:
    """The 4 cells around the lattice edge along ``axis`` that starts at vertex ``(i, j, k)`` (a row of
    :func:`edge_contacts`); some may lie outside the grid."""
    b, c = (axis + 1) % 3, (axis + 2) % 3
    v = (int(i), int(j), int(k))
    cells = []
    for db in (-1, 0):
        for dc in (-1, 0):
            cell = [0, 0, 0]
            cell[axis], cell[b], cell[c] = v[axis], v[b] + db, v[c] + dc
            cells.append(tuple(cell))
    return cells


def check_occupancy(occ: np.ndarray) -> str | None:
    """Why ``occ`` is not a valid polycube, or None when it is.

    Checks, in order: non-empty, edge-only contacts, vertex-only contacts, one
    face-connected solid, no enclosed cavity.

    Parameters
    ----------
    occ : (nx, ny, nz) bool

    Returns
    -------
    str or None
    """
    occ = _as_occupancy(occ)
    if not occ.any():
        return "empty occupancy"
    e = edge_contacts(occ)
    if len(e):
        return f"non-manifold: {len(e)} edge-only contact(s), first along axis {int(e[0, 0])} at vertex {tuple(int(i) for i in e[0, 1:])}"
    v = nonmanifold_vertices(occ)
    if len(v):
        return f"non-manifold: {len(v)} vertex-only contact(s), first at vertex {tuple(int(i) for i in v[0])}"
    return _solid_reason(occ)


def _solid_reason(occ: np.ndarray) -> str | None:
    """Why the non-empty ``occ`` is not one face-connected solid without an enclosed cavity, or None."""
    _, n_solid = ndimage.label(occ, structure=_FACE6)
    if n_solid != 1:
        return f"disconnected: {n_solid} solid components"
    _, n_empty = ndimage.label(~np.pad(occ, 1), structure=_FACE6)
    if n_empty != 1:
        return f"enclosed cavity: {n_empty - 1} void(s) do not reach the outside"
    return None


def validate_occupancy(occ: np.ndarray) -> None:
    """Raise :class:`~polycubenet.errors.PolycubeError` when ``occ`` is not a valid polycube."""
    reason = check_occupancy(occ)
    if reason is not None:
        raise PolycubeError(reason)


def solid_genus(occ: np.ndarray) -> int:
    """Genus of a valid polycube from the Euler characteristic of its cubical complex.

    Counts the closed cells of the solid -- lattice vertices, edges, square faces and
    cubes that belong to at least one occupied cell -- and returns ``1 - chi``
    (valid because the solid is connected and has no cavities, so ``b0 = 1, b2 = 0``).
    Independent of :func:`polycube_surface`.

    Parameters
    ----------
    occ : (nx, ny, nz) bool

    Returns
    -------
    int
    """
    occ = _as_occupancy(occ)
    P = np.pad(occ, 1)
    n = occ.shape

    def any_of(shifts_axes: tuple[int, ...]) -> int:
        # elements indexed like vertices along the axes in shifts_axes, like cells otherwise
        shape = tuple(n[a] + 1 if a in shifts_axes else n[a] for a in range(3))
        acc = np.zeros(shape, dtype=bool)
        for offs in itertools.product(*[(0, 1) if a in shifts_axes else (1,) for a in range(3)]):
            sl = tuple(slice(o, o + shape[a]) for a, o in enumerate(offs))
            acc |= P[sl]
        return int(acc.sum())

    n_vertices = any_of((0, 1, 2))
    n_edges = any_of((1, 2)) + any_of((0, 2)) + any_of((0, 1))
    n_faces = any_of((0,)) + any_of((1,)) + any_of((2,))
    n_cubes = int(occ.sum())
    chi = n_vertices - n_edges + n_faces - n_cubes
    return 1 - chi


# --------------------------------------------------------------------------- surface


def refine_grid(coords: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Subdivide each interval of ``coords`` into ``ceil(length / h)`` equal pieces.

    Parameters
    ----------
    coords : (n+1,) float64, strictly increasing
    h : float, target spacing

    Returns
    -------
    fine : (m+1,) float64, contains every value of ``coords`` exactly
    counts : (n,) int64, pieces per original interval
    """
    coords = np.asarray(coords, dtype=np.float64)
    lengths = np.diff(coords)
    counts = np.maximum(1, np.ceil(lengths / h - 1e-9)).astype(np.int64)
    parts = [coords[i] + lengths[i] * (np.arange(counts[i]) / counts[i]) for i in range(len(lengths))]
    fine = np.concatenate(parts + [coords[-1:]])
    return fine, counts


def polycube_quads(
    xs: np.ndarray,
    ys: np.ndarray,
    zs: np.ndarray,
    occ: np.ndarray,
    h: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Boundary quads between occupied and empty cells.

    Parameters
    ----------
    xs, ys, zs : (nx+1,), (ny+1,), (nz+1,) float64, strictly increasing
    occ : (nx, ny, nz) bool, a valid polycube (:func:`check_occupancy`)
    h : float or None, when given every grid interval is split into pieces no longer
        than ``h`` first (a refined but geometrically identical surface)

    Returns
    -------
    V : (nv, 3) float64, grid nodes on the boundary (sorted by node index)
    Q : (nq, 4) int64, quads counter-clockwise seen from outside (outward normal)
    """
    occ = _as_occupancy(occ)
    grids = [np.asarray(g, dtype=np.float64) for g in (xs, ys, zs)]
    for a, g in enumerate(grids):
        if g.ndim != 1 or len(g) != occ.shape[a] + 1:
            raise ValueError(f"grid axis {a} has {len(g)} planes for {occ.shape[a]} cells")
        if np.any(np.diff(g) <= 0):
            raise ValueError(f"grid axis {a} is not strictly increasing")
    if h is not None:
        refined = [refine_grid(g, h) for g in grids]
        grids = [r[0] for r in refined]
        for a, (_, counts) in enumerate(refined):
            occ = np.repeat(occ, counts, axis=a)
    n = occ.shape
    P = np.pad(occ, 1)
    node_shape = (n[0] + 1, n[1] + 1, n[2] + 1)
    quads = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        inner = [slice(1, -1)] * 3
        lo, hi = list(inner), list(inner)
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        A, B = P[tuple(lo)], P[tuple(hi)]  # cells below / above each plane of this axis
        for sign, mask in ((+1, A & ~B), (-1, ~A & B)):
            idx = np.argwhere(mask)  # (plane, cell, cell) in x, y, z order
            if not len(idx):
                continue
            eb = np.zeros(3, dtype=np.int64)
            ec = np.zeros(3, dtype=np.int64)
            eb[b], ec[c] = 1, 1
            corners = np.stack([idx, idx + eb, idx + eb + ec, idx + ec], axis=1)  # CCW seen from +axis
            if sign < 0:
                corners = corners[:, ::-1]
            quads.append(corners)
    if not quads:
        raise ValueError("empty occupancy has no surface")
    Qn = np.concatenate(quads)  # (nq, 4, 3) node indices
    lin = np.ravel_multi_index((Qn[..., 0], Qn[..., 1], Qn[..., 2]), node_shape)
    used, inv = np.unique(lin, return_inverse=True)
    Q = inv.reshape(lin.shape).astype(np.int64)
    i, j, k = np.unravel_index(used, node_shape)
    V = np.column_stack([grids[0][i], grids[1][j], grids[2][k]])
    return V, Q


def _triangle_quality(V: np.ndarray, T: np.ndarray) -> np.ndarray:
    """``4 sqrt(3) area / sum(edge^2)`` per triangle (1 equilateral, 0 degenerate)."""
    a, b, c = V[T[..., 0]], V[T[..., 1]], V[T[..., 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    ssq = ((b - a) ** 2).sum(-1) + ((c - b) ** 2).sum(-1) + ((a - c) ** 2).sum(-1)
    return 2.0 * np.sqrt(3.0) * area2 / np.maximum(ssq, 1e-300)


def triangulate_quads(Q: np.ndarray, V: np.ndarray | None = None) -> np.ndarray:
    """Split each quad into two triangles (orientation kept).

    Parameters
    ----------
    Q : (nq, 4) int64
    V : (nv, 3) float64 or None; when given, each quad uses the diagonal whose worse
        triangle has the better shape quality on these vertex positions (e.g. the
        deformed shape), otherwise always the diagonal 0-2

    Returns
    -------
    F : (2 nq, 3) int64, the two triangles of quad ``q`` are rows ``2q, 2q + 1``
    """
    Q = np.asarray(Q, dtype=np.int64)
    A = np.stack([Q[:, [0, 1, 2]], Q[:, [0, 2, 3]]], axis=1)
    if V is None:
        return A.reshape(-1, 3)
    B = np.stack([Q[:, [0, 1, 3]], Q[:, [1, 2, 3]]], axis=1)
    qa = _triangle_quality(V, A).min(axis=1)
    qb = _triangle_quality(V, B).min(axis=1)
    return np.where((qb > qa)[:, None, None], B, A).reshape(-1, 3)


def polycube_surface(
    xs: np.ndarray,
    ys: np.ndarray,
    zs: np.ndarray,
    occ: np.ndarray,
    h: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangulated boundary between occupied and empty cells.

    Parameters
    ----------
    xs, ys, zs : (nx+1,), (ny+1,), (nz+1,) float64, strictly increasing
    occ : (nx, ny, nz) bool, a valid polycube (:func:`check_occupancy`)
    h : float or None, refine the grid to spacing ``<= h`` first (see :func:`polycube_quads`)

    Returns
    -------
    V : (nv, 3) float64, grid nodes on the boundary
    F : (nf, 3) int64, outward oriented; two triangles per boundary quad; every
        triangle lies in a grid plane, so its normal is exactly an axis
    """
    V, Q = polycube_quads(xs, ys, zs, occ, h)
    return V, triangulate_quads(Q)


def _unique_edges(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undirected edges ``(E, 2)`` (sorted pairs) of faces ``F`` and their face counts ``(E,)``."""
    edges = np.sort(F[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    base = int(F.max()) + 1 if len(F) else 1
    keys, counts = np.unique(edges[:, 0] * base + edges[:, 1], return_counts=True)
    return np.column_stack([keys // base, keys % base]), counts


def euler_characteristic(F: np.ndarray, n_vertices: int | None = None) -> int:
    """``V - E + F`` of a triangle mesh (``V`` = vertices used by faces unless given).

    Parameters
    ----------
    F : (nf, 3) int64
    n_vertices : int or None

    Returns
    -------
    int
    """
    F = np.asarray(F, dtype=np.int64)
    n_edges = len(_unique_edges(F)[0])
    nv = len(np.unique(F)) if n_vertices is None else int(n_vertices)
    return nv - n_edges + len(F)


def surface_genus(F: np.ndarray) -> int:
    """Genus of a closed, connected, orientable triangle surface from ``V - E + F = 2 - 2g``.

    Parameters
    ----------
    F : (nf, 3) int64

    Returns
    -------
    int

    Raises
    ------
    PolycubeError
        When the surface is open, non-manifold along an edge, or has several components.
    """
    F = np.asarray(F, dtype=np.int64)
    uniq, counts = _unique_edges(F)
    if np.any(counts != 2):
        raise PolycubeError(f"surface not closed 2-manifold: {int((counts != 2).sum())} bad edge(s)")
    used = np.unique(F)
    remap = np.searchsorted(used, uniq)
    g = coo_matrix((np.ones(len(uniq)), (remap[:, 0], remap[:, 1])), shape=(len(used), len(used)))
    n_comp, _ = connected_components(g, directed=False)
    if n_comp != 1:
        raise PolycubeError(f"surface has {n_comp} components")
    chi = len(used) - len(uniq) + len(F)
    if chi % 2:
        raise PolycubeError(f"odd Euler characteristic {chi}")
    return (2 - chi) // 2


def transform_grid(
    xs: np.ndarray,
    ys: np.ndarray,
    zs: np.ndarray,
    occ: np.ndarray,
    center: np.ndarray,
    scale: float,
    perm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The grid of the polycube mapped by ``p -> ((p - center) * scale) @ perm.T``.

    Parameters
    ----------
    xs, ys, zs : plane coordinates
    occ : (nx, ny, nz) bool
    center : (3,) float64
    scale : float, > 0
    perm : (3, 3) signed permutation matrix (entries 0, +-1)

    Returns
    -------
    xs, ys, zs, occ of the mapped polycube (axes permuted, flipped where the sign is -1)
    """
    perm = np.asarray(perm, dtype=np.float64)
    if not (np.all(np.isin(perm, (-1.0, 0.0, 1.0))) and np.all(np.abs(perm).sum(0) == 1) and np.all(np.abs(perm).sum(1) == 1)):
        raise ValueError("perm must be a signed permutation matrix")
    grids = [np.asarray(g, dtype=np.float64) for g in (xs, ys, zs)]
    src = np.argmax(np.abs(perm), axis=1)  # new axis i comes from old axis src[i]
    signs = perm[np.arange(3), src]
    out_grids = []
    new_occ = np.transpose(_as_occupancy(occ), src)
    for i in range(3):
        g = signs[i] * ((grids[src[i]] - center[src[i]]) * scale)
        if signs[i] < 0:
            g = g[::-1]
            new_occ = np.flip(new_occ, axis=i)
        out_grids.append(g)
    return out_grids[0], out_grids[1], out_grids[2], np.ascontiguousarray(new_occ)


def convex_edges(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, occ: np.ndarray) -> list[dict]:
    """Grid lines that are a convex edge of the solid wherever the solid reaches them.

    A line along ``axis`` qualifies when, in every slab along the axis, its four
    surrounding cells are either all empty or exactly the same single cell is occupied
    (a convex 90 degree edge, possibly ending on end faces).  Such an edge can be
    rounded by a map local to its four cells (:class:`~polycubenet.synth.deform.RoundEdge`).

    Parameters
    ----------
    xs, ys, zs : plane coordinates
    occ : (nx, ny, nz) bool

    Returns
    -------
    list of dict with ``axis`` (int), ``corner`` ((2,) coordinates on the two other axes
    in cyclic order), ``signs`` ((2,) outward directions), ``room`` (float, the
    smallest width of the four cells across the edge) and ``rooms`` (that width on each of
    the two other axes)
    """
    occ = _as_occupancy(occ)
    grids = [np.asarray(g, dtype=np.float64) for g in (xs, ys, zs)]
    P = np.pad(occ, 1)
    out = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        Q = np.moveaxis(P, (axis, b, c), (0, 1, 2))[1:-1]  # (n_axis, nb + 2, nc + 2)
        quads = [Q[:, :-1, :-1], Q[:, 1:, :-1], Q[:, :-1, 1:], Q[:, 1:, 1:]]  # lower-left, right, upper...
        count = sum(q.astype(np.int64) for q in quads)  # (n_axis, nb + 1, nc + 1)
        ok = np.all(count <= 1, axis=0) & np.any(count == 1, axis=0)
        for qi, q in enumerate(quads):
            other = [quads[k] for k in range(4) if k != qi]
            single = ok & np.all(~q | (count == 1), axis=0) & np.any(q, axis=0)
            # the occupied cell must be this same quadrant in every non-empty slab
            single &= ~np.any(np.stack([o.any(axis=0) for o in other]), axis=0)
            for j, k in np.argwhere(single):
                db, dc = qi & 1, qi >> 1  # occupied cell is on the + side of the line when 1
                gb, gc = grids[b], grids[c]
                rooms = []
                for g, idx in ((gb, j), (gc, k)):
                    rooms.append(min(g[cell + 1] - g[cell] for cell in (idx - 1, idx) if 0 <= cell < len(g) - 1))
                out.append({
                    "axis": axis,
                    "corner": np.array([gb[j], gc[k]]),
                    "signs": np.array([-1.0 if db else 1.0, -1.0 if dc else 1.0]),
                    "room": float(min(rooms)),
                    "rooms": (float(rooms[0]), float(rooms[1])),
                })
    return out


def compress(coords: list[np.ndarray], occ: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Crop to the occupied bounding box and merge adjacent identical slabs.

    Parameters
    ----------
    coords : three plane-coordinate arrays ``(n_a + 1,)``
    occ : (nx, ny, nz) bool

    Returns
    -------
    coords, occ of the minimal grid describing the same solid
    """
    occ = _as_occupancy(occ)
    if not occ.any():
        raise PolycubeError("the polycube has no occupied cell")
    coords = [np.asarray(c, dtype=np.float64) for c in coords]
    for a in range(3):
        other = tuple(x for x in range(3) if x != a)
        filled = np.flatnonzero(occ.any(axis=other))
        lo, hi = filled[0], filled[-1] + 1
        occ = np.take(occ, np.arange(lo, hi), axis=a)
        coords[a] = coords[a][lo : hi + 1]
        slabs = np.moveaxis(occ, a, 0)
        same = np.all(slabs[1:] == slabs[:-1], axis=(1, 2))  # slab i+1 equals slab i
        keep_cells = np.concatenate([[True], ~same])
        keep_planes = np.concatenate([keep_cells, [True]])  # drop the plane between equal slabs
        occ = np.compress(keep_cells, occ, axis=a)
        coords[a] = coords[a][keep_planes]
    return coords, occ


def _matching_grids(got, truth) -> tuple[list, list] | None:
    """The minimal grids of two polycubes when their topology and occupancy agree, else ``None``."""
    ga, oa = compress([got.xs, got.ys, got.zs], got.occupancy)
    gb, ob = compress([truth.xs, truth.ys, truth.zs], truth.occupancy)
    if oa.shape != ob.shape or not bool((oa == ob).all()):
        return None
    return ga, gb


def plane_offset(got, truth) -> float | None:
    """The largest distance between corresponding planes of two polycubes of the same minimal
    grid topology and occupancy, or ``None`` when the topology or occupancy differs: it tells a
    polycube whose cells are right but whose planes are displaced from one with other cells."""
    grids = _matching_grids(got, truth)
    return None if grids is None else float(max(np.abs(a - b).max() for a, b in zip(*grids)))


def same_structure(got, truth, atol: float) -> bool:
    """Whether two polycubes (objects with ``xs, ys, zs, occupancy``) have the same structure:
    the same minimal grid topology and occupancy, with plane positions within ``atol``."""
    grids = _matching_grids(got, truth)
    return grids is not None and all(np.allclose(a, b, atol=atol) for a, b in zip(*grids))
