"""Inference: batch planning, generate() (any resolution, reproducible, batch-independent,
chunked == unchunked, input validation) and the ModelSource of the pipeline.

A tiny randomly initialised model is written to a checkpoint once per module; its output
layer gets non-zero weights so that the generated clouds depend on the condition and on
every network path (a zero output layer would make the equality checks vacuous).
"""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
import torch

from polycubenet.data import PolycubeCloud
from polycubenet.inference import ModelSource, generate, load_model, plan_batches
from polycubenet.model import Diffusion, PolycubeNet, preset
from polycubenet.model.checkpoint import save_checkpoint
from polycubenet.pipeline import PipelineConfig

STEPS = 3


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    torch.manual_seed(0)
    net = PolycubeNet(preset("tiny"))
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
        torch.nn.init.normal_(net.denoiser.out.bias, std=0.05)
    path = tmp_path_factory.mktemp("model") / "tiny.pt"
    save_checkpoint(path, {"kind": "published", "model_config": net.config.to_dict(),
                           "diffusion": Diffusion().to_dict(), "ema": net.state_dict()})
    return path


def _cloud(n: int, seed: int) -> np.ndarray:
    """A box-like condition cloud in the canonical frame (diagonal ~1, centred)."""
    rng = np.random.default_rng(seed)
    return ((rng.random((n, 3)) - 0.5) * np.array([0.7, 0.5, 0.3])).astype(np.float32)


