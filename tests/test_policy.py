"""The fallback policy on its own (polycubenet/policy.py): order, what leaves a source, what is kept, and
the seconds of the sources left.  The drivers (pipeline, flow) are tested with real stages elsewhere."""

from __future__ import annotations

import pytest

from polycubenet.errors import PartError, PolycubeError
from polycubenet import policy
from polycubenet.policy import (LEARNED_DRAWS, Attempt, draw_anchors, draw_fallbacks, draw_seed, draw_steps, draw_stretch, draw_turn, learned_draws, leaves_source, refinement, run_chain,
                                source_label, source_names)


def _scripted(script: dict):
    """``attempt`` whose outcome per source is ``script[source]``: an exception (raised at the stage in
    its ``stage`` attribute, after 1 s of that stage) or a quality dict."""
    calls = []

    def attempt(src, tracker):
        calls.append(src)
        outcome = script[src]
        tracker.seconds["polycube"] = 1.0
        if isinstance(outcome, BaseException):
            tracker.stage = getattr(outcome, "at", "polycube")
            tracker.seconds[tracker.stage] = tracker.seconds.get(tracker.stage, 0.0) + 1.0
            raise outcome
        tracker.seconds["pullback"] = 2.0
        return Attempt(src, outcome, payload=src, seconds=dict(tracker.seconds))

    return attempt, calls


def _at(exc, stage):
    exc.at = stage
    return exc


VOXELS = ["voxel", "voxel+1", "voxel+2", "voxel+3", "voxel+3*"]


def test_source_order():
    assert source_names("auto") == ["learned", "classical"] + VOXELS
    assert source_names("classical") == ["classical"] + VOXELS and source_names("voxel") == VOXELS
    assert source_names("learned") == ["learned"] and source_names("oracle", fallback=True)[1:] == ["classical"] + VOXELS
    assert source_names("classical", classical=False) == VOXELS
    assert refinement("voxel+2") == ("voxel", 2) and refinement("voxel") == ("voxel", 0)
    assert refinement("classical") == ("classical", 0) and source_label("voxel+1") == "voxel (refinement 1)"
    assert refinement("voxel+3*") == ("voxel", 3) and source_label("voxel+3*") == "voxel (refinement 3, 1.5x hexes)"


def test_the_last_source_partitions_the_finest_voxel_polycube_denser():
    import dataclasses

    from polycubenet.pipeline import PipelineConfig
    from polycubenet.policy import DENSER_HEXES, source_config

    cfg = PipelineConfig(target_hexes=5000)
    assert source_config("voxel+3", cfg) is cfg and source_config("classical", cfg) is cfg
    assert source_config("voxel+3*", cfg).target_hexes == 7500 == round(5000 * DENSER_HEXES)
    sized = dataclasses.replace(cfg, target_size=0.03)
    assert source_config("voxel+3*", sized).target_size == pytest.approx(0.03 / 1.5 ** (1 / 3))
    # tried like a refinement: only after the finest voxel polycube gave a mesh that did not end the chain
    attempt, calls = _scripted({"voxel": {"valid": True, "sj_min": 0.3, "hausdorff": 0.0128},
                                "voxel+1": {"valid": True, "sj_min": 0.3, "hausdorff": 0.0116},
                                "voxel+2": {"valid": True, "sj_min": 0.3, "hausdorff": 0.0117},
                                "voxel+3": {"valid": False, "sj_min": -0.178},
                                "voxel+3*": {"valid": True, "sj_min": 0.3, "hausdorff": 0.0082}})
    out = run_chain(VOXELS, attempt, min_sj=0.2)
    assert calls == VOXELS and out.chosen.source == "voxel+3*"
    assert "voxel (refinement 3) polycube's hex mesh is not valid" in out.fallback_reason
    attempt, calls = _scripted({"voxel": {"valid": True, "sj_min": 0.3, "hausdorff": 0.0128},
                                "voxel+1": {"valid": True, "sj_min": 0.31, "hausdorff": 0.0116},
                                "voxel+2": {"valid": True, "sj_min": 0.3, "hausdorff": 0.0117},
                                "voxel+3": _at(PolycubeError("no finer voxel polycube"), "polycube")})
    out = run_chain(VOXELS, attempt, min_sj=0.2)
    assert calls == VOXELS[:4] and out.chosen.source == "voxel+1"


