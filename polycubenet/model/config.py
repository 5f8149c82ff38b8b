"""Model configurations: frozen dataclasses, stored in every checkpoint.

A :class:`StreamConfig` describes one two-stream stack (``blocks`` TS blocks, each
with ``layers`` latent self-attention layers); :class:`ModelConfig` pairs the
condition encoder with the denoiser and fixes how clouds are scaled into the
network.  ``PRESETS`` holds the named ones:

* ``paper`` -- the paper's sizes (denoiser 6 x 4, d = 256, 256 latents, 8 heads;
  encoder 6 x 6, 64 tokens, 8 heads);
* ``cpu`` -- sized to train on a few CPU cores in hours;
* ``cpu-anchored`` -- ``cpu`` with anchored points (:attr:`ModelConfig.anchored`);
* ``cpu-anchored-normals`` -- ``cpu-anchored`` whose anchors carry the part's normals;
* ``tiny`` -- for tests.
"""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class StreamConfig:
    """One stack of two-stream blocks.

    Attributes
    ----------
    blocks : number of TS blocks (read -> ``layers`` x self-attention -> write)
    layers : latent self-attention layers per block (the paper's H)
    dim : width of both streams
    latents : learned latent tokens of this stack
    heads : attention heads
    mlp_ratio : hidden width of the feed-forward layers, in multiples of ``dim``
    write_mlp_ratio : hidden width of the feed-forward layer after each write (the point stream's own
        per-point network), in multiples of ``dim`` (0: ``mlp_ratio``)
    """

    blocks: int
    layers: int
    dim: int
    latents: int
    heads: int
    mlp_ratio: float = 4.0
    write_mlp_ratio: float = 0.0

    def __post_init__(self):
        for name in ("blocks", "layers", "dim", "latents", "heads"):
            if getattr(self, name) < 1:
                raise ValueError(f"StreamConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.dim % self.heads:
            raise ValueError(f"StreamConfig.dim ({self.dim}) must be a multiple of heads ({self.heads})")


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """The whole network.

    Attributes
    ----------
    encoder : the condition encoder e(g); its latents are the condition tokens z_c
    denoiser : eps_theta(x_t, z_c, t); its latents are z_init, joined by z_c and a time token
    point_dim : channels of a generated point (xyz + normal)
    cond_dim : channels of a condition point (xyz)
    fourier : frequencies of the Fourier features of positions (0 = linear embedding only)
    xyz_scale : canonical-frame coordinates (diagonal 1, centred) are multiplied by this
        before entering the network, so the data has roughly unit spread like the noise
    chunk : points processed at once on the point side at inference (memory is linear in
        the number of points with a constant set by this)
    anchored : the denoiser also sees an *anchor* per point, a sample of the part, and the
        generated point is ``anchor + displacement``: the diffusion runs over each anchor's
        displacement to its place on the polycube (and the normal there) instead of over free
        positions.  The target becomes nearly a function of the anchor, far less ambiguous than
        a free point set; the paper's recipe is ``anchored=False``.
    anchor_gain : displacements enter the network multiplied by ``xyz_scale * anchor_gain``
        (they are small: 99 % within 8 % of the diagonal per axis on the synthetic pairs)
    anchor_normals : an anchored model's anchor also carries the part's unit surface normal
        there (anchors are ``(n, 6)``).  From positions alone the network has to estimate the
        local surface direction itself, which the CPU-trained model had not learned (its
        normals' axis matched the target's at 66 % of the points, snapping the part's own
        normal matches at 99 %); the polycube labels still come from the generated normals.
    local_k : an anchored model's point stream also sees each anchor's ``local_k`` nearest
        condition points (:class:`~polycubenet.model.network.LocalContext`; 0: none).  Without it a
        point learns its surroundings only through the latents, which blur steps thinner than a few
        percent of the diagonal (session 19: held-out pairs with a slab under 3 % are exact 41 % of
        the time, thicker ones 66-78 %).
    local_ref : the local context reads at most this many condition points (an even stride through
        larger ones), so that a neighbourhood spans the same distance as in training
    recycle : the denoiser also takes its own previous estimate of the clean cloud per point
        (self-conditioning, or recycling: :class:`~polycubenet.model.network.Denoiser`); zeros on a
        first evaluation.  A one-step model then evaluates twice at the same timestep, the second
        time seeing where its first answer put every point (``train --recycle``, ``generate(recycles=)``).
    genus_classes : > 0: the condition also carries the part's genus (a topological fact of the input
        surface, which extraction checks the polycube against), one learned vector per genus
        ``0 .. genus_classes - 1`` (the last one for that genus and more) plus one for "unknown",
        added to every condition token (:meth:`~polycubenet.model.network.PolycubeNet.encode`); the
        vectors start at zero, so a file trained without them keeps its function.  0: the cloud only
        (the paper's).
    """

    encoder: StreamConfig
    denoiser: StreamConfig
    point_dim: int = 6
    cond_dim: int = 3
    fourier: int = 8
    xyz_scale: float = 2.0
    chunk: int = 32768
    anchored: bool = False
    anchor_gain: float = 4.0
    anchor_normals: bool = False
    local_k: int = 0
    local_ref: int = 2048
    recycle: bool = False
    genus_classes: int = 0

    @property
    def anchor_dim(self) -> int:
        """Channels of an anchor (0 for a free-point model)."""
        return (6 if self.anchor_normals else 3) if self.anchored else 0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        d = dict(d)
        d["encoder"] = StreamConfig(**d["encoder"])
        d["denoiser"] = StreamConfig(**d["denoiser"])
        return cls(**d)


PRESETS: dict[str, ModelConfig] = {
    "paper": ModelConfig(
        encoder=StreamConfig(blocks=6, layers=6, dim=256, latents=64, heads=8),
        denoiser=StreamConfig(blocks=6, layers=4, dim=256, latents=256, heads=8),
    ),
    # sized for a 2-core CPU: the point side (FF, read/write projections) dominates the cost,
    # so the width is small; the latent side is where the capacity is
    "cpu": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0),
    ),
    # the cpu preset with anchored points (see ModelConfig.anchored)
    "cpu-anchored": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        anchored=True,
    ),
    # cpu-anchored whose anchors carry the part's normals (see ModelConfig.anchor_normals)
    "cpu-anchored-normals": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        anchored=True,
        anchor_normals=True,
    ),
    # cpu-anchored-normals with five latent layers per denoiser block instead of three: more capacity
    # where it is cheap (64 latents, not the points).  ``train --init`` from a cpu-anchored-normals file
    # starts it as that file's function: the added layers begin as identities (``grow_identity``)
    "cpu-anchored-normals-deep": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=5, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        anchored=True,
        anchor_normals=True,
    ),
    # cpu-anchored-normals with three times the hidden width in the denoiser's per-point feed-forward layers
    # (after each write: 576 instead of 192), the network that places each generated point.  ``train --init``
    # from a cpu-anchored-normals file starts it as that file's function: the added hidden units' output
    # weights start at zero (``train._widen_hidden``)
    "cpu-anchored-normals-wide-write": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0, write_mlp_ratio=6.0),
        anchored=True,
        anchor_normals=True,
    ),
    # a larger cpu-anchored-normals for a long training line: six latent layers per denoiser block instead of
    # three and twice the per-point feed-forward width after each write (1.46x the parameters, about 1.3x the
    # CPU time a training step).  ``train --init`` from a cpu-anchored-normals file starts it as that file's
    # function (the added latent layers as identities, the added hidden units with zero output weights)
    "cpu-anchored-normals-big": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=6, dim=96, latents=64, heads=4, mlp_ratio=2.0, write_mlp_ratio=4.0),
        anchored=True,
        anchor_normals=True,
    ),
    # cpu-anchored-normals with each anchor's 16 nearest condition points (ModelConfig.local_k).
    # ``train --init`` from a cpu-anchored-normals file starts it as that file's function: the local
    # context's output projection starts at zero
    "cpu-anchored-normals-local": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        anchored=True,
        anchor_normals=True,
        local_k=16,
    ),
    # cpu-anchored-normals that also reads its own previous estimate (ModelConfig.recycle).  ``train
    # --init`` from a cpu-anchored-normals file starts it as that file's function: the estimate's
    # projection starts at zero
    "cpu-anchored-normals-recycle": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        anchored=True,
        anchor_normals=True,
        recycle=True,
    ),
    # cpu-anchored-normals told the part's genus (ModelConfig.genus_classes: 0-6, 7 and more, unknown).
    # ``train --init`` from a cpu-anchored-normals file starts it as that file's function: the genus
    # vectors start at zero
    "cpu-anchored-normals-genus": ModelConfig(
        encoder=StreamConfig(blocks=2, layers=2, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=3, layers=3, dim=96, latents=64, heads=4, mlp_ratio=2.0),
        anchored=True,
        anchor_normals=True,
        genus_classes=8,
    ),
    "tiny": ModelConfig(
        encoder=StreamConfig(blocks=1, layers=1, dim=32, latents=8, heads=2, mlp_ratio=2.0),
        denoiser=StreamConfig(blocks=1, layers=1, dim=32, latents=8, heads=2, mlp_ratio=2.0),
        fourier=4,
    ),
}


def preset(name: str) -> ModelConfig:
    """The named preset (``paper``, ``cpu``, ``tiny``)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown model preset {name!r}; choose from {sorted(PRESETS)}") from None
