"""Guiding the model with a less trained version of itself (autoguidance), measured on held-out pairs.

    python benchmarks/autoguidance.py --data HELDOUT [--count 100] [--steps 1 4] \\
        [--good polycubenet/checkpoints/polycubenet-cpu.pt] [--bad REV:PATH ...] [--weights 1 1.25 1.5 2] \\
        [--out benchmarks/results/autoguidance.json]

Each evaluation of the denoiser is replaced by ``bad + w * (good - bad)``: ``w = 1`` is the good model alone,
``w > 1`` pushes its prediction further from the weaker model's (Karras et al. 2024, "Guiding a diffusion model
with a bad version of itself"), ``0 < w < 1`` averages the two (an ensemble).  Both models must share the
architecture and the diffusion parametrisation; every committed checkpoint of this project's line does
(preset ``cpu-anchored-normals``, v-prediction).  A ``--bad`` of the form ``REV:PATH`` is read from git.
The metrics are :func:`polycubenet.evaluate.evaluate`'s at ``--n-out 4096``, noise seed 0, so the ``w = 1``
row is the good model's own figure in the same run.  Prints a table and writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: the default weaker models: the shipped line at 8.20 h (commit 1e44d44), 11.18 h (76332b0) and 16.30 h (087c520)
DEFAULT_BAD = ("1e44d44:polycubenet/checkpoints/polycubenet-cpu.pt", "76332b0:polycubenet/checkpoints/polycubenet-cpu.pt",
               "087c520:polycubenet/checkpoints/polycubenet-cpu.pt")


def guided_model(good, bad, weight: float):
    """A :class:`~polycubenet.model.checkpoint.Loaded` whose denoiser returns ``bad + weight * (good - bad)``
    (``good``, ``bad``: loaded checkpoints with the same diffusion parametrisation)."""
    import torch

    from polycubenet.model.checkpoint import Loaded

    if good.diffusion.to_dict() != bad.diffusion.to_dict():
        raise ValueError(f"the two models differ in diffusion: {good.diffusion.to_dict()} vs {bad.diffusion.to_dict()}")

    class Guided(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.good, self.bad, self.config = good.model.eval(), bad.model.eval(), good.model.config

        def encode(self, cond, chunk=None):
            return self.good.encode(cond, chunk=chunk), (self.bad.encode(cond, chunk=chunk) if weight != 1 else None)

        def denoise(self, x, t, z, chunk=None, **kw):
            out = self.good.denoise(x, t, z[0], chunk=chunk, **kw)
            if weight == 1:
                return out
            low = self.bad.denoise(x, t, z[1], chunk=chunk, **kw)
            return low + weight * (out - low)

    return Loaded(model=Guided(), diffusion=good.diffusion, meta=good.meta, path=None)


def read_checkpoint(spec: str, tmp: Path) -> Path:
    """``spec`` as a file: a path, or ``REV:PATH`` written out of git into ``tmp``."""
    if Path(spec).is_file():
        return Path(spec)
    rev, _, path = spec.partition(":")
    blob = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], capture_output=True, check=True).stdout
    out = tmp / f"{rev}.pt"
    out.write_bytes(blob)
    return out


def main(argv=None) -> int:
    import torch

    from polycubenet.atomic import write_json
    from polycubenet.evaluate import evaluate
    from polycubenet.model.checkpoint import load_checkpoint

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="held-out shard folder")
    ap.add_argument("--count", type=int, default=100)
    ap.add_argument("--good", default=str(ROOT / "polycubenet/checkpoints/polycubenet-cpu.pt"))
    ap.add_argument("--bad", nargs="+", default=list(DEFAULT_BAD), help="weaker checkpoints: files or REV:PATH")
    ap.add_argument("--weights", nargs="+", type=float, default=[1.0, 1.25, 1.5, 2.0])
    ap.add_argument("--steps", nargs="+", type=int, default=[1], help="DDIM steps (the product's draws: 1, then 4)")
    ap.add_argument("--out", default=None, help="JSON of the rows")
    args = ap.parse_args(argv)

    rows = []
    good = load_checkpoint(args.good, device="cpu")
    print(f"{'weaker model':>12} {'CPU-h':>6} {'w':>5} {'steps':>5} {'exact':>6} {'genus':>6} {'Chamfer':>8} {'failed':>6}")
    with tempfile.TemporaryDirectory() as tmp, torch.no_grad():
        for spec in args.bad:
            bad = load_checkpoint(read_checkpoint(spec, Path(tmp)), device="cpu")
            hours = float(bad.meta.get("cpu_hours") or 0.0)
            for steps in args.steps:
                for w in args.weights:
                    if w == 1 and any(r["weight"] == 1 and r["steps"] == steps for r in rows):
                        continue  # the good model alone: once per step count
                    t0 = time.perf_counter()
                    r = evaluate(guided_model(good, bad, w), args.data, args.count, n_out=4096, steps=steps, seed=0,
                                 progress=False)
                    row = {"bad": spec, "bad_cpu_hours": round(hours, 2), "weight": w, "steps": steps,
                           "exact": r["exact_structure_rate"], "genus": r["genus_match_rate"],
                           "chamfer_median": r["chamfer_median"], "extract_failed": r["extract_failed_rate"],
                           "exact_genus_le2": r["exact_structure_rate_genus_le2"],
                           "seconds": round(time.perf_counter() - t0, 1)}
                    rows.append(row)
                    print(f"{Path(spec.partition(':')[0]).stem[:12]:>12} {hours:6.2f} {w:5.2f} {steps:5d} "
                          f"{row['exact']:6.2f} {row['genus']:6.2f} {row['chamfer_median']:8.5f} {row['extract_failed']:6.2f}",
                          flush=True)
    if args.out:
        write_json(args.out, {"good": args.good, "data": args.data, "count": args.count, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
