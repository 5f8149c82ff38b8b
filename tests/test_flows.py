"""The orchestration: library helpers, the stage tasks' rules, and the flows under one
session-scoped ``prefect_test_harness``.

Synthetic parts (held-out seeds, STL in mm) with ground-truth sidecars give the polycube
(``polycube="oracle"``), so these tests exercise the orchestration, not the model.  Most
runs use a thread pool (stage functions counted by wrapping them); one uses a local Dask
cluster.  Recomputation is counted (calls of the library's stage functions, Prefect task
states), never timed.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "90")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from polycubenet import library  # noqa: E402
from polycubenet.data import Polycube  # noqa: E402
from polycubenet.errors import OpenBoundaryError, PartError, PolycubeError  # noqa: E402
from polycubenet.frame import Transform  # noqa: E402
from polycubenet.pipeline import PipelineConfig  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
GOOD = (9005, 9004)  # held-out synthetic seeds: genus 1 and 2, quick to mesh
SMALL = dict(n_sample=2048, n_polycube=4096, n_learned=2048, n_register=1000, target_hexes=600)
STAGE_FNS = ("load_sample", "polycube_cloud", "cleanup_extract", "register", "partition_pullback", "report_export")


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="session")
def prefect_harness():
    """One Prefect test server for every flow test (it takes ~15 s to start)."""
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield


@pytest.fixture(scope="session")
def part_lib(tmp_path_factory) -> Path:
    """Two good synthetic parts, an unreadable file, an open surface, and a part whose oracle
    polycube has the wrong genus (its PolycubeError must be final for that part only)."""
    import trimesh

    d = tmp_path_factory.mktemp("parts")
    library.write_synthetic_parts(d, GOOD)
    (d / "broken.stl").write_bytes(b"this is not an STL file at all\n" * 4)
    box = trimesh.creation.box(extents=[30, 20, 10])
    trimesh.Trimesh(box.vertices, box.faces[:-1], process=False).export(d / "open_box.stl")
    from polycubenet.io import load_part, write_surface

    p = load_part(d / f"synth-{GOOD[1]}.stl")  # the same shape, other bytes: its own content hash
    write_surface(p.vertices, p.faces, d / "wrong_genus.obj")
    other = library.write_synthetic_parts(tmp_path_factory.mktemp("other"), [GOOD[0]])[0]
    shutil.copy(library.sidecar_path(other), d / "wrong_genus.polycube.npz")
    return d


def _runner(kind="threads", workers=2):
    from flows.runners import make_runner

    return make_runner(workers, kind=kind)


def _mesh(inputs, out, runner=None, **kw):
    from flows.mesh_library import mesh_library

    args = dict(polycube="oracle", fallback=False, formats=["vtu", "inp"], **SMALL)
    args.update(kw)
    f = mesh_library.with_options(task_runner=runner or _runner())
    state = f(inputs=[str(i) for i in inputs], out=str(out), return_state=True, **args)
    return state, state.result()


class Counter:
    """Wraps the library's stage functions (the tasks call them through the module) and counts calls."""

    def __init__(self, monkeypatch, fail: dict | None = None):
        self.calls = {n: 0 for n in STAGE_FNS}
        for name in STAGE_FNS:
            real = getattr(library, name)

            def wrapped(*a, _real=real, _name=name, **k):
                self.calls[_name] += 1
                if fail and _name in fail:
                    raise fail[_name]
                return _real(*a, **k)

            monkeypatch.setattr(library, name, wrapped)


@pytest.fixture(scope="module")
def batch(prefect_harness, part_lib, tmp_path_factory):
    out = tmp_path_factory.mktemp("batch") / "out"
    state, res = _mesh([part_lib], out)
    return {"state": state, "res": res, "out": out}


def _rows(res):
    return {r["name"]: r for r in res["rows"]}


# --------------------------------------------------------------------------- library (no Prefect)


def test_discover_folders_globs_and_preference(tmp_path):
    (tmp_path / "a").mkdir()
    for name in ("a/p.step", "a/p.stl", "a/q.obj", "a/notes.txt", "r.STL"):
        (tmp_path / name).write_text("x")
    found = library.discover([tmp_path])
    assert [p.name for p in found] == ["p.step", "q.obj", "r.STL"]  # the STL export of p.step is skipped
    assert [p.name for p in library.discover([str(tmp_path / "a" / "*.stl")], prefer_cad=False)] == ["p.stl"]
    with pytest.raises(FileNotFoundError, match="nothing-here"):
        library.discover([tmp_path / "nothing-here"])


def test_discover_volume_meshes_but_not_the_runs_own_output(tmp_path):
    (tmp_path / "out" / "p").mkdir(parents=True)
    for name in ("t.mesh", "u.vtu", "v.msh", "w.vtk", "p.stl", "p.mesh", "out/p/hex.vtu", "out/p/hex.mesh"):
        (tmp_path / name).write_text("x")
    found = [p.relative_to(tmp_path).as_posix() for p in library.discover([tmp_path], exclude=[tmp_path / "out"])]
    assert found == ["p.stl", "t.mesh", "u.vtu", "v.msh", "w.vtk"]  # the surface beats the volume mesh of p
    assert "out/p/hex.vtu" in [p.relative_to(tmp_path).as_posix() for p in library.discover([tmp_path])]


def test_part_names_disambiguate_same_stems():
    names = library.part_names([Path("x/a.stl"), Path("y/a.stl"), Path("b.stl")], ["1" * 64, "2" * 64, "3" * 64])
    assert names == ["a-11111111", "a-22222222", "b"]


def test_keys_change_only_downstream_of_a_changed_parameter():
    base = library.chain_keys("h" * 64, library.stage_params(PipelineConfig(**SMALL)))
    finer = library.chain_keys("h" * 64, library.stage_params(PipelineConfig(**{**SMALL, "target_hexes": 2000})))
    same = [s for s in library.STAGES if base[s] == finer[s]]
    assert same == ["load_sample", "polycube", "extract", "register"]
    other_file = library.chain_keys("g" * 64, library.stage_params(PipelineConfig(**SMALL)))
    assert all(other_file[s] != base[s] for s in library.STAGES)
    fallback = library.chain_keys("h" * 64, library.stage_params(PipelineConfig(**SMALL)), source="classical")
    assert fallback["load_sample"] == base["load_sample"] and fallback["polycube"] != base["polycube"]


