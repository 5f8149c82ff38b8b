"""Synthetic pairs: topology, validity, invertibility, correspondence, reproducibility."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from polycubenet.frame import canonicalize, face_normals_areas
from polycubenet.sampling import interpolate
from polycubenet.synth import (
    DeformationMap,
    check_invertible,
    check_occupancy,
    jacobian_determinants,
    load_shard,
    make_pair,
    pair_seed,
    polycube_surface,
    random_deformation,
    random_polycube,
    solid_genus,
    surface_genus,
    transform_grid,
    write_dataset,
)
from polycubenet.synth.__main__ import main as synth_main
from polycubenet.synth.deform import FFD, Bend, RoundEdge, RoundHole, SlantEnd
from polycubenet.synth.pairs import snap_rotation
from polycubenet.synth.polycube import convex_edges


def _unit_grid(occ):
    return [np.arange(n + 1, dtype=float) for n in occ.shape]


# --------------------------------------------------------------------------- topology


def test_genus_two_independent_computations_agree_over_many_seeds():
    genera = []
    for s in range(160):
        pc = random_polycube(np.random.default_rng(s))
        assert check_occupancy(pc.occupancy) is None
        _, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
        g_euler = surface_genus(F)  # V - E + F of the triangulated boundary
        assert g_euler == pc.genus == solid_genus(pc.occupancy), s  # cubical complex of the solid
        genera.append(g_euler)
    assert set(range(5)) <= set(genera), sorted(set(genera))
    assert max(genera) >= 6


@pytest.mark.parametrize("k", [0, 1, 2, 3, 4])
def test_genus_by_construction_plate_with_k_holes(k):
    occ = np.ones((2 * k + 1, 3, 1), dtype=bool)
    occ[1 : 2 * k : 2, 1, 0] = False  # k separated square holes through a plate
    assert solid_genus(occ) == k
    V, F = polycube_surface(*_unit_grid(occ), occ, h=0.4)
    assert surface_genus(F) == k


def test_genus_cube_frame_is_five():
    occ = np.ones((3, 3, 3), dtype=bool)
    for axis in range(3):  # the centre column along each axis: a cube frame of 12 bars
        sl = [1, 1, 1]
        sl[axis] = slice(None)
        occ[tuple(sl)] = False
    assert check_occupancy(occ) is None
    assert solid_genus(occ) == 5
    assert surface_genus(polycube_surface(*_unit_grid(occ), occ)[1]) == 5


def test_surface_is_closed_oriented_and_axis_aligned():
    pc = random_polycube(np.random.default_rng(7), style="frame")
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy, h=0.03)
    normals, areas = face_normals_areas(V, F)
    assert np.all(areas > 0)
    big = np.abs(normals).max(axis=1)
    np.testing.assert_allclose(big, 1.0, atol=1e-9)
    assert np.all(np.sort(np.abs(normals), axis=1)[:, :2] <= 1e-9)
    volume = np.einsum("ij,ij->i", V[F[:, 0]], np.cross(V[F[:, 1]], V[F[:, 2]])).sum() / 6.0
    cell_volume = np.einsum("i,j,k->ijk", np.diff(pc.xs), np.diff(pc.ys), np.diff(pc.zs))[pc.occupancy].sum()
    assert volume == pytest.approx(cell_volume, rel=1e-9)  # outward and closed


# --------------------------------------------------------------------------- validity


def test_edge_contact_is_rejected():
    occ = np.zeros((2, 2, 1), dtype=bool)
    occ[0, 0, 0] = occ[1, 1, 0] = True
    reason = check_occupancy(occ)
    assert reason is not None and "edge" in reason


def test_vertex_contact_is_rejected():
    occ = np.zeros((2, 2, 2), dtype=bool)
    occ[0, 0, 0] = occ[1, 1, 1] = True
    reason = check_occupancy(occ)
    assert reason is not None and "vertex" in reason
    # the same pinch inside a larger solid (two blocks joined at one corner)
    big = np.zeros((4, 4, 4), dtype=bool)
    big[:2, :2, :2] = True
    big[2:, 2:, 2:] = True
    assert "vertex" in check_occupancy(big)


def test_empty_cells_in_edge_contact_are_rejected():
    occ = np.ones((2, 2, 3), dtype=bool)
    occ[0, 0, 1] = occ[1, 1, 1] = False  # two notches meeting along an edge
    reason = check_occupancy(occ)
    assert reason is not None and "edge" in reason


def test_cavity_and_disconnected_are_rejected_and_valid_passes():
    occ = np.ones((3, 3, 3), dtype=bool)
    assert check_occupancy(occ) is None
    occ[1, 1, 1] = False
    assert "cavity" in check_occupancy(occ)
    two = np.zeros((3, 1, 1), dtype=bool)
    two[0] = two[2] = True
    assert "disconnected" in check_occupancy(two)
    ell = np.zeros((2, 2, 1), dtype=bool)
    ell[0, 0, 0] = ell[1, 0, 0] = ell[0, 1, 0] = True
    assert check_occupancy(ell) is None


# --------------------------------------------------------------------------- deformations


def test_random_deformations_are_invertible_and_serialisable():
    for s in range(12):
        rng = np.random.default_rng(100 + s)
        pc = random_polycube(rng)
        lo, hi = pc.bounds
        holes = [(f.axis, f.lo, f.hi) for f in pc.features if f.kind in ("through_hole", "pocket")]
        edges = convex_edges(pc.xs, pc.ys, pc.zs, pc.occupancy)
        d = random_deformation(rng, lo, hi, holes, edges, strength=1.0)
        ok, worst = check_invertible(d, lo, hi, np.random.default_rng(s), n=2048)
        assert ok and worst > 0, (s, worst, d.kinds)
        X = lo + (hi - lo) * np.random.default_rng(s).random((50, 3))
        assert np.array_equal(DeformationMap.from_dict(d.to_dict())(X), d(X))


def test_bend_jacobian_matches_closed_form():
    bend = Bend(along=0, toward=2, center=np.zeros(3), curvature=0.8)
    X = np.random.default_rng(0).uniform(-0.5, 0.5, (200, 3))
    np.testing.assert_allclose(jacobian_determinants(bend, X), 1.0 - 0.8 * X[:, 2], atol=1e-6)


def test_rounding_maps_are_invertible_and_round():
    hole = RoundHole(axis=2, center=np.zeros(3), half=np.array([0.1, 0.1]), p=64.0, strength=1.0, fade=1.0)
    edge = RoundEdge(axis=2, corner=np.array([0.5, 0.5]), signs=np.array([1.0, 1.0]), radius=0.1, style="fillet", fade=0.5)
    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    for m in (hole, edge, DeformationMap([hole, edge])):
        ok, worst = check_invertible(m, lo, hi, np.random.default_rng(1), n=8192)
        assert ok, worst
    # the square hole's wall becomes (nearly) a circle of radius ~0.1
    t = np.linspace(-0.1, 0.1, 41)
    wall = np.concatenate([np.column_stack([t, np.full_like(t, 0.1), np.zeros_like(t)]),
                           np.column_stack([np.full_like(t, 0.1), t, np.zeros_like(t)])])
    r = np.linalg.norm(hole(wall)[:, :2], axis=1)
    assert r.max() - r.min() < 0.002
    # the fillet maps the bounding-box corner onto a circle of radius 0.1 about (0.4, 0.4)
    corner_faces = np.column_stack([np.full_like(t, 0.5), 0.4 + np.abs(t), np.zeros_like(t)])
    r = np.linalg.norm(edge(corner_faces)[:, :2] - 0.4, axis=1)
    np.testing.assert_allclose(r, 0.1, atol=1e-12)


def test_slanted_chamfer_cuts_the_corner_along_its_two_legs_and_is_invertible():
    """``radius2``: a chamfer with legs 0.3 and 0.1 (a cut at atan(1/3) to the x face, a slanted end)."""
    cut = RoundEdge(axis=2, corner=np.array([0.5, 0.5]), signs=np.array([1.0, 1.0]), radius=0.3, style="chamfer",
                    fade=0.3, radius2=0.1)
    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    ok, worst = check_invertible(cut, lo, hi, np.random.default_rng(2), n=8192)
    assert ok, worst
    t = np.linspace(0.0, 1.0, 41)
    faces = np.concatenate([np.column_stack([0.2 + 0.3 * t, np.full_like(t, 0.5), np.zeros_like(t)]),
                            np.column_stack([np.full_like(t, 0.5), 0.4 + 0.1 * t, np.zeros_like(t)])])
    Y = cut(faces)
    # the corner's two faces land on the line through (0.2, 0.5) and (0.5, 0.4)
    np.testing.assert_allclose((Y[:, 0] - 0.2) / 0.3 + (Y[:, 1] - 0.4) / 0.1, 1.0, atol=1e-9)
    # a map written before radius2 existed still loads, as the symmetric chamfer
    d = cut.to_dict()
    d.pop("radius2")
    old = DeformationMap.from_dict({"maps": [d]})
    assert old.maps[0].radius2 is None


def test_cad_features_add_slanted_ends_and_round_bosses_to_valid_pairs():
    """Off, the generator is the one before the option; on, some pairs get a slanted end and
    more cylinders (bosses too).  make_pair checks each pair's map and genus itself."""
    def kinds(cad):
        out = []
        for i in range(12):
            p = make_pair(pair_seed(5, i), n_cond=128, n_target=128, cad_features=cad)
            out += [m.kind + ("/slanted" if getattr(m, "radius2", None) is not None else "") for m in p.deformation.maps]
        return out

    base, cad = kinds(False), kinds(True)
    assert "round_edge/slanted" in cad and "round_edge/slanted" not in base
    assert cad.count("round_hole") > base.count("round_hole")


