"""Reading parts and writing hex meshes.

``load_part`` turns a CAD or mesh file into a validated :class:`~polycubenet.data.Part`:
a closed, manifold, orientable, connected triangle surface with outward normals and a
non-zero volume.  ``write_hex`` / ``read_hex`` move a :class:`~polycubenet.data.HexMesh`
to and from the usual solver and viewer formats through meshio.

Input formats
-------------
- Mesh files, read by trimesh with ``process=False`` (or by the small readers below):
  ``.stl`` (binary and ASCII), ``.obj``, ``.ply``, ``.off``, ``.glb``.
- Volume meshes, read by meshio: ``.mesh`` (MEDIT), ``.vtu`` / ``.vtk`` (VTK), ``.msh``
  (Gmsh).  The part is the boundary of their solid cells (tetrahedra, hexahedra, wedges,
  pyramids, linear or higher order -- only the corner nodes are used): every cell face that
  no other cell shares, quads split into two triangles.  A file with no solid cells but
  triangles or quads is read as a surface.
- CAD files, read by gmsh's OpenCASCADE kernel and meshed into triangles:
  ``.step`` / ``.stp`` and ``.iges`` / ``.igs``.  OpenCASCADE converts coordinates from the
  unit the file declares to millimetres; ``units`` rescales them to another unit.  gmsh is a
  process-wide singleton, so every use here holds ``GMSH_LOCK``; it is initialised without
  signal handlers (safe in worker threads) and left alone if the caller initialised it.

Repairs and refusals
--------------------
Only *safe* repairs are made, and each is recorded as a sentence in
``part.meta["repairs"]``:

- merge coincident vertices (closer than ``tol.MERGE_REL`` × bbox diagonal) and drop
  unreferenced vertices;
- drop degenerate faces (a repeated vertex, or area below ``tol.AREA_REL`` × diagonal²)
  and exact duplicate faces (same vertices, same orientation);
- fan-triangulate polygons of OFF files (trimesh does the same for OBJ and PLY);
- orient faces consistently, then outward (an inside-out surface is flipped);
- with ``keep_largest=True``, keep the largest of several components.

Everything else raises a :class:`~polycubenet.errors.PartError` subclass whose message
starts with the file path and says what is wrong (see ``load_part``), self-intersecting
surfaces included (``SelfIntersectionError``, found by MeshLab's per-face test).

The topology checks are vectorised (sorted edge keys, ``np.unique``-style run lengths and
``scipy.sparse.csgraph.connected_components``), so a million-face surface is checked in
seconds.

``write_surface`` writes a triangle surface (STL, OBJ, PLY, OFF, GLB) atomically.

Output formats
--------------
``SUPPORTED_HEX_FORMATS``: ``.vtu``, ``.vtk`` (VTK), ``.mesh`` (Medit, opened by HexaLab),
``.inp`` (Abaqus), ``.msh`` (Gmsh 4.1), ``.bdf`` (Nastran).  All use the VTK hexahedron
node order, which is also the order of Medit, Abaqus C3D8, Gmsh and Nastran CHEXA.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import re
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from . import tol
from .atomic import atomic_path
from .data import HexMesh, Part
from .hexmesh import hex_volumes  # re-exported: volumes of the hexes read back
from .errors import (
    DegenerateVolumeError,
    EmptyMeshError,
    InvalidCoordinatesError,
    MultipleComponentsError,
    NonManifoldError,
    SelfIntersectionError,
    NotTriangularError,
    OpenBoundaryError,
    PartError,
    TooLargeError,
    UnknownFormatError,
    UnreadableFileError,
)

__all__ = [
    "SUPPORTED_PART_FORMATS",
    "SUPPORTED_HEX_FORMATS",
    "load_part",
    "part_from_arrays",
    "write_surface",
    "write_hex",
    "read_hex",
    "hex_volumes",
    "gmsh_session",
    "quiet_stdout",
    "GMSH_LOCK",
]

#: file extension -> format name, for ``load_part``
SUPPORTED_PART_FORMATS: dict[str, str] = {
    ".stl": "stl",
    ".obj": "obj",
    ".ply": "ply",
    ".off": "off",
    ".glb": "glb",
    ".step": "step",
    ".stp": "step",
    ".iges": "iges",
    ".igs": "iges",
    # volume meshes: the part is the boundary surface of their solid cells (tets, hexes, ...)
    ".mesh": "medit",
    ".vtu": "vtu",
    ".vtk": "vtk",
    ".msh": "gmsh",
}

#: the volume-mesh formats among ``SUPPORTED_PART_FORMATS`` (read through meshio)
VOLUME_FORMATS = ("medit", "vtu", "vtk", "gmsh")

#: file extension -> meshio format name, for ``write_hex`` / ``read_hex``
SUPPORTED_HEX_FORMATS: dict[str, str] = {
    ".vtu": "vtu",
    ".vtk": "vtk",
    ".mesh": "medit",
    ".inp": "abaqus",
    ".msh": "gmsh",
    ".bdf": "nastran",
}

_CAD_FORMATS = ("step", "iges")

#: length units we know: canonical name -> millimetres per unit
_MM_PER_UNIT = {
    "mm": 1.0,
    "cm": 10.0,
    "m": 1e3,
    "km": 1e6,
    "um": 1e-3,
    "in": 25.4,
    "ft": 304.8,
    "mil": 0.0254,
    "mi": 1_609_344.0,
}
_UNIT_ALIASES = {
    "millimeter": "mm",
    "millimetre": "mm",
    "centimeter": "cm",
    "centimetre": "cm",
    "meter": "m",
    "metre": "m",
    "kilometer": "km",
    "kilometre": "km",
    "micron": "um",
    "micrometer": "um",
    "micrometre": "um",
    "µm": "um",
    "inch": "in",
    "inches": "in",
    "foot": "ft",
    "feet": "ft",
    "mile": "mi",
    "miles": "mi",
}


# ---------------------------------------------------------------------------------------------
# public API: loading
# ---------------------------------------------------------------------------------------------


def load_part(
    path: str | os.PathLike,
    *,
    mesh_size: float | None = None,
    keep_largest: bool = False,
    max_faces: int = tol.MAX_FACES,
    units: str | None = None,
) -> Part:
    """Read a CAD or mesh file and return a validated, outward-oriented closed surface.

    Parameters
    ----------
    path : str or PathLike
        ``.stl .obj .ply .off .glb`` (mesh files), ``.mesh .vtu .vtk .msh`` (volume meshes,
        read as the boundary of their cells) or ``.step .stp .iges .igs`` (CAD files).
    mesh_size : float, optional
        CAD files only: target triangle edge length, in the output ``units`` (mm by
        default).  Default: ``tol.CAD_MESH_SIZE_REL`` (2%) of the bounding-box diagonal,
        refined on curved faces (16 segments per full turn).  Ignored for mesh files.
    keep_largest : bool
        With several disconnected components, keep the one with the largest volume
        (recorded in the repairs) instead of raising ``MultipleComponentsError``.
    max_faces : int
        Refuse surfaces with more triangles (``TooLargeError``).  Checked from file headers
        before parsing where the format allows (binary STL, PLY, OFF, OBJ line counts), from
        an area estimate before meshing a CAD file, and again on the final array.
    units : str, optional
        Length unit of the coordinates (``"mm"``, ``"m"``, ``"in"``, ...).  CAD files are
        *converted* to it from the unit their header declares (default: millimetres); mesh
        files carry no unit, so for them it only labels the coordinates (default None: unknown).

    Returns
    -------
    Part
        ``vertices : (V, 3) float64``, ``faces : (F, 3) int64`` (outward), and ``meta`` with
        ``path``, ``format``, ``units``, ``genus``, ``sharpest_edge_deg`` (:func:`sharpest_convex_edge_deg`),
        ``area``, ``volume``, ``repairs`` (list of sentences), ``n_vertices``, ``n_faces``, ``bbox_diagonal``; CAD files also
        ``file_units`` (the unit declared in the file, or None) and ``mesh_size``.

    Raises
    ------
    UnreadableFileError
        Missing, empty, truncated or corrupt file, or content that is not the format its
        extension says (the message guesses what it is), or a face index out of range.
    UnknownFormatError
        Extension not in ``SUPPORTED_PART_FORMATS``.
    NotTriangularError
        A face with fewer than three vertices (polygons with more are triangulated).
    InvalidCoordinatesError
        NaN or infinite coordinates.
    EmptyMeshError
        No faces (also: only degenerate faces; a CAD file with no surfaces).
    TooLargeError
        More than ``max_faces`` triangles.
    OpenBoundaryError
        Boundary edges (holes); the message gives their number.
    NonManifoldError
        Edges with more than two faces, pinched vertices, or a non-orientable surface.
    MultipleComponentsError
        Several components and ``keep_largest=False``.
    SelfIntersectionError
        Triangles that cross other triangles of the surface.
    DegenerateVolumeError
        Zero enclosed volume (a flat or collapsed surface).
    """
    path = Path(path)
    fmt = SUPPORTED_PART_FORMATS.get(path.suffix.lower())
    if not path.exists():
        raise UnreadableFileError(path, "file not found")
    if not path.is_file():
        raise UnreadableFileError(path, "not a regular file")
    if fmt is None:
        supported = " ".join(sorted(SUPPORTED_PART_FORMATS))
        raise UnknownFormatError(path, f"unknown extension {path.suffix!r}; supported: {supported}")
    unit = _canonical_unit(units)
    if path.stat().st_size == 0:
        raise UnreadableFileError(path, f"file is empty (0 bytes), expected {fmt.upper()} data")

    meta: dict = {"path": str(path), "format": fmt, "units": unit}
    repairs: list[str] = []
    if fmt in _CAD_FORMATS:
        vertices, faces, cad_meta = _read_cad(path, fmt, mesh_size=mesh_size, max_faces=max_faces, unit=unit,
                                              repairs=repairs)
        meta.update(cad_meta)
    else:
        readers = {"stl": _read_stl, "off": _read_off, "obj": _read_obj, "ply": _read_ply, "glb": _read_glb,
                   **{f: _read_volume for f in VOLUME_FORMATS}}
        try:
            vertices, faces = readers[fmt](path, max_faces, repairs)
        except (PartError, MemoryError):
            raise
        except Exception as exc:  # a parser failed: the file is not what its extension says
            raise UnreadableFileError(path, f"cannot parse as {fmt.upper()} ({_short(exc)}){_hint(path, fmt)}") from exc
    return part_from_arrays(
        vertices,
        faces,
        path=path,
        keep_largest=keep_largest,
        max_faces=max_faces,
        meta=meta,
        repairs=repairs,
        record_orientation=fmt not in _CAD_FORMATS,
    )


def part_from_arrays(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    path: str | os.PathLike | None = None,
    keep_largest: bool = False,
    max_faces: int = tol.MAX_FACES,
    meta: dict | None = None,
    repairs: list[str] | None = None,
    record_orientation: bool = True,
) -> Part:
    """Repair and validate a triangle soup into a :class:`Part` (what ``load_part`` does after reading).

    Parameters
    ----------
    vertices : (V, 3) array_like of float
    faces : (F, 3) array_like of int
    path : str or PathLike, optional
        Named in error messages and stored in ``meta["path"]``.
    keep_largest, max_faces
        As in :func:`load_part`.
    meta : dict, optional
        Extra metadata to start from (``format``, ``units``, ...).
    repairs : list of str, optional
        Repairs already made by a reader; the ones made here are appended.
    record_orientation : bool
        Record face re-orientation as a repair (False for CAD meshes, whose triangle
        orientation is an artefact of the mesher, not a defect of the file).

    Returns
    -------
    Part
        See :func:`load_part`.
    """
    where = None if path is None else str(path)
    repairs = list(repairs or [])
    meta = dict(meta or {})
    meta.setdefault("path", where)
    meta.setdefault("format", None)
    meta.setdefault("units", None)

    v = np.asarray(vertices)
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        if f.size == 0:
            raise EmptyMeshError(where, "the surface has no faces")
        raise NotTriangularError(where, f"faces must be triangles, shape (F, 3); got shape {f.shape}")
    if len(f) == 0:
        raise EmptyMeshError(where, "the surface has no faces")
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        if v.size == 0:
            raise EmptyMeshError(where, "the surface has no vertices")
        raise InvalidCoordinatesError(where, f"vertices must have shape (V, 3); got shape {v.shape}")
    if len(f) > max_faces:
        raise TooLargeError(where, f"{len(f):,} faces exceed the limit of {max_faces:,} (max_faces)")
    if not np.issubdtype(f.dtype, np.integer):
        if not np.issubdtype(f.dtype, np.floating) or not np.all(f == np.round(f)):
            raise UnreadableFileError(where, f"face indices must be integers; got dtype {f.dtype}")
    f = f.astype(np.int64)
    if f.min() < 0 or f.max() >= len(v):
        bad = int(np.count_nonzero((f < 0) | (f >= len(v))))
        raise UnreadableFileError(
            where, f"{bad} face indices are outside the {len(v)} vertices (range {f.min()}..{f.max()}): corrupt file"
        )
    try:
        v = v.astype(np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidCoordinatesError(where, f"vertex coordinates are not numbers ({_short(exc)})") from exc
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        n_nan = int(np.isnan(v).any(axis=1).sum())
        n_inf = int((~finite).sum()) - n_nan
        raise InvalidCoordinatesError(
            where, f"{n_nan + n_inf} vertices have invalid coordinates ({n_nan} with NaN, {n_inf} infinite)"
        )

    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    diag = _diagonal(v[used])
    if diag == 0.0:
        raise DegenerateVolumeError(where, "all vertices coincide (zero-size bounding box)")

    # -- safe repairs ------------------------------------------------------------------------
    v, f = _merge_vertices(v, f, tol.MERGE_REL * diag, repairs)
    f, n_degenerate = _drop_degenerate_faces(v, f, tol.AREA_REL * diag * diag, repairs)
    if len(f) == 0:
        raise EmptyMeshError(where, f"all {n_degenerate} faces are degenerate (zero area)")
    f = _drop_duplicate_faces(f, repairs)
    v, f = _drop_unreferenced(v, f, repairs)
    after = f" (after dropping {n_degenerate} degenerate faces)" if n_degenerate else ""

    # -- topology -----------------------------------------------------------------------------
    topo = _edge_topology(f)
    n_boundary, n_nonmanifold = topo["n_boundary"], topo["n_nonmanifold"]
    if n_nonmanifold:
        extra = f" and {n_boundary} boundary edges" if n_boundary else ""
        raise NonManifoldError(
            where, f"{n_nonmanifold} non-manifold edges (shared by more than two faces){extra}{after}"
        )
    if n_boundary:
        raise OpenBoundaryError(
            where, f"the surface is not closed: {n_boundary} boundary edges (holes or a missing face){after}"
        )
    n_pinched = _count_pinched_vertices(f, len(v), topo)
    if n_pinched:
        raise NonManifoldError(
            where, f"{n_pinched} non-manifold vertices (pinch points where separate sheets touch at a vertex)"
        )

    # -- orientation and components --------------------------------------------------------
    comp, flip = _orient(f, topo)
    if comp is None:
        raise NonManifoldError(
            where, "the surface is non-orientable (no consistent inside/outside, e.g. a Klein bottle)"
        )
    n_flip = int(flip.sum())
    if n_flip:
        f[flip] = f[flip][:, ::-1]
        if record_orientation:
            repairs.append(f"reoriented {n_flip} of {len(f)} faces to a consistent orientation")
    # -- self-intersections (before components: overlapping shells are crossings, not parts) --
    crossing = self_intersecting_faces(v, f)
    if len(crossing):
        tri_area = _face_areas(v, f)
        share = float(tri_area[crossing].sum() / tri_area.sum())
        c = v[f[crossing[0]]].mean(axis=0)
        where_c = f"({c[0]:.4g}, {c[1]:.4g}, {c[2]:.4g})"
        if share > tol.SELF_INTERSECTION_AREA:
            raise SelfIntersectionError(
                where,
                f"the surface intersects itself: {len(crossing)} triangles ({share:.2%} of the area) cross other "
                f"triangles, the first near {where_c}; it bounds no well-defined solid -- repair it in CAD",
            )
        # slivers crossing each other (common in scans and exports) are left as they are, and said
        repairs.append(f"left {len(crossing)} slightly self-intersecting triangles ({share:.3%} of the area, the "
                       f"first near {where_c}) as they are")

    n_comp = int(comp.max()) + 1
    center = 0.5 * (v.min(axis=0) + v.max(axis=0))
    face_vol = _face_volumes(v - center, f)
    comp_vol = np.bincount(comp, weights=face_vol, minlength=n_comp)
    if n_comp > 1:
        sizes = np.bincount(comp, minlength=n_comp)
        if not keep_largest:
            shown = ", ".join(str(s) for s in sorted(sizes.tolist(), reverse=True)[:8])
            raise MultipleComponentsError(
                where,
                f"{n_comp} disconnected components (faces per component: {shown}"
                f"{', ...' if n_comp > 8 else ''}) that do not touch; mesh each from its own file, or keep the "
                f"largest with keep_largest=True (CLI: --keep-largest)",
            )
        keep = int(np.argmax(np.abs(comp_vol)))
        mask = comp == keep
        repairs.append(
            f"kept the largest of {n_comp} components ({int(mask.sum())} faces, volume {abs(comp_vol[keep]):.6g}); "
            f"dropped {int((~mask).sum())} faces in the other {n_comp - 1}"
        )
        f, comp_vol, n_comp = f[mask], comp_vol[keep : keep + 1], 1
        v, f = _drop_unreferenced(v, f, None)
        comp = np.zeros(len(f), dtype=np.int64)
    volume = float(comp_vol.sum())
    if volume < 0:
        f = f[:, ::-1].copy()
        volume = -volume
        if record_orientation:
            repairs.append("the surface was inside-out (negative volume): flipped all faces to point outward")

    diag = _diagonal(v)
    if volume <= tol.VOLUME_REL * diag**3:
        raise DegenerateVolumeError(
            where,
            f"the enclosed volume is zero ({volume:.3g} for a bounding-box diagonal of {diag:.6g}): "
            "a flat or collapsed surface",
        )

    # -- invariants ---------------------------------------------------------------------------
    n_edges = 3 * len(f) // 2
    euler = len(v) - n_edges + len(f)
    genus = (2 - euler) // 2
    area = float(_face_areas(v, f).sum())
    meta.update(
        genus=int(genus),
        sharpest_edge_deg=sharpest_convex_edge_deg(v, f),
        area=area,
        volume=volume,
        repairs=repairs,
        n_vertices=int(len(v)),
        n_faces=int(len(f)),
        bbox_diagonal=float(diag),
    )
    return Part(
        vertices=np.ascontiguousarray(v, dtype=np.float64), faces=np.ascontiguousarray(f, dtype=np.int64), meta=meta
    )


def sharpest_convex_edge_deg(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The sharpest convex edge of a closed, outward-oriented triangle surface: the largest angle (degrees)
    between the normals of two triangles that meet on an edge where the surface bends outward; 90 on a box,
    near 180 at a knife edge (where a slanted cut crosses a hole, or a hole grazes an edge), 0 with no convex
    edge.  A polycube maps such an edge onto a right angle or a flat face, so past about 130 degrees (faces
    meeting under 50 degrees) a polycube hex mesh is far harder to keep within its bars."""
    from .classical import _dihedral, edge_topology
    from .frame import face_normals_areas

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    edges, pair = edge_topology(f)
    n, _ = face_normals_areas(v, f)
    # convex: the second face's third vertex lies behind the first face's plane
    third = f[pair[:, 1]].sum(axis=1) - edges.sum(axis=1)
    convex = np.einsum("ij,ij->i", n[pair[:, 0]], v[third] - v[edges[:, 0]]) < 0
    return float(_dihedral(n, pair[convex]).max()) if convex.any() else 0.0


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Indices of the triangles that cross another triangle of the surface (MeshLab's per-face
    self-intersection test, through pymeshlab; triangles that only share an edge or a vertex do
    not count).  About 0.4 s for 160k triangles."""
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return np.flatnonzero(ms.current_mesh().face_selection_array())


def write_surface(vertices: np.ndarray, faces: np.ndarray, path: str | os.PathLike) -> Path:
    """Write a triangle surface atomically; the format follows the extension.

    Parameters
    ----------
    vertices : (V, 3) float
    faces : (F, 3) int
    path : str or PathLike
        ``.stl`` (binary), ``.obj``, ``.ply`` (binary), ``.off`` or ``.glb``.

    Returns
    -------
    Path
        ``path``.
    """
    import trimesh

    path = Path(path)
    fmt = SUPPORTED_PART_FORMATS.get(path.suffix.lower())
    if fmt is None or fmt in _CAD_FORMATS or fmt in VOLUME_FORMATS:
        raise ValueError(f"{path}: cannot write a surface as {path.suffix!r}; use .stl .obj .ply .off or .glb")
    mesh = trimesh.Trimesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), process=False)
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=fmt)
    return path


# ---------------------------------------------------------------------------------------------
# public API: hex meshes
# ---------------------------------------------------------------------------------------------


def write_hex(mesh: HexMesh, path: str | os.PathLike, *, cell_data: dict[str, np.ndarray] | None = None) -> Path:
    """Write a hex mesh; the format follows the extension (``SUPPORTED_HEX_FORMATS``).

    The file is written atomically (temporary file + rename) with full float precision
    where the format allows (``.vtu``/``.vtk``/``.msh``: binary float64; ``.inp``/``.mesh``:
    17 significant digits; ``.bdf``: 16-character large-field ``GRID*`` cards, 11-12
    significant digits, written by this module because meshio's writer fails on negative
    coordinates).

    Parameters
    ----------
    mesh : HexMesh
        ``points : (P, 3) float64``, ``hexes : (H, 8) int64`` in VTK order.
    path : str or PathLike
        Target file; its extension picks the format.
    cell_data : dict of str to (H,) or (H, k) array, optional
        Per-hex fields (e.g. the scaled Jacobian).  Stored in ``.vtu``, ``.vtk`` and ``.msh``;
        the other formats cannot hold them (a warning says so).  ``mesh.boundary`` is stored as
        the point field ``boundary`` in ``.vtu`` and ``.vtk``.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    ValueError
        Unknown extension, or ``cell_data`` of the wrong length.
    """
    import meshio

    path = Path(path)
    fmt = _hex_format(path)
    n_hex = len(mesh.hexes)
    cells = [meshio.CellBlock("hexahedron", np.ascontiguousarray(mesh.hexes, dtype=np.int64))]
    cdata: dict[str, list[np.ndarray]] = {}
    for name, values in (cell_data or {}).items():
        values = np.asarray(values)
        if len(values) != n_hex:
            raise ValueError(f"cell_data[{name!r}] has {len(values)} values for {n_hex} hexes")
        cdata[name] = [values]
    pdata: dict[str, np.ndarray] = {}
    kwargs: dict = {}
    if cdata and fmt not in ("vtu", "vtk", "gmsh"):
        warnings.warn(f"{path.suffix} cannot store cell data; {sorted(cdata)} not written to {path}", stacklevel=2)
        cdata = {}
    if fmt in ("vtu", "vtk") and mesh.boundary is not None:
        pdata["boundary"] = np.asarray(mesh.boundary).astype(np.uint8)
    if fmt == "gmsh":
        # tags that Gmsh expects on every element; without them meshio warns and invents zeros
        cdata["gmsh:physical"] = [np.ones(n_hex, dtype=np.int32)]
        cdata["gmsh:geometrical"] = [np.ones(n_hex, dtype=np.int32)]
    elif fmt in ("medit", "abaqus"):
        kwargs = {"float_fmt": ".17g"} if fmt == "medit" else {"float_fmt": ".17e"}
    m = meshio.Mesh(np.ascontiguousarray(mesh.points, dtype=np.float64), cells, point_data=pdata, cell_data=cdata)
    with atomic_path(path) as tmp:
        if fmt == "nastran":
            _write_nastran(tmp, m.points, mesh.hexes)
        else:
            meshio.write(tmp, m, file_format=fmt, **kwargs)
    return path


def _nastran_float(x: float) -> str:
    """A 16-character Nastran real with as many digits as fit (11-12 significant)."""
    for digits in range(11, 0, -1):
        mant, _, exp = f"{x:.{digits}E}".partition("E")
        text = f"{mant}E{int(exp):+d}"
        if len(text) <= 16:
            return text
    raise ValueError(f"cannot write {x!r} in 16 characters")


def _write_nastran(path: Path, points: np.ndarray, hexes: np.ndarray) -> None:
    """Nastran bulk data: large-field ``GRID*`` cards and small-field ``CHEXA`` cards.

    meshio's own writer fails on negative coordinates (its 16-character float format is one
    character too long for them), so this writes the same layout itself; meshio reads it back.
    """
    with open(path, "w") as fh:
        fh.write("$ Nastran bulk data written by polycubenet\nBEGIN BULK\n")
        for i, (x, y, z) in enumerate(np.asarray(points, dtype=np.float64).tolist(), start=1):
            fh.write(f"GRID*   {i:<16d}{'':<16s}{_nastran_float(x):>16s}{_nastran_float(y):>16s}\n")
            fh.write(f"*       {_nastran_float(z):>16s}\n")
        for e, h in enumerate((np.asarray(hexes, dtype=np.int64) + 1).tolist(), start=1):
            tag = f"+1{e:<6x}"
            fh.write(f"CHEXA   {e:<8d}{1:<8d}" + "".join(f"{n:<8d}" for n in h[:6]) + tag + "\n")
            fh.write(tag + "".join(f"{n:<8d}" for n in h[6:]) + "\n")
        fh.write("ENDDATA\n")


def read_hex(path: str | os.PathLike) -> HexMesh:
    """Read a hex mesh written by :func:`write_hex` (or any file of a supported format).

    Parameters
    ----------
    path : str or PathLike
        A file with an extension in ``SUPPORTED_HEX_FORMATS``.

    Returns
    -------
    HexMesh
        ``points : (P, 3) float64``, ``hexes : (H, 8) int64`` (all hexahedron blocks, other cell
        types ignored), ``boundary`` from the ``boundary`` point field when present, and
        ``meta["cell_data"]``: the names of the per-hex fields found.

    Raises
    ------
    ValueError
        Unknown extension, or no hexahedra in the file.
    """
    import meshio

    path = Path(path)
    fmt = _hex_format(path)
    m = meshio.read(path, file_format=fmt)
    blocks = [c.data for c in m.cells if c.type == "hexahedron"]
    if not blocks:
        raise ValueError(f"{path}: no hexahedra in the file (cell types: {sorted({c.type for c in m.cells})})")
    points = np.asarray(m.points, dtype=np.float64)
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])
    boundary = m.point_data.get("boundary")
    names = sorted(k for k in m.cell_data if not k.startswith(("gmsh:", "medit:", "nastran:", "abaqus:")))
    return HexMesh(
        points=points,
        hexes=np.concatenate(blocks).astype(np.int64),
        boundary=None if boundary is None else np.asarray(boundary).astype(bool).ravel(),
        meta={"path": str(path), "format": fmt, "cell_data": names},
    )


# ---------------------------------------------------------------------------------------------
# readers
# ---------------------------------------------------------------------------------------------


def _read_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as exc:
        raise UnreadableFileError(path, f"cannot read the file ({_short(exc)})") from exc


def _too_large(path: Path, n: int, max_faces: int, what: str = "faces") -> None:
    if n > max_faces:
        raise TooLargeError(path, f"the file declares {n:,} {what}, over the limit of {max_faces:,} (max_faces)")


_STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])


def _read_stl(path: Path, max_faces: int, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Binary STL by its header count (so a truncated file is caught), else ASCII STL."""
    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(84)
    n_declared = int(np.frombuffer(head[80:84], "<u4")[0]) if len(head) == 84 else -1
    looks_ascii = head.lstrip()[:5].lower() == b"solid"
    if n_declared >= 0 and size == 84 + 50 * n_declared:
        _too_large(path, n_declared, max_faces, "triangles")
        data = _read_bytes(path)
        tri = np.frombuffer(data, dtype=_STL_DTYPE, count=n_declared, offset=84)["v"].astype(np.float64)
        vertices = tri.reshape(-1, 3)
        return vertices, np.arange(len(vertices), dtype=np.int64).reshape(-1, 3)
    if looks_ascii:
        data = _read_bytes(path)
        if b"\0" not in data[:4096]:
            return _read_ascii_stl(path, data, max_faces)
    if n_declared >= 0 and 84 < size < 84 + 50 * n_declared and not looks_ascii and _stl_records_plausible(path):
        raise UnreadableFileError(
            path,
            f"truncated binary STL: the header announces {n_declared:,} triangles "
            f"({84 + 50 * n_declared:,} bytes) but the file has {size:,} bytes",
        )
    raise UnreadableFileError(
        path,
        f"not a valid STL file: neither binary (the header's triangle count {max(n_declared, 0):,} "
        f"does not match the size of {size:,} bytes) nor ASCII ('solid ... facet ...'){_hint(path, 'stl')}",
    )


