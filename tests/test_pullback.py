"""Pull-back of polycube hex meshes onto parts: identity, exact and perturbed synthetic maps,
pillowing, untangling, the analytic scaled-Jacobian gradient and guarded smoothing."""

from __future__ import annotations

import numpy as np
import pytest

from polycubenet.data import HexMesh, Polycube
from polycubenet.hexmesh import boundary_quads, hex_volumes, partition
from polycubenet.polycube import polycube_surface
from polycubenet.pullback import (
    CORNER_FRAMES,
    PartSurface,
    PullbackConfig,
    boundary_face_counts,
    chart_labels,
    classify_boundary,
    ease_poor_hexes,
    guarded_corner_snap,
    guarded_spot_capture,
    mend_spots,
    guarded_smooth,
    harmonic_extension,
    hex_edges,
    optimise_quality,
    pillow,
    pull_back,
    sj_terms,
)
from polycubenet.quality import quality_report, scaled_jacobian

#: a genus-4 synthetic plate (searched in seeds 0..50 for genus >= 2: rounded holes and edges,
#: the raw map leaves a folded hex, about 1.5 s per pull-back)
SYNTH_SEED = 8
SYNTH_HEXES = 2500


def _polycube(occ, xs, ys, zs) -> Polycube:
    return Polycube(np.asarray(xs, float), np.asarray(ys, float), np.asarray(zs, float), np.asarray(occ, bool))


def l_polycube() -> Polycube:
    """An L-block: 3 x 1 x 1 bottom bar plus a 1 x 1 x 1 block on one end (cells of the grid)."""
    occ = np.zeros((2, 1, 2), bool)
    occ[0, 0, 0] = occ[1, 0, 0] = occ[0, 0, 1] = True
    return _polycube(occ, [0, 1, 3], [0, 1], [0, 1, 2])


def structured_box(n: int) -> HexMesh:
    """An n x n x n block of unit cubes (VTK order, positive)."""
    pc = _polycube(np.ones((1, 1, 1), bool), [0, n], [0, n], [0, n])
    return partition(pc, target_size=1.0)