def test_a_slanted_end_cuts_the_whole_end_face_and_leaves_the_rest():
    """``SlantEnd``: the +x end face of the unit box, past z = -0.2, lands on the plane tilted atan(0.7)
    from it (through the pivot line); a point 'fade' inside the face, or below the pivot, does not move;
    invertible with the fade it is drawn with (2 slope reach), folded with a fade far too short."""
    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    cut = SlantEnd(axis=0, by=2, face=0.5, sign=1.0, pivot=-0.2, side=1.0, slope=0.7, fade=2 * 0.7 * 0.7)
    ok, worst = check_invertible(cut, lo, hi, np.random.default_rng(3), n=8192)
    assert ok and worst > 0.2, worst
    g = np.linspace(-0.5, 0.5, 21)
    face = np.array([[0.5, y, z] for y in g for z in g])
    Y = cut(face)
    past = face[:, 2] > -0.2
    np.testing.assert_allclose(Y[past, 0], 0.5 - 0.7 * (face[past, 2] + 0.2), atol=1e-12)  # the slanted plane
    np.testing.assert_allclose(Y[~past], face[~past], atol=1e-12)  # below the pivot: the end face stays
    inner = face.copy()
    inner[:, 0] = 0.5 - cut.fade - 1e-9
    np.testing.assert_allclose(cut(inner), inner, atol=1e-12)  # beyond the fade: identity
    # the cut reaches 0.49 into the part at the top edge: a whole end, not an edge's chamfer
    assert 0.5 - Y[:, 0].min() == pytest.approx(0.49)
    short = SlantEnd(axis=0, by=2, face=0.5, sign=1.0, pivot=-0.2, side=1.0, slope=0.7, fade=0.2)
    assert not check_invertible(short, lo, hi, np.random.default_rng(3), n=8192)[0]
    assert DeformationMap.from_dict(DeformationMap([cut]).to_dict()).maps[0] == cut


