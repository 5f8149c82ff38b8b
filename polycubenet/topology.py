"""Mend the topology of an extracted occupancy with moves of several cells.

The structure extraction (:mod:`polycubenet.structure`) settles its cells by single-cell flips that lower the
face-evidence cost.  A generated cloud of a machined part often leaves an occupancy that no single flip can
mend: a hole the vote filled (genus one short), two holes merged or a spurious one (genus one over), a thin
bridge the vote left empty (two or three solid components).  Each of these is one *move* of a few cells:

* a **run**: every cell of a maximal run of equal cells along an axis flips -- an occupied run punches a
  straight hole, an empty run between two occupied cells is filled (closes a slot, bridges components);
* a **plug**: an empty region of one layer that the layer's solid encloses is filled (closes a hole there);
* a **drop**: a solid component other than the largest is removed.

:func:`mend` applies such moves greedily, at most ``max_moves`` of them, each the one that leaves the fewest
defects (components beyond one, cavities, edge- and vertex-only contacts, then the genus's distance from the
part's), the cheapest of those; it returns the mended occupancy only when no defect is left.  The cost is
the extraction's own (votes contradicted, boundary faces without their points), so the move the cloud's
evidence contradicts least wins; whether the result is the part's polycube is left to the extraction's
validation (the cloud's distance to the polycube, coverage) and to the pull-back.
"""

from __future__ import annotations

from typing import Callable, Iterator

import numpy as np
from scipy import ndimage

from .polycube import edge_contacts, nonmanifold_vertices, solid_genus

_FACE6 = ndimage.generate_binary_structure(3, 1)


def defects(occ: np.ndarray, genus: int | None = None) -> int:
    """How far ``occ`` is from a valid polycube of ``genus`` (0: it is one; ``genus`` None: any genus).

    The sum of: solid components beyond one, enclosed cavities, edge- and vertex-only contacts and, once
    those are all zero, ``|solid genus - genus|``.  An empty occupancy counts ``occ.size + 1``."""
    occ = np.asarray(occ, dtype=bool)
    if not occ.any():
        return occ.size + 1
    _, n_solid = ndimage.label(occ, structure=_FACE6)
    _, n_empty = ndimage.label(~np.pad(occ, 1), structure=_FACE6)
    n = (n_solid - 1) + (n_empty - 1) + len(edge_contacts(occ)) + len(nonmanifold_vertices(occ))
    if n == 0 and genus is not None:
        n = abs(int(solid_genus(occ)) - int(genus))
    return int(n)


def _line_cells(axis: int, j: int, k: int, i0: int, i1: int) -> tuple:
    b, c = [d for d in range(3) if d != axis]
    idx = [None, None, None]
    idx[axis], idx[b], idx[c] = np.arange(i0, i1), np.full(i1 - i0, j), np.full(i1 - i0, k)
    return tuple(idx)


def moves(occ: np.ndarray) -> Iterator[tuple[str, tuple]]:
    """Every candidate move of ``occ`` (see the module docstring): ``(kind, cells)`` with ``cells`` an index
    tuple of the cells that flip, ``kind`` one of ``"punch"``, ``"fill"``, ``"plug"``, ``"drop"``."""
    occ = np.asarray(occ, dtype=bool)
    for a in range(3):
        o = np.moveaxis(occ, a, 0)
        n = o.shape[0]
        for j in range(o.shape[1]):
            for k in range(o.shape[2]):
                line = o[:, j, k]
                edges = np.flatnonzero(np.diff(line.astype(np.int8))) + 1
                starts = np.concatenate([[0], edges])
                ends = np.concatenate([edges, [n]])
                for i0, i1 in zip(starts.tolist(), ends.tolist()):
                    if line[i0]:
                        yield "punch", _line_cells(a, j, k, i0, i1)
                    elif i0 > 0 and i1 < n:  # an empty run between two occupied cells
                        yield "fill", _line_cells(a, j, k, i0, i1)
        for i in range(occ.shape[a]):
            layer = np.take(occ, i, axis=a)
            lab, n_lab = ndimage.label(~layer)
            if n_lab == 0:
                continue
            border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
            for lbl in range(1, n_lab + 1):
                if lbl in border:
                    continue
                u, v = np.nonzero(lab == lbl)
                idx = [None, None, None]
                b, c = [d for d in range(3) if d != a]
                idx[a], idx[b], idx[c] = np.full(len(u), i), u, v
                yield "plug", tuple(idx)
    lab, n_solid = ndimage.label(occ, structure=_FACE6)
    if n_solid > 1:
        sizes = np.bincount(lab.ravel())[1:]
        for lbl in np.argsort(sizes)[:-1] + 1:
            yield "drop", np.nonzero(lab == lbl)


def mend(occ: np.ndarray, cost: Callable[[np.ndarray], float], genus: int | None = None,
         max_moves: int = 3, beam: int = 4) -> tuple[np.ndarray, list[str]] | None:
    """``occ`` mended to a valid polycube of ``genus`` by at most ``max_moves`` moves, and the moves'
    kinds; None when it cannot be (or has no defect to mend).

    A beam search: from each of the ``beam`` best occupancies so far, every candidate move (:func:`moves`)
    that leaves no more :func:`defects` (a move that removes one defect may bring another, as a dropped
    component can uncover a genus one over); the ``beam`` best of those, fewest defects then lowest
    ``cost(occupancy)``, go on.  The first depth that reaches no defect returns its cheapest."""
    occ = np.asarray(occ, dtype=bool)
    bad = defects(occ, genus)
    if bad == 0:
        return None
    states = [(bad, occ, [])]
    seen = {occ.tobytes()}
    for _ in range(max_moves):
        found: dict[bytes, tuple] = {}
        for bad, state, done in states:
            work = state.copy()
            for kind, cells in moves(state):
                work[cells] = ~work[cells]
                d = defects(work, genus)
                if d <= bad:
                    key = work.tobytes()
                    if key not in found and key not in seen:
                        found[key] = (d, float(cost(work)), work.copy(), done + [kind])
                work[cells] = ~work[cells]
        if not found:
            return None
        seen.update(found)
        ranked = sorted(found.values(), key=lambda t: (t[0], t[1]))
        if ranked[0][0] == 0:
            return ranked[0][2], ranked[0][3]
        states = [(d, o, k) for d, _, o, k in ranked[:beam]]
    return None
