"""The learned structure realised exactly on the part (``polycubenet.realise``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from polycubenet.data import Polycube
from polycubenet.errors import PolycubeError
from polycubenet.polycube import polycube_surface
from polycubenet.pullback import PullbackConfig
from polycubenet.realise import RealiseConfig, _merge_close, match_structure, planar_patches, realise
from polycubenet.sampling import poisson_disk

SLANT = 0.8  # the sheared end moves in x by SLANT * (height above the floor), canonical units (a 39 degree end)


def _l_polycube(Vc):
    """The L-block's own polycube in the canonical frame of ``Vc`` (x in {0, 1, 3}, z in {0, 1, 2} before scaling)."""
    lo, hi = Vc.min(axis=0), Vc.max(axis=0)
    s = (hi[0] - lo[0]) / 3.0
    xs, ys, zs = lo[0] + s * np.array([0.0, 1.0, 3.0]), lo[1] + s * np.array([0.0, 1.0]), lo[2] + s * np.array([0.0, 1.0, 2.0])
    occ = np.zeros((2, 1, 2), dtype=bool)
    occ[0, 0, :] = True
    occ[1, 0, 0] = True
    return Polycube(xs, ys, zs, occ)


def _shear(lo, hi, s):
    """Tilts the long arm's end face: x -= SLANT * (z - floor) near the end (a ramp in x, so every
    face stays planar); the map from the L's polycube onto the sheared part."""
    x1, x3 = lo[0] + s, hi[0]

    def f(P):
        P = np.array(P, dtype=np.float64, copy=True)
        ramp = np.clip((P[:, 0] - x1) / (x3 - x1), 0.0, 1.0)
        P[:, 0] -= SLANT * ramp * (P[:, 2] - lo[2])
        return P

    return f


@pytest.fixture(scope="module")
def slanted_l(l_block_canonical):
    Vc, F = l_block_canonical
    poly = _l_polycube(Vc)
    lo, hi = Vc.min(axis=0), Vc.max(axis=0)
    shear = _shear(lo, hi, (hi[0] - lo[0]) / 3.0)
    return shear(Vc), F, poly, shear


def _on_polycube(points, poly) -> float:
    Vq, Fq = polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy)
    return float(trimesh.proximity.closest_point(trimesh.Trimesh(Vq, Fq, process=False), points)[1].max())


def test_a_slanted_end_is_realised_exactly_on_the_learned_polycube(slanted_l):
    V, F, poly, shear = slanted_l
    got = realise(V, F, poly, shear)
    assert got.map.meta["collapsed_slabs"] == 0
    assert np.array_equal(got.polycube.occupancy, poly.occupancy)
    # the flattened surface is the learned polycube's surface ...
    assert _on_polycube(got.map.Vp, poly) < 1e-9
    # ... and its points go exactly onto the part, also on the slanted end that the polycube has axis-aligned
    s = poisson_disk(*polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy), 3000, seed=3)
    part = trimesh.Trimesh(V, F, process=False)
    exact = trimesh.proximity.closest_point(part, got.map_points(s.points))[1]
    assert exact.max() < 1e-6
    end = s.points[:, 0] > poly.xs[-1] - 1e-9  # the polycube's end face: where the identity map misses the part
    off = trimesh.proximity.closest_point(part, s.points[end])[1]
    assert off.max() > 0.05


def test_a_learned_polycube_of_another_structure_is_refused(slanted_l):
    V, F, _, shear = slanted_l
    lo, hi = V.min(axis=0), V.max(axis=0)
    box = Polycube(np.array([lo[0], hi[0]]), np.array([lo[1], hi[1]]), np.array([lo[2], hi[2]]), np.ones((1, 1, 1), bool))
    with pytest.raises(PolycubeError, match="learned labels"):
        realise(V, F, box, lambda P: np.asarray(P, float), RealiseConfig(own_structure=False))