def test_a_plane_cut_slants_the_end_and_leaves_the_walls_near_it_straight():
    """``SlantEnd(profile="cut")`` puts the end face on the same slanted plane as the smooth fade, but only a
    slab a little deeper than the cut moves: a wall normal to x at x = -0.2 (a hole's or a step's) stays one
    plane, where the smooth fade over twice the cut's depth tilts it; faces normal to y and z stay in their
    planes; invertible, and a cut too shallow for its depth folds."""
    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    args = dict(axis=0, by=2, face=0.5, sign=1.0, pivot=-0.2, side=1.0, slope=0.7)
    smooth = SlantEnd(**args, fade=2 * 0.7 * 0.7)
    cut = SlantEnd(**args, fade=1.2 * 0.7 * 0.7, profile="cut")
    ok, worst = check_invertible(cut, lo, hi, np.random.default_rng(3), n=8192)
    assert ok and worst > 0.1, worst
    g = np.linspace(-0.5, 0.5, 21)
    face = np.array([[0.5, y, z] for y in g for z in g])
    np.testing.assert_allclose(cut(face), smooth(face), atol=1e-12)  # the same slanted end
    wall = face.copy()
    wall[:, 0] = -0.2
    assert np.ptp(cut(wall)[:, 0]) < 1e-12 and np.ptp(smooth(wall)[:, 0]) > 0.01
    X = lo + (hi - lo) * np.random.default_rng(4).random((4096, 3))
    np.testing.assert_allclose(cut(X)[:, 1:], X[:, 1:], atol=1e-12)  # only x moves
    assert DeformationMap.from_dict(DeformationMap([cut]).to_dict()).maps[0] == cut
    assert not check_invertible(SlantEnd(**args, fade=0.8 * 0.7 * 0.7, profile="cut"), lo, hi,
                                np.random.default_rng(3), n=8192)[0]


def test_cut_slants_keep_their_slab_clear_of_the_faces_they_would_tilt():
    """``random_deformation(cut_ends=True)`` places each cut so that no ``keep_out`` face normal to the cut's
    axis lies in its slab past the pivot (a hole's wall there would come out tilted): with a hole box near
    both x ends of a bar, over many seeds cuts are still placed (most of them of an x end) and none moves the
    hole's x faces off their planes."""
    from polycubenet.synth.deform import random_deformation

    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    lo[0], hi[0] = -1.0, 1.0
    holes = [(np.array([-0.85, -0.1, -0.5]), np.array([-0.7, 0.1, 0.5])),
             (np.array([0.7, -0.1, -0.5]), np.array([0.85, 0.1, 0.5]))]
    g = np.linspace(-0.5, 0.5, 11)
    walls = np.array([[x, y, z] for x in (-0.85, -0.7, 0.7, 0.85) for y in (-0.1, 0.0, 0.1) for z in g])
    placed = ends = 0
    for s in range(80):
        d = random_deformation(np.random.default_rng(s), lo, hi, whole_ends=True, strength=0.0, cut_ends=True,
                               keep_out=holes)
        for m in d.maps:
            if m.kind == "slant_end":
                placed += 1
                assert m.profile == "cut"
                np.testing.assert_allclose(m(walls)[:, 0], walls[:, 0], atol=1e-12)  # the x walls stay planes
                ends += m.axis == 0
    assert placed >= 10 and ends >= 5


def test_whole_slants_add_slanted_end_cuts_to_valid_pairs():
    """``whole_slants``: some pairs get a ``slant_end`` map (make_pair checks each map's Jacobian and the
    genus itself); without the option none does."""
    with_, without = [], []
    for i in range(10):
        with_ += make_pair(pair_seed(6, i), n_cond=64, n_target=64, cad_features=True, whole_slants=True).deformation.kinds
        without += make_pair(pair_seed(6, i), n_cond=64, n_target=64, cad_features=True).deformation.kinds
    assert "slant_end" in with_ and "slant_end" not in without


def test_full_slants_cut_across_the_whole_end_and_leave_the_default_stream():
    """``full_ends=1``: every whole-end cut pivots on the end's edge, so the slanted plane covers the whole
    end face (no strip of it stays where it was); the default cuts leave 20-70 % of it flat.  With
    ``full_ends=0`` a seed draws exactly the maps it drew before the option existed; a share outside
    [0, 1] is refused."""
    from polycubenet.synth.deform import random_deformation

    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    lo[0], hi[0] = -1.0, 1.0  # a long bar: the cuts mostly take an end of x

    g = np.linspace(0.0, 1.0, 41)
    grid = lo + (hi - lo) * np.array([[u, v, w] for u in g for v in g for w in g])

    def flat_share(full):
        shares = []
        for s in range(60):
            d = random_deformation(np.random.default_rng(s), lo, hi, whole_ends=True, strength=0.0, full_ends=full)
            for m in d.maps:
                if m.kind != "slant_end":
                    continue
                face = grid[np.isclose(grid[:, m.axis], m.face)]
                moved = np.abs(m(face)[:, m.axis] - m.face) > 1e-9
                shares.append(1.0 - moved.mean())
        return np.array(shares)

    full, partial = flat_share(1.0), flat_share(0.0)
    assert len(full) >= 10 and len(partial) >= 10
    assert full.max() <= 0.05  # only the pivot's row of the grid stays on the face
    assert partial.min() >= 0.15
    for s in range(20):
        a = random_deformation(np.random.default_rng(s), lo, hi, whole_ends=True, strength=0.5).to_dict()
        b = random_deformation(np.random.default_rng(s), lo, hi, whole_ends=True, strength=0.5, full_ends=0.0).to_dict()
        assert a == b
    with pytest.raises(ValueError, match="full_ends"):
        random_deformation(np.random.default_rng(0), lo, hi, whole_ends=True, full_ends=1.5)



def test_max_strength_caps_the_global_maps():
    """``max_strength=0``: the pairs keep their roundings and cuts but get no global map (ramp, taper,
    shear, twist, bend, FFD), which some of the same seeds get without the cap."""
    glob = {"ramp", "taper", "shear", "twist", "bend", "ffd"}
    capped, free = [], []
    for i in range(8):
        capped += make_pair(pair_seed(6, i), n_cond=64, n_target=64, cad_features=True, max_strength=0.0).deformation.kinds
        free += make_pair(pair_seed(6, i), n_cond=64, n_target=64, cad_features=True).deformation.kinds
    assert glob & set(free) and not glob & set(capped)
    assert {"round_hole", "round_edge"} & set(capped)

