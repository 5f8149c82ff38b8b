"""Gaussian diffusion over polycube clouds: a plain class (no parameters, not an nn.Module).

T = 1024 steps.  The paper's recipe (the default) is epsilon prediction with a cosine
schedule and the hybrid loss: for each iteration ``w ~ U[0.4, 0.8)`` and
``L = w * L2 + (1 - w) * L1`` on the noise (``loss="l2"`` gives the plain DDPM
objective, for comparison).  Options for learning more per CPU-hour, each recorded in
the checkpoint (:meth:`Diffusion.to_dict`):

* ``prediction="v"``: the network predicts ``v = sqrt(ab) eps - sqrt(1 - ab) x0``;
* ``schedule="cosine_ztsnr"``: the cosine schedule rescaled to zero terminal SNR
  (ᾱ at t = T-1 is exactly 0, so sampling starts from pure noise; needs ``v``);
* ``min_snr``: Min-SNR-γ weighting of each sample's loss, ``min(SNR, γ) / (SNR + 1)``
  for v (``/ SNR`` for eps);
* ``pairing="ot"``: before noising, each cloud's noise points are matched to its
  target points by a minimum-cost assignment (the set analogue of minibatch optimal
  transport), so the regression target is far less ambiguous.  Deterministic DDIM
  integrates the same interpolant, so sampling is unchanged.  Sampling is DDIM over
precomputed ``(t, t_prev)`` pairs, stride 4 by default; ``eta`` interpolates between
deterministic DDIM (0) and DDPM's ancestral sampling (1, with stride 1 it *is* DDPM).

Clouds enter the network as ``[xyz * xyz_scale, normal]`` (:func:`to_network`) and
leave through :func:`from_network` (normals renormalised).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch


def to_network(points: torch.Tensor, normals: torch.Tensor | None, xyz_scale: float) -> torch.Tensor:
    """``[xyz * scale, normals]`` (or only the scaled xyz when ``normals`` is None)."""
    x = points * xyz_scale
    return x if normals is None else torch.cat([x, normals], dim=-1)


def from_network(x: torch.Tensor, xyz_scale: float) -> torch.Tensor:
    """Inverse of :func:`to_network` for a generated cloud: xyz unscaled, normals unit length."""
    p = x[..., :3] / xyz_scale
    n = x[..., 3:6]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    return torch.cat([p, n], dim=-1)


def anchored_to_network(anchor: torch.Tensor, points: torch.Tensor | None, normals: torch.Tensor | None,
                        xyz_scale: float, gain: float) -> tuple[torch.Tensor | None, torch.Tensor]:
    """``(x0, anchor)`` in network units for an anchored model: ``x0 = [(points - anchor) * xyz_scale * gain,
    normals]`` (None without points) and the anchor's position scaled like any position (an anchor's
    normal, channels 3..5 when present, passes unchanged)."""
    a = torch.cat([anchor[..., :3] * xyz_scale, anchor[..., 3:]], dim=-1)
    if points is None:
        return None, a
    return torch.cat([(points - anchor[..., :3]) * (xyz_scale * gain), normals], dim=-1), a


def anchored_from_network(x: torch.Tensor, anchor_net: torch.Tensor, xyz_scale: float, gain: float) -> torch.Tensor:
    """Inverse of :func:`anchored_to_network` for a generated cloud: anchor + displacement, unit normals."""
    p = anchor_net[..., :3] / xyz_scale + x[..., :3] / (xyz_scale * gain)
    n = x[..., 3:6]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    return torch.cat([p, n], dim=-1)


def _cosine_alpha_bar(T: int, s: float = 0.008) -> np.ndarray:
    t = np.arange(T + 1, dtype=np.float64) / T
    f = np.cos((t + s) / (1 + s) * math.pi / 2) ** 2
    betas = np.clip(1 - f[1:] / f[:-1], 0, 0.999)
    return np.cumprod(1 - betas)


def _zero_terminal_snr(ab: np.ndarray) -> np.ndarray:
    """Shift and scale sqrt(ᾱ) so that its last value is 0 and its first unchanged (Lin et al. 2024)."""
    r = np.sqrt(ab)
    r0, rT = r[0], r[-1]
    r = (r - rT) * r0 / (r0 - rT)
    return r**2


def ot_pair_noise(x0: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """``noise`` with each cloud's points permuted to a minimum-cost assignment onto ``x0``'s points.

    The set of noise points of each cloud is unchanged (so is its distribution); only which
    noise point goes with which target point changes.  Squared Euclidean cost over all channels.
    """
    from scipy.optimize import linear_sum_assignment

    out = torch.empty_like(noise)
    a = x0.detach().float().cpu().numpy()
    b = noise.detach().float().cpu().numpy()
    for k in range(a.shape[0]):
        cost = (a[k] ** 2).sum(1)[:, None] + (b[k] ** 2).sum(1)[None, :] - 2.0 * a[k] @ b[k].T
        _, col = linear_sum_assignment(cost)
        out[k] = noise[k, torch.as_tensor(col, device=noise.device)]
    return out


class Diffusion:
    """Forward process, hybrid loss and DDIM / DDPM sampling.

    Parameters
    ----------
    T : number of diffusion steps
    schedule : ``"cosine"`` (default), ``"cosine_ztsnr"`` (zero terminal SNR) or ``"linear"``
        (betas from 1e-4 to 0.02 scaled to T)
    prediction : ``"eps"`` (default, the paper) or ``"v"``
    min_snr : Min-SNR-γ loss weighting (None: every timestep weighted 1)
    pairing : ``"random"`` (default) or ``"ot"`` (noise matched to the target points)
    """

    def __init__(self, T: int = 1024, schedule: str = "cosine", prediction: str = "eps",
                 min_snr: float | None = None, pairing: str = "random"):
        if prediction not in ("eps", "v"):
            raise ValueError(f"unknown prediction {prediction!r} (eps, v)")
        if pairing not in ("random", "ot"):
            raise ValueError(f"unknown noise pairing {pairing!r} (random, ot)")
        if schedule in ("cosine", "cosine_ztsnr"):
            ab = _cosine_alpha_bar(T)
            if schedule == "cosine_ztsnr":
                if prediction != "v":
                    raise ValueError("a zero-terminal-SNR schedule needs prediction='v' (eps is undefined at SNR 0)")
                ab = _zero_terminal_snr(ab)
        elif schedule == "linear":
            scale = 1000.0 / T
            betas = np.linspace(scale * 1e-4, scale * 0.02, T, dtype=np.float64)
            ab = np.cumprod(1 - betas)
        else:
            raise ValueError(f"unknown noise schedule {schedule!r} (cosine, cosine_ztsnr, linear)")
        self.T = T
        self.schedule = schedule
        self.prediction = prediction
        self.min_snr = None if min_snr is None else float(min_snr)
        self.pairing = pairing
        self.alpha_bar = ab  # float64, alpha_bar[t] for t = 0..T-1
        self.betas = 1 - ab / np.concatenate([[1.0], ab[:-1]])

    def to_dict(self) -> dict:
        return {"T": self.T, "schedule": self.schedule, "prediction": self.prediction, "min_snr": self.min_snr,
                "pairing": self.pairing}

    @classmethod
    def from_dict(cls, d: dict) -> "Diffusion":
        # checkpoints written before these options existed are eps / cosine / random
        return cls(T=int(d["T"]), schedule=d["schedule"], prediction=d.get("prediction", "eps"),
                   min_snr=d.get("min_snr"), pairing=d.get("pairing", "random"))

    def split(self, out: torch.Tensor, x_t: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x0, eps)`` from the network output ``out`` at integer timestep ``t``."""
        ab = float(self.alpha_bar[t])
        if self.prediction == "v":
            a, s = math.sqrt(ab), math.sqrt(1 - ab)
            return a * x_t - s * out, s * x_t + a * out
        return (x_t - math.sqrt(1 - ab) * out) / math.sqrt(ab), out

    # ------------------------------------------------------------------ training
    def _ab(self, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        ab = torch.as_tensor(self.alpha_bar, device=like.device)[t].to(like.dtype)
        return ab.view(-1, *([1] * (like.dim() - 1)))

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        """x_t = sqrt(ab_t) x0 + sqrt(1 - ab_t) noise."""
        ab = self._ab(t, x0)
        return ab.sqrt() * x0 + (1 - ab).sqrt() * noise

    def training_loss(
        self,
        model: Callable,
        x0: torch.Tensor,
        cond: torch.Tensor,
        *,
        loss: str = "hybrid",
        generator: torch.Generator | None = None,
        autocast: Callable | None = None,
        anchor: torch.Tensor | None = None,
        t_bias: float = 1.0,
        t_uniform: float = 0.0,
        recycle: float = 0.0,
        point_weight: torch.Tensor | None = None,
        normal_weight: float = 1.0,
        genus: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, dict]:
        """One batch: random t and noise, predict the noise, the hybrid (or l2, or l1) loss.

        ``t_bias`` > 1 draws t towards the noisy end: ``t = T (1 - (1 - u)^t_bias)`` with u uniform
        (1: uniform, the paper's).  A model sampled in a few DDIM steps from pure noise spends its
        first step, the one that decides the shape, at t = T - 1, where the uniform draw puts
        few samples.  ``t_uniform`` > 0: that fraction of the batch (each pair with that probability)
        draws its t uniformly instead, so a one-step model biased to the noisy end also learns the
        low-noise timesteps at which a further DDIM step refines its first cloud.  ``recycle`` > 0 (a
        model with ``ModelConfig.recycle``): with that probability the batch is first evaluated without
        gradient, and the loss is that of a second evaluation given the first one's clean estimate
        (``x0_prev``, clipped like a sampling step's); otherwise the model gets no estimate (zeros).
        ``point_weight`` (``(B, N)``, mean 1): each point's share of the loss (``train.face_weights``).
        ``normal_weight`` != 1 (targets with normals, channels 3..5): the part of each point's position
        error along its target normal, i.e. across the plane the point belongs on, weighs that much
        against the part along the plane: where the polycube's planes are what the extraction reads,
        a point slid along its face costs little and one off its plane a thin slab.
        ``genus`` (``(B,)``, a model with ``ModelConfig.genus_classes``; -1: unknown): each pair's genus,
        given to the model with its condition.

        Returns ``(loss, stats)`` where ``stats`` holds the float values of the L2 and L1
        terms and the weight used.
        """
        B = x0.shape[0]
        dev = x0.device
        if t_bias == 1.0:
            t = torch.randint(0, self.T, (B,), device=dev, generator=generator)
        else:
            u = torch.rand((B,), device=dev, generator=generator, dtype=torch.float64)
            t = (self.T * (1.0 - (1.0 - u) ** t_bias)).long().clamp_(0, self.T - 1)
        if t_uniform > 0.0:
            pick = torch.rand((B,), device=dev, generator=generator) < t_uniform
            t = torch.where(pick, torch.randint(0, self.T, (B,), device=dev, generator=generator), t)
        noise = torch.randn(x0.shape, device=dev, dtype=x0.dtype, generator=generator)
        if self.pairing == "ot":
            noise = ot_pair_noise(x0, noise)
        x_t = self.q_sample(x0, t, noise)
        extra = {} if anchor is None else {"anchor": anchor}
        if genus is not None:
            extra["genus"] = genus
        ctx = autocast if autocast is not None else _null
        recycled = recycle > 0.0 and float(torch.rand((), generator=generator, device=dev)) < recycle
        if recycled:
            with torch.no_grad(), ctx():
                first = model(x_t, t, cond, **extra).float()
            extra["x0_prev"] = self.clean_estimate(first, x_t, t).clamp(-1.0, 1.0).to(x_t.dtype)
        with ctx():
            out = model(x_t, t, cond, **extra)
        if self.prediction == "v":
            ab = self._ab(t, x0)
            target = ab.sqrt() * noise - (1 - ab).sqrt() * x0
        else:
            target = noise
        err = out.float() - target.float()
        if normal_weight != 1.0 and x0.shape[-1] >= 6:
            n = x0[..., 3:6].float()
            n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-8)
            across = (err[..., :3] * n).sum(-1, keepdim=True) * n  # the error's component across the plane
            err = torch.cat([err[..., :3] + (normal_weight ** 0.5 - 1.0) * across, err[..., 3:]], dim=-1)
        if point_weight is not None:  # a weight w on a point's squared error, sqrt(w) on its error
            err = err * point_weight.float().sqrt().unsqueeze(-1)
        if self.min_snr is not None:
            ab = torch.as_tensor(self.alpha_bar, device=dev)[t]
            snr = ab / (1 - ab).clamp_min(1e-12)
            wt = snr.clamp(max=self.min_snr) / ((snr + 1) if self.prediction == "v" else snr.clamp_min(1e-12))
            wt = wt.float().view(-1, *([1] * (err.dim() - 1)))
            l2 = (wt * err.pow(2)).mean()
            l1 = (wt * err.abs()).mean()
        else:
            l2 = err.pow(2).mean()
            l1 = err.abs().mean()
        if loss == "hybrid":
            w = float(0.4 + 0.4 * torch.rand((), generator=generator, device=dev).item())
        elif loss == "l2":
            w = 1.0
        elif loss == "l1":  # a median rather than a mean: a point whose place is two-valued (a step's edge)
            w = 0.0  # takes one of them instead of the middle
        else:
            raise ValueError(f"unknown loss {loss!r} (hybrid, l2, l1)")
        total = w * l2 + (1 - w) * l1
        return total, {"l2": float(l2.detach()), "l1": float(l1.detach()), "w": w, "recycled": recycled}

    def clean_estimate(self, out: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """x_0 from the network output ``out`` at per-row timesteps ``t`` (:meth:`split`'s first half)."""
        ab = self._ab(t, x_t)
        if self.prediction == "v":
            return ab.sqrt() * x_t - (1 - ab).sqrt() * out
        return (x_t - (1 - ab).sqrt() * out) / ab.sqrt().clamp_min(1e-6)

    # ------------------------------------------------------------------ sampling
    def timestep_pairs(self, steps: int | None = None, stride: int = 4) -> list[tuple[int, int]]:
        """``(t, t_prev)`` pairs from T-1 down to 0 (``t_prev = -1`` means "x_0").

        ``steps`` (when given) spaces that many timesteps evenly, or, a sequence, lists the timesteps
        themselves (e.g. ``(1023, 64)``: the one-step jump from pure noise, then one refining step from
        t = 64); otherwise every ``stride``-th timestep is used (stride 4 -> 256 network evaluations at
        T = 1024).
        """
        if steps is not None and not isinstance(steps, (int, np.integer)):
            ts = np.unique(np.asarray(steps, dtype=int))
            if len(ts) != len(steps) or ts[0] < 0 or ts[-1] > self.T - 1:
                raise ValueError(f"explicit timesteps must be distinct and in 0..{self.T - 1}, got {list(steps)}")
        elif steps is not None:
            if not 1 <= steps <= self.T:
                raise ValueError(f"steps must be in 1..{self.T}, got {steps}")
            # from T-1 (pure noise under zero terminal SNR) down: one step is a single jump from T-1 to x_0
            ts = np.unique(np.round(np.linspace(self.T - 1, 0, steps)).astype(int))
        else:
            if stride < 1:
                raise ValueError(f"stride must be >= 1, got {stride}")
            ts = np.arange(self.T - 1, -1, -stride)[::-1]
        ts = ts[::-1]
        prev = list(ts[1:]) + [-1]
        return [(int(a), int(b)) for a, b in zip(ts, prev)]

    def ddim_step(self, x_t: torch.Tensor, eps: torch.Tensor, t: int, t_prev: int, eta: float,
                  noise: torch.Tensor | None, clip: float | None = None) -> torch.Tensor:
        """One DDIM update from t to t_prev (generalised: eta = 1 is the DDPM posterior).

        ``eps`` is the network's output: the noise, or ``v`` when ``prediction == "v"``.

        ``clip`` bounds the predicted x_0 (network units) and re-derives the noise from
        it: near t = T the division by sqrt(alpha_bar) would otherwise amplify errors.
        """
        ab = float(self.alpha_bar[t])
        ab_prev = float(self.alpha_bar[t_prev]) if t_prev >= 0 else 1.0
        x0, eps = self.split(eps, x_t, t)
        if clip is not None:
            x0 = x0.clamp(-clip, clip)
            eps = (x_t - math.sqrt(ab) * x0) / math.sqrt(1 - ab)
        sigma = eta * math.sqrt(max((1 - ab_prev) / (1 - ab) * (1 - ab / ab_prev), 0.0))
        dir_coef = math.sqrt(max(1 - ab_prev - sigma**2, 0.0))
        x = math.sqrt(ab_prev) * x0 + dir_coef * eps
        if sigma > 0 and noise is not None:
            x = x + sigma * noise
        return x

    def ddpm_step(self, x_t: torch.Tensor, eps: torch.Tensor, t: int, noise: torch.Tensor | None) -> torch.Tensor:
        """Ancestral DDPM step t -> t-1 from the posterior q(x_{t-1} | x_t, x_0) (Ho et al.)."""
        ab = float(self.alpha_bar[t])
        ab_prev = float(self.alpha_bar[t - 1]) if t > 0 else 1.0
        beta = 1 - ab / ab_prev
        x0, _ = self.split(eps, x_t, t)
        c0 = math.sqrt(ab_prev) * beta / (1 - ab)
        ct = math.sqrt(1 - beta) * (1 - ab_prev) / (1 - ab)
        mean = c0 * x0 + ct * x_t
        var = beta * (1 - ab_prev) / (1 - ab)
        if t > 0 and noise is not None:
            return mean + math.sqrt(var) * noise
        return mean

    @torch.no_grad()
    def sample(
        self,
        model,
        cond: torch.Tensor,
        n_out: int,
        *,
        steps: int | None = None,
        stride: int = 4,
        eta: float = 0.0,
        generator: torch.Generator | list | None = None,
        chunk: int | None = None,
        clip: float | None = 1.0,
        autocast: Callable | None = None,
        progress: Callable[[int, int], None] | None = None,
        anchor: torch.Tensor | None = None,
        recycles: int = 0,
        genus=None,
    ) -> torch.Tensor:
        """Generate ``(B, n_out, point_dim)`` clouds in network units for conditions ``cond``.

        ``model`` has ``encode(cond, chunk)`` and ``denoise(x_t, t, z_c, chunk[, anchor])``; an
        anchored model gets ``anchor`` ``(B, n_out, 3)`` (network units) with every call.  All
        randomness comes from ``generator`` (on the device of ``cond``), so a seed
        reproduces the output; a list of generators gives each batch element its own
        stream (its result then does not depend on the rest of the batch).

        A recycling model (``model.config.recycle``) gets its latest clean estimate with every
        evaluation (zeros at the first), and each step evaluates it ``1 + recycles`` times.
        ``genus`` (one int per condition, -1 unknown): the parts' genus, for a model that takes it
        (``ModelConfig.genus_classes``; such a model given None is told "unknown").
        """
        B = cond.shape[0]
        dev = cond.device
        dim = model.config.point_dim
        x = _randn((B, n_out, dim), dev, generator)
        ctx = autocast() if autocast is not None else _null()
        with ctx:
            z_c = model.encode(cond, chunk=chunk) if genus is None else model.encode(cond, chunk=chunk, genus=genus)
        pairs = self.timestep_pairs(steps, stride)
        recycling = bool(getattr(getattr(model, "config", None), "recycle", False))
        if recycles and not recycling:
            raise ValueError("recycles need a model that takes its previous estimate (ModelConfig.recycle)")
        extra = {} if anchor is None else {"anchor": anchor}
        for i, (t, t_prev) in enumerate(pairs):
            tt = torch.full((B,), t, device=dev, dtype=torch.long)
            for _ in range(1 + (int(recycles) if recycling else 0)):
                with (autocast() if autocast is not None else _null()):
                    eps = model.denoise(x, tt, z_c, chunk=chunk, **extra)
                eps = eps.float()
                if recycling:
                    x0 = self.split(eps, x, t)[0]
                    extra["x0_prev"] = (x0.clamp(-clip, clip) if clip is not None else x0).to(x.dtype)
            noise = _randn(x.shape, dev, generator) if eta > 0 and t_prev >= 0 else None
            x = self.ddim_step(x, eps, t, t_prev, eta, noise, clip)
            if progress is not None:
                progress(i + 1, len(pairs))
        return x


def _randn(shape, device, generator) -> torch.Tensor:
    if isinstance(generator, (list, tuple)):
        if len(generator) != shape[0]:
            raise ValueError(f"{len(generator)} generators for a batch of {shape[0]}")
        return torch.cat([torch.randn((1, *shape[1:]), device=device, generator=g) for g in generator])
    return torch.randn(shape, device=device, generator=generator)


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
