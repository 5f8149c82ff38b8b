"""benchmarks/learned_meshes.py: the comparison against the baseline checkpoint."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from learned_meshes import summary  # noqa: E402


def _row(ok, seconds):
    return [ok, 0.3 if ok else None, 1 if ok else None, seconds, 0.005, None, "registration"]


def test_summary_counts_gains_and_losses_against_the_first_checkpoint():
    result = {
        "base.pt": {"a": _row(True, 1.0), "b": _row(True, 2.0), "c": _row(False, 3.0)},
        "new.pt": {"a": _row(True, 1.5), "b": _row(False, 2.5), "c": _row(True, 3.5)},
    }
    rows = summary(["base", "new"], ["base.pt", "new.pt"], result)
    assert [(r["name"], r["meshed"], r["parts"]) for r in rows] == [("base", 2, 3), ("new", 2, 3)]
    assert rows[0]["gained"] == [] and rows[0]["lost"] == []
    assert rows[1]["gained"] == ["c"] and rows[1]["lost"] == ["b"]
    assert rows[1]["seconds"] == 7.5
