"""benchmarks/unseen_parts.py: the ``machined`` family is the ``mixed`` one without the wedge's notch."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import unseen_parts  # noqa: E402


def _build(tmp_path: Path, family: str, seed=(11, 7)) -> tuple[Path, str]:
    from polycubenet.io import gmsh_session, quiet_stdout

    path = tmp_path / f"{family}.step"
    with gmsh_session() as gmsh:
        gmsh.model.add(family)
        desc = unseen_parts.build_part(gmsh.model.occ, np.random.default_rng(list(seed)), family)
        with quiet_stdout():
            gmsh.write(str(path))
        gmsh.model.remove()
    return path, desc


def test_machined_slanted_end_is_a_plane_cut_where_mixed_notches_a_knife_edge(tmp_path):
    # seed (11, 7): a block with a 33-degree slanted end and nothing else (mixed_11_007)
    mixed, desc_m = _build(tmp_path, "mixed")
    machined, desc_c = _build(tmp_path, "machined")
    assert desc_m == desc_c and "slanted end 33 deg" in desc_m
    assert unseen_parts.knife_edge_deg(mixed) > 135  # the notch under the slanted face: 180 - 33
    assert unseen_parts.knife_edge_deg(machined) < 125  # the slanted face on the top: 90 + 33


def test_a_block_has_no_knife_edge(tmp_path):
    path, desc = _build(tmp_path, "blocks", seed=(7, 0))
    assert abs(unseen_parts.knife_edge_deg(path) - 90) < 1, desc


def test_an_unknown_family_is_refused():
    import pytest

    with pytest.raises(ValueError, match="family must be one of"):
        unseen_parts.build_part(None, np.random.default_rng(0), "round")


def test_even_anchors_are_spread_evenly_where_the_pipeline_draws_them_independently(monkeypatch):
    """``--anchors even`` (:func:`unseen_parts.use_even_anchors`) replaces the model's anchors, for every
    caller of ``inference.model_anchors``, by a Poisson-disk sample: its closest pair of anchors is far
    further apart than among the pipeline's independent samples of the same part, with the same count,
    the normals alongside, and the same function of the seed."""
    import trimesh

    from polycubenet import inference
    from polycubenet.sampling import min_spacing

    box = trimesh.creation.box(extents=(1.0, 0.6, 0.3))
    V, F = np.asarray(box.vertices, float), np.asarray(box.faces)
    uniform = inference.part_anchors(V, F, 1024, seed=3, normals=True)
    monkeypatch.setattr(inference, "part_anchors", inference.part_anchors)  # restored after the test
    unseen_parts.use_even_anchors()
    even = inference.part_anchors(V, F, 1024, seed=3, normals=True)
    assert even.shape == uniform.shape == (1024, 6)
    np.testing.assert_allclose(np.linalg.norm(even[:, 3:], axis=1), 1.0, atol=1e-5)
    assert min_spacing(even[:, :3]) > 3 * min_spacing(uniform[:, :3])
    np.testing.assert_array_equal(even, inference.part_anchors(V, F, 1024, seed=3, normals=True))


def test_the_map_column_says_when_a_realisation_put_back_thin_slabs_of_the_part():
    assert unseen_parts.map_name({"map": "registration (why not the realisation)"}) == "registration"
    assert unseen_parts.map_name({"map": "exact (realised)", "realised": {"inserted_slabs": 0}}) == "exact"
    assert unseen_parts.map_name({"map": "exact (realised)", "realised": {"inserted_slabs": 2}}) == "exact, 2 inserted"
    own = {"map": "exact (realised, the part's structure)",
           "realised": {"inserted_slabs": 0, "structure": "the part's (1 cells differ from the learned polycube's)"}}
    assert unseen_parts.map_name(own) == "exact, part's structure"
    assert unseen_parts.map_name({"map": "exact (realised)", "realised": {"structure": "learned"}}) == "exact"


def _surface_types(family: str, seed=(11, 7)) -> tuple[str, list[str]]:
    from polycubenet.io import gmsh_session

    with gmsh_session() as gmsh:
        gmsh.model.add(family)
        try:
            desc = unseen_parts.build_part(gmsh.model.occ, np.random.default_rng(list(seed)), family)
            types = [gmsh.model.getType(d, t) for d, t in gmsh.model.occ.getEntities(2)]
            assert len(gmsh.model.occ.getEntities(3)) == 1
        finally:
            gmsh.model.remove()
    return desc, types


def test_finished_parts_are_the_machined_ones_with_rounded_and_chamfered_edges():
    desc_c, types_c = _surface_types("machined")
    desc_f, types_f = _surface_types("finished")
    assert desc_f.startswith(desc_c + ", fillet")  # the same part, then finished
    assert set(types_c) == {"Plane"}  # a block with a slanted end: planes only
    assert len(types_f) > len(types_c) and set(types_f) - {"Plane"}  # a fillet's round face (a chamfer adds a plane)


def _genus(path: Path) -> int:
    from polycubenet.io import load_part

    return int(load_part(path).meta["genus"])


def test_every_hole_through_a_profile_or_a_turned_part_is_a_tunnel(tmp_path):
    """The two families drawn like the examples: a profile's holes go through its legs (one tunnel each); a
    turned part's bolt holes and its bore are one tunnel each, and a cross hole two where it crosses the bore."""
    for seed in [(5, 6), (5, 8), (5, 12)]:  # an L with 3 round holes, a U and a stair with 2 holes each, no mitre
        path, desc = _build(tmp_path, "profiles", seed)
        holes = desc.count(" hole")
        assert holes >= 2 and _genus(path) == holes, desc
    for seed in [(5, 3), (5, 13)]:  # 5 bolt holes and a bore; a bore crossed by a cross hole
        path, desc = _build(tmp_path, "turned", seed)
        bolts = int(desc.split(" bolt holes")[0].rsplit(" ", 1)[1]) if "bolt holes" in desc else 0
        bore = "bore" in desc
        cross = (2 if bore else 1) * ("cross hole" in desc)
        assert _genus(path) == bolts + bore + cross > 0, desc
