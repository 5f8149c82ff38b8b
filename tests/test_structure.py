"""Polycube structure extraction and regular partition on small known cases."""

from __future__ import annotations

import numpy as np
import pytest

from polycubenet.data import Polycube
from polycubenet.errors import PolycubeError
from polycubenet.hexmesh import boundary_quads, hex_volumes, partition
from polycubenet.polycube import compress, polycube_surface, solid_genus
from polycubenet.quality import scaled_jacobian
from polycubenet.sampling import poisson_disk
from polycubenet.structure import ExtractConfig, cluster_planes, extract


def _l_block() -> Polycube:
    occ = np.zeros((2, 1, 2), bool)
    occ[:, 0, 0] = True
    occ[0, 0, 1] = True
    return Polycube(np.array([-0.4, 0.0, 0.4]), np.array([-0.15, 0.15]), np.array([-0.2, 0.0, 0.2]), occ)


def _genus2() -> Polycube:
    """A 5 x 3 plate with two through holes along z."""
    occ = np.ones((5, 3, 1), bool)
    occ[1, 1, 0] = occ[3, 1, 0] = False
    g = np.array([-0.45, -0.3, -0.1, 0.1, 0.3, 0.45])
    return Polycube(g, np.array([-0.25, -0.08, 0.08, 0.25]), np.array([-0.06, 0.06]), occ)


def _cloud(poly: Polycube, n: int, noise: float, outliers: float, seed: int):
    V, F = polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy)
    s = poisson_disk(V, F, n, seed=seed)
    rng = np.random.default_rng(seed)
    P = s.points + rng.normal(scale=noise, size=s.points.shape)
    N = s.normals.copy()
    k = int(outliers * n)
    if k:
        P = np.vstack([P, rng.uniform(P.min(0), P.max(0), size=(k, 3))])
        N = np.vstack([N, rng.normal(size=(k, 3))])
    return P, N


def _same_solid(a: Polycube, b: Polycube, atol: float) -> bool:
    ga, oa = compress([a.xs, a.ys, a.zs], a.occupancy)
    gb, ob = compress([b.xs, b.ys, b.zs], b.occupancy)
    return oa.shape == ob.shape and bool((oa == ob).all()) and all(np.allclose(x, y, atol=atol) for x, y in zip(ga, gb))


@pytest.mark.parametrize("make,genus", [(_l_block, 0), (_genus2, 2)])
@pytest.mark.parametrize("noise,outliers", [(0.0, 0.0), (0.005, 0.02)])
def test_extract_recovers_known_polycube(make, genus, noise, outliers):
    truth = make()
    assert solid_genus(truth.occupancy) == genus
    P, N = _cloud(truth, 8192, noise, outliers, seed=3)
    got = extract(P, N, genus=genus)
    assert _same_solid(got, truth, atol=max(3 * noise, 1e-3))
    assert got.meta["genus"] == genus and got.meta["coverage"] > 0.95


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_extract_retries_without_the_plane_filter_when_a_narrow_hole_is_lost(seed):
    """A plate with a hole one point spacing wide (2048 points): the hole's walls carry a few
    points each, fewer than the plane filter asks for, so the filtered extraction finds genus 0
    and fails the part's genus 1.  The relaxed second try (planes of one point) recovers it."""
    occ = np.ones((3, 3, 1), bool)
    occ[1, 1, 0] = False
    truth = Polycube(np.array([-0.45, -0.0125, 0.0125, 0.45]), np.array([-0.3, -0.0125, 0.0125, 0.3]),
                     np.array([-0.05, 0.05]), occ)
    P, N = _cloud(truth, 2048, 0.0, 0.0, seed=seed)
    with pytest.raises(PolycubeError, match="genus 0 differs"):
        extract(P, N, genus=1, config=ExtractConfig(relaxed_plane_points=None))
    got = extract(P, N, genus=1)
    assert _same_solid(got, truth, atol=2e-3)
    assert "genus 0 differs" in got.meta["relaxed_planes"]


def test_extract_rejects_wrong_genus_with_reason():
    P, N = _cloud(_genus2(), 8192, 0.0, 0.0, seed=1)
    with pytest.raises(PolycubeError, match="genus 2 differs from the part's genus 1") as err:
        extract(P, N, genus=1, part="plate.step")
    assert "plate.step" in str(err.value)


