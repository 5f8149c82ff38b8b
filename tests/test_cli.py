"""The ``polycubenet`` command line: arguments, exit codes, ``report``, and the training
commands it would run (the commands that mesh are run under the Prefect harness in
tests/test_flows.py)."""

from __future__ import annotations

import json

import pytest

from flows import cli
from polycubenet import library


def _manifest(out, min_sj=None, hausdorff=0.004):
    rows = [
        {"name": "bracket", "path": "/parts/bracket.step", "hash": "a" * 64, "status": "meshed", "stage": "export",
         "error": None, "provenance": "learned", "fallback": None, "timings": {"load_sample": 0.5, "export": 1.25},
         "computed": ["load_sample", "export"], "reused": [], "files": ["hex.vtu", "preview.png"],
         "quality": {"hexes": 4800, "sj_min": 0.31, "sj_avg": 0.93, "valid": True, "hausdorff": hausdorff,
                     "warnings": ["The part has walls about 0.27 thick (0.31% of the diagonal) over 5.9% of its surface."]}},
        {"name": "crushed", "path": "/parts/crushed.stl", "hash": "b" * 64, "status": "failed", "stage": "load_sample",
         "error": "OpenBoundaryError: /parts/crushed.stl: 12 boundary edges", "provenance": None, "fallback": None,
         "timings": {}, "computed": [], "reused": [], "files": [], "quality": None},
    ]
    (out / "bracket").mkdir(parents=True)
    (out / "bracket" / "preview.png").write_bytes(b"\x89PNG\r\n")
    config = {} if min_sj is None else {"config": {"min_sj": min_sj}}
    library.write_manifest(out, rows, parameters={"formats": ["vtu"], **config})
    return rows


