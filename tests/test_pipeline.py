"""The whole spine on small cases, with a known polycube as the "generated" cloud.

Fails when any stage regresses: the structure must be the ground truth, the mesh
valid with good average quality and close to the surface, and outputs complete.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from polycubenet.data import Polycube
from polycubenet.errors import PartError, PolycubeError
from polycubenet.frame import canonicalize
from polycubenet.io import read_hex
from polycubenet.pipeline import OracleSource, PipelineConfig, mesh_part, mesh_part_safe, mesh_surface
from polycubenet.polycube import compress
from polycubenet.synth import make_pair

SMALL = PipelineConfig(n_sample=2048, n_polycube=8192, n_register=1500, target_hexes=1500)


def _same(a: Polycube, b: Polycube, atol: float) -> bool:
    ga, oa = compress([a.xs, a.ys, a.zs], a.occupancy)
    gb, ob = compress([b.xs, b.ys, b.zs], b.occupancy)
    return oa.shape == ob.shape and bool((oa == ob).all()) and all(np.allclose(x, y, atol=atol) for x, y in zip(ga, gb))


def _l_block_file(tmp_path):
    a = trimesh.creation.box(bounds=[[0, 0, 0], [60, 20, 15]])
    b = trimesh.creation.box(bounds=[[0, 0, 15], [20, 20, 45]])
    m = trimesh.boolean.union([a, b], engine="manifold")
    path = tmp_path / "l_block.stl"
    m.export(path)
    return path, m


def _exact_polycube(V, F) -> Polycube:
    """A part that is itself a polycube, in its canonical frame: planes = its vertex coordinates."""
    Vc, _ = canonicalize(V, F)
    grid = [np.unique(np.round(Vc[:, a], 9)) for a in range(3)]
    centres = np.stack(np.meshgrid(*[0.5 * (g[1:] + g[:-1]) for g in grid], indexing="ij"), axis=-1).reshape(-1, 3)
    inside = trimesh.Trimesh(Vc, F, process=False).ray.contains_points(centres)
    return Polycube(*grid, inside.reshape([len(g) - 1 for g in grid]))


def test_l_block_file_end_to_end(tmp_path):
    path, m = _l_block_file(tmp_path)
    truth = _exact_polycube(m.vertices, m.faces)
    res = mesh_part(path, OracleSource(truth), SMALL)
    assert res.status == "meshed"
    assert _same(res.polycube, truth, atol=0.02)
    q = res.report.to_dict()
    assert q["valid"] and q["sj_min"] > 0.2 and q["sj_avg"] > 0.85
    assert q["surface"]["hausdorff"] < 0.01
    # the mesh is in the part's own coordinates (mm), not the canonical frame
    lo, hi = res.mesh.points.min(0), res.mesh.points.max(0)
    np.testing.assert_allclose(lo, m.bounds[0], atol=0.6)
    np.testing.assert_allclose(hi, m.bounds[1], atol=0.6)
    out = res.write(tmp_path / "out", formats=("vtu", "inp"))
    back = read_hex(out / "hex.inp")
    assert back.hexes.shape == res.mesh.hexes.shape
    row = json.loads((out / "result.json").read_text())
    assert row["status"] == "meshed" and row["provenance"] == "oracle" and row["valid"] is True
    for name in ("quality.json", "quality.png", "preview.png", "polycube.npz", "hex.vtu"):
        assert (out / name).stat().st_size > 0


def test_genus2_deformed_pair():
    pair = make_pair(5, n_cond=64, n_target=64)  # an extrusion with a rounded hole, genus 2
    assert pair.genus == 2
    cfg = PipelineConfig(n_sample=2048, n_polycube=8192, n_register=1500, target_hexes=4000)
    res = mesh_surface(pair.shape_vertices, pair.faces, OracleSource(pair.polycube), cfg,
                       part_meta={"genus": pair.genus}, canonical=True)
    assert _same(res.polycube, pair.polycube, atol=0.02)
    assert res.polycube.meta["genus"] == 2
    q = res.report.to_dict()
    assert q["valid"] and q["sj_avg"] > 0.8
    assert q["surface"]["hausdorff"] < 0.03
    assert set(res.timings) >= {"sample", "polycube", "cleanup", "extract", "register", "partition", "pullback", "report"}


def test_wrong_polycube_is_reported_not_meshed(tmp_path):
    path, m = _l_block_file(tmp_path)
    torus_like = Polycube(np.linspace(-0.4, 0.4, 4), np.linspace(-0.3, 0.3, 4), np.array([-0.1, 0.1]), np.ones((3, 3, 1), bool))
    torus_like.occupancy[1, 1, 0] = False
    with pytest.raises(PolycubeError, match="genus 1 differs from the part's genus 0") as err:
        mesh_part(path, OracleSource(torus_like), SMALL)
    assert err.value.stage == "extract"
    res = mesh_part_safe(path, OracleSource(torus_like), SMALL)
    assert res.status == "failed" and res.stage == "extract" and "PolycubeError" in res.error
    assert res.mesh is None


def test_bad_part_fails_at_load(tmp_path):
    bad = tmp_path / "broken.stl"
    bad.write_bytes(b"solid x\nfacet normal 0 0 1\n")
    with pytest.raises(PartError) as err:
        mesh_part(bad, OracleSource(Polycube(np.array([0.0, 1]), np.array([0.0, 1]), np.array([0.0, 1]), np.ones((1, 1, 1), bool))))
    assert err.value.stage == "load"
