"""Hard CAD models for the mesher (issue 15): features the example parts do not have.

Each model is built by one function with gmsh's OpenCASCADE kernel (millimetres,
deterministic: the STEP header timestamp is fixed by ``make_examples.build_step``), written
as STEP, read back by gmsh (exactly one solid) and loaded by ``polycubenet.io.load_part``
(a closed, valid surface with the intended genus).  The features: slanted faces meeting at
high-valence corners, thin walls, a step inside a through-hole, a twisted hole, helical
grooves and ridges, many small holes, a wedge cut, a ring with an inner step, fillets on
every edge, a gusset, curved tubes and caps.

The mesher is tuned on these 15 fixed models, so ``--seed N`` builds a second set that it has
never been tuned on: the same 15 families with other dimensions, each family drawing its
parameters from ``random.Random(f"{N}-{name}")`` within ranges that keep its character and
its genus (box sizes +-30 %, wall thickness, cut planes, hole sizes, twist angle, helix pitch,
turns and tube radius, 6-16 jittered holes in the plate, ...; see ``VARIANTS``).  Without a
seed the files are the fixed models, byte for byte.

    python benchmarks/hard_models.py [--out DIR] [--models NAME ...] [--seed N]

prints one line per model (name, genus, volume, description).  ``make_all(folder, seed=N)`` is
what ``benchmarks/bench_classical.py --sets hard [--hard-seed N]`` calls; its default folder
``benchmarks/results/hard_models/`` (``hard_models_seed<N>/`` for a seed) is ignored by git
(the STEP files are regenerated, not committed).
"""

from __future__ import annotations

import argparse
import functools
import math
import random
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
# the models (millimetres); the keyword arguments' defaults are the fixed set, a seed draws others
# ---------------------------------------------------------------------------------------------


def pyramid_block(occ, ax=60.0, ay=60.0, h=30.0, top=25.0, apex=(0.5, 0.5)):
    """Block 60x60x30 topped by a pyramid to a single apex (valence-4 corner of slanted faces)."""
    pts = [(0, 0, 0), (ax, 0, 0), (ax, ay, 0), (0, ay, 0), (0, 0, h), (ax, 0, h), (ax, ay, h), (0, ay, h),
           (ax * apex[0], ay * apex[1], h + top)]
    faces = [[0, 3, 2, 1], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7],
             [4, 5, 8], [5, 6, 8], [6, 7, 8], [7, 4, 8]]
    _polyhedron(occ, pts, faces)


def three_cut_corner(occ, size=(70.0, 55.0, 45.0), corner=(50.0, 37.0, 30.0),
                     normals=((3, 1, 1), (1, 3, 1), (1, 1, 3))):
    """Box 70x55x45 whose top corner is cut by three slanted planes meeting at one vertex."""
    occ.addBox(0, 0, 0, *size)
    _cut(occ, [_half_space(occ, corner, n) for n in normals])


def thin_tray(occ, lx=90.0, ly=60.0, lz=40.0, t=5.0):
    """Open box (tray) 90x60x40 with 5 mm walls and floor (wall ~ 1/15 of its width)."""
    occ.addBox(0, 0, 0, lx, ly, lz)
    _cut(occ, [(3, occ.addBox(t, t, t, lx - 2 * t, ly - 2 * t, lz))])


def thin_u_channel(occ, lx=120.0, ly=45.0, lz=30.0, t=3.0):
    """Long thin U-channel 120x45x30 with 3 mm walls."""
    occ.addBox(0, 0, 0, lx, ly, lz)
    _cut(occ, [(3, occ.addBox(-1, t, t, lx + 2, ly - 2 * t, lz))])


def counterbore(occ, a=60.0, b=60.0, h=30.0, r_bore=11.0, depth=12.0, r_hole=5.5):
    """Block 60x60x30 with a counterbored through-hole (bore r 11 x 12 deep, then r 5.5 through)."""
    occ.addBox(0, 0, 0, a, b, h)
    _cut(occ, [(3, occ.addCylinder(a / 2, b / 2, h - depth, 0, 0, depth + 1, r_bore)),
               (3, occ.addCylinder(a / 2, b / 2, -1, 0, 0, h + 2, r_hole))])