def _bumped_l(Vc):
    """The L-block's polycube with a bump the part does not have: a half-cell on the floor's far end (x in
    {0, 1, 2, 3}, z in {0, 1, 1.5, 2} before scaling), genus 0 like the L."""
    lo, hi = Vc.min(axis=0), Vc.max(axis=0)
    s = (hi[0] - lo[0]) / 3.0
    xs, ys, zs = (lo[0] + s * np.array([0.0, 1.0, 2.0, 3.0]), lo[1] + s * np.array([0.0, 1.0]),
                  lo[2] + s * np.array([0.0, 1.0, 1.5, 2.0]))
    occ = np.zeros((3, 1, 3), dtype=bool)
    occ[:, 0, 0] = True  # the floor
    occ[0, 0, 1:] = True  # the upright arm
    occ[2, 0, 1] = True  # the bump
    return Polycube(xs, ys, zs, occ, meta={"genus": 0})


def test_a_flattened_part_of_its_own_structure_is_kept_with_the_part_s_planes_or_refused_when_off(l_block_canonical):
    """The learned polycube has a bump the L does not: on the learned labels the part flattens onto the L, a
    valid polycube of the same genus but another structure.  With ``own_structure`` (the default) that solid is
    kept, on the part's own planes, its map exact onto the part, and its meta says how the learned one differed;
    without it the realisation is refused as before.  A flattened solid of another genus is refused either way."""
    V, F = l_block_canonical
    bumped = _bumped_l(V)
    identity = lambda P: np.asarray(P, float)  # noqa: E731
    got = realise(V, F, bumped, identity)
    assert got.map.meta["structure"].startswith("the part's (") and "3x1x3" in got.map.meta["structure"]
    assert got.polycube.meta["own_structure"] and got.polycube.meta["learned_grid_shape"] == [3, 1, 3]
    np.testing.assert_array_equal(got.polycube.occupancy, _l_polycube(V).occupancy)
    np.testing.assert_allclose(got.polycube.zs, _l_polycube(V).zs, atol=1e-9)  # the part's planes, not the learned
    s = poisson_disk(*polycube_surface(got.polycube.xs, got.polycube.ys, got.polycube.zs, got.polycube.occupancy),
                     2000, seed=4)
    assert _on_polycube(got.map.Vp, got.polycube) < 1e-9
    assert trimesh.proximity.closest_point(trimesh.Trimesh(V, F, process=False), got.map_points(s.points))[1].max() < 1e-6
    with pytest.raises(PolycubeError, match="own structure is off"):
        realise(V, F, bumped, identity, RealiseConfig(own_structure=False))
    torus_genus = Polycube(bumped.xs, bumped.ys, bumped.zs, bumped.occupancy, meta={"genus": 1})
    with pytest.raises(PolycubeError, match="3x1x3.*of genus 0, the learned polycube of genus 1"):
        realise(V, F, torus_genus, identity)
    # without a genus in its meta the learned polycube's own is read off its cells
    plain = Polycube(bumped.xs, bumped.ys, bumped.zs, bumped.occupancy)
    assert realise(V, F, plain, identity).polycube.meta["own_structure"]


def test_a_mesh_on_the_part_s_own_structure_says_so_in_its_map(l_block_canonical, monkeypatch):
    """Through :func:`pull_back_learned`: the bumped polycube's registration mesh (the identity, made to read
    as off the part) does not end the chain, the realisation keeps the part's structure, its mesh ends the chain
    and its ``map`` says whose structure it is (the benchmarks' ``map_name`` reads it)."""
    import sys

    from polycubenet import pipeline
    from polycubenet.pipeline import PipelineConfig, pull_back_learned
    from polycubenet.policy import ends_chain

    identity = lambda P: np.asarray(P, float)  # noqa: E731
    real = pipeline.pull_back

    def off_when_registered(mesh_pc, to_part, *a, **k):
        m = real(mesh_pc, to_part, *a, **k)
        if to_part is identity:  # the registration's map: as if 5 % off the part
            m.meta["hausdorff"] = 0.05
        return m

    monkeypatch.setattr(pipeline, "pull_back", off_when_registered)

    sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1] / "benchmarks"))
    from unseen_parts import map_name

    V, F = l_block_canonical
    cfg = PipelineConfig(target_hexes=800)
    mesh, used = pull_back_learned(_bumped_l(V), _Map(identity), V, F, cfg)
    assert mesh.meta["map"] == "exact (realised, the part's structure)" and ends_chain(mesh.meta, cfg.min_sj)
    assert mesh.meta["realised"]["structure"].startswith("the part's (")
    assert used.meta["own_structure"] and used.occupancy.sum() == 3
    assert map_name(mesh.meta) == "exact, part's structure"


