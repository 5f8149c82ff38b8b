"""Topology mends of an extracted occupancy (polycubenet.topology) and their place in the extraction."""

from __future__ import annotations

import numpy as np
import pytest

from polycubenet.data import Polycube
from polycubenet.errors import PolycubeError
from polycubenet.polycube import check_occupancy, polycube_surface, solid_genus
from polycubenet.sampling import poisson_disk
from polycubenet.structure import ExtractConfig, extract
from polycubenet.topology import defects, mend, moves


#: the extraction with the mends on (off by default)
MENDS = ExtractConfig(mend_moves=3)


def _hamming(truth: np.ndarray):
    return lambda occ: float((occ != truth).sum())


def _ring() -> np.ndarray:
    occ = np.ones((3, 3, 2), bool)
    occ[1, 1, :] = False
    return occ


def test_defects_counts_what_keeps_an_occupancy_from_a_polycube_of_the_genus():
    ring = _ring()
    assert defects(ring) == 0 and defects(ring, 1) == 0
    assert defects(ring, 0) == 1 and defects(ring, 3) == 2
    bar = np.ones((5, 1, 1), bool)
    bar[2] = False  # two components
    assert defects(bar) == 1
    diag = np.zeros((2, 2, 1), bool)
    diag[0, 0, 0] = diag[1, 1, 0] = True  # two components touching along an edge (and its two vertices)
    assert defects(diag) == 1 + 1 + 2
    assert defects(np.zeros((2, 2, 2), bool)) > 8


def test_a_filled_hole_is_punched_again():
    truth = _ring()
    filled = np.ones_like(truth)
    got, done = mend(filled, _hamming(truth), genus=1)
    assert done == ["punch"] and (got == truth).all()


def test_a_missing_bridge_is_filled_and_a_stray_component_dropped():
    bar = np.zeros((5, 3, 1), bool)
    bar[:, 1, 0] = True
    cut = bar.copy()
    cut[2, 1, 0] = False
    got, done = mend(cut, _hamming(bar), genus=0)
    assert done == ["fill"] and (got == bar).all()

    truth = np.zeros((5, 1, 3), bool)
    truth[:, 0, 0] = True
    broken = truth.copy()
    broken[2, 0, 0] = False  # the bar cut in two ...
    broken[2, 0, 2] = True  # ... and a stray cell above it: three components
    got, done = mend(broken, _hamming(truth), genus=0)
    assert len(done) == 2 and "fill" in done and (got == truth).all()  # the stray cell: dropped or punched


def test_a_spurious_hole_is_plugged_to_the_parts_genus():
    ring = _ring()
    got, done = mend(ring, _hamming(np.ones_like(ring)), genus=0)  # the cost asks for the solid block
    assert len(done) == 1 and defects(got, 0) == 0 and solid_genus(got) == 0
    assert int(got.sum()) == int(ring.sum()) + 1  # one cell of one layer: the cheapest plug


def test_mend_leaves_a_valid_occupancy_alone_and_gives_up_beyond_its_moves():
    ring = _ring()
    assert mend(ring, _hamming(ring), genus=1) is None
    three = np.zeros((7, 1, 1), bool)
    three[[0, 3, 6]] = True  # three components: two fills
    truth = np.ones_like(three)
    assert mend(three, _hamming(truth), genus=0, max_moves=1) is None
    got, done = mend(three, _hamming(truth), genus=0, max_moves=2)
    assert done == ["fill", "fill"] and (got == truth).all()


def test_moves_flip_maximal_runs_plugs_and_small_components():
    occ = np.zeros((4, 3, 1), bool)
    occ[:3, :, 0] = True
    occ[1, 1, 0] = False  # a hole in the 3 x 3 block's layer
    kinds = {}
    for kind, cells in moves(occ):
        kinds.setdefault(kind, []).append(len(cells[0]))
    assert kinds["plug"] == [1]  # the hole, in the one z layer
    assert "drop" not in kinds  # one component
    assert 3 in kinds["punch"] and 1 in kinds["fill"]


