"""Training: data and augmentation, resume after a kill == uninterrupted run, checkpoints
rebuild the model from the file alone, publishing, DDP with 2 CPU processes (gloo)."""

import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from polycubenet.model.checkpoint import load_checkpoint, publish
from polycubenet.synth.shards import write_dataset
from polycubenet.train import DevicePairs, PairData, TrainConfig, lr_at, train


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    d = tmp_path_factory.mktemp("shards")
    write_dataset(d, count=6, seed=321, per_shard=3, n_cond=128, n_target=128, progress=False)
    return d


CFG = TrainConfig(preset="tiny", steps=8, batch=4, points=64, warmup=2, ckpt_every=4, log_every=2, seed=5, threads=1)


def test_batches_keep_the_pair_consistent(shards):
    data = PairData(shards)
    assert len(data) == 6
    rng = np.random.default_rng(0)
    x0, cond = data.batch(np.array([0, 3]), 50, rng, dataclasses.replace(CFG, jitter=0.0))
    assert x0.shape == (2, 50, 6) and cond.shape == (2, 50, 3)
    n = x0[..., 3:].numpy()
    # normals stay unit axis vectors under the anisotropic scaling
    assert np.allclose(np.abs(n).max(axis=-1), 1) and np.allclose(np.linalg.norm(n, axis=-1), 1)
    # the polycube points still lie on planes of their own normal's axis: per axis label,
    # the coordinate along that axis takes few distinct values (faces), like the raw data
    raw = data.target_points[0]
    raw_n = data.target_normals[0]
    ax = np.abs(raw_n).argmax(axis=1)
    x0_full, _ = data.batch(np.array([0]), 128, np.random.default_rng(1), dataclasses.replace(CFG, jitter=0.0))
    p, q = x0_full[0, :, :3].numpy(), x0_full[0, :, 3:].numpy()
    qa = np.abs(q).argmax(axis=1)
    for a in range(3):
        assert len(np.unique(np.round(p[qa == a, a], 5))) <= len(np.unique(np.round(raw[ax == a, a], 5)))
    # condition re-normalised to diagonal ~1 (subset of the full cloud: at most 1)
    d = np.linalg.norm(cond.numpy().max(axis=1) - cond.numpy().min(axis=1), axis=-1)
    assert np.all(d <= 1.0 + 1e-5) and np.all(d > 0.6)


@pytest.mark.parametrize("on_device", [False, True])
def test_mirrored_pairs_mirror_shape_polycube_normals_and_anchors_alike(shards, on_device):
    """``mirror_aug``: the same draw as without it (points, scaling, jitter), each pair's three axes each
    kept or negated, one pattern per pair shared by the condition, the polycube's points and normals and
    the anchors; at 1.0 every axis of every pair is negated, at 0.5 both patterns occur."""
    data = PairData(shards)
    idx = np.arange(6).repeat(4)
    cfg = dataclasses.replace(CFG, jitter=0.001)

    def draw(p):
        c = dataclasses.replace(cfg, mirror_aug=p)
        if on_device:
            return DevicePairs(data, torch.device("cpu"), anchors=6).batch(idx, 64, torch.Generator().manual_seed(3), c)
        return data.batch(idx, 64, np.random.default_rng(3), c, anchors=6)

    plain, every, half = draw(0.0), draw(1.0), draw(0.5)
    for a, b in zip(plain, every):
        np.testing.assert_allclose(b.numpy(), -a.numpy(), atol=1e-6)
    signs = []
    for a, b in zip(plain, half):
        a, b = a.numpy().reshape(len(idx), 64, -1, 3), b.numpy().reshape(len(idx), 64, -1, 3)
        np.testing.assert_allclose(np.abs(b), np.abs(a), atol=1e-6)
        big = np.abs(a) > 1e-3
        s = np.where(big, np.sign(b) * np.sign(a), 0.0)
        per_pair = np.array([[np.unique(s[k, ..., j][big[k, ..., j]]) for j in range(3)] for k in range(len(idx))])
        assert per_pair.shape == (len(idx), 3, 1)  # one sign per pair and axis, in every channel
        signs.append(per_pair[..., 0])
    assert all(np.array_equal(signs[0], s) for s in signs[1:])
    assert (signs[0] < 0).any() and (signs[0] > 0).any()


def test_learning_rate_schedule():
    cfg = TrainConfig(lr=1e-3, warmup=10, steps=110, min_lr_ratio=0.1)
    assert lr_at(0, cfg) == pytest.approx(1e-4)
    assert lr_at(9, cfg) == pytest.approx(1e-3)
    assert lr_at(60, cfg) == pytest.approx(1e-3 * (0.1 + 0.9 * 0.5))
    assert lr_at(110, cfg) == pytest.approx(1e-4)


