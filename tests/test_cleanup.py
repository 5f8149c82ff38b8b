"""Two-phase L1 outlier filter: removes off-surface points, keeps the surface, L1 metric, explicit tau / K."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from polycubenet.cleanup import default_k, remove_outliers, spacing_l1
from polycubenet.sampling import poisson_disk, uniform_sample


@pytest.fixture(scope="module")
def noisy_cloud(l_block_canonical):
    """4096 Poisson-disk points on the L-block (diagonal 1) + Gaussian noise of 0.1 spacing."""
    V, F = l_block_canonical
    s = poisson_disk(V, F, 4096, seed=3)
    spacing = float(np.median(cKDTree(s.points).query(s.points, k=2)[0][:, 1]))
    rng = np.random.default_rng(3)
    pts = s.points + rng.normal(scale=0.1 * spacing, size=s.points.shape)
    return pts, s.normals, spacing


def _surface_distance(V, F, points):
    import trimesh

    _, d, _ = trimesh.proximity.closest_point(trimesh.Trimesh(V, F, process=False), points)
    return d


def test_removes_uniform_outliers(l_block_canonical, noisy_cloud):
    V, F = l_block_canonical
    pts, nrm, spacing = noisy_cloud
    rng = np.random.default_rng(7)
    n_out = int(0.02 * len(pts))
    lo, hi = V.min(0), V.max(0)
    out = lo + rng.random((n_out, 3)) * (hi - lo)
    out_n = rng.normal(size=(n_out, 3))
    P = np.vstack([pts, out])
    N = np.vstack([nrm, out_n])
    kept, kept_n, mask = remove_outliers(P, N)
    assert mask.shape == (len(P),) and mask.dtype == bool
    np.testing.assert_array_equal(kept, P[mask])
    np.testing.assert_array_equal(kept_n, N[mask])

    inlier_loss = 1.0 - mask[: len(pts)].mean()
    assert inlier_loss < 0.02
    # an "outlier" within a sample spacing of the surface is on the surface at this
    # resolution; every point that is clearly off it (> 2 spacings) must go
    d = _surface_distance(V, F, out)
    far = d > 2.0 * spacing
    assert far.sum() >= 0.6 * n_out  # the test is about something
    assert 1.0 - mask[len(pts):][far].mean() >= 0.9
    assert 1.0 - mask[len(pts):].mean() >= 0.6


@pytest.mark.parametrize("kind", ["poisson", "uniform"])
def test_clean_cloud_loses_under_one_percent(l_block_canonical, noisy_cloud, kind):
    V, F = l_block_canonical
    if kind == "poisson":
        pts = noisy_cloud[0]
    else:  # white noise: Rayleigh-tailed nearest-neighbour distances, the harder case
        pts = uniform_sample(V, F, 4096, np.random.default_rng(11)).points
    kept, kept_n, mask = remove_outliers(pts)
    assert kept_n is None
    assert 1.0 - mask.mean() < 0.01


def test_order_two_catches_outlier_pairs(l_block_canonical, noisy_cloud):
    V, F = l_block_canonical
    pts, _, spacing = noisy_cloud
    rng = np.random.default_rng(5)
    lo, hi = V.min(0), V.max(0)
    centers = lo + rng.random((400, 3)) * (hi - lo)
    centers = centers[_surface_distance(V, F, centers) > 4.0 * spacing][:20]
    pairs = np.concatenate([centers, centers + 0.3 * spacing * rng.normal(size=centers.shape)])
    P = np.vstack([pts, pairs])
    _, _, m1 = remove_outliers(P, order=1)
    _, _, m2 = remove_outliers(P, order=2)
    # the paper's nearest-neighbour rule keeps a close pair (each is the other's neighbour)
    assert m1[len(pts):].mean() > 0.5
    # the second neighbour does not
    assert not m2[len(pts):].any()
    assert 1.0 - m2[: len(pts)].mean() < 0.01


def test_phase_one_uses_l1_distance():
    # a cluster keeps the median spacing small; a and b are at L2 distance 1.04 but L1 distance 1.8
    rng = np.random.default_rng(0)
    cluster = rng.random((50, 3)) * 0.5 + 10.0
    a, b = np.zeros(3), np.full(3, 0.6)
    P = np.vstack([cluster, a, b])
    _, _, mask = remove_outliers(P, tau=1.5, k=0)
    assert mask[:50].all() and not mask[50] and not mask[51]
    _, _, mask = remove_outliers(P, tau=1.9, k=0)
    assert mask.all()


def test_explicit_k_prunes_the_k_sparsest():
    rng = np.random.default_rng(1)
    P = rng.random((500, 3))
    d = cKDTree(P).query(P, k=2, p=1)[0][:, 1]
    _, _, mask = remove_outliers(P, tau=np.inf, k=7)
    assert (~mask).sum() == 7
    assert set(np.flatnonzero(~mask)) == set(np.argsort(d)[-7:])


def test_defaults_scale_free(noisy_cloud):
    pts = noisy_cloud[0]
    _, _, m1 = remove_outliers(pts)
    _, _, m2 = remove_outliers(pts * 1000.0 + 5.0)
    np.testing.assert_array_equal(m1, m2)
    assert spacing_l1(pts * 2.0) == pytest.approx(2.0 * spacing_l1(pts))


def test_default_k_rule():
    d = np.ones(1000)
    d[:10] = 10.0  # ten clear outliers
    assert default_k(d) == 10
    d[:200] = 10.0  # capped at 5 %
    assert default_k(d) == 50
    assert default_k(np.ones(2)) == 0


def test_tiny_and_bad_input():
    P = np.zeros((2, 3))
    kept, _, mask = remove_outliers(P)
    assert mask.all() and len(kept) == 2
    with pytest.raises(ValueError, match="points must be"):
        remove_outliers(np.zeros((5, 2)))
    with pytest.raises(ValueError, match="NaN"):
        remove_outliers(np.full((5, 3), np.nan))
    with pytest.raises(ValueError, match="normals"):
        remove_outliers(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="tau"):
        remove_outliers(np.random.default_rng(0).random((5, 3)), tau=-1.0)
    with pytest.raises(ValueError, match="order"):
        remove_outliers(np.random.default_rng(0).random((5, 3)), order=0)