# ----------------------------------------------------------------------------- plan_batches
def test_plan_batches_groups_resolutions_within_the_budget():
    rng = np.random.default_rng(5)
    n_in = rng.choice([100, 200, 400], size=60)
    n_out = rng.choice([300, 600], size=60)
    n_in[7], n_out[7] = 5000, 6000  # larger than the budget on its own
    budget = 2000
    batches = plan_batches(n_in, n_out, budget)
    flat = [i for b in batches for i in b]
    assert sorted(flat) == list(range(60))  # every request exactly once
    for b in batches:
        assert len({(int(n_in[i]), int(n_out[i])) for i in b}) == 1  # one resolution per batch
        if b == [7]:
            continue
        assert 7 not in b
        assert sum(int(n_in[i] + n_out[i]) for i in b) <= budget
        assert b == sorted(b)  # original order kept inside a group
    assert [7] in batches
    # packing is tight: a group is split only when the next request would overflow the budget
    for (a, c), count in zip(*np.unique(np.stack([n_in, n_out], 1), axis=0, return_counts=True)):
        if a == 5000:
            continue
        per = budget // (a + c)
        n_batches = sum(1 for b in batches if (n_in[b[0]], n_out[b[0]]) == (a, c))
        assert n_batches == -(-count // per)


def test_plan_batches_validates_its_arguments():
    with pytest.raises(ValueError, match="n_in has 2 entries"):
        plan_batches([10, 20], [10], 100)
    with pytest.raises(ValueError, match="point_budget"):
        plan_batches([10], [10], 0)


# ----------------------------------------------------------------------------- generate
def test_any_resolution_gives_xyz_and_unit_normals(ckpt):
    conds = [_cloud(17, 0), _cloud(250, 1), _cloud(64, 2)]
    n_out = [5, 300, 64]
    out = generate(conds, n_out, model=ckpt, steps=STEPS, device="cpu")
    assert len(out) == 3
    for cloud, n in zip(out, n_out):
        assert cloud.shape == (n, 6) and cloud.dtype == np.float32
        assert np.isfinite(cloud).all()
        np.testing.assert_allclose(np.linalg.norm(cloud[:, 3:], axis=1), 1.0, atol=1e-5)
    # one int for every request
    same = generate(conds[:2], 40, model=ckpt, steps=STEPS, device="cpu")
    assert [c.shape for c in same] == [(40, 6), (40, 6)]


def test_a_seed_reproduces_the_output(ckpt):
    conds = [_cloud(80, 3), _cloud(80, 4)]
    a = generate(conds, 90, model=ckpt, steps=STEPS, seed=7, device="cpu")
    b = generate(conds, 90, model=ckpt, steps=STEPS, seed=7, device="cpu")
    c = generate(conds, 90, model=ckpt, steps=STEPS, seed=8, device="cpu")
    for x, y, z in zip(a, b, c):
        np.testing.assert_array_equal(x, y)
        assert np.abs(x - z).max() > 1e-2


def test_a_request_does_not_depend_on_its_batch(ckpt):
    conds = [_cloud(100, 10 + i) for i in range(4)]
    together = generate(conds, 120, model=ckpt, steps=STEPS, seed=3, device="cpu")  # one batch of 4
    alone = generate(conds, 120, model=ckpt, steps=STEPS, seed=3, device="cpu", point_budget=1)  # 4 batches
    for x, y in zip(together, alone):
        np.testing.assert_allclose(x, y, atol=1e-5)
    # the same request (index 0) next to other conditions, and with mixed resolutions in the list
    other = generate([conds[0], _cloud(100, 99), _cloud(33, 98)], [120, 120, 50], model=ckpt, steps=STEPS,
                     seed=3, device="cpu")
    np.testing.assert_allclose(other[0], together[0], atol=1e-4)
    # the check is not vacuous: the condition changes the output
    assert np.abs(other[1] - together[1]).max() > 1e-3
    # a request's noise is a function of its own condition and the seed: the last request of the
    # batch of 4, asked for first and alone, is the same cloud
    (last,) = generate([conds[3]], 120, model=ckpt, steps=STEPS, seed=3, device="cpu")
    np.testing.assert_allclose(last, together[3], atol=1e-5)
    reordered = generate(conds[::-1], 120, model=ckpt, steps=STEPS, seed=3, device="cpu")
    for x, y in zip(reordered[::-1], together):
        np.testing.assert_allclose(x, y, atol=1e-5)


def test_chunked_equals_unchunked(ckpt):
    conds = [_cloud(50, 20), _cloud(50, 21)]
    full = generate(conds, 40, model=ckpt, steps=STEPS, seed=1, device="cpu")
    chunked = generate(conds, 40, model=ckpt, steps=STEPS, seed=1, device="cpu", chunk=7)
    for x, y in zip(full, chunked):
        np.testing.assert_allclose(y, x, atol=1e-4)


@pytest.mark.parametrize("bad, index", [
    (np.zeros((10, 2), np.float32), 1),
    (np.zeros((0, 3), np.float32), 1),
    (np.full((10, 3), np.nan, np.float32), 2),
    (np.zeros(30, np.float32), 2),
])
def test_bad_conditions_name_the_request(ckpt, bad, index):
    conds = [_cloud(20, 0), _cloud(20, 1), _cloud(20, 2)]
    conds[index] = bad
    with pytest.raises(ValueError, match=f"condition {index}:"):
        generate(conds, 10, model=ckpt, steps=STEPS, device="cpu")


def test_bad_output_sizes_are_refused(ckpt):
    conds = [_cloud(20, 0), _cloud(20, 1)]
    with pytest.raises(ValueError, match="2 conditions but 3 output sizes"):
        generate(conds, [10, 10, 10], model=ckpt, steps=STEPS, device="cpu")
    with pytest.raises(ValueError, match="n_out"):
        generate(conds, [10, 0], model=ckpt, steps=STEPS, device="cpu")


def test_a_missing_checkpoint_is_reported(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_model(tmp_path / "missing.pt", device="cpu")
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        generate([_cloud(10, 0)], 10, model=tmp_path / "missing.pt", steps=STEPS, device="cpu")


# ----------------------------------------------------------------------------- pipeline source
def test_model_source_returns_a_learned_cloud(ckpt):
    config = PipelineConfig(n_learned=70, seed=4)  # the model generates n_learned points (not n_polycube)
    sample = types.SimpleNamespace(points=_cloud(90, 30).astype(np.float64))
    src = ModelSource(ckpt, steps=STEPS, seed=2, device="cpu")
    cloud = src(sample, None, None, config)
    assert isinstance(cloud, PolycubeCloud)
    assert cloud.meta["provenance"] == "learned" and cloud.meta["checkpoint"] == ckpt.name
    assert cloud.points.shape == (70, 3) and cloud.normals.shape == (70, 3)
    assert cloud.points.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-5)
    # the source's seed and the config's seed together select the noise, as documented
    (direct,) = generate([sample.points], 70, model=ckpt, steps=STEPS, seed=2 + 4, device="cpu")
    np.testing.assert_allclose(cloud.points, direct[:, :3], atol=1e-6)


@pytest.fixture(scope="module")
def anchored_ckpt(tmp_path_factory):
    import dataclasses

    torch.manual_seed(1)
    net = PolycubeNet(dataclasses.replace(preset("tiny"), anchored=True))
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
    path = tmp_path_factory.mktemp("model") / "tiny-anchored.pt"
    save_checkpoint(path, {"kind": "published", "model_config": net.config.to_dict(),
                           "diffusion": Diffusion(prediction="v", schedule="cosine_ztsnr").to_dict(),
                           "ema": net.state_dict()})
    return path


def test_an_anchored_model_moves_each_anchor_a_bounded_step(anchored_ckpt):
    """Each output point is its anchor plus a displacement the network can represent (the clipped
    x0 over xyz_scale * anchor_gain); the anchors are required, and batching changes nothing."""
    from polycubenet.inference import part_anchors

    loaded = load_model(anchored_ckpt, "cpu")
    cfg = loaded.model.config
    conds = [_cloud(100, 20 + i) for i in range(3)]
    with pytest.raises(ValueError, match="anchored"):
        generate(conds, 50, model=loaded, steps=STEPS, device="cpu")
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) - 0.3
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    anchors = [part_anchors(V, F, 50, seed=i) for i in range(3)]
    out = generate(conds, 50, model=loaded, steps=STEPS, device="cpu", anchors=anchors)
    bound = 1.0 / (cfg.xyz_scale * cfg.anchor_gain) + 1e-5
    moved = [np.abs(o[:, :3] - a).max() for o, a in zip(out, anchors)]
    assert max(moved) <= bound and min(moved) > 1e-3  # moved, but not further than representable
    np.testing.assert_allclose(np.linalg.norm(out[0][:, 3:], axis=1), 1.0, atol=1e-5)
    (alone,) = generate([conds[2]], 50, model=loaded, steps=STEPS, device="cpu", anchors=[anchors[2]])
    np.testing.assert_allclose(alone, out[2], atol=1e-5)
    with pytest.raises(ValueError, match="anchors 0"):
        generate(conds[:1], 50, model=loaded, steps=STEPS, device="cpu", anchors=[anchors[0][:10]])