def _bosses(top2: float):
    """(x, z) section of a base with two bosses, the second's top at ``top2`` (y: one cell)."""
    xs, ys = np.array([0.0, 0.3, 0.6, 0.9]), np.array([0.0, 0.4])
    if top2 == 0.5:
        zs = np.array([0.0, 0.2, 0.5])
        occ = np.array([[1, 1], [1, 0], [1, 1]], bool)[:, None, :]
    else:
        zs = np.array([0.0, 0.2, 0.5, top2])
        occ = np.array([[1, 1, 0], [1, 0, 0], [1, 1, 1]], bool)[:, None, :]
    return xs, ys, zs, occ


def test_a_thin_slab_of_the_learned_polycube_collapses_onto_the_part_plane_but_a_thick_one_does_not():
    xs, ys, zs, occ = _bosses(0.5)  # the part: both bosses end at z = 0.5
    for top2, ok in ((0.51, True), (0.6, False)):
        lx, ly, lz, locc = _bosses(top2)  # the learned polycube draws the second boss a little higher
        learned = Polycube(lx, ly, lz, locc)
        if ok:
            got, planes, collapsed, inserted = match_structure([xs, ys, zs], occ, learned)
            assert (collapsed, inserted) == (1, 0)
            np.testing.assert_allclose(planes[2], [0.0, 0.2, 0.505])
            np.testing.assert_allclose(planes[0], xs)
        else:
            with pytest.raises(PolycubeError):
                match_structure([xs, ys, zs], occ, learned)


def test_close_planes_facing_opposite_ways_stay_apart_with_keep_sheets_only_across_each_other():
    """Six z-charts (one triangle each): the two faces of a thin slot, one above the other (+z at 0.300, -z at
    0.305), two opposite faces side by side (+z at 0.450, -z at 0.455: a flattening's stagger), and a low step
    (+z at 0.600 and 0.604).  With a merge distance of 0.01 all three pairs merge; with ``keep_sheets`` the slot
    stays open while the side-by-side pair and the step still merge."""
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    X, F, labels = [], [], []
    for k, (x0, z, lab) in enumerate(((0.0, 0.300, 5), (0.0, 0.305, 4), (2.0, 0.450, 5), (3.5, 0.455, 4),
                                      (6.0, 0.600, 5), (8.0, 0.604, 5))):
        X += [[x + x0, y, z] for x, y in tri]
        F.append([3 * k, 3 * k + 1, 3 * k + 2])
        labels.append(lab)
    X, F, labels = np.array(X), np.array(F), np.array(labels)
    merged = _merge_close(X, F, labels, 0.01)
    assert np.unique(np.round(merged[:, 2], 6)).tolist() == [0.3025, 0.4525, 0.602]
    kept = _merge_close(X, F, labels, 0.01, keep_sheets=True)
    assert np.unique(np.round(kept[:, 2], 6)).tolist() == [0.3, 0.305, 0.4525, 0.602]