def _source_keys(kind: str, part: Path) -> dict:
    """Every stage key of a part (fixed content hash) whose polycube comes from source ``kind``."""
    params = library.stage_params(PipelineConfig(**SMALL), polycube=kind,
                                  polycube_extra=library.source_extra(kind, part))
    return library.chain_keys("h" * 64, params)


def test_classical_cloud_key_follows_the_construction_version(monkeypatch, tmp_path):
    """A cached classical cloud made by older code (or other settings) must not be reused."""
    from polycubenet import classical

    before = _source_keys("classical", tmp_path / "p.stl")
    monkeypatch.setattr(classical, "VERSION", classical.VERSION + "-next")
    after = _source_keys("classical", tmp_path / "p.stl")
    assert after["load_sample"] == before["load_sample"] and after["polycube"] != before["polycube"]


def test_voxel_source_by_name_and_its_key(monkeypatch, tmp_path):
    from polycubenet import voxel
    from polycubenet.policy import source_names

    assert isinstance(library.make_source("voxel", tmp_path / "p.stl", None), voxel.VoxelSource)
    finer = library.make_source("voxel+2", tmp_path / "p.stl", None)
    assert isinstance(finer, voxel.VoxelSource) and finer.refine == 2
    with pytest.raises(ValueError, match="unknown per-part polycube source"):
        library.make_source("voxel+x", tmp_path / "p.stl", None)

    before = _source_keys("voxel", tmp_path / "p.stl")
    # a refinement has its own keys (its own cached stages)
    assert _source_keys("voxel+1", tmp_path / "p.stl")["polycube"] != before["polycube"]
    # the denser last source: the same refinement, its own keys, and its partition's hexes in the pullback key
    denser = library.make_source("voxel+3*", tmp_path / "p.stl", None)
    assert isinstance(denser, voxel.VoxelSource) and denser.refine == 3
    params = library.stage_params(PipelineConfig(**SMALL), polycube="voxel+3*")
    assert params["pullback"]["target_hexes"] == round(1.5 * SMALL["target_hexes"])
    assert library.stage_params(PipelineConfig(**SMALL), polycube="voxel+3")["pullback"]["target_hexes"] == SMALL["target_hexes"]
    assert _source_keys("voxel+3*", tmp_path / "p.stl")["polycube"] != _source_keys("voxel+3", tmp_path / "p.stl")["polycube"]
    monkeypatch.setattr(voxel, "VERSION", voxel.VERSION + "-next")
    assert _source_keys("voxel", tmp_path / "p.stl")["polycube"] != before["polycube"]
    vox = ["voxel", "voxel+1", "voxel+2", "voxel+3", "voxel+3*"]
    assert source_names("classical", False) == ["classical"] + vox
    assert source_names("learned", True) == ["learned", "classical"] + vox == source_names("auto")
    assert source_names("oracle", False) == ["oracle"] and source_names("voxel", True) == vox
    assert source_names("auto", classical=False) == ["learned"] + vox


def test_polycube_to_frame_follows_a_signed_permutation():
    rng = np.random.default_rng(0)
    occ = rng.random((2, 3, 4)) > 0.3
    poly = Polycube(np.array([0.0, 1, 3]), np.array([0.0, 2, 3, 5]), np.array([0.0, 1, 2, 4, 8]), occ)
    R = np.array([[0.0, 0, -1], [1, 0, 0], [0, -1, 0]])  # canonical x = -file z, y = file x, z = -file y
    T = Transform(np.array([1.0, 2.0, 3.0]), 0.5, R)
    out = library.polycube_to_frame(poly, T)
    centres = lambda g: 0.5 * (g[1:] + g[:-1])  # noqa: E731
    for i, j, k in np.argwhere(occ):  # every occupied file cell lands on an occupied canonical cell
        c = T.forward(np.array([centres(poly.xs)[i], centres(poly.ys)[j], centres(poly.zs)[k]]))
        idx = [np.searchsorted(g, c[a]) - 1 for a, g in enumerate(out.grid)]
        assert out.occupancy[tuple(idx)]
    assert out.occupancy.sum() == occ.sum() and all(np.all(np.diff(g) > 0) for g in out.grid)
    with pytest.raises(PolycubeError, match="axis-aligned"):
        c, s = np.cos(0.3), np.sin(0.3)
        library.polycube_to_frame(poly, Transform(np.zeros(3), 1.0, np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])))


# --------------------------------------------------------------------------- task rules (task.fn level)


def test_retry_rule_is_final_for_part_and_polycube_errors():
    from prefect.states import Failed

    from tasks.common import retry_transient

    def retries(exc):
        return retry_transient(None, None, Failed(data=exc))

    assert not retries(OpenBoundaryError("p.stl", "3 boundary edges"))
    assert not retries(PolycubeError("genus 1 differs from 2", part="p.stl"))
    assert not retries(ValueError("a bug is not retried"))
    assert not retries(FileNotFoundError("gone"))
    assert retries(ConnectionResetError("worker lost"))
    assert retries(TimeoutError("slow storage"))
    assert retries(RuntimeError("CUDA out of memory. Tried to allocate 2 GiB"))


def test_stage_task_fn_writes_and_reuses_its_file(part_lib, tmp_path):
    from tasks import mesh as T

    cfg = PipelineConfig(**SMALL)
    path = part_lib / f"synth-{GOOD[0]}.stl"
    dest = tmp_path / "load.npz"
    rec = T.load_sample.fn(str(path), str(dest), key="k", config=cfg, name="x")
    assert rec["path"] == str(dest) and rec["stage"] == "load_sample" and rec["flow_run"] is None
    part, sample, transform, meta = library.read_loaded(dest)
    assert len(sample.points) == cfg.n_sample and meta["part"]["genus"] == 1
    from polycubenet.io import load_part

    assert np.allclose(transform.inverse(part.vertices), load_part(path).vertices)  # the way back to mm
    again = T.load_sample.fn(str(path), str(dest), key="k", config=cfg, name="x")
    assert again["flow_run"] == "file"  # a complete file with the keyed name is not recomputed
    with pytest.raises(PartError, match="broken.stl"):
        T.load_sample.fn(str(part_lib / "broken.stl"), str(tmp_path / "b.npz"), key="b", config=cfg)
    assert not (tmp_path / "b.npz").exists() and not list(tmp_path.glob(".tmp-*"))