def test_resume_after_interruption_equals_one_run(shards, tmp_path):
    full = train(shards, tmp_path / "full", CFG, resume=False, progress=False)
    assert full["step"] == 8
    # "killed" after 4 steps (the checkpoint at step 4 is what survives), then resumed
    train(shards, tmp_path / "cut", dataclasses.replace(CFG, steps=4), resume=False, progress=False)
    s4 = torch.load(tmp_path / "cut" / "last.pt", weights_only=False)
    assert s4["step"] == 4
    s4["train_config"]["steps"] = 8  # the resumed command asks for 8 steps
    train(shards, tmp_path / "cut", dataclasses.replace(CFG, steps=4, warmup=2), resume=True, progress=False)
    assert torch.load(tmp_path / "cut" / "last.pt", weights_only=False)["step"] == 4  # nothing left to do
    # resume to 8 with the same schedule as the uninterrupted run
    cut = tmp_path / "cut2"
    train(shards, cut, dataclasses.replace(CFG, steps=8), resume=False, progress=False, max_seconds=0.0)
    first = torch.load(cut / "last.pt", weights_only=False)["step"]
    assert 1 <= first < 8  # stopped early by the time limit, checkpoint written
    out = train(shards, cut, CFG, resume=True, progress=False)
    assert out["step"] == 8
    a = torch.load(tmp_path / "full" / "last.pt", weights_only=False)
    b = torch.load(cut / "last.pt", weights_only=False)
    for k in a["model"]:
        np.testing.assert_allclose(b["model"][k], a["model"][k], atol=1e-6, err_msg=k)
    for k in a["ema"]:
        np.testing.assert_allclose(b["ema"][k], a["ema"][k], atol=1e-6, err_msg=k)
    log = [json.loads(line) for line in (tmp_path / "full" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == [2, 4, 6, 8] and all(np.isfinite(r["loss_l2"]) for r in log)


def test_checkpoint_rebuilds_the_model_and_publishes(shards, tmp_path):
    train(shards, tmp_path / "run", CFG, resume=False, progress=False)
    ck = tmp_path / "run" / "last.pt"
    loaded = load_checkpoint(ck)
    s = torch.load(ck, weights_only=False)
    assert loaded.config.to_dict() == s["model_config"] and loaded.meta["step"] == 8
    for k, v in loaded.model.state_dict().items():
        assert torch.equal(v, s["ema"][k])
    raw = load_checkpoint(ck, weights="model")
    assert any(not torch.equal(raw.model.state_dict()[k], s["ema"][k]) for k in s["ema"])
    pub = publish(ck, tmp_path / "pub.pt", metrics={"chamfer_median": 0.5})
    assert pub.stat().st_size < ck.stat().st_size / 2
    lp = load_checkpoint(pub)
    assert lp.meta["metrics"]["chamfer_median"] == 0.5 and lp.meta["kind"] == "published"
    x, t, c = torch.randn(1, 20, 6), torch.tensor([50]), torch.randn(1, 30, 3)
    with torch.no_grad():
        np.testing.assert_allclose(lp.model(x, t, c), loaded.model(x, t, c), atol=5e-3)


def test_bad_checkpoints_are_refused(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_checkpoint(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="cannot be read"):
        load_checkpoint(bad)
    torch.save({"hello": 1}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a PolycubeNet checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")


def test_resume_refuses_another_model(shards, tmp_path):
    train(shards, tmp_path / "r", dataclasses.replace(CFG, steps=2), resume=False, progress=False)
    with pytest.raises(ValueError, match="another model config"):
        train(shards, tmp_path / "r", dataclasses.replace(CFG, preset="cpu", steps=3), progress=False)


def test_ddp_with_two_cpu_processes(shards, tmp_path):
    run = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", "29533",
           "-m", "polycubenet.train", "--data", str(shards), "--out", str(run), "--preset", "tiny",
           "--steps", "3", "--batch", "4", "--points", "32", "--warmup", "1", "--ckpt-every", "3",
           "--log-every", "1", "--threads", "1", "--no-progress"]
    p = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    s = torch.load(run / "last.pt", weights_only=False)
    assert s["step"] == 3 and s["world_size"] == 2
    assert len((run / "log.jsonl").read_text().splitlines()) == 3
    assert load_checkpoint(run / "last.pt").meta["step"] == 3


def test_anchors_are_the_part_points_of_the_drawn_targets(shards):
    """For an anchored model each drawn target point comes with the part point it is the image of,
    transformed by the same augmentation (so target - anchor is the true displacement)."""
    data = PairData(shards)
    cfg = dataclasses.replace(CFG, jitter=0.0, scale_aug=0.0)
    x0, cond, anchor = data.batch(np.array([1, 4]), 40, np.random.default_rng(3), cfg, anchors=True)
    assert anchor.shape == (2, 40, 3)
    for b, k in enumerate((1, 4)):
        for q, a in zip(x0[b, :, :3].numpy(), anchor[b].numpy()):
            i = np.flatnonzero(np.all(np.isclose(data.target_points[k], q, atol=1e-6), axis=1))
            assert len(i) >= 1 and np.allclose(data.target_on_shape[k][i[0]], a, atol=1e-6)
    # with the anisotropic scaling both move together: displacements stay small (the raw data's bound)
    x0, _, anchor = data.batch(np.array([1, 4]), 40, np.random.default_rng(3), CFG, anchors=True)
    raw = np.abs(data.target_points[[1, 4]] - data.target_on_shape[[1, 4]]).max()
    assert np.abs(x0[..., :3].numpy() - anchor.numpy()).max() <= 1.3 * raw + 1e-6


def test_an_anchored_model_trains_resumes_and_publishes(shards, tmp_path):
    run = tmp_path / "run"
    cfg = dataclasses.replace(CFG, preset="tiny", steps=4)
    from polycubenet.model import preset as model_preset

    mcfg = dataclasses.replace(model_preset("tiny"), anchored=True)
    out = train(shards, run, cfg, eval_dir=shards, progress=False, model_config=mcfg)
    assert out["step"] == 4 and np.isfinite(out["loss_l2"]) and np.isfinite(out["heldout_l2"])
    from polycubenet.model.checkpoint import load_checkpoint, publish

    pub = publish(run / "last.pt", tmp_path / "pub.pt")
    loaded = load_checkpoint(pub)
    assert loaded.model.config.anchored and loaded.meta["cpu_hours"] > 0


def test_anchor_normals_are_the_parts_normals_and_turn_with_the_scaling(shards):
    """With 6-channel anchors each anchor also carries the part's unit normal at its point (that of the
    nearest condition point); an anisotropic scaling turns it as a normal turns (inverse scale)."""
    data = PairData(shards)
    cfg = dataclasses.replace(CFG, jitter=0.0, scale_aug=0.0)
    _, _, anchor = data.batch(np.array([2]), 64, np.random.default_rng(5), cfg, anchors=6)
    a = anchor[0].numpy()
    assert a.shape == (64, 6)
    np.testing.assert_allclose(np.linalg.norm(a[:, 3:], axis=1), 1.0, atol=1e-5)
    j = np.argmin(((data.cond[2][None] - a[:, None, :3]) ** 2).sum(-1), axis=1)
    assert np.mean(np.sum(data.cond_normals[2][j] * a[:, 3:], axis=1) > 0.99) > 0.95
    # under the anisotropic scaling the same draws give the same points: their normals are n / s, renormalised
    x_raw, _, _ = data.batch(np.array([2]), 64, np.random.default_rng(5), cfg, anchors=6)
    _, _, scaled = data.batch(np.array([2]), 64, np.random.default_rng(5), CFG, anchors=6)
    sc = scaled[0].numpy()
    np.testing.assert_allclose(np.linalg.norm(sc[:, 3:], axis=1), 1.0, atol=1e-5)
    off_axis = np.abs(a[:, 3:]).max(1) < 0.95
    if off_axis.any():  # a normal not along an axis turns
        assert np.abs(sc[off_axis, 3:] - a[off_axis, 3:]).max() > 1e-3


def test_an_anchor_normals_model_starts_as_the_anchored_one_it_widens(shards, tmp_path):
    """``--init`` from an anchored model without normals: the input projection gets zero columns for
    the normal, so the new model computes exactly the old function until it trains."""
    from polycubenet.model import preset as model_preset
    from polycubenet.model.checkpoint import load_checkpoint, publish

    old_cfg = dataclasses.replace(model_preset("tiny"), anchored=True)
    train(shards, tmp_path / "old", dataclasses.replace(CFG, preset="tiny", steps=3), progress=False,
          model_config=old_cfg)
    old = load_checkpoint(publish(tmp_path / "old" / "last.pt", tmp_path / "old.pt")).model.float().eval()
    new_cfg = dataclasses.replace(old_cfg, anchor_normals=True)
    train(shards, tmp_path / "new", dataclasses.replace(CFG, preset="tiny", steps=1, lr=0.0), progress=False,
          model_config=new_cfg, init=tmp_path / "old" / "last.pt")
    new = load_checkpoint(publish(tmp_path / "new" / "last.pt", tmp_path / "new.pt")).model.float().eval()
    assert new.config.anchor_normals and new.denoiser.embed.proj.weight.shape[1] == \
        old.denoiser.embed.proj.weight.shape[1] + 3
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, 20, 6, generator=g)
    cond = torch.randn(1, 30, 3, generator=g)
    anchor = torch.randn(1, 20, 3, generator=g)
    normal = torch.nn.functional.normalize(torch.randn(1, 20, 3, generator=g), dim=-1)
    t = torch.tensor([300])
    with torch.no_grad():
        a = old(x, t, cond, anchor=anchor)
        b = new(x, t, cond, anchor=torch.cat([anchor, normal], -1))
    torch.testing.assert_close(a, b, atol=1e-3, rtol=1e-3)  # float16 publishing
    with pytest.raises(ValueError, match="anchors have 3 channels"):
        new(x, t, cond, anchor=anchor)


def _grown_from_tiny(shards, tmp_path, **denoiser):
    """A tiny anchored model trained 3 steps, and a model whose denoiser differs by ``denoiser`` started from
    it by ``--init`` (one step at learning rate 0): ``(old, new, new config)``."""
    from polycubenet.model import preset as model_preset

    old_cfg = dataclasses.replace(model_preset("tiny"), anchored=True)
    train(shards, tmp_path / "old", dataclasses.replace(CFG, steps=3), progress=False, model_config=old_cfg)
    old = load_checkpoint(tmp_path / "old" / "last.pt").model.eval()
    new_cfg = dataclasses.replace(old_cfg, denoiser=dataclasses.replace(old_cfg.denoiser, **denoiser))
    train(shards, tmp_path / "new", dataclasses.replace(CFG, steps=1, lr=0.0), progress=False,
          model_config=new_cfg, init=tmp_path / "old" / "last.pt")
    return old, load_checkpoint(tmp_path / "new" / "last.pt").model.eval(), new_cfg


def _assert_same_function(a, b):
    g = torch.Generator().manual_seed(0)
    x, cond, anchor = torch.randn(2, 20, 6, generator=g), torch.randn(2, 30, 3, generator=g), torch.randn(2, 20, 3, generator=g)
    t = torch.tensor([300, 900])
    with torch.no_grad():
        torch.testing.assert_close(b(x, t, cond, anchor=anchor), a(x, t, cond, anchor=anchor))


def test_a_deeper_model_starts_as_the_shallower_one_it_grows(shards, tmp_path):
    """``--init`` into a preset with more latent layers per block (``cpu-anchored-normals-deep`` over
    ``cpu-anchored-normals``): the added layers start as identities, so the deeper model computes the
    shallower one's function until it trains; they are fresh, not zero, once it has trained."""
    old, new, deep_cfg = _grown_from_tiny(shards, tmp_path, layers=3)
    assert len(new.denoiser.blocks[0].layers) == 3 and len(old.denoiser.blocks[0].layers) == 1
    _assert_same_function(old, new)
    # and the added layers learn: a step with a learning rate moves their zeroed projections
    train(shards, tmp_path / "more", dataclasses.replace(CFG, steps=2, warmup=0, lr=1e-2), progress=False,
          model_config=deep_cfg, init=tmp_path / "old" / "last.pt")
    grown = load_checkpoint(tmp_path / "more" / "last.pt").model
    assert grown.denoiser.blocks[0].layers[2].ff.net[-1].weight.abs().sum() > 0


def test_a_wider_write_network_starts_as_the_narrower_one_it_widens(shards, tmp_path):
    """``--init`` into a preset with wider per-point feed-forward layers (``cpu-anchored-normals-wide-write``
    over ``cpu-anchored-normals``): the old hidden units are kept, the added ones start with zero output
    weights, so the wider model computes the narrower one's function until it trains; then they learn."""
    old, new, wide_cfg = _grown_from_tiny(shards, tmp_path, write_mlp_ratio=6.0)
    w_old, w_new = old.denoiser.blocks[0].write_ff.net[0].weight, new.denoiser.blocks[0].write_ff.net[0].weight
    assert w_new.shape[0] == 3 * w_old.shape[0]  # 6.0 against the preset's 2.0
    assert new.denoiser.blocks[0].read_ff.net[0].weight.shape == old.denoiser.blocks[0].read_ff.net[0].weight.shape
    _assert_same_function(old, new)
    # the added units are live (fresh input weights) and learn: a step moves their zero output weights
    n_old = w_old.shape[0]
    assert w_new[n_old:].abs().sum() > 0
    train(shards, tmp_path / "more", dataclasses.replace(CFG, steps=2, warmup=0, lr=1e-2), progress=False,
          model_config=wide_cfg, init=tmp_path / "old" / "last.pt")
    grown = load_checkpoint(tmp_path / "more" / "last.pt").model
    assert grown.denoiser.blocks[0].write_ff.net[2].weight[:, n_old:].abs().sum() > 0


def test_a_deeper_and_wider_model_starts_as_the_one_it_grows(shards, tmp_path):
    """``--init`` into a preset that is both deeper and wider (``cpu-anchored-normals-big`` over
    ``cpu-anchored-normals``): the added latent layers start as identities and the added hidden units with zero
    output weights, both at once, so the larger model computes the smaller one's function until it trains."""
    from polycubenet.model import preset as model_preset

    big, base = model_preset("cpu-anchored-normals-big"), model_preset("cpu-anchored-normals")
    assert big.denoiser.layers > base.denoiser.layers and big.denoiser.write_mlp_ratio > base.denoiser.mlp_ratio
    assert dataclasses.replace(big, denoiser=base.denoiser) == base  # only the denoiser's sizes differ
    old, new, _ = _grown_from_tiny(shards, tmp_path, layers=3, write_mlp_ratio=4.0)
    assert len(new.denoiser.blocks[0].layers) == 3 and len(old.denoiser.blocks[0].layers) == 1
    assert new.denoiser.blocks[0].write_ff.net[0].weight.shape[0] > old.denoiser.blocks[0].write_ff.net[0].weight.shape[0]
    _assert_same_function(old, new)


def test_a_growing_folder_is_reread_loading_only_the_new_shards(shards, tmp_path, monkeypatch):
    import shutil

    import polycubenet.train as tr

    grow = tmp_path / "grow"
    grow.mkdir()
    files = sorted(shards.glob("shard-*.npz"))
    shutil.copy(files[0], grow / files[0].name)
    loads = []
    real = tr.load_shard
    monkeypatch.setattr(tr, "load_shard", lambda p: loads.append(p.name) or real(p))
    cache: dict = {}
    first = PairData(grow, cache=cache)
    first_normals = first.anchor_normals.copy()
    shutil.copy(files[1], grow / files[1].name)
    second = PairData(grow, cache=cache)
    assert loads == [files[0].name, files[1].name]  # the first shard was not read again
    assert len(second) == 6 and np.array_equal(second.cond[:3], first.cond)
    # anchor normals: the cached first shard's plus the new one's, as an uncached read computes them
    fresh = PairData(grow).anchor_normals
    assert np.array_equal(second.anchor_normals, fresh) and np.array_equal(fresh[:3], first_normals)
    # each pair is held once: the cached shards are views of the arrays the training draws from
    for d, lo in zip((cache[str((grow / f.name).resolve())] for f in files[:2]), (0, 3)):
        assert np.shares_memory(d["cond_points"], second.cond) and np.array_equal(d["cond_points"], second.cond[lo:lo + 3])
        assert np.shares_memory(d["anchor_normals"], second.anchor_normals)
    # subsampled points are distinct within a pair
    ci = tr._subsample(np.random.default_rng(0), 5, 128, 100)
    assert ci.shape == (5, 100) and all(len(set(row)) == 100 for row in ci)


def test_fit_steps_ends_the_cosine_with_the_time_limit(shards, tmp_path):
    cfg = dataclasses.replace(CFG, steps=10**6, warmup=2, log_every=2, ckpt_every=10**6, lr=1e-3, min_lr_ratio=0.1,
                              fit_steps=True)
    out = train(shards, tmp_path / "run", cfg, progress=False, max_seconds=6.0)
    assert out["step"] < 10**6
    # the schedule was re-fitted to the pace: it ends near its floor, not at the start of a 10**6-step cosine
    assert out["lr"] < 0.2 * cfg.lr
    s = torch.load(tmp_path / "run" / "last.pt", map_location="cpu", weights_only=False)
    assert s["gpu_hours"] == 0.0 and s["cpu_hours"] > 0  # a CPU run adds CPU-hours only


def test_boolean_flags_parse_false_as_false(tmp_path, shards):
    from polycubenet.train import main

    # --fit-steps false with a time limit runs the full (short) schedule instead of fitting it
    assert main(["--data", str(shards), "--out", str(tmp_path / "r"), "--preset", "tiny", "--steps", "4",
                 "--batch", "2", "--points", "32", "--warmup", "1", "--threads", "1", "--fit-steps", "false",
                 "--max-minutes", "5", "--no-progress"]) == 0
    s = torch.load(tmp_path / "r" / "last.pt", map_location="cpu", weights_only=False)
    assert s["train_config"]["fit_steps"] is False and s["step"] == 4


def test_ema_update_is_the_moving_average():
    from polycubenet.train import ema_update

    torch.manual_seed(0)
    model, ema = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
    before = [p.detach().clone() for p in ema.parameters()]
    ema_update(ema, model, 0.9)
    for e, b, m in zip(ema.parameters(), before, model.parameters()):
        assert torch.allclose(e, 0.9 * b + 0.1 * m)


def test_device_batches_draw_what_the_numpy_builder_draws(shards):
    """The GPU training's builder (run here on the CPU): every drawn row is a distinct subset of its own
    pair's points, target, normal and anchor channels from the same point, and with the scaling on the
    full condition comes back to diagonal 1 and the anchor normals stay unit, as ``PairData.batch``."""
    data = PairData(shards)
    dev = DevicePairs(data, torch.device("cpu"), anchors=6)
    assert len(dev) == len(data)
    gen = torch.Generator().manual_seed(0)
    x0, cond, anchor = dev.batch(np.array([1, 4, 1]), 40, gen, dataclasses.replace(CFG, jitter=0.0, scale_aug=0.0))
    assert x0.shape == (3, 40, 6) and cond.shape == (3, 40, 3) and anchor.shape == (3, 40, 6)
    for b, k in enumerate((1, 4, 1)):
        full = np.concatenate([data.target_points[k], data.target_normals[k], data.target_on_shape[k],
                               data.anchor_normals[k]], axis=1)
        row = np.concatenate([x0[b].numpy(), anchor[b].numpy()], axis=1)
        hit = np.all(np.isclose(row[:, None, :], full[None], atol=1e-6), axis=2)  # (40, M): same point, all channels
        assert hit.any(axis=1).all()
        assert len({tuple(r) for r in np.round(row[:, :3], 6)}) == 40  # distinct within the row
        c = cond[b].numpy()
        assert np.isclose(c[:, None, :], data.cond[k][None], atol=1e-6).all(axis=2).any(axis=1).all()
    assert not torch.equal(x0[0], x0[2])  # the same pair twice: two draws
    x0, cond, anchor = dev.batch(np.array([0, 2, 5]), 128, gen, dataclasses.replace(CFG, jitter=0.0))
    d = np.linalg.norm(cond.numpy().max(axis=1) - cond.numpy().min(axis=1), axis=-1)
    np.testing.assert_allclose(d, 1.0, atol=1e-4)  # all 128 condition points: the full cloud, diagonal 1
    np.testing.assert_allclose(np.linalg.norm(anchor[..., 3:].numpy(), axis=-1), 1.0, atol=1e-5)
    # every point drawn without the scaling: the numpy builder's cloud, in another order
    cfg0 = dataclasses.replace(CFG, jitter=0.0, scale_aug=0.0)
    x0, cond = DevicePairs(data, torch.device("cpu")).batch(np.array([3]), 128, gen, cfg0)
    ref, ref_cond = data.batch(np.array([3]), 128, np.random.default_rng(0), cfg0)
    for a, b in ((x0, ref), (cond, ref_cond)):
        np.testing.assert_allclose(np.sort(a[0].numpy(), axis=0), np.sort(b[0].numpy(), axis=0), atol=1e-6)


def _anchored_probe():
    """A fixed input ``(x, t, cond, anchor)`` of a tiny anchored model with anchor normals."""
    g = torch.Generator().manual_seed(0)
    x, cond = torch.randn(2, 20, 6, generator=g), torch.randn(2, 30, 3, generator=g)
    anchor = torch.cat([torch.randn(2, 20, 3, generator=g),
                        torch.nn.functional.normalize(torch.randn(2, 20, 3, generator=g), dim=-1)], -1)
    return x, torch.tensor([300, 900]), cond, anchor


def test_a_local_context_model_starts_as_the_one_without_and_its_new_module_has_its_own_rate(shards, tmp_path):
    """``--init`` into a preset with a local context (``cpu-anchored-normals-local`` over
    ``cpu-anchored-normals``): its output projection starts at zero, so the model computes the old
    function; ``fresh_lr_mult`` 0 then keeps the new module where it started while the rest trains,
    and a positive one moves it (the multiplier survives a resume)."""
    from polycubenet.model import preset as model_preset

    old_cfg = dataclasses.replace(model_preset("tiny"), anchored=True, anchor_normals=True)
    train(shards, tmp_path / "old", dataclasses.replace(CFG, steps=3), progress=False, model_config=old_cfg)
    old = load_checkpoint(tmp_path / "old" / "last.pt").model.eval()
    new_cfg = dataclasses.replace(old_cfg, local_k=4)
    x, t, cond, anchor = _anchored_probe()
    frozen = dataclasses.replace(CFG, steps=4, warmup=0, lr=1e-2, fresh_lr_mult=0.0)
    train(shards, tmp_path / "frozen", dataclasses.replace(frozen, steps=2), progress=False, model_config=new_cfg,
          init=tmp_path / "old" / "last.pt")
    train(shards, tmp_path / "frozen", frozen, progress=False, model_config=new_cfg)  # resumed to step 4
    end = load_checkpoint(tmp_path / "frozen" / "last.pt").model.eval()
    assert end.denoiser.local.out.weight.abs().sum() == 0  # the multiplier 0 held across the resume
    assert not torch.equal(end.denoiser.out.weight, old.denoiser.out.weight)  # while the rest trained
    train(shards, tmp_path / "zero", dataclasses.replace(CFG, steps=1, lr=0.0), progress=False, model_config=new_cfg,
          init=tmp_path / "old" / "last.pt")
    same = load_checkpoint(tmp_path / "zero" / "last.pt").model.eval()
    with torch.no_grad():
        torch.testing.assert_close(same(x, t, cond, anchor=anchor), old(x, t, cond, anchor=anchor))
    train(shards, tmp_path / "moves", dataclasses.replace(frozen, fresh_lr_mult=1.0), progress=False,
          model_config=new_cfg, init=tmp_path / "old" / "last.pt")
    moved = load_checkpoint(tmp_path / "moves" / "last.pt").model
    assert moved.denoiser.local.out.weight.abs().sum() > 0


def test_the_condition_has_its_own_resolution(shards):
    """``cond_points``: the condition is drawn at its own resolution, the target at ``points``."""
    data = PairData(shards)
    cfg = dataclasses.replace(CFG, points=32, cond_points=96)
    x0, cond, anchor = data.batch(np.arange(3), 32, np.random.default_rng(0), cfg, anchors=6)
    assert x0.shape == (3, 32, 6) and anchor.shape == (3, 32, 6) and cond.shape == (3, 96, 3)
    dev = DevicePairs(data, torch.device("cpu"), anchors=6)
    x0, cond, anchor = dev.batch(np.arange(3), 32, torch.Generator().manual_seed(0), cfg)
    assert x0.shape == (3, 32, 6) and cond.shape == (3, 96, 3)


def test_recycle_needs_a_recycling_model(tmp_path):
    """``--recycle`` on a preset whose model takes no previous estimate is refused before any training,
    naming the preset to use."""
    from polycubenet.train import TrainConfig, train

    with pytest.raises(ValueError, match="cpu-anchored-normals-recycle"):
        train(tmp_path / "data", tmp_path / "run", TrainConfig(preset="tiny", recycle=0.5, steps=1))
    assert not (tmp_path / "run").exists()


def test_face_weights_lift_the_points_of_a_small_plane():
    """Target points on a plane that holds few of the pair's points weigh more than those on a large
    one, by the share to -power; the same coordinate on another axis or side is another plane."""
    from polycubenet.train import face_weights

    n_big, n_small = 90, 10
    pts = torch.zeros(1, n_big + n_small, 6)
    pts[0, :n_big, :3] = torch.rand(n_big, 3)
    pts[0, :n_big, 2] = 0.0  # the bottom z = 0, normal -z
    pts[0, :n_big, 5] = -1.0
    pts[0, n_big:, :3] = torch.rand(n_small, 3)
    pts[0, n_big:, 2] = 0.3  # a small face z = 0.3, normal +z
    pts[0, n_big:, 5] = 1.0
    w = face_weights(pts, 0.5)
    assert float(w.mean()) == pytest.approx(1.0, rel=1e-5)
    assert torch.allclose(w[0, :n_big], w[0, 0]) and torch.allclose(w[0, n_big:], w[0, n_big])
    assert float(w[0, n_big] / w[0, 0]) == pytest.approx((0.1 / 0.9) ** -0.5, rel=1e-4)
    # the small face's points turned to face -z at z = 0 join the bottom plane: all weights equal
    same = pts.clone()
    same[0, n_big:, 2], same[0, n_big:, 5] = 0.0, -1.0
    assert torch.allclose(face_weights(same, 0.5), torch.ones(1, n_big + n_small))
    # at z = 0 but facing +z: another plane (the other side), weighted as the small one was
    other_side = same.clone()
    other_side[0, n_big:, 5] = 1.0
    assert torch.allclose(face_weights(other_side, 0.5), w)
    # the cap (a multiple of the pair's mean, before the final scaling) bounds a lone point's weight:
    # uncapped it would be 90 times the bottom's, capped it weighs what the capped small plane does
    lone = pts.clone()
    lone[0, -1, 2] = 0.7
    lw = face_weights(lone, 1.0, cap=3.0)
    assert float(lw[0, -1]) == pytest.approx(float(lw[0, n_big]), rel=1e-5)
    assert float(lw[0, -1] / lw[0, 0]) < 10.0


def test_face_weight_trains_and_is_recorded_in_the_recipe(shards, tmp_path):
    """--face-weight changes the loss of the same draws, and is a recipe flag: a run records it, and
    recipe_flags gives it back for a continuation."""
    from polycubenet.train import recipe_flags

    cfg = dataclasses.replace(CFG, preset="tiny", steps=2, log_every=1, ckpt_every=2)
    losses = {}
    for fw in (0.0, 0.5):
        run = tmp_path / f"fw{fw}"
        train(shards, run, dataclasses.replace(cfg, face_weight=fw), progress=False)
        rows = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
        losses[fw] = rows[0]["loss_l2"]
        flags = recipe_flags(run / "last.pt")
        assert float(flags[flags.index("--face-weight") + 1]) == fw
    assert np.isfinite(losses[0.5]) and losses[0.5] != pytest.approx(losses[0.0], rel=1e-4)


def test_slant_weights_weigh_the_points_of_slanted_faces():
    """A point whose part normal is more than 15 degrees from every axis weighs 1 + gain times a flat one, the
    batch's mean weight stays 1, and the sign or length of a normal does not matter."""
    import numpy as np
    import torch

    from polycubenet.train import slant_weights

    t = np.radians(30.0)
    normals = [[0, 0, 1], [-1, 0, 0], [np.sin(t), 0, np.cos(t)], [0, -2 * np.cos(np.radians(10)), 2 * np.sin(np.radians(10))]]
    anchor = torch.tensor([[[0.0, 0.0, 0.0, *n] for n in normals]])
    w = slant_weights(anchor, 3.0)
    assert w.shape == (1, 4)
    assert float(w.mean()) == pytest.approx(1.0)
    assert float(w[0, 2] / w[0, 0]) == pytest.approx(4.0)  # the 30-degree face
    assert float(w[0, 3]) == pytest.approx(float(w[0, 1]))  # 10 degrees off an axis: flat
    assert torch.allclose(slant_weights(anchor, 0.0), torch.ones(1, 4))


def test_a_genus_model_starts_as_the_one_without_and_learns_the_genus_it_is_told(shards, tmp_path):
    """``--init`` into a preset told the part's genus (``cpu-anchored-normals-genus`` over
    ``cpu-anchored-normals``): the genus vectors start at zero, so every genus gives the old function;
    training moves the vectors of the genera its pairs have (and of "unknown", ``genus_drop``), after
    which the genus changes the prediction, a genus past the table's end shares its last class and
    None is "unknown"."""
    from polycubenet.model import preset as model_preset
    from polycubenet.train import recipe_flags

    old_cfg = dataclasses.replace(model_preset("tiny"), anchored=True, anchor_normals=True)
    train(shards, tmp_path / "old", dataclasses.replace(CFG, steps=2), progress=False, model_config=old_cfg)
    old = load_checkpoint(tmp_path / "old" / "last.pt").model.eval()
    new_cfg = dataclasses.replace(old_cfg, genus_classes=3)
    x, t, cond, anchor = _anchored_probe()
    train(shards, tmp_path / "zero", dataclasses.replace(CFG, steps=1, lr=0.0), progress=False, model_config=new_cfg,
          init=tmp_path / "old" / "last.pt")
    same = load_checkpoint(tmp_path / "zero" / "last.pt").model.eval()
    with torch.no_grad():
        ref = old(x, t, cond, anchor=anchor)
        for genus in (None, [0, 2], [1, -1]):
            torch.testing.assert_close(same(x, t, cond, anchor=anchor, genus=genus), ref)
        with pytest.raises(ValueError, match="takes no genus"):
            old(x, t, cond, anchor=anchor, genus=[1, 1])
    genera = set(int(v) for v in PairData(shards).genus)
    train(shards, tmp_path / "moves", dataclasses.replace(CFG, steps=3, warmup=0, lr=1e-2, genus_drop=0.5),
          progress=False, model_config=new_cfg, init=tmp_path / "old" / "last.pt")
    moved = load_checkpoint(tmp_path / "moves" / "last.pt").model.eval()
    rows = moved.genus.weight.abs().sum(dim=1)
    for k in {min(v, 2) for v in genera} | {3}:  # every class its pairs have, and "unknown"
        assert rows[k] > 0
    with torch.no_grad():
        a, b = moved(x, t, cond, anchor=anchor, genus=[0, 0]), moved(x, t, cond, anchor=anchor, genus=[2, 2])
        assert not torch.allclose(a, b)
        torch.testing.assert_close(moved(x, t, cond, anchor=anchor, genus=[7, 9]), b)
        torch.testing.assert_close(moved(x, t, cond, anchor=anchor, genus=None),
                                   moved(x, t, cond, anchor=anchor, genus=[-1, -1]))
    flags = recipe_flags(tmp_path / "moves" / "last.pt")
    assert float(flags[flags.index("--genus-drop") + 1]) == 0.5
