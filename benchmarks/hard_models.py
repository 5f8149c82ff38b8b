"""Hard CAD models for the mesher (issue 15): features the example parts do not have.

Each model is built by one function with gmsh's OpenCASCADE kernel (millimetres,
deterministic: the STEP header timestamp is fixed by ``make_examples.build_step``), written
as STEP, read back by gmsh (exactly one solid) and loaded by ``polycubenet.io.load_part``
(a closed, valid surface with the intended genus).  The features: slanted faces meeting at
high-valence corners, thin walls, a step inside a through-hole, a twisted hole, helical
grooves and ridges, many small holes, a wedge cut, a ring with an inner step, fillets on
every edge, a gusset, curved tubes and caps.

    python benchmarks/hard_models.py [--out DIR] [--models NAME ...]

prints one line per model (name, genus, volume, description).  ``make_all(folder)`` is what
``benchmarks/bench_classical.py --sets hard`` calls; its default folder
``benchmarks/results/hard_models/`` is ignored by git (the STEP files are regenerated, not
committed).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for _p in (ROOT, ROOT / "scripts"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from make_examples import E, Spec, _cut, _fuse, _only_volume, build_step  # noqa: E402

DEFAULT_OUT = ROOT / "benchmarks" / "results" / "hard_models"


# ---------------------------------------------------------------------------------------------
# helpers on the OpenCASCADE model
# ---------------------------------------------------------------------------------------------


def _unit(v):
    n = math.sqrt(sum(c * c for c in v))
    return tuple(c / n for c in v)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _half_space(occ, point, normal, size: float = 1000.0):
    """A big box filling the side of the plane through ``point`` that ``normal`` points to (a cut tool)."""
    n = _unit(normal)
    b = occ.addBox(-size / 2, -size / 2, 0, size, size, size)  # the half-space z > 0, bounded
    axis = _cross((0.0, 0.0, 1.0), n)
    s, c = math.sqrt(sum(a * a for a in axis)), n[2]
    if s > 1e-12:
        occ.rotate([(3, b)], 0, 0, 0, *axis, math.atan2(s, c))
    elif c < 0:
        occ.rotate([(3, b)], 0, 0, 0, 1, 0, 0, math.pi)
    occ.translate([(3, b)], *point)
    return (3, b)


def _plane_normal(p, q, r, away_from):
    """The normal of the plane through p, q, r, oriented to point away from ``away_from``."""
    n = _cross(tuple(b - a for a, b in zip(p, q)), tuple(b - a for a, b in zip(p, r)))
    if sum(c * (x - y) for c, x, y in zip(n, away_from, p)) > 0:
        n = tuple(-c for c in n)
    return n


def _polyhedron(occ, points, faces) -> int:
    """A solid bounded by planar polygons ``faces`` (lists of indices into ``points``)."""
    ptag = [occ.addPoint(*p) for p in points]
    lines: dict = {}
    surfaces = []
    for f in faces:
        loop = []
        for a, b in zip(f, f[1:] + f[:1]):
            key = (min(a, b), max(a, b))
            if key not in lines:
                lines[key] = occ.addLine(ptag[key[0]], ptag[key[1]])
            loop.append(lines[key] if (a, b) == key else -lines[key])
        surfaces.append(occ.addPlaneSurface([occ.addCurveLoop(loop)]))
    return occ.addVolume([occ.addSurfaceLoop(surfaces)])


def _helix_tube(occ, radius, pitch, z0, turns, r_tube, phase=0.0, per_turn=24):
    """A tube of circular section ``r_tube`` swept along a helix (axis z, through (radius, 0, z0)
    rotated by ``phase``) of ``turns`` turns: an interpolating spline through the helix points,
    the disc at its start normal to it, swept with the Frenet trihedron (the section keeps
    facing the axis)."""
    n = int(round(turns * per_turn))
    pts = []
    for k in range(n + 1):
        t = phase + 2 * math.pi * turns * k / n
        pts.append(occ.addPoint(radius * math.cos(t), radius * math.sin(t), z0 + pitch * turns * k / n))
    wire = occ.addWire([occ.addSpline(pts)])
    c, s = math.cos(phase), math.sin(phase)
    tangent = _unit((-radius * s * 2 * math.pi, radius * c * 2 * math.pi, pitch))
    disk = occ.addDisk(radius * c, radius * s, z0, r_tube, r_tube, zAxis=list(tangent), xAxis=[c, s, 0.0])
    out = occ.addPipe([(2, disk)], wire, "Frenet")
    occ.synchronize()
    return [dt for dt in out if dt[0] == 3]


def _square_wire(occ, half, angle, z, cx=0.0, cy=0.0) -> int:
    c, s = math.cos(angle), math.sin(angle)
    corners = [(-half, -half), (half, -half), (half, half), (-half, half)]
    pts = [occ.addPoint(cx + c * x - s * y, cy + s * x + c * y, z) for x, y in corners]
    return occ.addCurveLoop([occ.addLine(pts[i], pts[(i + 1) % 4]) for i in range(4)])


# ---------------------------------------------------------------------------------------------
# the models (millimetres)
# ---------------------------------------------------------------------------------------------


def pyramid_block(occ):
    """Block 60x60x30 topped by a pyramid to a single apex (valence-4 corner of slanted faces)."""
    a, h, top = 60.0, 30.0, 25.0
    pts = [(0, 0, 0), (a, 0, 0), (a, a, 0), (0, a, 0), (0, 0, h), (a, 0, h), (a, a, h), (0, a, h),
           (a / 2, a / 2, h + top)]
    faces = [[0, 3, 2, 1], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7],
             [4, 5, 8], [5, 6, 8], [6, 7, 8], [7, 4, 8]]
    _polyhedron(occ, pts, faces)


def three_cut_corner(occ):
    """Box 70x55x45 whose top corner is cut by three slanted planes meeting at one vertex."""
    occ.addBox(0, 0, 0, 70, 55, 45)
    q = (50.0, 37.0, 30.0)
    _cut(occ, [_half_space(occ, q, n) for n in ((3, 1, 1), (1, 3, 1), (1, 1, 3))])


def thin_tray(occ):
    """Open box (tray) 90x60x40 with 5 mm walls and floor (wall ~ 1/15 of its width)."""
    t = 5.0
    occ.addBox(0, 0, 0, 90, 60, 40)
    _cut(occ, [(3, occ.addBox(t, t, t, 90 - 2 * t, 60 - 2 * t, 40))])


def thin_u_channel(occ):
    """Long thin U-channel 120x45x30 with 3 mm walls."""
    t = 3.0
    occ.addBox(0, 0, 0, 120, 45, 30)
    _cut(occ, [(3, occ.addBox(-1, t, t, 122, 45 - 2 * t, 30))])


def counterbore(occ):
    """Block 60x60x30 with a counterbored through-hole (bore r 11 x 12 deep, then r 5.5 through)."""
    occ.addBox(0, 0, 0, 60, 60, 30)
    _cut(occ, [(3, occ.addCylinder(30, 30, 18, 0, 0, 13, 11)), (3, occ.addCylinder(30, 30, -1, 0, 0, 32, 5.5))])


def twisted_hole(occ):
    """Block 60x60x40 with a 18x18 square hole twisted by 90 degrees through it (lofted sections)."""
    h, twist, n = 40.0, math.pi / 2, 9
    z0, z1 = -4.0, h + 4.0
    wires = [_square_wire(occ, 9.0, twist * (z - 0) / h, z, 30, 30)
             for z in (z0 + (z1 - z0) * k / (n - 1) for k in range(n))]
    tool = occ.addThruSections(wires, makeSolid=True, makeRuled=False)
    block = occ.addBox(0, 0, 0, 60, 60, h)
    occ.cut([(3, block)], [dt for dt in tool if dt[0] == 3])
    occ.synchronize()


def helical_groove(occ):
    """Cylinder r 20 x 80 with a helical groove (r 3 section, pitch 20, 3 turns) cut into its side."""
    occ.addCylinder(0, 0, 0, 0, 0, 80, 20)
    _cut(occ, _helix_tube(occ, 20.0, 20.0, 10.0, 3.0, 3.0))


def threaded_rod(occ):
    """Rod r 12 x 80 with two helical ridges fused on (r 2.5 section, pitch 24, 2.5 turns each)."""
    rod = occ.addCylinder(0, 0, 0, 0, 0, 80, 12)
    ridges = _helix_tube(occ, 12.0, 24.0, 10.0, 2.5, 2.5) + _helix_tube(occ, 12.0, 24.0, 10.0, 2.5, 2.5, phase=math.pi)
    occ.fuse([(3, rod)], ridges)
    occ.synchronize()


def perforated_plate(occ):
    """Plate 120x90x8 with a 4x3 grid of round holes r 4."""
    occ.addBox(0, 0, 0, 120, 90, 8)
    _cut(occ, [(3, occ.addCylinder(x, y, -1, 0, 0, 10, 4)) for x in (21, 47, 73, 99) for y in (20, 45, 70)])


def wedge_cut(occ):
    """Box 80x50x40 with one top corner cut away by a slanted plane (a triangular face)."""
    occ.addBox(0, 0, 0, 80, 50, 40)
    p, q, r = (45.0, 50.0, 40.0), (80.0, 20.0, 40.0), (80.0, 50.0, 12.0)
    _cut(occ, [_half_space(occ, p, _plane_normal(p, q, r, away_from=(0, 0, 0)))])


def stepped_ring(occ):
    """Ring r 40 / 25 x 24 high with a step on its inner face (bore r 25 below, r 31 above z 12)."""
    occ.addCylinder(0, 0, 0, 0, 0, 24, 40)
    _cut(occ, [(3, occ.addCylinder(0, 0, -1, 0, 0, 26, 25)), (3, occ.addCylinder(0, 0, 12, 0, 0, 13, 31))])


def filleted_block(occ):
    """Block 60x45x30 with a through-hole r 8, every edge (outer and the hole's) filleted r 3."""
    occ.addBox(0, 0, 0, 60, 45, 30)
    _cut(occ, [(3, occ.addCylinder(30, 22.5, -1, 0, 0, 32, 8))])
    vol = _only_volume(occ)
    edges = [t for _, t in occ.getEntities(1)]
    occ.fillet([vol], edges, [3.0], removeVolume=True)
    occ.synchronize()


def gusset_bracket(occ):
    """L-bracket (base 80x60x8, upright 8x60x60) with a triangular rib (gusset) in its middle."""
    base = occ.addBox(0, 0, 0, 80, 60, 8)
    upright = occ.addBox(0, 0, 0, 8, 60, 60)
    y0, y1 = 26.0, 34.0  # rib 8 thick; it overlaps the plates by 1 mm so the fuse is clean
    prof = [(7, 7), (50, 7), (7, 50)]
    pts = [(x, y0, z) for x, z in prof] + [(x, y1, z) for x, z in prof]
    rib = _polyhedron(occ, pts, [[0, 2, 1], [3, 4, 5], [0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]])
    occ.fuse([(3, base)], [(3, upright), (3, rib)])
    occ.synchronize()


def tube_elbow(occ):
    """90-degree tube elbow: outer r 10, bore r 6, bend radius 40, 30 mm straight legs."""
    R, L = 40.0, 30.0

    def body(r, extra):
        t = occ.addTorus(0, 0, 0, R, r, angle=math.pi / 2)
        a = occ.addCylinder(R, extra, 0, 0, -L - 2 * extra, 0, r)
        b = occ.addCylinder(extra, R, 0, -L - 2 * extra, 0, 0, r)
        out, _ = occ.fuse([(3, t)], [(3, a), (3, b)])
        return out

    outer = body(10.0, 0.0)
    inner = body(6.0, 1.0)
    occ.cut(outer, inner)
    occ.synchronize()


def capsule_post(occ):
    """Post r 15: a cylinder 50 long on a flat base, capped by a hemisphere (curved, smooth seam)."""
    cyl = occ.addCylinder(0, 0, 0, 0, 0, 50, 15)
    cap = occ.addSphere(0, 0, 50, 15)
    occ.fuse([(3, cyl)], [(3, cap)])
    occ.synchronize()


SPECS = [
    Spec("pyramid_block", 0, "block with a pyramid top: four slanted faces meet at one apex", pyramid_block),
    Spec("three_cut_corner", 0, "box corner cut by three slanted planes meeting at one vertex", three_cut_corner),
    Spec("thin_tray", 0, "open box 90x60x40, 5 mm walls and floor", thin_tray),
    Spec("thin_u_channel", 0, "thin U-channel 120x45x30, 3 mm walls", thin_u_channel),
    Spec("counterbore", 1, "block with a counterbored through-hole (step inside the hole)", counterbore),
    Spec("twisted_hole", 1, "block with a square hole twisted 90 degrees through it", twisted_hole),
    Spec("helical_groove", 0, "cylinder with a 3-turn helical groove in its side", helical_groove),
    Spec("threaded_rod", 0, "rod with two helical ridges (double-start thread)", threaded_rod),
    Spec("perforated_plate", 12, "plate with a 4x3 grid of small round holes", perforated_plate),
    Spec("wedge_cut", 0, "box with a top corner cut away by one slanted plane", wedge_cut),
    Spec("stepped_ring", 1, "ring with a step on its inner face", stepped_ring),
    Spec("filleted_block", 1, "block with a through-hole, every edge filleted", filleted_block),
    Spec("gusset_bracket", 0, "L-bracket with a triangular rib (slanted face)", gusset_bracket),
    Spec("tube_elbow", 1, "90-degree tube elbow with straight legs", tube_elbow),
    Spec("capsule_post", 0, "cylinder with a hemispherical cap on a flat base", capsule_post),
]
BY_NAME = {s.name: s for s in SPECS}


def _check_step(path: Path) -> float:
    """gmsh re-imports ``path`` as exactly one solid; returns its volume (mm^3)."""
    from polycubenet.io import gmsh_session, quiet_stdout

    with gmsh_session() as gmsh:
        gmsh.model.add(f"check-{path.stem}")
        try:
            with quiet_stdout():
                gmsh.model.occ.importShapes(str(path))
            gmsh.model.occ.synchronize()
            vols = gmsh.model.getEntities(3)
            if len(vols) != 1:
                raise RuntimeError(f"{path.name}: re-imported as {len(vols)} solids")
            return gmsh.model.occ.getMass(3, vols[0][1])
        finally:
            gmsh.model.remove()


def build(name: str, path: str | Path, check: bool = True) -> dict:
    """Write model ``name`` to the STEP file ``path``; with ``check``, re-import it with gmsh
    (one solid) and load it with ``polycubenet.io.load_part`` (closed, genus as intended).
    Returns ``{name, description, genus, volume, path}`` (volume of the B-rep, mm^3)."""
    spec = BY_NAME[name]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    build_step(spec, path)
    row = {"name": name, "description": spec.description, "genus": spec.genus, "path": str(path), "volume": None}
    if check:
        from polycubenet.io import load_part

        row["volume"] = _check_step(path)
        meta = load_part(path).meta
        if meta["genus"] != spec.genus:
            raise RuntimeError(f"{name}: loaded with genus {meta['genus']}, intended {spec.genus}")
        if abs(meta["volume"] - row["volume"]) > 0.02 * row["volume"]:
            raise RuntimeError(f"{name}: surface volume {meta['volume']:.0f} vs B-rep {row['volume']:.0f}")
        row["triangles"] = meta["n_faces"]
    return row


def make_all(folder: str | Path = DEFAULT_OUT, names=None, check: bool = True, verbose: bool = False) -> list[Path]:
    """Write every model (or those in ``names``) as ``<folder>/<name>.step``; returns the paths.
    The files are rebuilt every time (a few seconds; the bytes are the same each run)."""
    folder = Path(folder)
    paths = []
    for spec in SPECS:
        if names and spec.name not in names:
            continue
        row = build(spec.name, folder / f"{spec.name}.step", check=check)
        if verbose:
            vol = "-" if row["volume"] is None else f"{row['volume']:.0f}"
            print(f"{spec.name:<18} genus {spec.genus:>2}  volume {vol:>9} mm^3  {spec.description}", flush=True)
        paths.append(Path(row["path"]))
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--models", nargs="*", default=None, choices=list(BY_NAME))
    args = ap.parse_args(argv)
    paths = make_all(args.out, args.models, verbose=True)
    print(f"wrote {len(paths)} models to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
