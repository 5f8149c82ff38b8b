"""``python -m polycubenet.model``: parameter counts of the model presets."""

from __future__ import annotations

import argparse
import sys

from .config import PRESETS
from .network import PolycubeNet, count_parameters


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polycubenet.model", description=__doc__)
    ap.add_argument("--preset", action="append", help="only these presets (default: all)")
    args = ap.parse_args(argv)
    names = args.preset or list(PRESETS)
    print(f"{'preset':<8} {'encoder':>12} {'denoiser':>12} {'total':>12}  fp32 MB  layout")
    for name in names:
        cfg = PRESETS[name]
        net = PolycubeNet(cfg)
        e, d = count_parameters(net.encoder), count_parameters(net.denoiser)
        lay = (f"enc {cfg.encoder.blocks}x{cfg.encoder.layers} d{cfg.encoder.dim} z{cfg.encoder.latents}; "
               f"den {cfg.denoiser.blocks}x{cfg.denoiser.layers} d{cfg.denoiser.dim} z{cfg.denoiser.latents} h{cfg.denoiser.heads}")
        print(f"{name:<8} {e:>12,} {d:>12,} {e + d:>12,}  {4 * (e + d) / 2**20:7.1f}  {lay}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
