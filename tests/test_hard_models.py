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


def test_a_model_that_fails_does_not_stop_the_set_but_is_named(tmp_path, monkeypatch, capsys):
    """``make_all(keep_going=True)`` (the benchmark's): a model whose check fails is still handed on (its file
    exists; the benchmark's load then reports it as a failed part), one that was never written is left out, the
    rest of the set is built, and each failure is named on stderr.  Without ``keep_going`` the first one raises."""
    names = [s.name for s in hard_models.SPECS[:4]]
    bad_check, bad_build = names[1], names[2]
    (tmp_path / f"{bad_build}.step").write_text("left by an earlier run")

    def fake_build(name, path, check=True, seed=None):
        if name == bad_build:
            raise RuntimeError("OCC refused the fillet")
        Path(path).write_text(name)
        if name == bad_check:
            raise RuntimeError(f"{name}: loaded with genus 0, intended 1")
        return {"name": name, "path": str(path), "volume": 1.0, "genus": 0, "description": name}

    monkeypatch.setattr(hard_models, "build", fake_build)
    got = hard_models.make_all(tmp_path, names=names, keep_going=True)
    assert [p.stem for p in got] == [n for n in names if n != bad_build]
    assert not (tmp_path / f"{bad_build}.step").exists()  # no stale file from before stands in for it
    err = capsys.readouterr().err
    assert f"hard model {bad_check}" in err and "intended 1" in err and "kept for the benchmark" in err
    assert f"hard model {bad_build}" in err and "left out" in err
    with pytest.raises(RuntimeError, match="intended 1"):
        hard_models.make_all(tmp_path, names=names)