def smooth_perturbation(amplitude: float, seed: int, scale: float = 0.35):
    """A smooth displacement field (K, 3) -> (K, 3) of magnitude about ``amplitude``."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(3, 3, 3)) / scale
    phase = rng.uniform(0, 2 * np.pi, size=(3, 3))

    def field(p):
        out = np.empty_like(p)
        for a in range(3):
            out[:, a] = np.sin(p @ k[a].T + phase[a]).mean(axis=1)
        return amplitude * out

    return field


@pytest.fixture(scope="module")
def synth_pair():
    from polycubenet.synth import make_pair

    pair = make_pair(SYNTH_SEED, n_cond=64, n_target=64, sampler="uniform")
    assert pair.genus >= 2
    return pair, partition(pair.polycube, target_hexes=SYNTH_HEXES)


# --------------------------------------------------------------------------- building blocks


def test_sj_terms_match_quality_and_gradient_matches_torch():
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(0)
    m = structured_box(3)
    X = m.points + rng.normal(scale=0.15, size=m.points.shape)
    s = sj_terms(X, m.hexes)
    assert np.allclose(s.min(axis=1), scaled_jacobian(X, m.hexes), atol=1e-12)
    W = rng.normal(size=s.shape)
    _, g = sj_terms(X, m.hexes, lambda t: W)

    Xt = torch.tensor(X, requires_grad=True)
    C = Xt[torch.as_tensor(m.hexes)]
    fr = torch.as_tensor(CORNER_FRAMES)
    x1 = C[:, 1] + C[:, 2] + C[:, 5] + C[:, 6] - C[:, 0] - C[:, 3] - C[:, 4] - C[:, 7]
    x2 = C[:, 2] + C[:, 3] + C[:, 6] + C[:, 7] - C[:, 0] - C[:, 1] - C[:, 4] - C[:, 5]
    x3 = C[:, 4] + C[:, 5] + C[:, 6] + C[:, 7] - C[:, 0] - C[:, 1] - C[:, 2] - C[:, 3]
    V = torch.cat([torch.stack([x1, x2, x3], 1)[:, None], C[:, fr[:, 1:]] - C[:, fr[:, 0]][:, :, None]], 1)
    det = (V[..., 0, :] * torch.cross(V[..., 1, :], V[..., 2, :], dim=-1)).sum(-1)
    st = det / ((V * V).sum(-1).prod(-1)).sqrt()
    (st * torch.as_tensor(W)).sum().backward()
    assert np.allclose(st.detach().numpy(), s, atol=1e-12)
    assert np.allclose(Xt.grad.numpy(), g, rtol=1e-9, atol=1e-9 * np.abs(g).max())


def test_classify_boundary_on_l_block():
    m = partition(l_polycube(), target_size=0.5)
    bs = classify_boundary(m.points, m.hexes)
    # the L-block has 12 polycube corners, all of them "corner" nodes (3 distinct normals)
    corner_pts = m.points[bs.nodes[bs.kind >= 3]]
    assert len(corner_pts) == 12
    assert set(map(tuple, corner_pts.tolist())) == {
        (0, 0, 0), (3, 0, 0), (0, 1, 0), (3, 1, 0), (3, 0, 1), (3, 1, 1),
        (1, 0, 1), (1, 1, 1), (0, 0, 2), (1, 0, 2), (0, 1, 2), (1, 1, 2),
    }
    # edge nodes carry the direction of their polycube edge: perpendicular to both normals
    e = bs.kind == 2
    assert e.sum() > 0 and np.allclose(np.abs(bs.tangent[e]).sum(axis=1), 1.0)
    # quad labels agree with the outward quad normals
    q = bs.quads
    n = np.cross(m.points[q[:, 1]] - m.points[q[:, 0]], m.points[q[:, 3]] - m.points[q[:, 0]])
    axis = np.argmax(np.abs(n), axis=1)
    assert np.array_equal(bs.quad_label, 2 * axis + (n[np.arange(len(n)), axis] > 0))


def test_chart_labels_follow_normals_on_l_block():
    pc = l_polycube()
    m = partition(pc, target_size=0.25)
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy, h=0.2)
    surf = PartSurface(V, F)
    bs = classify_boundary(m.points, m.hexes)
    face = bs.kind == 1
    nodes = bs.nodes[face]
    lab = np.argmax(bs.label_mask[face], axis=1)
    normals = np.zeros((len(nodes), 3))
    normals[np.arange(len(nodes)), lab // 2] = np.where(lab % 2 == 1, 1.0, -1.0)
    got = chart_labels(surf.centroids, surf.normals, m.points[nodes], normals, lab, np.full(len(nodes), 0.25))
    axis = np.argmax(np.abs(surf.normals), axis=1)
    want = 2 * axis + (surf.normals[np.arange(len(F)), axis] > 0)
    assert np.array_equal(got, want)


def test_part_surface_features_of_l_block():
    pc = l_polycube()
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy, h=0.25)
    surf = PartSurface(V, F, feature_angle_deg=50.0)
    # every sharp segment lies on a polycube edge: two of its coordinates are grid planes
    mid = 0.5 * (V[surf.seg[:, 0]] + V[surf.seg[:, 1]])
    on_plane = np.stack([np.isin(mid[:, a], g) for a, g in enumerate((pc.xs, pc.ys, pc.zs))], axis=1)
    assert on_plane.sum(axis=1).min() == 2
    # 18 polycube edges: the L profile (perimeter 10) twice, plus its 6 corners along y
    length = np.linalg.norm(V[surf.seg[:, 0]] - V[surf.seg[:, 1]], axis=1).sum()
    assert length == pytest.approx(26.0)
    # the 12 corners are the feature vertices, and each is where three sharp edges meet
    assert len(surf.feature_vertices) == 12
    assert np.array_equal(np.sort(surf.branch_vertices), np.sort(surf.feature_vertices))
    P, d, _ = surf.closest_on_curves(np.array([[1.5, -0.2, 0.1]]))
    assert np.allclose(P, [[1.5, 0.0, 0.0]]) and d[0] == pytest.approx(np.hypot(0.2, 0.1))


def test_harmonic_extension_is_linear_on_a_grid():
    m = structured_box(4)
    b = m.boundary
    f = m.points @ np.array([1.0, -2.0, 0.5])  # linear: discrete-harmonic on a regular grid
    vals = np.where(b, f, 0.0)[:, None]
    out = harmonic_extension(hex_edges(m.hexes), len(m.points), b, vals)
    assert np.allclose(out[:, 0], f, atol=1e-9)


def test_pillow_topology_and_orientation():
    m = structured_box(3)
    before = boundary_face_counts(m.hexes)
    assert (before >= 2).sum() == 20  # 8 corner + 12 edge cubes of a 3 x 3 x 3 block
    X, H, inner = pillow(m.points, m.hexes, thickness=0.3)
    Q = len(boundary_quads(m.hexes))
    assert len(H) == len(m.hexes) + Q and len(X) == len(m.points) + m.boundary.sum()
    counts = boundary_face_counts(H)
    assert counts.max() == 1 and (counts[len(m.hexes):] == 1).all() and (counts[: len(m.hexes)] == 0).all()
    assert (hex_volumes(X, H) > 0).all()
    # outer nodes stay, inner copies are inside the box
    assert np.array_equal(X[: len(m.points)], m.points)
    ins = X[len(m.points):]
    assert (ins > 0).all() and (ins < 3).all()
    assert np.array_equal(np.flatnonzero(inner >= 0), np.flatnonzero(m.boundary))


def test_optimise_untangles_a_tangled_mesh():
    m = structured_box(4)
    X = m.points.copy()
    interior = np.flatnonzero(~m.boundary)
    # push two interior nodes through their neighbours
    X[interior[0]] += [1.3, 0.9, 0.0]
    X[interior[-1]] -= [0.0, 1.2, 1.1]
    sj0 = scaled_jacobian(X, m.hexes)
    assert sj0.min() < 0
    Y, info = optimise_quality(X, m.hexes, movable=~m.boundary, config=PullbackConfig(optimise_iterations=300))
    sj = scaled_jacobian(Y, m.hexes)
    assert sj.min() > 0.5
    assert info["sj_min_start"] == pytest.approx(sj0.min()) and info["sj_min"] == pytest.approx(sj.min())
    assert np.array_equal(Y[m.boundary], m.points[m.boundary])  # fixed nodes did not move


def test_guarded_smoothing_never_lowers_the_minimum():
    rng = np.random.default_rng(1)
    m = structured_box(4)
    X = m.points.copy()
    X[~m.boundary] += rng.normal(scale=0.2, size=((~m.boundary).sum(), 3))
    sj0 = scaled_jacobian(X, m.hexes)
    Y, info = guarded_smooth(X, m.hexes, ~m.boundary, sweeps=5, step=0.5)
    sj = scaled_jacobian(Y, m.hexes)
    assert sj.min() >= sj0.min() - 1e-12
    assert sj.mean() > sj0.mean()
    assert np.array_equal(Y[m.boundary], X[m.boundary])
    assert info["moved"][0] > 0


# --------------------------------------------------------------------------- the pipeline


@pytest.mark.parametrize("interior", ["correction", "harmonic"])
def test_identity_on_l_block_without_pillow_is_exact(interior):
    pc = l_polycube()
    m = partition(pc, target_size=0.25)
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    out = pull_back(m, lambda p: p.copy(), V, F, PullbackConfig(pillow=False, interior=interior))
    assert out.hexes.shape == m.hexes.shape
    assert np.allclose(out.points, m.points, atol=1e-6)
    rep = quality_report(out, surface=(V, F), n_samples=20_000)
    assert rep.sj_min > 0.999 and rep.surface["hausdorff"] < 1e-6
    assert out.meta["valid"] and out.meta["pillowed"] is False
    assert out.meta["projection"]["snapped"]["corner"] == 12


def test_identity_on_l_block_with_pillow():
    pc = l_polycube()
    m = partition(pc, target_size=0.25)
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    out = pull_back(m, lambda p: p.copy(), V, F)
    H0 = len(m.hexes)
    assert len(out.hexes) == H0 + len(boundary_quads(m.hexes))
    sj = scaled_jacobian(out.points, out.hexes)
    # the original hexes stay near-perfect (they give a little to the pillow layer's worst)
    assert sj[:H0].mean() > 0.95 and sj[:H0].min() > 0.8
    assert sj[H0:].min() > 0.45  # pillow hexes: 45 degrees at convex edges, less at corners
    rep = quality_report(out, surface=(V, F), n_samples=20_000)
    assert rep.valid and rep.surface["hausdorff"] < 1e-6
    assert out.meta["multi_boundary_before"] == 80 and out.meta["multi_boundary_after"] == 0
    assert out.boundary.sum() == m.boundary.sum()
    # boundary nodes may slide on the surface, but the snapped polycube corners stay put
    bs = classify_boundary(m.points, m.hexes)
    corners = bs.nodes[bs.kind >= 3]
    assert np.allclose(out.points[corners], m.points[corners], atol=1e-6)


def test_synth_pair_exact_map(synth_pair):
    pair, m = synth_pair
    out = pull_back(m, pair.polycube_to_shape, pair.shape_vertices, pair.faces)
    rep = quality_report(out, surface=(pair.shape_vertices, pair.faces), n_samples=50_000)
    assert rep.valid and rep.sj_min > 0, rep.summary()
    assert rep.sj_avg >= 0.8
    assert rep.surface["hausdorff"] <= 0.01
    assert out.meta["valid"] and not out.meta["warnings"]
    assert out.meta["multi_boundary_before"] > 0 and out.meta["multi_boundary_after"] == 0
    assert set(out.meta["timings"]) >= {"boundary", "interior", "optimise", "pillow", "optimise_pillow", "total"}
    # the raw map leaves a folded hex on this part (rounded edges): the pipeline removed it
    assert out.meta["stages"]["mapped"]["sj_min"] <= 0 < 0.25 < out.meta["sj_min"] == pytest.approx(rep.sj_min)


def test_synth_pair_perturbed_map(synth_pair):
    pair, m = synth_pair
    field = smooth_perturbation(0.01, seed=3)
    err = np.linalg.norm(field(m.points), axis=1)
    assert 0.003 < err.max() < 0.02  # about 1% of the diagonal (the part's diagonal is 1)

    def to_part(p):
        return pair.polycube_to_shape(p) + field(p)

    out = pull_back(m, to_part, pair.shape_vertices, pair.faces)
    rep = quality_report(out, surface=(pair.shape_vertices, pair.faces), n_samples=50_000)
    assert rep.valid and rep.sj_min > 0, rep.summary()
    assert rep.sj_avg >= 0.8
    assert rep.surface["hausdorff"] <= 0.015


def test_coverage_fit_under_a_two_percent_map_error(synth_pair):
    # a registration-sized map error (2 % of the diagonal) on a part with rounded holes and
    # edges: the projected quads cut across the roundings.  Without the coverage fit (steps 1b
    # and 4c) this gave a Hausdorff distance of 1.89 % (min SJ 0.32); with it 1.09 % (0.30).
    pair, m = synth_pair
    field = smooth_perturbation(0.02, seed=3)

    def to_part(p):
        return pair.polycube_to_shape(p) + field(p)

    out = pull_back(m, to_part, pair.shape_vertices, pair.faces)
    rep = quality_report(out, surface=(pair.shape_vertices, pair.faces), n_samples=50_000)
    assert rep.valid and rep.sj_avg >= 0.85, rep.summary()
    assert rep.surface["hausdorff"] <= 0.013
    proj = out.meta["projection"]
    # the fit tightened both one-sided distances of the projected quads
    assert proj["coverage_s2h"][-1] < 0.8 * proj["coverage_s2h"][0]
    assert proj["coverage_h2s"][-1] < proj["coverage_h2s"][0]
    # the guarded fit on the finished mesh never took a hex below min(bar, its SJ before)
    st = out.meta["stages"]
    before = st["released"] if "released" in st else st["pillow_optimised"]
    bar = PullbackConfig().final_coverage_sj
    assert st["coverage_final"]["sj_min"] >= min(bar, before["sj_min"]) - 1e-9
    assert proj["guarded_s2h"][-1] <= proj["guarded_s2h"][0]


def test_coverage_config_is_validated():
    with pytest.raises(ValueError, match="coverage"):
        PullbackConfig(coverage_iterations=-1)
    with pytest.raises(ValueError, match="coverage"):
        PullbackConfig(coverage_max_move=0.0)


def test_invalid_result_is_flagged_not_silent():
    # a mirroring map turns every hex inside out; with no optimisation nothing can fix it
    pc = l_polycube()
    m = partition(pc, target_size=0.5)
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    mirror = np.array([-1.0, 1.0, 1.0])
    cfg = PullbackConfig(pillow=False, optimise_iterations=0, smoothing_sweeps=0, release_rounds=0)
    out = pull_back(m, lambda p: p * mirror, V * mirror, F[:, ::-1], cfg)
    assert out.meta["valid"] is False
    assert any("not valid" in w for w in out.meta["warnings"])
    assert not quality_report(out).valid


def test_bad_inputs_raise():
    pc = l_polycube()
    m = partition(pc, target_size=0.5)
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    with pytest.raises(ValueError, match="F must be"):
        pull_back(m, lambda p: p, V, F[:, :2])
    with pytest.raises(ValueError, match="NaN"):
        pull_back(m, lambda p: p * np.nan, V, F)
    with pytest.raises(ValueError, match="shape"):
        pull_back(m, lambda p: p[:-1], V, F)
    with pytest.raises(ValueError, match="interior"):
        PullbackConfig(interior="nope")
    with pytest.raises(ValueError, match="pillow_thickness"):
        PullbackConfig(pillow_thickness=1.5)


# --------------------------------------------------------------------------- releasing poor corners


@pytest.fixture(scope="module")
def cylinder_runs():
    """A cylinder through the classical chain (box polycube: its vertical edges land on the round
    side, where pillow hexes get flat corners) with three release settings."""
    import trimesh

    from polycubenet.pipeline import PipelineConfig, mesh_surface

    mesh = trimesh.creation.cylinder(radius=0.6, height=2.0, sections=48)
    runs = {}
    for key, over in {
        # the release alone (ease_poor_hexes would lift the poor corners the release leaves)
        "old_bar": dict(release_sj=0.1, release_rounds=2, ease_spots=False),
        "default": dict(ease_spots=False),
        "no_deviation_allowed": dict(release_max_deviation=0.0, ease_spots=False),
        "old_bar_eased": dict(release_sj=0.1, release_rounds=2),
    }.items():
        # min_sj=None: the flattening's mesh is kept whatever its quality (this is about the pull-back, not the policy)
        cfg = PipelineConfig(polycube="classical", target_hexes=1500, pullback=PullbackConfig(**over), min_sj=None)
        runs[key] = mesh_surface(mesh.vertices, mesh.faces, None, cfg, part_meta={"genus": 0})
    return runs


def test_releasing_poor_corners_lifts_the_minimum_within_the_fidelity_bar(cylinder_runs):
    old, new = cylinder_runs["old_bar"], cylinder_runs["default"]
    assert old.report.valid and new.report.valid
    # with a release bar of 0.1 the flat pillow corners on the round side stay (min SJ 0.13)
    assert old.report.sj_min < 0.2
    assert new.report.sj_min >= 0.35, new.report.summary()
    assert new.mesh.meta["projection"]["released"] > 0 and not new.mesh.meta["projection"]["release_reverted"]
    assert new.report.surface["hausdorff"] <= 0.01


def test_poor_corners_a_release_leaves_are_eased_within_the_fidelity_bar(cylinder_runs):
    """The flat pillow corners the 0.1 release bar leaves (SJ < 0.2) lifted by ease_poor_hexes, the mesh still
    within the bar and the moved surface nodes within the slack of the surface."""
    old, eased = cylinder_runs["old_bar"], cylinder_runs["old_bar_eased"]
    assert old.report.sj_min < 0.2
    assert eased.report.valid and eased.report.sj_min >= 0.2, eased.report.summary()
    assert eased.report.surface["hausdorff"] <= 0.01
    info = eased.mesh.meta["eased"]
    assert info["kept"] and 0 < info["off_surface_max"] <= PullbackConfig().ease_slack * (1 + 1e-4)
    assert eased.row()["eased"] == {"hexes": info["hexes"], "surface_nodes": info["surface_nodes"],
                                    "off_surface_max": round(info["off_surface_max"], 6)}


def test_a_release_that_costs_fidelity_is_undone_after_the_final_coverage_fit(cylinder_runs):
    undone, old = cylinder_runs["no_deviation_allowed"], cylinder_runs["old_bar"]
    meta = undone.mesh.meta
    assert meta["projection"]["release_reverted"] and meta["projection"]["released"] == 0
    st = meta["stages"]["release_undone"]
    assert st["deviation"] > st["deviation_before"]
    # the undone state is the unreleased mesh (with its own final coverage fit): still valid, no better
    assert undone.report.valid and undone.report.sj_min < 0.2
    assert undone.report.surface["hausdorff"] <= old.report.surface["hausdorff"] + 1e-3


@pytest.fixture(scope="module")
def slanted_end_runs():
    """A bar whose end is slanted at 54 degrees (a knife edge at its foot) through the classical chain, with and
    without the second, stronger release (the first release cuts the knife edge and is undone)."""
    import trimesh

    from polycubenet.pipeline import PipelineConfig, mesh_surface

    pts = np.array([[0, 0, 0], [3, 0, 0], [0, 1, 0], [3, 1, 0], [0, 0, 1], [1.6, 0, 1], [0, 1, 1], [1.6, 1, 1]], float)
    bar = trimesh.convex.convex_hull(pts)
    runs = {}
    for key, pull in {"default": PullbackConfig().release_retry_regularisation, "off": 0.0}.items():
        cfg = PipelineConfig(polycube="classical", target_hexes=1500, min_sj=None,
                             pullback=PullbackConfig(release_retry_regularisation=pull))
        runs[key] = mesh_surface(bar.vertices, bar.faces, None, cfg, part_meta={"genus": 0})
    return runs


def test_an_undone_release_is_tried_again_with_a_stronger_pull(slanted_end_runs):
    on, off = slanted_end_runs["default"], slanted_end_runs["off"]
    for run in (on, off):  # the weak release cut the knife edge: undone in both
        st = run.mesh.meta["stages"]["release_undone"]
        assert st["deviation"] > PullbackConfig().release_max_deviation
    assert on.report.valid
    proj = on.mesh.meta["projection"]
    assert proj["re_released"] and not proj["release_reverted"] and proj["released"] > 0
    assert not off.mesh.meta["projection"]["re_released"]
    # the second release lifts the minimum and stays within the deviation the first one was held to
    assert on.report.sj_min > off.report.sj_min + 0.02, (on.report.sj_min, off.report.sj_min)
    assert on.mesh.meta["stages"]["re-released"]["deviation"] <= PullbackConfig().release_max_deviation
    assert on.report.surface["hausdorff"] <= 0.01


@pytest.mark.parametrize("first_min, calls_expected", [(-0.9, 1), (-0.01, 2)])
def test_a_far_from_valid_result_is_not_recomputed_without_the_coverage_fit(monkeypatch, first_min, calls_expected):
    import polycubenet.pullback as pb

    calls = []

    def fake_once(mesh_pc, to_part, V, F, config, diagonal=None):
        calls.append(config.coverage_iterations)
        return HexMesh(mesh_pc.points, mesh_pc.hexes, mesh_pc.boundary,
                       meta={"valid": False, "sj_min": first_min, "timings": {"total": 1.0}})

    monkeypatch.setattr(pb, "_pull_back_once", fake_once)
    pc = l_polycube()
    m = partition(pc, target_size=0.5)
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy)
    out = pb.pull_back(m, lambda p: p, V, F)
    assert len(calls) == calls_expected and calls[0] == PullbackConfig().coverage_iterations
    assert ("coverage_retry" in out.meta) == (calls_expected == 2)


def test_a_cut_corner_gets_a_node_back_under_the_quality_guard():
    """A box mesh whose corner node sits inside the part's corner: the snap puts it back on the
    corner (the part's feature vertex) without lowering any hex; a mesh on its corners is left."""
    m = structured_box(4)
    pc = _polycube(np.ones((1, 1, 1), bool), [0, 4], [0, 4], [0, 4])
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy, h=0.5)
    V = V / np.linalg.norm([4, 4, 4])  # the pull-back's frame: diagonal 1
    X = m.points / np.linalg.norm([4, 4, 4])
    surf = PartSurface(V, F)
    nodes = np.flatnonzero(m.boundary)
    hloc = np.full(len(nodes), 0.25 / np.sqrt(3))  # one cell
    untouched, info = guarded_corner_snap(surf, X, m.hexes, nodes, hloc, sj_bar=0.3)
    assert info["corner_snaps"] == 0 and np.array_equal(untouched, X)
    corner = int(np.argmin(np.linalg.norm(X, axis=1)))  # the node at (0, 0, 0)
    cut = X.copy()
    cut[corner] += 0.35 * 0.25 / np.sqrt(3)  # inward along the diagonal: the part's corner is cut
    before = scaled_jacobian(cut, m.hexes)
    out, info = guarded_corner_snap(surf, cut, m.hexes, nodes, hloc, sj_bar=0.3)
    assert info["corner_snaps"] == 1
    assert np.allclose(out[corner], 0.0)
    assert (scaled_jacobian(out, m.hexes) >= np.minimum(before, 0.3) - 1e-9).all()
    # a part corner 1.9 cells beyond the mesh's along x: all the way would shear the corner hex to
    # SJ 0.22 (< the 0.3 bar), so the node goes only as far as the bar allows (0.75 of the way)
    cell = 0.25 / np.sqrt(3)
    shifted = PartSurface(V - [1.9 * cell, 0, 0], F)
    corners = shifted.V[shifted.branch_vertices]
    assert len(corners) == 8
    target = corners[np.argmin(np.linalg.norm(corners - X[corner], axis=1))]
    out, info = guarded_corner_snap(shifted, X, m.hexes, nodes, hloc, sj_bar=0.3)
    assert np.allclose(out[corner], X[corner] + 0.75 * (target - X[corner]))
    assert scaled_jacobian(out, m.hexes).min() >= 0.3 - 1e-9


