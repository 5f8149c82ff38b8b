"""Poisson-disk (blue-noise) sampling of a triangle surface with an exact map back.

``poisson_disk(V, F, n, seed)`` returns exactly ``n`` points.  Candidates are
drawn area-uniformly (face chosen with probability proportional to its area,
uniform barycentrics), ``oversample * n`` of them, and Yuksel's sample
elimination (open3d ``sample_points_poisson_disk`` with ``pcl=``) keeps ``n`` of
them that are as evenly spread as possible.  Elimination picks existing
candidates, so every output point is one of our candidates and keeps its face id
and barycentric coordinates exactly.  Where open3d cannot be imported (the lent GPU
machines' image has none), the same elimination runs in numpy/scipy
(:func:`eliminate_samples`, ~5x slower): the same method and parameters, and on every
part tried the very points open3d keeps (tested on a torus); ``meta["eliminator"]`` says
which ran.
"""

from __future__ import annotations

import heapq

import numpy as np
from scipy.spatial import cKDTree

from .data import SurfaceSample
from .frame import face_normals_areas

MIN_POINTS = 1
MAX_POINTS = 1 << 20


def _open3d():
    try:
        from ._o3d import open3d as o3d
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise ImportError(
            "Poisson-disk sampling needs open3d (pip install open3d; on Debian also "
            "`apt-get install libusb-1.0-0`)"
        ) from exc
    return o3d


