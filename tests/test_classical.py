"""The classical polycube: labelling, repair, refinement, deformation and the exact map."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from polycubenet.classical import (
    DIRECTIONS,
    ClassicalCloud,
    ClassicalConfig,
    ClassicalSource,
    _rotation_between,
    classical_polycube,
    edge_topology,
    flipped_faces,
    label_faces,
    label_issues,
    repair_labels,
    split_constrained_edges,
    vertex_axes,
)
from polycubenet.frame import canonicalize, face_normals_areas
from polycubenet.pipeline import PipelineConfig
from polycubenet.polycube import surface_genus
from polycubenet.sampling import interpolate, uniform_sample
from polycubenet.structure import extract


def _canon(m):
    V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    Vc, _ = canonicalize(V, F)
    return Vc, F


def test_rotation_between_maps_normals_onto_targets():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = DIRECTIONS[rng.integers(0, 6, 200)]
    n[:3] = -d[:3]  # antiparallel cases
    n[3:5] = d[3:5]  # already aligned
    R = _rotation_between(n, d)
    np.testing.assert_allclose(np.einsum("kij,kj->ki", R, n), d, atol=1e-9)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_polycube_part_is_labelled_by_its_normals_and_stays_put(l_block_canonical):
    V, F = l_block_canonical
    labels, rep = label_faces(V, F)
    normals, _ = face_normals_areas(V, F)
    truth = np.argmax(normals @ DIRECTIONS.T, axis=1)
    assert (labels == truth).all()
    issues = label_issues(V, F, labels)
    assert issues["charts"] == 8  # the L-block has 8 planar faces
    assert issues["opposite_edges"] == issues["bad_charts"] == issues["turning_points"] == 0
    assert issues["high_valence_corners"] == 0
    Vp, Vs, Fs, ls, meta = classical_polycube(V, F)
    assert meta["flipped"] == 0
    # already a polycube: flattening changes it only a little (ARAP keeps the shape)
    assert np.abs(Vp - Vs).max() < 0.02


def test_smoothing_removes_noise_and_repair_merges_small_charts():
    m = trimesh.creation.box(extents=[3.0, 2.0, 1.0]).subdivide().subdivide().subdivide()
    V, F = _canon(m)
    rng = np.random.default_rng(3)
    normals, areas = face_normals_areas(V, F)
    edges, edge_faces = edge_topology(F)
    truth = np.argmax(normals @ DIRECTIONS.T, axis=1)
    # a tiny island of a wrong (non-opposite) label inside a face
    noisy = truth.copy()
    top = np.flatnonzero(truth == 5)
    cen = V[F[top]].mean(1)
    centre = top[np.argmin(np.linalg.norm(cen[:, :2], axis=1))]  # middle of the +z face
    island = np.unique(np.concatenate([edge_faces[(edge_faces == centre).any(1)].ravel(), [centre]]))
    noisy[island] = 1
    assert label_issues(V, F, noisy)["bad_charts"] >= 1
    w = np.ones(len(edges))
    cfg = ClassicalConfig(min_chart_area=0.01)
    fixed, rep = repair_labels(noisy, V, F, normals, areas, edges, edge_faces, w, cfg, rng)
    assert rep["merged_charts"] >= 1
    assert (fixed == truth).all()
    # opposite labels next to each other are separated
    opp = truth.copy()
    opp[island] = 4  # -z inside +z
    assert label_issues(V, F, opp)["opposite_edges"] > 0
    fixed, rep = repair_labels(opp, V, F, normals, areas, edges, edge_faces, w, cfg, rng)
    assert label_issues(V, F, fixed)["opposite_edges"] == 0


def test_the_rim_of_a_thin_plate_is_kept_as_its_own_chart_only_with_keep_strips():
    """A plate 1 % as thick as it is wide: each rim face is a strip under the minimum chart area that borders both
    the top (+z) and the bottom (-z).  Merged into either, it puts top and bottom on one plane (the plate cut to
    nothing); ``keep_strips`` keeps the rims' own labels, and still merges a small island that is not a strip."""
    m = trimesh.creation.box(extents=[2.0, 2.0, 0.02]).subdivide().subdivide().subdivide()
    V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    normals, areas = face_normals_areas(V, F)
    edges, edge_faces = edge_topology(F)
    truth = np.argmax(normals @ DIRECTIONS.T, axis=1)
    rim = truth // 2 != 2
    assert areas[rim].sum() / 4 < 0.01 * areas.sum()  # each rim face is under the minimum area below
    w = np.ones(len(edges))
    off = ClassicalConfig(min_chart_area=0.01, keep_strips=False)
    merged, _ = repair_labels(truth, V, F, normals, areas, edges, edge_faces, w, off, np.random.default_rng(0))
    assert (merged[rim] // 2 == 2).any()  # a rim merged into the top or bottom
    cfg = ClassicalConfig(min_chart_area=0.01, keep_strips=True)
    kept, rep = repair_labels(truth, V, F, normals, areas, edges, edge_faces, w, cfg, np.random.default_rng(0))
    assert (kept == truth).all() and rep["merged_charts"] == 0
    # a small island of a wrong label inside the top is still merged
    noisy = truth.copy()
    top = np.flatnonzero(truth == 5)
    centre = top[np.argmin(np.linalg.norm(V[F[top]].mean(1)[:, :2], axis=1))]
    noisy[np.unique(edge_faces[(edge_faces == centre).any(1)].ravel())] = 1
    fixed, rep = repair_labels(noisy, V, F, normals, areas, edges, edge_faces, w, cfg, np.random.default_rng(0))
    assert rep["merged_charts"] >= 1 and (fixed == truth).all()


def test_split_constrained_edges_leaves_no_collapsing_edge():
    m = trimesh.creation.box(extents=[1.0, 1.0, 1.0])  # 12 triangles: every edge joins two borders
    V, F = _canon(m)
    normals, _ = face_normals_areas(V, F)
    labels = np.argmax(normals @ DIRECTIONS.T, axis=1)
    Vs, Fs, ls, parent = split_constrained_edges(V, F, labels)
    assert len(Fs) > len(F)
    edges, edge_faces = edge_topology(Fs)  # still a closed 2-manifold
    assert surface_genus(Fs) == 0
    inside = ls[edge_faces[:, 0]] == ls[edge_faces[:, 1]]
    ax = vertex_axes(Fs, ls, len(Vs))
    both = ax[edges[:, 0]] & ax[edges[:, 1]]
    both[np.arange(len(edges)), ls[edge_faces[:, 0]] // 2] = False
    assert not (inside & both.any(1)).any()
    # new vertices are midpoints of their parents: still on the original surface
    np.testing.assert_allclose(Vs, 0.5 * (Vs[parent[:, 0]] + Vs[parent[:, 1]]), atol=1e-12)
    # the same total area, orientation kept
    _, a0 = face_normals_areas(V, F)
    n1, a1 = face_normals_areas(Vs, Fs)
    assert a1.sum() == pytest.approx(a0.sum())
    assert (np.einsum("ij,ij->i", n1, DIRECTIONS[ls]) > 0.99).all()


@pytest.mark.parametrize("shape", ["sphere", "torus"])
def test_curved_parts_become_valid_polycubes_of_their_genus(shape, torus):
    if shape == "sphere":
        m = trimesh.creation.icosphere(subdivisions=3)
        V, F = _canon(m)
    else:
        V, F = torus
        V, _ = canonicalize(V, F)
    genus = surface_genus(F)
    Vp, Vs, Fs, ls, meta = classical_polycube(V, F)
    # a genus-0 blob flattens without a fold; the torus keeps a few tiny folds at the
    # corners of its square hole (turning points), which the pipeline's pullback absorbs
    limit = 0 if shape == "sphere" else 0.005 * len(Fs)
    assert meta["flipped"] <= limit
    assert flipped_faces(Vp, Fs, ls).sum() == meta["flipped"]
    assert meta["flipped"] <= meta["flipped_before_untangle"]
    # the solid the flattened surface bounds, read off directly, has the part's genus at once
    assert meta["structure_genus"] == genus and meta["orientation"] == 0
    # every chart is exactly flat along its axis
    for k in range(3):
        ax = ls // 2
        coord = Vp[Fs[:, k], ax]
        ref = Vp[Fs[:, 0], ax]
        assert np.abs(coord - ref).max() < 1e-9
    s = uniform_sample(Vp, Fs, 8000, np.random.default_rng(0))
    poly = extract(s.points, DIRECTIONS[ls[s.face_ids]], genus=genus)
    assert poly.meta["genus"] == genus


def test_source_cloud_and_exact_map(torus):
    V, F = torus
    V, _ = canonicalize(V, F)
    cfg = PipelineConfig(n_polycube=4000)
    cloud = ClassicalSource(ClassicalConfig(retries=0, fix_rounds=1))(None, V, F, cfg)
    assert isinstance(cloud, ClassicalCloud)
    assert cloud.meta["provenance"] == "classical"
    assert cloud.points.shape == (4000, 3)
    # normals are axes
    assert np.allclose(np.abs(cloud.normals).max(1), 1.0) and np.allclose(np.linalg.norm(cloud.normals, axis=1), 1.0)
    corr = cloud.correspondence()
    Fs = cloud.surface_faces
    rng = np.random.default_rng(1)
    fid = rng.integers(0, len(Fs), 300)
    b = rng.dirichlet([2.0, 2.0, 2.0], 300)
    on_pc = interpolate(cloud.polycube_vertices, Fs, fid, b)
    expect = interpolate(cloud.surface_vertices, Fs, fid, b)
    got = corr.map_points(on_pc)
    # exact (same triangle, same barycentrics) wherever the flattening is injective: all but
    # points on the few folds, which still land on the part's surface
    exact = np.linalg.norm(got - expect, axis=1) < 1e-6
    assert exact.mean() >= 0.95
    _, dist, _ = trimesh.proximity.closest_point(trimesh.Trimesh(cloud.surface_vertices, Fs, process=False), got)
    assert dist.max() < 1e-6
    # inside the polycube the map is finite and lands inside the part's bounding box (slack 10%)
    inner = on_pc - 0.02 * cloud.normals[cKD(cloud.points, on_pc)]
    out = corr.map_points(inner)
    assert np.isfinite(out).all()
    lo, hi = V.min(0) - 0.1, V.max(0) + 0.1
    assert ((out > lo) & (out < hi)).all()


def cKD(points, query):
    from scipy.spatial import cKDTree

    return cKDTree(points).query(query)[1]


def test_cloud_round_trips_through_npz(tmp_path, l_block_canonical):
    V, F = l_block_canonical
    cloud = ClassicalSource(ClassicalConfig(retries=0))(None, V, F, PipelineConfig(n_polycube=2000))
    path = cloud.save(tmp_path / "cloud.npz")
    back = ClassicalCloud.load(path)
    np.testing.assert_array_equal(back.surface_faces, cloud.surface_faces)
    np.testing.assert_allclose(back.polycube_vertices, cloud.polycube_vertices)
    assert back.meta["provenance"] == "classical"
    assert back.meta["flipped"] == cloud.meta["flipped"]


def _slot_ring(slot: float):
    """A flat genus-1 polycube (a 3 x 3 x 1 ring) whose hole is only ``slot`` wide along x:
    what a flattening gives when the two walls of a handle's hole end up on nearly one plane."""
    from polycubenet.polycube import polycube_surface

    xs = np.array([-0.25 - 0.5 * slot, -0.5 * slot, 0.5 * slot, 0.25 + 0.5 * slot])
    ys = np.array([-0.3, -0.1, 0.1, 0.3])
    zs = np.array([-0.05, 0.05])
    occ = np.ones((3, 3, 1), bool)
    occ[1, 1, 0] = False
    V, F = polycube_surface(xs, ys, zs, occ, h=0.05)
    normals, _ = face_normals_areas(V, F)
    labels = np.argmax(normals @ DIRECTIONS.T, axis=1)
    return V, F, labels


def _extract_flat(V, F, labels, genus, n=6000):
    s = uniform_sample(V, F, n, np.random.default_rng(0))
    return extract(s.points, DIRECTIONS[labels[s.face_ids]], genus=genus)


def test_space_planes_keeps_a_pinched_hole_open_for_the_extraction():
    """Regression (fertility): two charts' planes 0.001 apart (a handle's hole pinched by the
    flattening) are merged by the extraction, which closes the handle; spacing the planes
    apart keeps the surface's structure and lets the extraction see the hole."""
    from polycubenet.classical import flat_structure, space_planes
    from polycubenet.errors import PolycubeError

    V, F, labels = _slot_ring(0.001)
    st = flat_structure(V, F, labels)  # read off the surface itself: the hole is there
    assert st["reason"] is None and st["genus"] == 1
    with pytest.raises(PolycubeError, match="genus"):
        _extract_flat(V, F, labels, genus=1)
    X = space_planes(V, F, labels, gap=0.02)
    xs = np.unique(X[F[labels // 2 == 0, 0], 0])
    assert np.diff(xs).min() >= 0.02 - 1e-12
    # a monotone per-axis map: charts stay planar, nothing flips, same structure
    for k in range(3):
        np.testing.assert_allclose(X[F[:, k], labels // 2], X[F[:, 0], labels // 2], atol=1e-12)
    assert flipped_faces(X, F, labels).sum() == 0
    assert flat_structure(X, F, labels)["genus"] == 1
    poly = _extract_flat(X, F, labels, genus=1)
    assert poly.meta["genus"] == 1
    # planes already far apart do not move
    np.testing.assert_allclose(space_planes(X, F, labels, gap=0.02), X)


def test_orientation_search_stops_at_its_face_budget(monkeypatch):
    """When no orientation gives the part's genus, the search flattens at most
    ``orientation_budget // faces`` of them (deterministic; the 12-hole plate tried all 9)."""
    import polycubenet.classical as C

    V, F = _canon(trimesh.creation.icosphere(subdivisions=2))
    monkeypatch.setattr(C, "flat_structure", lambda *a, **k: {"reason": "forced", "genus": None})
    calls = []
    real = C._flatten
    monkeypatch.setattr(C, "_flatten", lambda *a, **k: calls.append(1) or real(*a, **k))
    *_, meta = classical_polycube(V, F, ClassicalConfig(orientation_budget=3 * len(F)))
    assert len(calls) == 3 and len(meta["orientations_tried"]) == 3 and meta["orientations_allowed"] == 3
    calls.clear()
    *_, meta = classical_polycube(V, F, ClassicalConfig())  # 64000 // 1280 faces: every orientation
    assert len(calls) == 9


def test_weight_blocks_factorize_once_per_block_and_flatten_alike(monkeypatch, torus):
    """Holding the flatness weight for blocks of iterations reuses each axis' factorization within a
    block (3 axes x 5 blocks instead of 3 x 25 iterations) and flattens the torus about as well."""
    import dataclasses

    from polycubenet import classical

    V, F = torus
    V, _ = canonicalize(V, F)
    labels, _ = label_faces(V, F)
    Vs, Fs, ls, _ = split_constrained_edges(V, F, labels)
    calls = []
    real = classical.factorized

    def counting(A):
        calls.append(A.shape[0])
        return real(A)

    monkeypatch.setattr(classical, "factorized", counting)
    out = {}
    for blocks in (1, 5):
        calls.clear()
        cfg = dataclasses.replace(ClassicalConfig(), weight_blocks=blocks)
        Xp, meta = classical.deform_to_polycube(Vs, Fs, ls, cfg)
        out[blocks] = (len(calls), meta, Xp)
    assert out[1][0] == 75 and out[5][0] == 15
    # the same labelling flattens to nearly the same surface with the same number of folds
    assert abs(out[5][1]["flipped"] - out[1][1]["flipped"]) <= max(2, out[1][1]["flipped"] // 10)
    assert np.abs(out[5][2] - out[1][2]).max() < 0.05


def test_a_compactness_retry_with_the_same_labels_is_not_flattened_again(monkeypatch):
    """Only the labelling depends on the compactness: a retry whose labels equal an earlier attempt's
    reuses that flattening (same flips, recorded as ``same_labels_as``) instead of deforming again,
    and the result is the one a full run gives."""
    import polycubenet.classical as C

    V, F = _canon(trimesh.creation.icosphere(subdivisions=2))
    real_label, real_deform = C.label_faces, C.deform_to_polycube
    first = {}

    def fixed_labels(V, F, config=ClassicalConfig(), seed=0):  # every compactness gives the first labelling
        if "labels" not in first:
            first["labels"] = real_label(V, F, config, seed=seed)
        return first["labels"][0].copy(), dict(first["labels"][1])

    deforms = []

    def folding_deform(*a, **k):  # report folds, so that every compactness retry is tried
        deforms.append(1)
        Xp, meta = real_deform(*a, **k)
        return Xp, {**meta, "flipped": 5}

    monkeypatch.setattr(C, "label_faces", fixed_labels)
    monkeypatch.setattr(C, "deform_to_polycube", folding_deform)
    cfg = ClassicalConfig(fix_rounds=0, retries=2)
    (Vp, Vs, Fs, ls, info), attempts = C._flatten(V, F, cfg, seed=0)
    assert len(attempts) == 3 and len(deforms) == 1
    assert [a.get("same_labels_as") for a in attempts] == [None, 0, 0]
    assert [a["compactness"] for a in attempts] == [1.5, 3.0, 6.0]
    assert all(a["flipped"] == attempts[0]["flipped"] for a in attempts)
    # the flattening kept is the first labelling's, as a single attempt gives it
    monkeypatch.setattr(C, "label_faces", real_label)
    monkeypatch.setattr(C, "deform_to_polycube", real_deform)
    (Vp0, *_), _ = C._flatten(V, F, ClassicalConfig(fix_rounds=0, retries=0), seed=0)
    np.testing.assert_array_equal(Vp, Vp0)