def test_extract_rejects_a_cloud_that_is_not_a_polycube():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(4000, 3))
    P /= np.linalg.norm(P, axis=1, keepdims=True)  # a sphere: normals everywhere
    with pytest.raises(PolycubeError):
        extract(0.5 * P, P)


def test_cluster_planes_separates_and_merges():
    rng = np.random.default_rng(0)
    c = np.concatenate([rng.normal(0.0, 0.002, 300), rng.normal(0.05, 0.002, 300), rng.normal(0.052, 0.002, 10)])
    planes = cluster_planes(c, bandwidth=0.002, min_points=5, merge=0.006)
    assert len(planes) == 2
    np.testing.assert_allclose(planes, [0.0, 0.05], atol=1.5e-3)


def test_cluster_planes_keeps_two_close_faces_that_face_opposite_ways():
    """Two planes closer than the merge distance: one plane when their points face one way (a thick face),
    two when they face opposite ways (the faces of a thin plate), unless closer than ``sheet``."""
    rng = np.random.default_rng(1)
    c = np.concatenate([rng.normal(0.0, 0.0005, 200), rng.normal(0.005, 0.0005, 200)])
    up = np.r_[np.full(200, -1), np.full(200, 1)]
    assert len(cluster_planes(c, bandwidth=0.003, min_points=5, merge=0.006)) == 1
    assert len(cluster_planes(c, 0.003, 5, 0.006, signs=np.ones(400), sheet=0.003)) == 1
    got = cluster_planes(c, 0.003, 5, 0.006, signs=up, sheet=0.003)
    np.testing.assert_allclose(got, [0.0, 0.005], atol=3e-4)  # each face placed by its own points
    assert len(cluster_planes(c, 0.003, 5, 0.006, signs=up, sheet=0.006)) == 1


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_extract_keeps_a_plate_thinner_than_the_merge_distance(seed):
    """A block with a fin 0.6 point spacings thick (2048 points): the fin's two faces are closer than the
    merge distance, so merged into one plane they leave a sheet of no thickness and the cloud is far from
    the polycube; kept apart because they face opposite ways, the fin is recovered."""
    occ = np.zeros((2, 1, 3), bool)
    occ[0, 0, :] = True
    occ[1, 0, 1] = True
    truth = Polycube(np.array([-0.4, 0.0, 0.4]), np.array([-0.3, 0.3]), np.array([-0.2, -0.007, 0.007, 0.2]), occ)
    P, N = _cloud(truth, 2048, 0.0, 0.0, seed=seed)
    with pytest.raises(PolycubeError, match="cloud is far from the extracted polycube"):
        extract(P, N, genus=0, config=ExtractConfig(sheet_bandwidths=None))
    got = extract(P, N, genus=0)
    assert _same_solid(got, truth, atol=2e-3)


def test_partition_is_conforming_and_fills_the_polycube():
    poly = _genus2()
    m = partition(poly, target_hexes=3000)
    vol = hex_volumes(m.points, m.hexes)
    assert (vol > 0).all()
    cell = np.multiply.outer(np.multiply.outer(np.diff(poly.xs), np.diff(poly.ys)), np.diff(poly.zs))
    np.testing.assert_allclose(vol.sum(), cell[poly.occupancy].sum(), rtol=1e-12)
    np.testing.assert_allclose(scaled_jacobian(m.points, m.hexes), 1.0, atol=1e-12)
    assert 0.7 * 3000 < len(m.hexes) < 1.4 * 3000
    # conforming: the boundary is exactly the polycube surface (every interior face shared by two hexes)
    q = boundary_quads(m.hexes)
    area = 0.0
    for quad in m.points[q]:
        area += np.linalg.norm(np.cross(quad[1] - quad[0], quad[3] - quad[0]))
    V, F = polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy)
    tri = V[F]
    area_ref = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    np.testing.assert_allclose(area, area_ref, rtol=1e-9)
    assert m.boundary.sum() == len(np.unique(q))


def test_partition_size_controls():
    poly = _l_block()
    coarse = partition(poly, target_size=0.2)
    fine = partition(poly, target_size=0.05)
    assert len(fine.hexes) > 20 * len(coarse.hexes)
    with pytest.raises(ValueError, match="not both"):
        partition(poly, target_size=0.1, target_hexes=10)