def test_a_checkpoints_own_default_steps_are_used_on_cpu(tmp_path):
    """The number of DDIM steps chosen when a checkpoint was published is its default on a CPU
    (and is what the cache key records)."""
    from polycubenet.inference import resolve_steps

    torch.manual_seed(0)
    net = PolycubeNet(preset("tiny"))
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
    path = save_checkpoint(tmp_path / "two.pt", {"kind": "published", "model_config": net.config.to_dict(),
                                                 "diffusion": Diffusion().to_dict(), "ema": net.state_dict(),
                                                 "default_steps": 2})
    cond = [_cloud(80, 5)]
    (a,) = generate(cond, 40, model=path, device="cpu")
    (b,) = generate(cond, 40, model=path, steps=2, device="cpu")
    (c,) = generate(cond, 40, model=path, steps=5, device="cpu")
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 1e-4
    assert resolve_steps(None, "cpu", path) == ("cpu", 2) and resolve_steps(7, "cpu", path) == ("cpu", 7)


def test_model_source_further_draws_and_their_place_in_the_chain(ckpt, anchored_ckpt, monkeypatch):
    """``draw_source(k)`` is the same model and device at the policy's steps and seed offset of draw
    ``k``; the pipeline puts the draws right after the first (policy.source_names), without one that
    would repeat the first."""
    from polycubenet import policy
    from polycubenet.pipeline import source_chain

    assert ModelSource(anchored_ckpt, steps=1, device="cpu").further_draws() == (1, 2, 3, 4, 5)  # the shipped table
    assert ModelSource(anchored_ckpt, steps=4, device="cpu").further_draws() == (2, 3, 4)
    assert ModelSource(anchored_ckpt, steps=1, device="cpu").draw_source(3).anchors == "even"
    d5 = ModelSource(anchored_ckpt, steps=1, seed=2, device="cpu").draw_source(5)
    assert (d5.steps, d5.seed, d5.anchors) == (4, 3, "even")
    # a model without anchors: an evenly spread draw is an earlier one again (the first; the one-step draw at
    # seed +1), so it is skipped
    assert ModelSource(ckpt, steps=1, device="cpu").further_draws() == (1, 2, 5)
    assert ModelSource(ckpt, steps=4, device="cpu").further_draws() == (2,)
    LEARNED_DRAWS = ((4, 0, False), (4, 1, False), (4, 2, False))
    monkeypatch.setattr(policy, "LEARNED_DRAWS", LEARNED_DRAWS)
    src = ModelSource(ckpt, steps=1, seed=2, device="cpu")
    assert src.further_draws() == (1, 2, 3)
    d1, d3 = src.draw_source(1), src.draw_source(3)
    assert (d1.model, d1.steps, d1.seed, d1.device) == (ckpt, LEARNED_DRAWS[0][0], 2, "cpu")
    assert (d3.steps, d3.seed) == (LEARNED_DRAWS[2][0], 2 + LEARNED_DRAWS[2][1])
    assert d1.further_draws() == (2, 3) and ModelSource(ckpt, steps=8, device="cpu").draw_source(2).steps == 8
    chain = source_chain(src, PipelineConfig(polycube="auto"))
    assert [n for n, _ in chain][:5] == ["learned", "learned+1", "learned+2", "learned+3", "classical"]
    assert chain[0][1] is src and chain[1][1].steps == LEARNED_DRAWS[0][0] and chain[2][1].seed == 3
    assert [n for n, _ in source_chain(d1, PipelineConfig(polycube="auto"))][:4] == [
        "learned", "learned+2", "learned+3", "classical"]
    assert [n for n, _ in source_chain(src, PipelineConfig(polycube="learned"))] == [
        "learned", "learned+1", "learned+2", "learned+3"]
    # an injected source without a second draw (a test's fake, the oracle) is used alone
    assert [n for n, _ in source_chain(lambda *a: None, PipelineConfig(polycube="learned"))] == ["learned"]
    # the table's turn goes with the draw, in the pipeline and in the flow's sources, and into the flow's cache key
    from polycubenet import library

    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((1, 1, True, "y"), (4, 1, True, None)))
    assert src.draw_source(1).turn == "y" and src.turn is None and src.draw_source(2).turn is None
    assert library.make_source("learned+1", "p.stl", None, checkpoint=ckpt, steps=1, device="cpu").turn == "y"
    keys = [library.source_extra(f"learned+{k}", "p.stl", ckpt, steps=1, device="cpu") for k in (1, 2)]
    assert keys[0]["turn"] == "y" and "turn" not in keys[1] and keys[0]["seed"] == keys[1]["seed"] == 1
    # so does its anchor spread; a uniform draw's key is what it was before spreads existed
    monkeypatch.setattr(policy, "LEARNED_DRAWS", ((1, 0, True, None, "even"), (1, 1, True, None)))
    assert src.draw_source(1).anchors == "even" and src.anchors == "uniform" == src.draw_source(2).anchors
    assert library.make_source("learned+1", "p.stl", None, checkpoint=ckpt, steps=1, device="cpu").anchors == "even"
    keys = [library.source_extra(f"learned+{k}", "p.stl", ckpt, steps=1, device="cpu") for k in (1, 2)]
    assert keys[0]["anchors"] == "even" and "anchors" not in keys[1] and keys[0]["seed"] == 0