def _smeared_ring(seed: int):
    """A 3 x 3 plate with a narrow hole, sampled, and the model's kind of error: the top and bottom faces
    smeared over the hole (twice as many points there as the hole's walls carry)."""
    occ = np.ones((3, 3, 1), bool)
    occ[1, 1, 0] = False
    truth = Polycube(np.array([-0.45, -0.05, 0.05, 0.45]), np.array([-0.3, -0.05, 0.05, 0.3]),
                     np.array([-0.05, 0.05]), occ)
    V, F = polycube_surface(truth.xs, truth.ys, truth.zs, truth.occupancy)
    s = poisson_disk(V, F, 4096, seed=seed)
    rng = np.random.default_rng(seed)
    P = s.points + rng.normal(scale=0.002, size=s.points.shape)
    N = s.normals.copy()
    walls = (np.abs(P[:, 0]) < 0.06) & (np.abs(P[:, 1]) < 0.06) & (np.abs(N[:, 2]) < 0.5)
    k = 2 * int(walls.sum())
    z = np.where(rng.random(k) < 0.5, -0.05, 0.05)
    smear = np.c_[rng.uniform(-0.05, 0.05, k), rng.uniform(-0.05, 0.05, k), z]
    return truth, np.vstack([P, smear]), np.vstack([N, np.c_[np.zeros(k), np.zeros(k), np.sign(z)]])


@pytest.mark.parametrize("seed", [0, 1])
def test_extract_punches_the_hole_a_smeared_cloud_filled(seed):
    truth, P, N = _smeared_ring(seed)
    with pytest.raises(PolycubeError, match="genus 0 differs from the part's genus 1"):
        extract(P, N, genus=1, config=ExtractConfig(mend_moves=0))
    with pytest.raises(PolycubeError, match="genus 0 differs"):  # the classical flattening's clouds: no mends
        extract(P, N, genus=1, config=MENDS.for_exact_clouds())
    with pytest.raises(PolycubeError, match="genus 0 differs"):  # the default: no mends (ExtractConfig.mend_moves)
        extract(P, N, genus=1)
    got = extract(P, N, genus=1, config=MENDS)
    assert got.meta["genus"] == 1 and (got.occupancy == truth.occupancy).all()
    assert got.meta["mended"].startswith("punch (was: genus 0); without the mends: ")
    assert "polycube genus 0 differs from the part's genus 1" in got.meta["mended"]


def test_a_mend_the_cloud_contradicts_is_rejected_with_the_first_reason(monkeypatch):
    """Two real holes, the part's genus said to be 1: a mend closes one, and the validation rejects the
    polycube whose surface the hole's walls are far from; the error is the first try's, as without mends."""
    import polycubenet.structure as structure

    tried = []
    real = structure.mend

    def spy(*args, **kw):
        out = real(*args, **kw)
        tried.append(None if out is None else out[1])
        return out

    monkeypatch.setattr(structure, "mend", spy)
    occ = np.ones((5, 3, 1), bool)
    occ[1, 1, 0] = occ[3, 1, 0] = False
    g = np.array([-0.45, -0.3, -0.1, 0.1, 0.3, 0.45])
    plate = Polycube(g, np.array([-0.25, -0.08, 0.08, 0.25]), np.array([-0.06, 0.06]), occ)
    V, F = polycube_surface(plate.xs, plate.ys, plate.zs, plate.occupancy)
    s = poisson_disk(V, F, 8192, seed=1)
    with pytest.raises(PolycubeError, match="genus 2 differs from the part's genus 1") as err:
        extract(s.points, s.normals, genus=1, part="plate.step", config=MENDS)
    assert "plate.step" in str(err.value)
    assert tried and None not in tried  # a mend (a plug, or a punch that opens a hole to the side) was made, and rejected


def test_the_mends_come_after_every_other_try(monkeypatch):
    """A plate with a narrow hole that only the relaxed plane filter finds (test_structure's case): the strict
    try's occupancy has genus 0, and mending it there would take the cloud before the relaxed try extracts it
    exactly; the mends are the last resort, so they are not even tried."""
    import polycubenet.structure as structure

    calls = []
    monkeypatch.setattr(structure, "mend", lambda *a, **k: calls.append(a) or None)
    occ = np.ones((3, 3, 1), bool)
    occ[1, 1, 0] = False
    truth = Polycube(np.array([-0.45, -0.0125, 0.0125, 0.45]), np.array([-0.3, -0.0125, 0.0125, 0.3]),
                     np.array([-0.05, 0.05]), occ)
    V, F = polycube_surface(truth.xs, truth.ys, truth.zs, truth.occupancy)
    s = poisson_disk(V, F, 2048, seed=0)
    got = extract(s.points, s.normals, genus=1, config=MENDS)
    assert "relaxed_planes" in got.meta and "mended" not in got.meta and not calls
    assert (got.occupancy == occ).all()


def test_the_held_out_evaluation_extracts_with_the_config_it_is_given():
    from polycubenet.evaluate import _structure

    truth, P, N = _smeared_ring(0)
    bare = _structure(P, N, truth, 1, "pair 0")
    mended = _structure(P, N, truth, 1, "pair 0", MENDS)
    assert not bare["genus_match"] and "genus 0 differs" in bare["error"]
    assert mended["genus_match"] and mended["exact"] and mended["error"] is None
