"""The bad-input corpus for :func:`polycubenet.io.load_part`, generated into a folder.

``make_corpus(dir)`` writes files that must be *refused*, each with the exact
:class:`~polycubenet.errors.PartError` subclass expected; ``make_repairable(dir)`` writes
files that must *load* after a safe repair, with a word expected in ``meta["repairs"]``.
Some cases need a keyword argument of ``load_part`` (``max_faces``, ``keep_largest``):
``load_kwargs(path)`` gives it.

Everything is built from a few arrays (a cube, boxes, tetrahedra, a Möbius strip, a Klein
bottle) and tiny writers, plus two CAD files written by gmsh; nothing is read from outside
the repository.  Run ``python tests/bad_inputs.py DIR`` to write the corpus for a look.
"""

from __future__ import annotations

import dataclasses
import functools
import struct
import sys
from pathlib import Path
from collections.abc import Callable

import numpy as np

from polycubenet.errors import (
    DegenerateVolumeError,
    EmptyMeshError,
    InvalidCoordinatesError,
    MultipleComponentsError,
    SelfIntersectionError,
    NonManifoldError,
    NotTriangularError,
    OpenBoundaryError,
    PartError,
    TooLargeError,
    UnknownFormatError,
    UnreadableFileError,
)


# ---------------------------------------------------------------------------------------------
# shapes: (V, F) arrays, faces outward
# ---------------------------------------------------------------------------------------------


def cube(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box: ``(8, 3)`` vertices and ``(12, 3)`` outward triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    v = lo + corners * (hi - lo)  # index = 4 i + 2 j + k
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    return v, f


def tetra(offset=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) + offset
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)
    return v, f


