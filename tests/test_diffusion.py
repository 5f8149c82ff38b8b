"""Diffusion: schedule, hybrid loss, DDIM pairs, DDIM(eta=1, every step) == DDPM, reproducibility."""

import numpy as np
import pytest
import torch

from polycubenet.model import Diffusion, PolycubeNet, preset
from polycubenet.model.diffusion import from_network, to_network


@pytest.fixture
def net(tiny_net):
    return tiny_net


def test_schedule():
    d = Diffusion()
    assert d.T == 1024
    ab = d.alpha_bar
    assert ab[0] > 0.999 and ab[-1] < 1e-3 and np.all(np.diff(ab) < 0)
    lin = Diffusion(schedule="linear")
    assert np.all(np.diff(lin.alpha_bar) < 0) and lin.alpha_bar[-1] < 1e-3
    with pytest.raises(ValueError):
        Diffusion(schedule="sigmoid")


def test_q_sample_matches_the_closed_form():
    d = Diffusion()
    x0 = torch.randn(3, 10, 6)
    noise = torch.randn(3, 10, 6)
    t = torch.tensor([0, 500, 1023])
    xt = d.q_sample(x0, t, noise)
    for i, ti in enumerate(t.tolist()):
        ab = d.alpha_bar[ti]
        np.testing.assert_allclose(xt[i], np.sqrt(ab) * x0[i] + np.sqrt(1 - ab) * noise[i], atol=1e-5)


def test_timestep_pairs():
    d = Diffusion()
    pairs = d.timestep_pairs()  # stride 4
    assert len(pairs) == 256 and pairs[0][0] == 1023 and pairs[-1] == (3, -1)
    assert all(a - b == 4 for a, b in pairs[:-1])
    p10 = d.timestep_pairs(steps=10)
    assert len(p10) == 10 and p10[0][0] == 1023 and p10[-1] == (0, -1)
    assert all(a > b for a, b in p10)
    assert d.timestep_pairs(steps=1) == [(1023, -1)]  # one step starts from pure noise, not from t = 0
    assert [a for a, _ in d.timestep_pairs(stride=1)] == list(range(1023, -1, -1))
    with pytest.raises(ValueError):
        d.timestep_pairs(steps=0)


def test_hybrid_loss_weights(net):
    d = Diffusion()
    x0 = torch.randn(2, 20, 6)
    cond = torch.randn(2, 30, 3)
    ws = []
    for s in range(30):
        loss, st = d.training_loss(net, x0, cond, generator=torch.Generator().manual_seed(s))
        assert 0.4 <= st["w"] < 0.8
        assert float(loss.detach()) == pytest.approx(st["w"] * st["l2"] + (1 - st["w"]) * st["l1"], rel=1e-5)
        ws.append(st["w"])
    assert np.ptp(ws) > 0.1  # w really is drawn per iteration
    loss, st = d.training_loss(net, x0, cond, loss="l2", generator=torch.Generator().manual_seed(0))
    assert st["w"] == 1.0 and float(loss.detach()) == pytest.approx(st["l2"], rel=1e-6)
    loss, st = d.training_loss(net, x0, cond, loss="l1", generator=torch.Generator().manual_seed(0))
    assert st["w"] == 0.0 and float(loss.detach()) == pytest.approx(st["l1"], rel=1e-6)
    with pytest.raises(ValueError):
        d.training_loss(net, x0, cond, loss="huber")


def test_ddim_with_eta_one_and_every_step_is_ddpm(net):
    d = Diffusion(T=64)
    cond = torch.randn(1, 25, 3)
    n = 12
    got = d.sample(net, cond, n, stride=1, eta=1.0, clip=None, generator=torch.Generator().manual_seed(7))
    # DDPM ancestral sampling written out independently, with the same random stream
    g = torch.Generator().manual_seed(7)
    x = torch.randn((1, n, 6), generator=g)
    with torch.no_grad():
        z = net.encode(cond)
        for t in range(63, -1, -1):
            eps = net.denoise(x, torch.tensor([t]), z)
            noise = torch.randn(x.shape, generator=g) if t > 0 else None
            x = d.ddpm_step(x, eps, t, noise)
    np.testing.assert_allclose(got, x, rtol=1e-5, atol=1e-4)  # equal to float32 rounding
    # and deterministic DDIM is a different sampler
    det = d.sample(net, cond, n, stride=1, eta=0.0, clip=None, generator=torch.Generator().manual_seed(7))
    assert float((det - got).abs().max()) > 1e-3


