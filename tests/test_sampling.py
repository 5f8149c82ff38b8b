"""Poisson-disk sampling: exact count, blue noise, reproducibility, exact barycentric map."""

from __future__ import annotations

import numpy as np
import pytest

from polycubenet.data import SurfaceSample
from polycubenet.sampling import interpolate, min_spacing, poisson_disk, uniform_sample


@pytest.mark.parametrize("n", [64, 100, 1000, 4096, 20000])
def test_exact_count_and_exact_map(torus, n):
    V, F = torus
    s = poisson_disk(V, F, n, seed=1)
    assert s.points.shape == (n, 3) and s.normals.shape == (n, 3)
    assert s.face_ids.shape == (n,) and s.barycentrics.shape == (n, 3)
    np.testing.assert_allclose(interpolate(V, F, s.face_ids, s.barycentrics), s.points, rtol=0, atol=1e-9)
    assert (s.barycentrics >= -1e-12).all()
    np.testing.assert_allclose(s.barycentrics.sum(1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-12)
    assert len(np.unique(s.points, axis=0)) == n


def test_largest_count(l_block):
    V, F = l_block
    s = poisson_disk(V, F, 65536, seed=0)
    assert len(s.points) == 65536
    np.testing.assert_allclose(interpolate(V, F, s.face_ids, s.barycentrics), s.points, rtol=0, atol=1e-9)


@pytest.mark.parametrize("n", [256, 4096])
def test_blue_noise_beats_uniform(torus, n):
    V, F = torus
    s = poisson_disk(V, F, n, seed=2)
    u = uniform_sample(V, F, n, np.random.default_rng(2))
    # Poisson-disk keeps points apart: the closest pair is far more than white noise's
    assert min_spacing(s.points) > 5.0 * min_spacing(u.points)
    # and the spacing is near the ideal for n disks on this area (hexagonal packing radius)
    area = 4 * np.pi**2 * 1.0 * 0.35
    ideal = np.sqrt(2 * area / (np.sqrt(3) * n))
    assert min_spacing(s.points) > 0.3 * ideal


def test_reproducible_by_seed(torus):
    V, F = torus
    a = poisson_disk(V, F, 2048, seed=11)
    b = poisson_disk(V, F, 2048, seed=11)
    c = poisson_disk(V, F, 2048, seed=12)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.face_ids, b.face_ids)
    assert not np.array_equal(a.points, c.points)


def test_sample_roundtrip_npz(tmp_path, torus):
    V, F = torus
    s = poisson_disk(V, F, 128, seed=0)
    p = s.save(tmp_path / "s.npz")
    t = SurfaceSample.load(p)
    np.testing.assert_array_equal(t.points, s.points)
    np.testing.assert_array_equal(t.face_ids, s.face_ids)
    assert t.meta == s.meta
    assert not list(tmp_path.glob(".tmp-*"))


def test_rejects_bad_counts(torus):
    V, F = torus
    with pytest.raises(ValueError):
        poisson_disk(V, F, 0)
    with pytest.raises(ValueError, match="zero area"):
        uniform_sample(np.zeros((3, 3)), np.array([[0, 1, 2]]), 10, np.random.default_rng(0))


def test_without_open3d_the_numpy_elimination_gives_the_same_points(torus, monkeypatch):
    import polycubenet.sampling as sampling

    V, F = torus
    with_o3d = poisson_disk(V, F, 1500, seed=4)

    def missing():
        raise ImportError("no open3d here")

    monkeypatch.setattr(sampling, "_open3d", missing)
    s = poisson_disk(V, F, 1500, seed=4)
    assert s.meta["eliminator"] == "numpy" and with_o3d.meta["eliminator"] == "open3d"
    assert len(s.points) == 1500
    assert np.allclose(interpolate(V, F, s.face_ids, s.barycentrics), s.points)
    # Yuksel's elimination with open3d's parameters: the very points open3d keeps
    key = lambda p: np.lexsort(p.T)  # noqa: E731
    assert np.allclose(s.points[key(s.points)], with_o3d.points[key(with_o3d.points)])
    assert min_spacing(s.points) > 5 * min_spacing(uniform_sample(V, F, 1500, np.random.default_rng(4)).points)
