"""The dual-latent two-stream transformer (paper, "Dual-Latent diffusion model").

A two-stream block ``TS(x, z)`` reads the point stream into the latent stream
(latents cross-attend to points), runs ``H`` self-attention layers on the latents
and writes back (points cross-attend to latents); every sub-layer is pre-norm and
residual.  Self-attention only ever runs over the fixed set of latents, so cost and
memory are linear in the number of points.

* :class:`ConditionEncoder` e(g): TS blocks over the part's cloud g -> condition tokens z_c.
* :class:`Denoiser` eps_theta(x_t, z_c, t): TS blocks over the noisy polycube cloud with
  latents ``[z_c, z_init, embed(t)]``.
* :class:`PolycubeNet` holds both.

Large clouds are processed in chunks of ``chunk`` points: the read attention uses an
online (streaming) softmax over point chunks and the write / feed-forward layers run
chunk by chunk, so a million output points fit in a few GB.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .config import ModelConfig, StreamConfig


class Attention(nn.Module):
    """Multi-head attention used for self attention (``context=None``) and cross attention.

    ``forward(x, context, chunk)``: queries from ``x`` (B, Lq, dim), keys and values from
    ``context`` (B, Lk, dim).  With ``chunk`` set and ``Lk > chunk``, keys and values are
    consumed ``chunk`` at a time with a streaming softmax (exact, memory O(Lq + chunk)).
    """

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.out = nn.Linear(dim, dim)

    def _split(self, t: torch.Tensor) -> torch.Tensor:
        B, L, D = t.shape
        return t.view(B, L, self.heads, D // self.heads).transpose(1, 2)

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None, chunk: int | None = None) -> torch.Tensor:
        ctx = x if context is None else context
        q = self._split(self.q(x))
        if chunk is None or ctx.shape[1] <= chunk:
            k, v = self.kv(ctx).chunk(2, dim=-1)
            o = F.scaled_dot_product_attention(q, self._split(k), self._split(v))
        else:
            o = self._streaming(q, ctx, chunk)
        B, H, L, Dh = o.shape
        return self.out(o.transpose(1, 2).reshape(B, L, H * Dh))

    def _streaming(self, q: torch.Tensor, ctx: torch.Tensor, chunk: int) -> torch.Tensor:
        scale = 1.0 / math.sqrt(q.shape[-1])
        m = torch.full(q.shape[:-1] + (1,), -torch.inf, device=q.device, dtype=torch.float32)
        denom = torch.zeros_like(m)
        acc = torch.zeros(q.shape, device=q.device, dtype=torch.float32)
        for s in range(0, ctx.shape[1], chunk):
            k, v = self.kv(ctx[:, s : s + chunk]).chunk(2, dim=-1)
            k, v = self._split(k), self._split(v)
            logits = (q @ k.transpose(-1, -2)).float() * scale
            m_new = torch.maximum(m, logits.amax(dim=-1, keepdim=True))
            p = torch.exp(logits - m_new)
            corr = torch.exp(m - m_new)
            denom = denom * corr + p.sum(dim=-1, keepdim=True)
            acc = acc * corr + p @ v.float()
            m = m_new
        return (acc / denom).to(q.dtype)


class FeedForward(nn.Module):
    """Pre-norm residual MLP: ``x + W2 gelu(W1 norm(x))``."""

    def __init__(self, dim: int, ratio: float):
        super().__init__()
        hidden = int(round(dim * ratio))
        self.norm = nn.LayerNorm(dim)
        self.net = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(self.norm(x))


class LatentLayer(nn.Module):
    """One transformer layer on the latents: pre-norm self attention + feed-forward."""

    def __init__(self, dim: int, heads: int, ratio: float):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.attn = Attention(dim, heads)
        self.ff = FeedForward(dim, ratio)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        z = z + self.attn(self.norm(z))
        return self.ff(z)

    def make_identity(self) -> None:
        """Zero both residual branches' output projections: the layer then returns its input
        (a layer added to a trained model starts as a no-op, :func:`grow_identity`)."""
        for lin in (self.attn.out, self.ff.net[-1]):
            nn.init.zeros_(lin.weight)
            nn.init.zeros_(lin.bias)


class _NormedContext:
    """A point stream seen through a LayerNorm, normalised lazily chunk by chunk."""

    def __init__(self, norm: nn.LayerNorm, x: torch.Tensor):
        self.norm, self.x = norm, x
        self.shape = x.shape

    def __getitem__(self, idx):
        return self.norm(self.x[idx])


class TwoStreamBlock(nn.Module):
    """``(x, z) -> (x', z')``: read (z attends to x), H latent layers, write (x attends to z)."""

    def __init__(self, cfg: StreamConfig, write: bool = True):
        super().__init__()
        d = cfg.dim
        self.read_norm_z = nn.LayerNorm(d)
        self.read_norm_x = nn.LayerNorm(d)
        self.read = Attention(d, cfg.heads)
        self.read_ff = FeedForward(d, cfg.mlp_ratio)
        self.layers = nn.ModuleList(LatentLayer(d, cfg.heads, cfg.mlp_ratio) for _ in range(cfg.layers))
        self.has_write = write
        if write:
            self.write_norm_x = nn.LayerNorm(d)
            self.write_norm_z = nn.LayerNorm(d)
            self.write = Attention(d, cfg.heads)
            self.write_ff = FeedForward(d, cfg.write_mlp_ratio or cfg.mlp_ratio)

    def forward(self, x: torch.Tensor, z: torch.Tensor, chunk: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        big = chunk is not None and x.shape[1] > chunk
        if big:
            z = z + self.read(self.read_norm_z(z), _NormedContext(self.read_norm_x, x), chunk=chunk)
        else:
            z = z + self.read(self.read_norm_z(z), self.read_norm_x(x))
        z = self.read_ff(z)
        for layer in self.layers:
            z = layer(z)
        if not self.has_write:
            return x, z
        zn = self.write_norm_z(z)
        if big:
            out = torch.empty_like(x)
            for s in range(0, x.shape[1], chunk):
                xs = x[:, s : s + chunk]
                xs = xs + self.write(self.write_norm_x(xs), zn)
                out[:, s : s + chunk] = self.write_ff(xs)
            return out, z
        x = x + self.write(self.write_norm_x(x), zn)
        return self.write_ff(x), z


class PointEmbed(nn.Module):
    """Point features: Fourier features of the first 3 channels (positions) + all channels, then linear."""

    def __init__(self, in_dim: int, dim: int, fourier: int):
        super().__init__()
        self.fourier = fourier
        self.register_buffer("freqs", (2.0 ** torch.arange(fourier)) * math.pi, persistent=False)
        self.proj = nn.Linear(in_dim + 6 * fourier, dim)

    def forward(self, p: torch.Tensor) -> torch.Tensor:
        if self.fourier:
            a = p[..., :3, None] * self.freqs  # (..., 3, F)
            feats = torch.cat([p, a.sin().flatten(-2), a.cos().flatten(-2)], dim=-1)
        else:
            feats = p
        return self.proj(feats)


class LocalContext(nn.Module):
    """Each anchor's ``k`` nearest condition points, as features added to its point stream.

    Per neighbour: its offset from the anchor and its distance, in units of ``radius`` (network
    units), beside the anchor's own channels after its position (its normal); a shared MLP, a max
    over the neighbours and an output projection that starts at zero, so that a model given this
    context starts as the same function as the one without it (``train --init``).  The latents
    carry the part as a whole; this carries the few percent of the diagonal around a point, where a
    thin slab's two faces are told apart.  Condition clouds larger than ``ref`` points are read at an
    even stride (neighbourhoods then span what they spanned in training)."""

    def __init__(self, k: int, dim: int, anchor_dim: int, radius: float, ref: int):
        super().__init__()
        self.k, self.radius, self.ref = k, radius, ref
        # narrow before the max (the per-neighbour tensors are k times the points'): 32 wide at dim 96
        hidden = max(8, dim // 3)
        self.mlp = nn.Sequential(nn.Linear(4 + anchor_dim - 3, hidden), nn.GELU(), nn.Linear(hidden, hidden))
        self.out = nn.Linear(hidden, dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, anchor: torch.Tensor, cond: torch.Tensor, chunk: int | None = None) -> torch.Tensor:
        c = cond[..., :3]
        B, m, _ = c.shape
        if m > self.ref:
            c = c[:, :: -(-m // self.ref)]
            m = c.shape[1]
        k = min(self.k, m)
        step = min(chunk or anchor.shape[1], 1024)
        flat = c.reshape(B * m, 3)
        base = (torch.arange(B, device=c.device) * m)[:, None, None]
        outs = []
        for s in range(0, anchor.shape[1], step):
            a = anchor[:, s : s + step]
            with torch.no_grad():
                dist, idx = torch.cdist(a[..., :3].float(), c.float()).topk(k, dim=-1, largest=False)
                off = (flat[(idx + base).reshape(-1)].view(B, a.shape[1], k, 3) - a[..., None, :3]) / self.radius
                feats = torch.cat([off, dist[..., None] / self.radius,
                                   a[..., None, 3:].expand(-1, -1, k, -1)], dim=-1).to(a.dtype)
            outs.append(self.out(self.mlp(feats).amax(dim=2)))
        return torch.cat(outs, dim=1)


def timestep_embedding(t: torch.Tensor, dim: int, max_period: float = 10000.0) -> torch.Tensor:
    """Sinusoidal embedding of integer timesteps ``t`` (B,) -> (B, dim)."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    a = t.float()[:, None] * freqs[None]
    emb = torch.cat([a.cos(), a.sin()], dim=-1)
    if dim % 2:
        emb = F.pad(emb, (0, 1))
    return emb