def test_plane_offset_tells_displaced_planes_from_other_cells():
    """The evaluation's split of "other structure": the same cells with planes moved (their largest
    move), or other cells (None); an extra plane between equal slabs changes nothing."""
    from polycubenet.polycube import plane_offset, same_structure

    occ = np.zeros((2, 1, 2), bool)
    occ[:, 0, 0] = True
    occ[0, 0, 1] = True  # an L
    a = Polycube(np.array([-0.4, 0.0, 0.4]), np.array([-0.15, 0.15]), np.array([-0.2, 0.0, 0.2]), occ)
    moved = Polycube(a.xs + np.array([0.0, 0.03, 0.0]), a.ys, a.zs - 0.01, occ)
    assert plane_offset(a, moved) == pytest.approx(0.03)
    assert not same_structure(a, moved, atol=0.02) and same_structure(a, moved, atol=0.04)
    split = Polycube(np.array([-0.4, -0.2, 0.0, 0.4]), a.ys, a.zs, np.concatenate([occ[:1], occ], axis=0))
    assert plane_offset(a, split) == pytest.approx(0.0)
    other = occ.copy()
    other[1, 0, 1] = True  # the full block
    assert plane_offset(a, Polycube(a.xs, a.ys, a.zs, other)) is None


def _slanted_block(deg: float, seed: int):
    """A 0.8 x 0.3 x 0.2 block whose -x end is one face slanted ``deg`` degrees from upright over the
    whole height, sampled with 4096 points whose normals are snapped to their nearest axis, as the
    model generates them: the slanted face is a ramp of -x (or +z) points."""
    import trimesh

    top = -0.4 + 0.2 * np.tan(np.radians(deg))
    xz = [(-0.4, -0.1), (0.4, -0.1), (0.4, 0.1), (top, 0.1)]
    m = trimesh.convex.convex_hull(np.array([(x, y, z) for x, z in xz for y in (-0.15, 0.15)])).subdivide()
    s = poisson_disk(np.asarray(m.vertices), np.asarray(m.faces), 4096, seed=seed)
    k = np.argmax(np.abs(s.normals), axis=1)
    N = np.zeros_like(s.normals)
    N[np.arange(len(N)), k] = np.sign(s.normals[np.arange(len(N)), k])
    return s.points, N


@pytest.mark.parametrize("deg,seed", [(35, 1), (40, 0), (45, 2)])
def test_extract_flattens_a_slanted_end_into_the_end_face(deg, seed):
    """Without flattening, the ramp's points cluster into thin planes at many x and the cloud is far
    from every polycube the vote makes; flattened, the ramp is the block's end face and the polycube one
    box, whose -x plane lies within the ramp (between the slant's foot at x = -0.4 and its top)."""
    P, N = _slanted_block(deg, seed)
    with pytest.raises(PolycubeError, match="far from the extracted polycube"):
        extract(P, N, genus=0, config=ExtractConfig().for_exact_clouds())  # no fallbacks
    got = extract(P, N, genus=0, config=ExtractConfig(ramp_min_deg=10.0))
    assert got.occupancy.shape == (1, 1, 1) and got.occupancy.all()
    top = -0.4 + 0.2 * np.tan(np.radians(deg))
    assert -0.41 < got.xs[0] < top and abs(got.xs[1] - 0.4) < 0.01
    assert abs(got.zs[0] + 0.1) < 0.01 and abs(got.zs[1] - 0.1) < 0.01
    assert "ramp(s)" in got.meta["ramps"]


def test_flatten_ramps_leaves_axis_faces_and_steps_alone():
    """An L-block's cloud (two parallel -z faces a step apart, edges between faces) has no ramp."""
    from polycubenet.structure import axis_labels, flatten_ramps, point_spacing

    P, N = _cloud(_l_block(), 4096, 0.002, 0.0, seed=4)
    axis, sign = axis_labels(N)
    flat, n_ramps, n_moved = flatten_ramps(P, axis, sign, point_spacing(P))
    assert n_ramps == 0 and n_moved == 0 and np.array_equal(flat, P)