def test_evenly_spread_anchors_are_a_blue_noise_sample_that_the_model_source_hands_the_model(tmp_path):
    """``part_anchors(spread="even")`` is a Poisson-disk sample: its closest pair of points is far
    apart next to independent samples' of the same size; ``ModelSource(anchors="even")`` draws from
    those anchors (the cloud's anchors are them), and an unknown spread is an error."""
    import dataclasses

    from scipy.spatial import cKDTree

    from polycubenet.inference import part_anchors

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) - 0.3
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    uniform = part_anchors(V, F, 400, seed=5, normals=True)
    even = part_anchors(V, F, 400, seed=5, normals=True, spread="even")
    assert even.shape == uniform.shape == (400, 6)
    np.testing.assert_allclose(np.linalg.norm(even[:, 3:], axis=1), 1.0, atol=1e-5)
    gap = [cKDTree(a[:, :3]).query(a[:, :3], k=2)[0][:, 1].min() for a in (uniform, even)]
    assert gap[1] > 3 * gap[0], gap
    np.testing.assert_array_equal(even, part_anchors(V, F, 400, seed=5, normals=True, spread="even"))
    with pytest.raises(ValueError, match="unknown anchor spread"):
        part_anchors(V, F, 10, spread="blue")
    torch.manual_seed(2)
    net = PolycubeNet(dataclasses.replace(preset("tiny"), anchored=True, anchor_normals=True))
    path = save_checkpoint(tmp_path / "tiny-even.pt", {
        "kind": "published", "model_config": net.config.to_dict(),
        "diffusion": Diffusion(prediction="v", schedule="cosine_ztsnr").to_dict(), "ema": net.state_dict()})
    config = PipelineConfig(n_learned=60, seed=3)
    sample = types.SimpleNamespace(points=_cloud(90, 31).astype(np.float64))
    cloud = ModelSource(path, steps=1, device="cpu", anchors="even")(sample, V, F, config)
    np.testing.assert_allclose(cloud.anchors, part_anchors(V, F, 60, seed=3, spread="even"), atol=1e-6)
    assert cloud.meta["anchors"] == "even"
    with pytest.raises(ValueError, match="unknown anchor spread"):
        ModelSource(path, anchors="blue")


