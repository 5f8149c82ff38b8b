"""The demo driver: a batch with a good and a bad part finishes, the bad one recorded with its error."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from polycubenet.data import SurfaceSample
from polycubenet.demo import discover, main


def test_batch_with_bad_part_goes_on(tmp_path):
    src = tmp_path / "parts"
    src.mkdir()
    trimesh.creation.box([2.0, 1.0, 0.5]).export(src / "good_box.stl")
    open_box = trimesh.creation.box()
    open_box.faces = open_box.faces[:-2]  # one side missing: open boundary
    open_box.export(src / "open_box.stl")
    (src / "garbage.obj").write_bytes(b"\x00\xff" * 50)
    out = tmp_path / "out"
    assert main([str(src), "-o", str(out), "--points", "256"]) == 0
    rows = {r["part"]: r for r in json.loads((out / "manifest.json").read_text())["parts"]}
    assert rows["good_box.stl"]["status"] == "sampled" and rows["good_box.stl"]["genus"] == 0
    assert rows["open_box.stl"]["status"] == "failed"
    assert "OpenBoundaryError" in rows["open_box.stl"]["error"] and "open_box.stl" in rows["open_box.stl"]["error"]
    assert rows["garbage.obj"]["status"] == "failed" and "UnreadableFileError" in rows["garbage.obj"]["error"]
    s = SurfaceSample.load(out / "good_box" / "sample.npz")
    assert s.points.shape == (256, 3)
    np.testing.assert_allclose(np.linalg.norm(np.ptp(s.points, axis=0)), 1.0, atol=0.05)  # canonical frame
    assert (out / "good_box" / "sample.png").stat().st_size > 1000
    assert not (out / "open_box").exists() or not any((out / "open_box").iterdir())
    assert not list(out.rglob(".tmp-*"))


def test_discover_prefers_cad_over_mesh_export(tmp_path):
    for name in ["a.step", "a.stl", "b.stl", "c.txt"]:
        (tmp_path / name).write_text("x")
    assert [p.name for p in discover([tmp_path])] == ["a.step", "b.stl"]