def test_report_rebuilds_html_and_prints_the_table(tmp_path, capsys):
    _manifest(tmp_path)
    assert cli.main(["report", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    lines = [ln for ln in text.splitlines() if ln.startswith(("bracket", "crushed"))]
    assert len(lines) == 2 and "4800" in lines[0] and "0.93" in lines[0]
    assert "OpenBoundaryError" in lines[1] and "load_sample" in lines[1]
    assert "2 parts: 1 meshed (0 of them flagged invalid: see quality.json), 1 failed" in text
    html = (tmp_path / "report.html").read_text()
    assert "bracket/preview.png" in html and "crushed" in html and "12 boundary edges" in html
    assert "crushed/preview.png" not in html  # no pictures for a failed part


@pytest.mark.parametrize("bar, under", [(0.2, False), (0.35, True), (None, False)])
def test_a_part_meshed_under_the_runs_quality_bar_is_marked(tmp_path, capsys, bar, under):
    """The run's quality bar (its manifest's min_sj) marks a valid part under it in the report and the summary."""
    _manifest(tmp_path, min_sj=bar)
    assert cli.main(["report", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    html = (tmp_path / "report.html").read_text()
    row = next(ln for ln in html.splitlines() if ">bracket</a>" in ln)
    assert ("class='warn'" in row) == under and ("class='ok'" in row) == (not under)
    assert ("1 valid but under the quality bar (SJ min < 0.35)" in html) == under
    assert ("1 valid but under the quality bar (SJ min < 0.35)" in text) == under


@pytest.mark.parametrize("hausdorff, off", [(0.004, False), (0.0100, False), (0.082, True), (None, False)])
def test_a_valid_part_meshed_off_its_surface_is_marked(tmp_path, capsys, hausdorff, off):
    """A valid mesh farther from the part than the Hausdorff bar (1 % of the diagonal: the best any source gave, kept)
    is marked in the report and counted in the summary, as a part under the quality bar is; one within it, or
    without the measure, is not."""
    _manifest(tmp_path, min_sj=0.2, hausdorff=hausdorff)
    assert cli.main(["report", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    html = (tmp_path / "report.html").read_text()
    row = next(ln for ln in html.splitlines() if ">bracket</a>" in ln)
    assert ("class='warn'" in row) == off and ("class='ok'" in row) == (not off)
    said = "1 valid but off the part (Hausdorff > 1 % of the diagonal)"
    assert (said in html) == off and (said in text) == off
    assert "walls about 0.27 thick" in html  # the part's quality warnings head its section
    assert "under the quality bar" not in text


def test_usage_errors_exit_2_without_running_anything(tmp_path, capsys):
    assert cli.main(["report", str(tmp_path)]) == 2
    assert cli.main(["retry", str(tmp_path)]) == 2
    assert cli.main(["mesh", str(tmp_path / "nope"), "-o", str(tmp_path / "out")]) == 2
    (tmp_path / "empty").mkdir()
    assert cli.main(["mesh", str(tmp_path / "empty"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "nope" in err and "no parts found" in err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SystemExit) as exc:
        cli.main(["mesh", "x.stl", "-o", "o", "--size", "0.02", "--hexes", "100"])
    assert exc.value.code == 2


def test_mesh_options_map_to_flow_arguments():
    a = cli._parser().parse_args(["mesh", "p", "-o", "o", "--size", "0.03", "--formats", "vtu, inp,bdf",
                                  "--polycube", "oracle", "--no-fallback", "--points", "2048", "--work", "w"])
    kw = cli._mesh_kwargs(a)
    assert kw["target_size"] == 0.03 and kw["target_hexes"] is None
    assert kw["formats"] == ["vtu", "inp", "bdf"] and kw["polycube"] == "oracle" and kw["fallback"] is False
    assert kw["n_sample"] == 2048 and kw["work"] == "w" and "checkpoint" not in kw
    b = cli._parser().parse_args(["mesh", "p", "-o", "o", "--hexes", "800"])
    assert cli._mesh_kwargs(b)["target_hexes"] == 800 and "target_size" not in cli._mesh_kwargs(b)
    assert "min_sj" not in cli._mesh_kwargs(b)  # the flow's default bar
    c = cli._parser().parse_args(["mesh", "p", "-o", "o", "--min-sj", "0.3"])
    assert cli._mesh_kwargs(c)["min_sj"] == 0.3


@pytest.mark.parametrize("argv, polycube, fallback", [
    ([], "learned", True),                                   # auto is the default: the model, then classical
    (["--polycube", "auto"], "learned", True),
    (["--polycube", "auto", "--no-fallback"], "learned", False),
    (["--polycube", "learned"], "learned", False),           # the model's polycube only
    (["--polycube", "classical"], "classical", False),
])
def test_polycube_policy_maps_to_source_and_fallback(argv, polycube, fallback):
    kw = cli._mesh_kwargs(cli._parser().parse_args(["mesh", "p", "-o", "o", *argv]))
    assert (kw["polycube"], kw["fallback"]) == (polycube, fallback)


def test_train_commands_use_torchrun_for_several_gpus(tmp_path):
    from flows.train import train_steps

    one = train_steps("d", str(tmp_path), "h", steps=10, preset="cpu", batch=None, points=256, nproc=1,
                      resume=True, eval_count=5, eval_steps=4)
    assert one["train"][1:3] == ["-m", "polycubenet.train"] and "--no-resume" not in one["train"]
    assert one["train"][one["train"].index("--points") + 1] == "256"
    assert one["train"][one["train"].index("--out") + 1] == str(tmp_path)
    four = train_steps("d", str(tmp_path), "h", steps=10, preset="paper", batch=64, points=None, nproc=4,
                       resume=False, eval_count=5, eval_steps=None)
    assert four["train"][1:3] == ["-m", "torch.distributed.run"] and "--nproc_per_node=4" in four["train"]
    assert four["train"][-1] == "--no-resume" and "--points" not in four["train"]
    ev = four["evaluate"]
    assert ev[ev.index("--checkpoint") + 1] == str(tmp_path / "last.pt")
    assert ev[ev.index("--publish") + 1] == str(tmp_path / "published.pt")


def test_publish_writes_checkpoint_and_metrics_together(tmp_path):
    from tasks.train import publish

    ck, metrics = tmp_path / "published.pt", tmp_path / "metrics.json"
    ck.write_bytes(b"weights" * 100)
    metrics.write_text(json.dumps({"chamfer": 0.012, "structure_ok": 0.8, "rows": [1, 2, 3]}))
    res = publish.fn(str(ck), str(metrics), str(tmp_path / "pub"), "polycubenet-cpu-1")
    pub = tmp_path / "pub"
    assert (pub / "polycubenet-cpu-1.pt").read_bytes() == ck.read_bytes() == (pub / "latest.pt").read_bytes()
    body = json.loads((pub / "latest.json").read_text())
    assert body["checkpoint"] == "polycubenet-cpu-1.pt" and body["metrics"] == {"chamfer": 0.012, "structure_ok": 0.8}
    assert res["summary"]["chamfer"] == 0.012 and not list(pub.glob(".tmp-*"))


def test_leave_keeps_the_exit_code_where_native_destructors_would_abort(tmp_path):
    # open3d used in one worker thread, then gmsh first loaded in another: at the normal exit libEGL's
    # destructor aborts (rc 134) although the work is done; the console script ends through leave()
    import subprocess
    import sys
    import textwrap

    body = textwrap.dedent("""
        import threading
        import numpy as np
        import trimesh

        m = trimesh.creation.icosphere(3)
        V, F = np.asarray(m.vertices), np.asarray(m.faces)

        def raycast():  # the library (and open3d) first imported in a worker thread, as in the flow
            from polycubenet import pullback

            pullback._closest(pullback._scene(V, F), np.zeros((3, 3)))

        for fn in (raycast, lambda: __import__("gmsh")):
            t = threading.Thread(target=fn)
            t.start()
            t.join()
        print("done")
    """)
    script = tmp_path / "leave.py"
    script.write_text(body + "from flows.cli import leave\nleave(3)\n")
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 3 and r.stdout.strip() == "done", (r.returncode, r.stderr[-500:])