def test_an_uncovered_spot_on_an_edge_is_captured_only_when_the_mesh_is_off_the_part():
    """A box mesh with one node in the middle of an edge pulled inside the part (its quads cut the part's
    edge there, by more than the Hausdorff bar): the capture brings the boundary back onto the edge
    within the target, no hex dropping below min(bar, its SJ before); a mesh within the bar is left as is."""
    m = structured_box(4)
    pc = _polycube(np.ones((1, 1, 1), bool), [0, 4], [0, 4], [0, 4])
    V, F = polycube_surface(pc.xs, pc.ys, pc.zs, pc.occupancy, h=0.5)
    V = V / np.linalg.norm([4, 4, 4])
    X = m.points / np.linalg.norm([4, 4, 4])
    surf = PartSurface(V, F)
    nodes = np.flatnonzero(m.boundary)
    cell = 0.25 / np.sqrt(3)
    hloc = np.full(len(nodes), cell)
    args = dict(sj_bar=0.3, trigger=0.01, target=0.008, samples=20000)
    out, info = guarded_spot_capture(surf, X, m.hexes, nodes, hloc, **args)
    assert info["spot_captures"] == 0 and np.array_equal(out, X) and info["spot_gap_before"] < 0.01
    edge = int(np.argmin(np.linalg.norm(X - [2 * cell, 0, 0], axis=1)))  # mid-edge node at (2, 0, 0) cells
    cut = X.copy()
    cut[edge] += [0.0, 0.4 * cell, 0.4 * cell]  # into the part, off its edge
    before = scaled_jacobian(cut, m.hexes)
    out, info = guarded_spot_capture(surf, cut, m.hexes, nodes, hloc, **args)
    assert info["spot_gap_before"] > 0.01
    assert info["spot_captures"] >= 1 and info["spot_gap_after"] <= 0.008
    assert (scaled_jacobian(out, m.hexes) >= np.minimum(before, 0.3) - 1e-9).all()
    assert np.linalg.norm(out[edge] - X[edge]) < 0.3 * cell  # the node went back towards the edge
    # no node within reach of the spots (radius 0.1 cell): nothing moves, the spots are counted
    out, info = guarded_spot_capture(surf, cut, m.hexes, nodes, hloc, radius=0.1, **args)
    assert info["spot_captures"] == 0 and np.array_equal(out, cut) and info["spot_captures_refused"] > 0