def join(*meshes) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, n = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def mobius(n: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A Möbius strip: open (two boundary edges per rim segment) and non-orientable."""
    u = 2 * np.pi * np.arange(n) / n
    v = []
    for t in (-0.3, 0.3):
        v.append(
            np.stack([(1 + t * np.cos(u / 2)) * np.cos(u), (1 + t * np.cos(u / 2)) * np.sin(u), t * np.sin(u / 2)], 1)
        )
    v = np.concatenate(v)  # index j * n + i
    f = []
    for i in range(n):
        a, b = i, n + i
        if i + 1 < n:
            c, d = i + 1, n + i + 1
        else:  # the half twist: rim 0 meets rim 1
            c, d = n, 0
        f += [(a, c, d), (a, d, b)]
    return v, np.array(f, dtype=np.int64)


def klein_bottle(n: int = 32, m: int = 16, r: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed non-orientable surface (figure-8 immersion of the Klein bottle).

    The grid is offset by half a step in ``v`` so no two vertices coincide (the immersion
    crosses itself at ``v = 0`` and ``v = pi``); edges and vertices are all manifold.
    """
    u = 2 * np.pi * np.arange(n) / n
    v = 2 * np.pi * (np.arange(m) + 0.5) / m
    uu, vv = np.meshgrid(u, v, indexing="ij")
    w = np.cos(uu / 2) * np.sin(vv) - np.sin(uu / 2) * np.sin(2 * vv)
    pts = np.stack(
        [(r + w) * np.cos(uu), (r + w) * np.sin(uu), np.sin(uu / 2) * np.sin(vv) + np.cos(uu / 2) * np.sin(2 * vv)], -1
    )
    idx = np.arange(n * m).reshape(n, m)

    def vid(i, j):
        if i == n:  # (u + 2 pi, v) is (u, -v): column j meets column m - 1 - j
            return idx[0, (m - 1 - j) % m]
        return idx[i, j % m]

    f = []
    for i in range(n):
        for j in range(m):
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            f += [(a, b, c), (a, c, d)]
    return pts.reshape(-1, 3), np.array(f, dtype=np.int64)


# ---------------------------------------------------------------------------------------------
# writers
# ---------------------------------------------------------------------------------------------


def stl_bytes(v: np.ndarray, f: np.ndarray) -> bytes:
    tri = np.asarray(v, np.float32)[np.asarray(f)]
    rec = np.zeros(len(f), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = tri
    return b"binary STL written by tests/bad_inputs.py".ljust(80, b" ") + struct.pack("<I", len(f)) + rec.tobytes()


def write_stl(path: Path, v, f) -> None:
    path.write_bytes(stl_bytes(v, f))


def write_obj(path: Path, v, f, extra: str = "") -> None:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(v, float).tolist()]
    lines += ["f " + " ".join(str(i + 1) for i in face) for face in np.asarray(f).tolist()]
    path.write_text("\n".join(lines) + "\n" + extra)


def write_off(path: Path, v, faces: list) -> None:
    """``faces``: a list of index lists (polygons allowed)."""
    lines = ["OFF", f"{len(v)} {len(faces)} 0"]
    lines += [" ".join(repr(float(c)) for c in p) for p in np.asarray(v, float)]
    lines += [" ".join(str(i) for i in [len(face), *face]) for face in faces]
    path.write_text("\n".join(lines) + "\n")


def trimesh_bytes(v, f, file_type: str) -> bytes:
    import trimesh

    data = trimesh.Trimesh(v, f, process=False).export(file_type=file_type)
    return data if isinstance(data, bytes) else data.encode()


@functools.cache
def cad_box_bytes(kind: str) -> bytes:
    """A 10 x 20 x 5 mm box with a through hole, as STEP (``kind="step"``) or IGES bytes."""
    import tempfile

    from polycubenet.io import gmsh_session, quiet_stdout

    with tempfile.TemporaryDirectory() as tmp, gmsh_session() as gmsh:
        gmsh.model.add("corpus-box")
        try:
            box = gmsh.model.occ.addBox(0, 0, 0, 10, 20, 5)
            hole = gmsh.model.occ.addCylinder(5, 10, -1, 0, 0, 7, 2)
            gmsh.model.occ.cut([(3, box)], [(3, hole)])
            gmsh.model.occ.synchronize()
            out = Path(tmp) / f"box.{kind}"
            with quiet_stdout():
                gmsh.write(str(out))
            return out.read_bytes()
        finally:
            gmsh.model.remove()


EMPTY_STEP = """ISO-10303-21;
HEADER;
FILE_DESCRIPTION(('a model with no shapes'),'2;1');
FILE_NAME('empty.step','2024-01-01T00:00:00',('polycubenet'),(''),'','','');
FILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 1 1 1 1 }'));
ENDSEC;
DATA;
ENDSEC;
END-ISO-10303-21;
"""


def _garbage(seed: int, n: int = 3001) -> bytes:
    """Random bytes (never a valid binary STL: 3001 is not 84 + 50 k)."""
    return np.random.default_rng(seed).bytes(n)


def _flat_double_sided() -> tuple[np.ndarray, list]:
    """A closed two-sided square: front split on one diagonal, back on the other (manifold, volume 0)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    return v, [[0, 1, 2], [0, 2, 3], [1, 0, 3], [1, 3, 2]]


def _open_cube():
    v, f = cube()
    return v, f[2:]  # the two triangles of the bottom face removed


def _fin():
    v, f = cube()
    v = np.vstack([v, [[0.5, -0.5, -0.5]]])
    return v, np.vstack([f, [[0, 1, 8]]])  # a third face on the cube edge 0-1


def _bowtie():
    a = tetra()
    b_v = np.array([[0, 0, 0], [1, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=float)
    b_f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]], dtype=np.int64)
    return join(a, (b_v, b_f))  # edge (0,0,0)-(1,0,0) is shared by 4 faces once merged


def _pinch():
    return join(cube(), cube((1, 1, 1), (2, 2, 2)))  # touch at the vertex (1, 1, 1)


def _nested():
    outer = cube((0, 0, 0), (3, 3, 3))
    iv, jf = cube((1, 1, 1), (2, 2, 2))
    return join(outer, (iv, jf[:, ::-1]))  # a hollow box: two shells


def _inside_out():
    v, f = cube()
    return v, f[:, ::-1]


def _mixed_orientation():
    v, f = cube()
    f = f.copy()
    f[[1, 4, 7]] = f[[1, 4, 7], ::-1]
    return v, f


def _ascii_ply(v, f) -> bytes:
    header = (
        "ply\nformat ascii 1.0\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    body = "".join(f"{a} {b} {c}\n" for a, b, c in v) + "".join(f"3 {a} {b} {c}\n" for a, b, c in f)
    return (header + body).encode()


def _obj_text_with(mesh, row: int, coords: str) -> str:
    v, f = mesh
    lines = [f"v {x} {y} {z}" if i != row else f"v {coords}" for i, (x, y, z) in enumerate(v.tolist())]
    lines += ["f " + " ".join(str(i + 1) for i in face) for face in f.tolist()]
    return "\n".join(lines) + "\n"


def _off_bytes(v, f) -> bytes:
    lines = ["OFF", f"{len(v)} {len(f)} 0"] + [f"{a} {b} {c}" for a, b, c in v] + [f"3 {a} {b} {c}" for a, b, c in f]
    return ("\n".join(lines) + "\n").encode()


def _ply_binary_cube() -> bytes:
    return trimesh_bytes(*cube(), "ply")


# ---------------------------------------------------------------------------------------------
# the cases
# ---------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Case:
    """One corpus file.

    ``write(path)`` creates it (None: deliberately absent); ``error`` is the exact class
    ``load_part`` must raise (None: it must load); ``repair`` a word expected in the repairs;
    ``kwargs`` the ``load_part`` keywords.
    """

    name: str
    error: type[PartError] | None
    description: str
    write: Callable[[Path], None] | None
    kwargs: dict = dataclasses.field(default_factory=dict)
    repair: str | None = None


def _bytes(data_fn):
    return lambda p: p.write_bytes(data_fn())


def _cut(data_fn, frac: float):
    def write(p: Path):
        data = data_fn()
        p.write_bytes(data[: int(len(data) * frac)])

    return write


BAD_CASES: list[Case] = [
    # files that are not there, empty, cut or garbage
    Case("missing.stl", UnreadableFileError, "file does not exist", None),
    Case("empty.stl", UnreadableFileError, "0-byte STL", lambda p: p.write_bytes(b"")),
    Case("empty.obj", UnreadableFileError, "0-byte OBJ", lambda p: p.write_bytes(b"")),
    Case("empty.ply", UnreadableFileError, "0-byte PLY", lambda p: p.write_bytes(b"")),
    Case("empty.off", UnreadableFileError, "0-byte OFF", lambda p: p.write_bytes(b"")),
    Case("empty.glb", UnreadableFileError, "0-byte GLB", lambda p: p.write_bytes(b"")),
    Case("empty.step", UnreadableFileError, "0-byte STEP", lambda p: p.write_bytes(b"")),
    Case("empty.igs", UnreadableFileError, "0-byte IGES", lambda p: p.write_bytes(b"")),
    Case(
        "truncated_binary.stl",
        UnreadableFileError,
        "binary STL cut in the middle",
        _cut(lambda: stl_bytes(*cube()), 0.6),
    ),
    Case(
        "truncated_ascii.stl",
        UnreadableFileError,
        "ASCII STL without its end",
        _cut(lambda: trimesh_bytes(*cube(), "stl_ascii"), 0.5),
    ),
    Case("truncated.ply", UnreadableFileError, "binary PLY cut short", _cut(_ply_binary_cube, 0.8)),
    Case(
        "truncated_ascii.ply",
        UnreadableFileError,
        "ASCII PLY missing its last faces",
        _cut(lambda: _ascii_ply(*cube()), 0.9),
    ),
    Case(
        "truncated.off",
        UnreadableFileError,
        "OFF with fewer lines than its header announces",
        _cut(lambda: _off_bytes(*cube()), 0.7),
    ),
    Case(
        "truncated.glb",
        UnreadableFileError,
        "GLB shorter than its header says",
        _cut(lambda: trimesh_bytes(*cube(), "glb"), 0.7),
    ),
    Case(
        "truncated.step",
        UnreadableFileError,
        "STEP cut in the middle of its DATA section",
        _cut(lambda: cad_box_bytes("step"), 0.5),
    ),
    Case(
        "truncated.iges",
        UnreadableFileError,
        "IGES without its terminate line",
        _cut(lambda: cad_box_bytes("iges"), 0.6),
    ),
    Case("garbage.stl", UnreadableFileError, "random bytes named .stl", _bytes(lambda: _garbage(1))),
    Case("garbage.obj", UnreadableFileError, "random bytes named .obj", _bytes(lambda: _garbage(2))),
    Case("garbage.step", UnreadableFileError, "random bytes named .step", _bytes(lambda: _garbage(3))),
    Case("garbage.off", UnreadableFileError, "random bytes named .off", _bytes(lambda: _garbage(4))),
    Case(
        "text.ply", UnreadableFileError, "a text note named .ply", lambda p: p.write_text("not a mesh, just a note\n")
    ),
    Case("ply_named.stl", UnreadableFileError, "a PLY file with an .stl extension", _bytes(_ply_binary_cube)),
    Case(
        "stl_named.off", UnreadableFileError, "a binary STL with an .off extension", _bytes(lambda: stl_bytes(*cube()))
    ),
    Case("obj_named.step", UnreadableFileError, "an OBJ file with a .step extension", lambda p: write_obj(p, *cube())),
    Case(
        "step_named.obj",
        UnreadableFileError,
        "a STEP file with an .obj extension",
        _bytes(lambda: cad_box_bytes("step")),
    ),
    Case(
        "index_out_of_range.obj",
        UnreadableFileError,
        "OBJ face refers to vertex 99 of 8",
        lambda p: write_obj(p, *cube(), extra="f 1 2 99\n"),
    ),
    Case(
        "index_out_of_range.off",
        UnreadableFileError,
        "OFF face refers to vertex 42 of 8",
        lambda p: write_off(p, cube()[0], cube()[1].tolist()[:-1] + [[0, 1, 42]]),
    ),
    Case(
        "bad_number.stl",
        UnreadableFileError,
        "ASCII STL with a non-numeric coordinate",
        lambda p: p.write_bytes(trimesh_bytes(*cube(), "stl_ascii").replace(b"vertex", b"vertex x", 1)),
    ),
    # unknown formats
    Case(
        "points.xyz",
        UnknownFormatError,
        "a point cloud format we do not read",
        lambda p: p.write_text("0 0 0\n1 0 0\n"),
    ),
    Case("drawing.dwg", UnknownFormatError, "an AutoCAD drawing", _bytes(lambda: _garbage(5, 200))),
    Case("noext", UnknownFormatError, "a file without an extension", _bytes(lambda: stl_bytes(*cube()))),
    # faces that are not triangles
    Case(
        "line_face.off",
        NotTriangularError,
        "OFF with a 2-vertex face",
        lambda p: write_off(p, cube()[0], cube()[1].tolist() + [[0, 7]]),
    ),
    Case(
        "line_face.obj",
        NotTriangularError,
        "OBJ with a 2-vertex face",
        lambda p: write_obj(p, *cube(), extra="f 1 8\n"),
    ),
    # coordinates
    Case(
        "nan_vertex.off",
        InvalidCoordinatesError,
        "a NaN coordinate",
        lambda p: write_off(p, np.vstack([cube()[0][:7], [[np.nan, 1, 1]]]), cube()[1].tolist()),
    ),
    Case(
        "inf_vertex.stl",
        InvalidCoordinatesError,
        "an infinite coordinate",
        lambda p: write_stl(p, np.vstack([cube()[0][:7], [[np.inf, 1, 1]]]), cube()[1]),
    ),
    Case(
        "nan_vertex.obj",
        InvalidCoordinatesError,
        "a 'nan' coordinate in an OBJ",
        lambda p: p.write_text(_obj_text_with(cube(), 3, "nan 1 1")),
    ),
    # nothing to mesh
    Case(
        "no_faces.obj",
        EmptyMeshError,
        "OBJ with vertices only",
        lambda p: write_obj(p, cube()[0], np.zeros((0, 3), int)),
    ),
    Case("no_faces.off", EmptyMeshError, "OFF with zero faces", lambda p: write_off(p, cube()[0], [])),
    Case(
        "no_facets.stl",
        EmptyMeshError,
        "ASCII STL with no facets",
        lambda p: p.write_text("solid nothing\nendsolid nothing\n"),
    ),
    Case(
        "all_degenerate.stl",
        EmptyMeshError,
        "every triangle has zero area",
        lambda p: write_stl(
            p, np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 1, 0]])
        ),
    ),
    Case("no_solids.step", EmptyMeshError, "valid STEP header, no shapes", lambda p: p.write_text(EMPTY_STEP)),
    # open, non-manifold, non-orientable
    Case("open_cube.stl", OpenBoundaryError, "a cube with one face missing", lambda p: write_stl(p, *_open_cube())),
    Case(
        "mobius.obj", OpenBoundaryError, "a Möbius strip (open and non-orientable)", lambda p: write_obj(p, *mobius())
    ),
    Case("single_triangle.off", OpenBoundaryError, "one triangle", lambda p: write_off(p, tetra()[0][:3], [[0, 1, 2]])),
    Case(
        "bowtie_edge.obj",
        NonManifoldError,
        "two tetrahedra sharing an edge (4 faces on it)",
        lambda p: write_obj(p, *_bowtie()),
    ),
    Case(
        "fin_edge.off",
        NonManifoldError,
        "a cube with a fin: three faces on an edge",
        lambda p: write_off(p, _fin()[0], _fin()[1].tolist()),
    ),
    Case(
        "double_wall.stl",
        NonManifoldError,
        "a cube with a face duplicated back to back",
        lambda p: write_stl(p, cube()[0], np.vstack([cube()[1], cube()[1][:2, ::-1]])),
    ),
    Case("pinch_vertex.stl", NonManifoldError, "two cubes touching at one vertex", lambda p: write_stl(p, *_pinch())),
    Case(
        "klein_bottle.obj", NonManifoldError, "a closed non-orientable surface", lambda p: write_obj(p, *klein_bottle())
    ),
    # components, volume, size
    Case(
        "two_boxes.stl",
        MultipleComponentsError,
        "two disjoint boxes",
        lambda p: write_stl(p, *join(cube(), cube((2, 0, 0), (3, 2, 2)))),
    ),
    Case(
        "overlapping_boxes.stl",
        SelfIntersectionError,
        "two closed boxes that overlap (one surface crossing the other)",
        lambda p: write_stl(p, *join(cube(), cube((0.5, 0.5, 0.5), (1.5, 1.5, 1.5)))),
    ),
    Case(
        "hollow_box.obj",
        MultipleComponentsError,
        "a box with an internal void (two shells)",
        lambda p: write_obj(p, *_nested()),
    ),
    Case(
        "flat_double_sided.off",
        DegenerateVolumeError,
        "a closed two-sided flat square (volume 0)",
        lambda p: write_off(p, *_flat_double_sided()),
    ),
    Case(
        "flat_tetra.stl",
        DegenerateVolumeError,
        "a tetrahedron squashed flat (coplanar vertices)",
        lambda p: write_stl(p, np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, 0]], float), tetra()[1]),
    ),
    Case(
        "one_point.obj",
        DegenerateVolumeError,
        "every vertex at the same point",
        lambda p: write_obj(p, np.zeros((4, 3)), tetra()[1]),
    ),
    Case(
        "too_many_faces.stl",
        TooLargeError,
        "12 faces with max_faces=10 (header check)",
        lambda p: write_stl(p, *cube()),
        kwargs={"max_faces": 10},
    ),
    Case(
        "too_many_faces.obj",
        TooLargeError,
        "12 faces with max_faces=10 (line count)",
        lambda p: write_obj(p, *cube()),
        kwargs={"max_faces": 10},
    ),
    Case(
        "too_fine.step",
        TooLargeError,
        "a CAD box whose requested mesh size gives too many triangles",
        _bytes(lambda: cad_box_bytes("step")),
        kwargs={"max_faces": 1000, "mesh_size": 0.1},
    ),
]


def _dup_vertices_obj(p: Path) -> None:
    v, f = cube()
    write_obj(p, v[f].reshape(-1, 3), np.arange(36).reshape(12, 3))  # every corner repeated


def _quads_off(p: Path) -> None:
    v, _ = cube()
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    write_off(p, v, quads)


REPAIR_CASES: list[Case] = [
    Case(
        "inside_out.stl",
        None,
        "a cube with every face reversed",
        lambda p: write_stl(p, *_inside_out()),
        repair="inside-out",
    ),
    Case(
        "mixed_orientation.obj",
        None,
        "a cube with three faces reversed",
        lambda p: write_obj(p, *_mixed_orientation()),
        repair="reoriented 3",
    ),
    Case(
        "duplicate_vertices.obj",
        None,
        "a cube whose corners are listed once per face",
        _dup_vertices_obj,
        repair="merged",
    ),
    Case(
        "degenerate_face.obj",
        None,
        "a cube plus a face with a repeated vertex",
        lambda p: write_obj(p, *cube(), extra="f 1 1 2\n"),
        repair="degenerate",
    ),
    Case(
        "sliver_face.off",
        None,
        "a cube plus a zero-area face on three collinear points",
        lambda p: write_off(p, np.vstack([cube()[0], [[0.5, 0, 0]]]), cube()[1].tolist() + [[0, 8, 4]]),
        repair="degenerate",
    ),
    Case(
        "duplicate_face.stl",
        None,
        "a cube with a face listed twice",
        lambda p: write_stl(p, cube()[0], np.vstack([cube()[1], cube()[1][:1]])),
        repair="duplicate faces",
    ),
    Case(
        "unused_vertex.obj",
        None,
        "a cube plus a vertex no face uses",
        lambda p: write_obj(p, np.vstack([cube()[0], [[5, 5, 5]]]), cube()[1]),
        repair="unreferenced",
    ),
    Case("quads.off", None, "a cube of quads", _quads_off, repair="triangulated 6"),
    Case(
        "two_boxes_keep.stl",
        None,
        "two disjoint boxes, keep_largest=True",
        lambda p: write_stl(p, *join(cube(), cube((2, 0, 0), (3, 2, 2)))),
        kwargs={"keep_largest": True},
        repair="largest of 2",
    ),
]


def _write(cases: list[Case], folder: str | Path) -> list[Path]:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for case in cases:
        path = folder / case.name
        if case.write is not None:
            case.write(path)
        paths.append(path)
    return paths


def make_corpus(folder: str | Path) -> list[tuple[Path, type[PartError], str]]:
    """Write every bad input into ``folder``.

    Returns
    -------
    list of (path, error class, description)
        ``load_part(path, **load_kwargs(path))`` must raise exactly that class, with the
        file name in the message.
    """
    paths = _write(BAD_CASES, folder)
    return [(p, c.error, c.description) for p, c in zip(paths, BAD_CASES, strict=True)]


def make_repairable(folder: str | Path) -> list[tuple[Path, str, str]]:
    """Write the inputs that load after a safe repair.

    Returns
    -------
    list of (path, word expected in ``meta["repairs"]``, description)
    """
    paths = _write(REPAIR_CASES, folder)
    return [(p, c.repair, c.description) for p, c in zip(paths, REPAIR_CASES, strict=True)]


def load_kwargs(path: str | Path) -> dict:
    """The ``load_part`` keywords a corpus file needs (by file name; usually none)."""
    name = Path(path).name
    for case in BAD_CASES + REPAIR_CASES:
        if case.name == name:
            return dict(case.kwargs)
    return {}


if __name__ == "__main__":  # write the corpus for a look, and show what load_part says
    from polycubenet.io import load_part

    out = Path(sys.argv[1] if len(sys.argv) > 1 else "bad_inputs")
    for path, error, description in make_corpus(out):
        try:
            load_part(path, **load_kwargs(path))
            got = "LOADED"
        except PartError as exc:
            got = f"{type(exc).__name__}: {exc}"
        print(f"{'ok ' if got.startswith(error.__name__ + ':') else 'BAD'} {description:<60} {got}")
    for path, repair, description in make_repairable(out):
        part = load_part(path, **load_kwargs(path))
        ok = any(repair in r for r in part.meta["repairs"])
        print(f"{'ok ' if ok else 'BAD'} {description:<60} {part.meta['repairs']}")