# --------------------------------------------------------------------------- flows


def test_batch_with_good_and_bad_parts(batch, part_lib):
    assert batch["state"].is_completed()  # bad parts never fail the batch
    res, out = batch["res"], batch["out"]
    rows = _rows(res)
    assert res["counts"] == {"meshed": 2, "failed": 3}
    for seed in GOOD:
        r = rows[f"synth-{seed}"]
        assert r["status"] == "meshed" and r["stage"] == "export" and r["provenance"] == "oracle"
        assert r["computed"] == list(library.STAGES) and r["reused"] == []
        assert r["quality"]["hexes"] > 100 and r["quality"]["sj_avg"] > 0.5 and r["quality"]["hausdorff"] < 0.05
        from polycubenet.io import read_hex

        m = read_hex(out / r["name"] / "hex.inp")
        assert len(m.hexes) == r["quality"]["hexes"]
        assert {"hex.vtu", "hex.inp", "quality.json", "preview.png", "result.json"} <= set(r["files"])
    assert rows["broken"]["stage"] == "load_sample" and "UnreadableFileError" in rows["broken"]["error"]
    assert "broken.stl" in rows["broken"]["error"]
    assert rows["open_box"]["stage"] == "load_sample" and "OpenBoundaryError" in rows["open_box"]["error"]
    assert rows["wrong_genus"]["stage"] == "extract" and "PolycubeError" in rows["wrong_genus"]["error"]
    assert "genus" in rows["wrong_genus"]["error"]
    manifest = json.loads((out / "manifest.json").read_text())
    assert {r["name"]: r["status"] for r in manifest["parts"]} == {n: r["status"] for n, r in rows.items()}
    assert manifest["parameters"]["config"]["target_hexes"] == SMALL["target_hexes"]
    html = (out / "report.html").read_text()
    assert all(n in html for n in rows) and "synth-9005/preview.png" in html
    assert not list(out.rglob(".tmp-*"))


def test_artifacts_read_back_from_the_api(batch):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId

    run_id = batch["state"].state_details.flow_run_id
    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[run_id])))
    by_key = {a.key: a for a in arts}
    table = by_key["mesh-library-summary"].data
    table = json.loads(table) if isinstance(table, str) else table
    assert sorted(r["part"] for r in table) == sorted(_rows(batch["res"]))
    assert {r["part"]: r["status"] for r in table}["wrong_genus"] == "failed"
    md = by_key["part-synth-9005"].data
    assert "meshed" in md and "sj_min" in md and "data:image/jpeg;base64," in md
    assert "UnreadableFileError" in by_key["part-broken"].data
    progress = [a for a in arts if a.type == "progress"]
    assert len(progress) == 1 and float(progress[0].data) == pytest.approx(100.0)


def test_a_part_meshed_off_its_surface_shows_where_in_its_artifact(tmp_path, monkeypatch):
    """The part's markdown artifact embeds deviation.png beside the preview when the export wrote one (a mesh off
    the part), and only the preview otherwise."""
    import prefect.artifacts
    from PIL import Image

    from flows.mesh_library import _part_artifact

    said = {}
    monkeypatch.setattr(prefect.artifacts, "create_markdown_artifact",
                        lambda markdown, key, description: said.update({key: markdown}))
    d = tmp_path / "bracket"
    d.mkdir()
    for name, colour in (("preview.png", (20, 120, 200)), ("deviation.png", (200, 30, 30))):
        Image.new("RGB", (200, 100), colour).save(d / name)
    row = {"name": "bracket", "status": "meshed", "path": "parts/bracket.step", "stage": "export",
           "provenance": "learned", "timings": {"export": 1.0}, "reused": [], "quality": {"hausdorff": 0.02}}
    _part_artifact(row, tmp_path)
    md = said["part-bracket"]
    assert md.count("data:image/jpeg;base64,") == 2 and "where the mesh leaves the part" in md
    (d / "deviation.png").unlink()
    _part_artifact(row, tmp_path)
    assert said["part-bracket"].count("data:image/jpeg;base64,") == 1


def test_forced_failure_then_retry_reuses_earlier_stages(prefect_harness, part_lib, tmp_path, monkeypatch):
    from flows.retry_failed import retry_failed

    out = tmp_path / "out"
    part = part_lib / f"synth-{GOOD[0]}.stl"
    first = Counter(monkeypatch, fail={"partition_pullback": PolycubeError("forced failure", part="synth-9005.stl")})
    state, res = _mesh([part, part_lib / "broken.stl"], out)
    assert state.is_completed() and res["counts"] == {"meshed": 0, "failed": 2}
    row = _rows(res)[f"synth-{GOOD[0]}"]
    assert row["stage"] == "pullback" and "forced failure" in row["error"]
    assert first.calls["partition_pullback"] == 1  # a PolycubeError is final: no retry

    monkeypatch.undo()
    again = Counter(monkeypatch)
    res2 = retry_failed(out=str(out), runner="threads", workers=2)
    assert res2["retried"] == 2
    row = _rows(res2)[f"synth-{GOOD[0]}"]
    assert row["status"] == "meshed"
    # counted, not timed: every stage before the failure came from the cache
    assert again.calls["polycube_cloud"] == 0 and again.calls["cleanup_extract"] == 0 and again.calls["register"] == 0
    assert again.calls["partition_pullback"] == 1 and again.calls["report_export"] == 1
    assert again.calls["load_sample"] == 1  # only the broken file, which failed again (not cached)
    assert row["reused"] == ["load_sample", "polycube", "extract", "register"]
    assert row["computed"] == ["pullback", "export"]
    manifest = library.read_manifest(out)
    assert {r["name"]: r["status"] for r in manifest["parts"]} == {"broken": "failed", f"synth-{GOOD[0]}": "meshed"}

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    with get_client(sync_client=True) as client:  # the task states say the same as the counters
        runs = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[_flow_run_of(res2)])))
    names = {tr.name: tr.state.name for tr in runs}
    cached = sorted(n.split("-synth")[0] for n, s in names.items() if s == "Cached")
    assert cached == ["extract", "load-sample", "polycube", "register"]


def _flow_run_of(res) -> str:
    return json.loads((Path(res["manifest"])).read_text())["last_run"]["flow_run"]


