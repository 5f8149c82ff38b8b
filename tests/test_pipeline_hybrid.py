"""The hybrid polycube policy of the pipeline: learned first, classical when it is invalid."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from polycubenet.data import Polycube
from polycubenet.errors import PolycubeError
from polycubenet.pipeline import OracleSource, PipelineConfig, mesh_part, mesh_part_safe

SMALL = dict(n_sample=2048, n_polycube=8192, n_register=1500, target_hexes=1200)


@pytest.fixture(scope="module")
def l_block_file(tmp_path_factory):
    a = trimesh.creation.box(bounds=[[0, 0, 0], [60, 20, 15]])
    b = trimesh.creation.box(bounds=[[0, 0, 15], [20, 20, 45]])
    m = trimesh.boolean.union([a, b], engine="manifold")
    path = tmp_path_factory.mktemp("hybrid") / "l_block.stl"
    m.export(path)
    return path


def _torus_like() -> Polycube:
    """A genus-1 polycube: wrong for the genus-0 L-block."""
    p = Polycube(np.linspace(-0.4, 0.4, 4), np.linspace(-0.3, 0.3, 4), np.array([-0.1, 0.1]), np.ones((3, 3, 1), bool))
    p.occupancy[1, 1, 0] = False
    return p


class _Raises:
    """A 'learned' source that gives up (as a model may when it cannot produce a cloud)."""

    calls = 0

    def __call__(self, sample, V, F, config):
        type(self).calls += 1
        raise PolycubeError("model produced no usable cloud")


class _MustNotRun:
    def __call__(self, sample, V, F, config):
        raise AssertionError("the learned source must not be called in classical mode")


def test_auto_falls_back_when_the_learned_polycube_fails_validation(l_block_file, tmp_path):
    cfg = PipelineConfig(polycube="auto", **SMALL)
    res = mesh_part(l_block_file, OracleSource(_torus_like()), cfg)
    assert res.status == "meshed"
    assert res.provenance == "classical" and res.source == "classical"  # the flattening, not a voxel refinement
    assert "genus 1 differs from the part's genus 0" in res.fallback_reason
    assert res.fallback_reason.startswith("learned polycube rejected at extract:")
    assert res.polycube.meta["provenance"] == "classical" and res.polycube.meta["genus"] == 0
    q = res.report.to_dict()
    assert q["valid"] and q["sj_min"] > 0.2 and q["surface"]["hausdorff"] < 0.02
    # the rejected attempt's time is kept apart from the classical one
    assert "rejected_extract" in res.timings and "extract" in res.timings and "polycube" in res.timings
    row = res.row()
    assert row["provenance"] == "classical" and row["fallback_reason"] == res.fallback_reason
    out = res.write(tmp_path / "out")
    qj = json.loads((out / "quality.json").read_text())
    assert qj["provenance"] == "classical" and "genus 1" in qj["fallback_reason"]
    assert qj["sharpest_edge_deg"] == pytest.approx(90.0, abs=0.5)
    rj = json.loads((out / "result.json").read_text())
    assert rj["provenance"] == "classical" and rj["fallback_reason"] == res.fallback_reason
    assert rj["sharpest_edge_deg"] == pytest.approx(90.0, abs=0.5)  # an L-block: right angles, no knife edge


def test_auto_falls_back_when_the_learned_source_raises(l_block_file):
    _Raises.calls = 0
    res = mesh_part(l_block_file, _Raises(), PipelineConfig(polycube="auto", **SMALL))
    assert _Raises.calls == 1
    assert res.provenance == "classical" and res.status == "meshed"
    assert res.fallback_reason == "learned polycube rejected at polycube: model produced no usable cloud"


class _Broken:
    """A learned source whose cloud is fine but whose attempt breaks later (or at once)."""

    def __init__(self, inner=None, exc=None):
        self.inner, self.exc = inner, exc

    def __call__(self, sample, V, F, config):
        if self.exc is not None:
            raise self.exc
        return self.inner(sample, V, F, config)


@pytest.mark.parametrize("where", ["generate", "register", "realise", "pullback"])
def test_auto_falls_back_on_any_error_of_the_learned_attempt(l_block_file, monkeypatch, where):
    """Not only a rejected polycube: any exception of the learned attempt (a model bug, CPD running out of
    memory, a pullback error) hands the part to the classical chain, and the reason names the stage."""
    from polycubenet import pipeline

    if where == "generate":
        src = _Broken(exc=RuntimeError("CUDA error: device-side assert triggered"))
    else:
        src = _Broken(inner=OracleSource(_l_truth(l_block_file)))
        if where == "register":
            monkeypatch.setattr(pipeline, "align", lambda *a, **k: (_ for _ in ()).throw(MemoryError("CPD")))
        elif where == "realise":  # the registration's mesh taken as not ending the chain, then the realisation fails
            from polycubenet import policy

            monkeypatch.setattr(pipeline, "ends_chain", lambda *a, **k: False)
            real_ends = policy.ends_chain  # the policy's view too (run_chain runs the rest after the map's mesh)
            monkeypatch.setattr(policy, "ends_chain", lambda q, m: q.get("map") != "registration" and real_ends(q, m))
            monkeypatch.setattr(pipeline, "learned_map", lambda *a, **k: (_ for _ in ()).throw(ValueError("flattening")))
        else:
            real = pipeline.pull_back

            def pull(mesh_pc, fn, V, F, cfg, diagonal=None):  # only the learned attempt uses pull_back directly
                raise FloatingPointError("overflow in the harmonic solve")

            monkeypatch.setattr(pipeline, "pull_back", pull)
            monkeypatch.setattr(pipeline, "_pull_back_classical",
                                lambda mesh_pc, corr, Vc, F, config, diagonal=None: real(mesh_pc, corr.map_points, Vc, F,
                                                                                         config.pullback, diagonal))
    # pullback: the learned attempt without its exact realisation (which pulls back like the classical chain)
    cfg = PipelineConfig(polycube="auto", **SMALL, **({"realise": None} if where == "pullback" else {}))
    res = mesh_part(l_block_file, src, cfg)
    assert res.status == "meshed" and res.provenance == "classical" and res.report.to_dict()["valid"]
    stage = {"generate": "polycube", "register": "register", "realise": "pullback", "pullback": "pullback"}[where]
    assert res.fallback_reason.startswith(f"learned polycube rejected at {stage}: ")
    exc_name = {"generate": "RuntimeError", "register": "MemoryError", "realise": "ValueError",
                "pullback": "FloatingPointError"}[where]
    assert exc_name in res.fallback_reason


def test_a_bad_part_is_final_and_learned_alone_fails_with_a_clear_reason(l_block_file, monkeypatch):
    from polycubenet.errors import PartError

    calls = []

    class BadPart:
        def __call__(self, sample, V, F, config):
            calls.append(1)
            raise PartError(None, "the part is not watertight")

    with pytest.raises(PartError):  # a PartError is not a polycube problem: no other source is tried
        mesh_part(l_block_file, BadPart(), PipelineConfig(polycube="auto", **SMALL))
    assert calls == [1]
    # learned alone: an unexpected error is a failed part with its cause, not a crash of the batch
    res = mesh_part_safe(l_block_file, _Broken(exc=RuntimeError("bad weights")), PipelineConfig(polycube="learned", **SMALL))
    assert res.status == "failed" and res.stage == "polycube"
    assert "learned polycube failed at polycube: RuntimeError: bad weights" in res.error


def _l_truth(l_block_file) -> Polycube:
    """The L-block is its own polycube (in its canonical frame)."""
    from polycubenet.frame import canonicalize

    m = trimesh.load(l_block_file)
    Vc, _ = canonicalize(np.asarray(m.vertices, float), np.asarray(m.faces))
    grid = [np.unique(np.round(Vc[:, a], 9)) for a in range(3)]
    centres = np.stack(np.meshgrid(*[0.5 * (g[1:] + g[:-1]) for g in grid], indexing="ij"), -1).reshape(-1, 3)
    inside = trimesh.Trimesh(Vc, m.faces, process=False).ray.contains_points(centres)
    return Polycube(*grid, inside.reshape([len(g) - 1 for g in grid]))


def test_auto_keeps_a_valid_learned_polycube(l_block_file):
    res = mesh_part(l_block_file, OracleSource(_l_truth(l_block_file)), PipelineConfig(polycube="auto", **SMALL))
    assert res.provenance == "oracle" and res.fallback_reason is None and res.source == "learned"
    assert res.row()["provenance"] == "oracle" and res.row()["fallback_reason"] is None
    assert not any(k.startswith("rejected_") for k in res.timings)


def test_learned_mode_does_not_fall_back(l_block_file):
    cfg = PipelineConfig(polycube="learned", **SMALL)
    with pytest.raises(PolycubeError, match="model produced no usable cloud") as err:
        mesh_part(l_block_file, _Raises(), cfg)
    assert err.value.stage == "polycube"
    res = mesh_part_safe(l_block_file, OracleSource(_torus_like()), cfg)
    assert res.status == "failed" and res.stage == "extract"


def test_classical_mode_and_no_source(l_block_file):
    cfg = PipelineConfig(polycube="classical", **SMALL)
    res = mesh_part(l_block_file, _MustNotRun(), cfg)
    assert res.provenance == "classical" and res.fallback_reason is None
    assert res.report.to_dict()["valid"]
    # no source at all: the classical polycube whatever the mode
    res2 = mesh_part(l_block_file, None, PipelineConfig(polycube="learned", **SMALL))
    assert res2.provenance == "classical"
    np.testing.assert_array_equal(res2.polycube.occupancy, res.polycube.occupancy)


def test_unknown_mode_is_rejected(l_block_file):
    with pytest.raises(ValueError, match="polycube must be one of"):
        mesh_part(l_block_file, _Raises(), PipelineConfig(polycube="magic", **SMALL))


def _invalid_first(monkeypatch, label: str, sj: float = -0.2):
    """Make the pullback of the ``label`` polycube come out invalid (as fertility's classical
    flattening does), leaving every other pullback as it is."""
    from polycubenet import pipeline

    real = pipeline._pull_back_classical

    def pull(mesh_pc, corr, Vc, F, config, diagonal=None):
        mesh = real(mesh_pc, corr, Vc, F, config, diagonal)
        if corr.meta["method"].startswith(label):
            mesh.meta.update(valid=False, sj_min=sj)
        return mesh

    monkeypatch.setattr(pipeline, "_pull_back_classical", pull)


def test_classical_mode_falls_back_to_the_voxel_polycube_when_its_mesh_is_invalid(l_block_file, monkeypatch):
    _invalid_first(monkeypatch, "classical")
    res = mesh_part(l_block_file, _MustNotRun(), PipelineConfig(polycube="classical", **SMALL))
    assert res.provenance == "voxel" and res.status == "meshed"
    assert res.fallback_reason.startswith("pullback: the classical polycube's hex mesh is not valid")
    assert "-0.200" in res.fallback_reason
    assert res.report.to_dict()["valid"]
    assert res.polycube.meta["provenance"] == "voxel"
    # the rejected attempt's time is kept apart from the kept one's
    assert {"rejected_polycube", "rejected_pullback", "polycube", "pullback"} <= set(res.timings)
    assert res.row()["provenance"] == "voxel"


def test_when_no_polycube_gives_a_valid_mesh_the_best_one_is_kept(l_block_file, monkeypatch):
    from polycubenet import pipeline

    real = pipeline._pull_back_classical

    def pull(mesh_pc, corr, Vc, F, config, diagonal=None):  # both invalid; the classical one less so
        mesh = real(mesh_pc, corr, Vc, F, config, diagonal)
        voxel = mesh_pc.meta.get("source") == "voxel"
        mesh.meta.update(valid=False, sj_min=-0.5 if voxel else -0.1)
        return mesh

    def tagged_partition(poly, **kw):
        from polycubenet.hexmesh import partition

        m = partition(poly, **kw)
        m.meta["source"] = poly.meta.get("provenance")
        return m

    monkeypatch.setattr(pipeline, "_pull_back_classical", pull)
    monkeypatch.setattr(pipeline, "partition", tagged_partition)
    res = mesh_part(l_block_file, _MustNotRun(), PipelineConfig(polycube="classical", **SMALL))
    assert res.provenance == "classical"
    assert res.mesh.meta["sj_min"] == pytest.approx(-0.1)
    assert "classical polycube's hex mesh is not valid" in res.fallback_reason


def test_a_rejected_classical_polycube_falls_back_to_the_voxel_one(l_block_file, monkeypatch):
    from polycubenet import classical

    def refuse(self, sample, V, F, config):
        raise PolycubeError("l_block.stl: flattening folded")

    monkeypatch.setattr(classical.ClassicalSource, "__call__", refuse)
    res = mesh_part(l_block_file, _Raises(), PipelineConfig(polycube="auto", **SMALL))
    assert res.provenance == "voxel" and res.report.to_dict()["valid"]
    assert res.fallback_reason == ("learned polycube rejected at polycube: model produced no usable cloud; "
                                   "classical polycube rejected at polycube: l_block.stl: flattening folded")
    # learned alone and voxel alone
    res = mesh_part(l_block_file, _MustNotRun(), PipelineConfig(polycube="voxel", **SMALL))
    assert res.provenance == "voxel" and res.fallback_reason is None
