"""The network: attention, two-stream blocks, chunked (memory-linear) inference, presets."""

import numpy as np
import pytest
import torch

from polycubenet.model import Attention, PolycubeNet, StreamConfig, preset
from polycubenet.model.__main__ import main as params_main
from polycubenet.model.config import ModelConfig


@pytest.fixture
def tiny(tiny_net):
    return tiny_net


def test_streaming_attention_equals_full_softmax():
    torch.manual_seed(1)
    att = Attention(32, 4)
    q = torch.randn(2, 9, 32)
    ctx = torch.randn(2, 300, 32)
    full = att(q, ctx)
    for chunk in (1, 7, 64, 299):
        np.testing.assert_allclose(att(q, ctx, chunk=chunk).detach(), full.detach(), atol=2e-5)


def test_chunked_denoiser_equals_unchunked(tiny):
    torch.manual_seed(2)
    cond = torch.randn(2, 150, 3)
    x = torch.randn(2, 211, 6)
    t = torch.tensor([5, 900])
    with torch.no_grad():
        z = tiny.encode(cond)
        z_chunk = tiny.encode(cond, chunk=16)
        np.testing.assert_allclose(z_chunk, z, atol=2e-5)
        a = tiny.denoise(x, t, z)
        b = tiny.denoise(x, t, z, chunk=13)
    np.testing.assert_allclose(b, a, atol=2e-5)
    assert float(a.abs().mean()) > 1e-3  # not a zero output that would make the check vacuous


def test_any_resolution_in_and_out(tiny):
    with torch.no_grad():
        for n_in, n_out in [(17, 5), (64, 1000), (500, 33)]:
            eps = tiny(torch.randn(1, n_out, 6), torch.tensor([10]), torch.randn(1, n_in, 3))
            assert eps.shape == (1, n_out, 6) and torch.isfinite(eps).all()


def test_points_are_processed_independently_given_the_latents(tiny):
    """The write step makes each output point depend on the latents, not on the other points:
    permuting the noisy points permutes the prediction (and nothing else changes)."""
    torch.manual_seed(3)
    x = torch.randn(1, 50, 6)
    cond = torch.randn(1, 40, 3)
    perm = torch.randperm(50)
    with torch.no_grad():
        a = tiny(x, torch.tensor([100]), cond)
        b = tiny(x[:, perm], torch.tensor([100]), cond)
    np.testing.assert_allclose(b, a[:, perm], atol=2e-5)


def test_condition_changes_the_prediction(tiny):
    torch.manual_seed(4)
    x = torch.randn(1, 30, 6)
    with torch.no_grad():
        a = tiny(x, torch.tensor([100]), torch.randn(1, 40, 3))
        b = tiny(x, torch.tensor([100]), torch.randn(1, 40, 3))
    assert float((a - b).abs().max()) > 1e-4


def test_paper_preset_has_the_papers_layout():
    cfg = preset("paper")
    net = PolycubeNet(cfg)
    den, enc = net.denoiser, net.encoder
    assert len(den.blocks) == 6 and all(len(b.layers) == 4 for b in den.blocks)
    assert tuple(den.latents.shape) == (256, 256)
    assert den.blocks[0].read.heads == 8
    assert len(enc.blocks) == 6 and all(len(b.layers) == 6 for b in enc.blocks)
    assert tuple(enc.latents.shape) == (64, 256) and enc.blocks[0].read.heads == 8


def test_denoiser_latents_are_condition_tokens_learned_latents_and_time(tiny):
    seen = {}
    den = tiny.denoiser
    h = den.blocks[0].read.register_forward_hook(lambda m, i, o: seen.update(z=o.shape))
    with torch.no_grad():
        den(torch.zeros(1, 4, 6), torch.tensor([3]), torch.zeros(1, 8, 32))
    h.remove()
    assert seen["z"][1] == tiny.config.encoder.latents + tiny.config.denoiser.latents + 1


def test_config_round_trip_and_validation():
    cfg = preset("cpu")
    assert ModelConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ValueError, match="multiple of heads"):
        StreamConfig(blocks=1, layers=1, dim=30, latents=4, heads=4)
    with pytest.raises(ValueError, match="unknown model preset"):
        preset("huge")