def _stl_records_plausible(path: Path, n: int = 8) -> bool:
    """Whether the first complete binary-STL records look like triangles (not random bytes)."""
    with open(path, "rb") as fh:
        data = fh.read(84 + 50 * n)
    k = (len(data) - 84) // 50
    if k < 1:
        return False
    rec = np.frombuffer(data, dtype=_STL_DTYPE, count=k, offset=84)
    values = np.concatenate([rec["normal"].reshape(k, -1), rec["v"].reshape(k, -1)], axis=1).astype(np.float64)
    if not np.isfinite(values).all() or np.abs(values).max() > 1e12:
        return False
    normal_len = np.linalg.norm(values[:, :3], axis=1)
    return bool(np.all((normal_len < 1e-3) | (np.abs(normal_len - 1) < 1e-2)))


def _read_ascii_stl(path: Path, data: bytes, max_faces: int) -> tuple[np.ndarray, np.ndarray]:
    low = data.lower()
    n_facets = low.count(b"endfacet")
    _too_large(path, n_facets, max_faces, "triangles")
    if b"endsolid" not in low[-4096:]:
        raise UnreadableFileError(path, "truncated ASCII STL: no 'endsolid' at the end of the file")
    coords = re.findall(rb"vertex\s+(\S+)\s+(\S+)\s+(\S+)", data, flags=re.IGNORECASE)
    if len(coords) != 3 * n_facets:
        raise UnreadableFileError(
            path, f"corrupt ASCII STL: {len(coords)} vertex lines for {n_facets} facets (expected 3 per facet)"
        )
    try:
        vertices = np.array(coords, dtype=np.float64) if coords else np.zeros((0, 3))
    except ValueError as exc:
        raise UnreadableFileError(
            path, f"corrupt ASCII STL: a vertex coordinate is not a number ({_short(exc)})"
        ) from exc
    return vertices, np.arange(len(vertices), dtype=np.int64).reshape(-1, 3)