def test_a_mesh_off_the_part_at_one_spot_is_mended_and_one_on_it_is_left():
    """mend_spots on a finished mesh (the part's units): the box mesh with a mid-edge node pulled inside, its
    Hausdorff distance above the bar, comes back within it and valid; a mesh within the bar, or not valid, is
    returned as it is, and so is one farther off than a mend is tried at (a missing feature, not a spot)."""
    m = structured_box(4)
    V, F = polycube_surface(np.array([0.0, 4.0]), np.array([0.0, 4.0]), np.array([0.0, 4.0]),
                            np.ones((1, 1, 1), bool), h=0.5)
    pts = m.points.copy()
    edge = int(np.argmin(np.linalg.norm(pts - [2.0, 0.0, 0.0], axis=1)))
    pts[edge] += [0.0, 0.4, 0.4]
    sj = scaled_jacobian(pts, m.hexes)
    off = HexMesh(pts, m.hexes, m.boundary, meta={"valid": True, "hausdorff": 0.025, "sj_min": float(sj.min()),
                                                 "timings": {}})
    out = mend_spots(off, V, F)
    assert out is not off and out.meta["spots"]["kept"] and out.meta["valid"]
    assert out.meta["hausdorff"] <= 0.01 and out.meta["spots"]["hausdorff_before"] == 0.025
    assert scaled_jacobian(out.points, out.hexes).min() >= min(sj.min(), PullbackConfig().capture_sj) - 1e-9
    for meta in ({"valid": True, "hausdorff": 0.005}, {"valid": False, "hausdorff": 0.03}):
        same = HexMesh(pts, m.hexes, m.boundary, meta=dict(meta))
        assert mend_spots(same, V, F) is same and "spots" not in same.meta
    far = HexMesh(pts, m.hexes, m.boundary, meta={"valid": True, "hausdorff": 0.05, "sj_min": float(sj.min())})
    assert mend_spots(far, V, F) is far and not far.meta["spots"]["kept"] and "5.00 %" in far.meta["spots"]["skipped"]
    assert mend_spots(far, V, F, PullbackConfig(capture_max=0.06)).meta["spots"]["kept"]