@pytest.mark.parametrize("deg,seed", [(30, 3), (40, 0), (45, 2)])
def test_flatten_ramps_takes_a_sparse_ramp_whole(deg, seed, monkeypatch):
    """A generated ramp is sparser than the faces around it (a quarter of the slanted end's points
    here): its slanted points split into patches a flood of 2.5 spacings does not join.  Every point of
    the ramp moves, and no point off it; without the on-plane pass some of the ramp stays behind."""
    import polycubenet.structure as structure
    from polycubenet.structure import axis_labels, flatten_ramps, point_spacing

    P, N = _slanted_block(deg, seed)
    on = np.abs(P[:, 0] - (-0.4 + (P[:, 2] + 0.1) * np.tan(np.radians(deg)))) < 1e-6
    keep = ~on | (np.random.default_rng(seed).random(len(P)) < 0.25)
    P, N, ramp = P[keep], N[keep], on[keep]
    axis, sign = axis_labels(N)

    def moved():
        flat, n_ramps, _ = flatten_ramps(P, axis, sign, point_spacing(P))
        assert n_ramps >= 1
        return np.any(flat != P, axis=1)

    got = moved()
    assert got[ramp].all() and not got[~ramp].any()
    monkeypatch.setattr(structure, "RAMP_ON_PLANE", False)
    assert not moved()[ramp].all()


def test_only_a_generated_cloud_gets_the_generator_fallbacks():
    """With the fallbacks configured, the pipeline extracts a learned cloud with them, a classical
    flattening's cloud without them: the same slanted-end cloud gives a box as ``learned`` and is
    rejected as ``classical``."""
    import dataclasses

    from polycubenet.data import PolycubeCloud
    from polycubenet.pipeline import PipelineConfig, cloud_polycube
    from polycubenet.structure import GENERATOR_FALLBACKS

    P, N = _slanted_block(40, 0)
    cfg = PipelineConfig(extract=dataclasses.replace(ExtractConfig(), **GENERATOR_FALLBACKS))
    learned = cloud_polycube(PolycubeCloud(P, N, meta={"provenance": "learned"}), P, N, 0, cfg, "part")
    assert learned.occupancy.shape == (1, 1, 1) and learned.meta["provenance"] == "learned"
    with pytest.raises(PolycubeError, match="far from the extracted polycube"):
        cloud_polycube(PolycubeCloud(P, N, meta={"provenance": "classical"}), P, N, 0, cfg, "part")


def test_only_the_first_draw_and_the_one_step_draws_get_the_generator_fallbacks():
    """The model's 4-step further draw (``learned+1``) is extracted bare: the slanted-end cloud that the
    first draw's extraction flattens into a box is rejected as a second draw's; the one-step draw at
    another seed (``learned+2``) is extracted as the first; classical and voxel sources keep the config
    as it is."""
    from polycubenet.data import PolycubeCloud
    from polycubenet.pipeline import PipelineConfig, cloud_polycube
    from polycubenet.policy import extraction_config

    P, N = _slanted_block(40, 0)
    cfg = PipelineConfig()
    cloud = PolycubeCloud(P, N, meta={"provenance": "learned"})
    first = cloud_polycube(cloud, P, N, 0, extraction_config("learned", cfg), "part")
    assert first.occupancy.shape == (1, 1, 1) and "ramps" in first.meta
    with pytest.raises(PolycubeError, match="far from the extracted polycube"):
        cloud_polycube(cloud, P, N, 0, extraction_config("learned+1", cfg), "part")
    assert cloud_polycube(cloud, P, N, 0, extraction_config("learned+2", cfg), "part").occupancy.shape == (1, 1, 1)
    assert extraction_config("classical", cfg) is cfg and extraction_config("voxel+2", cfg) is cfg


def _slanted_block_mesh(deg: float):
    """The 0.8 x 0.3 x 0.2 block of :func:`_slanted_block` as a triangle mesh (planar faces)."""
    import trimesh

    top = -0.4 + 0.2 * np.tan(np.radians(deg))
    xz = [(-0.4, -0.1), (0.4, -0.1), (0.4, 0.1), (top, 0.1)]
    m = trimesh.convex.convex_hull(np.array([(x, y, z) for x, z in xz for y in (-0.15, 0.15)]))
    return np.asarray(m.vertices), np.asarray(m.faces)