def test_a_thin_step_the_learned_polycube_drew_on_one_plane_is_put_back_but_a_thick_one_is_not():
    """The other direction: the part's second boss is a little higher (two close planes), the learned
    polycube has both bosses end on one plane.  The part's thin slab is collapsed to compare the cells, then
    put back around the learned plane, the part's thickness wide; the solid is the part's."""
    lx, ly, lz, locc = _bosses(0.5)
    learned = Polycube(lx, ly, lz, locc)
    for top2, ok in ((0.51, True), (0.6, False)):
        xs, ys, zs, occ = _bosses(top2)
        if ok:
            got, planes, collapsed, inserted = match_structure([xs, ys, zs], occ, learned)
            assert (collapsed, inserted) == (0, 1)
            np.testing.assert_allclose(planes[2], [0.0, 0.2, 0.495, 0.505])
            np.testing.assert_allclose(got[2], zs)
        else:
            with pytest.raises(PolycubeError):
                match_structure([xs, ys, zs], occ, learned)
    # cells outside the thin slab that differ: refused
    xs, ys, zs, occ = _bosses(0.51)
    occ = occ.copy()
    occ[1, 0, 1] = True  # the part has no gap between the bosses
    with pytest.raises(PolycubeError):
        match_structure([xs, ys, zs], occ, learned)


class _Map:
    """A registration's map (``map_points``) for :func:`pull_back_learned`."""

    def __init__(self, fn):
        self.map_points = fn


def test_a_learned_polycube_whose_registration_misses_the_slant_is_meshed_through_its_realisation(slanted_l):
    """A registration that leaves the end face where the polycube has it (the identity): its mesh is off the
    part, so the realisation is tried, follows the slanted end (each planar face of the part one label) and is
    kept, with its polycube."""
    from polycubenet.pipeline import PipelineConfig, pull_back_learned
    from polycubenet.policy import distance_to_part, ends_chain

    V, F, poly, _ = slanted_l
    cfg = PipelineConfig(target_hexes=1500)
    identity = _Map(lambda P: np.asarray(P, float))
    registration_alone = PipelineConfig(target_hexes=1500, realise=None, learned_maps=("registration",),
                                        pullback=PullbackConfig(capture_spots=False))
    plain, _ = pull_back_learned(poly, identity, V, F, registration_alone)
    assert plain.meta["map"] == "registration" and not ends_chain(plain.meta, cfg.min_sj)
    mesh, used = pull_back_learned(poly, identity, V, F, cfg)
    assert mesh.meta["map"] == "exact (realised)" and ends_chain(mesh.meta, cfg.min_sj)
    assert distance_to_part(mesh.meta) < 0.25 * distance_to_part(plain.meta)
    # the registration's mesh with its uncovered spots mended ends the chain too, but only when no later step
    # does: the realised mesh is closer to the part and better
    mended, _ = pull_back_learned(poly, identity, V, F,
                                  dataclasses.replace(registration_alone, pullback=PullbackConfig()))
    assert mended.meta["spots"]["kept"] and ends_chain(mended.meta, cfg.min_sj)
    assert distance_to_part(mesh.meta) < distance_to_part(mended.meta) and mesh.meta["sj_min"] > mended.meta["sj_min"]
    assert np.array_equal(used.occupancy, poly.occupancy) and "realised_polycube" in mesh.meta