def twisted_hole(occ, a=60.0, b=60.0, h=40.0, half=9.0, twist=90.0):
    """Block 60x60x40 with a 18x18 square hole twisted by 90 degrees (``twist``) through it (lofted sections)."""
    twist, n = math.radians(twist), 9
    z0, z1 = -4.0, h + 4.0
    wires = [_square_wire(occ, half, twist * (z - 0) / h, z, a / 2, b / 2)
             for z in (z0 + (z1 - z0) * k / (n - 1) for k in range(n))]
    tool = occ.addThruSections(wires, makeSolid=True, makeRuled=False)
    block = occ.addBox(0, 0, 0, a, b, h)
    occ.cut([(3, block)], [dt for dt in tool if dt[0] == 3])
    occ.synchronize()


def helical_groove(occ, r=20.0, length=80.0, pitch=20.0, turns=3.0, r_tube=3.0, z0=10.0):
    """Cylinder r 20 x 80 with a helical groove (r 3 section, pitch 20, 3 turns) cut into its side."""
    occ.addCylinder(0, 0, 0, 0, 0, length, r)
    _cut(occ, _helix_tube(occ, r, pitch, z0, turns, r_tube))


def threaded_rod(occ, r=12.0, length=80.0, pitch=24.0, turns=2.5, r_tube=2.5, z0=10.0):
    """Rod r 12 x 80 with two helical ridges fused on (r 2.5 section, pitch 24, 2.5 turns each)."""
    rod = occ.addCylinder(0, 0, 0, 0, 0, length, r)
    ridges = (_helix_tube(occ, r, pitch, z0, turns, r_tube)
              + _helix_tube(occ, r, pitch, z0, turns, r_tube, phase=math.pi))
    occ.fuse([(3, rod)], ridges)
    occ.synchronize()


def perforated_plate(occ, lx=120.0, ly=90.0, t=8.0, r_hole=4.0,
                     holes=tuple((x, y) for x in (21, 47, 73, 99) for y in (20, 45, 70))):
    """Plate 120x90x8 with a 4x3 grid of round holes r 4 (``holes``: their centres; genus = their number)."""
    occ.addBox(0, 0, 0, lx, ly, t)
    _cut(occ, [(3, occ.addCylinder(x, y, -1, 0, 0, t + 2, r_hole)) for x, y in holes])


def wedge_cut(occ, size=(80.0, 50.0, 40.0), cut=(35.0, 30.0, 28.0)):
    """Box 80x50x40 with one top corner cut away by a slanted plane (a triangular face) through the
    three points at distances ``cut`` from that corner along its edges."""
    lx, ly, lz = size
    occ.addBox(0, 0, 0, lx, ly, lz)
    p, q, r = (lx - cut[0], ly, lz), (lx, ly - cut[1], lz), (lx, ly, lz - cut[2])
    _cut(occ, [_half_space(occ, p, _plane_normal(p, q, r, away_from=(0, 0, 0)))])


def stepped_ring(occ, r_out=40.0, r_in=25.0, h=24.0, r_step=31.0, z_step=12.0):
    """Ring r 40 / 25 x 24 high with a step on its inner face (bore r 25 below, r 31 above z 12)."""
    occ.addCylinder(0, 0, 0, 0, 0, h, r_out)
    _cut(occ, [(3, occ.addCylinder(0, 0, -1, 0, 0, h + 2, r_in)),
               (3, occ.addCylinder(0, 0, z_step, 0, 0, h - z_step + 1, r_step))])


def filleted_block(occ, a=60.0, b=45.0, h=30.0, r_hole=8.0, fillet=3.0):
    """Block 60x45x30 with a through-hole r 8, every edge (outer and the hole's) filleted r 3."""
    occ.addBox(0, 0, 0, a, b, h)
    _cut(occ, [(3, occ.addCylinder(a / 2, b / 2, -1, 0, 0, h + 2, r_hole))])
    vol = _only_volume(occ)
    edges = [t for _, t in occ.getEntities(1)]
    occ.fillet([vol], edges, [fillet], removeVolume=True)
    occ.synchronize()