def test_a_turned_draw_is_the_turned_part_drawn_and_turned_back(tmp_path):
    """``ModelSource(turn=...)``: the model sees the part's samples and anchors (points and their
    normals) turned a half-turn about the axis, and the cloud comes back turned the other way, with
    the unturned anchors; turning does change what the model draws."""
    import dataclasses

    from polycubenet.inference import TURNS, model_anchors

    torch.manual_seed(2)
    net = PolycubeNet(dataclasses.replace(preset("tiny"), anchored=True, anchor_normals=True))
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
    path = save_checkpoint(tmp_path / "tiny-normals.pt", {
        "kind": "published", "model_config": net.config.to_dict(),
        "diffusion": Diffusion(prediction="v", schedule="cosine_ztsnr").to_dict(), "ema": net.state_dict()})
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) - 0.3
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    config = PipelineConfig(n_learned=60, seed=3)
    sample = types.SimpleNamespace(points=_cloud(90, 31).astype(np.float64))
    plain = ModelSource(path, steps=2, device="cpu")(sample, V, F, config)
    turned = ModelSource(path, steps=2, device="cpu", turn="z")(sample, V, F, config)
    R = TURNS["z"]
    a = model_anchors(load_model(path, "cpu"), V, F, 60, 3)
    assert a.shape == (60, 6)
    aR = np.hstack([a[:, :3] @ R, a[:, 3:] @ R]).astype(np.float32)
    (raw,) = generate([sample.points @ R], 60, model=path, steps=2, seed=3, device="cpu", anchors=[aR])
    np.testing.assert_allclose(turned.points, raw[:, :3] @ R, atol=1e-6)
    np.testing.assert_allclose(turned.normals, raw[:, 3:] @ R, atol=1e-6)
    np.testing.assert_allclose(turned.anchors, plain.anchors)
    np.testing.assert_allclose(turned.anchor_normals, a[:, 3:])
    assert turned.meta["turn"] == "z" and "turn" not in plain.meta
    assert np.abs(turned.points - plain.points).max() > 1e-4
    with pytest.raises(ValueError, match="unknown turn"):
        ModelSource(path, turn="w")