def test_sigkill_mid_batch_then_rerun(prefect_harness, part_lib, tmp_path, monkeypatch):
    from prefect.settings import PREFECT_API_URL

    out = tmp_path / "out"
    drop = tmp_path / "drop"
    drop.mkdir()
    for seed in GOOD:
        for f in (f"synth-{seed}.stl", f"synth-{seed}.polycube.npz"):
            shutil.copy(part_lib / f, drop / f)
    shutil.copy(part_lib / f"synth-{GOOD[0]}.stl", drop / "twin.stl")  # same bytes, another name
    shutil.copy(part_lib / f"synth-{GOOD[0]}.polycube.npz", drop / "twin.polycube.npz")
    code = (
        "from flows.mesh_library import mesh_library\n"
        "from flows.runners import make_runner\n"
        f"mesh_library.with_options(task_runner=make_runner(1, kind='threads'))(inputs=[{str(drop)!r}], out={str(out)!r},"
        f" polycube='oracle', fallback=False, formats=['vtu', 'inp'], **{SMALL!r})\n"
    )
    env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "PREFECT_LOGGING_LEVEL": "WARNING"}
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 240
        # killed once the first part has finished (the manifest is rewritten as each part finishes)
        while time.time() < deadline and proc.poll() is None and not (out / "manifest.json").exists():
            time.sleep(0.1)
        assert proc.poll() is None, "the batch finished (or died) before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    finished = {p.parent.name for p in out.glob("*/result.json")}
    assert 1 <= len(finished) < 3
    # the manifest was rewritten as each part finished: it exists, says the run is incomplete, and
    # every part it lists is whole (a kill between a part's result and the manifest leaves it out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["last_run"]["complete"] is False
    assert {r["name"] for r in manifest["parts"]} <= finished and manifest["parts"]
    work = out / ".work"
    finals = [f for f in work.rglob("*.npz") if not f.name.startswith(".tmp-")]  # a write the kill cut short
    assert finals
    for f in finals:  # a file with its final name is whole
        with np.load(f, allow_pickle=False) as z:
            assert all(z[k].size >= 0 for k in z.files)
    counts_before = {s: len(list(work.rglob(f"{s}-*.npz"))) for s in ("load_sample", "polycube", "extract", "register", "pullback")}

    keys_before = {n: json.loads((out / n / "result.json").read_text()).get("key") for n in finished}
    calls = Counter(monkeypatch)
    state, res = _mesh([drop], out, runner=_runner("threads", 1))  # one thread: twin and synth-9005 never race
    assert state.is_completed() and res["counts"] == {"meshed": 3, "failed": 0}
    rows = _rows(res)
    for name in finished:  # nothing that finished is recomputed
        assert rows[name]["computed"] == [], (name, finished, counts_before, calls.calls,
                                              {n: (r["computed"], r["keys"].get("export")) for n, r in rows.items()},
                                              keys_before)
    # twin.stl has synth-9005's bytes: its stages share the keys, so only its export is its own
    fn_of = {"load_sample": "load_sample", "polycube": "polycube_cloud", "extract": "cleanup_extract",
             "register": "register", "pullback": "partition_pullback"}
    for stage, fn in fn_of.items():
        assert calls.calls[fn] == 2 - counts_before[stage], (stage, calls.calls, counts_before)
    assert calls.calls["report_export"] == 3 - len(finished)
    assert not list(out.rglob(".tmp-*"))  # no partial file anywhere
    for r in rows.values():
        json.loads((out / r["name"] / "result.json").read_text())
        assert (out / r["name"] / "hex.vtu").stat().st_size > 0


def test_dask_runner_local_cluster(batch, part_lib):
    """The same parts on a local Dask cluster: only the export (new formats) is computed, on the worker."""
    state, res = _mesh([part_lib / f"synth-{s}.stl" for s in GOOD], batch["out"], runner=_runner("dask", 1),
                       formats=["vtu", "mesh"])
    assert state.is_completed() and res["counts"] == {"meshed": 2, "failed": 0}
    for r in res["rows"]:
        assert r["reused"] == ["load_sample", "polycube", "extract", "register", "pullback"]
        assert r["computed"] == ["export"] and "hex.mesh" in r["files"]
    manifest = library.read_manifest(batch["out"])
    assert len(manifest["parts"]) == 5  # merged with the earlier rows


def test_the_runs_quality_bar_reaches_the_stages_and_a_retry(prefect_harness, part_lib, tmp_path):
    """``min_sj`` of the flow is the run's quality bar: the stages' config carries it (the chain's bar and the
    pull-back's easing) and the manifest records it, so that the report marks parts under it and a retry of the
    folder meshes at the same bar.  (A laxer bar than the default: a stricter one makes every part under it try
    every map and source, minutes per part.)"""
    from flows.retry_failed import mesh_arguments

    out = tmp_path / "out"
    _, res = _mesh([part_lib / f"synth-{GOOD[0]}.stl"], out, min_sj=0.15)
    (row,) = res["rows"]
    assert row["status"] == "meshed" and row["quality"]["valid"]
    manifest = library.read_manifest(out)
    config = manifest["parameters"]["config"]
    assert config["min_sj"] == 0.15 and config["pullback"]["ease_below"] == 0.15
    assert library.quality_bar(manifest) == 0.15 and mesh_arguments(manifest)["min_sj"] == 0.15


