"""An anchored model's own map from its polycube to the part (``polycubenet.anchormap``)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from polycubenet.anchormap import anchor_map, snap_to_polycube
from polycubenet.data import Polycube
from polycubenet.polycube import polycube_surface
from polycubenet.sampling import poisson_disk

from test_realise import _l_polycube, _Map, _shear, slanted_l  # noqa: F401 - the slanted L-block fixture


def _generated(poly, shear, n=3000, noise=0.004, seed=0):
    """A generated cloud of ``poly`` (its surface samples with their normals, moved by ``noise`` of Gaussian
    error) and each point's anchor: the part point it stands for (``shear`` of the exact point)."""
    s = poisson_disk(*polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy), n, seed=seed)
    rng = np.random.default_rng(seed)
    return s.points + noise * rng.standard_normal(s.points.shape), s.normals, shear(s.points)


def test_points_snap_onto_the_face_of_their_own_direction_and_the_map_follows_the_anchors(slanted_l):
    V, F, poly, shear = slanted_l
    P, N, A = _generated(poly, shear)
    snapped, dist = snap_to_polycube(poly, P, N)
    Vq, Fq = polycube_surface(poly.xs, poly.ys, poly.zs, poly.occupancy)
    assert trimesh.proximity.closest_point(trimesh.Trimesh(Vq, Fq, process=False), snapped)[1].max() < 1e-9
    assert np.quantile(dist, 0.99) < 0.02
    amap = anchor_map(poly, P, N, A)
    assert amap.meta["dropped"] < 0.01 * len(P)
    # on the polycube's end face, where the identity is far from the part, the map lands on the slanted end
    q = poisson_disk(Vq, Fq, 2000, seed=5).points
    end = q[:, 0] > poly.xs[-1] - 1e-9
    err = np.linalg.norm(amap.map_points(q[end]) - shear(q[end]), axis=1)
    miss = np.linalg.norm(q[end] - shear(q[end]), axis=1)
    assert np.median(miss) > 0.05 and np.median(err) < 0.1 * np.median(miss)


def test_a_point_whose_direction_the_polycube_lacks_or_that_lies_far_from_it_is_not_used(slanted_l):
    _, _, poly, shear = slanted_l
    P, N, A = _generated(poly, shear)
    stray = np.array([[0.0, 0.0, 5.0]])  # far above the polycube, normal up
    amap = anchor_map(poly, np.vstack([P, stray]), np.vstack([N, [[0.0, 0.0, 1.0]]]), np.vstack([A, stray]))
    assert amap.meta["dropped"] >= 1
    assert not np.any(np.all(np.isclose(amap.anchors, stray), axis=1))
    with pytest.raises(ValueError, match="must all be"):
        anchor_map(poly, P, N, A[:-1])


def test_a_learned_polycube_whose_registration_misses_the_slant_is_meshed_through_the_models_own_map(slanted_l):
    """The registration leaves the end face where the polycube has it (the identity), so its mesh is off the
    part; the anchors say where each polycube point belongs, and the mesh through them follows the slanted end
    (no exact realisation needed)."""
    from polycubenet.pipeline import PipelineConfig, pull_back_learned
    from polycubenet.policy import distance_to_part, ends_chain

    V, F, poly, shear = slanted_l
    P, N, A = _generated(poly, shear)
    from polycubenet.pullback import PullbackConfig

    unmended = PullbackConfig(capture_spots=False)  # the registration's mesh as the map leaves it (no spot mend)
    cfg = PipelineConfig(target_hexes=1500, realise=None, learned_maps=("registration", "anchors"), pullback=unmended)
    identity = _Map(lambda X: np.asarray(X, float))
    plain, _ = pull_back_learned(poly, identity, V, F, cfg)  # no anchors: the registration alone
    assert plain.meta["map"] == "registration" and not ends_chain(plain.meta, cfg.min_sj)
    assert "anchors" not in PipelineConfig().learned_maps  # an option, not the default
    registration_alone = PipelineConfig(target_hexes=1500, realise=None, learned_maps=("registration",),
                                        pullback=unmended)
    by_default, _ = pull_back_learned(poly, identity, V, F, registration_alone, anchored=(P, N, A))
    assert by_default.meta["map"] == "registration"
    mesh, used = pull_back_learned(poly, identity, V, F, cfg, anchored=(P, N, A))
    assert mesh.meta["map"] == "anchors" and ends_chain(mesh.meta, cfg.min_sj)
    assert distance_to_part(mesh.meta) < 0.25 * distance_to_part(plain.meta)
    assert used is poly


def test_the_flow_stages_carry_each_kept_points_anchor_to_the_pull_back(slanted_l, tmp_path, monkeypatch):
    """The batched generation's cloud file keeps the anchors, the outlier filter keeps them row by row with
    the points, and the pull-back stage hands them to ``pull_back_learned``."""
    from polycubenet import library, pipeline
    from polycubenet.data import HexMesh

    V, F, poly, shear = slanted_l
    part = tmp_path / "slanted.stl"
    trimesh.Trimesh(V, F, process=False).export(part)
    cfg = pipeline.PipelineConfig(n_sample=2048, target_hexes=400)
    loaded = library.load_sample(part, tmp_path / "loaded.npz", cfg)
    P, N, _ = _generated(poly, shear, n=2000, noise=0.0)
    P = np.vstack([P, [[3.0, 3.0, 3.0]]])  # one stray point for the outlier filter
    N = np.vstack([N, [[1.0, 0.0, 0.0]]])
    A = P + np.array([10.0, 0.0, 0.0])  # a known anchor for every point
    cloud = library.write_generated(np.hstack([P, N]), tmp_path / "cloud.npz", {}, anchors=A)
    ext = library.cleanup_extract(cloud, loaded, tmp_path / "extract.npz", cfg)
    arrays, _ = library._load_arrays(ext)
    assert len(arrays["points"]) < len(P)
    np.testing.assert_allclose(arrays["anchors"], arrays["points"] + [10.0, 0.0, 0.0])
    seen = {}

    def fake(poly, corr, Vc, F, config, diagonal=None, part=None, partitioned=None, anchored=None, part_points=None,
             phase="all", prior=None):
        seen["anchored"], seen["phase"] = anchored, phase
        return HexMesh(np.zeros((8, 3)), np.arange(8)[None], meta={"valid": True}), poly

    monkeypatch.setattr(pipeline, "pull_back_learned", fake)
    corr = library.register(ext, loaded, tmp_path / "register.npz", cfg)
    library.partition_pullback(ext, corr, loaded, tmp_path / "hex.npz", cfg)
    got = seen["anchored"]
    assert got is not None and np.array_equal(got[2], arrays["anchors"]) and np.array_equal(got[0], arrays["points"])
    assert seen["phase"] == "all"  # one call unless the flow asks for the map's mesh first