def _decode_text(path: Path, data: bytes, fmt: str) -> str:
    if b"\0" in data[:65536]:
        raise UnreadableFileError(path, f"binary data where a text {fmt.upper()} file was expected{_hint(path, fmt)}")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
        bad = sum(1 for c in text[:65536] if ord(c) < 32 and c not in "\r\n\t\f\v")
        if bad:
            raise UnreadableFileError(path, f"not a text {fmt.upper()} file{_hint(path, fmt)}") from None
        return text


def _read_off(path: Path, max_faces: int, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """OFF (and COFF/NOFF/...): own reader, to catch truncation and faces of fewer than 3 vertices."""
    text = _decode_text(path, _read_bytes(path), "off")
    lines = []
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            lines.append(line)
    if not lines or not re.fullmatch(r"[A-Za-z0-9]*OFF", lines[0].split()[0]):
        raise UnreadableFileError(path, f"not an OFF file: the first line is not 'OFF'{_hint(path, 'off')}")
    key, *rest = lines[0].split()
    if key.startswith(("4", "n")) or "4OFF" in key:
        raise UnreadableFileError(path, f"unsupported OFF variant {key!r} (only 3D OFF)")
    pos = 1
    if not rest:
        if len(lines) < 2:
            raise UnreadableFileError(path, "truncated OFF: no vertex/face count line")
        rest = lines[1].split()
        pos = 2
    try:
        nv, nf = int(rest[0]), int(rest[1])
    except (ValueError, IndexError) as exc:
        raise UnreadableFileError(path, f"malformed OFF count line {' '.join(rest)!r}") from exc
    _too_large(path, nf, max_faces)
    if len(lines) < pos + nv + nf:
        raise UnreadableFileError(
            path,
            f"truncated OFF: the header announces {nv} vertices and {nf} faces, "
            f"the file has {len(lines) - pos} data lines",
        )
    try:
        vertices = np.array([ln.split()[:3] for ln in lines[pos : pos + nv]], dtype=np.float64).reshape(nv, 3)
    except ValueError as exc:
        raise UnreadableFileError(path, f"malformed OFF vertex line ({_short(exc)})") from exc
    tris: list[list[int]] = []
    n_poly = 0
    for i, ln in enumerate(lines[pos + nv : pos + nv + nf]):
        tok = ln.split()
        try:
            k = int(tok[0])
            idx = [int(t) for t in tok[1 : 1 + k]]
        except ValueError as exc:
            raise UnreadableFileError(path, f"malformed OFF face line {i}: {ln[:60]!r}") from exc
        if len(idx) != k:
            raise UnreadableFileError(path, f"malformed OFF face line {i}: announces {k} vertices, lists {len(idx)}")
        if k < 3:
            raise NotTriangularError(path, f"face {i} has {k} vertices; a face needs at least 3")
        if k == 3:
            tris.append(idx)
        else:
            n_poly += 1
            tris.extend([idx[0], idx[j], idx[j + 1]] for j in range(1, k - 1))
    if n_poly:
        repairs.append(f"triangulated {n_poly} polygonal faces (fan from their first vertex)")
    faces = np.array(tris, dtype=np.int64).reshape(-1, 3)
    return vertices, faces


def _read_obj(path: Path, max_faces: int, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    data = _read_bytes(path)
    _decode_text(path, data, "obj")
    if not re.search(rb"(?m)^[ \t]*v[ \t]", data):
        raise UnreadableFileError(path, f"not an OBJ file: no vertex ('v x y z') lines{_hint(path, 'obj')}")
    _too_large(path, len(re.findall(rb"(?m)^[ \t]*f[ \t]", data)), max_faces)
    short = re.findall(rb"(?m)^[ \t]*f(?:[ \t]+[^ \t\r\n]+){0,2}[ \t]*\r?$", data)
    if short:
        raise NotTriangularError(
            path, f"{len(short)} faces have fewer than 3 vertices (e.g. {short[0].strip().decode(errors='replace')!r})"
        )
    try:
        return _trimesh_arrays(
            path, "obj", skip_materials=True, group_material=False, split_object=False, maintain_order=True
        )
    except IndexError as exc:
        raise UnreadableFileError(
            path, f"corrupt OBJ: a face refers to a vertex that does not exist ({_short(exc)})"
        ) from exc


def _read_ply(path: Path, max_faces: int, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if not head.startswith(b"ply"):
        raise UnreadableFileError(path, f"not a PLY file: it does not start with 'ply'{_hint(path, 'ply')}")
    n_faces = re.search(rb"element\s+face\s+(\d+)", head)
    n_vertices = re.search(rb"element\s+vertex\s+(\d+)", head)
    if n_faces:
        _too_large(path, int(n_faces.group(1)), max_faces)
    vertices, faces = _trimesh_arrays(path, "ply")
    # trimesh reads a cut ASCII PLY without complaint: compare with the header's counts
    # (polygons are triangulated, so there are at least as many triangles as declared faces)
    if (n_vertices and len(vertices) < int(n_vertices.group(1))) or (n_faces and len(faces) < int(n_faces.group(1))):
        raise UnreadableFileError(
            path,
            f"truncated or corrupt PLY: the header declares {int(n_vertices.group(1)) if n_vertices else '?'} vertices "
            f"and {int(n_faces.group(1)) if n_faces else '?'} faces; read {len(vertices)} and {len(faces)}",
        )
    return vertices, faces


def _read_glb(path: Path, max_faces: int, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    with open(path, "rb") as fh:
        head = fh.read(12)
    if not head.startswith(b"glTF"):
        raise UnreadableFileError(path, f"not a GLB file: no 'glTF' magic{_hint(path, 'glb')}")
    declared = int(np.frombuffer(head[8:12], "<u4")[0]) if len(head) == 12 else -1
    if declared != path.stat().st_size:
        raise UnreadableFileError(
            path, f"truncated or corrupt GLB: the header announces {declared} bytes, the file has {path.stat().st_size}"
        )
    return _trimesh_arrays(path, "glb")


#: the faces of each solid cell type (VTK corner order), each listed counter-clockwise seen from
#: outside a positively oriented cell; triangles and quads of the surface cell types themselves
_CELL_FACES: dict[str, list[tuple[int, ...]]] = {
    "tetra": [(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)],
    "hexahedron": [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)],
    "wedge": [(0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)],
    "pyramid": [(0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)],
}
_CELL_CORNERS = {"tetra": 4, "hexahedron": 8, "wedge": 6, "pyramid": 5}
_SURFACE_CORNERS = {"triangle": 3, "quad": 4}


def _cell_kind(name: str) -> tuple[str | None, int]:
    """``(kind, corners)`` of a meshio cell type name (``tetra10`` -> ``("tetra", 4)``), else ``(None, 0)``."""
    base = name.rstrip("0123456789")
    if base in _CELL_CORNERS:
        return base, _CELL_CORNERS[base]
    if base in _SURFACE_CORNERS:
        return base, _SURFACE_CORNERS[base]
    return None, 0


def _read_volume(path: Path, max_faces: int, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The boundary triangles of a volume mesh (see the module docstring)."""
    import meshio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = meshio.read(path, file_format=SUPPORTED_PART_FORMATS[path.suffix.lower()])
    pts = np.asarray(m.points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise UnreadableFileError(path, f"points have shape {pts.shape}, expected (n, 3)")
    if pts.shape[1] == 2:
        raise UnreadableFileError(path, "a 2-D mesh (points have 2 coordinates) has no solid to mesh")
    solid_faces: list[np.ndarray] = []
    surface_faces: list[np.ndarray] = []
    n_solid = 0
    skipped: dict[str, int] = {}
    for block in m.cells:
        kind, k = _cell_kind(block.type)
        data = np.asarray(block.data, dtype=np.int64)
        if kind is None or len(data) == 0:
            if kind is None and block.type not in ("vertex", "line") and not block.type.startswith("line"):
                skipped[block.type] = skipped.get(block.type, 0) + len(data)
            continue
        corners = data[:, :k]
        if kind in _CELL_FACES:
            n_solid += len(corners)
            # orient each cell positively (a mirrored file lists its cells the other way round)
            p = pts[corners]
            if kind == "tetra":
                vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])
            else:  # sign from the centroid: the first face's normal points away from it
                f0 = _CELL_FACES[kind][0]
                n0 = np.cross(p[:, f0[1]] - p[:, f0[0]], p[:, f0[2]] - p[:, f0[0]])
                vol = -np.einsum("ij,ij->i", n0, p.mean(axis=1) - p[:, f0[0]])
            for face in _CELL_FACES[kind]:
                f = corners[:, list(face)]
                f[vol < 0] = f[vol < 0][:, ::-1]
                solid_faces.append(f if len(face) == 4 else np.pad(f, ((0, 0), (0, 1)), constant_values=-1))
        else:
            surface_faces.append(corners if k == 4 else np.pad(corners, ((0, 0), (0, 1)), constant_values=-1))
    if skipped:
        repairs.append("ignored cells of unsupported type: " + ", ".join(f"{n} {t}" for t, n in sorted(skipped.items())))
    if n_solid:
        faces = np.concatenate(solid_faces)
        # boundary faces: those whose vertex set occurs once (an interior face is shared by two cells)
        key = np.sort(faces, axis=1)
        _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
        faces = faces[counts[inverse.ravel()] == 1]
        what = f"the boundary of {n_solid} solid cells"
        if surface_faces:
            repairs.append(f"read {what}; the file's own surface cells were ignored")
        else:
            repairs.append(f"read {what}")
    elif surface_faces:
        faces = np.concatenate(surface_faces)
        repairs.append("the file has no solid cells: its triangles/quads were read as the surface")
    else:
        raise EmptyMeshError(path, "no solid cells (tetra, hexahedron, wedge, pyramid) and no surface cells in the file")
    tri = faces[faces[:, 3] < 0][:, :3]
    quad = faces[faces[:, 3] >= 0]
    tris = np.concatenate([tri, quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]])
    _too_large(path, len(tris), max_faces)
    if tris.size and (tris.max() >= len(pts) or tris.min() < 0):
        raise UnreadableFileError(path, "a cell refers to a node that does not exist")
    # interior nodes are expected in a volume mesh: keep the boundary's only, silently
    used, tris = np.unique(tris, return_inverse=True)
    return pts[used], tris.reshape(-1, 3)


def _trimesh_arrays(path: Path, fmt: str, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """Load with trimesh (``process=False``); a scene's meshes are concatenated in world coordinates."""
    import trimesh

    loaded = trimesh.load(str(path), file_type=fmt, process=False, **kwargs)
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        if not meshes:
            raise EmptyMeshError(path, f"the {fmt.upper()} file contains no triangle mesh")
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes])
        vertices = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in meshes])
        faces = np.concatenate(
            [np.asarray(m.faces, dtype=np.int64).reshape(-1, 3) + o for m, o in zip(meshes, offsets[:-1], strict=True)]
        )
        return vertices, faces
    if not isinstance(loaded, trimesh.Trimesh):
        raise EmptyMeshError(path, f"the {fmt.upper()} file contains no triangle mesh ({type(loaded).__name__})")
    return np.asarray(loaded.vertices, dtype=np.float64), np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3)


