"""Rigid ICP with scale, low-rank CPD against a dense reference, the field, and the correspondence."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from polycubenet.registration import (
    CPDResult,
    Correspondence,
    _cpd_dense,
    align,
    cpd_nonrigid,
    farthest_point_sampling,
    refine,
    rigid_align,
)
from polycubenet.sampling import interpolate, poisson_disk


def smooth_warp(p: np.ndarray, a: float = 0.05, wavelength: float = 1.0) -> np.ndarray:
    """``p + a sin(2 pi p_perm / wavelength)``: a smooth, invertible warp of magnitude ~a."""
    b = 2.0 * np.pi / wavelength
    return p + a * np.sin(b * p[:, [1, 2, 0]])


@pytest.fixture(scope="module")
def part(l_block_canonical):
    return l_block_canonical


@pytest.fixture(scope="module")
def sample(part):
    V, F = part
    return poisson_disk(V, F, 1500, seed=0)


@pytest.fixture(scope="module")
def box():
    import trimesh

    m = trimesh.creation.box(extents=[0.8, 0.5, 0.3]).subdivide().subdivide()
    V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    return poisson_disk(V, F, 1200, seed=1), poisson_disk(V, F, 1200, seed=2)


# ---------------------------------------------------------------------------- rigid


@pytest.mark.parametrize("method", ["point_to_plane", "point_to_point"])
def test_rigid_recovers_similarity(sample, method):
    R = Rotation.from_rotvec(np.radians(7.0) * np.array([1.0, 2.0, -1.0]) / np.sqrt(6.0)).as_matrix()
    s, t = 1.07, np.array([0.02, -0.015, 0.01])
    tgt = s * sample.points @ R.T + t
    res = rigid_align(sample.points, tgt, sample.normals, sample.normals @ R.T, method=method)
    np.testing.assert_allclose(res.R, R, atol=1e-3)
    assert res.s == pytest.approx(s, abs=1e-3)
    np.testing.assert_allclose(res.t, t, atol=1e-3)
    np.testing.assert_allclose(res.apply(sample.points), tgt, atol=1e-3)
    assert res.normal_agreement > 0.999
    assert res.angle_deg == pytest.approx(7.0, abs=1e-2)


def test_rigid_recovers_similarity_across_samplings(part, sample):
    """Target is a different sample of the transformed surface (no exact point pairs)."""
    V, F = part
    R = Rotation.from_rotvec(np.radians([2.0, -3.0, 4.0])).as_matrix()
    s, t = 0.95, np.array([-0.01, 0.02, 0.005])
    other = poisson_disk(s * V @ R.T + t, F, 1500, seed=9)
    res = rigid_align(sample.points, other.points, sample.normals, other.normals)
    np.testing.assert_allclose(res.R, R, atol=1e-3)
    assert res.s == pytest.approx(s, abs=1e-3)
    np.testing.assert_allclose(res.t, t, atol=1e-3)


@pytest.mark.parametrize("normals", [True, False])
def test_rigid_does_not_flip_symmetric_box(box, normals):
    a, b = box
    R5 = Rotation.from_rotvec(np.radians(5.0) * np.array([0.0, 0.0, 1.0])).as_matrix()
    tgt = b.points @ R5.T
    an = a.normals if normals else None
    bn = b.normals @ R5.T if normals else None
    res = rigid_align(a.points, tgt, an, bn, allow_permutations=True)
    # the box is symmetric under 180 degree turns: those fit as well, but are not taken
    assert res.start == 0
    # point-to-plane (with normals) is exact on planar faces; point-to-point between two
    # different samplings is limited by the sampling (a fraction of a degree)
    tol_deg = 0.05 if normals else 1.0
    assert res.angle_deg == pytest.approx(5.0, abs=tol_deg)
    np.testing.assert_allclose(res.R, R5, atol=np.radians(tol_deg) * 1.5)


def test_rigid_angle_is_clamped_without_permutations(sample):
    R90 = Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix()
    tgt = sample.points @ R90.T
    res = rigid_align(sample.points, tgt, sample.normals, sample.normals @ R90.T, max_angle_deg=20.0)
    assert res.angle_deg <= 20.0 + 1e-6


def test_rigid_permutations_find_a_quarter_turn(sample):
    R90 = Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix()
    tgt = sample.points @ R90.T
    res = rigid_align(sample.points, tgt, sample.normals, sample.normals @ R90.T, allow_permutations=True)
    assert res.start != 0
    np.testing.assert_allclose(res.R, R90, atol=1e-6)


# ---------------------------------------------------------------------------- CPD


def test_fps_is_deterministic_and_spread(sample):
    i1 = farthest_point_sampling(sample.points, 50)
    i2 = farthest_point_sampling(sample.points, 50)
    np.testing.assert_array_equal(i1, i2)
    assert len(np.unique(i1)) == 50
    r = farthest_point_sampling(sample.points, 10_000, radius=0.2)
    assert 1 < len(r) < 200


def test_cpd_recovers_smooth_warp(sample):
    Y = sample.points
    X = smooth_warp(Y)
    mag = np.linalg.norm(X - Y, axis=1).mean()
    res = cpd_nonrigid(Y, X, max_iter=40, backend="numpy")
    err = np.linalg.norm(res.points - X, axis=1).mean()
    assert mag > 0.03
    assert err / mag < 0.02
    # the field at the moving points is exactly what moved them
    np.testing.assert_allclose(res.displacement(Y), res.points - Y, rtol=0, atol=1e-12)
    # and it extends the warp to points it never saw (midpoints of neighbouring samples)
    Z = 0.5 * (Y[:-1] + Y[1:])[:200]
    true = smooth_warp(Z) - Z
    assert np.linalg.norm(res.displacement(Z) - true, axis=1).mean() / mag < 0.05


def test_cpd_coarse_levels(part):
    V, F = part
    Y = poisson_disk(V, F, 2100, seed=5).points
    X = smooth_warp(Y)
    mag = np.linalg.norm(X - Y, axis=1).mean()
    res = cpd_nonrigid(Y, X, coarse=1024, max_iter=40, backend="numpy")
    assert res.meta["coarse_levels"] == [1024] and res.meta["coarse_iterations"][0] > 0
    assert res.iterations == res.meta["coarse_iterations"][0] + res.meta["fine_iterations"]
    assert np.linalg.norm(res.points - X, axis=1).mean() / mag < 0.02
    # the levels share one landmark basis: the final field still reproduces the points
    np.testing.assert_allclose(res.displacement(Y), res.points - Y, rtol=0, atol=1e-12)
    assert cpd_nonrigid(Y, X, coarse=None, max_iter=2, backend="numpy").meta["coarse_levels"] == []


@pytest.fixture(scope="module")
def small_pair(part):
    V, F = part
    Y = poisson_disk(V, F, 300, seed=4).points
    return Y, smooth_warp(Y)


def test_lowrank_matches_dense_with_full_estep(small_pair):
    """Same iterations, dense E-step (k = M): only the Nystrom kernel differs."""
    Y, X = small_pair
    mag = np.linalg.norm(X - Y, axis=1).mean()
    T, _, s2, _ = _cpd_dense(Y, X, max_iter=10, tol_rel=0.0)
    res = cpd_nonrigid(Y, X, max_iter=10, tol_rel=0.0, k=len(Y), n_landmarks=150, backend="numpy")
    assert np.abs(res.points - T).max() / mag < 1e-6
    assert res.sigma2 == pytest.approx(s2, rel=1e-6)
    res64 = cpd_nonrigid(Y, X, max_iter=10, tol_rel=0.0, k=len(Y), n_landmarks=64, backend="numpy")
    assert np.abs(res64.points - T).max() / mag < 1e-4


def test_dense_reference_matches_pycpd(small_pair):
    """The dense reference is the textbook algorithm: it agrees with pycpd (benchmark-only dependency)."""
    pycpd = pytest.importorskip("pycpd")
    Y, X = small_pair
    Y, X = Y[:150], X[:150]
    T, _, s2, _ = _cpd_dense(Y, X, beta=0.5, lam=300.0, w=0.1, max_iter=15, tol_rel=0.0)
    reg = pycpd.DeformableRegistration(X=X, Y=Y, alpha=300.0, beta=0.5, w=0.1, max_iterations=15, tolerance=1e-300)
    TY, _ = reg.register()
    np.testing.assert_allclose(T, TY, rtol=0, atol=1e-9)
    assert s2 == pytest.approx(reg.sigma2, rel=1e-8)


def test_lowrank_truncated_matches_dense_at_convergence(small_pair):
    Y, X = small_pair
    mag = np.linalg.norm(X - Y, axis=1).mean()
    T, _, _, _ = _cpd_dense(Y, X, max_iter=60)
    res = cpd_nonrigid(Y, X, max_iter=60, backend="numpy")  # default k, landmarks
    assert np.abs(res.points - T).max() / mag < 1e-2
    assert np.linalg.norm(res.points - T, axis=1).mean() / mag < 2e-3


def test_torch_backend_matches_numpy(small_pair):
    pytest.importorskip("torch")
    Y, X = small_pair
    # the default truncated E-step over a few iterations, and every moving point as a neighbour over more: the
    # backends agree to round-off at each iteration, and round-off can flip which point is a sample's k-th
    # nearest when two are almost as near (with k = 16 here at the tenth iteration)
    for kw in ({"max_iter": 5}, {"max_iter": 10, "k": len(Y)}):
        a = cpd_nonrigid(Y, X, tol_rel=0.0, backend="numpy", **kw)
        b = cpd_nonrigid(Y, X, tol_rel=0.0, backend="torch", device="cpu", **kw)
        assert b.meta["backend"] == "torch"
        np.testing.assert_allclose(b.points, a.points, rtol=0, atol=1e-8)
        assert b.sigma2 == pytest.approx(a.sigma2, rel=1e-8)


def test_cpd_result_round_trip(tmp_path, small_pair):
    Y, X = small_pair
    res = cpd_nonrigid(Y, X, max_iter=5, backend="numpy")
    back = CPDResult.load(res.save(tmp_path / "cpd.npz"))
    assert back.iterations == res.iterations and back.beta == res.beta and back.meta == res.meta
    np.testing.assert_array_equal(back.displacement(X), res.displacement(X))


def test_cpd_validates_input(small_pair):
    Y, X = small_pair
    with pytest.raises(ValueError, match="beta"):
        cpd_nonrigid(Y, X, beta=0.0)
    with pytest.raises(ValueError, match="w must"):
        cpd_nonrigid(Y, X, w=1.0)
    with pytest.raises(ValueError, match="Y must"):
        cpd_nonrigid(Y[:, :2], X)
    with pytest.raises(ValueError, match="backend"):
        cpd_nonrigid(Y, X, backend="jax")


# ---------------------------------------------------------------------------- correspondence


@pytest.fixture(scope="module")
def polycube_like(part):
    """A "polycube cloud": another sample of the part, warped, slightly turned, scaled and moved.

    Returns the cloud, its normals and each cloud point's true position on the part.
    """
    V, F = part
    s = poisson_disk(V, F, 1200, seed=21)
    R = Rotation.from_rotvec(np.radians([1.0, -2.0, 1.5])).as_matrix()
    cloud = 1.03 * smooth_warp(s.points, a=0.03) @ R.T + np.array([0.01, 0.0, -0.01])
    return cloud, s.normals @ R.T, s.points


def test_align_correspondence(part, sample, polycube_like, tmp_path):
    V, F = part
    cloud, normals, truth = polycube_like
    corr = align(sample, cloud, normals, backend="numpy")
    M = len(cloud)
    assert corr.face_ids.shape == (M,) and corr.barycentrics.shape == (M, 3)
    # face ids + barycentrics reconstruct the surface points exactly
    np.testing.assert_allclose(interpolate(V, F, corr.face_ids, corr.barycentrics), corr.surface_points, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(corr.surface_points, sample.points[corr.sample_ids])
    # the stored field reproduces the mapped points anywhere
    np.testing.assert_allclose(corr.map_points(cloud), corr.mapped, rtol=0, atol=1e-12)
    # the field carries each cloud point far closer to its true partner than doing nothing
    before = np.linalg.norm(cloud - truth, axis=1).mean()
    assert np.linalg.norm(corr.mapped - truth, axis=1).mean() < 0.25 * before
    # snapping to the nearest sample cannot beat the sampling itself (the true partner's
    # distance to its nearest sample); it stays within half of that again
    floor = cKDTree(sample.points).query(truth)[0].mean()
    assert np.linalg.norm(corr.surface_points - truth, axis=1).mean() < 1.5 * floor
    assert corr.meta["direction"].startswith("polycube")
    back = Correspondence.load(corr.save(tmp_path / "corr.npz"))
    for name in ("points", "mapped", "face_ids", "barycentrics", "surface_points", "landmarks", "coef", "normals"):
        np.testing.assert_array_equal(getattr(back, name), getattr(corr, name))
    np.testing.assert_allclose(back.map_points(cloud[:10]), corr.mapped[:10], atol=1e-12)


def test_align_projects_onto_surface(part, sample, polycube_like):
    V, F = part
    cloud, normals, truth = polycube_like
    corr = align(sample, cloud, normals, surface=(V, F), backend="numpy")
    assert corr.meta["projection"] == "surface"
    assert (corr.barycentrics >= 0).all()
    np.testing.assert_allclose(corr.barycentrics.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(interpolate(V, F, corr.face_ids, corr.barycentrics), corr.surface_points, rtol=0, atol=1e-9)
    # with the mesh there is no sampling floor
    assert np.linalg.norm(corr.surface_points - truth, axis=1).mean() < 0.25 * np.linalg.norm(cloud - truth, axis=1).mean()
    # projecting onto the triangles is at least as close as snapping to the nearest sample
    assert corr.distance.mean() <= np.linalg.norm(corr.mapped - sample.points[corr.sample_ids], axis=1).mean() + 1e-12


def test_refine_follows_a_local_bend_the_registration_field_smooths_over():
    """A bump narrower than the registration's kernel: the registration leaves the cloud off the part there,
    the refined map (a second, finer field from where the first one put the cloud) brings it onto the part."""
    import trimesh

    m = trimesh.creation.box(extents=[0.8, 0.5, 0.3]).subdivide().subdivide().subdivide()
    V, F = np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)
    sample = poisson_disk(V, F, 1500, seed=0)
    s = poisson_disk(V, F, 1200, seed=21)
    d = np.linalg.norm(s.points - np.array([0.4, 0.0, 0.0]), axis=1)
    cloud = s.points + 0.05 * np.exp(-(d / 0.12) ** 2)[:, None] * np.array([1.0, 0.0, 0.0])  # the +x end bulges
    corr = align(sample, cloud, s.normals, backend="numpy")
    ref = refine(corr, sample.points)
    off = cKDTree(poisson_disk(V, F, 20000, seed=5).points)
    near = d < 0.15
    base_off = off.query(corr.mapped)[0]
    ref_off = off.query(ref.map_points(cloud))[0]
    assert ref_off[near].mean() < 0.7 * base_off[near].mean()
    assert ref_off.max() < 0.7 * base_off.max()
    assert ref_off.mean() <= base_off.mean()  # and no worse elsewhere
    assert ref.meta["beta"] < corr.meta["beta"]