def test_tall_bosses_give_more_and_taller_bosses_and_leave_the_default_stream():
    """``tall_bosses``: over the same seeds, more bosses and taller ones (height over the bounding box along
    the boss's axis), every polycube still valid; off, a seed gives exactly the polycube it gave before."""
    from polycubenet.synth.polycube import random_polycube

    def bosses(tall):
        n, frac = 0, []
        for s in range(60):
            pc = random_polycube(np.random.default_rng([77, s]), tall_bosses=tall)
            assert pc.genus >= 0
            for f in pc.features:
                if f.kind == "boss":
                    n += 1
                    frac.append((f.hi - f.lo)[f.axis] / (pc.bounds[1] - pc.bounds[0])[f.axis])
        return n, float(np.median(frac))

    (n_off, h_off), (n_on, h_on) = bosses(False), bosses(True)
    assert n_on > 1.5 * n_off and h_on > 1.5 * h_off
    a = random_polycube(np.random.default_rng(5))
    b = random_polycube(np.random.default_rng(5), tall_bosses=False)
    assert np.array_equal(a.occupancy, b.occupancy) and np.allclose(a.xs, b.xs)


def test_min_holes_drill_at_least_that_many_holes_and_leave_the_default_stream():
    """``min_holes``: over the same seeds nine blocks in ten or more keep at least that many through-holes (a
    hole is only attempted: a later feature may fill it) and the genus rises; 0 gives exactly the polycube the
    seed gave before the option."""
    from polycubenet.synth.polycube import random_polycube

    def holes_and_genus(k):
        holes, genus = [], []
        for s in range(40):
            pc = random_polycube(np.random.default_rng([78, s]), style="block", min_holes=k)
            holes.append(sum(f.kind == "through_hole" for f in pc.features))
            genus.append(pc.genus)
        return np.array(holes), np.array(genus)

    (h0, g0), (h2, g2) = holes_and_genus(0), holes_and_genus(2)
    assert (h0 < 2).sum() >= 10  # without the option many blocks have fewer than two holes
    assert (h2 >= 2).mean() >= 0.9 and (g2 >= 2).mean() > (g0 >= 2).mean() + 0.2
    a = random_polycube(np.random.default_rng(5))
    b = random_polycube(np.random.default_rng(5), min_holes=0)
    assert np.array_equal(a.occupancy, b.occupancy) and np.allclose(a.xs, b.xs)


def test_breakouts_open_a_hole_into_an_end_the_slanted_cut_tilts_and_leave_the_default_stream():
    """``breakouts``: the opened box runs from a through-hole's side to the bounding box's end and keeps the hole
    a handle (filling the box back gives the same genus); the cut of that end (``breakout_cut``) tilts the open
    layers' end face inward and leaves it where it is beyond the pivot; ``make_pair`` puts that cut on that end;
    0 gives exactly the pair the seed gave before the option."""
    from polycubenet.synth.deform import breakout_cut
    from polycubenet.synth.pairs import make_pair
    from polycubenet.synth.polycube import _Builder, random_polycube, solid_genus

    seen = 0
    for s in range(30):
        pc = random_polycube(np.random.default_rng([79, s]), min_holes=1, breakouts=1.0)
        out = next((f for f in pc.features if f.kind == "breakout"), None)
        if out is None:
            continue
        e, blo, bhi = out.axis, out.lo, out.hi
        lo, hi = pc.bounds
        assert blo[e] <= lo[e] + 1e-9 or bhi[e] >= hi[e] - 1e-9  # open to the end
        assert any(f.kind == "through_hole" and (np.isclose(f.hi[e], blo[e]) or np.isclose(f.lo[e], bhi[e]))
                   for f in pc.features)  # from a hole's side
        cell = [(g[:-1] + g[1:]) / 2 for g in (pc.xs, pc.ys, pc.zs)]
        assert not pc.occupancy[np.ix_(*[(c > bl) & (c < bh) for c, bl, bh in zip(cell, blo, bhi)])].any()
        cut = breakout_cut(np.random.default_rng(s), lo, hi, blo, bhi, e)
        if cut is None:
            continue
        assert cut.axis == e and cut.profile == "cut" and cut.face in (lo[e], hi[e])
        open_side = -1.0 if blo[cut.by] <= lo[cut.by] + 1e-9 else 1.0
        assert cut.side == open_side  # the tilted layers are the open ones
        end = np.tile(0.5 * (lo + hi), (2, 1))
        end[:, e] = cut.face
        end[0, cut.by] = (lo if open_side < 0 else hi)[cut.by]  # the open layers' far face
        end[1, cut.by] = cut.pivot - cut.side * 1e-3  # short of the pivot
        moved = cut(end) - end
        assert cut.sign * moved[0, e] < -1e-6 and abs(moved[1, e]) < 1e-12
        seen += 1
    assert seen >= 8
    opened = 0
    for s in range(20):  # on a drilled block the opened layers leave the hole a handle
        b = _Builder(np.random.default_rng([80, s]), np.array([6, 5, 4]))
        assert b.through_hole(int(s % 3))
        before = b.occ.copy()
        if b.breakout():
            opened += 1
            assert solid_genus(b.occ) == solid_genus(before) == 1 and (before & ~b.occ).any()
    assert opened >= 15
    for seed in range(8):  # make_pair: the pair's only slanted cut is the breakout's, on its end
        pair = make_pair(seed, n_cond=64, n_target=64, whole_slants=True, min_holes=1, breakouts=1.0)
        out = next((f for f in pair.meta["features"] if f["kind"] == "breakout"), None)
        cuts = [m for m in pair.deformation.maps if m.kind == "slant_end"]
        if out is not None and cuts:
            assert len(cuts) == 1 and cuts[0].axis == out["axis"] and cuts[0].profile == "cut"
            seen += 1
    assert seen >= 12
    a = make_pair(3, n_cond=64, n_target=64, whole_slants=True)
    b = make_pair(3, n_cond=64, n_target=64, whole_slants=True, breakouts=0.0)
    assert np.array_equal(a.cond.points, b.cond.points) and np.array_equal(a.target.points, b.target.points)


