"""benchmarks/unseen_split.py: parts are put in the class their sharpest edge and thinnest feature say."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import unseen_split  # noqa: E402


def test_read_part_gives_the_thinnest_features_thickness_over_the_hex_edge(tmp_path):
    """A 60 x 60 x 20 block with a fin 0.6 thick and 20 tall along one side of its top: the 3000-hex edge is
    (73 440 / 3000)^(1/3) = 2.90, so the fin's 0.6 is 0.21 of it; the plain block has no thin feature."""
    import trimesh

    block = trimesh.creation.box(bounds=[[0, 0, 0], [60, 60, 20]])
    fin = trimesh.creation.box(bounds=[[0, 0, 20], [60, 0.6, 40]])  # a wall 0.6 thick standing on the block
    finned = trimesh.boolean.union([block, fin], engine="manifold")  # manifold3d: a declared dependency
    block.export(tmp_path / "block.stl")
    finned.export(tmp_path / "finned.stl")
    deg, ratio = unseen_split.read_part(tmp_path / "block.stl")
    assert deg == pytest.approx(90, abs=1) and ratio is None
    deg, ratio = unseen_split.read_part(tmp_path / "finned.stl")
    h = (abs(finned.volume) / unseen_split.HEXES) ** (1 / 3)
    assert deg == pytest.approx(90, abs=1)
    assert ratio == pytest.approx(0.6 / h, rel=0.05)
    assert unseen_split.depth_class(ratio) == "0.15-0.3 hex"
    assert unseen_split.like_class(deg, ratio) == unseen_split.LIKE_BINS[0]


def test_split_counts_each_part_in_its_class_and_keeps_unknown_parts_apart():
    info = {"plain": ("block 10x10x10", 90.0, None),
            "fin": ("block 10x10x10, boss", 90.0, 0.1),        # a wall under 0.15 of a hex
            "stub": ("block 10x10x10, boss", 95.0, 0.4),       # thin, but not that thin
            "wedge": ("block 10x10x10, slanted end 20 deg", 160.0, None)}  # a knife edge
    meshed = {"plain": True, "fin": False, "stub": True, "wedge": False, "lost": True}
    out = unseen_split.split(meshed, info)
    like, other = unseen_split.LIKE_BINS
    assert out["like"] == {like: [2, 2], other: [0, 2], "unknown": [1, 1]}
    assert out["depth"] == {"none thinner than a hex": [1, 2], "under 0.15 hex": [0, 1], "0.3-0.5 hex": [1, 1],
                            "unknown": [1, 1]}
    assert out["thin"] == {unseen_split.THIN_BINS[0]: [1, 2], unseen_split.THIN_BINS[1]: [1, 2], "unknown": [1, 1]}
    again = unseen_split.split(meshed, info, out)  # added to what is there
    assert again["like"][like] == [4, 4]


@pytest.mark.parametrize("ratio, want", [(None, "none thinner than a hex"), (0.99, "0.5-1 hex"), (0.5, "0.5-1 hex"),
                                         (0.49, "0.3-0.5 hex"), (0.3, "0.3-0.5 hex"), (0.15, "0.15-0.3 hex"),
                                         (0.149, "under 0.15 hex")])
def test_depth_bins_edges(ratio, want):
    assert unseen_split.depth_class(ratio) == want