def test_part_over_the_time_limit_fails_alone_and_the_batch_goes_on(prefect_harness, part_lib, tmp_path, monkeypatch):
    """A part stuck in a stage (here: extraction blocked until the test ends) becomes a failed row
    naming the limit and the stage once it has run ``part_timeout`` seconds; the other part meshes."""
    import threading

    release = threading.Event()
    real = library.cleanup_extract
    calls = []

    def slow(*a, **k):
        calls.append(1)
        if len(calls) == 1:  # the first part to get there is stuck
            release.wait(300)
        return real(*a, **k)

    monkeypatch.setattr(library, "cleanup_extract", slow)
    from flows import mesh_library as ml

    # a thread cannot be stopped: the flow (its thread pool) ends only when the stuck call returns, so the
    # call is released as soon as its part has been written off.  The limit leaves the other part (~10 s alone)
    # room on a loaded machine: at 30 s it once failed too with the suite beside two other processes on 2 cores
    monkeypatch.setattr(ml, "PROGRESS_HOOKS", [lambda ev: ev["status"] == "failed" and release.set()])
    try:
        t0 = time.monotonic()
        _, res = _mesh([part_lib / f"synth-{s}.stl" for s in GOOD], tmp_path / "out", part_timeout=60.0)
        assert time.monotonic() - t0 < 240  # did not wait for the stuck stage (held up to 300 s)
    finally:
        release.set()
    rows = res["rows"]
    assert sorted(r["status"] for r in rows) == ["failed", "meshed"], [r["error"] for r in rows]
    bad = next(r for r in rows if r["status"] == "failed")
    assert bad["stage"] == "extract"
    assert bad["error"].startswith("PartTimeout:") and "over the per-part limit of 60 s" in bad["error"]
    manifest = library.read_manifest(tmp_path / "out")
    assert sorted(r["status"] for r in manifest["parts"]) == ["failed", "meshed"]


def test_dask_worker_of_a_part_over_the_limit_is_restarted(prefect_harness, part_lib, tmp_path):
    """On Dask the task past the limit is cancelled and its worker process restarted: with a limit
    shorter than any part, every part fails with that reason and the flow still completes."""
    state, res = _mesh([part_lib / f"synth-{s}.stl" for s in GOOD], tmp_path / "out", runner=_runner("dask", 1),
                       part_timeout=0.3)
    assert state.is_completed() and res["counts"] == {"meshed": 0, "failed": 2}
    for r in res["rows"]:
        assert r["error"].startswith("PartTimeout:") and "was restarted" in r["error"], r["error"]


def test_local_dask_workers_start_without_malloc_trim(monkeypatch):
    """Dask's default MALLOC_TRIM_THRESHOLD_ made numpy-heavy stages 2-3x slower in its workers: the
    runner's local cluster must start its workers without it (and keep the thread limit)."""
    import copy
    import os

    import dask
    from distributed import Client, LocalCluster

    from flows.runners import dask_runner, prepare_dask

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    saved = copy.deepcopy(dask.config.config)
    try:
        assert "MALLOC_TRIM_THRESHOLD_" in dask.config.get("distributed.nanny.pre-spawn-environ")  # Dask's default
        runner = dask_runner(1)
        prepare_dask(runner)
        with LocalCluster(**runner.cluster_kwargs) as cluster, Client(cluster) as client:
            env = client.run(lambda: (os.environ.get("MALLOC_TRIM_THRESHOLD_"), os.environ.get("OMP_NUM_THREADS")))
        assert list(env.values()) == [(None, "1")]
    finally:
        dask.config.config.clear()
        dask.config.config.update(saved)


_WORKER_EXIT = """
import sys

import numpy as np
import trimesh
from distributed import Client, LocalCluster

from flows.runners import dask_runner, prepare_dask


def stages(out):  # a part's stages in the task's thread: open3d's raycasting, then a VTK preview
    from polycubenet import pullback
    from polycubenet.render import render_hex_quality

    m = trimesh.creation.icosphere(2)
    pullback._closest(pullback._scene(np.asarray(m.vertices), np.asarray(m.faces)), np.zeros((3, 3)))
    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    return render_hex_quality(cube, np.arange(8)[None], np.array([0.5]), out, backend="pyvista")


if __name__ == "__main__":
    runner = dask_runner(1)
    prepare_dask(runner)
    with LocalCluster(**runner.cluster_kwargs) as cluster, Client(cluster) as client:
        print(client.submit(stages, sys.argv[1], pure=False).result())
"""


def test_local_dask_workers_leave_without_aborting_in_native_destructors(tmp_path):
    """A worker process whose task thread raycast with open3d and then rendered a VTK preview (every part
    does) aborted in libEGL's destructor as the cluster closed: glibc's "malloc_consolidate(): unaligned
    fastbin chunk detected" on the terminal after every ``polycubenet mesh`` run, though its results were
    complete.  The runner's workers load open3d in their main thread as they start
    (``flows.runners.dask_setup``)."""
    pytest.importorskip("pyvista")
    script = tmp_path / "worker_exit.py"
    script.write_text(_WORKER_EXIT)
    r = subprocess.run([sys.executable, str(script), str(tmp_path / "preview.png")], capture_output=True, text=True,
                       timeout=300, cwd=str(Path(__file__).resolve().parents[1]))
    assert r.returncode == 0 and r.stdout.split() == ["pyvista"], (r.returncode, r.stdout, r.stderr[-2000:])
    assert "fastbin" not in r.stderr and "malloc" not in r.stderr, r.stderr[-2000:]


def test_scan_drops_meshes_only_new_and_changed(batch, part_lib, tmp_path):
    from flows.scan_drops import scan_drops

    drop = tmp_path / "drop"
    shutil.copytree(part_lib, drop)
    out = batch["out"].parent / "scan-out"
    work = str(batch["out"] / ".work")  # same content + parameters -> the batch's stages are reused
    opts = {**{k: v for k, v in SMALL.items() if k != "target_hexes"}, "work": work, "fallback": False}
    kw = dict(polycube="oracle", formats=["vtu"], target_hexes=SMALL["target_hexes"], runner="threads", workers=2,
              mesh_options=opts)
    first = scan_drops(drop=str(drop), out=str(out), **kw)
    assert len(first["new"]) == 5 and first["changed"] == []
    assert all(set(r["computed"]) <= {"export", "load_sample"} for r in first["rows"])  # failed loads are not cached
    nothing = scan_drops(drop=str(drop), out=str(out), **kw)
    assert nothing["new"] == [] and nothing["changed"] == []

    (drop / "broken.stl").write_bytes(b"still not an STL, but different\n" * 3)
    shutil.copy(drop / f"synth-{GOOD[1]}.stl", drop / "copy.stl")
    shutil.copy(drop / f"synth-{GOOD[1]}.polycube.npz", drop / "copy.polycube.npz")
    second = scan_drops(drop=str(drop), out=str(out), **kw)
    assert [Path(p).name for p in second["new"]] == ["copy.stl"]
    assert [Path(p).name for p in second["changed"]] == ["broken.stl"]
    copy = _rows(second)["copy"]
    assert copy["status"] == "meshed" and copy["computed"] == ["export"]  # same bytes as synth-9004: cached
    manifest = library.read_manifest(out)
    assert len(manifest["parts"]) == 6