def test_plane_patches_finds_each_planar_face_and_leaves_a_round_one():
    """Anchors on the slanted block: six planar faces, each one patch (the slanted end among them);
    on a faceted cylinder's wall no strip is wide enough to be a face, while its two caps are."""
    import trimesh

    from polycubenet.planesnap import plane_patches
    from polycubenet.sampling import uniform_sample

    V, F = _slanted_block_mesh(30)
    s = uniform_sample(V, F, 4096, np.random.default_rng(0))
    patch = plane_patches(s.points, s.normals)
    assert patch.max() + 1 == 6 and (patch >= 0).mean() > 0.9
    slanted = np.abs(s.normals[:, 0]) > 0.5  # the slanted end (normal 30 deg from -x) and the +x end
    for r in np.unique(patch[slanted & (patch >= 0)]):  # each patch holds one face's normal only
        assert np.ptp(s.normals[patch == r], axis=0).max() < 1e-6
    cyl = trimesh.creation.cylinder(radius=0.2, height=0.6, sections=48)
    c = uniform_sample(np.asarray(cyl.vertices), np.asarray(cyl.faces), 4096, np.random.default_rng(1))
    p = plane_patches(c.points, c.normals)
    wall = np.abs(c.normals[:, 2]) < 0.5
    assert (p[wall] == -1).all() and (p[~wall] >= 0).mean() > 0.9 and p.max() + 1 == 2


def test_snap_planes_puts_a_slanted_face_on_one_plane_and_leaves_the_rest():
    """A cloud that took the slanted end half the way to the -x end face (a ramp, as the model leaves
    it): the end's points go to one x; the axis faces are left as they are with ``min_deg=5``, and the
    extraction then gives one box where the ramp alone gives more slabs."""
    from polycubenet.planesnap import snap_planes
    from polycubenet.sampling import uniform_sample

    deg = 40.0
    V, F = _slanted_block_mesh(deg)
    s = uniform_sample(V, F, 4096, np.random.default_rng(2))
    A, AN = s.points, s.normals
    end = AN[:, 0] < -0.5
    P = A.copy()
    P[end, 0] = -0.4 + 0.5 * (A[end, 0] + 0.4)  # half the way onto x = -0.4
    P += np.random.default_rng(3).normal(0.0, 0.002, P.shape)
    k = np.argmax(np.abs(AN), axis=1)
    N = np.zeros_like(AN)
    N[np.arange(len(N)), k] = np.sign(AN[np.arange(len(N)), k])
    got, info = snap_planes(P, N, A, AN, min_deg=5.0)
    # a white-noise sample leaves a few of the end's points in gaps wider than the face's reach: those stay
    assert info["faces"] == 1 and info["tilted"] == 1 and info["points"] >= 0.95 * end.sum()
    x, count = np.unique(got[end, 0], return_counts=True)
    assert count.max() == info["points"] and np.array_equal(got[~end], P[~end])
    assert -0.4 < x[np.argmax(count)] < -0.4 + 0.5 * 0.2 * np.tan(np.radians(deg))
    cfg = ExtractConfig().for_exact_clouds()
    poly = extract(got, N, genus=0, config=cfg)
    assert poly.occupancy.shape == (1, 1, 1)
    try:
        ramp = extract(P, N, genus=0, config=cfg).occupancy.shape
    except PolycubeError:
        ramp = None
    assert ramp != (1, 1, 1)