def test_gussets_are_lone_ribs_resting_in_concave_corners_and_leave_the_default_stream():
    """``gussets``: each rib is one layer thick along its axis, every cell of its two inner sides rests on solid
    that is no other rib, nothing lies beside it along the axis or just past its free faces; the cut of an L's rib
    (``gusset_cut``) puts the rib's free corner on the line between its two legs (70-95 % of the rib), moves
    nothing of the L, and is refused where solid other than the rib lies in its region; make_pair cuts the ribs
    first and leaves their edges otherwise sharp; 0 gives exactly the pair the seed gave before the option."""
    from polycubenet.synth.deform import GUSSET_FADE, gusset_cut
    from polycubenet.synth.polycube import _behind, _Builder

    ribs = 0
    for s in range(40):
        b = _Builder(np.random.default_rng([91, s]), np.array([6, 5, 4]))
        b.notch(int(s % 3), through=True)  # an L or a step: concave corners
        for _ in range(2):
            before, rib_before = b.occ.copy(), b.ribs.copy()
            if not b.gusset():
                assert np.array_equal(b.occ, before)
                continue
            ribs += 1
            kind, a, lo, hi = b.features[-1]
            sb, sc = b.signs[len(b.features) - 1]
            assert kind == "gusset" and hi[a] - lo[a] == 1 and b.occ[b.box(lo, hi)].all()
            assert check_occupancy(b.occ) is None
            bb, cc = (a + 1) % 3, (a + 2) % 3
            solid = before & ~rib_before
            box = b.box(lo, hi)
            for ax, sg in ((bb, sb), (cc, sc)):  # the rib's inner sides: the cells behind them are solid
                blo, bhi = lo.copy(), hi.copy()
                if sg > 0:
                    blo[ax], bhi[ax] = lo[ax], lo[ax] + 1
                else:
                    blo[ax], bhi[ax] = hi[ax] - 1, hi[ax]
                assert _behind(solid, ax, int(sg))[b.box(blo, bhi)].all()
            for side in (lo[a] - 1, hi[a]):  # nothing beside it along its axis
                blo, bhi = lo.copy(), hi.copy()
                blo[a], bhi[a] = side, side + 1
                if 0 <= side < b.occ.shape[a]:
                    assert not b.occ[b.box(blo, bhi)].any()
            assert not before[box].any()
    assert ribs >= 25

    occ = np.zeros((3, 3, 3), dtype=bool)  # an L along x: base z < 1, upright y < 1; the rib at x = 1
    occ[:, :, 0] = True
    occ[:, 0, :] = True
    rib = occ.copy()
    rib[1, 1:, 1:] = True
    g = [np.arange(4.0)] * 3
    lo, hi = np.array([1.0, 1.0, 1.0]), np.array([2.0, 3.0, 3.0])
    for s in range(10):
        cut = gusset_cut(np.random.default_rng(s), *g, rib, lo, hi, 0, (1.0, 1.0))
        assert cut is not None and cut.style == "chamfer" and np.allclose(cut.corner, [3.0, 3.0])
        assert 0.7 * 2 <= cut.radius <= 0.95 * 2 and 0.7 * 2 <= cut.radius2 <= 0.95 * 2
        free = cut(np.array([[1.5, 3.0, 3.0]]))[0]  # the rib's free corner, on the chamfer's line
        assert np.allclose(free[1:], [3.0 - cut.radius / 2, 3.0 - cut.radius2 / 2])
        L = np.array([[x, y, z] for x in (0.0, 1.5, 3.0) for y in np.linspace(0, 3, 7) for z in np.linspace(0, 3, 7)
                      if y <= 1.0 or z <= 1.0])
        assert np.allclose(cut(L), L)  # the plates do not move
    crowded = rib.copy()
    crowded[2, 2, 2] = True  # solid in another layer within the cut's region
    assert gusset_cut(np.random.default_rng(0), *g, crowded, lo, hi, 0, (1.0, 1.0)) is None

    cut_pairs = 0
    for seed in range(12):
        pair = make_pair(seed, n_cond=64, n_target=64, style="extrusion", gussets=1.0)
        found = [f for f in pair.meta["features"] if f["kind"] == "gusset"]
        chamfers = [m for m in pair.deformation.maps if m.kind == "round_edge" and m.style == "chamfer"
                    and m.fade == GUSSET_FADE and m.radius2 is not None]
        for m in chamfers:  # the ribs' cuts come first, each on a rib's free edge
            assert pair.deformation.maps.index(m) < len(chamfers)
            assert any(f["axis"] == m.axis and np.allclose(f["signs"], m.signs) for f in found)
        cut_pairs += bool(chamfers)
    assert cut_pairs >= 6
    a = make_pair(3, n_cond=64, n_target=64, cad_features=True, whole_slants=True)
    b = make_pair(3, n_cond=64, n_target=64, cad_features=True, whole_slants=True, gussets=0.0)
    assert np.array_equal(a.cond.points, b.cond.points) and np.array_equal(a.target.points, b.target.points)


@pytest.mark.parametrize("flags, key, value", [(["--tall-bosses"], "tall_bosses", True),
                                               (["--min-holes", "2"], "min_holes", 2),
                                               (["--breakouts", "1"], "breakouts", 1.0),
                                               (["--gussets", "1"], "gussets", 1.0)])