def test_sampling_is_reproducible_from_a_generator(net):
    d = Diffusion(T=64)
    cond = torch.randn(2, 20, 3)
    a = d.sample(net, cond, 9, stride=4, eta=0.5, generator=torch.Generator().manual_seed(3))
    b = d.sample(net, cond, 9, stride=4, eta=0.5, generator=torch.Generator().manual_seed(3))
    c = d.sample(net, cond, 9, stride=4, eta=0.5, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b) and not torch.equal(a, c)
    # one generator per element: element 1 does not depend on element 0
    gens = lambda: [torch.Generator().manual_seed(10), torch.Generator().manual_seed(11)]  # noqa: E731
    both = d.sample(net, cond, 9, steps=8, generator=gens())
    alone = d.sample(net, cond[1:], 9, steps=8, generator=[torch.Generator().manual_seed(11)])
    np.testing.assert_allclose(both[1:], alone, atol=1e-5)


def test_network_units_round_trip():
    p = torch.rand(5, 3) - 0.5
    n = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    x = to_network(p, n, 2.0)
    back = from_network(x * torch.tensor([1, 1, 1, 3, 3, 3.0]), 2.0)  # normals come back unit length
    np.testing.assert_allclose(back[:, :3], p, atol=1e-6)
    np.testing.assert_allclose(back[:, 3:], n, atol=1e-6)


def test_a_tiny_model_learns_one_pair():
    """The loss must fall when fitting a single pair: the objective, the gradients and the
    optimiser are wired together correctly."""
    torch.manual_seed(0)
    m = PolycubeNet(preset("tiny"))
    d = Diffusion()
    opt = torch.optim.AdamW(m.parameters(), lr=5e-3)
    g = torch.Generator().manual_seed(0)
    # a fixed "polycube": points on two faces of a box, with axis normals
    pts = torch.rand(1, 32, 3) - 0.5
    pts[0, :16, 0] = 0.5
    pts[0, 16:, 2] = -0.5
    nrm = torch.zeros(1, 32, 3)
    nrm[0, :16, 0] = 1
    nrm[0, 16:, 2] = -1
    x0 = to_network(pts, nrm, 2.0)
    cond = to_network(torch.rand(1, 32, 3) - 0.5, None, 2.0)
    t_eval = torch.tensor([200])
    noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(99))

    def err():
        with torch.no_grad():
            return float((m(d.q_sample(x0, t_eval, noise), t_eval, cond) - noise).pow(2).mean())

    before = err()
    for _ in range(120):
        loss, _ = d.training_loss(m, x0, cond, generator=g)
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = err()
    assert after < 0.5 * before, (before, after)


def test_zero_terminal_snr_schedule_needs_v_and_ends_in_pure_noise():
    d = Diffusion(schedule="cosine_ztsnr", prediction="v")
    ab = d.alpha_bar
    assert ab[-1] == 0.0 and np.all(np.diff(ab) < 0)
    assert ab[0] == pytest.approx(Diffusion().alpha_bar[0])  # the low-noise end is unchanged
    with pytest.raises(ValueError, match="needs prediction='v'"):
        Diffusion(schedule="cosine_ztsnr")
    with pytest.raises(ValueError):
        Diffusion(prediction="x0")
    # the recipe survives the checkpoint round trip; old checkpoints read as the paper's recipe
    d2 = Diffusion(schedule="cosine_ztsnr", prediction="v", min_snr=5.0, pairing="ot")
    assert Diffusion.from_dict(d2.to_dict()).to_dict() == d2.to_dict()
    old = Diffusion.from_dict({"T": 1024, "schedule": "cosine"})
    assert (old.prediction, old.pairing, old.min_snr) == ("eps", "random", None)


