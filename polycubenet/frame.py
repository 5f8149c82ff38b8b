"""The canonical frame: where every part lives while it is meshed.

``canonicalize(V, F)`` finds a rigid rotation that aligns the part's dominant
(area-weighted) face normals with the coordinate axes, then centres the
rotated bounding box at the origin and scales its diagonal to 1.  The model is
trained on shapes in this frame, and the polycube it generates is axis-aligned
in it, so every later stage works in this frame and maps back with
:meth:`Transform.inverse` at the end.

Among the 24 rotations that align the same normals with the axes, the frame is
made unique (up to symmetries of the part) by ordering the axes by bounding-box
extent (x longest, z shortest) and choosing the signs so that the area-weighted
third moment of the surface along x and y is non-negative.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: faces further than this from their nearest axis do not pull the rotation
_ALIGN_CONE_DEG = 25.0
#: then the rotation is refined again with these tighter cones in turn, so that a slanted face within
#: the first cone (a 20-25 degree chamfer, a machined part's slanted end) stops tilting the frame
_TIGHTEN_CONES_DEG = (12.0, 5.0, 2.0)
#: faces within this angle count as aligned when scoring a candidate
_SCORE_CONE_DEG = 5.0


@dataclasses.dataclass(frozen=True)
class Transform:
    """A similarity transform ``p -> ((p - center) * scale) @ rotation.T``.

    Attributes
    ----------
    center : (3,) float64, in the original coordinates
    scale : float
    rotation : (3, 3) float64, proper rotation (det = +1)
    """

    center: np.ndarray
    scale: float
    rotation: np.ndarray

    def forward(self, points: np.ndarray) -> np.ndarray:
        """Map ``points : (..., 3)`` from the original frame to the canonical frame."""
        p = np.asarray(points, dtype=np.float64)
        return ((p - self.center) * self.scale) @ self.rotation.T

    def inverse(self, points: np.ndarray) -> np.ndarray:
        """Map ``points : (..., 3)`` from the canonical frame back to the original frame."""
        p = np.asarray(points, dtype=np.float64)
        return (p @ self.rotation) / self.scale + self.center

    def forward_normals(self, normals: np.ndarray) -> np.ndarray:
        """Rotate unit ``normals : (..., 3)`` into the canonical frame."""
        return np.asarray(normals, dtype=np.float64) @ self.rotation.T

    def inverse_normals(self, normals: np.ndarray) -> np.ndarray:
        """Rotate unit ``normals : (..., 3)`` back to the original frame."""
        return np.asarray(normals, dtype=np.float64) @ self.rotation

    def forward_mesh(self, V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map a mesh; faces are unchanged (a proper rotation keeps orientation)."""
        return self.forward(V), np.asarray(F)

    def inverse_mesh(self, V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.inverse(V), np.asarray(F)

    def compose(self, other: "Transform") -> "Transform":
        """The transform ``other.forward(self.forward(p))``."""
        # other(self(p)) = ((((p - c1) s1 R1^T) - c2) s2) R2^T
        #               = (p - c1 - c2 R1 / s1) s1 s2 (R2 R1)^T
        center = self.center + (other.center @ self.rotation) / self.scale
        return Transform(center, self.scale * other.scale, other.rotation @ self.rotation)

    def to_dict(self) -> dict:
        return {"center": self.center.tolist(), "scale": float(self.scale), "rotation": self.rotation.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "Transform":
        return cls(np.asarray(d["center"], float), float(d["scale"]), np.asarray(d["rotation"], float))

    @classmethod
    def identity(cls) -> "Transform":
        return cls(np.zeros(3), 1.0, np.eye(3))


def face_normals_areas(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit face normals ``(F, 3)`` and areas ``(F,)``; zero-area faces get a zero normal."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    cross = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    norm = np.linalg.norm(cross, axis=1)
    normals = np.divide(cross, norm[:, None], out=np.zeros_like(cross), where=norm[:, None] > 0)
    return normals, 0.5 * norm


def _weighted_kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Proper rotation R minimising ``sum w |R src_i - dst_i|^2``."""
    H = (src * w[:, None]).T @ dst
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def _nearest_axes(n: np.ndarray) -> np.ndarray:
    """For unit vectors ``n : (K, 3)`` the nearest signed coordinate axis, ``(K, 3)``."""
    k = np.argmax(np.abs(n), axis=1)
    t = np.zeros_like(n)
    t[np.arange(len(n)), k] = np.sign(n[np.arange(len(n)), k])
    return t


def _refine(R: np.ndarray, normals: np.ndarray, areas: np.ndarray, iters: int = 30,
            cone_deg: float = _ALIGN_CONE_DEG) -> np.ndarray:
    """Alternate nearest-axis assignment and weighted Kabsch from the start rotation ``R``, with the
    faces within ``cone_deg`` of their nearest axis."""
    cos_cone = np.cos(np.radians(cone_deg))
    for _ in range(iters):
        rn = normals @ R.T
        t = _nearest_axes(rn)
        cos = np.abs(rn).max(axis=1)
        w = areas * (cos > cos_cone)
        if w.sum() <= 0:
            return R
        R_next = _weighted_kabsch(normals, t, w)
        converged = np.allclose(R_next, R, atol=1e-14)
        R = R_next
        if converged:
            break
    return R


def _score(R: np.ndarray, normals: np.ndarray, areas: np.ndarray) -> float:
    """Area fraction of faces within ``_SCORE_CONE_DEG`` of an axis after rotation ``R``."""
    cos = np.abs(normals @ R.T).max(axis=1)
    return float(areas[cos > np.cos(np.radians(_SCORE_CONE_DEG))].sum() / max(areas.sum(), 1e-300))


def _frame_from(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """Rotation whose rows are ``a``, ``b`` orthonormalised and ``a x b``."""
    na = np.linalg.norm(a)
    if na < 1e-12:
        return None
    a = a / na
    b = b - a * (a @ b)
    nb = np.linalg.norm(b)
    if nb < 1e-6:
        return None
    b = b / nb
    return np.stack([a, b, np.cross(a, b)])


def _candidates(V: np.ndarray, normals: np.ndarray, areas: np.ndarray) -> list[np.ndarray]:
    """Start rotations: identity, principal axes, and frames of the dominant normal clusters."""
    out = [np.eye(3)]
    c = V - V.mean(axis=0)
    _, vecs = np.linalg.eigh(c.T @ c)
    pca = vecs.T[::-1]
    if np.linalg.det(pca) < 0:
        pca[2] *= -1
    out.append(pca)
    # dominant directions: area mass within 10 degrees (both orientations) of the heaviest faces
    order = np.argsort(-areas)[:256]
    cand = normals[order]
    cos10 = np.cos(np.radians(10.0))
    mass = (np.abs(cand @ normals.T) > cos10) @ areas
    ranked = cand[np.argsort(-mass)]
    masses = np.sort(mass)[::-1]
    if len(ranked) and masses[0] > 0:
        a = ranked[0]
        sin10 = np.sin(np.radians(10.0))
        perp = np.abs(ranked @ a) < sin10
        if perp.any():
            b = ranked[np.argmax(perp)]
            R = _frame_from(a, b)
            if R is not None:
                out.append(R)
        # a second frame from the best direction of a different cluster, for robustness
        other = np.abs(ranked @ a) < cos10
        if other.any() and masses[np.argmax(other)] > 0:
            a2 = ranked[np.argmax(other)]
            perp2 = np.abs(ranked @ a2) < sin10
            if perp2.any():
                R = _frame_from(a2, ranked[np.argmax(perp2)])
                if R is not None:
                    out.append(R)
    return out


def _disambiguate(R: np.ndarray, V: np.ndarray, F: np.ndarray, areas: np.ndarray) -> np.ndarray:
    """Among the 24 signed axis permutations of ``R`` pick the canonical one (module docstring)."""
    P = V @ R.T
    ext = P.max(axis=0) - P.min(axis=0)
    perm = np.argsort(-ext, kind="stable")
    R = R[perm]
    P = P[:, perm]
    centre = 0.5 * (P.max(axis=0) + P.min(axis=0))
    # third moment of the surface (area-weighted face centroids) about the bbox centre
    cent = P[F].mean(axis=1) - centre
    m3 = (areas[:, None] * cent**3).sum(axis=0)
    scale = np.abs(ext).max() ** 3 * max(areas.sum(), 1e-300)
    signs = np.where(m3 < -1e-9 * scale, -1.0, 1.0)
    R = R * signs[:, None]
    if np.linalg.det(R) < 0:
        R[2] *= -1
    return R


def best_rotation(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotation aligning the area-weighted face normals of ``(V, F)`` with the axes.

    Returns
    -------
    rotation : (3, 3) float64, proper
    aligned_fraction : float, area fraction of faces within 5 degrees of an axis afterwards
    """
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    normals, areas = face_normals_areas(V, F)
    best, best_score = np.eye(3), -1.0
    for R0 in _candidates(V, normals, areas):
        R = _refine(R0, normals, areas)
        s = _score(R, normals, areas)
        tight = R
        for cone in _TIGHTEN_CONES_DEG:
            tight = _refine(tight, normals, areas, cone_deg=cone)
        s_tight = _score(tight, normals, areas)
        if s_tight >= s - 1e-9:  # a part whose faces are mostly curved may lose aligned area: keep R
            R, s = tight, s_tight
        if s > best_score + 1e-12:
            best, best_score = R, s
    return _disambiguate(best, V, F, areas), best_score


def canonicalize(V: np.ndarray, F: np.ndarray, *, rotate: bool = True) -> tuple[np.ndarray, Transform]:
    """Put a part into the canonical frame.

    Parameters
    ----------
    V : (N, 3) float64
    F : (M, 3) int64
    rotate : bool, when False only centre and scale (rotation = identity)

    Returns
    -------
    V_canonical : (N, 3) float64, bounding box centred at 0 with diagonal 1
    transform : Transform, with ``transform.forward(V) == V_canonical``
    """
    V = np.asarray(V, dtype=np.float64)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise ValueError(f"vertices must be a non-empty (N, 3) array; got shape {V.shape}")
    R = best_rotation(V, F)[0] if rotate else np.eye(3)
    P = V @ R.T
    lo, hi = P.min(axis=0), P.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if not np.isfinite(diag) or diag <= 0:
        raise ValueError("cannot canonicalize a part with a zero-size bounding box")
    center = (0.5 * (lo + hi)) @ R  # back in the original coordinates
    t = Transform(center=center, scale=1.0 / diag, rotation=R)
    return t.forward(V), t