def test_the_models_further_draws_follow_the_first(monkeypatch):
    # the shipped table: a 4-step draw after a cheaper first, then a one-step draw at another seed, then one as
    # the first but with evenly spread anchors, then evenly spread ones at seed +1 at 1 and 4 steps; after a first
    # draw at 4 steps the 4-step draw at seed +0 would repeat the first (at 4 steps: never fewer than the first),
    # and the two even draws at seed +1 are one draw
    assert LEARNED_DRAWS == ((4, 0, False, None), (1, 1, True, None), (1, 0, True, None, "even"),
                             (1, 1, True, None, "even"), (4, 1, True, None, "even"))
    assert learned_draws(1) == (1, 2, 3, 4, 5) and learned_draws(4) == (2, 3, 4) == learned_draws(8)
    # for a model that takes no anchors the evenly spread draws are the first and the one-step seed +1 again
    assert learned_draws(1, anchored=False) == (1, 2, 5) and learned_draws(4, anchored=False) == (2,)
    assert [draw_fallbacks(f"learned+{k}") for k in range(6)] == [True, False, True, True, True, True]
    assert source_label("learned+2") == "learned (draw 3, 1 step, seed +1)"
    assert source_label("learned+3") == "learned (draw 4, 1 step, even anchors)"
    assert source_label("learned+4") == "learned (draw 5, 1 step, seed +1, even anchors)"
    assert source_label("learned+5") == "learned (draw 6, 4 steps, seed +1, even anchors)"
    assert [draw_anchors(f"learned+{k}") for k in (1, 2, 3, 4, 5)] == ["uniform", "uniform", "even", "even", "even"]
    # a later draw of an earlier one's cloud is tried only when it adds the generator fallbacks the earlier lacked
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((4, 0, False), (4, 0, True), (4, 0, False), (4, 0, True)))
    assert learned_draws(1) == (1, 2) and learned_draws(4) == ()
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((4, 0, True), (4, 0, False), (1, 2, False), (4, 2, True)))
    assert learned_draws(1) == (1, 3, 4) and learned_draws(4) == (3, 4) and learned_draws(2) == (1, 3, 4)
    # a draw of the part turned (measured in session 36, not in the table): named so, and at the first's steps
    # and seed it is not a repeat of the first
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((1, 0, True, "x"), (1, 0, True, None), (1, 1, True, "z")))
    assert [draw_turn(s) for s in ("learned", "learned+1", "learned+2", "learned+3")] == [None, "x", None, "z"]
    assert learned_draws(1) == (1, 3) and source_label("learned+1") == "learned (draw 2, 1 step, turned about x)"
    assert source_label("learned+3") == "learned (draw 4, 1 step, seed +1, turned about z)"
    # a draw with evenly spread anchors: at the first's steps and seed it is not a repeat of the first either
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((1, 0, True, None, "even"), (1, 0, True, None, "uniform")))
    assert [draw_anchors(s) for s in ("learned", "learned+1", "learned+2")] == ["uniform", "even", "uniform"]
    assert learned_draws(1) == (1,) == learned_draws(4)  # the uniform one repeats the first
    assert source_label("learned+1") == "learned (draw 2, 1 step, even anchors)"
    # a draw of the part stretched along the axes: not a repeat of the same draw unstretched, nor of one
    # stretched another way; named with its exponent
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((1, 0, True, None, "even"), (1, 0, True, None, "even", 0.5),
                                                  (1, 0, True, None, "even", -0.4), (1, 0, True, None, "even", 0.5),
                                                  (1, 0, True, None, "uniform", 0.0)))
    assert [draw_stretch(f"learned+{k}") for k in range(6)] == [None, None, 0.5, -0.4, 0.5, None]
    assert learned_draws(1) == (1, 2, 3)  # the fourth repeats the second, the fifth (no stretch) the first
    assert source_label("learned+2") == "learned (draw 3, 1 step, even anchors, stretched +0.5)"
    assert source_label("learned+3") == "learned (draw 4, 1 step, even anchors, stretched -0.4)"
    # a longer table: never with fewer steps than the first, never repeating the first
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((4, 0, False), (4, 1, False), (4, 2, False)))
    assert learned_draws(1) == (1, 2, 3) and learned_draws(4) == (2, 3) and learned_draws("stride4") == ()
    assert [draw_steps(f"learned+{k}", 1) for k in (1, 2, 3)] == [4, 4, 4] and draw_steps("learned", 1) == 1
    assert draw_steps("learned+2", 8) == 8 and learned_draws(8) == (2, 3)  # a run at 8 steps: 8-step draws
    assert [draw_seed(f"learned+{k}") for k in (1, 2, 3)] == [0, 1, 2] and draw_seed("learned") == 0
    assert source_names("auto", draws=(1, 2)) == ["learned", "learned+1", "learned+2", "classical"] + VOXELS
    assert source_names("learned", draws=(2, 3)) == ["learned", "learned+2", "learned+3"]
    assert source_names("oracle", fallback=True, draws=(1,))[:2] == ["oracle", "classical"]
    assert source_names("classical", draws=(1,)) == ["classical"] + VOXELS
    assert source_label("learned+1") == "learned (draw 2, 4 steps)"
    assert source_label("learned+3") == "learned (draw 4, 4 steps, seed +2)"
    # the second draw is a learned attempt: any of its errors hands the part on, like the first's
    assert leaves_source("learned+1", RuntimeError("CUDA error")) and not leaves_source("classical", KeyError("bug"))
    assert not leaves_source("learned+1", PartError("p.stl", "not closed"))
    attempt, calls = _scripted({"learned": _at(PolycubeError("genus 0, part 2"), "extract"),
                                "learned+1": {"valid": True, "sj_min": 0.4}, "classical": {"valid": True}})
    out = run_chain(source_names("auto", draws=(1, 2)), attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1"] and out.chosen.source == "learned+1"
    assert out.fallback_reason.startswith("learned polycube rejected at extract")
    # the third draw only when the two before were both rejected before a mesh
    attempt, calls = _scripted({"learned": _at(PolycubeError("cloud far"), "extract"),
                                "learned+1": _at(PolycubeError("genus 1, part 2"), "extract"),
                                "learned+2": {"valid": True, "sj_min": 0.5}, "classical": {"valid": True}})
    out = run_chain(source_names("auto", draws=(1, 2)), attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+2"] and out.chosen.source == "learned+2"


def test_first_valid_mesh_is_kept_and_later_sources_are_not_tried():
    attempt, calls = _scripted({"learned": {"valid": True, "sj_min": 0.3}, "classical": {"valid": True}})
    out = run_chain(["learned", "classical", "voxel"], attempt)
    assert calls == ["learned"] and out.chosen.source == "learned" and out.fallback_reason is None
    assert out.rejected_seconds == {}


def test_any_error_of_the_learned_attempt_falls_back_but_a_classical_bug_does_not():
    attempt, calls = _scripted({"learned": _at(RuntimeError("CUDA error"), "register"),
                                "classical": _at(KeyError("bug"), "pullback"), "voxel": {"valid": True}})
    with pytest.raises(KeyError) as err:
        run_chain(["learned", "classical", "voxel"], attempt)
    assert calls == ["learned", "classical"]
    assert err.value.stage == "pullback" and err.value.source == "classical"
    assert err.value.fallback_reason == "learned polycube rejected at register: RuntimeError: CUDA error"


def test_a_bad_part_is_final():
    attempt, calls = _scripted({"learned": PartError("p.stl", "open boundary"), "classical": {"valid": True}})
    with pytest.raises(PartError):
        run_chain(["learned", "classical"], attempt)
    assert calls == ["learned"]


def test_rejected_polycubes_then_the_best_invalid_mesh_with_every_reason_and_their_seconds():
    attempt, calls = _scripted({"learned": _at(PolycubeError("genus 0 differs from 2"), "extract"),
                                "classical": {"valid": False, "sj_min": -0.1},
                                "voxel": {"valid": False, "sj_min": -0.4}})
    out = run_chain(["learned", "classical", "voxel"], attempt)
    assert calls == ["learned", "classical", "voxel"]
    assert out.chosen.source == "classical"  # the higher minimum scaled Jacobian
    assert out.reasons == [
        "learned polycube rejected at extract: genus 0 differs from 2",
        "pullback: the classical polycube's hex mesh is not valid (minimum scaled Jacobian -0.100)",
        "pullback: the voxel polycube's hex mesh is not valid (minimum scaled Jacobian -0.400)",
        "no polycube gave a valid mesh: kept the classical one's (the highest minimum scaled Jacobian)",
    ]
    # left: the learned attempt (1 s polycube + 1 s extract) and the voxel one (1 + 2); the kept one is not counted
    assert out.rejected_seconds == {"polycube": 2.0, "extract": 1.0, "pullback": 2.0}


def test_when_every_source_is_rejected_the_last_error_is_returned_with_the_earlier_reasons():
    attempt, _ = _scripted({"learned": PolycubeError("no usable cloud"), "voxel": PolycubeError("no resolution")})
    out = run_chain(["learned", "voxel"], attempt)
    assert out.chosen is None and out.error_source == "voxel" and "no resolution" in str(out.error)
    assert out.reasons == ["learned polycube rejected at polycube: no usable cloud"]


def test_a_valid_mesh_under_the_bar_is_compared_with_the_next_one():
    """A mesh that is valid but under ``min_sj`` does not end the chain: the next source is meshed too
    and the better kept -- either way round."""
    chain = ["learned", "classical", "voxel"]
    attempt, calls = _scripted({"learned": {"valid": True, "sj_min": 0.05}, "classical": {"valid": True, "sj_min": 0.45}})
    out = run_chain(chain, attempt, min_sj=0.2)
    assert calls == ["learned", "classical"] and out.chosen.source == "classical"
    assert "valid but its minimum scaled Jacobian 0.050 is under 0.2" in out.fallback_reason
    assert out.rejected_seconds == {"polycube": 1.0, "pullback": 2.0}  # the learned attempt's
    attempt, calls = _scripted({"learned": {"valid": True, "sj_min": 0.15}, "classical": {"valid": True, "sj_min": 0.1},
                                "voxel": {"valid": True, "sj_min": 0.12}})
    out = run_chain(chain, attempt, min_sj=0.2)
    assert calls == chain and out.chosen.source == "learned"
    assert "voxel polycube's hex mesh is valid but worse" in out.fallback_reason
    assert out.rejected_seconds == {"polycube": 2.0, "pullback": 4.0}  # the classical and voxel attempts'
    attempt, calls = _scripted({"learned": {"valid": True, "sj_min": 0.25}, "classical": {"valid": True, "sj_min": 0.6}})
    assert run_chain(chain, attempt, min_sj=0.2).chosen.source == "learned" and calls == ["learned"]
    # HexGen rockerarm: the flattening's mesh is valid at 0.187, the voxel polycube's at 0.302
    attempt, calls = _scripted({"classical": {"valid": True, "sj_min": 0.187}, "voxel": {"valid": True, "sj_min": 0.302}})
    assert run_chain(["classical", "voxel"], attempt, min_sj=0.2).chosen.source == "voxel"
    attempt, calls = _scripted({"classical": {"valid": True, "sj_min": 0.05}, "voxel": {"valid": True, "sj_min": 0.5}})
    assert run_chain(["classical", "voxel"], attempt, min_sj=None).chosen.source == "classical" and calls == ["classical"]


def test_finer_voxel_polycubes_are_tried_while_the_mesh_is_off_the_part_or_under_the_bar():
    # HexGen fertility: 30 cells 1.26 % off, 34 cells under the bar, 38 cells good: 42 never made
    attempt, calls = _scripted({"voxel": {"valid": True, "sj_min": 0.244, "deviation": 0.0126},
                                "voxel+1": {"valid": True, "sj_min": 0.093, "deviation": 0.0146},
                                "voxel+2": {"valid": True, "sj_min": 0.302, "deviation": 0.0084},
                                "voxel+3": {"valid": True, "sj_min": 0.147, "deviation": 0.0058}})
    out = run_chain(VOXELS, attempt, min_sj=0.2)
    assert calls == VOXELS[:3] and out.chosen.source == "voxel+2"
    assert "the voxel polycube's hex mesh is valid but 1.26 % of the diagonal off" in out.fallback_reason
    assert "the voxel (refinement 1) polycube's hex mesh is valid but 1.46 % of the diagonal off" in out.fallback_reason
    # none good: every refinement made, the best kept (valid and faithful first, then min SJ)
    attempt, calls = _scripted({"voxel": {"valid": False, "sj_min": -0.5}, "voxel+1": {"valid": True, "sj_min": 0.15},
                                "voxel+2": {"valid": True, "sj_min": 0.3, "deviation": 0.02},
                                "voxel+3": {"valid": True, "sj_min": 0.1}, "voxel+3*": {"valid": True, "sj_min": 0.12}})
    out = run_chain(VOXELS, attempt, min_sj=0.2)
    assert calls == VOXELS and out.chosen.source == "voxel+1"


def test_a_refinement_is_not_tried_after_a_voxel_polycube_that_gave_no_mesh():
    attempt, calls = _scripted({"classical": {"valid": True, "sj_min": 0.1},
                                "voxel": PolycubeError("no voxel resolution in 8..44 gives a valid polycube")})
    out = run_chain(["classical"] + VOXELS, attempt, min_sj=0.2)
    assert calls == ["classical", "voxel"] and out.chosen.source == "classical"
    assert "voxel polycube rejected at polycube: no voxel resolution" in out.fallback_reason
    # a refinement that finds no finer resolution ends the refinements; the coarser mesh is kept
    attempt, calls = _scripted({"voxel": {"valid": True, "sj_min": 0.25, "deviation": 0.02},
                                "voxel+1": PolycubeError("no voxel resolution in 40..44")})
    out = run_chain(VOXELS, attempt, min_sj=0.2)
    assert calls == ["voxel", "voxel+1"] and out.chosen.source == "voxel"
    # every source rejected: the last error that was raised is returned
    attempt, calls = _scripted({"voxel": PolycubeError("no resolution")})
    out = run_chain(VOXELS, attempt)
    assert calls == ["voxel"] and out.chosen is None and out.error_source == "voxel" and out.reasons == []


def test_a_valid_mesh_off_the_part_tries_the_next_source_and_the_faithful_one_wins():
    # fertility through the classical polycube: untangled into a valid mesh 5 % of the diagonal off the part
    attempt, calls = _scripted({"classical": {"valid": True, "sj_min": 0.3, "deviation": 0.05},
                                "voxel": {"valid": True, "sj_min": 0.15, "deviation": 0.006}})
    out = run_chain(["classical", "voxel"], attempt)
    assert calls == ["classical", "voxel"] and out.chosen.source == "voxel"
    assert "5.00 % of the diagonal off the part" in out.fallback_reason
    assert out.rejected_seconds == {"polycube": 1.0, "pullback": 2.0}


def test_an_off_part_mesh_is_still_kept_over_an_invalid_one_and_faithful_meshes_end_the_chain():
    attempt, _ = _scripted({"classical": {"valid": True, "sj_min": 0.3, "deviation": 0.05},
                            "voxel": {"valid": False, "sj_min": -0.2, "deviation": 0.001}})
    out = run_chain(["classical", "voxel"], attempt)
    assert out.chosen.source == "classical" and out.chosen.quality["valid"]
    attempt, calls = _scripted({"classical": {"valid": True, "sj_min": 0.3, "deviation": 0.009},
                                "voxel": {"valid": True}})
    assert run_chain(["classical", "voxel"], attempt).chosen.source == "classical" and calls == ["classical"]


def test_when_no_mesh_follows_the_part_the_closest_one_above_the_bar_is_kept():
    # no mesh within the bar: the closest one above it is kept, whatever its minimum SJ
    attempt, calls = _scripted({"learned": {"valid": True, "sj_min": 0.302, "hausdorff": 0.0234},
                                "classical": {"valid": True, "sj_min": 0.301, "hausdorff": 0.0133},
                                "voxel": {"valid": True, "sj_min": 0.31, "hausdorff": 0.0199},
                                "voxel+1": {"valid": False, "sj_min": -0.9}})
    out = run_chain(["learned", "classical", "voxel", "voxel+1"], attempt, min_sj=0.2)
    assert calls == ["learned", "classical", "voxel", "voxel+1"] and out.chosen.source == "classical"
    # a closer mesh under the quality bar does not beat a farther one above it
    attempt, _ = _scripted({"classical": {"valid": True, "sj_min": 0.05, "hausdorff": 0.011},
                            "voxel": {"valid": True, "sj_min": 0.3, "hausdorff": 0.02}})
    out = run_chain(["classical", "voxel"], attempt, min_sj=0.2)
    assert out.chosen.source == "voxel"
    # the last source's mesh left for a closer earlier one says so; one under the bar says its SJ
    attempt, _ = _scripted({"classical": {"valid": True, "sj_min": 0.25, "hausdorff": 0.012},
                            "voxel": {"valid": True, "sj_min": 0.4, "hausdorff": 0.03}})
    out = run_chain(["classical", "voxel"], attempt, min_sj=0.2)
    assert out.chosen.source == "classical"
    assert "voxel polycube's hex mesh is valid but does not follow the part as closely" in out.fallback_reason
    attempt, _ = _scripted({"classical": {"valid": True, "sj_min": 0.25, "hausdorff": 0.03},
                            "voxel": {"valid": True, "sj_min": 0.1, "hausdorff": 0.012}})
    out = run_chain(["classical", "voxel"], attempt, min_sj=0.2)
    assert out.chosen.source == "classical"
    assert "voxel polycube's hex mesh is valid but 1.20 % of the diagonal off the part and worse" in out.fallback_reason
    # faithful meshes still rank by their minimum SJ, and any valid one above an invalid one
    assert policy.mesh_rank({"valid": True, "sj_min": 0.4, "hausdorff": 0.002}) > policy.mesh_rank(
        {"valid": True, "sj_min": 0.3, "hausdorff": 0.0001})
    assert policy.mesh_rank({"valid": True, "sj_min": 0.01, "hausdorff": 0.5}) > policy.mesh_rank(
        {"valid": False, "sj_min": -0.1, "hausdorff": 0.0})


def _two_phase(script: dict):
    """``attempt`` whose learned draws give ``script[source] = (mesh so far, rest)``: the quality of the draw's
    registration-map mesh, and that of its finished pull-back (an exception: the rest raises it); any other
    source ``script[source]`` as :func:`_scripted`.  ``calls`` records ``source`` and ``source:rest`` in order."""
    calls = []

    def attempt(src, tracker):
        calls.append(src)
        tracker.seconds["polycube"] = 1.0
        tracker.seconds["pullback"] = 2.0
        if not src.startswith("learned"):
            return Attempt(src, script[src], payload=src, seconds=dict(tracker.seconds))
        first, then = script[src]
        att = Attempt(src, first, payload=src, seconds=dict(tracker.seconds))

        def rest():
            calls.append(f"{src}:rest")
            if isinstance(then, BaseException):
                raise then
            return Attempt(src, then, payload=f"{src}:rest", seconds={**att.seconds, "pullback": 5.0})

        att.rest = rest
        return att

    return attempt, calls


FAR = {"valid": True, "sj_min": 0.3, "hausdorff": 0.034}  # stepped_shaft's first draw, 3.4 % off
NEAR = {"valid": True, "sj_min": 0.3, "hausdorff": 0.0165}  # bushing's, 1.65 % off: a near miss
GOOD = {"valid": True, "sj_min": 0.3, "hausdorff": 0.005}


def test_a_far_miss_waits_for_the_next_draws_and_a_near_miss_finishes_at_once():
    draws = ["learned", "learned+1", "learned+2", "classical"]
    # the first draw far off: the second draw's map first; it ends the chain, the first draw's rest never runs
    attempt, calls = _two_phase({"learned": (FAR, GOOD), "learned+1": (GOOD, GOOD), "learned+2": (GOOD, GOOD),
                                 "classical": GOOD})
    out = run_chain(draws, attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1"] and out.chosen.payload == "learned+1"
    # the waiting draw was left: its reason and seconds are in the run's summary
    assert out.fallback_reason == ("pullback: the learned polycube's hex mesh is valid but 3.40 % of the diagonal "
                                   "off the part (bar 1 %): the next polycube was tried and the better mesh kept")
    assert out.rejected_seconds == {"polycube": 1.0, "pullback": 2.0}
    # a near miss: its rest at once, which ends the chain
    attempt, calls = _two_phase({"learned": (NEAR, GOOD), "learned+1": (GOOD, GOOD), "learned+2": (GOOD, GOOD),
                                 "classical": GOOD})
    out = run_chain(draws, attempt, min_sj=0.2)
    assert calls == ["learned", "learned:rest"] and out.chosen.payload == "learned:rest"
    assert out.chosen.seconds["pullback"] == 5.0 and out.rejected_seconds == {}


def test_the_waiting_rests_run_after_the_last_draw_and_before_the_classical_chain(monkeypatch):
    draws = ["learned", "learned+1", "learned+2", "classical"]
    # every waiting rest finishing (FAR_RESTS None): the last draw has no later draw to wait for: its rest at once,
    # then the waiting ones in draw order
    monkeypatch.setattr(policy, "FAR_RESTS", None)
    attempt, calls = _two_phase({"learned": (FAR, FAR), "learned+1": (FAR, GOOD), "learned+2": (FAR, FAR),
                                 "classical": GOOD})
    out = run_chain(draws, attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+2", "learned+2:rest", "learned:rest", "learned+1:rest"]
    assert out.chosen.payload == "learned+1:rest"
    assert out.rejected_seconds == {"polycube": 2.0, "pullback": 10.0}  # the two finished draws left
    # no rest ends it: the classical chain after all of them, the best mesh kept
    attempt, calls = _two_phase({"learned": (FAR, FAR), "learned+1": (FAR, NEAR), "classical": FAR})
    out = run_chain(["learned", "learned+1", "classical"], attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+1:rest", "learned:rest", "classical"]
    assert out.chosen.payload == "learned+1:rest"  # the nearest one
    # the learned draws alone (--polycube learned): the waiting rests run at the end
    attempt, calls = _two_phase({"learned": (FAR, GOOD), "learned+1": (FAR, FAR)})
    out = run_chain(["learned", "learned+1"], attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+1:rest", "learned:rest"]
    assert out.chosen.payload == "learned:rest"


FARTHER = {"valid": True, "sj_min": 0.3, "hausdorff": 0.048}  # blocks_1132_000's maps, 4.8 % off
BROKEN = {"valid": False, "sj_min": -0.4, "hausdorff": 0.02}


def test_only_the_closest_waiting_draws_finish_and_the_others_say_so(monkeypatch):
    monkeypatch.setattr(policy, "FAR_RESTS", 1)
    draws = ["learned", "learned+1", "learned+2", "learned+3", "classical", "voxel"]
    # the closest waiting draw (learned+1, 3.4 % off) finishes and ends the chain; the farther and the invalid
    # one never run their rests
    script = {"learned": (FARTHER, GOOD), "learned+1": (FAR, GOOD), "learned+2": (BROKEN, GOOD),
              "learned+3": (FARTHER, FARTHER), "classical": GOOD, "voxel": GOOD}
    attempt, calls = _two_phase(script)
    out = run_chain(draws, attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+2", "learned+3", "learned+3:rest", "learned+1:rest"]
    assert out.chosen.payload == "learned+1:rest"
    # none ends it: the classical chain runs once after the one finished rest; the others are candidates whose
    # reasons say their realisation was not tried, and no rest runs again before the voxel polycube
    script.update({"learned+1": (FAR, FAR), "classical": FARTHER, "voxel": GOOD})
    attempt, calls = _two_phase(script)
    out = run_chain(draws, attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+2", "learned+3", "learned+3:rest", "learned+1:rest",
                     "classical", "voxel"]
    assert out.chosen.payload == "voxel"
    left = [r for r in out.reasons if "not tried" in r]
    assert len(left) == 2 and "learned polycube's hex mesh is valid but 4.80 %" in left[0]
    assert "learned (draw 3" in left[1] and "is not valid" in left[1]
    assert left[0].endswith("(its realisation not tried: only the closest far draw finishes)")
    # the learned draws alone: the same one finishes, the others' maps' meshes are kept as candidates
    attempt, calls = _two_phase({k: v for k, v in script.items() if k.startswith("learned")})
    out = run_chain(draws[:4], attempt, min_sj=0.2)
    assert calls == ["learned", "learned+1", "learned+2", "learned+3", "learned+3:rest", "learned+1:rest"]
    assert out.chosen.payload == "learned+1:rest"  # FAR's own rest, the closest mesh


def test_a_rest_that_fails_leaves_the_draw_as_any_error_of_its_attempt_does():
    attempt, calls = _two_phase({"learned": (NEAR, RuntimeError("realisation blew up")), "classical": FAR})
    out = run_chain(["learned", "classical"], attempt, min_sj=0.2)
    assert calls == ["learned", "learned:rest", "classical"]
    assert out.chosen.payload == "classical"  # the draw's mesh so far goes with it
    assert out.fallback_reason == "learned polycube rejected at pullback: RuntimeError: realisation blew up"
    assert out.rejected_seconds == {"polycube": 1.0, "pullback": 2.0}
    # a bad part is final, also when a waiting rest finds it
    attempt, calls = _two_phase({"learned": (FAR, PartError("the part", "not a closed surface")),
                                 "learned+1": (FAR, FAR), "classical": GOOD})
    with pytest.raises(PartError) as err:
        run_chain(["learned", "learned+1", "classical"], attempt, min_sj=0.2)
    assert err.value.source == "learned" and err.value.stage == "pullback" and "classical" not in calls