def test_a_few_inverted_hexes_are_eased_with_the_surface_nodes_near_the_surface_and_a_good_mesh_is_left():
    """ease_poor_hexes on a finished mesh (the part's units): the box mesh with a face node pushed through the
    first layer (inverted hexes) comes back valid, its moved surface nodes within ``ease_slack`` of the surface
    (on it with no slack); a valid mesh at the quality bar is returned as it is, and so is one with more poor
    hexes than a spot has (a folded map)."""
    m = structured_box(4)
    V, F = polycube_surface(np.array([0.0, 4.0]), np.array([0.0, 4.0]), np.array([0.0, 4.0]),
                            np.ones((1, 1, 1), bool), h=0.5)
    diag = float(np.sqrt(48.0))
    pts = m.points.copy()
    top = int(np.argmin(np.linalg.norm(pts - [2.0, 2.0, 4.0], axis=1)))
    pts[top] = [2.3, 2.2, 2.6]  # below the first layer's nodes (z = 3)
    sj = scaled_jacobian(pts, m.hexes)
    assert sj.min() < 0
    bad = HexMesh(pts, m.hexes, m.boundary, meta={"valid": False, "sj_min": float(sj.min()), "timings": {}})
    surface = PartSurface(V, F)
    for slack in (PullbackConfig().ease_slack, 0.0):
        out = ease_poor_hexes(bad, V, F, PullbackConfig(ease_slack=slack))
        assert out is not bad and out.meta["eased"]["kept"] and out.meta["valid"]
        assert scaled_jacobian(out.points, out.hexes).min() >= 0.2
        assert out.meta["hausdorff"] <= 0.01
        moved = np.flatnonzero(np.linalg.norm(out.points - pts, axis=1) > 0)
        nodes = np.intersect1d(moved, boundary_quads(m.hexes))
        assert top in nodes
        gap = surface.closest(out.points[nodes])[1]
        assert gap.max() <= slack * diag + 1e-6 * diag  # the closest-point query is float32
        assert out.meta["eased"]["off_surface_max"] == pytest.approx(gap.max() / diag, abs=1e-6)
    good = HexMesh(m.points, m.hexes, m.boundary, meta={"valid": True, "sj_min": 1.0, "hausdorff": 0.0})
    assert ease_poor_hexes(good, V, F) is good and "eased" not in good.meta
    folded = ease_poor_hexes(bad, V, F, PullbackConfig(ease_max_hexes=int((sj < 0.22).sum()) - 1))
    assert folded is bad and not bad.meta["eased"]["kept"] and "hexes under SJ" in bad.meta["eased"]["skipped"]


