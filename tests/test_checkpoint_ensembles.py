"""benchmarks/checkpoint_ensembles.py: the weight soup and the prediction ensemble it measures."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import checkpoint_ensembles as ce  # noqa: E402

from polycubenet.model import PolycubeNet, preset  # noqa: E402
from polycubenet.model.checkpoint import Loaded, load_checkpoint, save_checkpoint  # noqa: E402
from polycubenet.model.diffusion import Diffusion  # noqa: E402


def _net(seed: int, config=None) -> PolycubeNet:
    torch.manual_seed(seed)
    net = PolycubeNet(config or preset("tiny")).eval()
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.2)
        torch.nn.init.normal_(net.denoiser.out.bias, std=0.05)
    return net


def _save(net: PolycubeNet, path: Path) -> Path:
    return save_checkpoint(path, {"kind": "published", "model_config": net.config.to_dict(),
                                  "diffusion": Diffusion().to_dict(), "ema": net.state_dict()})


def test_soup_is_the_mean_of_the_weights(tmp_path):
    a, b = _net(0), _net(1)
    pa, pb = _save(a, tmp_path / "a.pt"), _save(b, tmp_path / "b.pt")
    state = ce.soup_state([pa, pb])
    sa, sb = a.state_dict(), b.state_dict()
    assert set(state["ema"]) == set(sa)
    for k in sa:
        torch.testing.assert_close(state["ema"][k], (sa[k] + sb[k]) / 2)
    assert state["lineage"][-1] == {"soup": [str(pa), str(pb)]}
    # a soup of one model with itself is that model
    same = ce.soup_state([pa, pa])
    for k in sa:
        torch.testing.assert_close(same["ema"][k], sa[k])


def test_soup_refuses_other_architectures(tmp_path):
    small = _net(0)
    cfg = preset("tiny")
    wide = _net(1, dataclasses.replace(cfg, denoiser=dataclasses.replace(cfg.denoiser, dim=2 * cfg.denoiser.dim)))
    with pytest.raises(ValueError, match="does not share the architecture"):
        ce.soup_state([_save(small, tmp_path / "s.pt"), _save(wide, tmp_path / "w.pt")])


def test_ensemble_averages_the_predictions(tmp_path):
    a, b = _net(0), _net(1)
    ens = ce.Ensemble([a, b]).eval()
    rng = np.random.default_rng(0)
    cond = torch.as_tensor(rng.random((1, 64, 3), dtype=np.float32) - 0.5)
    x = torch.as_tensor(rng.standard_normal((1, 32, a.config.point_dim), dtype=np.float32))
    t = torch.full((1,), 500, dtype=torch.long)
    with torch.no_grad():
        want = (a.denoise(x, t, a.encode(cond)) + b.denoise(x, t, b.encode(cond))) / 2
        got = ens.denoise(x, t, ens.encode(cond))
        torch.testing.assert_close(got, want)
        # two copies of one model sample exactly as the model does
        loaded = load_checkpoint(_save(a, tmp_path / "a.pt"))
        twice = Loaded(model=ce.Ensemble([loaded.model, loaded.model]).eval(), diffusion=loaded.diffusion, meta={})
        g = [torch.Generator().manual_seed(3)]
        one = loaded.diffusion.sample(loaded.model, cond, 16, steps=2, generator=g)
        g = [torch.Generator().manual_seed(3)]
        two = twice.diffusion.sample(twice.model, cond, 16, steps=2, generator=g)
    torch.testing.assert_close(one, two)
    assert not torch.allclose(got, a.denoise(x, t, a.encode(cond)))
