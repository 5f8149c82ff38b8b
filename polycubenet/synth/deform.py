"""Random smooth invertible deformations that turn a polycube into a "CAD" shape.

A :class:`DeformationMap` is a composition of elementary maps of R^3, applied in list
order, each a small object with JSON-able parameters (so a pair records its map
exactly and :meth:`DeformationMap.from_dict` rebuilds it).  Families:

``round_hole``
    a through-hole or pocket of rectangular section pushed toward a cylinder: in the
    hole's cross-section, after scaling the rectangle to a unit square, each point
    moves along its ray from the hole axis so that the square becomes a (super)circle;
    the effect fades to identity a little away from the hole.  Ray-wise monotone, so
    a bijection.
``round_edge``
    a fillet (square corner -> quarter circle) or chamfer (corner -> 45 degree cut) of
    a convex edge (of the bounding box, a step, an extruded profile), as a ray-wise
    radial map in the quadrant within ``radius`` of both faces, fading out within the
    four grid cells around the edge.  Bijective.
``ramp``
    heights scaled down along a direction by a C1 piecewise-linear profile: the top
    face becomes a planar ramp (slope up to ~35 degrees) with smooth ends.
``taper``, ``shear``, ``twist``, ``bend``
    the classical Barr deformations (bend: the part is wrapped around a circle).
``ffd``
    a free-form lattice: Bernstein (degree 3) control-point displacements over the
    bounding box, small enough to be injective (mild organic bending).

Every map is smooth except along measure-zero sets (the diagonals of the rounding
maps), where it stays continuous and bijective.  :func:`jacobian_determinants`
estimates ``det J`` with central differences; :func:`check_invertible` samples many
points in the bounding box and rejects a map whose determinant falls below a bound.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, ClassVar

import numpy as np

#: central-difference step of the Jacobian (the polycube's diagonal is 1)
FD_STEP = 1e-5
#: a deformation whose Jacobian determinant falls below this anywhere sampled is rejected
MIN_DET = 0.005


def _smoothstep(t: np.ndarray) -> np.ndarray:
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _soft_ramp(t: np.ndarray, e: float) -> np.ndarray:
    """C1 ramp from 0 (t <= 0) to 1 (t >= 1), linear on [e, 1 - e] with slope 1 / (1 - e)."""
    t = np.clip(t, 0.0, 1.0)
    k = 1.0 / (2.0 * e * (1.0 - e))
    return np.where(
        t < e, k * t * t, np.where(t > 1.0 - e, 1.0 - k * (1.0 - t) ** 2, (t - 0.5 * e) / (1.0 - e))
    )


def _pnorm(u: np.ndarray, v: np.ndarray, p: float) -> np.ndarray:
    """``(|u|^p + |v|^p)^(1/p)`` computed stably (inf = max)."""
    au, av = np.abs(u), np.abs(v)
    m = np.maximum(au, av)
    if np.isinf(p):
        return m
    safe = np.where(m > 0, m, 1.0)
    a, b = au / safe, av / safe  # in [0, 1]: no overflow
    if p >= 2 and float(np.log2(p)).is_integer():  # repeated squaring, much faster than pow
        for _ in range(int(np.log2(p))):
            a, b = a * a, b * b
        s = a + b
    else:
        s = a**p + b**p
    return m * s ** (1.0 / p)


class ElementaryMap:
    """Base class: ``__call__(X : (N, 3)) -> (N, 3)`` and JSON-able ``params``."""

    kind: ClassVar[str] = ""
    registry: ClassVar[dict[str, type["ElementaryMap"]]] = {}

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        if cls.kind:
            ElementaryMap.registry[cls.kind] = cls

    def __call__(self, X: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def to_dict(self) -> dict:
        out = {"kind": self.kind}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = np.asarray(v).tolist() if isinstance(v, np.ndarray) else v
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "ElementaryMap":
        sub = ElementaryMap.registry[d["kind"]]
        kwargs = {}
        for f in dataclasses.fields(sub):
            if f.name not in d and f.default is not dataclasses.MISSING:  # a field added later
                v = f.default
            else:
                v = d[f.name]
            kwargs[f.name] = np.asarray(v, dtype=np.float64) if isinstance(v, list) else v
        return sub(**kwargs)


def _other_axes(axis: int) -> tuple[int, int]:
    return (axis + 1) % 3, (axis + 2) % 3


@dataclasses.dataclass
class RoundHole(ElementaryMap):
    """Push a rectangular hole along ``axis`` toward an elliptic cylinder.

    Parameters
    ----------
    axis : int
    center : (3,) hole axis passes through this point (the ``axis`` component unused)
    half : (2,) half sizes of the hole section along the two other axes (cyclic order)
    p : float, exponent of the norm whose unit ball the square maps from (large = sharper)
    strength : float in (0, 1], 1 = fully round
    fade : float > 0, the effect vanishes at normalized radius ``1 + fade``
    """

    kind: ClassVar[str] = "round_hole"
    axis: int
    center: np.ndarray
    half: np.ndarray
    p: float
    strength: float
    fade: float

    def __call__(self, X: np.ndarray) -> np.ndarray:
        b, c = _other_axes(self.axis)
        u = (X[:, b] - self.center[b]) / self.half[0]
        v = (X[:, c] - self.center[c]) / self.half[1]
        Y = X.copy()
        near = np.maximum(np.abs(u), np.abs(v)) < 1.0 + self.fade  # rho >= sup norm: outside is identity
        if not near.any():
            return Y
        u, v = u[near], v[near]
        r2 = np.hypot(u, v)
        rho = _pnorm(u, v, self.p)
        w = 1.0 - _smoothstep((rho - 1.0) / self.fade)
        ratio = np.divide(rho, r2, out=np.ones_like(r2), where=r2 > 0)
        f = 1.0 + self.strength * w * (ratio - 1.0)
        Y[near, b] = self.center[b] + u * f * self.half[0]
        Y[near, c] = self.center[c] + v * f * self.half[1]
        return Y


@dataclasses.dataclass
class RoundEdge(ElementaryMap):
    """Fillet or chamfer the convex edge along ``axis`` at ``corner``.

    In the quadrant within ``radius`` of both faces (origin ``corner - radius * signs``),
    each point moves along its ray from the origin so that the square corner becomes a
    quarter circle (fillet) or a 45 degree cut (chamfer); the effect fades out between
    ``radius`` and ``radius * (1 + fade)`` (sup norm from the origin).  Ray-wise
    monotone, hence a bijection; identity outside that small region.

    Parameters
    ----------
    axis : int, the edge direction
    corner : (2,) the edge's coordinates on the two other axes (cyclic order)
    signs : (2,) +1 / -1, the outward direction of the two faces meeting at the edge
    radius : float, fillet radius / chamfer leg (on the first of the two other axes)
    style : str, ``fillet`` or ``chamfer``
    fade : float > 0
    radius2 : float or None, the leg on the second axis when it differs (an elliptic fillet,
        or a chamfer cut at ``atan(radius2 / radius)``: a slanted end); the map is the
        symmetric one in coordinates scaled by ``radius / radius2``, so still a bijection
    """

    kind: ClassVar[str] = "round_edge"
    axis: int
    corner: np.ndarray
    signs: np.ndarray
    radius: float
    style: str
    fade: float
    radius2: float | None = None

    def __call__(self, X: np.ndarray) -> np.ndarray:
        if self.style not in ("fillet", "chamfer"):
            raise ValueError(f"unknown edge style {self.style!r}")
        b, c = _other_axes(self.axis)
        r = self.radius
        k = 1.0 if self.radius2 is None else r / self.radius2  # scale of the second axis
        # quadrant coordinates: 0 at the centre of the rounding, positive toward the outside
        u = self.signs[0] * (X[:, b] - self.corner[0]) + r
        v = self.signs[1] * (X[:, c] - self.corner[1]) * k + r
        ninf = np.maximum(u, v)
        inside = (u > 0) & (v > 0) & (ninf < r * (1.0 + self.fade))
        Y = X.copy()
        if not inside.any():
            return Y
        u, v, ninf = u[inside], v[inside], ninf[inside]
        target = np.hypot(u, v) if self.style == "fillet" else u + v
        f = ninf / target  # <= 1: the ray's scale that maps the square onto the round
        w = 1.0 - _smoothstep((ninf / r - 1.0) / self.fade)
        g = w * (f - 1.0)
        Y[inside, b] += self.signs[0] * u * g
        Y[inside, c] += self.signs[1] * v * g / k
        return Y


@dataclasses.dataclass
class Ramp(ElementaryMap):
    """Scale heights above ``base`` along ``height_axis`` by ``1 - drop * ramp(t)``.

    ``t = direction * (x_dir - start) / length`` with a C1 ramp profile, so the top
    face becomes a planar slope with smooth ends.

    Parameters
    ----------
    height_axis, dir_axis : int, distinct
    base : float, height coordinate that stays fixed
    start, length : float, the ramp runs over ``[start, start + length]`` on dir_axis
    direction : float, +1 (lower toward +dir) or -1 (lower toward -dir)
    drop : float in [0, 1), relative height lost after the ramp
    blend : float in (0, 0.5), fraction of the ramp used by each smooth end
    """

    kind: ClassVar[str] = "ramp"
    height_axis: int
    dir_axis: int
    base: float
    start: float
    length: float
    direction: float
    drop: float
    blend: float

    def __call__(self, X: np.ndarray) -> np.ndarray:
        t = (X[:, self.dir_axis] - self.start) / self.length
        if self.direction < 0:
            t = 1.0 - t
        s = _soft_ramp(t, self.blend)
        Y = X.copy()
        Y[:, self.height_axis] = self.base + (X[:, self.height_axis] - self.base) * (1.0 - self.drop * s)
        return Y


@dataclasses.dataclass
class Taper(ElementaryMap):
    """Scale the two cross-section axes by ``1 + alpha_k * (x_axis - center_axis)``."""

    kind: ClassVar[str] = "taper"
    axis: int
    center: np.ndarray
    alpha: np.ndarray

    def __call__(self, X: np.ndarray) -> np.ndarray:
        b, c = _other_axes(self.axis)
        t = X[:, self.axis] - self.center[self.axis]
        Y = X.copy()
        Y[:, b] = self.center[b] + (X[:, b] - self.center[b]) * (1.0 + self.alpha[0] * t)
        Y[:, c] = self.center[c] + (X[:, c] - self.center[c]) * (1.0 + self.alpha[1] * t)
        return Y


@dataclasses.dataclass
class Shear(ElementaryMap):
    """``x_axis += amount * (x_by - center_by)``: side faces slant by ``atan(amount)``."""

    kind: ClassVar[str] = "shear"
    axis: int
    by: int
    center: np.ndarray
    amount: float

    def __call__(self, X: np.ndarray) -> np.ndarray:
        Y = X.copy()
        Y[:, self.axis] = X[:, self.axis] + self.amount * (X[:, self.by] - self.center[self.by])
        return Y


@dataclasses.dataclass
class SlantEnd(ElementaryMap):
    """Cut one end of the part by a plane tilted ``atan(slope)`` from its end face.

    The end face lies at ``face`` on ``axis`` (``sign`` +1: the high end, -1: the low end).  Past
    ``pivot`` on ``by`` (``side`` +1: above it, -1: below it) each point moves inward along ``axis`` by
    ``slope`` times its distance past the pivot, fully at the face and fading (smoothstep) to nothing
    ``fade`` inside it: the end face becomes a pivot-to-edge slanted face across the whole end, as a
    machined part's slanted end, where :class:`RoundEdge`'s long chamfer only cuts an edge.  Triangular
    Jacobian with ``det = 1 - slope * past * smoothstep' / fade >= 1 - 1.5 * slope * reach / fade``
    (``reach`` the farthest distance past the pivot): a bijection while ``fade > 1.5 * slope * reach``.
    """

    kind: ClassVar[str] = "slant_end"
    axis: int
    by: int
    face: float
    sign: float
    pivot: float
    side: float
    slope: float
    fade: float
    #: ``"smooth"``: the smoothstep fade above; ``"cut"``: a linear fade (``det = 1 - slope * past / fade``,
    #: a bijection while ``fade > slope * reach``) over a slab of the end only a little deeper than the cut,
    #: which :func:`random_deformation` places where no feature is (``cut_ends``): faces normal to ``by`` and
    #: to the third axis stay in their planes and nothing else moves, so the part has exactly a plane cut,
    #: as a saw or mill leaves it, and its holes and steps stay as straight as the polycube's
    profile: str = "smooth"

    def __call__(self, X: np.ndarray) -> np.ndarray:
        u = (self.sign * (X[:, self.axis] - self.face) + self.fade) / self.fade
        w = np.clip(u, 0.0, 1.0) if self.profile == "cut" else _smoothstep(u)
        past = np.maximum(0.0, self.side * (X[:, self.by] - self.pivot))
        Y = X.copy()
        Y[:, self.axis] = X[:, self.axis] - self.sign * self.slope * past * w
        return Y


@dataclasses.dataclass
class Twist(ElementaryMap):
    """Rotate the cross-section about ``axis`` by ``rate * (x_axis - center_axis)`` radians."""

    kind: ClassVar[str] = "twist"
    axis: int
    center: np.ndarray
    rate: float

    def __call__(self, X: np.ndarray) -> np.ndarray:
        b, c = _other_axes(self.axis)
        ang = self.rate * (X[:, self.axis] - self.center[self.axis])
        cs, sn = np.cos(ang), np.sin(ang)
        u, v = X[:, b] - self.center[b], X[:, c] - self.center[c]
        Y = X.copy()
        Y[:, b] = self.center[b] + cs * u - sn * v
        Y[:, c] = self.center[c] + sn * u + cs * v
        return Y


@dataclasses.dataclass
class Bend(ElementaryMap):
    """Barr's bend: the line along ``along`` through ``center`` wraps on a circle of radius
    ``1 / curvature`` that lies on the ``toward`` side; ``det J = 1 - curvature * n``
    where ``n = x_toward - center_toward`` (so ``curvature * n < 1`` is required)."""

    kind: ClassVar[str] = "bend"
    along: int
    toward: int
    center: np.ndarray
    curvature: float

    def __call__(self, X: np.ndarray) -> np.ndarray:
        k = self.curvature
        s = X[:, self.along] - self.center[self.along]
        n = X[:, self.toward] - self.center[self.toward]
        th = k * s
        sinc = np.sinc(th / np.pi)  # sin(th) / th
        half_sinc = np.sinc(th / (2.0 * np.pi))
        sin_over_k = s * sinc  # sin(th) / k
        one_minus_cos_over_k = s * np.sin(0.5 * th) * half_sinc  # (1 - cos th) / k
        Y = X.copy()
        Y[:, self.along] = self.center[self.along] + sin_over_k - n * np.sin(th)
        Y[:, self.toward] = self.center[self.toward] + one_minus_cos_over_k + n * np.cos(th)
        return Y


def _bernstein(t: np.ndarray, degree: int) -> np.ndarray:
    """Bernstein basis ``(N, degree + 1)`` at ``t : (N,)`` clipped to [0, 1]."""
    from math import comb

    t = np.clip(t, 0.0, 1.0)
    s = 1.0 - t
    tp, sp = [np.ones_like(t)], [np.ones_like(t)]
    for _ in range(degree):  # powers by repeated products (float pow is slow)
        tp.append(tp[-1] * t)
        sp.append(sp[-1] * s)
    return np.stack([comb(degree, k) * tp[k] * sp[degree - k] for k in range(degree + 1)], axis=1)


@dataclasses.dataclass
class FFD(ElementaryMap):
    """Free-form lattice: ``x + sum_ijk B_i(s) B_j(t) B_k(u) D_ijk`` over the box [lo, hi]."""

    kind: ClassVar[str] = "ffd"
    lo: np.ndarray
    hi: np.ndarray
    displacements: np.ndarray  # (l+1, m+1, n+1, 3)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        D = np.asarray(self.displacements, dtype=np.float64)
        T = (X - self.lo) / (self.hi - self.lo)
        Bx = _bernstein(T[:, 0], D.shape[0] - 1)
        By = _bernstein(T[:, 1], D.shape[1] - 1)
        Bz = _bernstein(T[:, 2], D.shape[2] - 1)
        l, m, n = D.shape[:3]
        Wxy = (Bx[:, :, None] * By[:, None, :]).reshape(len(X), l * m)
        T = (Wxy @ D.reshape(l * m, n * 3)).reshape(len(X), n, 3)
        return X + np.einsum("nk,nkd->nd", Bz, T)


@dataclasses.dataclass
class DeformationMap:
    """A composition of elementary maps, applied in list order.

    Attributes
    ----------
    maps : list of ElementaryMap
    """

    maps: list[ElementaryMap] = dataclasses.field(default_factory=list)

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Map ``X : (N, 3)`` (or ``(3,)``) to the deformed space."""
        X = np.asarray(X, dtype=np.float64)
        single = X.ndim == 1
        Y = X.reshape(-1, 3)
        for m in self.maps:
            Y = m(Y)
        return Y[0] if single else Y

    @property
    def kinds(self) -> list[str]:
        return [m.kind for m in self.maps]

    def to_dict(self) -> dict:
        return {"maps": [m.to_dict() for m in self.maps]}

    @classmethod
    def from_dict(cls, d: dict) -> "DeformationMap":
        return cls([ElementaryMap.from_dict(m) for m in d["maps"]])