def test_the_pipeline_eases_at_its_own_quality_bar():
    """PipelineConfig hands its min_sj to the pull-back's easing: a valid mesh at SJ ~0.3 is left as it is at the
    default bar (0.2) and eased at a bar of 0.45; with min_sj None the pull-back's own ease_below stands."""
    from polycubenet.pipeline import PipelineConfig

    m = structured_box(4)
    V, F = polycube_surface(np.array([0.0, 4.0]), np.array([0.0, 4.0]), np.array([0.0, 4.0]),
                            np.ones((1, 1, 1), bool), h=0.5)
    pts = m.points.copy()
    inner = int(np.argmin(np.linalg.norm(pts - [2.0, 2.0, 3.0], axis=1)))
    pts[inner] = [2.3, 2.25, 3.3]  # an interior node pulled off its place: poor (SJ 0.27), not inverted
    sj = scaled_jacobian(pts, m.hexes)
    assert 0.2 < sj.min() < 0.4, sj.min()
    poor = HexMesh(pts, m.hexes, m.boundary, meta={"valid": True, "sj_min": float(sj.min()), "hausdorff": 0.0,
                                                   "timings": {}})
    assert PipelineConfig().pullback.ease_below == 0.2
    assert ease_poor_hexes(poor, V, F, PipelineConfig().pullback) is poor and "eased" not in poor.meta
    strict = PipelineConfig(min_sj=0.45).pullback
    assert strict.ease_below == 0.45 and PipelineConfig(min_sj=None).pullback.ease_below == PullbackConfig().ease_below
    out = ease_poor_hexes(poor, V, F, strict)
    assert out is not poor and out.meta["eased"]["kept"] and out.meta["sj_min"] > sj.min()
    assert scaled_jacobian(out.points, out.hexes).min() == pytest.approx(out.meta["sj_min"], abs=1e-6)