def gusset_bracket(occ, lx=80.0, w=60.0, hz=60.0, t=8.0, rib_t=8.0, rib_x=43.0, rib_z=43.0):
    """L-bracket (base 80x60x8, upright 8x60x60) with a triangular rib (gusset, legs 43) in its middle."""
    base = occ.addBox(0, 0, 0, lx, w, t)
    upright = occ.addBox(0, 0, 0, t, w, hz)
    y0, y1 = w / 2 - rib_t / 2, w / 2 + rib_t / 2  # the rib overlaps the plates by 1 mm so the fuse is clean
    c = t - 1
    prof = [(c, c), (c + rib_x, c), (c, c + rib_z)]
    pts = [(x, y0, z) for x, z in prof] + [(x, y1, z) for x, z in prof]
    rib = _polyhedron(occ, pts, [[0, 2, 1], [3, 4, 5], [0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]])
    occ.fuse([(3, base)], [(3, upright), (3, rib)])
    occ.synchronize()


def tube_elbow(occ, R=40.0, L=30.0, r_out=10.0, r_in=6.0):
    """90-degree tube elbow: outer r 10, bore r 6, bend radius 40, 30 mm straight legs."""

    def body(r, extra):
        t = occ.addTorus(0, 0, 0, R, r, angle=math.pi / 2)
        a = occ.addCylinder(R, extra, 0, 0, -L - 2 * extra, 0, r)
        b = occ.addCylinder(extra, R, 0, -L - 2 * extra, 0, 0, r)
        out, _ = occ.fuse([(3, t)], [(3, a), (3, b)])
        return out

    outer = body(r_out, 0.0)
    inner = body(r_in, 1.0)
    occ.cut(outer, inner)
    occ.synchronize()


def capsule_post(occ, r=15.0, length=50.0):
    """Post r 15: a cylinder 50 long on a flat base, capped by a hemisphere (curved, smooth seam)."""
    cyl = occ.addCylinder(0, 0, 0, 0, 0, length, r)
    cap = occ.addSphere(0, 0, length, r)
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


# ---------------------------------------------------------------------------------------------
# seeded variants: the same 15 families with other dimensions (models never tuned on)
# ---------------------------------------------------------------------------------------------


def _u(rng, lo, hi, nd=1):
    return round(rng.uniform(lo, hi), nd)


def _dims(rng, *base, spread=0.3):
    """Each of ``base`` scaled by a factor in [1 - spread, 1 + spread], to 0.1 mm."""
    return tuple(_u(rng, b * (1 - spread), b * (1 + spread)) for b in base)


def _v_pyramid_block(g):
    ax, ay, h = _dims(g, 60, 60, 30)
    return dict(ax=ax, ay=ay, h=h, top=_u(g, 10, 45), apex=(_u(g, 0.35, 0.65, 2), _u(g, 0.35, 0.65, 2)))


def _v_three_cut_corner(g):
    size = _dims(g, 70, 55, 45)
    normals = tuple(tuple(_u(g, 2.4, 3.6) if i == j else _u(g, 0.6, 1.4) for j in range(3)) for i in range(3))
    return dict(size=size, corner=tuple(_u(g, 0.6 * s, 0.8 * s) for s in size), normals=normals)


def _v_thin_tray(g):
    return dict(zip(("lx", "ly", "lz"), _dims(g, 90, 60, 40)), t=_u(g, 2.5, 7))


def _v_thin_u_channel(g):
    return dict(zip(("lx", "ly", "lz"), _dims(g, 120, 45, 30)), t=_u(g, 2.5, 7))


def _v_counterbore(g):
    a, b, h = _dims(g, 60, 60, 30)
    r_hole = _u(g, 3, 8)
    r_bore = min(round(r_hole + g.uniform(3, 8), 1), min(a, b) / 2 - 4)
    return dict(a=a, b=b, h=h, r_bore=r_bore, depth=_u(g, 0.25 * h, 0.6 * h), r_hole=r_hole)


def _v_twisted_hole(g):
    a, b, h = _dims(g, 60, 60, 40)
    return dict(a=a, b=b, h=h, half=_u(g, 6, 11), twist=_u(g, 45, 120, 0))