# ---------------------------------------------------------------------------------------------
# CAD (STEP / IGES) through gmsh + OpenCASCADE
# ---------------------------------------------------------------------------------------------

#: gmsh is a process-wide singleton: every use in this module holds this lock
GMSH_LOCK = threading.RLock()


@contextlib.contextmanager
def gmsh_session(quiet: bool = True) -> Iterator[object]:
    """Hold the gmsh lock and an initialised gmsh; yield the ``gmsh`` module.

    If gmsh is already initialised (by the caller), it is reused and left initialised;
    otherwise it is initialised here without signal handlers (safe off the main thread) and
    finalised on exit.  ``General.Terminal`` is 0 unless ``quiet`` is False.
    """
    import gmsh

    with GMSH_LOCK:
        owner = not gmsh.isInitialized()
        if owner:
            try:
                gmsh.initialize([], readConfigFiles=False, interruptible=False)
            except TypeError:  # gmsh < 4.11 has no ``interruptible``
                gmsh.initialize([], readConfigFiles=False)
        terminal = gmsh.option.getNumber("General.Terminal")
        gmsh.option.setNumber("General.Terminal", 0 if quiet else 1)
        try:
            yield gmsh
        finally:
            if owner:
                gmsh.finalize()
            else:
                gmsh.option.setNumber("General.Terminal", terminal)