def test_parameter_count_command(capsys):
    assert params_main(["--preset", "tiny", "--preset", "cpu"]) == 0
    out = capsys.readouterr().out
    n_tiny = sum(p.numel() for p in PolycubeNet(preset("tiny")).parameters())
    assert f"{n_tiny:,}" in out and "cpu" in out


def test_local_context_reads_the_nearest_condition_points_only():
    """Each anchor's feature changes when one of its k nearest condition points moves, not when a far
    one does; a condition cloud over ``ref`` points is read at an even stride."""
    from polycubenet.model.network import LocalContext

    torch.manual_seed(0)
    ctx = LocalContext(k=4, dim=16, anchor_dim=6, radius=0.1, ref=64)
    for p in ctx.out.parameters():  # it starts at zero (a no-op); give it an output to look at
        torch.nn.init.normal_(p)
    anchor = torch.tensor([[[0.0, 0.0, 0.0, 0.0, 0.0, 1.0]]])
    near = 0.05 * torch.randn(1, 4, 3)
    far = 3.0 + torch.rand(1, 20, 3)
    cond = torch.cat([near, far], dim=1)
    base = ctx(anchor, cond)
    moved_far = cond.clone()
    moved_far[0, 10] += 0.5
    torch.testing.assert_close(ctx(anchor, moved_far), base)
    moved_near = cond.clone()
    moved_near[0, 1] += torch.tensor([0.0, 0.0, 0.03])
    assert (ctx(anchor, moved_near) - base).abs().max() > 1e-4
    big = torch.randn(1, 128, 3)
    torch.testing.assert_close(ctx(anchor, big), ctx(anchor, big[:, ::2]))
    # chunked over anchors = at once
    many = torch.cat([torch.randn(2, 50, 3), torch.nn.functional.normalize(torch.randn(2, 50, 3), dim=-1)], -1)
    torch.testing.assert_close(ctx(many, big.expand(2, -1, -1), chunk=7), ctx(many, big.expand(2, -1, -1)))


def test_recycling_model_starts_as_its_source_and_reads_its_previous_estimate():
    """A recycling model given a plain model's weights computes the plain model's function, with or
    without an estimate (its projection starts at zero); once that projection is trained, the estimate
    changes the output; a plain model refuses an estimate."""
    import dataclasses

    torch.manual_seed(0)
    plain_cfg = dataclasses.replace(preset("tiny"), anchored=True, anchor_normals=True)
    plain = PolycubeNet(plain_cfg).eval()
    for p in plain.denoiser.out.parameters():  # a trained-like, non-zero output
        torch.nn.init.normal_(p, std=0.1)
    rec = PolycubeNet(dataclasses.replace(plain_cfg, recycle=True)).eval()
    missing, unexpected = rec.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == sorted(f"denoiser.recycle.{k}" for k in rec.denoiser.recycle.state_dict())
    assert not unexpected
    x_t, cond = torch.randn(2, 10, 6), torch.randn(2, 20, 3)
    anchor, t = torch.randn(2, 10, 6), torch.tensor([1023, 1023])
    est = torch.rand(2, 10, 6) - 0.5
    with torch.no_grad():
        base = plain(x_t, t, cond, anchor=anchor)
        torch.testing.assert_close(rec(x_t, t, cond, anchor=anchor), base)
        torch.testing.assert_close(rec(x_t, t, cond, anchor=anchor, x0_prev=est), base)
        torch.nn.init.normal_(rec.denoiser.recycle[2].weight, std=0.1)
        changed = rec(x_t, t, cond, anchor=anchor, x0_prev=est)
        assert (changed - base).abs().max() > 1e-3
        # no estimate is the zero estimate (a first evaluation)
        torch.testing.assert_close(rec(x_t, t, cond, anchor=anchor),
                                   rec(x_t, t, cond, anchor=anchor, x0_prev=torch.zeros_like(est)))
    with pytest.raises(ValueError, match="previous estimate"):
        plain(x_t, t, cond, anchor=anchor, x0_prev=est)