def test_clean_cloud_snaps_a_learned_cloud_only_and_the_flow_file_keeps_what_it_needs(tmp_path):
    """Both drivers clean a cloud through ``pipeline.clean_cloud``: a learned cloud whose anchors carry the
    part's normals gets its slanted face on one plane (``snap_planes=5``), the same cloud as a classical
    one or with ``snap_planes=None`` (the default) does not; the flow's saved cloud (``write_generated``)
    keeps the anchors' normals for it."""
    import dataclasses

    from polycubenet.data import PolycubeCloud
    from polycubenet.library import write_generated
    from polycubenet.pipeline import PipelineConfig, clean_cloud
    from polycubenet.sampling import uniform_sample

    V, F = _slanted_block_mesh(40.0)
    s = uniform_sample(V, F, 4096, np.random.default_rng(2))
    end = s.normals[:, 0] < -0.5
    P = s.points.copy()
    P[end, 0] = -0.4 + 0.5 * (s.points[end, 0] + 0.4)
    k = np.argmax(np.abs(s.normals), axis=1)
    N = np.zeros_like(P)
    N[np.arange(len(N)), k] = np.sign(s.normals[np.arange(len(N)), k])
    path = write_generated(np.hstack([P, N]), tmp_path / "cloud.npz", {"checkpoint": "test"},
                           anchors=np.hstack([s.points, s.normals]))
    cloud = PolycubeCloud.load(path)
    assert np.allclose(cloud.anchor_normals, s.normals)

    def spread(c, cfg):
        Q, _, keep = clean_cloud(c, cfg)
        return np.ptp(Q[end[keep], 0])

    cfg = PipelineConfig(snap_planes=5.0)
    assert PipelineConfig().snap_planes is None
    assert spread(cloud, cfg) < 0.25 * spread(cloud, dataclasses.replace(cfg, snap_planes=None))
    assert cloud.meta["snapped"]["tilted"] == 1
    classical = dataclasses.replace(cloud, meta={"provenance": "classical"})
    assert spread(classical, cfg) == spread(cloud, dataclasses.replace(cfg, snap_planes=None))


def _polish_cell_by_cell(occ, costs, sweeps):
    """The polish as first written: every cell's flip delta, one cell after another, each sweep."""
    from polycubenet.polycube import check_occupancy
    from polycubenet.structure import _cell_flip_delta

    occ = occ.copy()
    valid = check_occupancy(occ) is None
    for _ in range(sweeps):
        changed = False
        for cell in np.ndindex(occ.shape):
            if _cell_flip_delta(occ, costs, cell) >= -1e-9:
                continue
            occ[cell] = not occ[cell]
            now_valid = check_occupancy(occ) is None
            if now_valid or not valid:
                valid, changed = now_valid, True
            else:
                occ[cell] = not occ[cell]
        if not changed:
            break
    return occ


@pytest.mark.parametrize("seed", range(6))
def test_polish_makes_the_flips_of_the_cell_by_cell_sweep(seed):
    """The polish looks only at cells whose flip lowers the cost and at the later neighbours of a flipped
    cell: it must end where visiting every cell in order ends, and its all-cells delta must be the scalar one."""
    from polycubenet.structure import _cell_flip_delta, _flip_deltas, _polish

    rng = np.random.default_rng(seed)
    shape = tuple(int(n) for n in rng.integers(3, 8, size=3))
    costs = []
    for a in range(3):
        fshape = list(shape)
        fshape[a] += 1
        # integer-valued vote counts (as the evidence gives) and fractional coverage terms
        costs.append(tuple(rng.integers(0, 6, size=fshape) + rng.random(fshape) * (k > 0) for k in range(3)))
    if seed % 2:  # a valid solid (a block with a notch) that must stay valid
        occ = np.ones(shape, dtype=bool)
        occ[: shape[0] // 2, : shape[1] // 2, :] = False
    else:
        occ = rng.random(shape) < 0.6
    deltas = _flip_deltas(occ, costs)
    for cell in np.ndindex(shape):
        assert deltas[cell] == pytest.approx(_cell_flip_delta(occ, costs, cell), abs=1e-9)
    got = _polish(occ, costs, 6)
    want = _polish_cell_by_cell(occ, costs, 6)
    assert (got != occ).any()  # the case flips something
    np.testing.assert_array_equal(got, want)


def test_cell_contacts_keep_the_grid_count_of_contacts_up_to_date():
    """Flipping cells one by one and updating the count by each cell's own edges and corners must give the
    count of the whole grid every time."""
    from polycubenet.polycube import cell_contacts, edge_contacts, nonmanifold_vertices

    rng = np.random.default_rng(0)
    occ = rng.random((5, 6, 4)) < 0.5
    padded = np.pad(occ, 1)
    count = len(edge_contacts(occ)) + len(nonmanifold_vertices(occ))
    seen = set()
    for _ in range(200):
        cell = tuple(int(rng.integers(n)) for n in occ.shape)
        before = cell_contacts(padded, cell)
        occ[cell] = padded[tuple(i + 1 for i in cell)] = not occ[cell]
        count += cell_contacts(padded, cell) - before
        assert count == len(edge_contacts(occ)) + len(nonmanifold_vertices(occ))
        seen.add(count)
    assert len(seen) > 5  # the count moved