def test_a_near_miss_off_the_part_is_pulled_back_once_more_through_a_denser_partition(slanted_l, monkeypatch):
    """A learned mesh that is valid but a little off the part (on round parts: the partition's) is pulled back
    once more through the same map at ``DENSER_HEXES`` times the hexes, and kept when that one ends the chain;
    a mesh far off the part (a wrong structure, not a coarse partition) is not, and neither is a near miss whose
    denser pull-back is no better (the first mesh kept)."""
    from polycubenet import pipeline, tol
    from polycubenet.data import HexMesh
    from polycubenet.pipeline import PipelineConfig, pull_back_learned
    from polycubenet.policy import DENSER_HEXES

    V, F, poly, _ = slanted_l
    identity = _Map(lambda P: np.asarray(P, float))
    cfg = PipelineConfig(target_hexes=1500, realise=None, learned_maps=("registration",),
                         pullback=PullbackConfig(capture_spots=False))
    base = len(pipeline.partition_polycube(poly, cfg).hexes)
    seen = []

    def fake(off):
        def pull_back(mesh_pc, to_part, Vc, F_, config, diagonal=None):
            n = len(mesh_pc.hexes)
            seen.append(n)
            d = off if n <= base else off / 1.5  # the denser partition follows the part closer
            return HexMesh(mesh_pc.points, mesh_pc.hexes, meta={"valid": True, "sj_min": 0.4, "hausdorff": d})
        return pull_back

    bar = tol.HAUSDORFF_REL_MAX
    monkeypatch.setattr(pipeline, "pull_back", fake(1.3 * bar))
    mesh, _ = pull_back_learned(poly, identity, V, F, cfg)
    assert len(seen) == 2 and seen[1] > 1.2 * seen[0] and seen[1] <= 1.1 * DENSER_HEXES * seen[0]
    assert mesh.meta["map"] == f"registration, {DENSER_HEXES:g}x hexes" and mesh.meta["hausdorff"] < bar
    seen.clear()
    monkeypatch.setattr(pipeline, "pull_back", fake(4 * bar))  # not a near miss
    mesh, _ = pull_back_learned(poly, identity, V, F, cfg)
    assert len(seen) == 1 and mesh.meta["map"] == "registration"
    seen.clear()
    monkeypatch.setattr(pipeline, "pull_back", lambda mesh_pc, *a, **k: (
        seen.append(len(mesh_pc.hexes)) or HexMesh(mesh_pc.points, mesh_pc.hexes, meta={
            "valid": True, "sj_min": 0.4, "hausdorff": 1.3 * bar if len(mesh_pc.hexes) <= base else 1.6 * bar})))
    mesh, _ = pull_back_learned(poly, identity, V, F, cfg)
    assert len(seen) == 2 and mesh.meta["map"] == "registration" and mesh.meta["hausdorff"] == 1.3 * bar
    # the spots are mended first: a near miss the mend brings onto the part costs no denser pull-back; one it
    # leaves off gets it, and the denser mesh is mended too
    mended = dataclasses.replace(cfg, pullback=PullbackConfig(capture_spots=True))
    for reach, pulls in ((1.7, 1), (1.2, 2)):  # how far off the part a mend can still close the gap
        seen.clear()
        monkeypatch.setattr(pipeline, "pull_back", fake(1.6 * bar))  # the denser one 1.07 x the bar off
        monkeypatch.setattr(pipeline, "mend_spots", lambda m, *a, r=reach, **k: HexMesh(
            m.points, m.hexes, meta={**m.meta, "hausdorff": 0.9 * bar, "spots": {"kept": True}})
            if bar < m.meta["hausdorff"] <= r * bar else m)
        mesh, _ = pull_back_learned(poly, identity, V, F, mended)
        assert len(seen) == pulls and mesh.meta["hausdorff"] < bar and mesh.meta["spots"]["kept"]
        assert mesh.meta["map"] == ("registration" if pulls == 1 else f"registration, {DENSER_HEXES:g}x hexes")


def test_the_flow_exports_the_polycube_a_mesh_was_realised_on(tmp_path, slanted_l):
    """The pull-back file carries the realised polycube (its thin slabs collapsed), which the export writes
    instead of the extracted one; a mesh of the registration alone exports the extracted polycube."""
    from polycubenet import library
    from polycubenet.data import HexMesh

    _, _, poly, _ = slanted_l
    extracted = Polycube(poly.xs, poly.ys, np.array([poly.zs[0], poly.zs[1], poly.zs[1] + 0.01, poly.zs[2]]),
                         np.concatenate([poly.occupancy[:, :, :1], poly.occupancy], axis=2), meta={"genus": 0})
    ext = library._save_arrays(tmp_path / "extract.npz", {"polycube": extracted.meta, "cloud": {}},
                               points=np.zeros((1, 3)), normals=np.zeros((1, 3)), xs=extracted.xs, ys=extracted.ys,
                               zs=extracted.zs, occupancy=extracted.occupancy)
    empty = dict(points=np.zeros((8, 3)), hexes=np.arange(8)[None], boundary=np.zeros((0, 4), np.int64))
    plain = HexMesh(**empty, meta={"map": "registration"}).save(tmp_path / "plain.npz")
    realised = HexMesh(**empty, meta={"map": "exact (realised)", "realised_polycube": poly.to_meta()}).save(tmp_path / "r.npz")
    got = library.meshed_polycube(realised, ext)
    assert np.array_equal(got.occupancy, poly.occupancy) and np.allclose(got.zs, poly.zs)
    assert library.meshed_polycube(plain, ext).occupancy.shape == extracted.occupancy.shape


