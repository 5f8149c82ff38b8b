"""benchmarks/draw_structures.py: what leaving a repeated structure, or stopping after rejected draws, would cost."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from draw_structures import replay, signature  # noqa: E402


def _part(meshed, draw, sigs):
    return {"meshed": meshed, "draw": draw, "draws": [{"sig": s} for s in sigs]}


def test_signature_is_the_cells_not_the_planes():
    occ = np.zeros((2, 3, 1), bool)
    occ[0, :, 0] = True
    assert signature(occ) == signature(occ.copy())
    assert signature(occ) != signature(occ.reshape(3, 2, 1))  # the same bits on another grid
    other = occ.copy()
    other[1, 0, 0] = True
    assert signature(occ) != signature(other)


def test_replay_counts_left_draws_and_lost_parts():
    rec = {
        "miss": _part(False, None, ["a", "a", None, "b", "a", "b"]),  # three repeats left, no part to lose
        "hit_on_a_repeat": _part(True, 3, ["c", "d", "c", "e"]),  # its meshing draw repeats draw 1: lost
        "hit_after_a_repeat": _part(True, 4, ["f", "f", None, "g"]),  # one draw left before it, kept
        "no_repeat": _part(True, 2, [None, "h"]),
        "rejected_first": _part(True, 4, [None, None, None, "i"]),  # lost by stopping after 2 or 3 rejections
        "rejected_miss": _part(False, None, [None, None, None, None, None]),
    }
    tot = replay(rec)
    assert tot["repeated"] == 3 and tot["left_on_misses"] == 3 and tot["left_before_the_hit"] == 1
    assert tot["lost"] == ["hit_on_a_repeat"]
    assert tot["stop_after_2_rejected"] == {"lost": ["rejected_first"], "stopped": 1}
    assert tot["stop_after_3_rejected"] == {"lost": ["rejected_first"], "stopped": 1}
    assert tot["stop_after_4_rejected"] == {"lost": [], "stopped": 1}