def test_generator_options_are_recorded_and_regenerated(tmp_path, flags, key, value):
    """``--tall-bosses``, ``--min-holes``, ``--breakouts`` and ``--gussets`` are in the manifest, and a shard's pair rebuilds from
    its seed with the option."""
    rc = synth_main(["--out", str(tmp_path), "--count", "2", "--seed", "6", "--per-shard", "2", "--n-cond", "40",
                     "--n-target", "40", "--cad-features", *flags, "--no-progress"])
    assert rc == 0
    recorded = json.loads((tmp_path / "dataset.json").read_text())["params"][key]
    assert recorded == value and type(recorded) is type(value)
    shard = load_shard(tmp_path / "shard-00000.npz")
    for k, rec in enumerate(shard):
        again = shard.regenerate(k)
        assert np.array_equal(rec["polycube"].occupancy, again.polycube.occupancy)
        # the evaluation's rib count is read from the recorded features: the rebuilt pair's gussets
        assert shard.ribs(k) == sum(f["kind"] == "gusset" for f in again.meta["features"])
    assert (sum(shard.ribs(k) for k in range(len(shard))) > 0) == (key == "gussets")


def test_non_invertible_maps_are_caught():
    lo, hi = -0.5 * np.ones(3), 0.5 * np.ones(3)
    rng = np.random.default_rng(0)
    folded_bend = Bend(along=0, toward=2, center=np.zeros(3), curvature=4.0)  # det = 1 - 4 z < 0 for z > 1/4
    ok, worst = check_invertible(folded_bend, lo, hi, rng)
    assert not ok and worst < 0
    D = np.zeros((2, 2, 2, 3))
    D[1, :, :, 0] = -2.0  # the +x side of the lattice pushed far past the -x side: a fold
    ok, worst = check_invertible(FFD(lo, hi, D), lo, hi, rng)
    assert not ok and worst < 0
    ok, _ = check_invertible(DeformationMap([]), lo, hi, rng)  # identity passes
    assert ok


# --------------------------------------------------------------------------- pairs


@pytest.fixture(scope="module")
def pair():
    return make_pair(pair_seed(0, 5), n_cond=512, n_target=512)


def test_pair_vertices_correspond_through_the_map(pair):
    np.testing.assert_allclose(pair.polycube_to_shape(pair.polycube_vertices), pair.shape_vertices, atol=1e-9)
    assert pair.shape_vertices.shape == pair.polycube_vertices.shape
    assert surface_genus(pair.faces) == pair.genus


def test_pair_samples_correspond_exactly(pair):
    c, t = pair.cond, pair.target
    assert c.points.shape == (512, 3) and t.points.shape == (512, 3)
    np.testing.assert_array_equal(c.face_ids, t.face_ids)
    np.testing.assert_array_equal(c.barycentrics, t.barycentrics)
    np.testing.assert_allclose(interpolate(pair.shape_vertices, pair.faces, c.face_ids, c.barycentrics), c.points, atol=1e-12)
    np.testing.assert_allclose(interpolate(pair.polycube_vertices, pair.faces, t.face_ids, t.barycentrics), t.points, atol=1e-12)
    np.testing.assert_allclose(pair.cond_on_polycube, t.points, atol=1e-12)
    np.testing.assert_allclose(pair.target_on_shape, c.points, atol=1e-12)
    # mapping the target points' triangle corners through the deformation gives the shape triangles
    tri = pair.polycube_vertices[pair.faces[t.face_ids]].reshape(-1, 3)
    mapped = pair.polycube_to_shape(tri).reshape(-1, 3, 3)
    np.testing.assert_allclose(np.einsum("kj,kjd->kd", t.barycentrics, mapped), c.points, atol=1e-9)


def test_pair_with_different_point_counts():
    p = make_pair(11, n_cond=300, n_target=200, sampler="uniform")
    assert p.cond.points.shape == (300, 3) and p.target.points.shape == (200, 3)
    np.testing.assert_allclose(interpolate(p.shape_vertices, p.faces, p.target.face_ids, p.target.barycentrics),
                               p.target_on_shape, atol=1e-12)
    np.testing.assert_allclose(interpolate(p.polycube_vertices, p.faces, p.cond.face_ids, p.cond.barycentrics),
                               p.cond_on_polycube, atol=1e-12)


def test_pair_is_in_the_canonical_frame_and_polycube_axis_aligned(pair):
    V = pair.shape_vertices
    lo, hi = V.min(0), V.max(0)
    np.testing.assert_allclose(0.5 * (lo + hi), 0.0, atol=1e-12)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-12)
    _, T = canonicalize(V, pair.faces)  # the shape is already canonical: canonicalize is ~identity
    np.testing.assert_allclose(T.forward(V), V, atol=1e-6)
    P = pair.polycube_transform.rotation
    assert np.all(np.isin(P, (-1.0, 0.0, 1.0))) and np.linalg.det(P) == pytest.approx(1.0)
    assert snap_rotation(pair.shape_transform.rotation)[0].tolist() == P.tolist()
    for normals in (face_normals_areas(pair.polycube_vertices, pair.faces)[0], pair.target.normals):
        np.testing.assert_allclose(np.abs(normals).max(axis=1), 1.0, atol=1e-9)
        assert np.all(np.sort(np.abs(normals), axis=1)[:, :2] <= 1e-9)
    # the stored grid is the transformed polycube: same surface (coarse vertices among the
    # refined ones, same area)
    pc = pair.polycube
    Vg, Fg = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    fine = {tuple(v) for v in np.round(pair.polycube_vertices, 12)}
    assert all(tuple(v) in fine for v in np.round(Vg, 12))
    area_g = face_normals_areas(Vg, Fg)[1].sum()
    area_f = face_normals_areas(pair.polycube_vertices, pair.faces)[1].sum()
    assert area_g == pytest.approx(area_f, rel=1e-9)
    assert solid_genus(pc.occupancy) == pair.genus == pc.meta["genus"]


def test_transform_grid_matches_transformed_surface():
    pc = random_polycube(np.random.default_rng(3))
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    P = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    c, s = np.array([0.1, -0.2, 0.05]), 1.7
    xs, ys, zs, occ = transform_grid(pc.xs, pc.ys, pc.zs, pc.occupancy, c, s, P)
    V2, F2 = polycube_surface(xs, ys, zs, occ)
    mapped = ((V - c) * s) @ P.T
    key = lambda A: np.array(sorted(map(tuple, np.round(A, 12))))  # noqa: E731
    np.testing.assert_array_equal(key(V2), key(mapped))
    assert face_normals_areas(V2, F2)[1].sum() == pytest.approx(face_normals_areas(mapped, F)[1].sum(), rel=1e-12)


