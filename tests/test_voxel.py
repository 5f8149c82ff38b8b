"""The voxel polycube: occupancy, repairs, images on the part, the cloud and a full pullback."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from polycubenet.classical import DIRECTIONS, ClassicalCloud
from polycubenet.cleanup import remove_outliers
from polycubenet.errors import PolycubeError
from polycubenet.frame import canonicalize, face_normals_areas
from polycubenet.hexmesh import enclosed_volume, partition
from polycubenet.pipeline import PipelineConfig, cloud_polycube
from polycubenet.polycube import check_occupancy, compress, edge_contacts, nonmanifold_vertices, same_structure, solid_genus, surface_genus
from polycubenet.pullback import pull_back
from polycubenet.structure import extract
from polycubenet.voxel import (
    VERSION,
    VoxelConfig,
    VoxelSource,
    _scene,
    repair_occupancy,
    voxel_polycube,
)

# a smaller cloud and a narrower resolution range keep the tests fast
FAST = VoxelConfig(min_cells=8, max_cells=20, extra_steps=0)


def _canon(m):
    V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    Vc, _ = canonicalize(V, F)
    return Vc, F


@pytest.fixture(scope="module")
def torus_c():
    return _canon(trimesh.creation.torus(1.0, 0.4, major_sections=40, minor_sections=20))


@pytest.fixture(scope="module")
def dumbbell_c():
    """Two blocks joined by a bar much thinner than a coarse cell (genus 0)."""
    a = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]])
    b = trimesh.creation.box(bounds=[[3, 0, 0], [4, 1, 1]])
    bar = trimesh.creation.box(bounds=[[0.9, 0.45, 0.45], [3.1, 0.55, 0.55]])
    m = trimesh.boolean.union([a, b, bar], engine="manifold")
    m = m.subdivide_to_size(0.2)
    return _canon(m)


def _distance_to(V, F, X):
    import open3d as o3d

    r = _scene(V, F).compute_closest_points(o3d.core.Tensor(np.asarray(X, np.float32)))
    return np.linalg.norm(r["points"].numpy() - X, axis=1)


def test_repair_removes_edge_and_vertex_contacts():
    occ = np.zeros((4, 4, 4), bool)
    occ[1, 1, 1] = occ[2, 2, 1] = True  # edge-only contact
    occ3 = np.zeros((4, 4, 4), bool)
    occ3[1, 1, 1] = occ3[2, 2, 2] = True  # vertex-only contact
    for o in (occ, occ3):
        assert check_occupancy(o) is not None
        frac = np.random.default_rng(0).random(o.shape)
        fixed, rep = repair_occupancy(o, frac)
        assert check_occupancy(fixed) is None
        assert len(edge_contacts(fixed)) == 0 and len(nonmanifold_vertices(fixed)) == 0
        assert (fixed >= o).all()  # repairs only add cells here (one component after adding)
        assert rep["added"] >= 1


def test_torus_voxel_polycube_has_the_parts_genus_and_images_on_the_part(torus_c):
    V, F = torus_c
    Vp, Vs, Fs, labels, poly, meta = voxel_polycube(V, F, FAST)
    assert meta["genus"] == 1 == meta["part_genus"] == poly.meta["genus"]
    assert solid_genus(poly.occupancy) == 1 and poly.occupancy.sum() == meta["cells"]
    assert surface_genus(Fs) == 1
    # outward, axis-aligned triangles with the classical label convention
    assert enclosed_volume(Vp, Fs) > 0
    n, _ = face_normals_areas(Vp, Fs)
    np.testing.assert_allclose(n, DIRECTIONS[labels], atol=1e-9)
    # images on the part, and close to their voxel vertex (within a couple of cells)
    assert _distance_to(V, F, Vs).max() < 1e-4
    assert np.linalg.norm(Vs - Vp, axis=1).max() < 2.0 * meta["cell_size"]
    assert meta["flipped"] == 0
    import json

    json.dumps(meta)  # JSON-able
    assert VERSION == "3"


def test_too_coarse_a_range_is_rejected(torus_c):
    V, F = torus_c
    with pytest.raises(PolycubeError):
        voxel_polycube(V, F, dataclasses.replace(FAST, min_cells=2, max_cells=3))


def test_thin_bar_survives(dumbbell_c):
    V, F = dumbbell_c
    Vp, Vs, Fs, labels, _, meta = voxel_polycube(V, F, FAST)
    assert meta["genus"] == 0
    # the bar (much thinner than a cell at this resolution) is in the voxel solid: every point
    # of the part is near the voxel boundary, in particular the middle of the bar
    h = meta["cell_size"]
    assert _distance_to(Vp, Fs, V).max() <= 2.0 * h
    mid = V[np.argmin(np.abs(V[:, 0]))]  # canonical frame: the bar's middle is at x = 0
    assert _distance_to(Vp, Fs, mid[None])[0] <= 2.0 * h
    assert _distance_to(V, F, Vs).max() < 1e-4


def test_source_cloud_extracts_and_pulls_back_valid(torus_c):
    V, F = torus_c
    cfg = PipelineConfig(n_polycube=4096, target_hexes=1000)
    cloud = VoxelSource(FAST)(None, V, F, cfg)
    assert isinstance(cloud, ClassicalCloud)
    assert cloud.meta["provenance"] == "voxel"
    assert len(cloud.points) == cfg.n_polycube
    P, N, _ = remove_outliers(cloud.points, cloud.normals)
    # the pipeline takes the voxel solid as built (not re-extracted from the cloud)
    poly = cloud_polycube(cloud, P, N, 1, cfg)
    assert poly.meta["genus"] == 1 and poly.meta["exact"] and poly.meta["provenance"] == "voxel"
    exact = cloud.exact_polycube()
    assert same_structure(poly, exact, atol=1e-12)
    grid, _ = compress([exact.xs, exact.ys, exact.zs], exact.occupancy)
    np.testing.assert_array_equal(poly.xs, grid[0])
    # the extraction of the same cloud agrees at this coarse resolution (planes a cell apart)
    assert same_structure(extract(P, N, genus=1, config=cfg.extract), exact, atol=0.25 * cloud.meta["cell_size"])
    corr = cloud.correspondence()
    # the map sends the voxel boundary vertices onto the part, points between them onto the
    # image triangles (chords of the part, so within a fraction of a cell of it)
    assert _distance_to(V, F, corr.map_points(cloud.polycube_vertices)).max() < 1e-4
    assert _distance_to(V, F, corr.map_points(cloud.points[::16])).max() < 0.25 * cloud.meta["cell_size"]
    mesh_pc = partition(poly, target_hexes=cfg.target_hexes)
    best = None
    for mode in ("harmonic", "correction"):  # as pipeline._pull_back_classical
        mesh = pull_back(mesh_pc, corr.map_points, V, F, dataclasses.replace(cfg.pullback, interior=mode))
        if best is None or mesh.meta["sj_min"] > best.meta["sj_min"]:
            best = mesh
        if best.meta.get("valid"):
            break
    assert best.meta["valid"], best.meta.get("warnings")
    assert best.meta["sj_min"] > 0


def test_images_on_the_parts_sharp_edges_stay_on_them():
    """A voxel box slightly larger than the part (a box): the closest points of its edge vertices
    lie on the part's edges.  The relaxation used to spread them over the faces (7 % of the
    diagonal off the edge here), so the mesh cut the part's edges; with the part's features
    (``surf``) they stay."""
    import trimesh

    from polycubenet.polycube import polycube_surface
    from polycubenet.pullback import PartSurface, _closest_on_segments
    from polycubenet.voxel import VoxelConfig, _scene, on_sharp_features, surface_images

    m = trimesh.creation.box(extents=[1.0, 0.6, 0.4]).subdivide().subdivide().subdivide()
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    grid = [np.linspace(-0.5, 0.5, 11) * 1.02, np.linspace(-0.3, 0.3, 7) * 1.02, np.linspace(-0.2, 0.2, 5) * 1.02]
    Vp, Fs = polycube_surface(*grid, np.ones((10, 6, 4), bool))
    surf = PartSurface(V, F, 50.0)
    X0, _ = surface_images(_scene(V, F), Vp, Fs, VoxelConfig(relax_rounds=0, untangle_rounds=0))
    on = on_sharp_features(X0, surf, 1e-5)
    assert on.sum() >= 40  # the 12 edges' vertices
    A, B = surf.V[surf.seg[:, 0]], surf.V[surf.seg[:, 1]]

    def off_edges(X):
        return max(_closest_on_segments(x[None], A, B)[1].min() for x in X[on])

    cfg = VoxelConfig(untangle_rounds=0)  # the relaxation alone (the untangling may still move a folded one)
    free, _ = surface_images(_scene(V, F), Vp, Fs, cfg)
    kept, rep = surface_images(_scene(V, F), Vp, Fs, cfg, surf)
    assert off_edges(free) > 0.01
    assert off_edges(kept) < 1e-6 and rep["pinned"] >= on.sum()
    _, rep = surface_images(_scene(V, F), Vp, Fs, VoxelConfig(), surf)
    assert rep["flipped"] == 0


def test_refinement_starts_finer_than_the_resolution_chosen_without_it(torus_c):
    V, F = torus_c
    cfg = dataclasses.replace(FAST, max_cells=24)
    *_, poly0, m0 = voxel_polycube(V, F, cfg)
    *_, poly1, m1 = voxel_polycube(V, F, cfg, refine=1)
    assert m1["base_resolution"] == m0["resolution"] and m1["refine"] == 1 and m0["refine"] == 0
    assert m1["resolution"] >= m0["resolution"] + cfg.refine_cells
    assert poly1.occupancy.sum() > poly0.occupancy.sum() and m1["genus"] == 1
    with pytest.raises(PolycubeError, match="refinement 9"):
        voxel_polycube(V, F, cfg, refine=9)


def test_an_exact_solid_is_taken_as_built_but_checked_and_never_for_a_generated_cloud(torus_c):
    """``cloud_polycube`` takes the solid a voxel cloud carries whatever its points say, still checks
    it against the part's genus, and extracts a learned cloud even if it carries a solid."""
    occ = np.ones((3, 3, 2), bool)
    occ[1, 1, :] = False  # a square ring: genus 1
    g = [np.array([0.0, 0.1, 0.101, 0.3]), np.array([0.0, 0.2, 0.4, 0.5]), np.array([0.0, 0.05, 0.1])]
    rng = np.random.default_rng(0)
    P = rng.random((500, 3))  # points that are no polycube at all
    N = rng.normal(size=(500, 3))
    cloud = ClassicalCloud(P, N, meta={"provenance": "voxel"}, grid_x=g[0], grid_y=g[1], grid_z=g[2], occupancy=occ)
    cfg = PipelineConfig()
    poly = cloud_polycube(cloud, P, N, 1, cfg, "ring.stl")
    assert poly.meta["exact"] and poly.occupancy.shape == (3, 3, 1)  # the minimal grid: the z slabs merged
    np.testing.assert_allclose(poly.xs, g[0])  # planes 0.001 apart kept (no cloud could resolve them)
    with pytest.raises(PolycubeError, match="genus 1 differs from the part's genus 2"):
        cloud_polycube(cloud, P, N, 2, cfg, "ring.stl")
    bad = ClassicalCloud(P, N, meta={"provenance": "voxel"}, grid_x=g[0], grid_y=g[1], grid_z=g[2],
                         occupancy=np.eye(3, dtype=bool)[:, :, None].repeat(2, axis=2))
    with pytest.raises(PolycubeError, match="not a valid polycube"):
        cloud_polycube(bad, P, N, None, cfg, "ring.stl")
    learned = ClassicalCloud(P, N, meta={"provenance": "learned"}, grid_x=g[0], grid_y=g[1], grid_z=g[2], occupancy=occ)
    with pytest.raises(PolycubeError):
        cloud_polycube(learned, P, N, 1, cfg, "ring.stl")
