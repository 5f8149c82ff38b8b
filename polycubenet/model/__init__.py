"""PolycubeNet: the dual-latent conditional diffusion model (network, configs, diffusion, checkpoints).

``python -m polycubenet.model`` prints the parameter counts of every preset.
"""

from .config import PRESETS, ModelConfig, StreamConfig, preset
from .diffusion import Diffusion, from_network, to_network
from .network import Attention, PolycubeNet, TwoStreamBlock, count_parameters

__all__ = [
    "PRESETS", "ModelConfig", "StreamConfig", "preset", "Diffusion", "from_network", "to_network",
    "Attention", "PolycubeNet", "TwoStreamBlock", "count_parameters",
]