def test_pair_save_load_roundtrip(pair, tmp_path):
    from polycubenet.synth import SynthPair

    path = pair.save(tmp_path / "pair.npz")
    back = SynthPair.load(path)
    np.testing.assert_array_equal(back.shape_vertices, pair.shape_vertices)
    np.testing.assert_array_equal(back.polycube.occupancy, pair.polycube.occupancy)
    np.testing.assert_allclose(back.polycube_to_shape(back.polycube_vertices[:100]), pair.shape_vertices[:100], atol=1e-9)


# --------------------------------------------------------------------------- shards


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def test_shards_are_byte_for_byte_reproducible(tmp_path):
    kw = dict(per_shard=2, n_cond=64, n_target=48, progress=False)
    a = write_dataset(tmp_path / "a", 3, seed=9, **kw)
    b = write_dataset(tmp_path / "b", 3, seed=9, workers=2, **kw)
    c = write_dataset(tmp_path / "c", 3, seed=10, **kw)
    assert len(a) == 2
    assert [_sha(p) for p in a] == [_sha(p) for p in b]
    assert _sha(tmp_path / "a" / "dataset.json") == _sha(tmp_path / "b" / "dataset.json")
    assert _sha(a[0]) != _sha(c[0])



def test_max_strength_is_recorded_and_regenerated(tmp_path):
    """``--max-strength``: in the manifest and each shard's parameters, so a shard's pair rebuilds with the
    cap (no global map at 0); a set made without it keeps its manifest (the parameter's default)."""
    rc = synth_main(["--out", str(tmp_path), "--count", "2", "--seed", "6", "--per-shard", "2", "--n-cond", "40",
                     "--n-target", "40", "--cad-features", "--max-strength", "0", "--no-progress"])
    assert rc == 0
    assert json.loads((tmp_path / "dataset.json").read_text())["params"]["max_strength"] == 0.0
    shard = load_shard(tmp_path / "shard-00000.npz")
    for k, rec in enumerate(shard):
        again = shard.regenerate(k)
        assert rec["meta"]["deformation"] == again.deformation.to_dict()
        assert not {"ramp", "taper", "shear", "twist", "bend", "ffd"} & set(again.deformation.kinds)

def test_shard_contents_and_loader(tmp_path):
    rc = synth_main(["--out", str(tmp_path), "--count", "3", "--seed", "4", "--per-shard", "3",
                     "--n-cond", "40", "--n-target", "40", "--full", "--no-progress"])
    assert rc == 0
    shard = load_shard(tmp_path / "shard-00000.npz")
    assert len(shard) == 3
    assert shard["cond_points"].shape == (3, 40, 3) and shard["target_normals"].shape == (3, 40, 3)
    assert shard["cond_points"].dtype == np.float32
    np.testing.assert_array_equal(shard["index"], [0, 1, 2])
    np.testing.assert_array_equal(shard["seeds"], [pair_seed(4, i) for i in range(3)])
    for k, rec in enumerate(shard):
        again = shard.regenerate(k)
        pc = rec["polycube"]
        np.testing.assert_array_equal(pc.occupancy, again.polycube.occupancy)
        np.testing.assert_array_equal(pc.xs, again.polycube.xs)
        assert rec["genus"] == again.genus == solid_genus(pc.occupancy)
        np.testing.assert_allclose(rec["cond_points"], again.cond.points, atol=1e-6)
        Vs, Vp, F = shard.mesh(k)
        np.testing.assert_array_equal(F, again.faces)
        pts = interpolate(Vp, F, rec["target_face_ids"], rec["target_barycentrics"].astype(np.float64))
        np.testing.assert_allclose(pts, rec["target_points"], atol=1e-6)
        assert rec["meta"]["deformation"] == again.deformation.to_dict()
    # a second run resumes: nothing changes
    before = _sha(tmp_path / "shard-00000.npz")
    assert synth_main(["--out", str(tmp_path), "--count", "3", "--seed", "4", "--per-shard", "3",
                       "--n-cond", "40", "--n-target", "40", "--full", "--no-progress"]) == 0
    assert _sha(tmp_path / "shard-00000.npz") == before
    # other parameters in the same folder are refused
    assert synth_main(["--out", str(tmp_path), "--count", "3", "--seed", "5", "--no-progress"]) == 2


def test_occupancy_problems_read_as_plain_sentences():
    edge = np.zeros((3, 3, 2), dtype=bool)
    edge[0, 0, :] = edge[1, 1, :] = True  # two columns meeting along an edge only
    corner = np.zeros((2, 2, 2), dtype=bool)
    corner[0, 0, 0] = corner[1, 1, 1] = True  # two cells meeting at a vertex only
    apart = np.zeros((3, 1, 1), dtype=bool)
    apart[0] = apart[2] = True
    assert check_occupancy(edge) == "non-manifold: 2 edge-only contact(s), first along axis 2 at vertex (1, 1, 0)"
    assert check_occupancy(corner) == "non-manifold: 1 vertex-only contact(s), first at vertex (1, 1, 1)"
    assert check_occupancy(apart) == "disconnected: 2 solid components"


def test_turned_polycubes_are_coaxial_squares_and_valid():
    """A turned part's polycube: valid, its grid across the axis symmetric about it (every square step, the bore
    and the bolt circle centred on the axis, so one radial map rounds them all), the body recorded as a feature."""
    from polycubenet.synth.polycube import turned_polycube

    genera = set()
    for s in range(30):
        pc = turned_polycube(np.random.default_rng([51, s]))
        assert check_occupancy(pc.occupancy) is None and pc.style == "turned"
        body = [f for f in pc.features if f.kind == "turned"]
        assert len(body) == 1
        for a in range(3):
            if a != body[0].axis:
                c = pc.grid[a]
                np.testing.assert_allclose(c, -c[::-1], atol=1e-12)
        genera.add(pc.genus)
    assert {0, 1, 4} <= genera  # a plain shaft, a bore (or a cross hole), a flange's four bolt holes


