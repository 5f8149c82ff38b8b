"""Two checkpoints together: does averaging them beat either one on held-out pairs?

    python benchmarks/checkpoint_ensembles.py --checkpoints A.pt B.pt --data HELDOUT [--count 256] \\
        [--json benchmarks/results/checkpoint_ensembles.json]

Rows, each measured as ``python -m polycubenet.evaluate --n-out 4096 --steps 1 --seed 0`` measures a
checkpoint (exact structure, genus match, Chamfer on the first ``--count`` held-out pairs):

* each checkpoint alone;
* ``soup``: one model whose weights are the uniform average of the checkpoints' EMA weights (they must
  share the architecture; sensible for checkpoints of one lineage, e.g. the shipped file and the continue
  file trained on from it);
* ``ensemble``: every model evaluated on the same noise and anchors, their v-predictions averaged (with the
  one-step sampler: their clean estimates averaged), at the cost of one evaluation per model.

``--soup-out FILE`` keeps the soup's weights (default: a temporary file), e.g. to mesh never-seen parts with
``benchmarks/unseen_parts.py --mesh --checkpoint FILE``.  Prints a table and writes the JSON.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


class Ensemble(nn.Module):
    """Several models as one: ``encode`` keeps one condition encoding per model, ``denoise`` averages their
    predictions (what ``Diffusion.sample`` calls; the models must share ``config``'s point layout)."""

    def __init__(self, nets):
        super().__init__()
        self.nets = nn.ModuleList(nets)
        self.config = nets[0].config

    def encode(self, cond, chunk=None):
        return [m.encode(cond, chunk=chunk) for m in self.nets]

    def denoise(self, x_t, t, z_c, chunk=None, **kw):
        outs = [m.denoise(x_t, t, z, chunk=chunk, **kw).float() for m, z in zip(self.nets, z_c)]
        return sum(outs) / len(outs)


def soup_state(paths) -> dict:
    """The first checkpoint's file contents with its EMA weights replaced by the uniform average of every
    checkpoint's (each tensor averaged in float32, stored in the first file's dtype); raises ValueError when
    the checkpoints' weights do not have the same names and shapes."""
    state = torch.load(paths[0], map_location="cpu", weights_only=False)
    members = [torch.load(c, map_location="cpu", weights_only=False)["ema"] for c in paths]
    for c, m in zip(paths, members):
        if set(m) != set(members[0]) or any(m[k].shape != members[0][k].shape for k in m):
            raise ValueError(f"{c} does not share the architecture of {paths[0]}: no soup")
    state["ema"] = {k: (sum(m[k].float() for m in members) / len(members)).to(members[0][k].dtype) for k in members[0]}
    state["lineage"] = list(state.get("lineage", [])) + [{"soup": [str(c) for c in paths]}]
    return state


def main(argv=None) -> int:
    from polycubenet.atomic import write_json
    from polycubenet.evaluate import evaluate
    from polycubenet.inference import load_model
    from polycubenet.model.checkpoint import Loaded

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", required=True)
    ap.add_argument("--data", required=True, help="held-out shards (python -m polycubenet.synth --seed 2 --count 256)")
    ap.add_argument("--count", type=int, default=256)
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/checkpoint_ensembles.json"))
    ap.add_argument("--soup-out", default=None, help="where to keep the soup's weights (default: a temporary file)")
    args = ap.parse_args(argv)
    if len(args.checkpoints) < 2:
        ap.error("--checkpoints needs two or more files")
    loaded = [load_model(c, "cpu") for c in args.checkpoints]
    try:
        state = soup_state(args.checkpoints)
    except ValueError as exc:
        ap.error(str(exc))
    soup_path = Path(args.soup_out) if args.soup_out else Path(tempfile.mkdtemp(prefix="soup-")) / "soup.pt"
    soup_path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, soup_path)

    ens = Ensemble([lo.model for lo in loaded]).eval()
    rows = {Path(c).stem: lo for c, lo in zip(args.checkpoints, loaded)}  # the models already read
    rows["soup"] = str(soup_path)
    rows["ensemble"] = Loaded(model=ens, diffusion=loaded[0].diffusion, meta=dict(loaded[0].meta), path=loaded[0].path)
    keep = ("exact_structure_rate", "exact_structure_rate_genus_le2", "genus_match_rate", "chamfer_median",
            "planes_added", "planes_missed", "gen_seconds_per_pair")
    result = {"checkpoints": args.checkpoints, "data": args.data, "count": args.count, "rows": {}}
    for name, ck in rows.items():
        r = evaluate(ck, args.data, args.count, n_out=4096, steps=1, seed=0, progress=False)
        result["rows"][name] = {k: r.get(k) for k in keep}
        print(f"[checkpoint_ensembles] {name}: exact {r['exact_structure_rate']:.3f}", file=sys.stderr, flush=True)
    print(f"\n{'row':32s}{'exact':>8s}{'g<=2 exact':>12s}{'genus':>8s}{'Chamfer':>10s}{'added/missed':>14s}")
    for name, r in result["rows"].items():
        print(f"{name:32s}{r['exact_structure_rate']:8.3f}{r['exact_structure_rate_genus_le2']:12.3f}"
              f"{r['genus_match_rate']:8.3f}{r['chamfer_median']:10.4f}{r['planes_added']:>8d} / {r['planes_missed']:<4d}")
    write_json(args.json, result)
    print(f"wrote {args.json} (soup weights: {soup_path})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