def test_cli_mesh_exit_code_and_summary(prefect_harness, part_lib, tmp_path, capsys):
    from flows.cli import main

    out = tmp_path / "cli-out"
    rc = main(["mesh", str(part_lib / f"synth-{GOOD[0]}.stl"), str(part_lib / "open_box.stl"), "-o", str(out),
               "--polycube", "oracle", "--no-fallback", "--runner", "threads", "--workers", "2",
               "--points", "2048", "--polycube-points", "4096", "--hexes", "600", "--formats", "vtu,bdf"])
    text = capsys.readouterr().out
    assert rc == 0  # a part that cannot be meshed is a manifest row, not a failure of the tool
    assert "synth-9005" in text and "meshed" in text and "OpenBoundaryError" in text
    rows = {r["name"]: r for r in library.read_manifest(out)["parts"]}
    assert rows["synth-9005"]["status"] == "meshed" and "hex.bdf" in rows["synth-9005"]["files"]
    assert rows["open_box"]["status"] == "failed"
    assert main(["mesh", str(tmp_path / "missing"), "-o", str(out)]) == 2


@pytest.fixture(scope="module")
def tiny_checkpoint(tmp_path_factory) -> Path:
    """An untrained tiny anchored model (as the shipped one: the policy's every draw applies): its clouds are
    noise, so the learned polycube is always rejected."""
    import dataclasses

    import torch

    from polycubenet.model import Diffusion, PolycubeNet, preset
    from polycubenet.model.checkpoint import save_checkpoint

    torch.manual_seed(0)
    cfg = dataclasses.replace(preset("tiny"), anchored=True)
    net = PolycubeNet(cfg)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    return save_checkpoint(path, {"model_config": cfg.to_dict(), "diffusion": Diffusion().to_dict(),
                                  "ema": net.state_dict(), "metrics": {}})


def test_learned_batches_then_classical_fallback(prefect_harness, part_lib, tiny_checkpoint, tmp_path, monkeypatch):
    """Generation runs as batched tasks (packed under the point budget) writing one learned cloud per
    part; a rejected learned polycube goes to the classical source with its own cache keys, and the
    row says so.  The classical construction itself is slow here, so its place is taken by the
    part's sidecar (provenance "classical"), and the voxel one gives up (:func:`_fake_sources`): this tests
    the wiring, not the constructions."""
    _fake_sources(monkeypatch)
    out = tmp_path / "out"
    budget = SMALL["n_sample"] + SMALL["n_learned"]  # one part per generation batch
    # "auto" is learned with the classical fallback, whatever ``fallback`` says
    state, res = _mesh([part_lib / f"synth-{GOOD[0]}.stl", part_lib / "wrong_genus.obj"], out, polycube="auto",
                       fallback=False, checkpoint=str(tiny_checkpoint), steps=2, point_budget=budget)
    assert state.is_completed()
    rows = _rows(res)
    good, wrong = rows[f"synth-{GOOD[0]}"], rows["wrong_genus"]
    assert good["status"] == "meshed" and good["provenance"] == "classical"
    # the first draw (2 steps) was rejected, then the model's second draw at 4 steps, its third at the first's
    # steps with the next seed, its fourth at the first's steps and seed, anchors evenly spread, its fifth and
    # sixth evenly spread at the next seed, at the first's steps and at 4 (the policy), then classical
    assert good["fallback"].startswith("learned polycube rejected")
    assert "learned (draw 2, 4 steps) polycube rejected" in good["fallback"]
    assert "learned (draw 3, 1 step, seed +1) polycube rejected" in good["fallback"]
    assert wrong["status"] == "failed" and wrong["stage"] == "polycube" and "no voxel polycube" in wrong["error"]
    assert wrong["fallback"].startswith("learned polycube rejected")
    assert "classical polycube rejected at extract" in wrong["fallback"] and "genus" in wrong["fallback"]
    work = out / ".work"
    learned = [library.PolycubeCloud.load(p) for p in work.rglob("polycube-*.npz")
               if library.PolycubeCloud.load(p).meta.get("provenance") == "learned"]
    assert len(learned) == 12 and all(c.points.shape == (SMALL["n_learned"], 3) for c in learned)
    assert sorted(int(c.meta["steps"]) for c in learned) == [2] * 8 + [4] * 4

    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterId

    with get_client(sync_client=True) as client:
        runs = client.read_task_runs(flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[_flow_run_of(res)])))
    assert sum(tr.name.startswith("generate-") for tr in runs) == 2  # the second draws are per part

    # the DDIM steps are in the learned polycube's key: other steps generate anew, the same steps reuse
    # (the second and sixth draws' 4 steps whatever the first's, the third's to fifth's at the first's steps); a
    # first draw at 4 steps has no second and no sixth (the fifth's cloud), its third to fifth are at 4 steps
    def learned_files():
        return {p.name for p in work.rglob("polycube-*.npz")
                if library.PolycubeCloud.load(p).meta.get("provenance") == "learned"}

    first = learned_files()
    parts = [part_lib / f"synth-{GOOD[0]}.stl", part_lib / "wrong_genus.obj"]
    for steps, expected in ((3, 20), (2, 20), (4, 28)):
        state, res = _mesh(parts, out, polycube="auto", checkpoint=str(tiny_checkpoint), steps=steps,
                           point_budget=budget)
        assert state.is_completed() and len(learned_files()) == expected
    assert first < learned_files()
    assert "second draw" not in _rows(res)[f"synth-{GOOD[0]}"]["fallback"]