@pytest.mark.parametrize("schedule,prediction", [("cosine", "eps"), ("cosine", "v"), ("cosine_ztsnr", "v")])
def test_split_recovers_x0_and_noise_from_the_exact_target(schedule, prediction):
    """Given the exact network target, split() returns the true x0 and noise, also at t = T-1
    (where the zero-terminal-SNR schedule has ᾱ = 0 and eps prediction could not recover x0)."""
    d = Diffusion(schedule=schedule, prediction=prediction)
    x0 = torch.randn(1, 50, 6, dtype=torch.float64)
    noise = torch.randn(1, 50, 6, dtype=torch.float64)
    for t in (0, 300, 1023):
        ab = d.alpha_bar[t]
        xt = d.q_sample(x0, torch.tensor([t]), noise)
        target = noise if prediction == "eps" else np.sqrt(ab) * noise - np.sqrt(1 - ab) * x0
        x0_hat, eps_hat = d.split(target, xt, t)
        np.testing.assert_allclose(eps_hat, noise, atol=1e-8)
        if prediction == "v" or ab > 1e-6:  # eps prediction cannot see x0 at vanishing signal
            np.testing.assert_allclose(x0_hat, x0, atol=1e-6)


def test_ot_pairing_permutes_each_clouds_noise_to_a_cheaper_assignment():
    from polycubenet.model.diffusion import ot_pair_noise

    g = torch.Generator().manual_seed(0)
    x0 = torch.rand(3, 64, 6, generator=g) * 2 - 1
    noise = torch.randn(3, 64, 6, generator=g)
    paired = ot_pair_noise(x0, noise)
    for k in range(3):
        # the same set of noise points...
        a = np.sort(noise[k].numpy().round(6), axis=0)
        b = np.sort(paired[k].numpy().round(6), axis=0)
        np.testing.assert_array_equal(a, b)
        # ...assigned at a cost no greater than the identity (or any random) assignment
        cost = lambda n: float((x0[k] - n).pow(2).sum())  # noqa: E731
        assert cost(paired[k]) < cost(noise[k])
        assert cost(paired[k]) <= cost(noise[k, torch.randperm(64, generator=g)])


@pytest.mark.parametrize("kw", [dict(prediction="v", schedule="cosine_ztsnr"), dict(pairing="ot"),
                                dict(min_snr=5.0), dict(prediction="v", min_snr=5.0)])
def test_recipe_options_train_and_sample(net, kw):
    """Each recipe option gives a finite loss with gradients and a finite sample."""
    d = Diffusion(**kw)
    x0 = torch.randn(2, 20, 6)
    cond = torch.randn(2, 30, 3)
    loss, st = d.training_loss(net, x0, cond, generator=torch.Generator().manual_seed(1))
    loss.backward()
    assert np.isfinite(st["l2"]) and st["l2"] > 0
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())
    x = d.sample(net, cond, 16, steps=6, generator=torch.Generator().manual_seed(2))
    assert torch.isfinite(x).all() and float(x.abs().max()) <= 1.0 + 1e-5  # the last step returns the clipped x0


def test_t_bias_draws_timesteps_towards_the_noisy_end():
    """``t_bias`` 3 puts about 63 % of the draws in the last quarter of the schedule (uniform: 25 %),
    where a few-step sampler takes its first step; 1 keeps the uniform draw."""
    d = Diffusion(prediction="v", schedule="cosine_ztsnr")
    seen = {}

    def model(x_t, t, cond):
        seen.setdefault("t", []).append(t.clone())
        return torch.zeros_like(x_t)

    x0, cond = torch.randn(4000, 2, 6), torch.randn(4000, 2, 3)
    for bias in (1.0, 3.0):
        seen.clear()
        loss, _ = d.training_loss(model, x0, cond, generator=torch.Generator().manual_seed(0), t_bias=bias)
        t = seen["t"][0].double()
        assert torch.isfinite(loss) and t.min() >= 0 and t.max() <= d.T - 1
        late = float((t >= 0.75 * d.T).double().mean())
        assert abs(late - (0.25 if bias == 1.0 else 0.25 ** (1 / 3))) < 0.03, (bias, late)


