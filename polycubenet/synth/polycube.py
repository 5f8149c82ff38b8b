"""Random polycubes for the synthetic data, built the way a machinist would.

:func:`random_polycube` starts from a stock block (or an extruded L/T/U/I profile, a
plate, a bar, a frame) on an integer lattice, then cuts or adds features as lattice
boxes -- through-holes (also crossing each other), blind pockets, slots, notches and
steps, bosses and arches (handles).  Lattice intervals get random physical widths,
never thinner than ``min_width`` of the diagonal (a face thinner than about two point
spacings of the training clouds cannot be told from noise).  Each feature is kept
only if the solid stays a valid polycube (:func:`polycubenet.polycube.check_occupancy`).
The general polycube operations (validity, genus, surface, minimal grid) live in
:mod:`polycubenet.polycube`; they are re-exported here for convenience.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..polycube import (  # noqa: F401  (re-exported)
    check_occupancy,
    compress,
    convex_edges,
    edge_contacts,
    euler_characteristic,
    nonmanifold_vertices,
    polycube_quads,
    polycube_surface,
    refine_grid,
    solid_genus,
    surface_genus,
    transform_grid,
    triangulate_quads,
    validate_occupancy,
)


# --------------------------------------------------------------------------- generator


@dataclasses.dataclass
class Feature:
    """One generator step, kept for the deformation (rounding holes) and for the record.

    Attributes
    ----------
    kind : str, ``through_hole``, ``pocket``, ``slot``, ``notch``, ``step``, ``boss``, ``arch``, ``breakout``,
        ``gusset``
    axis : int, the feature's axis (hole direction, boss normal, ...; a breakout's: the end it opens into; a
        gusset's: the line of the corner it fills, across which it is one layer thick)
    lo, hi : (3,) float64, the feature's box in the polycube's (normalized) coordinates
    signs : (2,) +1 / -1 or None, a gusset's: the outward directions of its free edge on the two other axes
        (cyclic order, as :class:`~polycubenet.synth.deform.RoundEdge`'s); None for the other kinds
    """

    kind: str
    axis: int
    lo: np.ndarray
    hi: np.ndarray
    signs: tuple[float, float] | None = None

    def to_dict(self) -> dict:
        d = {"kind": self.kind, "axis": int(self.axis), "lo": [float(v) for v in self.lo], "hi": [float(v) for v in self.hi]}
        if self.signs is not None:
            d["signs"] = [float(v) for v in self.signs]
        return d


@dataclasses.dataclass
class RandomPolycube:
    """A generated polycube with its provenance.

    Attributes
    ----------
    xs, ys, zs : (nx+1,), (ny+1,), (nz+1,) float64, minimal grid (no two adjacent
        slabs alike), bounding box centred at 0 with diagonal 1
    occupancy : (nx, ny, nz) bool, valid (:func:`check_occupancy`)
    genus : int, from :func:`solid_genus`
    style : str, the stock the part started from
    features : list of Feature, the features that were kept (holes still open)
    """

    xs: np.ndarray
    ys: np.ndarray
    zs: np.ndarray
    occupancy: np.ndarray
    genus: int
    style: str
    features: list[Feature]

    @property
    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.xs, self.ys, self.zs

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` of the bounding box, each ``(3,)``."""
        return (np.array([self.xs[0], self.ys[0], self.zs[0]]), np.array([self.xs[-1], self.ys[-1], self.zs[-1]]))


_STYLES = ("block", "plate", "bar", "extrusion", "frame")
_STYLE_P = (0.30, 0.25, 0.12, 0.18, 0.15)
_MARGIN = 2  # empty lattice layers around the stock, room for bosses and arches


class _Builder:
    """Lattice occupancy with transactional feature edits (kept only when valid)."""

    def __init__(self, rng: np.random.Generator, dims: np.ndarray):
        self.rng = rng
        self.n = np.asarray(dims, dtype=np.int64)
        self.M = _MARGIN
        self.occ = np.zeros(tuple(self.n + 2 * self.M), dtype=bool)
        self.stock_lo = np.full(3, self.M)
        self.stock_hi = self.M + self.n
        self.occ[tuple(slice(l, h) for l, h in zip(self.stock_lo, self.stock_hi))] = True
        self.features: list[tuple[str, int, np.ndarray, np.ndarray]] = []
        self.signs: dict[int, tuple[float, float]] = {}  # feature index -> a gusset's free-edge directions
        self.ribs = np.zeros_like(self.occ)  # the cells of the gussets: no rib rests on another

    def box(self, lo, hi) -> tuple[slice, slice, slice]:
        return tuple(slice(int(l), int(h)) for l, h in zip(lo, hi))

    def try_edit(self, kind: str, axis: int, lo, hi, value: bool, require_change: bool = True) -> bool:
        lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
        if np.any(lo < 0) or np.any(hi > self.occ.shape) or np.any(hi <= lo):
            return False
        sl = self.box(lo, hi)
        old = self.occ[sl].copy()
        if require_change and np.all(old == value):
            return False
        self.occ[sl] = value
        if check_occupancy(self.occ) is not None:
            self.occ[sl] = old
            return False
        self.features.append((kind, axis, lo, hi))
        return True

    # ----------------------------------------------------------- proposals
    def _rect(self, axis: int, max_frac: float = 0.45, wall: int = 1):
        """A rectangle in the two axes other than ``axis``, inside the stock with ``wall`` cells left."""
        lo, hi = self.stock_lo.copy(), self.stock_hi.copy()
        for a in range(3):
            if a == axis:
                continue
            span = self.n[a] - 2 * wall
            if span < 1:
                return None
            size = int(self.rng.integers(1, max(1, int(span * max_frac)) + 1))
            start = int(self.rng.integers(0, span - size + 1))
            lo[a] = self.stock_lo[a] + wall + start
            hi[a] = lo[a] + size
        return lo, hi

    def through_hole(self, axis: int) -> bool:
        r = self._rect(axis)
        if r is None:
            return False
        lo, hi = r
        lo[axis], hi[axis] = 0, self.occ.shape[axis]
        return self.try_edit("through_hole", axis, lo, hi, False)

    def pocket(self, axis: int) -> bool:
        r = self._rect(axis)
        if r is None or self.n[axis] < 2:
            return False
        lo, hi = r
        depth = int(self.rng.integers(1, self.n[axis]))
        if self.rng.random() < 0.5:
            lo[axis], hi[axis] = self.stock_hi[axis] - depth, self.occ.shape[axis]
        else:
            lo[axis], hi[axis] = 0, self.stock_lo[axis] + depth
        return self.try_edit("pocket", axis, lo, hi, False)

    def slot(self, axis: int) -> bool:
        """A channel through ``axis``, open on one side of a second axis."""
        others = [a for a in range(3) if a != axis]
        side_axis, width_axis = (others if self.rng.random() < 0.5 else others[::-1])
        if self.n[width_axis] < 3 or self.n[side_axis] < 2:
            return False
        lo, hi = np.zeros(3, dtype=np.int64), np.array(self.occ.shape, dtype=np.int64)
        w = int(self.rng.integers(1, max(1, self.n[width_axis] // 3) + 1))
        s = int(self.rng.integers(1, self.n[width_axis] - w))
        lo[width_axis] = self.stock_lo[width_axis] + s
        hi[width_axis] = lo[width_axis] + w
        depth = int(self.rng.integers(1, self.n[side_axis]))
        if self.rng.random() < 0.5:
            lo[side_axis] = self.stock_hi[side_axis] - depth
        else:
            hi[side_axis] = self.stock_lo[side_axis] + depth
        return self.try_edit("slot", axis, lo, hi, False)

    def notch(self, axis: int, through: bool) -> bool:
        """Remove a corner box (``through``: along the whole ``axis``, a step; else a corner cut)."""
        lo, hi = np.zeros(3, dtype=np.int64), np.array(self.occ.shape, dtype=np.int64)
        axes = [a for a in range(3) if a != axis] + ([] if through else [axis])
        for a in axes:
            if self.n[a] < 2:
                return False
            d = int(self.rng.integers(1, max(1, (self.n[a] * 2) // 3) + 1))
            if self.rng.random() < 0.5:
                lo[a] = self.stock_hi[a] - d
            else:
                hi[a] = self.stock_lo[a] + d
        return self.try_edit("step" if through else "notch", axis, lo, hi, False)

    def boss(self, axis: int) -> bool:
        r = self._rect(axis, max_frac=0.6, wall=0)
        if r is None:
            return False
        lo, hi = r
        height = int(self.rng.integers(1, self.M + 1))
        if self.rng.random() < 0.5:
            lo[axis], hi[axis] = self.stock_hi[axis], self.stock_hi[axis] + height
        else:
            lo[axis], hi[axis] = self.stock_lo[axis] - height, self.stock_lo[axis]
        return self.try_edit("boss", axis, lo, hi, True)

    def arch(self, axis: int) -> bool:
        """A handle on a face: two posts one layer high and a beam over them (genus + 1)."""
        others = [a for a in range(3) if a != axis]
        along, across = (others if self.rng.random() < 0.5 else others[::-1])
        if self.n[along] < 3:
            return False
        top = self.rng.random() < 0.5
        lvl0 = self.stock_hi[axis] if top else self.stock_lo[axis] - 1
        lvl1 = lvl0 + 1 if top else lvl0 - 1
        a0 = int(self.rng.integers(0, self.n[along] - 2))
        a1 = int(self.rng.integers(a0 + 2, self.n[along]))
        w = int(self.rng.integers(1, max(1, self.n[across] // 3) + 1))
        c0 = int(self.rng.integers(0, self.n[across] - w + 1))
        saved = self.occ.copy()
        for pos in (a0, a1):
            self.occ[self._cell_box(axis, along, across, lvl0, pos, pos + 1, c0, c0 + w)] = True
        self.occ[self._cell_box(axis, along, across, lvl1, a0, a1 + 1, c0, c0 + w)] = True
        if check_occupancy(self.occ) is not None:
            self.occ = saved
            return False
        lo = np.zeros(3, dtype=np.int64)
        hi = np.zeros(3, dtype=np.int64)
        lo[axis], hi[axis] = min(lvl0, lvl1), max(lvl0, lvl1) + 1
        lo[along], hi[along] = self.stock_lo[along] + a0, self.stock_lo[along] + a1 + 1
        lo[across], hi[across] = self.stock_lo[across] + c0, self.stock_lo[across] + c0 + w
        self.features.append(("arch", axis, lo, hi))
        return True

    def breakout(self) -> bool:
        """Open one through-hole into the nearer end of the stock beside it, over some of its layers: the box
        between the hole and that end, the hole's width, 1 to all but one of the layers along the hole from
        one face.  The layers left keep the hole closed (its handle stays), so with a slanted cut of that end
        across the open layers (:func:`polycubenet.synth.pairs.make_pair`) the hole breaks out through the
        slanted face, as a drilled hole near a machined part's slanted end does."""
        holes = [(axis, lo, hi) for kind, axis, lo, hi in self.features if kind == "through_hole"]
        if not holes:
            return False
        axis, lo, hi = holes[int(self.rng.integers(len(holes)))]
        if self.n[axis] < 2:
            return False
        walls = []  # (cells to the stock's end, end axis, low end?)
        for e in range(3):
            if e != axis:
                walls += [(int(lo[e] - self.stock_lo[e]), e, True), (int(self.stock_hi[e] - hi[e]), e, False)]
        walls = [w for w in walls if w[0] >= 1]
        if not walls:
            return False
        near = min(w[0] for w in walls)
        _, e, low = [w for w in walls if w[0] == near][int(self.rng.integers(sum(w[0] == near for w in walls)))]
        blo, bhi = np.asarray(lo).copy(), np.asarray(hi).copy()
        blo[e], bhi[e] = (0, lo[e]) if low else (hi[e], self.occ.shape[e])
        depth = int(self.rng.integers(1, self.n[axis]))
        if self.rng.random() < 0.5:
            blo[axis], bhi[axis] = 0, self.stock_lo[axis] + depth
        else:
            blo[axis], bhi[axis] = self.stock_hi[axis] - depth, self.occ.shape[axis]
        return self.try_edit("breakout", e, blo, bhi, False)

    def gusset(self) -> bool:
        """A rib in a concave corner (a gusset): one layer thick along the corner's line, 1-3 cells out along
        each of the two faces that meet there, every cell of its two inner sides resting on the solid, nothing in
        the layers beside it or one cell past its free faces.  Its
        free edge is cut across most of the rib by :func:`polycubenet.synth.pairs.make_pair` (``gussets``), into
        the triangle of a bracket's rib, which the other features never make."""
        occ = self.occ
        empty, solid = ~occ, occ & ~self.ribs
        cands = []
        for a in range(3):
            b, c = (a + 1) % 3, (a + 2) % 3
            for sb in (1, -1):
                for sc in (1, -1):
                    behind_b, behind_c = _behind(solid, b, sb), _behind(solid, c, sc)
                    corner = empty & behind_b & behind_c & _behind(behind_b, c, sc)
                    cands += [(a, sb, sc, tuple(int(v) for v in e)) for e in np.argwhere(corner)]
        if not cands:
            return False
        a, sb, sc, e = cands[int(self.rng.integers(len(cands)))]
        b, c = (a + 1) % 3, (a + 2) % 3

        def reach(along: int, s: int, rest: int, s_rest: int) -> int:
            """Cells from ``e`` along ``s * along`` that are empty and rest on the solid behind on ``rest``."""
            k, cell = 0, list(e)
            while k < 3:
                if not (0 <= cell[along] < occ.shape[along]) or occ[tuple(cell)]:
                    break
                below = list(cell)
                below[rest] -= s_rest
                if not solid[tuple(below)]:
                    break
                k += 1
                cell[along] += s
            return k

        kb, kc = reach(b, sb, c, sc), reach(c, sc, b, sb)
        if kb < 1 or kc < 1:  # pragma: no cover - the corner cell itself always qualifies
            return False
        kb, kc = int(self.rng.integers(1, kb + 1)), int(self.rng.integers(1, kc + 1))
        lo, hi = np.array(e, dtype=np.int64), np.array(e, dtype=np.int64) + 1
        for ax, s, k in ((b, sb, kb), (c, sc, kc)):
            if s > 0:
                hi[ax] = e[ax] + k
            else:
                lo[ax] = e[ax] - k + 1
        # room around it: nothing in the layers beside it along ``a`` or one cell past its free faces (a rib
        # stands alone in an open corner, not against another rib or inside a pocket)
        room_lo, room_hi = lo.copy(), hi.copy()
        room_lo[a], room_hi[a] = lo[a] - 1, hi[a] + 1
        for ax, s in ((b, sb), (c, sc)):
            if s > 0:
                room_hi[ax] += 1
            else:
                room_lo[ax] -= 1
        room_lo, room_hi = np.maximum(room_lo, 0), np.minimum(room_hi, occ.shape)
        if occ[self.box(room_lo, room_hi)].any():
            return False
        if not self.try_edit("gusset", a, lo, hi, True):
            return False
        self.signs[len(self.features) - 1] = (float(sb), float(sc))
        self.ribs[self.box(lo, hi)] = True
        return True

    def _cell_box(self, axis, along, across, lvl, a0, a1, c0, c1):
        sl = [slice(None)] * 3
        sl[axis] = slice(lvl, lvl + 1)
        sl[along] = slice(self.stock_lo[along] + a0, self.stock_lo[along] + a1)
        sl[across] = slice(self.stock_lo[across] + c0, self.stock_lo[across] + c1)
        return tuple(sl)


def _behind(occ: np.ndarray, axis: int, s: int) -> np.ndarray:
    """``out[e] = occ[e - s * unit(axis)]`` (False where that cell is outside the lattice)."""
    out = np.zeros_like(occ)
    src = np.moveaxis(occ, axis, 0)
    dst = np.moveaxis(out, axis, 0)
    if s > 0:
        dst[1:] = src[:-1]
    else:
        dst[:-1] = src[1:]
    return out


def _widths(rng: np.random.Generator, n: int, thin_p: float) -> np.ndarray:
    w = rng.uniform(0.5, 1.6, size=n)
    thin = rng.random(n) < thin_p
    w[thin] = rng.uniform(0.15, 0.35, size=int(thin.sum()))
    return w


#: thinnest grid interval, relative to the bounding-box diagonal (see the module docstring)
MIN_WIDTH = 0.025


def _enforce_min_width(coords: list[np.ndarray], min_width: float) -> list[np.ndarray]:
    """Widen intervals thinner than ``min_width`` times the (growing) diagonal until none is."""
    for _ in range(20):
        diag = float(np.linalg.norm([c[-1] - c[0] for c in coords]))
        floor = min_width * diag
        widths = [np.diff(c) for c in coords]
        if all(w.min() >= floor * (1 - 1e-9) for w in widths):
            break
        coords = [np.concatenate([[c[0]], c[0] + np.cumsum(np.maximum(w, floor * 1.001))]) for c, w in zip(coords, widths)]
    return coords


def random_polycube(
    rng: np.random.Generator,
    *,
    style: str | None = None,
    n_holes: int | None = None,
    max_tries: int = 50,
    min_width: float = MIN_WIDTH,
    tall_bosses: bool = False,
    min_holes: int = 0,
    breakouts: float = 0.0,
    gussets: float = 0.0,
) -> RandomPolycube:
    """A random valid polycube, machined-part style.

    Parameters
    ----------
    rng : np.random.Generator, the only source of randomness
    style : str or None, one of ``block, plate, bar, extrusion, frame`` (random if None)
    n_holes : int or None, number of through-holes to *attempt* (random if None);
        the genus is measured afterwards, not assumed
    max_tries : int, whole-part retries if the stock ends up degenerate
    min_width : float, thinnest interval relative to the bounding-box diagonal
    tall_bosses : bool, more bosses (at least one other feature, bosses twice as likely) and taller ones:
        each end's margin layers 0.6-3 stock widths instead of 0.6 (posts and bosses up to about the
        stock's height, as machined parts have).  Off, the random stream is the one before this option.
    min_holes : int, with ``n_holes`` None: attempt at least this many through-holes (the random count raised
        to it), for parts of genus 2 and more, as drilled machined parts are.  0: the random stream is the one
        before this option.
    breakouts : float in [0, 1], the share of parts with a through-hole that open one of them into the stock's
        nearer end over some of its layers (a feature ``breakout``, :meth:`_Builder.breakout`), for a slanted
        cut the hole breaks out through.  0: the random stream is the one before this option.
    gussets : float in [0, 1], the share of parts that, after their other features, get one or two ribs in
        concave corners where they have one (a feature ``gusset``, :meth:`_Builder.gusset`), for a cut across
        the rib's free edge into a bracket's triangular rib.  0: the random stream is the one before this option.

    Returns
    -------
    RandomPolycube, normalized (bounding box centred at 0, diagonal 1)
    """
    for _ in range(max_tries):
        pc = _random_polycube_once(rng, style, n_holes, min_width, tall_bosses, min_holes, breakouts, gussets)
        if pc is not None:
            return pc
    raise RuntimeError("random_polycube: no valid polycube")  # pragma: no cover - never seen


def _random_polycube_once(
    rng: np.random.Generator, style: str | None, n_holes: int | None, min_width: float, tall_bosses: bool = False,
    min_holes: int = 0, breakouts: float = 0.0, gussets: float = 0.0,
) -> RandomPolycube | None:
    if style is None:
        style = str(rng.choice(_STYLES, p=_STYLE_P))
    if style not in _STYLES:
        raise ValueError(f"unknown style {style!r}; expected one of {_STYLES}")
    if style == "block":
        dims = rng.integers(4, 11, size=3)
        hole_p = (0.30, 0.25, 0.18, 0.12, 0.08, 0.07)
    elif style == "plate":
        dims = np.array([rng.integers(7, 15), rng.integers(6, 13), rng.integers(1, 4)])
        hole_p = (0.06, 0.10, 0.12, 0.12, 0.12, 0.12, 0.12, 0.12, 0.12)
    elif style == "bar":
        dims = np.array([rng.integers(10, 17), rng.integers(3, 6), rng.integers(3, 6)])
        hole_p = (0.25, 0.25, 0.2, 0.15, 0.15)
    elif style == "extrusion":
        dims = np.array([rng.integers(6, 12), rng.integers(6, 12), rng.integers(3, 10)])
        hole_p = (0.35, 0.3, 0.2, 0.15)
    else:  # frame
        dims = rng.integers(5, 10, size=3)
        hole_p = (0.0, 0.0, 0.1, 0.2, 0.25, 0.25, 0.2)
    dims = dims[rng.permutation(3)]
    b = _Builder(rng, dims)

    if style == "extrusion":  # L / T / U / I profile: remove 1-3 boxes through the extrusion axis
        ax = int(np.argmin(dims)) if rng.random() < 0.5 else int(rng.integers(3))
        for _ in range(int(rng.integers(1, 4))):
            for _try in range(4):
                if rng.random() < 0.5:
                    ok = b.notch(ax, through=True)
                else:
                    ok = b.slot(ax)
                if ok:
                    break

    if n_holes is None:
        n_holes = max(int(rng.choice(len(hole_p), p=np.asarray(hole_p) / np.sum(hole_p))), int(min_holes))
    thin_axis = int(np.argmin(dims))
    for _ in range(n_holes):
        for _try in range(6):
            if style == "plate":
                axis = thin_axis if rng.random() < 0.85 else int(rng.integers(3))
            else:
                axis = int(rng.integers(3))
            if b.through_hole(axis):
                break
    if breakouts > 0 and rng.random() < breakouts:
        for _try in range(4):
            if b.breakout():
                break

    n_other = int(rng.integers(1 if tall_bosses else 0, 5))
    kinds = ("pocket", "slot", "notch", "step", "boss", "arch")
    kind_p = np.array([0.22, 0.15, 0.15, 0.18, 0.2, 0.1])
    if tall_bosses:  # bosses twice as likely (off: the very same probabilities as before the option)
        kind_p[4] = 0.4
        kind_p = kind_p / kind_p.sum()
    for _ in range(n_other):
        kind = str(rng.choice(kinds, p=kind_p))
        axis = int(rng.integers(3))
        for _try in range(4):
            ok = {
                "pocket": lambda: b.pocket(axis),
                "slot": lambda: b.slot(axis),
                "notch": lambda: b.notch(axis, through=False),
                "step": lambda: b.notch(axis, through=True),
                "boss": lambda: b.boss(axis),
                "arch": lambda: b.arch(axis),
            }[kind]()
            if ok:
                break
    if gussets > 0 and rng.random() < gussets:
        for _ in range(int(rng.integers(1, 3))):
            for _try in range(4):
                if b.gusset():
                    break

    occ = b.occ
    if check_occupancy(occ) is not None:  # pragma: no cover - every edit is validated
        return None
    thin_p = 0.15 if style != "plate" else 0.05
    coords = [np.concatenate([[0.0], np.cumsum(_widths(rng, s, thin_p))]) for s in occ.shape]
    # bosses and arches sit in the margin layers: make them a bit lower than stock layers
    for a in range(3):
        w = np.diff(coords[a])
        w[: _MARGIN] *= rng.uniform(0.6, 3.0) if tall_bosses else 0.6
        w[-_MARGIN:] *= rng.uniform(0.6, 3.0) if tall_bosses else 0.6
        coords[a] = np.concatenate([[0.0], np.cumsum(w)])
    coords = _enforce_min_width(coords, min_width)
    (cx, cy, cz), cocc = compress(coords, occ)
    lo = np.array([cx[0], cy[0], cz[0]])
    hi = np.array([cx[-1], cy[-1], cz[-1]])
    center, diag = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
    if diag <= 0:  # pragma: no cover
        return None
    norm = [(c - center[a]) / diag for a, c in enumerate((cx, cy, cz))]
    features = []
    for i, (kind, axis, flo, fhi) in enumerate(b.features):
        # features still present: holes/pockets/slots must still be empty, bosses/arches still there
        sl = b.box(flo, fhi)
        if kind in ("boss", "arch", "gusset"):
            if kind in ("boss", "gusset") and not occ[sl].all():
                continue
        elif occ[sl].any():
            continue
        flo_c = np.array([(coords[a][flo[a]] - center[a]) / diag for a in range(3)])
        fhi_c = np.array([(coords[a][fhi[a]] - center[a]) / diag for a in range(3)])
        features.append(Feature(kind, int(axis), flo_c, fhi_c, b.signs.get(i)))
    return RandomPolycube(norm[0], norm[1], norm[2], cocc, solid_genus(cocc), style, features)


#: the share of turned polycubes (:func:`turned_polycube`) with a flange at one end unless a dataset sets another
FLANGES = 0.35


def turned_polycube(rng: np.random.Generator, *, min_width: float = MIN_WIDTH, max_tries: int = 50,
                    bolt_circles: float = 0.0, flanges: float = FLANGES) -> RandomPolycube:
    """The polycube of a turned part (style ``turned``): what a shaft, a bushing or a flange is rounded from.

    2-4 coaxial steps of square section along a random axis (half sides 0.35-1, lengths 0.3-1.6, in lattice
    units), sometimes a thin flange at one end (half side 1.4-2 times the widest step) with four bolt holes on
    the two cross axes, a square bore along the axis, a square cross hole through one step.  Every square is
    centred on the axis, so one radial map about it (:func:`polycubenet.synth.pairs.make_pair` with ``turned``)
    rounds all of them at once into coaxial cylinders and the bore into a round bore; the bolt holes and the
    cross hole are :class:`Feature` ``through_hole`` for the hole rounding.  A draw with a grid interval thinner
    than ``min_width`` of the diagonal or an invalid occupancy is drawn again (widening intervals would move
    the squares off the axis).  The random stream of :func:`random_polycube` does not change.

    ``bolt_circles`` is the share of bolted flanges whose holes are not the four on the cross axes but 3-8
    spread evenly round the axis from a random start angle: each centred where the square ring of half side
    ``rb`` meets its direction, so the radial map puts the centres on one circle of radius ``rb``, as a drilled
    bolt circle.  With it above 0, every bolted flange's hole sides within ``min_width`` of another lattice line
    are moved onto it (:func:`_snap_sides`), the four on the axes too.  0 draws nothing more: a generator gives
    the polycubes it gave before this option existed.

    ``flanges`` is the share of draws with a flange (:data:`FLANGES`, which draws the same polycubes as before
    this option existed); 70 % of flanges are bolted.

    Returns
    -------
    RandomPolycube, normalized (bounding box centred at 0, diagonal 1), ``style == "turned"``
    """
    for _ in range(max_tries):
        pc = _turned_once(rng, min_width, bolt_circles, flanges)
        if pc is not None:
            return pc
    raise RuntimeError("turned_polycube: no valid polycube")  # pragma: no cover - never seen


def bolt_circle(k: int, start: float, rb: float) -> list[tuple[float, float]]:
    """``k`` hole centres across a turned part's axis, evenly spread in angle from ``start`` (radians), each on the
    square ring of half side ``rb`` (max-norm ``rb``): where a radial square-to-circle map puts them on a circle."""
    phi = start + 2 * np.pi * np.arange(k) / k
    d = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    d = rb * d / np.abs(d).max(axis=1, keepdims=True)
    return [(float(u), float(v)) for u, v in np.where(np.abs(d) < 1e-12, 0.0, d)]


def _snap_sides(holes: list[tuple], fixed: list[float], tol: float, ring: tuple[float, float]) -> list[tuple] | None:
    """Hole boxes ``(u lo, u hi, v lo, v hi)`` across a turned part's axis with every side within ``tol`` of a
    line already there (``fixed``, the squares' half sides, both signs; or an earlier hole's side) moved onto it.
    The lattice across the axis is one set of lines symmetric about it, so a side's mirror counts too.  None when a
    hole would come out thinner than ``tol``, two holes would touch, or a hole would leave the flange's square
    ring ``(inner, outer)`` half sides by less than ``tol`` (opened at the rim or into the step)."""
    inner, outer = ring
    lines = list({abs(v) for v in fixed})
    out = []
    for box in holes:
        sides = []
        for v in box:
            near = [x for x in lines if abs(abs(v) - x) < tol]
            a = min(near, key=lambda x: abs(abs(v) - x)) if near else abs(v)
            if not near:
                lines.append(a)
            sides.append(float(np.copysign(a, v)))
        if min(sides[1] - sides[0], sides[3] - sides[2]) < tol or np.abs(sides).max() > outer - tol:
            return None
        if sides[0] < inner + tol and sides[1] > -inner - tol and sides[2] < inner + tol and sides[3] > -inner - tol:
            return None
        out.append(tuple(sides))
    for i, a in enumerate(out):
        for b in out[i + 1:]:
            if a[0] < b[1] + tol and b[0] < a[1] + tol and a[2] < b[3] + tol and b[2] < a[3] + tol:
                return None
    return out


def _turned_once(rng: np.random.Generator, min_width: float, bolt_circles: float = 0.0,
                 flanges: float = FLANGES) -> RandomPolycube | None:
    axis = int(rng.integers(3))
    n = int(rng.integers(2, 5))
    half, length = rng.uniform(0.35, 1.0, n), rng.uniform(0.3, 1.6, n)
    flange = int(rng.choice([0, n - 1])) if rng.random() < flanges else None
    if flange is not None:
        half[flange] = rng.uniform(1.4, 2.0) * np.delete(half, flange).max()
        length[flange] = rng.uniform(0.15, 0.4)
    bore = rng.uniform(0.25, 0.6) * half.min() if rng.random() < 0.5 else 0.0
    ends = np.concatenate([[0.0], np.cumsum(length)])
    bolts, hb = [], 0.0
    if flange is not None and rng.random() < 0.7:
        inner = np.delete(half, flange).max()
        rb, hb = 0.5 * (half[flange] + inner), rng.uniform(0.15, 0.3) * (half[flange] - inner)
        bolts = [(rb, 0.0), (-rb, 0.0), (0.0, rb), (0.0, -rb)]
        if bolt_circles > 0 and rng.random() < bolt_circles:
            k = int(rng.integers(3, 9))
            bolts = bolt_circle(k, float(rng.uniform(0.0, 2 * np.pi / k)), rb)
            gap = min(max(abs(a - c), abs(b - d)) for i, (a, b) in enumerate(bolts) for c, d in bolts[i + 1:])
            hb = min(hb, 0.35 * gap)  # holes apart by at least 30 % of their own width
    cross, hc, mid = None, 0.0, 0.0
    if rng.random() < 0.3:
        cross = int(rng.integers(n))
        hc = rng.uniform(0.15, 0.3) * min(half[cross], 0.5 * length[cross])
        mid = 0.5 * (ends[cross] + ends[cross + 1])
    # the lattice: along the axis the step ends (and the cross hole's sides), across it every square's sides
    a_lines = np.unique(np.concatenate([ends, [mid - hc, mid + hc] if cross is not None else []]))
    holes = [(cu - hb, cu + hb, cv - hb, cv + hb) for cu, cv in bolts]  # (u lo, u hi, v lo, v hi) of each
    c_vals = [*half, bore, hc]
    if bolt_circles > 0 and holes:  # hole sides within the minimum width of another line are moved onto it
        diag0 = float(np.linalg.norm([ends[-1] - ends[0], 2 * half.max(), 2 * half.max()]))
        holes = _snap_sides(holes, [v for v in c_vals if v > 0], min_width * diag0, (inner, half[flange]))
        if holes is None:
            return None
    c_vals += [abs(v) for h in holes for v in h]
    c_lines = np.unique(np.round(np.concatenate([[v, -v] for v in c_vals if v > 0]), 12))
    ac, cc = 0.5 * (a_lines[1:] + a_lines[:-1]), 0.5 * (c_lines[1:] + c_lines[:-1])
    A, U, V = np.meshgrid(ac, cc, cc, indexing="ij")
    step = np.clip(np.searchsorted(ends, A) - 1, 0, n - 1)
    occ = np.maximum(np.abs(U), np.abs(V)) < half[step]
    occ &= ~(np.maximum(np.abs(U), np.abs(V)) < bore)
    for ulo, uhi, vlo, vhi in holes:
        occ &= ~((step == flange) & (U > ulo) & (U < uhi) & (V > vlo) & (V < vhi))
    if cross is not None:
        occ &= ~((np.abs(A - mid) < hc) & (np.abs(V) < hc))  # through along the first cross axis
    coords = [None, None, None]
    u_ax, v_ax = (axis + 1) % 3, (axis + 2) % 3
    coords[axis], coords[u_ax], coords[v_ax] = a_lines, c_lines, c_lines
    occ = np.moveaxis(occ, (0, 1, 2), (axis, u_ax, v_ax))
    diag = float(np.linalg.norm([c[-1] - c[0] for c in coords]))
    if min(np.diff(c).min() for c in coords) < min_width * diag or check_occupancy(occ) is not None:
        return None
    (cx, cy, cz), cocc = compress(coords, occ)
    center = np.array([0.5 * (c[0] + c[-1]) for c in (cx, cy, cz)])
    norm = [(c - center[a]) / diag for a, c in enumerate((cx, cy, cz))]

    def box(lo_d: dict, hi_d: dict) -> tuple[np.ndarray, np.ndarray]:
        lo = np.array([(lo_d[a] - center[a]) / diag for a in range(3)])
        hi = np.array([(hi_d[a] - center[a]) / diag for a in range(3)])
        return lo, hi

    features = [Feature("turned", axis, *box({axis: ends[0], u_ax: -half.max(), v_ax: -half.max()},
                                             {axis: ends[-1], u_ax: half.max(), v_ax: half.max()}))]
    for ulo, uhi, vlo, vhi in holes:
        features.append(Feature("through_hole", axis, *box({axis: ends[flange], u_ax: ulo, v_ax: vlo},
                                                          {axis: ends[flange + 1], u_ax: uhi, v_ax: vhi})))
    if cross is not None:
        features.append(Feature("through_hole", u_ax, *box({axis: mid - hc, u_ax: -half[cross], v_ax: -hc},
                                                         {axis: mid + hc, u_ax: half[cross], v_ax: hc})))
    return RandomPolycube(norm[0], norm[1], norm[2], cocc, solid_genus(cocc), "turned", features)
