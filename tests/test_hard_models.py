"""The seeded variants of benchmarks/hard_models.py: they build, load with the intended genus and differ by seed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("gmsh")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import hard_models  # noqa: E402


@pytest.mark.parametrize("name", ["thin_tray", "perforated_plate"])
def test_variant_builds_with_intended_genus(tmp_path, name):
    spec = hard_models.variant(name, 3)
    holes = spec.build.keywords.get("holes")
    assert spec.genus == (len(holes) if name == "perforated_plate" else hard_models.BY_NAME[name].genus)
    # check=True: gmsh re-imports one solid, load_part gives the intended genus and the same volume
    row = hard_models.build(name, tmp_path / f"{name}.step", seed=3)
    assert row["genus"] == spec.genus and row["volume"] > 0
    assert row["description"].startswith("seed 3:")


def test_seeds_give_different_models(tmp_path):
    vols = {s: hard_models.build("thin_tray", tmp_path / f"tray{s}.step", seed=s)["volume"] for s in (3, 4)}
    assert abs(vols[3] - vols[4]) > 0.01 * vols[3]
    assert hard_models.variant("thin_tray", 3) is not hard_models.BY_NAME["thin_tray"]
    assert hard_models.variant("thin_tray", None) is hard_models.BY_NAME["thin_tray"]
    # the draws are a function of (seed, name) only
    draw = hard_models.variant("perforated_plate", 3).build.keywords
    assert draw == hard_models.variant("perforated_plate", 3).build.keywords