def test_t_uniform_gives_a_share_of_the_batch_uniform_timesteps():
    """With the one-step recipe's ``t_bias`` 1000 every draw sits at the noisy end; ``t_uniform`` 0.5 gives
    about half the pairs a uniform timestep instead (a quarter then fall in the low-noise half, where a
    refining DDIM step evaluates the network), and the rest keep the biased draw."""
    d = Diffusion(prediction="v", schedule="cosine_ztsnr")
    seen = {}

    def model(x_t, t, cond):
        seen["t"] = t.clone()
        return torch.zeros_like(x_t)

    x0, cond = torch.randn(4000, 2, 6), torch.randn(4000, 2, 3)
    for share in (0.0, 0.5):
        d.training_loss(model, x0, cond, generator=torch.Generator().manual_seed(1), t_bias=1000.0, t_uniform=share)
        t = seen["t"].double()
        assert t.min() >= 0 and t.max() <= d.T - 1
        low = float((t < 0.5 * d.T).double().mean())
        end = float((t >= d.T - 2).double().mean())
        if share == 0.0:
            assert low < 0.002 and end > 0.99, (low, end)
        else:
            assert abs(low - 0.25) < 0.03 and abs(end - 0.5) < 0.03, (low, end)


class _Recording(torch.nn.Module):
    """A stand-in recycling model: records what each evaluation got and answers a fixed v."""

    def __init__(self):
        super().__init__()
        self.config = type("C", (), {"recycle": True, "point_dim": 6})()
        self.calls = []

    def encode(self, cond, chunk=None):
        return cond

    def denoise(self, x_t, t, z_c, chunk=None, x0_prev=None):
        return self(x_t, t, z_c, x0_prev=x0_prev)

    def forward(self, x_t, t, cond, x0_prev=None):
        self.calls.append(None if x0_prev is None else x0_prev.clone())
        return 0.3 * torch.ones_like(x_t) + (0.0 if x0_prev is None else 0.5 * x0_prev)


def test_recycle_trains_the_second_evaluation_on_the_first_ones_clean_estimate():
    """``recycle`` 1: the loss is that of a second evaluation given the first's clean estimate (clipped to the
    sampling step's range); ``recycle`` 0: one evaluation, no estimate; the sampler gives a recycling model
    its last estimate at every evaluation, ``1 + recycles`` evaluations per step."""
    d = Diffusion(prediction="v", schedule="cosine_ztsnr")
    x0, cond = 0.2 * torch.randn(3, 8, 6), torch.randn(3, 5, 3)
    m = _Recording()
    _, stats = d.training_loss(m, x0, cond, generator=torch.Generator().manual_seed(0), t_bias=1000.0, recycle=0.0)
    assert len(m.calls) == 1 and m.calls[0] is None and not stats["recycled"]
    m.calls.clear()
    g = torch.Generator().manual_seed(0)
    _, stats = d.training_loss(m, x0, cond, generator=g, t_bias=1000.0, recycle=1.0)
    assert stats["recycled"] and len(m.calls) == 2 and m.calls[0] is None
    # at t = T - 1 (zero terminal SNR) the clean estimate of a v answer is -v: here -0.3 everywhere
    torch.testing.assert_close(m.calls[1], torch.full_like(x0, -0.3), atol=1e-3, rtol=0)
    m.calls.clear()
    d.sample(m, cond, 8, steps=1, generator=torch.Generator().manual_seed(0), recycles=2)
    assert len(m.calls) == 3 and m.calls[0] is None
    torch.testing.assert_close(m.calls[1], torch.full_like(x0, -0.3), atol=1e-3, rtol=0)
    torch.testing.assert_close(m.calls[2], torch.full_like(x0, -(0.3 - 0.15)), atol=1e-3, rtol=0)
    m.config.recycle = False  # a model that does not take an estimate
    with pytest.raises(ValueError, match="recycles need"):
        d.sample(m, cond, 8, steps=1, recycles=1)