@contextlib.contextmanager
def quiet_stdout() -> Iterator[None]:
    """Silence file descriptor 1 (OpenCASCADE prints to C++ ``std::cout`` despite gmsh's options).

    This redirects the whole process's stdout for the duration, so keep it short.
    """
    import sys

    try:
        sys.stdout.flush()
    except Exception:  # noqa: BLE001 - a closed or exotic sys.stdout
        pass
    libc = None
    with contextlib.suppress(OSError):
        libc = ctypes.CDLL(None)
    try:
        saved = os.dup(1)
    except OSError:
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        yield
    finally:
        if libc is not None:
            libc.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def _read_cad(path: Path, fmt: str, *, mesh_size: float | None, max_faces: int, unit: str | None,
              repairs: list[str] | None = None):
    head = _read_bytes(path)
    file_units = _check_cad_file(path, fmt, head)
    scale = _MM_PER_UNIT[unit or "mm"]  # OpenCASCADE gives millimetres; we divide by this
    with gmsh_session() as gmsh:
        saved = {
            name: gmsh.option.getNumber(name)
            for name in (
                "Mesh.MeshSizeMax",
                "Mesh.MeshSizeMin",
                "Mesh.MeshSizeFromCurvature",
                "Mesh.MeshSizeExtendFromBoundary",
            )
        }
        saved_unit = gmsh.option.getString("Geometry.OCCTargetUnit")
        previous = gmsh.model.getCurrent() if gmsh.model.list() else None
        gmsh.model.add(f"polycubenet-load-{id(path)}")
        try:
            done: list[str] = []  # the repairs of this import, kept when it meshes
            diag, healed = _import_solid(gmsh, path, fmt, done, heal=True)
            h = float(mesh_size) * scale if mesh_size is not None else tol.CAD_MESH_SIZE_REL * diag
            if not h > 0:
                raise ValueError(f"mesh_size must be positive; got {mesh_size}")
            area = _surface_area(gmsh)
            estimate = int(area / (math.sqrt(3) / 4 * h * h))
            if estimate > max_faces:
                raise TooLargeError(
                    path,
                    f"meshing at size {h / scale:.4g} would give about {estimate:,} triangles, over the limit of "
                    f"{max_faces:,} (max_faces); pass a larger mesh_size",
                )
            gmsh.option.setNumber("Mesh.MeshSizeMax", h)
            gmsh.option.setNumber("Mesh.MeshSizeMin", h / 50)
            gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 16)
            gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 1)
            try:
                gmsh.model.mesh.generate(2)
            except Exception as exc:
                if not healed:
                    raise UnreadableFileError(path, f"gmsh could not mesh the surfaces ({_short(exc)})") from exc
                # a heal can keep the area and still break a face's boundary (a hemisphere's seam merged into
                # one edge, the hard set's capsule posts: "The 1D mesh seems not to be forming a closed loop")
                _empty_model(gmsh)
                done = []
                _import_solid(gmsh, path, fmt, done, heal=False)
                done.append(f"kept the CAD solid as imported: healed, gmsh could not mesh it ({_short(exc)})")
                try:
                    gmsh.model.mesh.generate(2)
                except Exception as exc2:
                    raise UnreadableFileError(path, f"gmsh could not mesh the surfaces, healed ({_short(exc)}) or "
                                                    f"as imported ({_short(exc2)})") from exc2
            if repairs is not None:
                repairs.extend(done)
            node_tags, coords, _ = gmsh.model.mesh.getNodes()
            _, tri_nodes = gmsh.model.mesh.getElementsByType(2)
        finally:
            gmsh.model.remove()
            if previous:
                gmsh.model.setCurrent(previous)
            for name, value in saved.items():
                gmsh.option.setNumber(name, value)
            gmsh.option.setString("Geometry.OCCTargetUnit", saved_unit)
    node_tags = np.asarray(node_tags, dtype=np.int64)
    lookup = np.full(int(node_tags.max()) + 1 if len(node_tags) else 1, -1, dtype=np.int64)
    lookup[node_tags] = np.arange(len(node_tags))
    faces = lookup[np.asarray(tri_nodes, dtype=np.int64)].reshape(-1, 3)
    vertices = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    if scale != 1.0:
        vertices /= scale
    meta = {"units": unit or "mm", "file_units": file_units, "mesh_size": h / scale}
    return vertices, faces, meta