class ConditionEncoder(nn.Module):
    """e(g): TS blocks over the condition cloud g (B, N, 3) -> condition tokens (B, latents, dim)."""

    def __init__(self, cfg: StreamConfig, in_dim: int, fourier: int):
        super().__init__()
        self.embed = PointEmbed(in_dim, cfg.dim, fourier)
        self.latents = nn.Parameter(torch.randn(cfg.latents, cfg.dim) * 0.02)
        # the point stream after the last block is never used: that block has no write
        self.blocks = nn.ModuleList(TwoStreamBlock(cfg, write=i < cfg.blocks - 1) for i in range(cfg.blocks))
        self.norm = nn.LayerNorm(cfg.dim)

    def forward(self, g: torch.Tensor, chunk: int | None = None) -> torch.Tensor:
        x = _embed_chunked(self.embed, g, chunk)
        z = self.latents.unsqueeze(0).expand(g.shape[0], -1, -1)
        for block in self.blocks:
            x, z = block(x, z, chunk=chunk)
        return self.norm(z)


class Denoiser(nn.Module):
    """eps_theta(x_t, z_c, t): TS blocks over x_t with latents ``[z_c, z_init, embed(t)]``."""

    def __init__(self, cfg: StreamConfig, point_dim: int, cond_width: int, fourier: int, anchor_dim: int = 0,
                 local: LocalContext | None = None, recycle: bool = False):
        super().__init__()
        d = cfg.dim
        if local is not None and anchor_dim == 0:
            raise ValueError("a local context needs an anchored denoiser")
        self.local = local
        self.anchored = anchor_dim > 0
        self.anchor_dim = anchor_dim
        # anchored: the input is [anchor (xyz, or xyz + part normal), x_t] and the Fourier features
        # are the anchor's position's
        self.embed = PointEmbed(point_dim + anchor_dim, d, fourier)
        self.latents = nn.Parameter(torch.randn(cfg.latents, d) * 0.02)
        self.cond_proj = nn.Linear(cond_width, d)
        self.time = nn.Sequential(nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        self.blocks = nn.ModuleList(TwoStreamBlock(cfg) for _ in range(cfg.blocks))
        self.out_norm = nn.LayerNorm(d)
        self.out = nn.Linear(d, point_dim)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        # recycling: the previous estimate of the clean point, added to the point stream; the last layer
        # starts at zero, so the model starts as the function of a file without it
        self.recycle = None
        if recycle:
            self.recycle = nn.Sequential(nn.Linear(point_dim, d), nn.GELU(), nn.Linear(d, d))
            nn.init.zeros_(self.recycle[2].weight)
            nn.init.zeros_(self.recycle[2].bias)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, z_c: torch.Tensor | tuple[torch.Tensor, torch.Tensor],
                chunk: int | None = None, anchor: torch.Tensor | None = None,
                x0_prev: torch.Tensor | None = None) -> torch.Tensor:
        B = x_t.shape[0]
        cond = None
        if isinstance(z_c, tuple):  # (tokens, condition points) from a model with a local context
            z_c, cond = z_c
        if (self.local is not None) != (cond is not None):
            raise ValueError("a local context needs the condition points with its tokens (and only it takes them)")
        if self.anchored != (anchor is not None):
            raise ValueError("an anchored denoiser needs anchor points (and only it takes them)")
        if x0_prev is not None and self.recycle is None:
            raise ValueError("this denoiser does not take a previous estimate (ModelConfig.recycle)")
        if x0_prev is not None and x0_prev.shape != x_t.shape:
            raise ValueError(f"the previous estimate has shape {tuple(x0_prev.shape)}, x_t {tuple(x_t.shape)}")
        if anchor is not None and anchor.shape[-1] != self.anchor_dim:
            raise ValueError(f"anchors have {anchor.shape[-1]} channels; this denoiser takes {self.anchor_dim}")
        # one row at a time: a (B, d) GEMM takes another kernel for B = 1 than for B > 1, so a batched
        # request would differ from the same request alone in the last bits (then amplified by sampling)
        emb = timestep_embedding(t, self.latents.shape[1]).to(x_t.dtype)
        temb = torch.cat([self.time(emb[i : i + 1]) for i in range(B)])  # (B, d)
        z = torch.cat([self.cond_proj(z_c), self.latents.unsqueeze(0).expand(B, -1, -1), temb[:, None]], dim=1)
        inp = x_t if anchor is None else torch.cat([anchor.to(x_t.dtype), x_t], dim=-1)
        x = _embed_chunked(self.embed, inp, chunk, add=temb[:, None])
        if self.local is not None:
            x = x + self.local(anchor, cond, chunk)
        if self.recycle is not None:
            x = x + self.recycle((torch.zeros_like(x_t) if x0_prev is None else x0_prev).to(x.dtype))
        for block in self.blocks:
            x, z = block(x, z, chunk=chunk)
        if chunk is not None and x.shape[1] > chunk:
            out = x_t.new_empty(x_t.shape)
            for s in range(0, x.shape[1], chunk):
                out[:, s : s + chunk] = self.out(self.out_norm(x[:, s : s + chunk]))
            return out
        return self.out(self.out_norm(x))


