"""benchmarks/continue_curve.py and its line in benchmarks/plot_learning_curve.py."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import plot_learning_curve  # noqa: E402
from continue_curve import point, select  # noqa: E402


def _meta(commit, hours):
    return {"commit": commit, "step": 100, "cpu_hours": hours, "gpu_hours": 0.62}


def test_select_keeps_versions_a_gap_apart_and_skips_those_already_measured():
    metas = [_meta("a", 20.0), _meta("b", 20.3), _meta("c", 20.6), _meta("d", 21.0), _meta("e", 21.2)]
    assert [m["commit"] for m in select(metas, set(), 0.5)] == ["a", "c", "e"]
    # a point already in the curve is not measured again but still spaces the next one
    assert [m["commit"] for m in select(metas, {"a", "c"}, 0.5)] == ["e"]
    assert [m["commit"] for m in select(metas, set(), 0.0)] == ["a", "b", "c", "d", "e"]


def test_point_takes_evaluates_summary_fields():
    rows = [
        {"genus": 0, "genus_match": True, "label_accuracy": 0.99},
        {"genus": 2, "genus_match": False, "label_accuracy": 0.98},
        {"genus": 3, "genus_match": False, "label_accuracy": 0.97},
        {"genus": 1, "genus_match": True, "label_accuracy": 0.96},
    ]
    res = {"rows": rows, "steps": 1, "n_out": 4096, "chamfer_median": 0.0066, "chamfer_identity_median": 0.0113,
           "exact_structure_rate": 0.5, "genus_match_rate_genus_le2": 2 / 3, "label_accuracy_median": 0.975}
    p = point(_meta("f" * 40, 55.31), res)
    assert p["genus_match_genus_le2"] == 2 / 3  # evaluate's figure over the genus <= 2 pairs
    assert p["pairs"] == 4 and p["exact"] == 0.5 and p["cpu_hours"] == 55.31
    assert abs(p["label_accuracy"] - 0.975) < 1e-9


#: one point of the shipped file's curve (``learning_curve.jsonl``)
SHIPPED = {"checkpoint": "polycubenet-cpu.pt", "cpu_hours": 21.0, "gpu_hours": 0.62, "steps": 1,
           "chamfer_median": 0.0065, "chamfer_identity": 0.0113, "exact": 0.63, "genus_match_genus_le2": 0.98,
           "parts_accepted": 7, "parts": 10, "anchored": True}


def _plot(tmp_path, capsys, cont: list[dict], feat: list[dict], slant: list[dict] | None = None) -> str:
    """Run the plot on the shipped point and these continue / feature / slant-moves points (an empty list: no
    file); its printout."""
    files = {}
    for name, pts in (("curve", [SHIPPED]), ("cont", cont), ("feat", feat), ("slant", slant or [])):
        files[name] = tmp_path / f"{name}.jsonl"
        if pts:
            files[name].write_text("".join(json.dumps(p) + "\n" for p in pts))
    out = tmp_path / "curve.png"
    assert plot_learning_curve.main(["--curve", str(files["curve"]), "--continue-curve", str(files["cont"]),
                                     "--features-curve", str(files["feat"]), "--slant-curve", str(files["slant"]),
                                     "--out", str(out)]) == 0
    assert out.stat().st_size > 0
    return capsys.readouterr().out


def test_plot_prints_and_draws_the_continue_line(tmp_path, capsys):
    cont = [{"commit": c * 40, "checkpoint": "polycubenet-cpu-continue.pt", "step": 1, "cpu_hours": h,
             "gpu_hours": 0.62, "pairs": 100, "steps": 1, "n_out": 4096, "chamfer_median": 0.0066,
             "chamfer_identity": 0.0113, "label_accuracy": 0.997, "exact": e, "genus_match_genus_le2": 0.95}
            for c, h, e in (("b", 55.31, 0.60), ("a", 30.34, 0.62))]
    text = _plot(tmp_path, capsys, cont, [])
    lines = text.split("continue file", 1)[1].splitlines()
    rows = [ln.split() for ln in lines if ln.strip() and ln.split()[0][0].isdigit()]
    assert [r[0] for r in rows] == ["30.34", "55.31"]  # sorted by CPU-hours
    assert rows[1][2] == "bbbbbbbb" and rows[1][6] == "60%"


def test_plot_prints_the_features_line_per_class(tmp_path, capsys):
    """The continue file read on pairs with machined features: one row per version, sorted by CPU-hours, the
    exact rate of each feature class beside the overall one; a class with no pair is a dash."""
    feat = [{"commit": c * 40, "checkpoint": "polycubenet-cpu-continue.pt", "step": 1, "cpu_hours": h,
             "gpu_hours": 0.62, "pairs": 256, "steps": 1, "n_out": 4096, "chamfer_median": 0.009,
             "chamfer_identity": 0.0113, "label_accuracy": 0.98, "exact": e, "genus_match_genus_le2": 0.97,
             "exact_by_feature": by}
            for c, h, e, by in (("d", 58.66, 0.40, {"slanted end": {"pairs": 128, "exact": 0.28, "extracted": 0.9},
                                                    "neither": {"pairs": 33, "exact": 0.64, "extracted": 0.9}}),
                                ("c", 14.82, 0.30, {"slanted end": {"pairs": 128, "exact": 0.15, "extracted": 0.9}}))]
    text = _plot(tmp_path, capsys, [], feat).split("machined features", 1)[1]
    rows = [ln.split() for ln in text.splitlines() if ln.strip() and ln.split()[0][0].isdigit()]
    assert [r[0] for r in rows] == ["14.82", "58.66"]
    assert rows[0][5:] == ["15%", "/128", "-", "-"]  # no chamfer, no neither pair at 14.82
    assert rows[1][5:] == ["28%", "/128", "-", "64%", "/", "33"]


def test_plot_prints_the_slant_moves_line_per_class(tmp_path, capsys):
    """The share of the way slanted faces are moved, per committed version: sorted by CPU-hours, one column per
    feature class (a dash where a class has no pair), then the error left on slanted points."""
    def cls(moved):
        return {"pairs": 128, "moved_median": moved}

    slant = [{"commit": c * 40, "cpu_hours": h, "gpu_hours": 0.62, "pairs": 256, "all": {"err_slanted_median": err},
              "by_feature": by}
             for c, h, err, by in (("f", 62.70, 0.0103, {"slanted end": cls(0.72), "chamfer": cls(0.58)}),
                                   ("e", 14.82, 0.0134, {"slanted end": cls(0.43)}))]
    feat = [{"commit": "e" * 40, "checkpoint": "polycubenet-cpu-continue.pt", "step": 1, "cpu_hours": 14.82,
             "gpu_hours": 0.62, "pairs": 256, "steps": 1, "n_out": 4096, "chamfer_median": 0.009,
             "chamfer_identity": 0.0113, "label_accuracy": 0.98, "exact": 0.3, "genus_match_genus_le2": 0.97,
             "exact_by_feature": {"slanted end": {"pairs": 128, "exact": 0.15, "extracted": 0.9}}}]
    text = _plot(tmp_path, capsys, [], feat, slant).split("share of the way", 1)[1]
    rows = [ln.split() for ln in text.splitlines() if ln.strip() and ln.split()[0][0].isdigit()]
    assert [r[0] for r in rows] == ["14.82", "62.70"]
    assert rows[0][3:] == ["0.43", "-", "-", "0.0134"]
    assert rows[1][3:] == ["0.72", "0.58", "-", "0.0103"]