def _import_solid(gmsh, path: Path, fmt: str, repairs: list[str], *, heal: bool) -> tuple[float, bool]:
    """Import the CAD file into the current gmsh model as closed solids in millimetres: loose faces sewn,
    touching solids fused, and (``heal``) the solids healed (:func:`_heal_solids`); what was done is appended
    to ``repairs``.  Returns the bounding box's diagonal and whether the solids are healed."""
    _import_in_mm(gmsh, path, fmt)
    if not gmsh.model.getEntities(2):
        raise EmptyMeshError(path, f"the {fmt.upper()} file contains no surfaces or solids")
    xmin, ymin, zmin, xmax, ymax, zmax = gmsh.model.getBoundingBox(-1, -1)
    diag = math.dist((xmin, ymin, zmin), (xmax, ymax, zmax))
    if not gmsh.model.getEntities(3):
        # loose faces (IGES, surface-only STEP): sew them into shells so the mesh is conformal
        with quiet_stdout():
            gmsh.model.occ.healShapes(tolerance=tol.CAD_SEW_REL * diag, sewFaces=True, makeSolids=True)
            gmsh.model.occ.synchronize()
    solids = gmsh.model.getEntities(3)
    if len(solids) > 1:
        # a multi-body part: solids that touch (or overlap) become one solid, their shared faces
        # inside it; solids that do not touch stay apart (and are refused as several components)
        with quiet_stdout():
            gmsh.model.occ.fuse(solids[:1], solids[1:])
            gmsh.model.occ.synchronize()
        after = len(gmsh.model.getEntities(3))
        if after < len(solids):
            repairs.append(f"fused {len(solids)} touching solids into {after}")
    # after the fuse: healing first would sew touching solids into non-manifold shells
    healed = bool(solids) and heal and _heal_solids(gmsh, path, fmt, repairs)
    return diag, healed


def _heal_solids(gmsh, path: Path, fmt: str, repairs: list[str]) -> bool:
    """Heal the imported solids before meshing (OpenCASCADE's ShapeFix through gmsh, at its default 1e-8
    tolerance: degenerate, small and open edges and faces fixed, faces sewn): where a chamfer meets a fillet
    a kernel can leave a sliver face (0.03 mm² beside 3000 mm² ones, session 48's finished never-seen parts)
    that gmsh meshes for minutes into degenerate triangles or leaves empty, so the surface is not closed.
    On a clean solid it changes nothing (the ten examples mesh to the same triangles).  A heal that changes
    the face or edge count is recorded in ``repairs``.

    A heal that changes the surface's area by more than ``tol.CAD_HEAL_AREA_REL`` is undone (the file
    imported again, unhealed, and that recorded): on a quarter torus fused to cylinders (the hard set's tube
    elbows) the small-edge fix emptied a cylinder face of 1150 mm², and gmsh then failed on the periodic
    faces or meshed for minutes without end.  Returns whether the heal was kept."""
    def counts():
        return len(gmsh.model.getEntities(2)), len(gmsh.model.getEntities(1))

    before, area = counts(), _surface_area(gmsh)
    with quiet_stdout():
        gmsh.model.occ.healShapes()
        gmsh.model.occ.synchronize()
    after, healed_area = counts(), _surface_area(gmsh)
    change = abs(healed_area - area) / max(area, 1e-300)
    if change > tol.CAD_HEAL_AREA_REL:
        _empty_model(gmsh)
        _import_solid(gmsh, path, fmt, [], heal=False)
        repairs.append(f"kept the CAD solid as imported: OpenCASCADE's ShapeFix changed its surface area by "
                       f"{100 * change:.2g} %")
        return False
    if after != before:
        repairs.append(f"healed the CAD solid (OpenCASCADE ShapeFix: small, degenerate and open edges and faces): "
                       f"{before[0]} faces and {before[1]} edges became {after[0]} and {after[1]}")
    return True