def _v_helical_groove(g):
    r, pitch, turns = _u(g, 14, 26), _u(g, 14, 28), _u(g, 2, 4, 2)
    r_tube = _u(g, 2, min(4.5, 0.3 * pitch))  # the turns stay >= 0.4 pitch apart
    z0 = round(r_tube + g.uniform(4, 8), 1)
    return dict(r=r, length=round(2 * z0 + pitch * turns, 1), pitch=pitch, turns=turns, r_tube=r_tube, z0=z0)


def _v_threaded_rod(g):
    r, pitch, turns = _u(g, 9, 16), _u(g, 18, 32), _u(g, 1.5, 3, 2)
    r_tube = _u(g, 1.8, min(3.5, 0.16 * pitch))  # two starts: neighbouring ridges pitch / 2 apart
    z0 = round(r_tube + g.uniform(5, 9), 1)
    return dict(r=r, length=round(2 * z0 + pitch * turns, 1), pitch=pitch, turns=turns, r_tube=r_tube, z0=z0)


def _v_perforated_plate(g, margin=4.0, web=4.0):
    """6-16 holes, one per cell of a grid over the plate (less ``margin``), each jittered in its
    cell but kept ``web`` from its neighbours and ``margin + web / 2`` from the plate's edge."""
    lx, ly = _dims(g, 120, 90)
    n = g.randint(6, 16)
    nx = math.ceil(math.sqrt(n * lx / ly))
    ny = math.ceil(n / nx)
    cw, ch = (lx - 2 * margin) / nx, (ly - 2 * margin) / ny
    r_hole = _u(g, 2.5, min(5.0, min(cw, ch) / 2 - web))
    jx, jy = cw / 2 - r_hole - web / 2 - 0.1, ch / 2 - r_hole - web / 2 - 0.1  # 0.1: the rounding
    cells = sorted(g.sample([(i, j) for i in range(nx) for j in range(ny)], n))
    holes = tuple((round(margin + (i + 0.5) * cw + g.uniform(-jx, jx), 1),
                   round(margin + (j + 0.5) * ch + g.uniform(-jy, jy), 1)) for i, j in cells)
    return dict(lx=lx, ly=ly, t=_u(g, 5, 11), r_hole=r_hole, holes=holes)


def _v_wedge_cut(g):
    size = _dims(g, 80, 50, 40)
    lo, hi = (0.25, 0.3, 0.3), (0.6, 0.8, 0.8)  # the cut's legs, as fractions of the box's edges
    return dict(size=size, cut=tuple(_u(g, a * s, b * s) for s, a, b in zip(size, lo, hi)))


def _v_stepped_ring(g):
    r_out, h = _u(g, 28, 52), _u(g, 17, 31)
    r_in = _u(g, 0.45 * r_out, 0.65 * r_out)
    return dict(r_out=r_out, r_in=r_in, h=h, r_step=_u(g, r_in + 0.3 * (r_out - r_in), r_in + 0.6 * (r_out - r_in)),
                z_step=_u(g, 0.3 * h, 0.7 * h))


def _v_filleted_block(g):
    a, b, h = _dims(g, 60, 45, 30)
    r_hole = _u(g, 0.12 * min(a, b), 0.25 * min(a, b))
    return dict(a=a, b=b, h=h, r_hole=r_hole, fillet=_u(g, 1.5, min(5.0, 0.5 * r_hole, 0.2 * h)))


def _v_gusset_bracket(g):
    lx, w, hz = _dims(g, 80, 60, 60)
    t = _u(g, 5, 10)
    return dict(lx=lx, w=w, hz=hz, t=t, rib_t=_u(g, 5, 10),
                rib_x=_u(g, 0.4 * (lx - t), 0.75 * (lx - t)), rib_z=_u(g, 0.4 * (hz - t), 0.75 * (hz - t)))


def _v_tube_elbow(g):
    r_out = _u(g, 7, 14)
    return dict(R=_u(g, max(25.0, 2 * r_out), 55), L=_u(g, 15, 45), r_out=r_out,
                r_in=round(r_out - g.uniform(2.5, min(7.0, 0.5 * r_out)), 1))


def _v_capsule_post(g):
    r = _u(g, 9, 22)
    return dict(r=r, length=_u(g, 1.5 * r, 5 * r))