def jacobian_determinants(f: Callable[[np.ndarray], np.ndarray], X: np.ndarray, h: float = FD_STEP) -> np.ndarray:
    """``det J_f`` at ``X : (N, 3)`` by central differences; returns ``(N,)``."""
    X = np.asarray(X, dtype=np.float64)
    n = len(X)
    stacked = np.concatenate([X + h * e for e in np.eye(3)] + [X - h * e for e in np.eye(3)])
    Y = f(stacked)
    J = np.stack([(Y[k * n : (k + 1) * n] - Y[(k + 3) * n : (k + 4) * n]) / (2 * h) for k in range(3)], axis=2)
    return np.linalg.det(J)


def check_invertible(
    f: Callable[[np.ndarray], np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    rng: np.random.Generator,
    *,
    n: int = 4096,
    extra: np.ndarray | None = None,
    min_det: float = MIN_DET,
) -> tuple[bool, float]:
    """Sample ``n`` points uniformly in the box ``[lo, hi]`` (plus ``extra``) and test ``det J > min_det``.

    Parameters
    ----------
    f : callable, ``(N, 3) -> (N, 3)``
    lo, hi : (3,) the bounding box
    rng : np.random.Generator
    n : int, random points in the box
    extra : (K, 3) or None, more points (e.g. the surface vertices)
    min_det : float

    Returns
    -------
    ok : bool
    min_det : float, the smallest determinant found (NaN counts as failure)
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    X = lo + (hi - lo) * rng.random((n, 3))
    if extra is not None:
        X = np.concatenate([X, np.asarray(extra, dtype=np.float64).reshape(-1, 3)])
    det = jacobian_determinants(f, X)
    worst = float(np.min(det)) if np.all(np.isfinite(det)) else float("nan")
    return bool(np.isfinite(worst) and worst > min_det), worst


# --------------------------------------------------------------------------- random maps


def empty_cells(xs, ys, zs, occ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(lo (3,), hi (3,))`` of every empty cell of a polycube grid (``occ (nx, ny, nz)``)."""
    g = [np.asarray(v, dtype=np.float64) for v in (xs, ys, zs)]
    return [(np.array([g[a][c[a]] for a in range(3)]), np.array([g[a][c[a] + 1] for a in range(3)]))
            for c in np.argwhere(~np.asarray(occ, dtype=bool))]


def _draw_tilt(rng: np.random.Generator, lo, hi, ext, by: int, side: float,
               full_ends: float) -> tuple[float, float, float]:
    """``(pivot, reach, slope)`` of a whole-end cut tilted along ``by`` toward ``side``: the pivot at 20-70 % of the
    end's extent on ``by`` (or, a ``full_ends`` share of the time, on the edge it tilts from: across the whole end),
    the distance past it to the end's edge, and the tangent of a 20-45 degree tilt."""
    pivot = float(lo[by] + rng.uniform(0.2, 0.7) * ext[by])
    if full_ends > 0 and rng.random() < full_ends:
        pivot = float(lo[by] if side > 0 else hi[by])
    reach = float(hi[by] - pivot if side > 0 else pivot - lo[by])
    return pivot, reach, float(np.tan(np.radians(rng.uniform(20.0, 45.0))))


def _place_cut(rng: np.random.Generator, lo, hi, ext, axis: int, sign: float,
               full_ends: float, keep_out, tries: int = 24) -> SlantEnd | None:
    """A plane cut of one end (:class:`SlantEnd` ``profile="cut"``) whose slab holds no face normal to ``axis`` of a
    ``keep_out`` box (the one kind of face the cut tilts; faces along it stay in their planes), or None after
    ``tries`` draws of the tilt's axis and side, the pivot, the slope and the slab's depth."""
    face = float(hi[axis] if sign > 0 else lo[axis])
    for _ in range(tries):
        by = int(rng.choice([a for a in range(3) if a != axis]))
        side = float(rng.choice([-1.0, 1.0]))
        pivot, reach, slope = _draw_tilt(rng, lo, hi, ext, by, side, full_ends)
        fade = float(rng.uniform(1.15, 1.5)) * slope * reach
        if fade > 0.6 * ext[axis] or reach <= 0:
            continue
        s_lo, s_hi = (face - fade, face) if sign > 0 else (face, face + fade)  # the slab along ``axis``
        b_lo, b_hi = (pivot, float(hi[by])) if side > 0 else (float(lo[by]), pivot)  # past the pivot on ``by``
        tol = 1e-9

        def sheared(bl, bh) -> bool:  # a face of the box normal to ``axis`` inside the slab, past the pivot
            if not (bh[by] > b_lo + tol and bl[by] < b_hi - tol):
                return False
            return any(s_lo + tol < x < s_hi - tol for x in (bl[axis], bh[axis]))

        if any(sheared(np.asarray(a, float), np.asarray(b, float)) for a, b in keep_out):
            continue
        return SlantEnd(axis, by, face, sign, pivot, side, slope, fade, profile="cut")
    return None


def breakout_cut(rng: np.random.Generator, lo, hi, box_lo, box_hi, axis: int) -> SlantEnd | None:
    """The plane cut (:class:`SlantEnd` ``profile="cut"``) of the end a ``breakout`` feature
    (:meth:`polycubenet.synth.polycube._Builder.breakout`: box ``box_lo``-``box_hi``, opening into the end on
    ``axis``) opens a hole into, tilted across the open layers so that the hole breaks out through the slanted
    face: the pivot between the open layers' top and the far face (a whole-end cut at the far face), a 20-45
    degree tilt, the slab 1.15-1.5 times the cut's depth and within 60 % of the length (a gentler slope if
    need be; None under 15 degrees)."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    box_lo, box_hi = np.asarray(box_lo, dtype=np.float64), np.asarray(box_hi, dtype=np.float64)
    ext = hi - lo
    tol = 1e-9
    # the hole's axis: besides the end's, the one the box reaches the bounding box on
    by = next(a for a in range(3) if a != axis and (box_lo[a] <= lo[a] + tol or box_hi[a] >= hi[a] - tol))
    sign = -1.0 if box_lo[axis] <= lo[axis] + tol else 1.0
    side = -1.0 if box_lo[by] <= lo[by] + tol else 1.0  # the open layers: below (-1) or above the pivot
    level = float(box_hi[by] if side < 0 else box_lo[by])
    far = float(hi[by] if side < 0 else lo[by])
    pivot = level + rng.uniform(0.0, 1.0) * (far - level)
    reach = float(pivot - lo[by] if side < 0 else hi[by] - pivot)
    slope = float(np.tan(np.radians(rng.uniform(20.0, 45.0))))
    k = float(rng.uniform(1.15, 1.5))
    slope = min(slope, 0.6 * ext[axis] / (k * reach))
    if reach <= 0 or slope < np.tan(np.radians(15.0)):
        return None
    return SlantEnd(axis, by, float(hi[axis] if sign > 0 else lo[axis]), sign, pivot, side, slope, k * slope * reach,
                    profile="cut")


#: how far past a gusset's free edge its cut fades out, in units of the cut's legs (:func:`gusset_cut`)
GUSSET_FADE = 0.2


def gusset_cut(rng: np.random.Generator, xs, ys, zs, occ, box_lo, box_hi, axis: int, signs) -> RoundEdge | None:
    """The cut that makes a ``gusset`` rib (:meth:`polycubenet.synth.polycube._Builder.gusset`: box
    ``box_lo``-``box_hi``, one layer thick along ``axis``, free edge outward along ``signs``) the triangle of a
    bracket's rib: a chamfer of its free edge (:class:`RoundEdge`) whose legs are 70-95 % of the rib's extents on
    the two other axes, so that only a narrow strip of the rib's top and outer faces is left.  None where the
    map's region (the legs inside the edge, :data:`GUSSET_FADE` of them outside, along every layer of ``axis``)
    holds solid other than the rib: the chamfer acts along the whole line and would cut that too."""
    b, c = _other_axes(axis)
    s = np.asarray(signs, dtype=np.float64)
    box_lo, box_hi = np.asarray(box_lo, dtype=np.float64), np.asarray(box_hi, dtype=np.float64)
    corner = np.array([box_hi[b] if s[0] > 0 else box_lo[b], box_hi[c] if s[1] > 0 else box_lo[c]])
    r_b = float(rng.uniform(0.7, 0.95) * (box_hi[b] - box_lo[b]))
    r_c = float(rng.uniform(0.7, 0.95) * (box_hi[c] - box_lo[c]))
    region = []
    for k, r in ((0, r_b), (1, r_c)):
        ends = sorted((corner[k] - s[k] * r, corner[k] + s[k] * r * GUSSET_FADE))
        region.append(ends)
    g = [np.asarray(v, dtype=np.float64) for v in (xs, ys, zs)]
    tol = 1e-9
    for cell in np.argwhere(np.asarray(occ, dtype=bool)):
        lo = np.array([g[a][cell[a]] for a in range(3)])
        hi = np.array([g[a][cell[a] + 1] for a in range(3)])
        if all(hi[ax] > r0 + tol and lo[ax] < r1 - tol for ax, (r0, r1) in zip((b, c), region)):
            if not (np.all(lo >= box_lo - tol) and np.all(hi <= box_hi + tol)):
                return None
    return RoundEdge(int(axis), corner, s.copy(), r_b, "chamfer", GUSSET_FADE, r_c)


def random_deformation(
    rng: np.random.Generator,
    lo: np.ndarray,
    hi: np.ndarray,
    holes: list[tuple[int, np.ndarray, np.ndarray]] = (),
    edges: list[dict] = (),
    *,
    strength: float | None = None,
    slanted_ends: bool = False,
    whole_ends: bool = False,
    max_strength: float | None = None,
    full_ends: float = 0.0,
    cut_ends: bool = False,
    keep_out: list[tuple[np.ndarray, np.ndarray]] = (),
) -> DeformationMap:
    """A random composition: roundings (holes, edges), then ramp / taper / shear / twist / bend / FFD.

    Parameters
    ----------
    rng : np.random.Generator
    lo, hi : (3,) bounding box of the polycube
    holes : list of ``(axis, lo (3,), hi (3,))`` boxes of holes and pockets that may be
        rounded into cylinders
    edges : list of dict, convex edges that may be filleted or chamfered
        (:func:`~polycubenet.synth.polycube.convex_edges`)
    strength : float in [0, 1] or None, overall intensity of the global maps
        (random if None; 0 keeps only roundings)
    slanted_ends : bool, also cut (probability 0.5) one convex edge by a long chamfer at
        20-45 degrees to one of its faces, up to most of its cells' widths: the slanted end
        or large bevel a machined part has.  Off, the random stream is the one before
        this option existed.
    whole_ends : bool, also (probability 0.5) cut a whole end of the bounding box (mostly of its
        longest axis) by a plane at 20-45 degrees (:class:`SlantEnd`: pivot at 20-70 % of the
        height, the fade within 80 % of the length, else a gentler slope, none under 15 degrees).
        Off, the random stream is the one before this option existed.
    max_strength : float or None, a cap on the random ``strength`` (0.35: the mild global maps of
        machined parts, no bends or twists at full strength); the random stream does not change.
    full_ends : float in [0, 1], the share of ``whole_ends`` cuts whose plane runs across the whole end
        (the pivot on the end's edge: no flat strip of the end face is left, as when a saw cuts a part's
        end off at an angle; the polycube's end face stays at the cut's outermost edge).  0: the random
        stream is the one before this option existed.
    cut_ends : bool, with ``whole_ends``: the cut as a plane cut (:class:`SlantEnd` ``profile="cut"``): a linear
        fade over 1.15-1.5 times the cut's depth instead of the smooth one over twice it, placed only where
        its slab holds no face of a ``keep_out`` box normal to the cut's axis (up to 24 draws, else no cut).
        The smooth fade shears every hole wall and step within twice the cut's depth, which a machined part's
        plane cut does not:
        a model trained on it tilts a real part's straight walls near a slanted end (up to 10-22 degrees on
        never-seen machined parts, where parts without a slanted end keep them within 0.6 degrees).
    keep_out : list of ``(lo (3,), hi (3,))`` boxes whose faces a cut may not tilt: the polycube's empty cells within
        its bounding box (holes, pockets, steps, the room around bosses), :func:`empty_cells`

    Returns
    -------
    DeformationMap
    """
    if not 0.0 <= full_ends <= 1.0:
        raise ValueError(f"full_ends must be in [0, 1]; got {full_ends}")
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    ext = hi - lo
    center = 0.5 * (lo + hi)
    if strength is None:
        strength = float(rng.choice([0.0, 0.35, 0.7, 1.0], p=[0.1, 0.3, 0.35, 0.25]))
        if max_strength is not None:
            strength = min(strength, float(max_strength))
    maps: list[ElementaryMap] = []

    # holes -> cylinders
    round_all = rng.random() < 0.8
    for axis, hlo, hhi in holes:
        if not round_all or rng.random() < 0.15:
            continue
        b, c = _other_axes(axis)
        hc = 0.5 * (np.asarray(hlo) + np.asarray(hhi))
        half = 0.5 * np.array([hhi[b] - hlo[b], hhi[c] - hlo[c]])
        if np.any(half <= 0):
            continue
        # room to the outside of the bounding box, in units of the half sizes
        room = min((hc[b] - half[0] - lo[b]) / half[0], (hi[b] - hc[b] - half[0]) / half[0],
                   (hc[c] - half[1] - lo[c]) / half[1], (hi[c] - hc[c] - half[1]) / half[1])
        fade = float(np.clip(rng.uniform(0.6, 1.0) * room, 0.25, 1.5))
        maps.append(RoundHole(axis, hc.copy(), half, float(rng.choice([4.0, 8.0, 16.0, 64.0], p=[0.2, 0.35, 0.3, 0.15])),
                              float(rng.uniform(0.7, 1.0)), fade))

    # convex edges (bounding box, steps, profiles) -> fillets / chamfers
    p_edge = float(rng.choice([0.0, 0.3, 0.7, 1.0], p=[0.2, 0.3, 0.3, 0.2]))
    chamfer_p = float(rng.choice([0.0, 0.3, 1.0], p=[0.5, 0.35, 0.15]))
    r_scale = rng.uniform(0.4, 1.0)
    for e in edges:
        if rng.random() >= p_edge:
            continue
        fade = 0.5
        r = float(min(0.9 * e["room"] / (1.0 + fade), r_scale * rng.uniform(0.02, 0.12)))
        if r < 0.004:
            continue
        style = "chamfer" if rng.random() < chamfer_p else "fillet"
        maps.append(RoundEdge(int(e["axis"]), np.asarray(e["corner"], dtype=np.float64).copy(),
                              np.asarray(e["signs"], dtype=np.float64).copy(), r, style, fade))

    if slanted_ends and edges and rng.random() < 0.5:
        e = edges[int(rng.integers(len(edges)))]
        room_b, room_c = e.get("rooms", (e["room"], e["room"]))
        fade = 0.3
        slope = np.tan(np.radians(rng.uniform(20.0, 45.0)))
        long_b = rng.random() < 0.5
        r_long = rng.uniform(0.4, 0.85) * (room_b if long_b else room_c) / (1.0 + fade)
        r_short = min(slope * r_long, 0.85 * (room_c if long_b else room_b) / (1.0 + fade))
        r_b, r_c = (r_long, r_short) if long_b else (r_short, r_long)
        if min(r_b, r_c) >= 0.004:
            maps.append(RoundEdge(int(e["axis"]), np.asarray(e["corner"], dtype=np.float64).copy(),
                                  np.asarray(e["signs"], dtype=np.float64).copy(), float(r_b), "chamfer", fade,
                                  float(r_c)))

    if whole_ends and rng.random() < 0.5:
        axis = int(np.argmax(ext)) if rng.random() < 0.7 else int(rng.integers(3))  # mostly an end of the length
        by = int(rng.choice([a for a in range(3) if a != axis]))
        sign, side = float(rng.choice([-1.0, 1.0])), float(rng.choice([-1.0, 1.0]))
        pivot, reach, slope = _draw_tilt(rng, lo, hi, ext, by, side, full_ends)
        slope = min(slope, 0.8 * ext[axis] / (2.0 * reach))  # the fade (2 slope reach) within 80 % of the length
        if cut_ends:
            cut = _place_cut(rng, lo, hi, ext, axis, sign, full_ends, keep_out)
            if cut is not None:
                maps.append(cut)
        elif slope >= np.tan(np.radians(15.0)):
            maps.append(SlantEnd(axis, by, float(hi[axis] if sign > 0 else lo[axis]), sign, pivot, side, slope,
                                 2.0 * slope * reach))

    if strength > 0:
        s = strength
        if rng.random() < 0.3 * s + 0.1:  # ramp
            h_ax = int(rng.integers(3))
            d_ax = int(rng.choice([a for a in range(3) if a != h_ax]))
            length = float(rng.uniform(0.3, 0.8) * ext[d_ax])
            start = float(lo[d_ax] + rng.uniform(0.0, ext[d_ax] - length))
            blend = float(rng.uniform(0.1, 0.3))
            angle = np.radians(rng.uniform(10.0, 35.0))
            drop = float(min(0.6, np.tan(angle) * length * (1 - blend) / max(ext[h_ax], 1e-9)))
            maps.append(Ramp(h_ax, d_ax, float(lo[h_ax]), start, length, float(rng.choice([-1.0, 1.0])), drop, blend))
        if rng.random() < 0.35 * s:  # taper
            axis = int(rng.integers(3))
            half_len = 0.5 * ext[axis]
            alpha = rng.uniform(-0.5, 0.5, size=2) / max(half_len, 1e-9) * 0.6 * s
            maps.append(Taper(axis, center.copy(), alpha))
        if rng.random() < 0.35 * s:  # shear
            axis = int(rng.integers(3))
            by = int(rng.choice([a for a in range(3) if a != axis]))
            maps.append(Shear(axis, by, center.copy(), float(np.tan(np.radians(rng.uniform(-20, 20) * s)))))
        if rng.random() < 0.3 * s:  # twist about the longest axis
            axis = int(np.argmax(ext))
            total = np.radians(rng.uniform(-30.0, 30.0) * s)
            maps.append(Twist(axis, center.copy(), float(total / max(ext[axis], 1e-9))))
        if rng.random() < 0.4 * s:  # bend the longest axis
            along = int(np.argmax(ext))
            toward = int(rng.choice([a for a in range(3) if a != along]))
            total = np.radians(rng.uniform(15.0, 70.0) * s) * rng.choice([-1.0, 1.0])
            k = total / max(ext[along], 1e-9)
            k = float(np.clip(k, -0.6 / (0.5 * ext[toward]), 0.6 / (0.5 * ext[toward])))
            maps.append(Bend(along, toward, center.copy(), k))
        if rng.random() < 0.3 + 0.4 * s:  # free-form lattice
            deg = rng.integers(2, 4, size=3)
            pad = 0.05 * np.max(ext)
            amp = rng.uniform(0.005, 0.03) * s
            D = rng.normal(0.0, amp, size=(deg[0] + 1, deg[1] + 1, deg[2] + 1, 3))
            for a in range(3):  # limit stretch/compression across each axis (thin plates stay intact)
                mean = D[..., a].mean(axis=a, keepdims=True)
                lam = min(1.0, 0.15 * ext[a] / (amp * deg[a] + 1e-12))
                D[..., a] = mean + lam * (D[..., a] - mean)
            maps.append(FFD(lo - pad, hi + pad, D))
    return DeformationMap(maps)