def test_a_stretched_draw_is_the_part_scaled_along_the_axes_drawn_and_scaled_back(tmp_path):
    """``ModelSource(stretch=p)``: the model sees the part's samples scaled by ``stretch_factors`` (the box
    part of the way to a cube, the extents' order and the unit diagonal kept) and the anchors' normals by the
    inverse, and the cloud comes back scaled the other way with unit normals and the part's own anchors."""
    import dataclasses

    from polycubenet.inference import model_anchors, stretch_factors

    torch.manual_seed(2)
    net = PolycubeNet(dataclasses.replace(preset("tiny"), anchored=True, anchor_normals=True))
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
    path = save_checkpoint(tmp_path / "tiny-normals.pt", {
        "kind": "published", "model_config": net.config.to_dict(),
        "diffusion": Diffusion(prediction="v", schedule="cosine_ztsnr").to_dict(), "ema": net.state_dict()})
    V = np.array([[0, 0, 0], [0.8, 0, 0], [0, 0.4, 0], [0, 0, 0.2]], float) - 0.2
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    e = np.array([0.8, 0.4, 0.2])
    d = stretch_factors(V, 0.5)
    np.testing.assert_allclose(d / d[0], np.sqrt(e[0] / e))  # the box half way (in logs) to a cube
    np.testing.assert_allclose(np.linalg.norm(e * d), np.linalg.norm(e))  # the same diagonal
    assert np.all(np.diff(e * d) < 0) and np.all(np.diff(e * stretch_factors(V, -0.5)) < 0)  # order kept
    np.testing.assert_allclose(stretch_factors(V, 0.0), 1.0)
    config = PipelineConfig(n_learned=60, seed=3)
    sample = types.SimpleNamespace(points=_cloud(90, 31).astype(np.float64))
    plain = ModelSource(path, steps=2, device="cpu")(sample, V, F, config)
    wide = ModelSource(path, steps=2, device="cpu", stretch=0.5)(sample, V, F, config)
    a = model_anchors(load_model(path, "cpu"), V, F, 60, 3)
    n = a[:, 3:] / d
    aS = np.hstack([a[:, :3] * d, n / np.linalg.norm(n, axis=1, keepdims=True)]).astype(np.float32)
    (raw,) = generate([sample.points * d], 60, model=path, steps=2, seed=3, device="cpu", anchors=[aS])
    np.testing.assert_allclose(wide.points, raw[:, :3] / d, atol=1e-6)
    back = raw[:, 3:] * d
    np.testing.assert_allclose(wide.normals, back / np.linalg.norm(back, axis=1, keepdims=True), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(wide.normals, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(wide.anchors, plain.anchors)
    assert wide.meta["stretch"] == 0.5 and "stretch" not in plain.meta
    assert np.abs(wide.points - plain.points).max() > 1e-4
    with pytest.raises(ValueError, match="stretch exponent"):
        ModelSource(path, stretch=1.5)


def test_a_genus_model_is_told_each_request_s_genus_and_the_model_source_the_part_s(ckpt, tmp_path):
    """A model with ``genus_classes``: ``generate(genus=)`` gives each request its own genus (a batch of
    two genera equals each alone; None is "unknown", not genus 0); ``ModelSource`` tells it the genus of
    the part's surface (a ring: 1) and records it; a surface that is not one closed manifold is
    "unknown"; a model without genus vectors ignores the argument."""
    import trimesh

    from polycubenet.inference import part_genus

    torch.manual_seed(3)
    net = PolycubeNet(dataclasses.replace(preset("tiny"), genus_classes=4))
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
        torch.nn.init.normal_(net.genus.weight, std=1.0)
    path = tmp_path / "genus.pt"
    save_checkpoint(path, {"kind": "published", "model_config": net.config.to_dict(),
                           "diffusion": Diffusion().to_dict(), "ema": net.state_dict()})
    c1, c2 = _cloud(80, 40), _cloud(80, 41)
    both = generate([c1, c2], 50, model=path, steps=2, device="cpu", genus=[1, 3])
    (one,) = generate([c1], 50, model=path, steps=2, device="cpu", genus=[1])
    (two,) = generate([c2], 50, model=path, steps=2, device="cpu", genus=[3])
    np.testing.assert_array_equal(both[0], one)
    np.testing.assert_array_equal(both[1], two)
    (zero,) = generate([c1], 50, model=path, steps=2, device="cpu", genus=[0])
    (unknown,) = generate([c1], 50, model=path, steps=2, device="cpu", genus=[None])
    (default,) = generate([c1], 50, model=path, steps=2, device="cpu")
    np.testing.assert_array_equal(unknown, default)
    assert np.abs(one - zero).max() > 1e-4 and np.abs(zero - unknown).max() > 1e-4
    with pytest.raises(ValueError, match="genus values"):
        generate([c1, c2], 50, model=path, steps=2, device="cpu", genus=[1])

    ring = trimesh.creation.annulus(r_min=0.2, r_max=0.4, height=0.2)
    V, F = np.asarray(ring.vertices) / 1.5, np.asarray(ring.faces)
    assert part_genus(F) == 1 and part_genus(F[:-1]) is None
    config = PipelineConfig(n_learned=50, seed=0)
    sample = types.SimpleNamespace(points=c1.astype(np.float64))
    cloud = ModelSource(path, steps=2, device="cpu")(sample, V, F, config)
    assert cloud.meta["genus_given"] == 1
    (told,) = generate([c1], 50, model=path, steps=2, device="cpu", genus=[1], seed=config.seed)
    np.testing.assert_allclose(cloud.points, told[:, :3], atol=1e-6)
    (plain,) = generate([c1], 50, model=ckpt, steps=2, device="cpu", genus=[2])
    np.testing.assert_array_equal(plain, generate([c1], 50, model=ckpt, steps=2, device="cpu")[0])