VARIANTS = {s.name: globals()[f"_v_{s.name}"] for s in SPECS}  # name -> draw(rng) -> keyword arguments


def _fmt(v):
    if isinstance(v, tuple):
        return ("/" if v and isinstance(v[0], tuple) else "x").join(_fmt(x) for x in v)
    return f"{v:g}"


def variant(name: str, seed: int | None = None) -> Spec:
    """The spec of model ``name``: the fixed one for ``seed=None``, else the family's variant with
    parameters drawn from ``random.Random(f"{seed}-{name}")`` (the genus of the perforated plate
    is its number of holes; the others keep theirs)."""
    spec = BY_NAME[name]
    if seed is None:
        return spec
    params = VARIANTS[name](random.Random(f"{seed}-{name}"))
    genus = len(params["holes"]) if "holes" in params else spec.genus
    desc = f"seed {seed}: " + ", ".join(f"{k} {len(v) if k == 'holes' else _fmt(v)}" for k, v in params.items())
    return Spec(name, genus, desc, functools.partial(spec.build, **params))


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


def build(name: str, path: str | Path, check: bool = True, seed: int | None = None) -> dict:
    """Write model ``name`` (its seeded variant for an integer ``seed``, see :func:`variant`) to
    the STEP file ``path``; with ``check``, re-import it with gmsh (one solid) and load it with
    ``polycubenet.io.load_part`` (closed, genus as intended).
    Returns ``{name, description, genus, volume, path}`` (volume of the B-rep, mm^3)."""
    spec = variant(name, seed)
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


def default_folder(seed: int | None = None) -> Path:
    """``benchmarks/results/hard_models/``, or ``hard_models_seed<N>/`` for the variants of seed N."""
    return DEFAULT_OUT if seed is None else DEFAULT_OUT.with_name(f"hard_models_seed{seed}")


def make_all(folder: str | Path | None = None, names=None, check: bool = True, verbose: bool = False,
             seed: int | None = None, keep_going: bool = False) -> list[Path]:
    """Write every model (or those in ``names``) as ``<folder>/<name>.step`` (``folder`` defaults to
    :func:`default_folder`); with an integer ``seed``, the seeded variants.  Returns the paths.
    The files are rebuilt every time (a few seconds; the bytes are the same each run).

    ``keep_going``: a model that does not build or fails its check does not stop the set (a benchmark over the
    set, ``bench_classical.py``): a line on stderr names it and the problem, and a model whose STEP file was
    written is still returned, so that the benchmark's own load reports it as a failed part; one that was not
    written is left out.  Without it the first failure raises, as a test of the models wants."""
    folder = default_folder(seed) if folder is None else Path(folder)
    paths = []
    for spec in SPECS:
        if names and spec.name not in names:
            continue
        path = folder / f"{spec.name}.step"
        path.unlink(missing_ok=True)  # a failed build must not leave an earlier run's file behind
        try:
            row = build(spec.name, path, check=check, seed=seed)
        except Exception as exc:  # noqa: BLE001 - OpenCASCADE and the loader raise many kinds
            if not keep_going:
                raise
            kept = path.is_file()
            print(f"hard model {spec.name}{'' if seed is None else f' (seed {seed})'}: {type(exc).__name__}: {exc}"
                  f" -- {'kept for the benchmark to report' if kept else 'left out (no STEP file)'}",
                  file=sys.stderr, flush=True)
            if kept:
                paths.append(path)
            continue
        if verbose:
            vol = "-" if row["volume"] is None else f"{row['volume']:.0f}"
            print(f"{spec.name:<18} genus {row['genus']:>2}  volume {vol:>9} mm^3  {row['description']}", flush=True)
        paths.append(Path(row["path"]))
    return paths


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None,
                    help="output folder (default benchmarks/results/hard_models/, or hard_models_seed<N>/ with --seed)")
    ap.add_argument("--models", nargs="*", default=None, choices=list(BY_NAME))
    ap.add_argument("--seed", type=int, default=None, help="build the seeded variants (other dimensions)")
    args = ap.parse_args(argv)
    out = default_folder(args.seed) if args.out is None else args.out
    paths = make_all(out, args.models, verbose=True, seed=args.seed)
    print(f"wrote {len(paths)} models to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
