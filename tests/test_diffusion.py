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