def _embed_chunked(embed: PointEmbed, p: torch.Tensor, chunk: int | None, add: torch.Tensor | None = None) -> torch.Tensor:
    if chunk is None or p.shape[1] <= chunk:
        x = embed(p)
        return x if add is None else x + add
    first = embed(p[:, :1])
    out = first.new_empty(p.shape[0], p.shape[1], first.shape[-1])
    for s in range(0, p.shape[1], chunk):
        xs = embed(p[:, s : s + chunk])
        out[:, s : s + chunk] = xs if add is None else xs + add
    return out


class PolycubeNet(nn.Module):
    """The conditional noise predictor: ``forward(x_t, t, cond) = eps_theta(x_t, e(cond), t)``.

    Tensors are in network units: positions multiplied by ``config.xyz_scale``
    (see :mod:`polycubenet.model.diffusion` for the conversion of clouds).
    """

    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        self.encoder = ConditionEncoder(config.encoder, config.cond_dim, config.fourier)
        local = None
        if config.local_k:
            # offsets in units of 5 % of the diagonal (network units: the diagonal is xyz_scale)
            local = LocalContext(config.local_k, config.denoiser.dim, config.anchor_dim, 0.05 * config.xyz_scale,
                                 config.local_ref)
        self.denoiser = Denoiser(config.denoiser, config.point_dim, config.encoder.dim, config.fourier,
                                 anchor_dim=config.anchor_dim, local=local, recycle=config.recycle)
        self.genus = None
        if config.genus_classes:
            # one vector per genus class and one for "unknown", zero at first: the function of a file without them
            self.genus = nn.Embedding(config.genus_classes + 1, config.encoder.dim)
            nn.init.zeros_(self.genus.weight)

    def genus_index(self, genus, batch: int, device) -> torch.Tensor:
        """``(batch,)`` rows of the genus table for ``genus`` (None, or one int per condition; None or a
        negative value: unknown; ``genus_classes - 1`` and more share the last class)."""
        k = self.config.genus_classes
        if genus is None:
            return torch.full((batch,), k, dtype=torch.long, device=device)
        g = torch.as_tensor(genus, dtype=torch.long, device=device).reshape(-1)
        if g.shape[0] != batch:
            raise ValueError(f"{g.shape[0]} genus values for {batch} conditions")
        return torch.where(g < 0, torch.full_like(g, k), g.clamp(max=k - 1))

    def encode(self, cond: torch.Tensor, chunk: int | None = None,
               genus=None) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """The condition tokens z_c; with a local context (``config.local_k``) ``(z_c, cond)``, which
        :meth:`denoise` takes as it is.  ``genus`` (a model with ``config.genus_classes``): each
        condition's part genus (:meth:`genus_index`), its vector added to every token; a model
        without them refuses one."""
        z = self.encoder(cond, chunk=chunk)
        if self.genus is not None:
            z = z + self.genus(self.genus_index(genus, z.shape[0], z.device)).to(z.dtype)[:, None]
        elif genus is not None:
            raise ValueError("this model takes no genus (ModelConfig.genus_classes is 0)")
        return (z, cond) if self.config.local_k else z

    def denoise(self, x_t: torch.Tensor, t: torch.Tensor, z_c: torch.Tensor, chunk: int | None = None,
                anchor: torch.Tensor | None = None, x0_prev: torch.Tensor | None = None) -> torch.Tensor:
        extra = {} if x0_prev is None else {"x0_prev": x0_prev}
        return self.denoiser(x_t, t, z_c, chunk=chunk, anchor=anchor, **extra)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                anchor: torch.Tensor | None = None, x0_prev: torch.Tensor | None = None,
                genus=None) -> torch.Tensor:
        return self.denoise(x_t, t, self.encode(cond, genus=genus), anchor=anchor, x0_prev=x0_prev)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def grow_identity(model: nn.Module, fresh: set[str]) -> list[str]:
    """Make every latent layer of ``model`` whose parameters are all in ``fresh`` (names of the
    ``state_dict`` not taken from an ``--init`` file) an identity (:meth:`LatentLayer.make_identity`),
    so that a deeper model started from a shallower one computes what that one computed.  Returns the
    names of the layers it changed."""
    grown = []
    for name, mod in model.named_modules():
        if isinstance(mod, LatentLayer) and all(f"{name}.{k}" in fresh for k in mod.state_dict()):
            mod.make_identity()
            grown.append(name)
    return grown
