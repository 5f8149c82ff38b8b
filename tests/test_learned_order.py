"""benchmarks/learned_order.py: the replayed orders spend what the policy they stand for would, and meshes the
parts it would (the replay is how session 86 chose ``policy.FAR_RESTS``)."""
from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import learned_order  # noqa: E402


def _draw(name, a_off, b, b_end, b_off=None, near=False, a_end=False, pre=1.0, a=2.0):
    return {"draw": name, "extract": None, "pre": pre, "a": a, "a_off": a_off, "a_valid": a_off is not None,
            "near": near, "a_end": a_end, "b": b, "b_end": b_end, "b_off": b_off, "b_sj": 0.3}


def _records():
    """Four far draws: the second (3.0 % off) has the rest that ends the chain; the last draw's rest runs at once
    in the policy since no draw follows it."""
    return [_draw("learned", 0.05, 40.0, False, 0.05), _draw("learned+1", 0.03, 10.0, True, 0.008),
            _draw("learned+2", None, 30.0, False, 0.05), _draw("learned+3", 0.04, 20.0, False, 0.05)]


def test_the_policy_order_runs_the_last_draws_rest_then_the_waiting_ones_in_draw_order():
    draws = _records()
    # 4 x (pre + A) = 12, the last draw's rest 20, then learned's 40 and learned+1's 10, which ends it
    assert learned_order.replay(draws, "policy") == (82.0, "B learned+1")
    # closest first: learned+1 (3 %) right after the last draw's rest
    assert learned_order.replay(draws, "closest") == (42.0, "B learned+1")
    assert learned_order.replay(draws, "cap1") == (42.0, "B learned+1")
    # no waiting rest: only the last draw's, which does not end it: the part is lost
    assert learned_order.replay(draws, "cap0") == (32.0, None)
    # learned+1's rest ends the chain at once in the draw-by-draw order
    assert learned_order.replay(draws, "now") == (56.0, "B learned+1")


def test_same_stops_the_waiting_rests_once_two_ended_equally_far_off():
    draws = [_draw("learned", 0.05, 40.0, False, 0.0479), _draw("learned+1", 0.06, 40.0, False, 0.0479),
             _draw("learned+2", 0.03, 40.0, True, 0.008), _draw("learned+3", 0.05, 40.0, False, 0.0480)]
    # the last draw's rest (4.80 %) and the first waiting one (4.79 %): equally off, the others are left, and with
    # them the one that would have ended the chain
    assert learned_order.replay(draws, "same") == (12.0 + 40.0 + 40.0, None)
    # a near miss's rest is not waiting: it runs whatever the others gave
    draws[2]["near"] = True
    assert learned_order.replay(draws, "same")[1] == "B learned+2"


def test_replay_files_totals_each_order_over_the_records(tmp_path, capsys):
    rec = {"sets": {"x:1": {"parts": [{"part": "p", "draws": _records()}]}}}
    path = tmp_path / "rec.json"
    path.write_text(json.dumps(rec))
    assert learned_order.replay_files([str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    row = dict(zip(learned_order.ORDERS, out[-2].split()[1:]))
    assert row["policy"] == "82/1" and row["cap1"] == "42/1" and row["cap0"] == "32/0"