def uniform_sample(V: np.ndarray, F: np.ndarray, n: int, rng: np.random.Generator) -> SurfaceSample:
    """Area-uniform random points on ``(V, F)`` (white noise, the baseline for blue noise).

    Parameters
    ----------
    V : (nv, 3) float64
    F : (nf, 3) int64
    n : int
    rng : np.random.Generator

    Returns
    -------
    SurfaceSample with ``n`` points
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    normals, areas = face_normals_areas(V, F)
    total = areas.sum()
    if not np.isfinite(total) or total <= 0:
        raise ValueError("cannot sample a surface with zero area")
    cdf = np.cumsum(areas)
    face_ids = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right")
    face_ids = np.minimum(face_ids, len(F) - 1)
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    bary = np.stack([1.0 - u - v, u, v], axis=1)
    points = interpolate(V, F, face_ids, bary)
    return SurfaceSample(points, normals[face_ids], face_ids, bary)


def interpolate(V: np.ndarray, F: np.ndarray, face_ids: np.ndarray, barycentrics: np.ndarray) -> np.ndarray:
    """Points ``(K, 3)`` at ``barycentrics (K, 3)`` of faces ``face_ids (K,)`` of ``(V, F)``."""
    tri = np.asarray(V, dtype=np.float64)[np.asarray(F)[face_ids]]
    return np.einsum("kj,kjd->kd", barycentrics, tri)


def poisson_disk(
    V: np.ndarray,
    F: np.ndarray,
    n: int,
    seed: int = 0,
    *,
    oversample: int = 5,
) -> SurfaceSample:
    """Exactly ``n`` blue-noise points on the surface ``(V, F)``.

    Parameters
    ----------
    V : (nv, 3) float64
    F : (nf, 3) int64
    n : int, number of points (1 .. 2**20)
    seed : int, makes the result reproducible
    oversample : int, candidates per output point

    Returns
    -------
    SurfaceSample
        ``points (n, 3)``, unit face ``normals (n, 3)``, ``face_ids (n,)`` and
        ``barycentrics (n, 3)`` with ``points == interpolate(V, F, face_ids, barycentrics)``.
    """
    n = int(n)
    if not MIN_POINTS <= n <= MAX_POINTS:
        raise ValueError(f"n must be in [{MIN_POINTS}, {MAX_POINTS}]; got {n}")
    rng = np.random.default_rng(seed)
    cand = uniform_sample(V, F, max(oversample, 2) * n, rng)
    try:
        o3d = _open3d()
    except ImportError:
        area = float(face_normals_areas(np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64))[1].sum())
        idx = np.sort(eliminate_samples(cand.points, n, area))
        return SurfaceSample(
            points=cand.points[idx], normals=cand.normals[idx], face_ids=cand.face_ids[idx],
            barycentrics=cand.barycentrics[idx],
            meta={"method": "poisson_disk", "seed": int(seed), "oversample": int(oversample), "eliminator": "numpy"},
        )
    o3d.utility.random.seed(int(np.random.SeedSequence(seed).generate_state(1)[0] & 0x7FFFFFFF))
    pcl = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cand.points))
    pcl.normals = o3d.utility.Vector3dVector(cand.normals)
    # open3d needs a mesh object for the call; with pcl= given it only eliminates among its points
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(V, dtype=np.float64)),
        o3d.utility.Vector3iVector(np.asarray(F, dtype=np.int32)),
    )
    kept = np.asarray(mesh.sample_points_poisson_disk(n, pcl=pcl).points)
    dist, idx = cKDTree(cand.points).query(kept)
    idx = np.unique(idx)
    if len(idx) > n:  # cannot happen with exact matches; keep the contract anyway
        idx = np.sort(rng.choice(idx, n, replace=False))
    elif len(idx) < n:  # compensation: top up with random unused candidates
        unused = np.setdiff1d(np.arange(len(cand.points)), idx)
        idx = np.sort(np.concatenate([idx, rng.choice(unused, n - len(idx), replace=False)]))
    return SurfaceSample(
        points=cand.points[idx],
        normals=cand.normals[idx],
        face_ids=cand.face_ids[idx],
        barycentrics=cand.barycentrics[idx],
        meta={"method": "poisson_disk", "seed": int(seed), "oversample": int(oversample), "eliminator": "open3d"},
    )


def eliminate_samples(points: np.ndarray, n: int, area: float, alpha: float = 8.0, beta: float = 0.65,
                      gamma: float = 1.5) -> np.ndarray:
    """Indices of ``n`` of ``points (M, 3)``, sampled on a surface of ``area``, kept by weighted
    sample elimination (Yuksel 2015, as open3d's ``sample_points_poisson_disk`` does it).

    Each point weighs ``sum (1 - d / r_max) ** alpha`` over its neighbours closer than
    ``r_max = 2 sqrt(area / n / (2 sqrt 3))`` (``d`` floored at ``r_min = r_max * beta *
    (1 - (n / M) ** gamma)``); the heaviest point is removed and its neighbours' weights
    lowered, until ``n`` remain.  Deterministic (ties go to the lower index).
    """
    P = np.asarray(points, dtype=np.float64)
    M, n = len(P), int(n)
    if n >= M:
        return np.arange(M)
    r_max = 2.0 * np.sqrt(area / n / (2.0 * np.sqrt(3.0)))
    r_min = r_max * beta * (1.0 - (n / M) ** gamma)
    pairs = cKDTree(P).query_pairs(r_max, output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    d = np.maximum(np.linalg.norm(P[i] - P[j], axis=1), r_min)
    w = (1.0 - np.minimum(d, r_max) / r_max) ** alpha
    weight = np.bincount(i, w, minlength=M) + np.bincount(j, w, minlength=M)
    # symmetric adjacency (CSR by hand): neighbours and pair weights of each point
    src = np.concatenate([i, j])
    dst = np.concatenate([j, i])
    ww = np.concatenate([w, w])
    order = np.argsort(src, kind="stable")
    dst, ww = dst[order], ww[order]
    start = np.concatenate([[0], np.cumsum(np.bincount(src, minlength=M))])
    alive = np.ones(M, dtype=bool)
    heap = [(-weight[k], k) for k in range(M)]
    heapq.heapify(heap)
    left = M
    while left > n:
        wk, k = heapq.heappop(heap)
        if not alive[k] or -wk != weight[k]:
            continue  # a stale entry
        alive[k] = False
        left -= 1
        for m, wm in zip(dst[start[k]:start[k + 1]], ww[start[k]:start[k + 1]]):
            if alive[m]:
                weight[m] -= wm
                heapq.heappush(heap, (-weight[m], int(m)))
    return np.flatnonzero(alive)


def min_spacing(points: np.ndarray) -> float:
    """Smallest distance between two distinct points of ``points : (N, 3)``."""
    d, _ = cKDTree(points).query(points, k=2)
    return float(d[:, 1].min())
