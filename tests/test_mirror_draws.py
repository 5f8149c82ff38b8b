"""benchmarks/mirror_draws.py's summary: the vote, its tie-break and the agreement table."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import mirror_draws  # noqa: E402


def _pair(own, others):
    """Eight draws: the unmirrored one first; each ``(key, exact)`` (key None: refused at extraction)."""
    return [{"key": k, "exact": e} for k, e in [own, *others]]


def test_vote_agreement_and_ceiling():
    rows = [
        # the unmirrored draw wrong, the majority right: the vote fixes it
        _pair(("a", False), [("b", True)] * 5 + [("a", False)] * 2),
        # a tie between the unmirrored draw's structure and another: the unmirrored one is kept
        _pair(("a", True), [("a", True)] * 3 + [("b", False)] * 4),
        # every draw refused: nothing to vote on
        _pair((None, False), [(None, False)] * 7),
        # all eight agree and are right
        _pair(("c", True), [("c", True)] * 7),
    ]
    res = mirror_draws.summarise(rows)
    assert res["pairs"] == 4
    assert res["single"] == 0.5
    assert res["any"] == 0.75
    assert res["vote"] == 0.75
    assert res["agreement"] == {"0": {"pairs": 1, "exact": 0.0}, "3": {"pairs": 1, "exact": 0.0},
                                "4": {"pairs": 1, "exact": 1.0}, "8": {"pairs": 1, "exact": 1.0}}