def test_a_learned_draw_far_off_waits_and_its_rest_is_a_stage_of_its_own(prefect_harness, part_lib, tiny_checkpoint,
                                                                           tmp_path, monkeypatch):
    """A learned draw whose registration map's mesh is far off the part (here: said to be 3.4 % off) leaves the
    rest of its pull-back until the later draws have theirs (:func:`polycubenet.policy.defers`); the rest then
    runs as a stage of its own, with its own file next to the map's, and its mesh is the one exported.  The
    second draw is the part's sidecar labelled as learned (the tiny model's draws are rejected at extraction)."""
    _fake_sources(monkeypatch)
    real_make_source = library.make_source

    def second_draw_is_the_sidecar(kind, part_path, transform, **model):
        if kind == "learned+1":
            return _sidecar_as("learned", part_path, transform)
        return real_make_source(kind, part_path, transform, **model)

    monkeypatch.setattr(library, "make_source", second_draw_is_the_sidecar)
    real_quality, seen = library.pullback_quality, []

    def quality(path):
        seen.append(Path(path).name)
        q = real_quality(path)
        return {**q, "hausdorff": 0.034} if len(seen) == 1 else q  # the second draw's map: far off

    monkeypatch.setattr(library, "pullback_quality", quality)
    state, res = _mesh([part_lib / f"synth-{GOOD[0]}.stl"], tmp_path / "out", polycube="auto",
                       checkpoint=str(tiny_checkpoint), steps=2)
    assert state.is_completed()
    row = res["rows"][0]
    assert row["status"] == "meshed" and row["provenance"] == "learned", row
    # the map's file, then (after the third and fourth draws, rejected at extraction) the rest's
    assert len(seen) == 2 and seen[1] == seen[0].replace(".npz", "-rest.npz")
    assert "learned (draw 3, 1 step, seed +1) polycube rejected at extract" in row["fallback"]
    assert "learned (draw 2" not in row["fallback"]
    rest = next((tmp_path / "out" / ".work").rglob("pullback-*-rest.npz"))
    assert library.HexMesh.load(rest).meta["valid"]


def _sidecar_as(provenance: str, part_path, transform):
    """A polycube source giving the part's ground-truth sidecar, labelled with ``provenance``."""
    src = library.SidecarOracle(library.sidecar_path(part_path), transform)

    def source(sample, V, F, config):
        cloud = src(sample, V, F, config)
        cloud.meta["provenance"] = provenance
        return cloud

    return source


def _fake_sources(monkeypatch):
    """``classical``: the part's sidecar relabelled (fast); ``voxel``: gives up."""
    real_make_source = library.make_source

    def fake_make_source(kind, part_path, transform, **model):
        if kind == "classical":
            return _sidecar_as("classical", part_path, transform)
        if kind == "voxel":
            def voxel(sample, V, F, config):
                raise PolycubeError("no voxel polycube in this test")

            return voxel
        return real_make_source(kind, part_path, transform, **model)

    monkeypatch.setattr(library, "classical_available", lambda: True)
    monkeypatch.setattr(library, "make_source", fake_make_source)


def _scripted_quality(monkeypatch, script):
    """The flow's view of each pulled-back mesh, in order (a real mesh is valid here; these force
    the invalid-mesh path)."""
    seen = []

    def quality(path):
        seen.append(path)
        return script[len(seen) - 1]

    monkeypatch.setattr(library, "pullback_quality", quality)
    return seen


def test_invalid_mesh_falls_back_to_the_next_source(prefect_harness, part_lib, tmp_path, monkeypatch):
    """A source whose pulled-back mesh is not valid is left for the next; the next one's valid mesh is
    exported and the row says why the first was left."""
    _fake_sources(monkeypatch)
    seen = _scripted_quality(monkeypatch, [{"valid": False, "sj_min": -0.3}, {"valid": True, "sj_min": 0.2}])
    state, res = _mesh([part_lib / f"synth-{GOOD[0]}.stl"], tmp_path / "out", fallback=True)
    assert state.is_completed() and len(seen) == 2 and seen[0] != seen[1]
    row = res["rows"][0]
    assert row["status"] == "meshed" and row["provenance"] == "classical"
    assert row["fallback"] == ("pullback: the oracle polycube's hex mesh is not valid "
                               "(minimum scaled Jacobian -0.300)")
    assert row["timings"]["rejected_pullback"] > 0 and row["timings"]["pullback"] > 0
    assert row["keys"]["pullback"] in seen[1]


def test_when_every_source_fails_the_best_invalid_mesh_is_exported(prefect_harness, part_lib, tmp_path, monkeypatch):
    """oracle: not valid (-0.1); classical: worse (-0.4); voxel: rejected -> the oracle mesh is exported,
    marked by every reason."""
    _fake_sources(monkeypatch)
    seen = _scripted_quality(monkeypatch, [{"valid": False, "sj_min": -0.1}, {"valid": False, "sj_min": -0.4}])
    state, res = _mesh([part_lib / f"synth-{GOOD[0]}.stl"], tmp_path / "out", fallback=True)
    assert state.is_completed() and len(seen) == 2
    row = res["rows"][0]
    assert row["status"] == "meshed" and row["provenance"] == "oracle"
    assert row["keys"]["pullback"] in seen[0]
    reasons = row["fallback"].split("; ")
    assert reasons[0].startswith("pullback: the oracle polycube's hex mesh is not valid (minimum scaled Jacobian -0.100)")
    assert reasons[1].startswith("pullback: the classical polycube's hex mesh is not valid (minimum scaled Jacobian -0.400)")
    assert reasons[2].startswith("voxel polycube rejected at polycube: no voxel polycube in this test")
    assert (tmp_path / "out" / f"synth-{GOOD[0]}" / "hex.vtu").is_file()


def test_a_finer_voxel_polycube_is_tried_and_its_own_stages_exported(prefect_harness, part_lib, tmp_path, monkeypatch):
    """oracle and classical not valid, the voxel mesh valid but under the bar: the flow makes ``voxel+1``
    (its own cache keys and stage files) and exports it; ``voxel+2`` is never made."""
    made = []
    real_make_source = library.make_source

    def fake_make_source(kind, part_path, transform, **model):
        if kind.startswith("voxel") or kind == "classical":
            src = library.SidecarOracle(library.sidecar_path(part_path), transform)

            def relabelled(sample, V, F, config):
                made.append(kind)
                cloud = src(sample, V, F, config)
                cloud.meta["provenance"] = "voxel" if kind.startswith("voxel") else kind
                return cloud

            return relabelled
        return real_make_source(kind, part_path, transform, **model)

    monkeypatch.setattr(library, "classical_available", lambda: True)
    monkeypatch.setattr(library, "make_source", fake_make_source)
    seen = _scripted_quality(monkeypatch, [{"valid": False, "sj_min": -0.3}, {"valid": False, "sj_min": -0.4},
                                           {"valid": True, "sj_min": 0.1}, {"valid": True, "sj_min": 0.35}])
    state, res = _mesh([part_lib / f"synth-{GOOD[0]}.stl"], tmp_path / "out", fallback=True)
    assert state.is_completed() and len(seen) == 4 and len(set(seen)) == 4
    assert made == ["classical", "voxel", "voxel+1"]
    row = res["rows"][0]
    assert row["status"] == "meshed" and row["provenance"] == "voxel"
    assert row["keys"]["pullback"] in seen[3]
    reasons = row["fallback"].split("; ")
    assert reasons[2] == ("pullback: the voxel polycube's hex mesh is valid but its minimum scaled Jacobian 0.100 "
                          "is under 0.2: the next polycube was tried and the better mesh kept")
    assert len(reasons) == 3