def _empty_model(gmsh) -> None:
    """The current gmsh model removed and added again, empty, under its name."""
    name = gmsh.model.getCurrent()
    gmsh.model.remove()
    gmsh.model.add(name)


def _surface_area(gmsh) -> float:
    return sum(gmsh.model.occ.getMass(2, tag) for _, tag in gmsh.model.getEntities(2))


def _import_in_mm(gmsh, path: Path, fmt: str) -> None:
    """Import a STEP/IGES file into the current gmsh model, in millimetres.

    OpenCASCADE converts to a target unit kept in a process-wide static (default millimetres).
    We ask for millimetres explicitly, since an earlier caller may have changed it; when the
    static does not exist yet (IGES before any STEP import), setting it fails, and then the
    default is in force.
    """
    for target in ("MM", ""):
        gmsh.option.setString("Geometry.OCCTargetUnit", target)
        try:
            with quiet_stdout():
                gmsh.model.occ.importShapes(str(path))
                gmsh.model.occ.synchronize()
            return
        except Exception as exc:
            if target and "target unit" in str(exc):
                continue
            raise UnreadableFileError(
                path, f"OpenCASCADE cannot read this {fmt.upper()} file ({_short(exc)}){_hint(path, fmt)}"
            ) from exc


def _check_cad_file(path: Path, fmt: str, data: bytes) -> str | None:
    """Cheap structural checks before OpenCASCADE sees the file; return the declared length unit."""
    if b"\0" in data[:65536]:
        raise UnreadableFileError(path, f"binary data where a text {fmt.upper()} file was expected{_hint(path, fmt)}")
    if fmt == "step":
        if not data.lstrip()[:12].upper() == b"ISO-10303-21":
            raise UnreadableFileError(
                path, f"not a STEP file: it does not start with 'ISO-10303-21;'{_hint(path, fmt)}"
            )
        if b"END-ISO-10303-21" not in data[-2048:].upper():
            raise UnreadableFileError(path, "truncated STEP file: no 'END-ISO-10303-21;' at the end")
        return _step_units(data)
    lines = [ln for ln in data.decode("latin-1").splitlines() if ln.strip()]
    if not lines or len(lines[0]) < 73 or lines[0][72] not in "SFCB":
        raise UnreadableFileError(path, f"not an IGES file: no start section in column 73{_hint(path, fmt)}")
    if len(lines[-1]) < 73 or lines[-1][72] != "T":
        raise UnreadableFileError(path, "truncated IGES file: no terminate ('T') line at the end")
    return _iges_units(lines)


_STEP_PREFIX = {
    "$": "m",
    ".MILLI.": "mm",
    ".CENTI.": "cm",
    ".DECI.": "dm",
    ".KILO.": "km",
    ".MICRO.": "um",
    ".NANO.": "nm",
}


def _step_units(data: bytes) -> str | None:
    """Length unit declared in a STEP file (``SI_UNIT(.MILLI.,.METRE.)`` or a named conversion)."""
    for m in re.finditer(rb"\(([^;]*?LENGTH_UNIT[^;]*?)\)\s*;", data):
        ent = re.sub(rb"\s+", b"", m.group(1)).upper()
        conv = re.search(rb"CONVERSION_BASED_UNIT\('([^']*)'", ent)
        if conv:
            name = conv.group(1).decode(errors="replace").lower()
            return _UNIT_ALIASES.get(name, name)
        si = re.search(rb"SI_UNIT\(([^,]*),\.METRE\.\)", ent)
        if si:
            return _STEP_PREFIX.get(si.group(1).decode(), si.group(1).decode().strip(".").lower() + "m")
    return None


_IGES_UNITS = {1: "in", 2: "mm", 4: "ft", 5: "mi", 6: "m", 7: "km", 8: "mil", 9: "um", 10: "cm", 11: "uin"}


def _iges_units(lines: list[str]) -> str | None:
    """Unit flag (global parameter 14) of an IGES file."""
    text = "".join(ln[:72] for ln in lines if len(ln) >= 73 and ln[72] == "G")
    params, i, delim = [], 0, ","
    if text.startswith("1H"):
        delim = text[2]
    while i < len(text) and len(params) < 16:
        m = re.match(r"\s*(\d+)H", text[i:])
        if m:  # Hollerith string nHxxxx
            n = int(m.group(1))
            start = i + m.end()
            params.append(text[start : start + n])
            i = start + n
        else:
            j = i
            while j < len(text) and text[j] not in (delim, ";"):
                j += 1
            params.append(text[i:j].strip())
            i = j
        if i < len(text) and text[i] in (delim, ";"):
            i += 1
    try:
        flag = int(float(params[13]))
    except (IndexError, ValueError):
        return None
    if flag == 3 and len(params) > 14:
        return params[14].strip().lower() or None
    return _IGES_UNITS.get(flag)


# ---------------------------------------------------------------------------------------------
# repairs and topology (vectorised)
# ---------------------------------------------------------------------------------------------


def _diagonal(v: np.ndarray) -> float:
    return float(np.linalg.norm(v.max(axis=0) - v.min(axis=0))) if len(v) else 0.0


def _group_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group equal rows of an integer array.

    Returns
    -------
    first : (G,) int64, index of one representative row per group
    inverse : (N,) int64, group of each row (groups in lexicographic order)
    """
    order = np.lexsort(a.T[::-1])
    s = a[order]
    new = np.ones(len(a), dtype=bool)
    new[1:] = np.any(s[1:] != s[:-1], axis=1)
    gid = np.cumsum(new) - 1
    inverse = np.empty(len(a), dtype=np.int64)
    inverse[order] = gid
    return order[new], inverse


def _merge_vertices(v: np.ndarray, f: np.ndarray, eps: float, repairs: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices that coincide after rounding to a grid of spacing ``eps``."""
    q = np.round((v - v.min(axis=0)) / eps).astype(np.int64)
    first, inverse = _group_rows(q)
    if len(first) == len(v):
        return v, f
    repairs.append(f"merged {len(v) - len(first)} duplicate vertices (closer than {eps:.3g})")
    return v[first], inverse[f]


def _drop_degenerate_faces(v: np.ndarray, f: np.ndarray, min_area: float, repairs: list[str]) -> tuple[np.ndarray, int]:
    """Drop faces with a repeated vertex; a zero-area face with three distinct vertices (a *cap*: one vertex on
    the segment between the other two, as a CAD mesher leaves on a sliver face) is removed by splitting the
    face across its long edge at that vertex (:func:`_split_caps`), which keeps a closed surface closed;
    a cap that cannot be split so is dropped.  Returns the faces and the number dropped (caps split not
    counted)."""
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    zero = ~repeated & (_face_areas(v, f) <= min_area)
    n_split = 0
    if zero.any():
        f, zero, n_split = _split_caps(v, f, zero)
        repeated = np.concatenate([repeated, np.zeros(len(f) - len(repeated), dtype=bool)])
    bad = repeated | zero
    n = int(bad.sum()) - n_split
    if n_split:
        repairs.append(f"removed {n_split} zero-area caps (a vertex on the opposite edge) by splitting the face "
                       "across that edge at it")
    if n:
        repairs.append(f"dropped {n} degenerate faces (repeated vertex or zero area)")
    return f[~bad], n


