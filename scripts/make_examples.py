"""Generate the example CAD parts in ``examples/parts/`` with gmsh's OpenCASCADE kernel.

Each part is a machined-looking solid built from boxes and cylinders with boolean cuts and
fuses, fillets and chamfers.  For each we write

- ``<name>.step``: the exact B-rep (the timestamp in its header is fixed, so regenerating
  gives the same bytes);
- ``<name>.stl``: a binary STL of the surface as ``polycubenet.io.load_part`` meshes it
  (outward, closed), at a mesh size chosen for roughly ``--triangles`` triangles;

then load both files back with ``load_part`` and check that the genus is the intended one,
and write ``README.md`` with the table.  Usage::

    python scripts/make_examples.py [--out examples/parts] [--triangles 5000]
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from collections.abc import Callable

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from polycubenet.atomic import write_text  # noqa: E402
from polycubenet.io import gmsh_session, load_part, quiet_stdout, write_surface  # noqa: E402


@dataclass(frozen=True)
class Spec:
    name: str
    genus: int
    description: str
    build: Callable  # build(occ) -> None; leaves exactly one volume in the model


# ---------------------------------------------------------------------------------------------
# helpers on the OpenCASCADE model
# ---------------------------------------------------------------------------------------------


def _edges_in(occ, box, dim=1):
    """Tags of the entities of ``dim`` inside the axis-aligned ``box`` (xmin, ymin, zmin, xmax, ymax, zmax)."""
    return [t for _, t in occ.getEntitiesInBoundingBox(*box, dim=dim)]


def _only_volume(occ) -> int:
    occ.synchronize()
    vols = occ.getEntities(3)
    if len(vols) != 1:
        raise RuntimeError(f"expected one volume, got {vols}")
    return vols[0][1]


def _fillet(occ, box, radius):
    vol = _only_volume(occ)
    edges = _edges_in(occ, box)
    if not edges:
        raise RuntimeError(f"no edge to fillet in {box}")
    occ.fillet([vol], edges, [radius], removeVolume=True)
    occ.synchronize()


def _chamfer(occ, box, distance):
    """Chamfer the edges inside ``box``, each measured on one of its adjacent faces."""
    import gmsh

    vol = _only_volume(occ)
    edges = _edges_in(occ, box)
    surfaces = []
    for e in edges:
        up, _ = gmsh.model.getAdjacencies(1, e)
        surfaces.append(int(up[0]))
    occ.chamfer([vol], edges, surfaces, [distance] * len(edges), removeVolume=True)
    occ.synchronize()


def _cut(occ, tool_dimtags):
    """Cut the tools out of the one other volume in the model."""
    occ.synchronize()
    objects = [dt for dt in occ.getEntities(3) if dt not in tool_dimtags]
    if len(objects) != 1:
        raise RuntimeError(f"expected one volume to cut from, got {objects}")
    occ.cut(objects, tool_dimtags)
    occ.synchronize()


def _fuse(occ, a, b):
    occ.fuse([(3, a)], [(3, b)])
    occ.synchronize()


# ---------------------------------------------------------------------------------------------
# the parts (millimetres)
# ---------------------------------------------------------------------------------------------

E = 0.5  # a little slack for bounding-box edge selection


def l_block(occ):
    _fuse(occ, occ.addBox(0, 0, 0, 60, 40, 20), occ.addBox(0, 0, 0, 20, 40, 60))
    _fillet(occ, (20 - E, -E, 20 - E, 20 + E, 40 + E, 20 + E), 6)  # the inner bend
    _chamfer(occ, (-E, -E, 60 - E, 20 + E, E, 60 + E), 3)  # one top edge


def u_channel(occ):
    occ.addBox(0, 0, 0, 90, 40, 30)
    _cut(occ, [(3, occ.addBox(-1, 8, 6, 92, 24, 30))])
    _fillet(occ, (-E, 8 - E, 6 - E, 90 + E, 8 + E, 6 + E), 3)
    _fillet(occ, (-E, 32 - E, 6 - E, 90 + E, 32 + E, 6 + E), 3)


def pocket_housing(occ):
    occ.addBox(0, 0, 0, 70, 50, 30)
    for x, y in [(0, 0), (70, 0), (70, 50), (0, 50)]:  # round the outer vertical edges
        _fillet(occ, (x - E, y - E, -E, x + E, y + E, 30 + E), 5)
    pocket = occ.addBox(10, 10, 12, 50, 30, 30)
    _cut(occ, [(3, pocket)])
    for x, y in [(10, 10), (60, 10), (60, 40), (10, 40)]:  # round the pocket's vertical edges
        _fillet(occ, (x - E, y - E, 12 - E, x + E, y + E, 30 + E), 4)


def t_slot_block(occ):
    occ.addBox(0, 0, 0, 80, 60, 40)
    _cut(occ, [(3, occ.addBox(-1, 23, 26, 82, 14, 20)), (3, occ.addBox(-1, 15, 12, 82, 30, 14))])
    _chamfer(occ, (-E, -E, 40 - E, 80 + E, E, 40 + E), 3)
    _chamfer(occ, (-E, 60 - E, 40 - E, 80 + E, 60 + E, 40 + E), 3)


def bushing(occ):
    _fuse(occ, occ.addCylinder(0, 0, 0, 0, 0, 8, 35), occ.addCylinder(0, 0, 0, 0, 0, 38, 20))
    _cut(occ, [(3, occ.addCylinder(0, 0, -1, 0, 0, 40, 10))])
    _fillet(occ, (-21, -21, 8 - E, 21, 21, 8 + E), 3)  # root of the sleeve on the flange


def stepped_shaft(occ):
    a = occ.addCylinder(0, 0, 0, 40, 0, 0, 15)
    b = occ.addCylinder(40, 0, 0, 30, 0, 0, 11)
    c = occ.addCylinder(70, 0, 0, 25, 0, 0, 8)
    occ.fuse([(3, a)], [(3, b), (3, c)])
    occ.synchronize()
    _cut(occ, [(3, occ.addCylinder(20, -20, 0, 0, 40, 0, 4))])  # a cross hole through the big step
    _chamfer(occ, (95 - E, -9, -9, 95 + E, 9, 9), 1.5)  # the free end


def clevis(occ):
    occ.addBox(0, 0, 0, 40, 40, 55)
    _cut(occ, [(3, occ.addBox(-1, 12, 20, 42, 16, 40))])  # the slot between the prongs
    _cut(occ, [(3, occ.addCylinder(20, -1, 40, 0, 42, 0, 5))])  # pin hole through both prongs
    for y in (0, 40):
        _fillet(occ, (-E, y - E, 55 - E, 40 + E, y + E, 55 + E), 4)


def bracket(occ):
    _fuse(occ, occ.addBox(0, 0, 0, 80, 50, 8), occ.addBox(0, 0, 0, 80, 8, 50))
    _fillet(occ, (-E, 8 - E, 8 - E, 80 + E, 8 + E, 8 + E), 6)  # inner bend
    _cut(occ, [(3, occ.addCylinder(x, 32, -1, 0, 0, 10, 5)) for x in (20, 60)])  # base holes
    _cut(occ, [(3, occ.addCylinder(40, -1, 32, 0, 10, 0, 7))])  # upright hole


def plate_with_holes(occ):
    occ.addBox(0, 0, 0, 100, 70, 10)
    for x, y in [(0, 0), (100, 0), (100, 70), (0, 70)]:
        _fillet(occ, (x - E, y - E, -E, x + E, y + E, 10 + E), 8)
    _cut(occ, [(3, occ.addCylinder(x, y, -1, 0, 0, 12, 6)) for x in (20, 80) for y in (18, 52)])


def flange(occ):
    _fuse(occ, occ.addCylinder(0, 0, 0, 0, 0, 12, 50), occ.addCylinder(0, 0, 0, 0, 0, 30, 25))
    _fillet(occ, (-26, -26, 12 - E, 26, 26, 12 + E), 4)
    _cut(occ, [(3, occ.addCylinder(0, 0, -1, 0, 0, 32, 14))])  # central bore
    holes = [(38 * math.cos(a), 38 * math.sin(a)) for a in (math.pi / 4 + k * math.pi / 2 for k in range(4))]
    _cut(occ, [(3, occ.addCylinder(x, y, -1, 0, 0, 14, 5)) for x, y in holes])


SPECS = [
    Spec("l_block", 0, "L-shaped block, filleted inner bend, one chamfered edge", l_block),
    Spec("u_channel", 0, "U-channel with filleted inner corners", u_channel),
    Spec("pocket_housing", 0, "housing with a blind rectangular pocket (rounded corners)", pocket_housing),
    Spec("t_slot_block", 0, "block with a T-slot running through, chamfered top edges", t_slot_block),
    Spec("bushing", 1, "flanged bushing with a through bore", bushing),
    Spec("stepped_shaft", 1, "three-step shaft with a cross hole and a chamfered end", stepped_shaft),
    Spec("clevis", 2, "clevis: two prongs with a pin hole through both", clevis),
    Spec("bracket", 3, "L-bracket, filleted bend, two base holes and one upright hole", bracket),
    Spec("plate_with_holes", 4, "plate with rounded corners and four through holes", plate_with_holes),
    Spec("flange", 5, "flange: disc with a hub, a central bore and four bolt holes", flange),
]

_STEP_STAMP = re.compile(r"'\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d'")


def build_step(spec: Spec, path: Path) -> None:
    """Build the part in a fresh gmsh model and write it as STEP (with a fixed timestamp)."""
    with gmsh_session() as gmsh:
        gmsh.model.add(spec.name)
        try:
            spec.build(gmsh.model.occ)
            _only_volume(gmsh.model.occ)
            with quiet_stdout():
                gmsh.write(str(path))
        finally:
            gmsh.model.remove()
    text = _STEP_STAMP.sub("'2024-01-01T00:00:00'", path.read_text(), count=1)
    write_text(path, text)


def make_stl(step: Path, stl: Path, triangles: int) -> int:
    """Mesh the STEP through ``load_part`` at a size giving about ``triangles``; write a binary STL."""
    part = load_part(step)
    h = part.meta["mesh_size"]
    for _ in range(3):
        ratio = len(part.faces) / triangles
        if 0.7 < ratio < 1.4:
            break
        h *= math.sqrt(ratio)
        part = load_part(step, mesh_size=h)
    write_surface(part.vertices, part.faces, stl)
    return len(part.faces)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "examples" / "parts")
    ap.add_argument("--triangles", type=int, default=5000, help="approximate triangles per STL (default 5000)")
    args = ap.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)

    rows = []
    for spec in SPECS:
        step, stl = out / f"{spec.name}.step", out / f"{spec.name}.stl"
        build_step(spec, step)
        n_tri = make_stl(step, stl, args.triangles)
        got = {p.suffix: load_part(p).meta for p in (step, stl)}
        for suffix, meta in got.items():
            if meta["genus"] != spec.genus:
                raise SystemExit(f"{spec.name}{suffix}: genus {meta['genus']}, intended {spec.genus}")
        meta = got[".stl"]
        rows.append((spec, n_tri, meta["volume"], got[".step"]["bbox_diagonal"]))
        print(f"{spec.name:<18} genus {spec.genus}  {n_tri:>6} triangles  volume {meta['volume']:>10.1f} mm^3")

    size = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    lines = [
        "# Example parts",
        "",
        "CAD-like solids made with gmsh's OpenCASCADE kernel by `scripts/make_examples.py`",
        "(`make examples` regenerates them; units: millimetres). Each part comes as the exact B-rep",
        "(`.step`) and as a closed, outward-oriented triangle surface (`.stl`, binary) meshed by",
        "`polycubenet.io.load_part`. The script loads both files back and checks the genus.",
        "",
        "| name | description | genus | STL triangles | volume (mm³) | bbox diagonal (mm) |",
        "|---|---|---|---|---|---|",
    ]
    for spec, n_tri, volume, diag in rows:
        lines.append(f"| `{spec.name}` | {spec.description} | {spec.genus} | {n_tri} | {volume:.0f} | {diag:.1f} |")
    lines += ["", f"Total size of this folder: {(size + 4096) / 1e6:.1f} MB.", ""]
    write_text(out / "README.md", "\n".join(lines))
    size = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    print(f"wrote {len(rows)} parts to {out} ({size / 1e6:.2f} MB)")
    if size > 5e6:
        raise SystemExit(f"{out} is {size / 1e6:.1f} MB, over the 5 MB budget: lower --triangles")
    return 0


if __name__ == "__main__":
    sys.exit(main())
