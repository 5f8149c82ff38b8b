"""Does it matter how the anchors are spread?  Held-out pairs drawn with evenly spread or independent anchors.

    python -m polycubenet.synth --out DENSE --count 128 --seed 2 --n-cond 16384 --n-target 16384
    python benchmarks/anchor_sampling.py --data DENSE --count 64 \\
        [--checkpoint polycubenet/checkpoints/polycubenet-cpu-continue.pt] \\
        [--arms random:2048:2048,even:2048:2048,random:2048:4096,even:2048:4096] \\
        [--json benchmarks/results/anchors_s37_heldout.json]

An anchored model moves each anchor (a point of the part, with its normal) onto the polycube, so the
generated cloud is spread over the polycube as the anchors are spread over the part.  The model learned
from evenly spread anchors (preimages of a blue-noise sample of the polycube) and the held-out figure
reads pairs with their Poisson-disk condition points as anchors.  Here every pair of a held-out folder
sampled densely (``--n-cond 16384``) is drawn once per arm ``ANCHORS:CONDITION:N``: ``N`` anchors chosen
from the pair's dense points either evenly (``even``: the first ``N`` of their farthest-point order,
:func:`polycubenet.registration.farthest_point_sampling`, the analogue of a Poisson-disk sample of the mesh,
which the shards do not store) or independently (``random``: a random subset, the statistics of the
pipeline's area-uniform samples), the condition the first ``CONDITION`` points of that order
(the condition's spread matters little: a random condition scored as an even one in session 37).  Each
cloud is read by the extraction against the pair's ground truth (exact structure, as
``python -m polycubenet.evaluate``).  Prints one row per arm; writes the JSON (per arm the exact count
and the per-pair flags).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def parse_arms(text: str) -> list[tuple[str, int, int]]:
    arms = []
    for entry in text.split(","):
        kind, cond, n = entry.split(":")
        if kind not in ("even", "random"):
            raise SystemExit(f"--arms: {entry!r}: the anchors are 'even' or 'random'")
        arms.append((kind, int(cond), int(n)))
    return arms


def main(argv=None) -> int:
    from polycubenet.atomic import write_json
    from polycubenet.evaluate import _pairs, _structure
    from polycubenet.inference import DEFAULT_CHECKPOINT, generate, load_model
    from polycubenet.registration import farthest_point_sampling

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="held-out folder sampled densely (--n-cond 16384)")
    ap.add_argument("--count", type=int, default=64)
    ap.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    ap.add_argument("--arms", default="random:2048:2048,even:2048:2048,random:2048:4096,even:2048:4096")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/anchors_s37_heldout.json"))
    args = ap.parse_args(argv)

    arms = parse_arms(args.arms)
    loaded = load_model(args.checkpoint, "cpu")
    items = list(_pairs(args.data, args.count))
    need = max(max(c, n) for _, c, n in arms)
    if not items or len(items[0][0]["cond_points"][items[0][1]]) < need:
        raise SystemExit(f"{args.data}: need pairs with at least {need} condition points (synth --n-cond 16384)")
    exact: dict[str, list[bool]] = {f"{k}:{c}:{n}": [] for k, c, n in arms}
    t0 = time.perf_counter()
    for j, (s, k) in enumerate(items):
        cp = np.asarray(s["cond_points"][k], np.float32)
        cn = np.asarray(s["cond_normals"][k], np.float32)
        gt, genus = s.polycube(k), int(s["genus"][k])
        # every prefix of a farthest-point order is evenly spread; the condition is its first CONDITION
        # points and evenly spread anchors its first N, so at N = CONDITION the anchors are the condition's
        # points, as the held-out figure reads its pairs (python -m polycubenet.evaluate)
        even = farthest_point_sampling(cp, need)
        random_anchors = np.random.default_rng(k + 7).permutation(len(cp))
        for kind, c, n in arms:
            ai = (even if kind == "even" else random_anchors)[:n]
            (cloud,) = generate([cp[even[:c]]], n, model=loaded, steps=1, seed=j, device="cpu",
                                anchors=[np.hstack([cp[ai], cn[ai]])])
            r = _structure(cloud[:, :3].astype(float), cloud[:, 3:].astype(float), gt, genus, f"pair {j}")
            exact[f"{kind}:{c}:{n}"].append(bool(r["exact"]))
        print(f"[anchors] {j + 1}/{len(items)} pairs, {time.perf_counter() - t0:.0f} s", flush=True)
    print(f"\n{len(items)} held-out pairs of {args.data}, {Path(args.checkpoint).name}, one step\n")
    print("| anchors | condition points | anchors (points drawn) | exact structure |")
    print("|---|---|---|---|")
    for key, flags in exact.items():
        kind, c, n = key.split(":")
        print(f"| {kind} | {c} | {n} | {sum(flags)} / {len(flags)} |")
    write_json(args.json, {"checkpoint": args.checkpoint, "data": args.data, "pairs": len(items),
                           "arms": {key: {"exact": sum(f), "pairs": len(f), "flags": f} for key, f in exact.items()},
                           "seconds": round(time.perf_counter() - t0, 1)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