def _split_caps(v: np.ndarray, f: np.ndarray, cap: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Split caps away.  For each cap ``(x, y, m)`` (``m`` the vertex opposite the longest edge, so between ``x``
    and ``y``) whose long edge has exactly one other face ``(y, x, d)``, not itself a cap: that face becomes
    ``(y, m, d)`` and ``(m, x, d)`` (the second appended; a later cap may split either half again) and the cap
    is removed.  Returns the faces, the mask of faces to drop (the caps, split or not: one that could not be
    split is dropped as before) and the number split."""
    faces = f.tolist()
    owners: dict[tuple[int, int], list[int]] = {}

    def own(j: int) -> None:
        t = faces[j]
        for q in range(3):
            owners.setdefault((t[q], t[(q + 1) % 3]), []).append(j)

    def disown(j: int) -> None:
        t = faces[j]
        for q in range(3):
            owners[(t[q], t[(q + 1) % 3])].remove(j)

    for j in range(len(faces)):
        own(j)
    n = 0
    for i in np.flatnonzero(cap):
        tri = faces[i]
        k = int(np.argmax([np.linalg.norm(v[tri[(q + 1) % 3]] - v[tri[q]]) for q in range(3)]))
        x, y, m = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
        other = [j for j in owners.get((y, x), []) if not (j < len(cap) and cap[j])]
        if len(other) != 1 or len(owners.get((x, y), [])) != 1:
            continue
        j = other[0]
        jt = faces[j]
        d = jt[(jt.index(y) + 2) % 3]
        disown(i)
        disown(j)
        faces[j] = [y, m, d]
        faces.append([m, x, d])
        own(j)
        own(len(faces) - 1)
        n += 1
    drop = np.concatenate([cap, np.zeros(len(faces) - len(cap), dtype=bool)])
    return np.asarray(faces, dtype=f.dtype), drop, n


def _drop_duplicate_faces(f: np.ndarray, repairs: list[str]) -> np.ndarray:
    """Drop faces repeating another face's vertices in the same cyclic order.

    A face with the same vertices in the *opposite* order is kept: it is a double-sided
    sheet, and the manifold and volume checks report it.
    """
    shift = np.argmin(f, axis=1)
    canon = f[np.arange(len(f))[:, None], (shift[:, None] + np.arange(3)) % 3]
    first, _ = _group_rows(canon)
    if len(first) == len(f):
        return f
    repairs.append(f"dropped {len(f) - len(first)} duplicate faces")
    return f[np.sort(first)]


def _drop_unreferenced(v: np.ndarray, f: np.ndarray, repairs: list[str] | None) -> tuple[np.ndarray, np.ndarray]:
    used = np.zeros(len(v), dtype=bool)
    used[f.ravel()] = True
    n_unused = int((~used).sum())
    if not n_unused:
        return v, f
    if repairs is not None:
        repairs.append(f"removed {n_unused} unreferenced vertices")
    remap = np.cumsum(used) - 1
    return v[used], remap[f]


def _edge_topology(f: np.ndarray) -> dict:
    """Half-edges sorted by undirected edge, with run lengths.

    Half-edge ``h = 3 * face + i`` goes from ``f[face, i]`` to ``f[face, (i + 1) % 3]``.

    Returns
    -------
    dict
        ``pairs`` : (E2, 2) int64, the two half-edges of each edge with exactly two faces;
        ``n_boundary``, ``n_nonmanifold`` : int, edges with one / more than two faces.
    """
    n_v = int(f.max()) + 1
    a = f.ravel()
    b = f[:, [1, 2, 0]].ravel()
    key = np.minimum(a, b) * n_v + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[start, len(ks)])
    two = start[counts == 2]
    return {
        "pairs": np.stack([order[two], order[two + 1]], axis=1),
        "n_boundary": int((counts == 1).sum()),
        "n_nonmanifold": int((counts > 2).sum()),
    }


def _connected_labels(n: int, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(i), dtype=np.int8), (i, j)), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def _count_pinched_vertices(f: np.ndarray, n_v: int, topo: dict) -> int:
    """Vertices whose faces form more than one fan (corner graph components per vertex).

    Corners ``c = 3 * face + i`` (vertex ``f[face, i]``) are linked across every manifold
    edge at both of its endpoints; on a closed manifold each vertex's corners are then one
    component.
    """
    flat = f.ravel()
    h = topo["pairs"]  # (E2, 2) half-edges
    nxt = 3 * (h // 3) + (h % 3 + 1) % 3
    start_v, end_v = flat[h], flat[nxt]
    # corner of each half-edge at the smaller / larger endpoint
    lo = np.where(start_v < end_v, h, nxt)
    hi = np.where(start_v < end_v, nxt, h)
    labels = _connected_labels(len(flat), np.r_[lo[:, 0], hi[:, 0]], np.r_[lo[:, 1], hi[:, 1]])
    n_lab = int(labels.max()) + 1
    pairs = np.sort(flat.astype(np.int64) * n_lab + labels)
    pairs = pairs[np.r_[True, pairs[1:] != pairs[:-1]]]  # distinct (vertex, fan) pairs
    fans = np.bincount(pairs // n_lab, minlength=n_v)
    return int((fans > 1).sum())


def _orient(f: np.ndarray, topo: dict) -> tuple[np.ndarray | None, np.ndarray]:
    """Consistent orientation by 2-colouring the faces on the orientation double cover.

    Node ``face`` means "keep", node ``face + F`` "flip".  Two faces crossing an edge in
    opposite directions must get the same choice, in the same direction opposite choices.
    The surface is orientable iff no face's two nodes share a component.

    Returns
    -------
    comp : (F,) int64 or None
        Connected component of each face (None when non-orientable).
    flip : (F,) bool
        Faces to reverse; per component the smaller of the two consistent choices.
    """
    n_f = len(f)
    h = topo["pairs"]
    flat = f.ravel()
    same = flat[h[:, 0]] == flat[h[:, 1]]  # both half-edges start at the same vertex
    f1, f2 = h[:, 0] // 3, h[:, 1] // 3
    i = np.r_[f1, f1 + n_f]
    j = np.r_[np.where(same, f2 + n_f, f2), np.where(same, f2, f2 + n_f)]
    labels = _connected_labels(2 * n_f, i, j)
    keep_lab, flip_lab = labels[:n_f], labels[n_f:]
    if np.any(keep_lab == flip_lab):
        return None, np.zeros(n_f, dtype=bool)
    flip = keep_lab > flip_lab
    rep = np.minimum(keep_lab, flip_lab)
    present = np.zeros(2 * n_f, dtype=bool)
    present[rep] = True
    comp = (np.cumsum(present) - 1)[rep].astype(np.int64)
    n_comp = int(comp.max()) + 1
    flipped = np.bincount(comp, weights=flip, minlength=n_comp)
    total = np.bincount(comp, minlength=n_comp)
    invert = flipped > total / 2  # flip the fewest faces in each component
    return comp, flip ^ invert[comp]


def _face_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area of each triangle, ``(F,)``."""
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def _face_volumes(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Signed volume of the tetrahedron (origin, triangle) per face; their sum is the enclosed volume."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return np.einsum("ij,ij->i", a, np.cross(b, c)) / 6.0


# ---------------------------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------------------------


def _canonical_unit(units: str | None) -> str | None:
    if units is None:
        return None
    u = str(units).strip().lower()
    u = _UNIT_ALIASES.get(u, u)
    if u not in _MM_PER_UNIT:
        raise ValueError(f"unknown length unit {units!r}; use one of {sorted(_MM_PER_UNIT)}")
    return u


def _hex_format(path: Path) -> str:
    fmt = SUPPORTED_HEX_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(
            f"{path}: unknown hex mesh extension {path.suffix!r}; supported: {' '.join(SUPPORTED_HEX_FORMATS)}"
        )
    return fmt


def _short(exc: BaseException, limit: int = 160) -> str:
    text = f"{type(exc).__name__}: {exc}".strip()
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _sniff(head: bytes) -> str | None:
    """Guess a format from the first bytes of a file (for hints in error messages)."""
    s = head.lstrip()
    if s.startswith(b"ply"):
        return "PLY"
    if s.startswith(b"glTF"):
        return "GLB"
    if s[:12].upper() == b"ISO-10303-21":
        return "STEP"
    first = s.split(b"\n", 1)[0]
    if re.match(rb"[A-Z]*OFF\b", first):
        return "OFF"
    if s[:5].lower() == b"solid" and b"facet" in s.lower():
        return "ASCII STL"
    if len(first.rstrip(b"\r")) >= 73 and first[72:73] == b"S":
        return "IGES"
    if re.search(rb"(?m)^[ \t]*v[ \t]+\S+[ \t]+\S+[ \t]+\S+", head) and b"\0" not in head:
        return "OBJ"
    if len(head) >= 84:
        return None  # could be a binary STL; decided by the STL reader
    return None


def _hint(path: Path, fmt: str) -> str:
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return ""
    kind = _sniff(head)
    size = path.stat().st_size
    if (
        kind is None
        and fmt != "stl"
        and len(head) >= 84
        and size == 84 + 50 * int(np.frombuffer(head[80:84], "<u4")[0])
    ):
        kind = "binary STL"
    if kind is None or kind.split()[-1].lower() == fmt:
        return ""
    return f"; the content looks like {kind}, not {fmt.upper()}: is the extension wrong?"
