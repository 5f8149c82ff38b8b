"""benchmarks/learned_meshes.py: the comparison against the baseline checkpoint."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import pytest  # noqa: E402
from learned_meshes import summary  # noqa: E402
from unseen_parts import parse_draws  # noqa: E402


def _row(ok, seconds):
    return [ok, 0.3 if ok else None, 1 if ok else None, seconds, 0.005, None, "registration"]


def _fake_jobs(monkeypatch, module, outcome, field: str) -> list:
    """Replace ``module._job`` by ``outcome(job as a dict) -> row``; returns the (arm, part, job[field]) it saw."""
    seen = []
    keys = ("arm", "checkpoint", "path", "steps", "draws", "mend_moves", "own", "sheets", "strips", "hexes")

    def fake_job(job):
        d = dict(zip(keys, job, strict=True))
        d["name"] = Path(d["path"]).stem
        seen.append((d["arm"], d["name"], d[field]))
        return d["arm"], d["name"], outcome(d)

    monkeypatch.setattr(module, "_job", fake_job)
    return seen


def test_summary_counts_gains_and_losses_against_the_first_checkpoint():
    # one arm per entry: the same checkpoint may come twice (with two tables of draws)
    result = [
        {"a": _row(True, 1.0), "b": _row(True, 2.0), "c": _row(False, 3.0)},
        {"a": _row(True, 1.5), "b": _row(False, 2.5), "c": _row(True, 3.5)},
    ]
    rows = summary(["base", "new"], ["same.pt", "same.pt"], result, ["4/0/n/-,1/1/y/-", "default"])
    assert [(r["name"], r["meshed"], r["parts"]) for r in rows] == [("base", 2, 3), ("new", 2, 3)]
    assert rows[0]["gained"] == [] and rows[0]["lost"] == []
    assert rows[1]["gained"] == ["c"] and rows[1]["lost"] == ["b"]
    assert rows[1]["seconds"] == 7.5
    assert [r["draws"] for r in rows] == ["4/0/n/-,1/1/y/-", "default"]


def test_draw_tables_parse_like_the_policys():
    from polycubenet.policy import LEARNED_DRAWS

    assert parse_draws("default") is None
    assert parse_draws("4/0/n/-,1/1/y/-,1/0/y/-/even,1/1/y/-/even,4/1/y/-/even") == LEARNED_DRAWS == (
        (4, 0, False, None), (1, 1, True, None), (1, 0, True, None, "even"), (1, 1, True, None, "even"),
        (4, 1, True, None, "even"))
    assert parse_draws("1/1/y/z") == ((1, 1, True, "z"),) and parse_draws("1/1/y/z/uniform") == ((1, 1, True, "z", "uniform"),)
    for bad in ("4/0/n", "4/0/maybe/-", "4/0/n/w", "4/0/n/-/1", "4/0/n/-/even/x"):
        with pytest.raises(ValueError):
            parse_draws(bad)


def test_misses_only_runs_the_later_arms_on_the_first_arms_misses(monkeypatch):
    import learned_meshes

    ran = []

    def fake_job(job):
        arm, ck, path, steps, draws, mend_moves, own, sheets, strips, hexes = job
        assert own is None and strips is None and hexes == 3000
        name = Path(path).stem
        ran.append((arm, name, mend_moves))
        ok = name == "a" or (mend_moves == 3 and name == "c")
        return arm, name, _row(ok, 1.0)

    monkeypatch.setattr(learned_meshes, "_job", fake_job)
    parts = [Path(f"/x/{n}.step") for n in "abc"]
    out = learned_meshes.compare(["m.pt", "m.pt"], parts, mends=[0, 3], misses_only=True)
    assert sorted(n for arm, n, _ in ran if arm == 1) == ["b", "c"]  # not a: the first arm meshed it
    assert out[1]["a"][-1] == "baseline" and out[1]["c"][0] and not out[1]["b"][0]
    rows = summary(["bare", "mend"], ["m.pt", "m.pt"], out)
    assert rows[1]["gained"] == ["c"] and rows[1]["lost"] == [] and rows[1]["meshed"] == 2
    ran.clear()
    learned_meshes.compare(["m.pt", "m.pt"], parts, mends=[0, 3])
    assert len(ran) == 6


def test_the_own_structure_arm_is_passed_on_and_its_meshes_on_the_part_s_structure_are_counted(monkeypatch):
    import learned_meshes

    def outcome(job):
        row = _row(job["name"] == "a" or (job["own"] and job["name"] == "b"), 1.0)
        if job["own"] and job["name"] == "b":
            row[6] = "exact, part's structure"
        return row

    seen = _fake_jobs(monkeypatch, learned_meshes, outcome, "own")
    parts = [Path(f"/x/{n}.step") for n in "ab"]
    out = learned_meshes.compare(["m.pt", "m.pt"], parts, misses_only=True, owns=[False, True])
    assert sorted(seen) == [(0, "a", False), (0, "b", False), (1, "b", True)]
    rows = summary(["off", "on"], ["m.pt", "m.pt"], out, owns=[False, True])
    assert [(r["meshed"], r["part_structure"], r["own_structure"]) for r in rows] == [(1, 0, False), (2, 1, True)]
    assert rows[1]["gained"] == ["b"]


def test_the_mesh_size_reaches_every_job(monkeypatch):
    import learned_meshes

    seen = _fake_jobs(monkeypatch, learned_meshes, lambda d: _row(True, 1.0), "hexes")
    parts = [Path(f"/x/{n}.step") for n in "ab"]
    learned_meshes.compare(["m.pt", "n.pt"], parts, hexes=5000)
    assert sorted(seen) == [(0, "a", 5000), (0, "b", 5000), (1, "a", 5000), (1, "b", 5000)]
    seen.clear()
    learned_meshes.compare(["m.pt"], parts)
    assert [h for _, _, h in seen] == [3000, 3000]  # the series' size unless told


def test_the_sheets_arm_reaches_each_job_and_the_summary(monkeypatch):
    import learned_meshes

    seen = _fake_jobs(monkeypatch, learned_meshes,
                      lambda job: _row(job["name"] == "a" or (job["sheets"] is not False and job["name"] == "b"), 1.0),
                      "sheets")
    parts = [Path(f"/x/{n}.step") for n in "ab"]
    out = learned_meshes.compare(["m.pt", "m.pt"], parts, sheets=[None, False])
    assert sorted(seen) == [(0, "a", None), (0, "b", None), (1, "a", False), (1, "b", False)]
    rows = summary(["on", "off"], ["m.pt", "m.pt"], out, sheets=[None, False])
    assert [(r["meshed"], r["sheets"]) for r in rows] == [(2, None), (1, False)] and rows[1]["lost"] == ["b"]


def test_the_strips_arm_reaches_each_job_and_the_summary(monkeypatch):
    import learned_meshes

    seen = _fake_jobs(monkeypatch, learned_meshes,
                      lambda job: _row(job["name"] == "a" or (job["strips"] is True and job["name"] == "b"), 1.0),
                      "strips")
    parts = [Path(f"/x/{n}.step") for n in "ab"]
    out = learned_meshes.compare(["m.pt", "m.pt"], parts, strips=[False, True])
    assert sorted(seen) == [(0, "a", False), (0, "b", False), (1, "a", True), (1, "b", True)]
    rows = summary(["off", "on"], ["m.pt", "m.pt"], out, strips=[False, True])
    assert [(r["meshed"], r["strips"]) for r in rows] == [(1, False), (2, True)] and rows[1]["gained"] == ["b"]


def test_files_are_run_alone_by_their_stems_and_stems_must_differ(monkeypatch, tmp_path):
    """``--files`` runs the named mesh files (no unseen sets unless ``--sets`` is given), each part named by its
    stem; two files with one stem, or a missing file, are refused before anything runs."""
    import json

    import learned_meshes
    import unseen_parts

    from polycubenet.inference import DEFAULT_CHECKPOINT

    def no_sets(*a, **k):
        raise AssertionError("no unseen set is built when only --files are given")

    monkeypatch.setattr(unseen_parts, "make_parts", no_sets)
    seen = _fake_jobs(monkeypatch, learned_meshes, lambda d: _row(d["name"] == "gusset_s1", 1.0), "path")
    a, b = tmp_path / "gusset_s1.step", tmp_path / "gusset_s2.step"
    for f in (a, b):
        f.write_text("not read: the job is replaced")
    out = tmp_path / "lm.json"
    ck = str(DEFAULT_CHECKPOINT)
    assert learned_meshes.main(["--checkpoints", ck, "--files", str(a), str(b), "--json", str(out)]) == 0
    assert sorted(name for _, name, _ in seen) == ["gusset_s1", "gusset_s2"]
    rec = json.loads(out.read_text())
    assert rec["sets"] == [] and rec["summary"][0]["meshed"] == 1 and rec["summary"][0]["parts"] == 2
    (tmp_path / "other").mkdir()
    twin = tmp_path / "other" / "gusset_s1.step"
    twin.write_text("x")
    for files in ([str(a), str(twin)], [str(a), str(tmp_path / "missing.step")]):
        seen.clear()
        with pytest.raises(SystemExit):
            learned_meshes.main(["--checkpoints", ck, "--files", *files, "--json", str(out)])
        assert seen == []