def test_planar_patches_are_the_flat_faces_not_a_finely_tessellated_cylinder():
    from polycubenet.classical import edge_topology
    from polycubenet.frame import face_normals_areas

    box = trimesh.creation.box(extents=[2.0, 1.0, 1.0]).subdivide().subdivide()
    cyl = trimesh.creation.cylinder(radius=0.5, height=2.0, sections=256)
    for m, planar_faces in ((box, 6), (cyl, 2)):
        V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
        n, _ = face_normals_areas(V, F)
        patch = planar_patches(n, edge_topology(F)[1])
        assert len(np.unique(patch[patch >= 0])) == planar_faces  # the box's 6 faces; the cylinder's 2 caps
        if m is cyl:
            side = np.abs(n[:, 2]) < 0.5
            assert (patch[side] == -1).all()


@pytest.mark.parametrize("retry_below, pillowed_sj, want", [
    (0.2, 0.15, [("correction", True), ("harmonic", True), ("correction", False)]),  # under the bar: no pillow
    (0.2, 0.35, [("correction", True)]),  # the first mesh ends the chain: nothing more
    (None, 0.15, [("correction", True)]),  # the classical source (no bar): a valid mesh is kept as it is
])
def test_a_realised_mesh_under_the_bar_is_pulled_back_again_without_the_pillow_layer(monkeypatch, retry_below,
                                                                                      pillowed_sj, want):
    """The pull-back behind a realised polycube tries both interior modes, then both without the pillow
    layer, until a mesh ends the chain, and keeps the best (valid, faithful, higher minimum SJ)."""
    import dataclasses

    from polycubenet import pipeline
    from polycubenet.data import HexMesh

    calls = []

    def fake_pull_back(mesh_pc, to_part, V, F, config, diagonal=None):
        calls.append((config.interior, config.pillow))
        sj = pillowed_sj if config.pillow else 0.31
        return HexMesh(np.zeros((8, 3)), np.arange(8)[None], meta={"valid": True, "sj_min": sj, "hausdorff": 0.004,
                                                                      "pillowed": config.pillow})

    monkeypatch.setattr(pipeline, "pull_back", fake_pull_back)
    cfg = pipeline.PipelineConfig()
    cfg = dataclasses.replace(cfg, classical=dataclasses.replace(cfg.classical, interior="correction"))
    mesh = pipeline._pull_back_classical(None, _Map(lambda P: P), None, None, cfg, retry_below=retry_below)
    assert calls == want
    assert (mesh.meta["interior"], mesh.meta["pillowed"]) == want[-1]  # the last one tried is the best here
    assert mesh.meta["sj_min"] == (0.31 if want[-1][1] is False else pillowed_sj)


