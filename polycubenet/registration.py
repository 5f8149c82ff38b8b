"""Registration of a polycube cloud to the part it came from: rigid, then non-rigid CPD.

The pipeline needs, for a point on the polycube, the point of the part surface it
stands for.  :func:`align` gets it in three steps:

1. :func:`rigid_align` -- similarity ICP (rotation, uniform scale, translation).
   Both clouds already live in the part's canonical frame, so the rotation is small:
   it starts from the identity and is clamped to ``max_angle_deg`` (default 20°) away
   from its start, which keeps a symmetric polycube from flipping by 180°.  The 24
   axis-aligned rotations are tried only when the caller asks; candidates are scored
   by distance *and* signed normal agreement (a flip of a nearly symmetric part can
   fit the points about as well, but turns the normals of its asymmetric features
   around), and a non-identity start must beat the identity by a clear margin -- so
   for an exactly symmetric polycube, where a flip is as good, the identity is kept.
2. :func:`cpd_nonrigid` -- Coherent Point Drift (Myronenko & Song 2010), written from
   scratch with a low-rank kernel (Nyström landmarks + Woodbury, float64) and a
   truncated E-step (each fixed point talks to its ``k`` nearest moving points), so
   an iteration costs ``O((M + N) k log + M m^2)`` instead of ``O(M N)``; large clouds
   are registered coarse-to-fine (1024, 4096, ... farthest-point samples first, one
   shared field basis).  torch is used on a GPU when one is present; the numpy/scipy
   path is the default otherwise.
3. Nearest-neighbour discretisation: every mapped polycube point takes the face id
   and barycentrics of the nearest part sample (or, given the part's mesh, of the
   closest point of the surface).

**Direction.**  The *polycube cloud moves* (CPD's ``Y``, the GMM centroids) and the
*part samples are fixed* (CPD's ``X``).  The fitted displacement field
``v(z) = sum_j g(z, l_j) phi_j`` is then defined on the polycube domain, so the hex
mesh's boundary vertices (which lie on the polycube) map to the part by
:meth:`Correspondence.map_points` -- rigid, then ``z + v(z)`` -- and a projection.

Units: all lengths (``beta``, distances) are in the canonical frame, where the part's
bounding-box diagonal is 1.  ``lam`` has units of 1 / length^2 there (the M-step
solves ``(G + lam sigma^2 diag(1/P1)) W = diag(1/P1) P X - Y``).  The defaults
``beta = 0.5``, ``lam = 300`` are strong, smooth fields -- about the textbook CPD
defaults (beta = 2, lambda = 2 on unit-variance data) rescaled to this frame -- and
were the best of those tried on synthetic polycube/part pairs (``polycubenet.synth``,
ground-truth maps): smaller kernels let points slide along the faces.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import sys
from typing import Any

import numpy as np
from scipy import linalg as sla
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from . import tol
from .data import SurfaceSample, _NpzRecord
from .threads import one_blas_thread
from .sampling import interpolate

#: default CPD kernel width (canonical frame, diagonal 1)
CPD_BETA = 0.5
#: default CPD regularisation weight (units 1 / length^2 in the canonical frame)
CPD_LAMBDA = 300.0
#: default CPD outlier weight w (uniform component of the mixture)
CPD_W = 0.1
#: default number of moving points each fixed point is compared with in the E-step (its KD-tree query is most of
#: the registration's time).  Session 57, generated clouds of the 118.30 h continue file registered at 32, 16 and
#: 8 (``benchmarks/cpd_neighbours.py``, the examples and never-seen turned 5 and machined 103): 16 takes 0.69-0.72
#: of 32's seconds and its map's mesh ends the chain on as many parts (8 / 10, 4 / 15, 7 / 15; 8 loses 2 turned
#: parts); the maps mostly within 0.1 % of the diagonal of 32's, a few settle elsewhere (up to 2.4 %) with meshes
#: as often within the bar (``benchmarks/results/s57_cpd_neighbours_C118.json``)
CPD_K = 16
#: CPD runs a coarse level of this many points first when a cloud has more than twice as many
CPD_COARSE = 1024
#: auto landmarks: farthest-point sampling until every moving point is within
#: LANDMARK_COVER * beta of a landmark, with the count clamped to LANDMARK_RANGE
LANDMARK_COVER = 0.5
LANDMARK_RANGE = (64, 600)
#: rigid candidates are scored as mean distance / diagonal + NORMAL_WEIGHT * (1 - normal agreement) / 2
NORMAL_WEIGHT = 0.1
#: a non-identity start must beat the identity's score by this relative margin
INIT_MARGIN = 0.05
#: with allow_permutations: iterations every start gets, and how many besides the identity go on
PERM_PROBE_ITER = 8
PERM_KEEP = 3
#: correspondences whose normals disagree by more than this are not used in ICP
ICP_NORMAL_DEG = 60.0


# --------------------------------------------------------------------------- helpers


def _as_points(a: Any, name: str) -> np.ndarray:
    p = np.asarray(a, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"{name} must be a non-empty (N, 3) array; got shape {p.shape}")
    if not np.isfinite(p).all():
        raise ValueError(f"{name} contains NaN or inf")
    return p


def _as_normals(a: Any, like: np.ndarray, name: str) -> np.ndarray | None:
    if a is None:
        return None
    n = np.asarray(a, dtype=np.float64)
    if n.shape != like.shape:
        raise ValueError(f"{name} must have shape {like.shape}; got {n.shape}")
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def gaussian_kernel(A: np.ndarray, B: np.ndarray, beta: float) -> np.ndarray:
    """Gaussian kernel matrix ``exp(-|a - b|^2 / (2 beta^2))``.

    Parameters
    ----------
    A : (P, 3) float64
    B : (Q, 3) float64
    beta : float, kernel width

    Returns
    -------
    (P, Q) float64
    """
    d2 = (A * A).sum(1)[:, None] + (B * B).sum(1)[None, :] - 2.0 * (A @ B.T)
    np.maximum(d2, 0.0, out=d2)
    return np.exp(-d2 / (2.0 * beta * beta))


def farthest_point_sampling(
    points: np.ndarray, m: int, *, radius: float = 0.0, min_count: int = 1, return_gaps: bool = False
):
    """Indices of up to ``m`` farthest-point samples of ``points : (N, 3)`` (deterministic).

    Starts at the point farthest from the centroid, then repeatedly adds the point
    farthest from those chosen.  Stops at ``m`` points, or earlier once every point is
    within ``radius`` of a chosen one (but not before ``min_count``).  Any prefix of the
    result is itself the farthest-point sample of that size.

    Returns
    -------
    idx : (m',) int64, m' <= m
    gaps : (m',) float64, only with ``return_gaps``: ``gaps[j]`` is the distance from
        point ``idx[j]`` to the ones before it, i.e. the covering radius of ``idx[:j]``
        (``gaps[0] = inf``)
    """
    P = np.asarray(points, dtype=np.float64)
    n = len(P)
    m = max(1, min(int(m), n))
    idx = np.empty(m, dtype=np.int64)
    gaps = np.empty(m, dtype=np.float64)
    idx[0] = int(np.argmax(((P - P.mean(0)) ** 2).sum(1)))
    gaps[0] = np.inf
    dmin = ((P - P[idx[0]]) ** 2).sum(1)
    r2 = float(radius) ** 2
    count = 1
    while count < m:
        j = int(np.argmax(dmin))
        if count >= min_count and dmin[j] <= r2:
            break
        idx[count] = j
        gaps[count] = math.sqrt(dmin[j])
        count += 1
        np.minimum(dmin, ((P - P[j]) ** 2).sum(1), out=dmin)
    if return_gaps:
        return idx[:count], gaps[:count]
    return idx[:count]


# --------------------------------------------------------------------------- rigid


def _proper_signed_permutations() -> np.ndarray:
    """The 24 rotations that map coordinate axes to coordinate axes, identity first, ``(24, 3, 3)``."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[np.arange(3), perm] = signs
            if np.linalg.det(R) > 0:
                mats.append(R)
    mats.sort(key=lambda R: -np.trace(R))  # identity (trace 3) first
    return np.stack(mats)


@dataclasses.dataclass
class RigidResult:
    """A similarity transform ``p -> s * p @ R.T + t`` and how well it fits.

    Attributes
    ----------
    R : (3, 3) float64, proper rotation
    s : float, uniform scale
    t : (3,) float64
    mean_distance : float, mean nearest-neighbour distance, both directions
    normal_agreement : float, mean dot of the normals of nearest pairs (nan without normals)
    score : float, ``mean_distance / diagonal + NORMAL_WEIGHT * (1 - normal_agreement) / 2``
    angle_deg : float, rotation angle of ``R``
    iterations : int
    start : int, index of the starting rotation (0: identity; else one of the 24 axis maps)
    """

    R: np.ndarray
    s: float
    t: np.ndarray
    mean_distance: float
    normal_agreement: float
    score: float
    angle_deg: float
    iterations: int
    start: int = 0

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform ``points : (K, 3)`` -> ``(K, 3)``."""
        return self.s * (np.asarray(points, dtype=np.float64) @ self.R.T) + self.t

    def apply_normals(self, normals: np.ndarray) -> np.ndarray:
        """Rotate ``normals : (K, 3)`` -> ``(K, 3)``."""
        return np.asarray(normals, dtype=np.float64) @ self.R.T

    def to_dict(self) -> dict:
        return {
            "R": self.R.tolist(), "s": float(self.s), "t": self.t.tolist(),
            "mean_distance": float(self.mean_distance), "normal_agreement": float(self.normal_agreement),
            "score": float(self.score), "angle_deg": float(self.angle_deg),
            "iterations": int(self.iterations), "start": int(self.start),
        }


def _clamp_rotation(R: np.ndarray, R0: np.ndarray, max_angle: float) -> np.ndarray:
    """``R`` if it is within ``max_angle`` (radians) of ``R0``, else the rotation on the same axis at ``max_angle``."""
    rv = Rotation.from_matrix(R @ R0.T).as_rotvec()
    ang = float(np.linalg.norm(rv))
    if ang <= max_angle:
        return R
    return Rotation.from_rotvec(rv * (max_angle / ang)).as_matrix() @ R0


def _umeyama(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Weighted similarity ``dst ~ s R src + t`` (Umeyama 1991), ``R`` proper."""
    wn = w / w.sum()
    ms, md = wn @ src, wn @ dst
    a, b = src - ms, dst - md
    H = (a * wn[:, None]).T @ b  # sum w a b^T
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    E = np.diag([1.0, 1.0, d])
    R = Vt.T @ E @ U.T
    var = float(wn @ (a * a).sum(1))
    s = float((S * np.diag(E)).sum() / var) if var > 0 else 1.0
    return R, s, md - s * (R @ ms)


def _fit_scale_translation(src, dst, w, R) -> tuple[float, np.ndarray]:
    """Best ``s, t`` for a fixed ``R``: minimise ``sum w |s R src + t - dst|^2``."""
    wn = w / w.sum()
    ms, md = wn @ src, wn @ dst
    a = (src - ms) @ R.T
    b = dst - md
    den = float(wn @ (a * a).sum(1))
    s = float(wn @ (a * b).sum(1)) / den if den > 0 else 1.0
    return s, md - s * (R @ ms)


def _pairs(Xs, Ns, tgt, tgt_n, tree_t, cos_max):
    """Symmetric nearest-neighbour pairs ``(i, j, dist, normal, weight)`` for the current pose."""
    d1, j1 = tree_t.query(Xs)
    d2, i2 = cKDTree(Xs).query(tgt)
    M, N = len(Xs), len(tgt)
    I = np.concatenate([np.arange(M), i2])
    J = np.concatenate([j1, np.arange(N)])
    dist = np.concatenate([d1, d2])
    w = np.ones(len(I))
    nrm = None
    if tgt_n is not None:
        # point-to-plane normal of each pair: the surface the point is matched onto
        nrm = np.concatenate([tgt_n[j1], Ns[i2] if Ns is not None else tgt_n[np.arange(N)]])
    if Ns is not None and tgt_n is not None:
        w *= (Ns[I] * tgt_n[J]).sum(1) >= cos_max
    # trim gross mismatches (coverage differences)
    med = float(np.median(dist[w > 0])) if (w > 0).any() else float(np.median(dist))
    w *= dist <= 3.0 * med + 1e-12
    if w.sum() < 6:
        w = np.ones(len(I))
    return I, J, dist, nrm, w


def _score(Xs, Ns, tgt, tgt_n, tree_t, diag) -> tuple[float, float, float]:
    d1, j1 = tree_t.query(Xs)
    d2, i2 = cKDTree(Xs).query(tgt)
    mean_d = float(np.concatenate([d1, d2]).mean())
    if Ns is None or tgt_n is None:
        agree = float("nan")
        score = mean_d / diag
    else:
        agree = float(np.concatenate([(Ns * tgt_n[j1]).sum(1), (Ns[i2] * tgt_n).sum(1)]).mean())
        score = mean_d / diag + NORMAL_WEIGHT * (1.0 - agree) / 2.0
    return mean_d, agree, score


def _icp(src, tgt, src_n, tgt_n, tree_t, R0, max_angle, max_iter, method, diag, init=None):
    """ICP from rotation ``R0`` (or from ``init=(R, s, t, iterations)``), rotation clamped near ``R0``."""
    cos_max = math.cos(math.radians(ICP_NORMAL_DEG))
    if init is None:
        R, s, t, it0 = R0.copy(), 1.0, tgt.mean(0) - R0 @ src.mean(0), 0
    else:
        R, s, t, it0 = init
    it = it0
    for it in range(it0 + 1, it0 + max_iter + 1):
        Xs = s * (src @ R.T) + t
        Ns = None if src_n is None else src_n @ R.T
        I, J, dist, nrm, w = _pairs(Xs, Ns, tgt, tgt_n, tree_t, cos_max)
        if method == "point_to_plane" and nrm is not None:
            sel = w > 0
            p, q, n = Xs[I[sel]], tgt[J[sel]], nrm[sel]
            c = p.mean(0)
            a = p - c
            Amat = np.column_stack([np.cross(a, n), (a * n).sum(1), n])
            r = ((p - q) * n).sum(1)
            delta, *_ = np.linalg.lstsq(Amat, -r, rcond=None)
            omega, sigma, tau = delta[:3], float(delta[3]), delta[4:]
            dR = Rotation.from_rotvec(omega).as_matrix()
            R_new = dR @ R
            s_new = s * (1.0 + sigma)
            t_new = (1.0 + sigma) * (dR @ (t - c)) + c + tau
            R_c = _clamp_rotation(R_new, R0, max_angle)
            if R_c is not R_new:
                s_new, t_new = _fit_scale_translation(src[I[sel]], q, np.ones(len(q)), R_c)
            step = float(np.linalg.norm(omega) + abs(sigma) + np.linalg.norm(tau))
            R, s, t = R_c, s_new, t_new
        else:
            R_new, s_new, t_new = _umeyama(src[I], tgt[J], w)
            R_c = _clamp_rotation(R_new, R0, max_angle)
            if R_c is not R_new:
                s_new, t_new = _fit_scale_translation(src[I], tgt[J], w, R_c)
            step = float(
                np.linalg.norm(Rotation.from_matrix(R_c @ R.T).as_rotvec())
                + abs(s_new / s - 1.0)
                + np.linalg.norm(t_new - t)
            )
            R, s, t = R_c, s_new, t_new
        if step < tol.ICP_STEP_MIN:
            break
    Xs = s * (src @ R.T) + t
    Ns = None if src_n is None else src_n @ R.T
    mean_d, agree, score = _score(Xs, Ns, tgt, tgt_n, tree_t, diag)
    angle = math.degrees(float(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))
    return RigidResult(R, float(s), np.asarray(t, float), mean_d, agree, score, angle, it)


def rigid_align(
    source: np.ndarray,
    target: np.ndarray,
    source_normals: np.ndarray | None = None,
    target_normals: np.ndarray | None = None,
    *,
    method: str | None = None,
    max_angle_deg: float = 20.0,
    allow_permutations: bool = False,
    max_iter: int = 60,
) -> RigidResult:
    """Similarity ICP: ``target ~ s * source @ R.T + t`` with a small rotation.

    Correspondences are nearest neighbours in both directions (source to target and
    target to source), pairs with disagreeing normals (> 60°) or distances above three
    times the median are dropped.  Each iteration either solves a scaled Umeyama
    (``"point_to_point"``) or linearises a point-to-plane step in rotation, scale and
    translation (``"point_to_plane"``, the default when ``target_normals`` are given).
    The rotation stays within ``max_angle_deg`` of its start.

    Parameters
    ----------
    source : (M, 3) float64, the moving cloud
    target : (N, 3) float64, the fixed cloud
    source_normals, target_normals : (M, 3), (N, 3) float64 or None
    method : {"point_to_plane", "point_to_point"} or None (auto)
    max_angle_deg : float, largest rotation away from the start
    allow_permutations : bool
        Also start from the 23 other axis-aligned rotations; the best score wins, but
        a non-identity start must beat the identity by ``INIT_MARGIN`` (relative).
    max_iter : int

    Returns
    -------
    RigidResult
    """
    src = _as_points(source, "source")
    tgt = _as_points(target, "target")
    src_n = _as_normals(source_normals, src, "source_normals")
    tgt_n = _as_normals(target_normals, tgt, "target_normals")
    if method is None:
        method = "point_to_plane" if tgt_n is not None else "point_to_point"
    if method not in ("point_to_plane", "point_to_point"):
        raise ValueError(f"method must be 'point_to_plane' or 'point_to_point'; got {method!r}")
    if method == "point_to_plane" and tgt_n is None:
        raise ValueError("point_to_plane needs target_normals")
    tree_t = cKDTree(tgt)
    diag = float(np.linalg.norm(tgt.max(0) - tgt.min(0))) or 1.0
    max_angle = math.radians(float(max_angle_deg))
    args = (src, tgt, src_n, tgt_n, tree_t)
    if not allow_permutations:
        return _icp(*args, np.eye(3), max_angle, int(max_iter), method, diag)
    # every start gets a few iterations; the identity and the best few others run to the end
    starts = _proper_signed_permutations()
    short = min(PERM_PROBE_ITER, int(max_iter))
    probes = [_icp(*args, R0, max_angle, short, method, diag) for R0 in starts]
    for k, r in enumerate(probes):
        r.start = k
    order = [0] + [k for k in np.argsort([r.score for r in probes]) if k != 0][:PERM_KEEP]
    best: RigidResult | None = None
    for k in order:
        r = probes[k]
        res = _icp(*args, starts[k], max_angle, int(max_iter) - short, method, diag, init=(r.R, r.s, r.t, r.iterations))
        res.start = k
        if best is None or res.score < best.score * (1.0 - INIT_MARGIN):
            best = res
    assert best is not None
    return best


# --------------------------------------------------------------------------- CPD backends


class _NumpyOps:
    name = "numpy"

    def index(self, idx):
        return np.asarray(idx)

    def asarray(self, a):
        return np.asarray(a, dtype=np.float64)

    def to_numpy(self, a):
        return np.asarray(a)

    def exp(self, a):
        return np.exp(a)

    def knn(self, T, X, k):
        d, idx = cKDTree(T).query(X, k=k)
        if k == 1:
            d, idx = d[:, None], idx[:, None]
        return d * d, idx

    def scatter(self, idx, vals, M):
        if vals.ndim == 1:
            return np.bincount(idx, vals, minlength=M)
        return np.stack([np.bincount(idx, vals[:, c], minlength=M) for c in range(vals.shape[1])], 1)

    def solve_spd(self, S, b):
        return _solve_spd_np(S, b)

    def kernel(self, A, B, beta):
        return gaussian_kernel(A, B, beta)


def _solve_spd_np(S: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``S x = b`` for symmetric positive (semi-)definite ``S`` (Cholesky, jitter fallback)."""
    S = 0.5 * (S + S.T)
    jitter = 0.0
    scale = float(np.trace(S)) / len(S) or 1.0
    for _ in range(6):
        try:
            c = sla.cho_factor(S + jitter * np.eye(len(S)), lower=True, check_finite=False)
            return sla.cho_solve(c, b, check_finite=False)
        except np.linalg.LinAlgError:
            jitter = scale * (1e-14 if jitter == 0.0 else jitter / scale * 100.0)
    return np.linalg.lstsq(S, b, rcond=None)[0]


class _TorchOps:
    name = "torch"

    def __init__(self, device):
        import torch

        self.torch = torch
        self.device = torch.device(device)

    def asarray(self, a):
        return self.torch.as_tensor(np.asarray(a, dtype=np.float64), device=self.device)

    def index(self, idx):
        return self.torch.as_tensor(np.asarray(idx, dtype=np.int64), device=self.device)

    def to_numpy(self, a):
        return a.detach().cpu().numpy()

    def exp(self, a):
        return self.torch.exp(a)

    def knn(self, T, X, k):
        torch = self.torch
        chunk = max(1, (1 << 24) // max(1, len(T)))
        ds, ids = [], []
        tt = (T * T).sum(1)
        for s in range(0, len(X), chunk):
            Xc = X[s : s + chunk]
            d2 = (Xc * Xc).sum(1)[:, None] + tt[None, :] - 2.0 * (Xc @ T.T)
            d2.clamp_(min=0.0)
            v, i = torch.topk(d2, k, dim=1, largest=False, sorted=True)
            ds.append(v)
            ids.append(i)
        return torch.cat(ds), torch.cat(ids)

    def scatter(self, idx, vals, M):
        shape = (M,) if vals.ndim == 1 else (M, vals.shape[1])
        return self.torch.zeros(shape, dtype=vals.dtype, device=vals.device).index_add_(0, idx, vals)

    def solve_spd(self, S, b):
        torch = self.torch
        S = 0.5 * (S + S.T)
        scale = float(torch.trace(S)) / len(S) or 1.0
        jitter = 0.0
        eye = torch.eye(len(S), dtype=S.dtype, device=S.device)
        for _ in range(6):
            L, info = torch.linalg.cholesky_ex(S + jitter * eye)
            if int(info) == 0:
                return torch.cholesky_solve(b, L)
            jitter = scale * (1e-14 if jitter == 0.0 else jitter / scale * 100.0)
        return torch.linalg.lstsq(S, b).solution

    def kernel(self, A, B, beta):
        d2 = (A * A).sum(1)[:, None] + (B * B).sum(1)[None, :] - 2.0 * (A @ B.T)
        return self.torch.exp(-d2.clamp(min=0.0) / (2.0 * beta * beta))


def _nvidia_present() -> bool:
    return os.path.exists("/proc/driver/nvidia") or os.path.exists("/dev/nvidia0")


def _ops(backend: str, device: str | None):
    if backend == "numpy":
        return _NumpyOps()
    if backend not in ("auto", "torch"):
        raise ValueError(f"backend must be 'auto', 'numpy' or 'torch'; got {backend!r}")
    if backend == "auto" and "torch" not in sys.modules and not _nvidia_present():
        return _NumpyOps()  # no GPU: do not pay torch's import time to find that out
    try:
        import torch
    except ImportError:
        if backend == "torch":
            raise ImportError("backend='torch' needs torch (pip install torch==2.13.0)") from None
        return _NumpyOps()
    if backend == "auto":
        return _TorchOps("cuda") if torch.cuda.is_available() else _NumpyOps()
    return _TorchOps(device or ("cuda" if torch.cuda.is_available() else "cpu"))


# --------------------------------------------------------------------------- CPD


@dataclasses.dataclass
class CPDResult(_NpzRecord):
    """Non-rigid CPD fit of moving points ``Y`` onto fixed points ``X``.

    The displacement field is ``v(z) = G(z, Y) W``, represented through the Nyström
    landmarks as ``v(z) = g(z, landmarks) @ coef`` (exactly what the fit used).

    Attributes
    ----------
    points : (M, 3) float64, the transformed moving points ``Y + v(Y)``
    W : (M, 3) float64, CPD coefficients (``G~ W = v(Y)`` with the low-rank ``G~``)
    landmarks : (m, 3) float64, the Nyström basis centres (a subset of ``Y``)
    coef : (m, 3) float64, field coefficients on the landmarks
    beta : float, kernel width
    sigma2 : float, final GMM variance
    iterations : int
    converged : bool, stopped on the tolerance (not on ``max_iter``)
    meta : dict, parameters (lam, w, k, backend, tol, ...)
    """

    points: np.ndarray
    W: np.ndarray
    landmarks: np.ndarray
    coef: np.ndarray
    beta: float
    sigma2: float
    iterations: int
    converged: bool
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self.beta = float(self.beta)
        self.sigma2 = float(self.sigma2)
        self.iterations = int(self.iterations)
        self.converged = bool(self.converged)

    def displacement(self, points: np.ndarray, *, chunk: int = 65536) -> np.ndarray:
        """Evaluate the displacement field at any points.

        Parameters
        ----------
        points : (K, 3) float64, in the moving cloud's coordinates
        chunk : int, rows per kernel block (memory ``chunk * m`` doubles)

        Returns
        -------
        (K, 3) float64, ``v(points)``; at the moving points it equals ``self.points - Y``
        """
        return field_displacement(points, self.landmarks, self.coef, self.beta, chunk=chunk)


def field_displacement(
    points: np.ndarray, landmarks: np.ndarray, coef: np.ndarray, beta: float, *, chunk: int = 65536
) -> np.ndarray:
    """``v(z) = g(z, landmarks) @ coef`` for ``points : (K, 3)`` -> ``(K, 3)``."""
    Z = np.asarray(points, dtype=np.float64)
    if Z.ndim != 2 or Z.shape[1] != 3:
        raise ValueError(f"points must be (K, 3); got shape {Z.shape}")
    out = np.empty_like(Z)
    for s in range(0, len(Z), chunk):
        out[s : s + chunk] = gaussian_kernel(Z[s : s + chunk], landmarks, beta) @ coef
    return out


def _global_sigma2(X: np.ndarray, Y: np.ndarray) -> float:
    """``sum_{m,n} |x_n - y_m|^2 / (D M N)`` in ``O(M + N)`` (the CPD initialisation)."""
    M, N = len(Y), len(X)
    sx, sy = X.sum(0), Y.sum(0)
    return float((M * (X * X).sum() + N * (Y * Y).sum() - 2.0 * sx @ sy) / (3.0 * M * N))


def cpd_nonrigid(
    Y: np.ndarray,
    X: np.ndarray,
    *,
    beta: float = CPD_BETA,
    lam: float = CPD_LAMBDA,
    w: float = CPD_W,
    max_iter: int = 100,
    tol_rel: float = 1e-4,
    n_landmarks: int | None = None,
    k: int = CPD_K,
    sigma2: float | None = None,
    coarse: int | None = CPD_COARSE,
    backend: str = "auto",
    device: str | None = None,
) -> CPDResult:
    """Non-rigid Coherent Point Drift: move ``Y`` onto ``X`` with a smooth Gaussian-kernel field.

    Low-rank M-step.  With Nyström landmarks ``L`` (farthest-point samples of ``Y``),
    ``C = G(Y, L)`` and ``A = G(L, L)``, the kernel is ``G ~ C A^-1 C^T``.  CPD's M-step
    ``(diag(P1) G + lam sigma^2 I) W = P X - diag(P1) Y =: R`` then solves by Woodbury as

        ``coef = (lam sigma^2 A + C^T diag(P1) C)^-1 C^T R``   (m x m, SPD, Cholesky)
        ``W = (R - diag(P1) C coef) / (lam sigma^2)``,   ``v(Y) = G~ W = C coef``

    -- no ``A^-1`` is ever formed.  Everything is float64 (float32 loses this solve).

    Truncated E-step.  Each fixed point ``x_n`` is compared only with its ``k`` nearest
    moving points (KD-tree on the moving points each iteration; brute-force blocks on
    torch): ``P[m, n] = exp(-|x_n - y_m|^2 / 2 sigma^2) / (sum_{k-NN} + c)``,
    ``c = (2 pi sigma^2)^{3/2} w / (1 - w) M / N``.  Once ``sigma`` is below the
    neighbourhood radius the dropped terms are negligible; while ``sigma`` is large the
    posterior is more local than the dense one (a soft nearest-neighbour pull).

    Two levels for large clouds (``coarse``, below), then ``sigma^2`` starts at the dense CPD initialisation (mean squared distance over all
    pairs, computed in ``O(M + N)``) unless given.  Iterations stop when the relative
    change of ``sigma^2`` is below ``tol_rel``, ``sigma^2 < tol.CPD_SIGMA2_MIN``, or after
    ``max_iter``.

    Parameters
    ----------
    Y : (M, 3) float64, moving points (the GMM centroids)
    X : (N, 3) float64, fixed points (the data)
    beta : float, Gaussian kernel width (canonical frame: diagonal 1)
    lam : float, regularisation weight (CPD's lambda, pycpd's alpha)
    w : float in [0, 1), weight of the uniform outlier component
    max_iter : int
    tol_rel : float, stop when ``|sigma2_prev - sigma2| / sigma2_prev < tol_rel``
    n_landmarks : int or None
        Nyström rank.  None: farthest-point sampling until every ``y`` is within
        ``LANDMARK_COVER * beta`` of a landmark, clamped to ``LANDMARK_RANGE``.
    k : int, neighbours per fixed point in the E-step (``k >= M`` gives the dense E-step)
    sigma2 : float or None, initial variance
    coarse : int or None
        When either cloud has more than ``2 * coarse`` points, first run CPD on
        ``coarse``, ``4 coarse``, ... (while below half the larger cloud) farthest-point
        samples of each (same landmarks, hence the same field basis), each level
        starting from the previous level's field and sigma^2, then the full clouds.  The
        truncated E-step sees only ``k`` neighbours, i.e. a radius that shrinks with
        density; the coarse level restores the wide early posteriors that let CPD
        find large, smooth motions.  None or 0: single level.
    backend : {"auto", "numpy", "torch"}; auto = torch on CUDA when available, else numpy
    device : str or None, torch device for ``backend="torch"``

    Returns
    -------
    CPDResult
    """
    Yn = _as_points(Y, "Y")
    Xn = _as_points(X, "X")
    if not beta > 0:
        raise ValueError(f"beta must be > 0; got {beta}")
    if not lam > 0:
        raise ValueError(f"lam must be > 0; got {lam}")
    if not 0 <= w < 1:
        raise ValueError(f"w must be in [0, 1); got {w}")
    M, N, D = len(Yn), len(Xn), 3
    k = int(max(1, min(int(k), M)))
    ops = _ops(backend, device)

    # landmarks: a prefix of one farthest-point ordering of Y, so that the coarse
    # level (a longer prefix) contains them and shares the same field basis
    levels = []  # coarse-to-fine subset sizes: coarse, 4 coarse, ... while below half the clouds
    if coarse:
        size = int(coarse)
        while 2 * size < max(M, N):
            levels.append(size)
            size *= 4
    n_coarse = max(levels, default=0)
    if n_landmarks is None:
        lo, hi = LANDMARK_RANGE
        order, gaps = farthest_point_sampling(Yn, max(min(hi, M), n_coarse), return_gaps=True)
        covered = np.flatnonzero(gaps[1:] <= LANDMARK_COVER * beta)  # gaps[j]: radius before point j
        m = int(covered[0]) + 1 if len(covered) else min(hi, M)
        m = max(min(lo, M), min(m, hi, M))
    else:
        m = max(1, min(int(n_landmarks), M))
        order = farthest_point_sampling(Yn, max(m, n_coarse))
    L_np = Yn[order[:m]]

    Yb, Xb, Lb = ops.asarray(Yn), ops.asarray(Xn), ops.asarray(L_np)
    C = ops.kernel(Yb, Lb, beta)  # (M, m)
    A = ops.kernel(Lb, Lb, beta)  # (m, m)
    s2 = _global_sigma2(Xn, Yn) if sigma2 is None else float(sigma2)
    if not s2 > 0:
        s2 = max(tol.CPD_SIGMA2_MIN, 1e-6)
    params = dict(beta=beta, lam=lam, w=w, k=k, tol_rel=tol_rel)

    # coarse levels: FPS prefixes of both clouds, same landmarks (so the same field basis);
    # each level's field and sigma^2 start the next one
    level_iters = []
    coef0 = None
    x_order = farthest_point_sampling(Xn, n_coarse) if levels else None
    for size in levels:
        yi, xi = ops.index(order[: min(size, M)]), ops.index(x_order[: min(size, N)])
        Cl = C[yi]
        T0 = None if coef0 is None else Yb[yi] + Cl @ coef0
        st = _cpd_iterate(ops, Yb[yi], Xb[xi], Cl, A, s2, T0, int(max_iter), **params)
        level_iters.append(st["iterations"])
        if st["coef"] is not None:
            coef0, s2 = st["coef"], st["sigma2"]
    it_coarse = sum(level_iters)
    T0 = None if coef0 is None else Yb + C @ coef0
    st = _cpd_iterate(ops, Yb, Xb, C, A, s2, T0, int(max_iter), **params)
    if st["coef"] is None:  # no iteration ran
        coef = np.zeros((m, D))
        W = np.zeros((M, D))
        T = Yn.copy()
    else:
        coef = ops.to_numpy(st["coef"])
        W = ops.to_numpy(st["W"])
        T = np.array(ops.to_numpy(st["T"]), dtype=np.float64)
    return CPDResult(
        points=T,
        W=W,
        landmarks=L_np,
        coef=coef,
        beta=float(beta),
        sigma2=st["sigma2"],
        iterations=it_coarse + st["iterations"],
        converged=st["converged"],
        meta={
            "lam": float(lam), "w": float(w), "k": k, "n_landmarks": int(m), "backend": ops.name,
            "tol_rel": float(tol_rel), "max_iter": int(max_iter), "coarse_levels": levels,
            "coarse_iterations": level_iters, "fine_iterations": st["iterations"],
        },
    )


def _cpd_iterate(ops, Yb, Xb, C, A, s2, T0, max_iter, *, beta, lam, w, k, tol_rel) -> dict:
    """CPD EM iterations (truncated E-step, low-rank M-step) from ``T0`` (default ``Yb``) and ``s2``."""
    M, N, D = len(Yb), len(Xb), 3
    k = min(k, M)
    T = Yb if T0 is None else T0
    xx = (Xb * Xb).sum(1)
    coef = W = None
    converged = False
    it = 0
    for it in range(1, max_iter + 1):
        # E-step (truncated): each x_n against its k nearest moving points
        d2, nbr = ops.knn(T, Xb, k)
        e = ops.exp(-d2 / (2.0 * s2))
        c = (2.0 * math.pi * s2) ** (D / 2.0) * w / (1.0 - w) * M / N
        den = e.sum(1) + c
        den = den + (den <= 0) * np.finfo(np.float64).tiny
        p = e / den[:, None]
        flat = nbr.reshape(-1)
        P1 = ops.scatter(flat, p.reshape(-1), M)
        PX = ops.scatter(flat, (p[:, :, None] * Xb[:, None, :]).reshape(-1, D), M)
        Np = float(P1.sum())
        if Np <= 0:
            break
        # M-step (low rank, Woodbury)
        alpha = lam * s2
        R = PX - P1[:, None] * Yb
        S = alpha * A + C.T @ (P1[:, None] * C)
        coef = ops.solve_spd(S, C.T @ R)
        W = (R - P1[:, None] * (C @ coef)) / alpha
        T = Yb + C @ coef
        # variance over the retained pairs, from moments (O(M + N))
        Pt1 = p.sum(1)
        s2_new = float(Pt1 @ xx - 2.0 * (PX * T).sum() + P1 @ (T * T).sum(1)) / (Np * D)
        s2_new = max(s2_new, tol.CPD_SIGMA2_MIN)
        change = abs(s2 - s2_new) / s2
        s2 = s2_new
        if change < tol_rel or s2 <= tol.CPD_SIGMA2_MIN:
            converged = True
            break
    return {"T": T, "coef": coef, "W": W, "sigma2": s2, "iterations": it, "converged": converged}


def _cpd_dense(
    Y: np.ndarray,
    X: np.ndarray,
    *,
    beta: float = CPD_BETA,
    lam: float = CPD_LAMBDA,
    w: float = CPD_W,
    max_iter: int = 100,
    tol_rel: float = 1e-4,
    sigma2: float | None = None,
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Reference dense CPD (full ``G``, full ``P``, ``O(M N)`` memory); for validation only.

    Same update rules and stopping rule as :func:`cpd_nonrigid`, without the low-rank
    kernel or the truncated E-step (the textbook algorithm, as in pycpd).

    Returns
    -------
    T : (M, 3) transformed ``Y``;  W : (M, 3);  sigma2 : float;  iterations : int
    """
    Y = _as_points(Y, "Y")
    X = _as_points(X, "X")
    M, N, D = len(Y), len(X), 3
    G = gaussian_kernel(Y, Y, beta)
    s2 = _global_sigma2(X, Y) if sigma2 is None else float(sigma2)
    T = Y.copy()
    W = np.zeros_like(Y)
    it = 0
    for it in range(1, int(max_iter) + 1):
        d2 = ((T[:, None, :] - X[None, :, :]) ** 2).sum(2)  # (M, N)
        e = np.exp(-d2 / (2.0 * s2))
        c = (2.0 * math.pi * s2) ** (D / 2.0) * w / (1.0 - w) * M / N
        P = e / (e.sum(0) + c + np.finfo(np.float64).tiny)[None, :]
        P1, Pt1 = P.sum(1), P.sum(0)
        Np = float(P1.sum())
        W = np.linalg.solve(P1[:, None] * G + lam * s2 * np.eye(M), P @ X - P1[:, None] * Y)
        T = Y + G @ W
        r2 = ((T[:, None, :] - X[None, :, :]) ** 2).sum(2)
        s2_new = max(float((P * r2).sum()) / (Np * D), tol.CPD_SIGMA2_MIN)
        change = abs(s2 - s2_new) / s2
        s2 = s2_new
        if change < tol_rel or s2 <= tol.CPD_SIGMA2_MIN:
            break
    return T, W, s2, it


# --------------------------------------------------------------------------- correspondence


@dataclasses.dataclass
class Correspondence(_NpzRecord):
    """Polycube cloud point -> part surface point, and the field that maps the polycube domain.

    Direction: the polycube cloud moved onto the part samples, so the map is defined
    on the polycube domain: ``map_points(z) = y + v(y)`` with ``y = s z R^T + t``.

    Attributes
    ----------
    points : (M, 3) float64, the (cleaned) polycube cloud, canonical frame
    mapped : (M, 3) float64, ``map_points(points)``: where each polycube point landed
    sample_ids : (M,) int64, the nearest part sample to each mapped point
    face_ids : (M,) int64, the part face of each polycube point's surface point
    barycentrics : (M, 3) float64, on that face; rows sum to 1
    surface_points : (M, 3) float64, ``interpolate(V, F, face_ids, barycentrics)``
    distance : (M,) float64, ``|mapped - surface_points|``
    rigid_R : (3, 3) float64;  rigid_t : (3,) float64 (scale in ``meta["rigid"]["s"]``)
    landmarks : (m, 3) float64;  coef : (m, 3) float64, the CPD field (``beta`` in meta)
    normals : (M, 3) float64 or None, the polycube cloud's normals
    meta : dict, ``direction``, ``projection``, ``beta``, ``lam``, ``w``, ``sigma2``,
        ``iterations``, ``converged``, ``rigid`` (RigidResult.to_dict())
    """

    points: np.ndarray
    mapped: np.ndarray
    sample_ids: np.ndarray
    face_ids: np.ndarray
    barycentrics: np.ndarray
    surface_points: np.ndarray
    distance: np.ndarray
    rigid_R: np.ndarray
    rigid_t: np.ndarray
    landmarks: np.ndarray
    coef: np.ndarray
    normals: np.ndarray | None = None
    meta: dict = dataclasses.field(default_factory=dict)

    def rigid(self, points: np.ndarray) -> np.ndarray:
        """The rigid (similarity) part of the map, ``(K, 3) -> (K, 3)``."""
        return float(self.meta["rigid"]["s"]) * (np.asarray(points, dtype=np.float64) @ self.rigid_R.T) + self.rigid_t

    def map_points(self, points: np.ndarray) -> np.ndarray:
        """Map polycube-domain points near the part surface: rigid, then ``+ v``.

        Parameters
        ----------
        points : (K, 3) float64, canonical frame (e.g. hex boundary vertices on the polycube)

        Returns
        -------
        (K, 3) float64 (not yet projected onto the surface)
        """
        y = self.rigid(points)
        return y + field_displacement(y, self.landmarks, self.coef, float(self.meta["beta"]))


#: the finer field of :func:`refine` (canonical frame, diagonal 1): the registration's field (``CPD_BETA``) is
#: too smooth to bend the polycube's axis-aligned steps onto a slanted or recessed face of the part
REFINE_BETA = 0.2


@dataclasses.dataclass
class RefinedCorrespondence:
    """A correspondence's map followed by a second, finer CPD field fitted from where the first one put the
    polycube cloud (:func:`refine`): ``map_points(z) = y + v2(y)`` with ``y = base.map_points(z)``."""

    base: Correspondence
    landmarks: np.ndarray
    coef: np.ndarray
    beta: float
    meta: dict = dataclasses.field(default_factory=dict)

    def map_points(self, points: np.ndarray) -> np.ndarray:
        y = self.base.map_points(points)
        return y + field_displacement(y, self.landmarks, self.coef, self.beta)


def refine(corr: Correspondence, part_points: np.ndarray, *, beta: float = REFINE_BETA, lam: float = CPD_LAMBDA,
           **cpd_kw) -> RefinedCorrespondence:
    """A second CPD pass with a narrower kernel (``beta``), from the polycube cloud as ``corr`` maps it onto the
    fixed part samples ``part_points`` ``(N, 3)``: the first field's large, smooth motion is kept and the second
    one adds the local bend (a step of the polycube onto a slanted face).  ``cpd_kw``: :func:`cpd_nonrigid`'s."""
    Y = corr.map_points(corr.points)
    cpd = cpd_nonrigid(Y, _as_points(part_points, "part_points"), beta=beta, lam=lam, **cpd_kw)
    return RefinedCorrespondence(base=corr, landmarks=cpd.landmarks, coef=cpd.coef, beta=float(cpd.beta),
                                 meta={"beta": float(cpd.beta), "lam": float(lam), "sigma2": cpd.sigma2,
                                       "iterations": cpd.iterations})


def _project_to_mesh(points: np.ndarray, V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest surface point of each of ``points : (K, 3)`` on ``(V, F)``: ``face_ids (K,)``, ``barycentrics (K, 3)``."""
    try:
        import trimesh
    except ImportError as exc:  # pragma: no cover - depends on the machine
        raise ImportError("projecting onto the part surface needs trimesh (pip install trimesh)") from exc
    mesh = trimesh.Trimesh(np.asarray(V, np.float64), np.asarray(F, np.int64), process=False)
    closest, _, tri = trimesh.proximity.closest_point(mesh, points)
    tri = np.asarray(tri, dtype=np.int64)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], closest)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(1, keepdims=True)
    return tri, bary


@one_blas_thread
def align(
    sample: SurfaceSample,
    cloud_points: np.ndarray,
    cloud_normals: np.ndarray | None = None,
    *,
    surface: tuple[np.ndarray, np.ndarray] | None = None,
    beta: float = CPD_BETA,
    lam: float = CPD_LAMBDA,
    w: float = CPD_W,
    max_iter: int = 100,
    tol_rel: float = 1e-4,
    n_landmarks: int | None = None,
    k: int = CPD_K,
    max_angle_deg: float = 20.0,
    allow_permutations: bool = False,
    coarse: int | None = CPD_COARSE,
    backend: str = "auto",
) -> Correspondence:
    """Register a polycube cloud to the part's surface sample and discretise the map.

    Rigid (:func:`rigid_align`, polycube cloud -> part samples), then non-rigid
    (:func:`cpd_nonrigid`, the rigidly placed polycube cloud moving onto the fixed part
    samples), then every mapped polycube point takes the face id and barycentrics of
    its nearest part sample -- or, when ``surface=(V, F)`` is given, of its closest
    point on the part's triangles.

    Parameters
    ----------
    sample : SurfaceSample, the part's samples (canonical frame) with their exact map to ``(V, F)``
    cloud_points : (M, 3) float64, the (cleaned) polycube cloud, canonical frame
    cloud_normals : (M, 3) float64 or None
    surface : (V (nv, 3), F (nf, 3)) or None, the part mesh the sample came from
    beta, lam, w, max_iter, tol_rel, n_landmarks, k, coarse, backend : see :func:`cpd_nonrigid`
    max_angle_deg, allow_permutations : see :func:`rigid_align`

    Returns
    -------
    Correspondence
    """
    P = _as_points(cloud_points, "cloud_points")
    Pn = _as_normals(cloud_normals, P, "cloud_normals")
    Xs = _as_points(sample.points, "sample.points")
    rig = rigid_align(
        P, Xs, Pn, sample.normals, max_angle_deg=max_angle_deg, allow_permutations=allow_permutations
    )
    Y = rig.apply(P)
    cpd = cpd_nonrigid(
        Y, Xs, beta=beta, lam=lam, w=w, max_iter=max_iter, tol_rel=tol_rel,
        n_landmarks=n_landmarks, k=k, coarse=coarse, backend=backend,
    )
    mapped = cpd.points
    _, sid = cKDTree(Xs).query(mapped)
    sid = np.asarray(sid, dtype=np.int64)
    if surface is None:
        face_ids = np.asarray(sample.face_ids, dtype=np.int64)[sid]
        bary = np.asarray(sample.barycentrics, dtype=np.float64)[sid]
        surf = Xs[sid]
        projection = "nearest_sample"
    else:
        V, F = surface
        face_ids, bary = _project_to_mesh(mapped, V, F)
        surf = interpolate(V, F, face_ids, bary)
        projection = "surface"
    return Correspondence(
        points=P,
        mapped=mapped,
        sample_ids=sid,
        face_ids=face_ids,
        barycentrics=bary,
        surface_points=surf,
        distance=np.linalg.norm(mapped - surf, axis=1),
        rigid_R=rig.R,
        rigid_t=rig.t,
        landmarks=cpd.landmarks,
        coef=cpd.coef,
        normals=Pn,
        meta={
            "direction": "polycube cloud (moving) -> part samples (fixed)",
            "projection": projection,
            "beta": cpd.beta, "sigma2": cpd.sigma2, "iterations": cpd.iterations,
            "converged": cpd.converged, **cpd.meta, "rigid": rig.to_dict(),
        },
    )