def test_bolt_circles_are_evenly_spread_square_holes_that_the_radial_map_puts_on_a_circle():
    """``bolt_circles``: bolted flanges with 3-8 square holes in the flange, apart and clear of the steps, their
    centres on a square ring (one radius after the radial map) and evenly spread in angle; 0 leaves every
    polycube as it was (the four on the cross axes)."""
    from polycubenet.synth.polycube import _turned_once, bolt_circle, turned_polycube

    centres = bolt_circle(5, 0.3, 2.0)
    assert np.allclose(np.abs(np.array(centres)).max(axis=1), 2.0)
    ang = np.sort(np.mod([np.arctan2(v, u) for u, v in centres], 2 * np.pi))
    assert np.allclose(np.diff(ang), 2 * np.pi / 5)
    counts = set()
    for s in range(200):
        a, b = turned_polycube(np.random.default_rng([52, s])), _turned_once(np.random.default_rng([52, s]), 0.025)
        if b is not None:  # off: the same polycube as before the option
            assert np.array_equal(a.occupancy, b.occupancy)
        pc = turned_polycube(np.random.default_rng([52, s]), bolt_circles=1.0)
        assert check_occupancy(pc.occupancy) is None
        body = next(f for f in pc.features if f.kind == "turned")
        bolts = [f for f in pc.features if f.kind == "through_hole" and f.axis == body.axis]
        if not bolts:
            continue
        counts.add(len(bolts))
        u = [k for k in range(3) if k != body.axis]
        mid = np.array([0.5 * (f.lo + f.hi)[u] for f in bolts])
        ring = np.abs(mid).max(axis=1)
        assert ring.max() - ring.min() < 2 * 0.025  # one ring: each side snapped by less than the min width
        assert pc.genus >= len(bolts)
    assert len(counts) >= 4  # several hole counts, not only the four on the axes


def _radial_share(P: np.ndarray, N: np.ndarray, deg: float = 15.0) -> float:
    """Of the points whose normal is across an axis through the origin, the share whose normal points along
    the radius from that axis (within ``deg``; the best of the three axes): about 1 on coaxial cylinders."""
    best = 0.0
    for a in range(3):
        u = [i for i in range(3) if i != a]
        side = np.abs(N[:, a]) < 0.1
        r, n = P[side][:, u], N[side][:, u]
        rn = np.linalg.norm(r, axis=1)
        k = rn > 0.02
        cos = np.abs((r[k] * n[k]).sum(1)) / (rn[k] * np.linalg.norm(n[k], axis=1))
        best = max(best, float((cos > np.cos(np.radians(deg))).mean()))
    return best


def test_turned_pairs_are_round_where_their_polycubes_are_square():
    """``turned``: the part's side walls are coaxial cylinders (normals along the radius) where its target
    polycube's are square (a third of the points, near the face centres) and other pairs' are not; off, a seed
    gives exactly the pair it gave before."""
    for s in (3, 5, 8):
        pair = make_pair(s, n_cond=600, n_target=600, turned=1.0)
        assert pair.meta["style"] == "turned"
        assert _radial_share(pair.cond.points, pair.cond.normals) > 0.75, s
        assert _radial_share(pair.target.points, pair.target.normals) < 0.45, s
        assert (np.abs(pair.target.normals).max(axis=1) > 0.999).all()
        other = make_pair(s, n_cond=600, n_target=600)
        assert other.meta["style"] != "turned" and _radial_share(other.cond.points, other.cond.normals) < 0.45
    a, b = make_pair(5, n_cond=100, n_target=100), make_pair(5, n_cond=100, n_target=100, turned=0.0)
    assert np.array_equal(a.cond.points, b.cond.points)


def test_turned_share_is_recorded_and_regenerated(tmp_path):
    rc = synth_main(["--out", str(tmp_path), "--count", "2", "--seed", "6", "--per-shard", "2", "--n-cond", "40",
                     "--n-target", "40", "--turned", "1", "--no-progress"])
    assert rc == 0
    assert json.loads((tmp_path / "dataset.json").read_text())["params"]["turned"] == 1.0
    shard = load_shard(tmp_path / "shard-00000.npz")
    for k, rec in enumerate(shard):
        again = shard.regenerate(k)
        assert np.array_equal(rec["polycube"].occupancy, again.polycube.occupancy)


def test_the_flange_share_sets_how_many_turned_parts_carry_a_bolted_flange(tmp_path):
    """``flanges``: the share of turned polycubes with a flange at one end (bolt holes are drilled only in a
    flange, in 70 % of them): none at 0, most at 1; recorded in the manifest and regenerated with it."""
    from polycubenet.synth.polycube import FLANGES, turned_polycube

    def bolted(share: float) -> float:
        n = 0
        for s in range(60):
            pc = turned_polycube(np.random.default_rng([53, s]), flanges=share)
            assert check_occupancy(pc.occupancy) is None
            body = next(f for f in pc.features if f.kind == "turned")
            n += any(f.kind == "through_hole" and f.axis == body.axis for f in pc.features)
        return n / 60

    few, most = bolted(FLANGES), bolted(1.0)
    assert bolted(0.0) == 0.0 and most > 0.4 and most > 2 * few > 0.1, (few, most)
    rc = synth_main(["--out", str(tmp_path), "--count", "2", "--seed", "6", "--per-shard", "2", "--n-cond", "40",
                     "--n-target", "40", "--turned", "1", "--flanges", "1", "--no-progress"])
    assert rc == 0 and json.loads((tmp_path / "dataset.json").read_text())["params"]["flanges"] == 1.0
    shard = load_shard(tmp_path / "shard-00000.npz")
    for k, rec in enumerate(shard):
        assert np.array_equal(rec["polycube"].occupancy, shard.regenerate(k).polycube.occupancy)
