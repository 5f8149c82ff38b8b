"""benchmarks/unseen_losses.py: every learned-path miss lands in the stage that lost it."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import unseen_losses  # noqa: E402

# rows as unseen_parts.py --mesh records them: ok, SJ min (or the exception's name), draw, seconds, Hausdorff
# / diagonal, why the first draw was left, map
ROWS = {
    "kept": [True, 0.31, 1, 5.0, 0.004, None, "registration"],
    "no polycube": [False, "PolycubeError", None, 1.2, None, "p.step: polycube genus 0 differs", None],
    "inverted": [False, -0.4, None, 9.0, 0.05, "pullback: not valid", "registration"],
    "a little off": [False, 0.30, None, 9.0, 0.012, "pullback: 1.2 % off", "registration"],
    "off": [False, 0.30, None, 9.0, 0.024, "pullback: 2.4 % off", "registration"],
    "far off": [False, 0.30, None, 9.0, 0.05, "pullback: 5 % off", "registration"],
    "poor": [False, 0.12, None, 9.0, 0.004, None, "exact (realised)"],
}
WANT = {"kept": "meshed", "no polycube": "rejected at extraction", "inverted": "not valid",
        "a little off": "off the part <= 1.5 %", "off": "off the part 1.5-3 %", "far off": "off the part > 3 %",
        "poor": "under the quality bar"}


def test_each_miss_is_put_in_the_stage_that_lost_it():
    assert {k: unseen_losses.bucket(r, 0.2, 0.01) for k, r in ROWS.items()} == WANT


def test_the_table_counts_sets_and_examples_once(tmp_path, capsys):
    files = []
    for seed in (1, 2):
        f = tmp_path / f"u{seed}.json"
        f.write_text(json.dumps({"family": "mixed", "seed": seed, "mesh": ROWS, "example_mesh": {"a": ROWS["kept"]}}))
        files.append(str(f))
    out = tmp_path / "losses.json"
    assert unseen_losses.main(files + ["--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["all"]["meshed"] == 2 and res["all"]["off the part > 3 %"] == 2 and sum(res["all"].values()) == 14
    assert res["examples"] == {"meshed": 1}
    assert res["sets"]["mixed:2"]["rejected at extraction"] == 1


def test_learned_misses_are_split_by_what_the_classical_chain_gives(tmp_path, capsys):
    # rows as unseen_classical.py records them: meets the bars, SJ min, kept source, seconds, Hausdorff / diagonal
    classical = {"kept": [True, 0.5, "classical", 6.0, 0.0], "no polycube": [True, 0.3, "voxel+1", 30.0, 0.008],
                 "inverted": [False, 0.1, "voxel+3*", 90.0, 0.02], "off": [True, 0.4, "classical", 6.0, 0.002]}
    (tmp_path / "unseen_classical_mixed5.json").write_text(json.dumps({"mesh": classical}))
    (tmp_path / "unseen_classical_examples.json").write_text(json.dumps({"mesh": {"a": classical["kept"]}}))
    f = tmp_path / "u5.json"
    f.write_text(json.dumps({"family": "mixed", "seed": 5, "mesh": ROWS, "example_mesh": {"a": ROWS["kept"]}}))
    out = tmp_path / "losses.json"
    assert unseen_losses.main([str(f), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    # parts without a classical row ("a little off", "far off", "poor") are left out of the split
    assert res["by_classical"] == {"flattening meets the bars": [1, 2], "only a voxel polycube does": [0, 1],
                                   "nothing meets the bars": [0, 1]}
    assert res["examples_by_classical"]["flattening meets the bars"] == [1, 1]
    assert res["either"] == 3  # the three the classical chain meets the bars on; the learned path adds none
    assert "flattening meets the bars" in capsys.readouterr().out


def test_parts_are_split_by_the_features_their_descriptions_name(tmp_path, capsys):
    assert unseen_losses.shape_class(None) is None  # an example part: no description
    assert unseen_losses.shape_class("block 50x43x19, rotated") == "no slanted end"
    assert unseen_losses.shape_class("block 70x44x17, round boss, slanted end 39 deg, rotated") == \
        "slanted end, no round hole"
    assert unseen_losses.shape_class("block 56x33x15, round hole, square hole, slanted end 21 deg") == \
        "slanted end and round hole"
    assert unseen_losses.shape_class("U profile 55x39x102, round hole, mitred end 34 deg, rotated") == \
        "slanted end and round hole"
    rows = [{"part": "kept", "accepted": True, "shape": "block, pocket, rotated"},
            {"part": "no polycube", "accepted": False, "shape": "block, round hole, slanted end 30 deg"},
            {"part": "off", "accepted": True, "shape": "block, slanted end 40 deg, rotated"},
            {"part": "poor", "accepted": True, "shape": "block, round hole, slanted end 25 deg"}]
    classical = {"kept": [True, 0.5, "classical", 6.0, 0.0], "no polycube": [False, 0.1, "voxel", 30.0, 0.02],
                 "off": [True, 0.4, "voxel+1", 6.0, 0.002]}  # "poor": no classical row
    (tmp_path / "unseen_classical_machined5.json").write_text(json.dumps({"mesh": classical}))
    f = tmp_path / "u5.json"
    f.write_text(json.dumps({"family": "machined", "seed": 5, "mesh": ROWS, "rows": rows, "example_mesh": {}}))
    out = tmp_path / "losses.json"
    assert unseen_losses.main([str(f), "--json", str(out)]) == 0
    by = json.loads(out.read_text())["by_shape"]
    assert by == {"no slanted end": {"parts": 1, "accepted": 1, "meshed": 1, "classical": 1},
                  "slanted end, no round hole": {"parts": 1, "accepted": 1, "meshed": 0, "classical": 1},
                  "slanted end and round hole": {"parts": 2, "accepted": 1, "meshed": 0, "classical": 0}}


def test_runs_without_meshes_are_read_at_extraction_only(tmp_path, capsys):
    rows = [{"part": "a", "accepted": True, "shape": "block, pocket"},
            {"part": "b", "accepted": False, "shape": "block, round hole, slanted end 30 deg"},
            {"part": "c", "accepted": True, "shape": "block, round hole, slanted end 30 deg"}]
    files = []
    for seed in (1, 2):
        f = tmp_path / f"u{seed}.json"
        f.write_text(json.dumps({"family": "machined", "seed": seed, "rows": rows}))  # no "mesh": made without --mesh
        files.append(str(f))
    out = tmp_path / "x.json"
    assert unseen_losses.main(files + ["--json", str(out)]) == 2  # the full tables need the meshing rows
    assert unseen_losses.main(files + ["--extraction-only", "--json", str(out)]) == 0
    by = json.loads(out.read_text())["by_shape"]
    assert by == {"no slanted end": {"parts": 2, "accepted": 2, "meshed": None, "classical": None},
                  "slanted end and round hole": {"parts": 4, "accepted": 2, "meshed": None, "classical": None}}


def test_parts_are_split_by_their_sharpest_convex_edge(tmp_path, capsys, monkeypatch):
    assert [unseen_losses.edge_class(d) for d in (None, 90.0, 130.0, 130.5, 150.0, 165.9)] == \
        [None, *unseen_losses.EDGE_BINS[:1] * 2, *unseen_losses.EDGE_BINS[1:2] * 2, unseen_losses.EDGE_BINS[2]]
    rows = [{"part": "kept", "knife_edge_deg": 90.0}, {"part": "no polycube", "knife_edge_deg": 145.0},
            {"part": "inverted", "knife_edge_deg": 160.0}, {"part": "off", "knife_edge_deg": 120.0},
            {"part": "poor"}]  # no angle recorded: left out
    monkeypatch.setattr(unseen_losses, "example_edges", lambda names: {"a": 90.0, "b": 140.0})
    f = tmp_path / "u5.json"
    f.write_text(json.dumps({"family": "machined", "seed": 5, "mesh": ROWS, "rows": rows,
                             "example_mesh": {"a": ROWS["kept"], "b": ROWS["off"]}}))
    out = tmp_path / "losses.json"
    assert unseen_losses.main([str(f), "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    lo, mid, hi = unseen_losses.EDGE_BINS
    assert res["by_edge"] == {lo: [1, 2, 0, 0], mid: [0, 1, 0, 0], hi: [0, 1, 0, 0]}  # no classical rows
    assert res["examples_by_edge"] == {lo: [1, 1, 0, 0], mid: [0, 1, 0, 0]}
    # with the classical chain's rows for the set: "kept" meets the bars, "inverted" does not, "off" is not there
    (tmp_path / "unseen_classical_machined5.json").write_text(json.dumps(
        {"mesh": {"kept": [True, 0.5, "classical", 6.0, 0.0], "no polycube": [True, 0.3, "voxel", 9.0, 0.005],
                  "inverted": [False, 0.1, "voxel+3*", 90.0, 0.02]}}))
    assert unseen_losses.main([str(f), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["by_edge"] == {lo: [1, 2, 1, 1], mid: [0, 1, 1, 1], hi: [0, 1, 0, 1]}
    assert "sharpest convex edge" in capsys.readouterr().out


def test_the_examples_sharpest_edges_are_read_from_their_files():
    edges = unseen_losses.example_edges(["l_block", "t_slot_block", "no_such_part"])  # right-angled blocks
    assert sorted(edges) == ["l_block", "t_slot_block"]
    assert all(88.0 < d < 95.0 for d in edges.values())  # 90 up to the tessellation of the STEP faces