def test_a_guarded_move_takes_the_largest_fraction_that_keeps_every_hex_and_the_extra_guard():
    """_guarded_move tries all fractions of a move in one SJ pass: on random moves of one node or of a node and a
    partner in a jittered box mesh it keeps exactly what trying the fractions one by one keeps (the largest that
    leaves no hex around the nodes below min(bar, its SJ before) and passes the extra guard), or leaves X as it was."""
    import scipy.sparse as sp

    from polycubenet.pullback import _guarded_move, _hex_incidence
    from polycubenet.quality import scaled_jacobian_and_degenerate

    m = structured_box(3)
    P = len(m.points)
    inc = sp.csc_matrix(_hex_incidence(m.hexes, P)[0])
    fractions = (1.0, 0.75, 0.5, 0.25)

    def one_by_one(X, group, v, bar, also):
        rows = np.flatnonzero(np.isin(m.hexes, group).any(axis=1))
        def sj():
            s, dg = scaled_jacobian_and_degenerate(X, m.hexes[rows])
            return np.where(dg, -np.inf, s)
        floor = np.minimum(sj(), bar) - 1e-9
        start = X[group].copy()
        for f in fractions:
            X[group] = start + f * v
            if (sj() >= floor).all() and also(X):
                return f
        X[group] = start
        return None

    rng = np.random.default_rng(3)
    kept = {f: 0 for f in fractions + (None,)}
    for _ in range(400):
        X0 = m.points + rng.normal(0.0, 0.08, m.points.shape)
        group = [int(rng.integers(P))] + ([int(rng.integers(P))] if rng.random() < 0.3 else [])
        v = rng.normal(0.0, rng.choice([0.1, 0.4, 0.8]), 3)
        bar = float(rng.choice([0.2, 0.6, 0.95]))
        limit = X0[group[0], 0] + rng.choice([0.02, np.inf])  # the extra guard: the node may not go far in +x
        ref = X0.copy()
        f = one_by_one(ref, group, v, bar, lambda Y: Y[group[0], 0] <= limit)
        got = X0.copy()
        moved = _guarded_move(got, m.hexes, inc, group, v, fractions, bar, lambda: got[group[0], 0] <= limit)
        assert moved == (f is not None)
        assert np.array_equal(got, ref)
        kept[f] += 1
    assert kept[None] > 0 and kept[1.0] > 0 and sum(kept[f] for f in (0.75, 0.5, 0.25)) > 0  # every branch seen