@pytest.mark.slow
def test_real_dask_cluster_survives_a_killed_worker(prefect_harness, tmp_path):
    """A ``dask scheduler`` and two ``dask worker`` processes on localhost; the flow meshes a folder
    through ``--dask-address``; one worker (nanny and process) is killed with SIGKILL while it runs a
    part.  Its task is rescheduled on the other worker and every part still finishes."""
    from distributed import Client
    from prefect.settings import PREFECT_API_URL

    from flows.runners import make_runner

    drop = tmp_path / "drop"
    library.write_synthetic_parts(drop, [*GOOD, 9007])
    sched_file = tmp_path / "scheduler.json"
    env = {**os.environ, "PREFECT_API_URL": PREFECT_API_URL.value(), "PYTHONPATH": str(ROOT),
           "OMP_NUM_THREADS": "1", "PREFECT_LOGGING_LEVEL": "WARNING"}
    common = dict(cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--scheduler-file",
                               str(sched_file), "--port", "0", "--dashboard-address", ":0"], **common)]
    try:
        deadline = time.time() + 60
        while not sched_file.exists() and time.time() < deadline:
            time.sleep(0.2)
        for _ in range(2):
            procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                           str(sched_file), "--nthreads", "1", "--dashboard-address", ":0"], **common))
        client = Client(scheduler_file=str(sched_file), timeout=60)
        client.wait_for_workers(2, timeout=120)
        address = client.scheduler.address
        nanny_of = {addr: ppid for addr, ppid in client.run(os.getppid).items()}
        pid_of = client.run(os.getpid)

        killed = {}

        def kill_first_busy_worker():
            end = time.time() + 240
            while time.time() < end and not killed:
                for addr, keys in client.processing().items():
                    if keys and addr in pid_of:
                        for pid in (pid_of[addr], nanny_of[addr]):
                            with contextlib.suppress(ProcessLookupError):
                                os.kill(pid, signal.SIGKILL)
                        killed[addr] = list(keys)
                        return
                time.sleep(0.05)

        import contextlib
        import threading

        killer = threading.Thread(target=kill_first_busy_worker, daemon=True)
        killer.start()
        state, res = _mesh([drop], tmp_path / "out", runner=make_runner(address=address))
        killer.join(timeout=5)
        assert killed, "no worker was ever busy"
        assert state.is_completed() and res["counts"] == {"meshed": 3, "failed": 0}, [r["error"] for r in res["rows"]]
        assert len(client.scheduler_info()["workers"]) == 1  # the killed one stayed dead: the other did the rest
        client.close()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait(timeout=30)


@pytest.mark.slow
def test_cli_batch_of_bad_and_awkward_files_gives_one_clear_row_each(prefect_harness, part_lib, tmp_path, capsys):
    """The whole bad-input corpus (every file that needs no special load option), plus parts a user
    expects to mesh -- two synthetic parts, a tet mesh, a STEP of two touching solids, an inside-out and
    an unwelded (duplicate-vertex) surface -- in one CLI batch: exit 0, one manifest row per file, a named error (never a
    traceback) for each bad file, a valid mesh for each good one."""
    import bad_inputs
    import meshio

    from flows.cli import main
    from polycubenet.io import gmsh_session

    drop = tmp_path / "drop"
    # (a file that does not exist is a usage error of the command, tested elsewhere)
    bad = [p for p, _, _ in bad_inputs.make_corpus(drop / "bad") if not bad_inputs.load_kwargs(p) and p.exists()]
    good = [shutil.copy(part_lib / f"synth-{s}.stl", drop / f"synth-{s}.stl") for s in GOOD]
    with gmsh_session() as gmsh:
        gmsh.model.add("tets")
        gmsh.model.occ.addBox(0, 0, 0, 40, 20, 10)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMax", 5.0)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(drop / "tet_box.msh"))
        gmsh.model.remove()
        gmsh.model.add("touching")
        gmsh.model.occ.addBox(0, 0, 0, 30, 20, 10)
        gmsh.model.occ.addBox(30, 0, 0, 20, 20, 25)
        gmsh.model.occ.synchronize()
        gmsh.write(str(drop / "two_solids.step"))
        gmsh.model.remove()
    m = meshio.read(drop / "tet_box.msh")
    meshio.Mesh(m.points, [("tetra", m.cells_dict["tetra"])]).write(drop / "tet_box.mesh")
    (drop / "tet_box.msh").unlink()
    good += [drop / "tet_box.mesh", drop / "two_solids.step"]
    repair_dir = drop / "repairable"
    repairable = {p.name: p for p, _, _ in bad_inputs.make_repairable(repair_dir)}
    good += [repairable["inside_out.stl"], repairable["duplicate_vertices.obj"]]
    files = [str(p) for p in bad + good]
    out = tmp_path / "out"
    rc = main(["mesh", *files, "-o", str(out), "--polycube", "classical", "--runner", "threads", "--workers", "2",
               "--points", "2048", "--polycube-points", "4096", "--hexes", "600"])
    text = capsys.readouterr()
    assert rc == 0
    assert "Traceback" not in text.out + text.err
    rows = library.read_manifest(out)["parts"]
    assert len(rows) == len(files)
    by_path = {Path(r["path"]).resolve(): r for r in rows}
    for p in bad:
        r = by_path[Path(p).resolve()]
        assert r["status"] == "failed" and re.match(r"^[A-Za-z]+Error: ", r["error"]), (p.name, r["error"])
    for p in good:
        r = by_path[Path(p).resolve()]
        assert r["status"] == "meshed" and r["quality"]["valid"], (Path(p).name, r["error"], r["quality"])