def test_explicit_timesteps_give_a_jump_then_a_refining_step():
    """A sequence of timesteps is taken as it is, from the noisiest down: ``(1023, 64)`` is the one-step jump
    to t = 64, then one step to x_0; repeated or out-of-range timesteps are refused."""
    d = Diffusion(prediction="v", schedule="cosine_ztsnr")
    assert d.timestep_pairs((1023, 64)) == [(1023, 64), (64, -1)]
    assert d.timestep_pairs([64, 1023]) == [(1023, 64), (64, -1)]
    assert d.timestep_pairs(1) == [(1023, -1)]
    for bad in ((1023, 1023), (1024, 3), (-1, 5)):
        with pytest.raises(ValueError, match="explicit timesteps"):
            d.timestep_pairs(bad)


def test_point_weight_scales_each_points_squared_error():
    """A point's weight multiplies its share of the L2 term: weight 0 on a point removes it, and with
    weights that sum as before the loss is the weighted mean, not the plain one."""
    d = Diffusion()
    x0 = torch.randn(2, 20, 6)
    cond = torch.randn(2, 30, 3)
    out = {}

    def model(x_t, t, c):  # a fixed prediction, so the loss is a known function of the target
        out["x_t"], out["t"] = x_t, t
        return torch.zeros_like(x_t)

    _, plain = d.training_loss(model, x0, cond, loss="l2", generator=torch.Generator().manual_seed(0))
    w = torch.ones(2, 20)
    w[:, :10] = 2.0
    w[:, 10:] = 0.0
    _, weighted = d.training_loss(model, x0, cond, loss="l2", generator=torch.Generator().manual_seed(0), point_weight=w)
    ab = d._ab(out["t"], x0)
    noise = (out["x_t"] - ab.sqrt() * x0) / (1 - ab).sqrt()
    target = noise if d.prediction == "eps" else ab.sqrt() * noise - (1 - ab).sqrt() * x0
    per_point = target.pow(2).mean(dim=-1)
    assert plain["l2"] == pytest.approx(float(per_point.mean()), rel=1e-4)
    assert weighted["l2"] == pytest.approx(float((w * per_point).mean()), rel=1e-4)
    assert weighted["l2"] != pytest.approx(plain["l2"], rel=1e-3)


def test_normal_weight_scales_the_error_across_the_plane_only():
    """A point's error along its target normal (off its plane) weighs ``normal_weight``; along the plane, 1."""
    d = Diffusion(prediction="v", schedule="cosine_ztsnr")
    x0 = torch.zeros(1, 8, 6)
    x0[..., :3] = torch.randn(1, 8, 3)
    x0[..., 5] = 1.0  # every target point on a plane of normal +z
    cond = torch.randn(1, 16, 3)

    class Off(torch.nn.Module):  # the exact v target at t = T - 1 (-x0) moved by ``shift``
        def __init__(self, shift):
            super().__init__()
            self.shift = shift

        def forward(self, x_t, t, cond):
            assert int(t.min()) == d.T - 1
            return -x0 + self.shift

    across, along = torch.zeros(6), torch.zeros(6)
    across[2], along[0] = 0.1, 0.1

    def l2(shift, w):
        return d.training_loss(Off(shift), x0, cond, loss="l2", t_bias=1e6, normal_weight=w,
                               generator=torch.Generator().manual_seed(0))[1]["l2"]

    assert l2(across, 1.0) == pytest.approx(l2(along, 1.0))
    assert l2(across, 4.0) == pytest.approx(4.0 * l2(across, 1.0), rel=1e-5)
    assert l2(along, 4.0) == pytest.approx(l2(along, 1.0), rel=1e-5)  # sliding along the plane costs the same
    diag = torch.zeros(6)
    diag[0] = diag[2] = 0.1  # half across, half along: only the across half is scaled
    assert l2(diag, 4.0) == pytest.approx(l2(across, 4.0) + l2(along, 1.0), rel=1e-5)