def test_the_learned_steps_run_in_their_order_and_stop_at_the_first_mesh_that_ends_the_chain(slanted_l, monkeypatch):
    """``learned_maps`` orders the maps and the exact realisation (``exact``, last when not named): with the
    realisation before the refined map, a realised mesh that ends the chain leaves the refined map unfitted;
    with the refined map first it is fitted and tried before the realisation, but only after a near miss
    (``pipeline.near_miss``): the identity's mesh of the slanted end is far off the part, so it is skipped."""
    from polycubenet import pipeline, policy, registration
    from polycubenet.pipeline import PipelineConfig, pull_back_learned
    from polycubenet.policy import distance_to_part

    V, F, poly, _ = slanted_l
    identity = _Map(lambda P: np.asarray(P, float))
    identity.points = poisson_disk(*polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy), 1000, seed=0).points
    fitted = []
    real_refine = registration.refine

    def counting(corr, part_points, **kw):
        fitted.append(len(part_points))
        return real_refine(corr, part_points, **kw)

    monkeypatch.setattr(registration, "refine", counting)
    cfg = PipelineConfig(target_hexes=1500, learned_maps=("registration", "exact", "refined"))
    mesh, used = pull_back_learned(poly, identity, V, F, cfg)
    assert mesh.meta["map"] == "exact (realised)" and fitted == []
    refined_first = PipelineConfig(target_hexes=1500, learned_maps=("registration", "refined"))  # exact appended
    alone, _ = pull_back_learned(poly, identity, V, F, dataclasses.replace(refined_first, realise=None,
                                                                            learned_maps=("registration",),
                                                                            pullback=PullbackConfig(capture_spots=False)))
    assert not pipeline.near_miss(alone) and distance_to_part(alone.meta) > 0.02
    mesh, _ = pull_back_learned(poly, identity, V, F, refined_first)
    assert fitted == [] and mesh.meta["map"] == "exact (realised)"
    monkeypatch.setattr(policy, "REFINE_NEAR_MISS", 1e3)  # every valid mesh a near miss
    mesh, _ = pull_back_learned(poly, identity, V, F, refined_first)
    assert fitted == [refined_first.n_sample]
    assert mesh.meta["map"] in ("refined", "exact (realised)")
    with pytest.raises(ValueError, match="learned_maps"):
        pull_back_learned(poly, identity, V, F, PipelineConfig(target_hexes=1500, learned_maps=("exact",)))


def test_the_map_and_the_rest_in_two_calls_give_what_one_call_gives(slanted_l):
    """``phase="map"`` runs the registration's map alone (no mend, no realisation); ``phase="rest"`` with that
    mesh runs the realisation (and the mend and denser pull-back after it): the mesh, its map and its polycube
    are those of one call.  A map's mesh that ends the chain needs no rest."""
    from polycubenet.pipeline import PipelineConfig, pull_back_learned
    from polycubenet.policy import ends_chain

    V, F, poly, shear = slanted_l
    cfg = PipelineConfig(target_hexes=1500)
    identity = _Map(lambda P: np.asarray(P, float))  # misses the slant: the realisation meshes it
    whole, whole_poly = pull_back_learned(poly, identity, V, F, cfg)
    first, _ = pull_back_learned(poly, identity, V, F, cfg, phase="map")
    assert first.meta["map"] == "registration" and "spots" not in first.meta and not ends_chain(first.meta, cfg.min_sj)
    rest, rest_poly = pull_back_learned(poly, identity, V, F, cfg, phase="rest", prior=first)
    assert rest.meta["map"] == whole.meta["map"] == "exact (realised)"
    assert np.allclose(rest.points, whole.points) and np.array_equal(rest.hexes, whole.hexes)
    assert np.array_equal(rest_poly.occupancy, whole_poly.occupancy) and rest.meta["sj_min"] == whole.meta["sj_min"]
    exact = _Map(shear)  # the true map: its own mesh ends the chain
    first, _ = pull_back_learned(poly, exact, V, F, cfg, phase="map")
    whole, _ = pull_back_learned(poly, exact, V, F, cfg)
    assert ends_chain(first.meta, cfg.min_sj) and whole.meta["map"] == "registration"
    assert np.allclose(first.points, whole.points)
    with pytest.raises(ValueError, match="prior"):
        pull_back_learned(poly, identity, V, F, cfg, phase="rest")
    with pytest.raises(ValueError, match="first of learned_maps"):
        pull_back_learned(poly, identity, V, F, PipelineConfig(target_hexes=1500, learned_maps=("exact", "registration")),
                          phase="map")


def test_the_second_labelling_is_tried_only_after_the_first_realised_the_structure(slanted_l, monkeypatch):
    """A labelling whose flattened part does not bound the learned structure ends the realisation (the other
    labelling is not flattened too); one that realised it but whose mesh does not end the chain (under the bar)
    is followed by the next labelling."""
    import types

    from polycubenet import pipeline
    from polycubenet.data import HexMesh
    from polycubenet.pipeline import PipelineConfig, pull_back_learned

    V, F, poly, _ = slanted_l
    cfg = PipelineConfig(target_hexes=800, learned_maps=("registration", "exact"),
                         pullback=PullbackConfig(capture_spots=False))
    monkeypatch.setattr(pipeline, "pull_back", lambda mesh_pc, *a, **k: HexMesh(
        mesh_pc.points, mesh_pc.hexes, meta={"valid": True, "sj_min": 0.4, "hausdorff": 0.05}))  # far off: no refined
    tried = []

    def refused(Vc, F_, p, corr, rc, **kw):
        tried.append(rc.planar_patches)
        return None, "the part flattened on the learned labels differs from the learned polycube: 6 cells differ"

    monkeypatch.setattr(pipeline, "learned_map", refused)
    mesh, _ = pull_back_learned(poly, _Map(lambda P: np.asarray(P, float)), V, F, cfg)
    assert tried == [True] and mesh.meta["map"].startswith("registration (") and "6 cells differ" in mesh.meta["map"]
    tried.clear()

    def realised(Vc, F_, p, corr, rc, **kw):
        tried.append(rc.planar_patches)
        return types.SimpleNamespace(polycube=p, map=types.SimpleNamespace(meta={"method": "fake"})), None

    monkeypatch.setattr(pipeline, "learned_map", realised)
    monkeypatch.setattr(pipeline, "_pull_back_classical", lambda mesh_pc, *a, **k: HexMesh(
        mesh_pc.points, mesh_pc.hexes, meta={"valid": True, "sj_min": 0.1, "hausdorff": 0.001}))  # under the bar
    pull_back_learned(poly, _Map(lambda P: np.asarray(P, float)), V, F, cfg)
    assert tried == [True, False]


def test_a_near_miss_map_mesh_opens_the_refined_map_even_when_a_farther_realised_mesh_outranks_it(slanted_l,
                                                                                                   monkeypatch):
    """The refined map is fitted after any near miss so far, not only when the best mesh is one: a realised mesh
    far off the part but above the quality bar ranks above the registration's near miss under it, and the refined
    map's mesh, faithful and above the bar, then ends the chain (never-seen mixed_1163_002, session 87)."""
    import types

    from polycubenet import pipeline, registration
    from polycubenet.data import HexMesh
    from polycubenet.pipeline import PipelineConfig, pull_back_learned

    V, F, poly, _ = slanted_l
    cfg = PipelineConfig(target_hexes=800, learned_maps=("registration", "exact", "refined"),
                         pullback=PullbackConfig(capture_spots=False))
    maps = iter([{"valid": True, "sj_min": 0.09, "hausdorff": 0.0105},  # the registration's: a near miss, under the bar
                 {"valid": True, "sj_min": 0.24, "hausdorff": 0.0084}])  # the refined map's: ends the chain

    def fake_pull_back(mesh_pc, to_part, *a, **k):
        getattr(to_part, "map_points", to_part)(mesh_pc.points[:1])  # the refined map is fitted on its first use
        return HexMesh(mesh_pc.points, mesh_pc.hexes, meta=dict(next(maps)))

    monkeypatch.setattr(pipeline, "pull_back", fake_pull_back)
    monkeypatch.setattr(pipeline, "learned_map", lambda Vc, F_, p, corr, rc, **kw: (types.SimpleNamespace(
        polycube=p, map=types.SimpleNamespace(meta={"method": "fake", "structure": "part"})), None))
    monkeypatch.setattr(pipeline, "_pull_back_classical", lambda mesh_pc, *a, **k: HexMesh(
        mesh_pc.points, mesh_pc.hexes, meta={"valid": True, "sj_min": 0.30, "hausdorff": 0.045}))  # far off, above
    fitted = []
    monkeypatch.setattr(registration, "refine", lambda corr, part_points, **kw: fitted.append(1) or corr)
    first, _ = pull_back_learned(poly, _Map(lambda P: np.asarray(P, float)), V, F, cfg, phase="map")
    mesh, _ = pull_back_learned(poly, _Map(lambda P: np.asarray(P, float)), V, F, cfg, phase="rest", prior=first)
    assert fitted == [1] and mesh.meta["map"].startswith("refined") and mesh.meta["hausdorff"] == 0.0084
