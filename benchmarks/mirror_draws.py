"""Mirror-image draws on held-out pairs: do they add structures, and does their agreement say which draw is right?

    python benchmarks/mirror_draws.py --checkpoint F --data HELDOUT [--count 128] \\
        [--json benchmarks/results/mirror_draws.json]

For every held-out pair the model generates the polycube of the part and of its 7 mirror images (each axis
flipped or not; the canonical frame is centred, so a mirror image is a part of the same distribution, and
the training pairs are not mirrored by augmentation), one step, one point per condition sample (the
evaluation's anchors); each cloud is mirrored back, filtered and extracted with the pair's genus, as
``python -m polycubenet.evaluate`` does, and compared with the ground truth (exact structure).  Reported:

* ``single``: the unmirrored draw alone (what ``evaluate`` measures, on these pairs);
* ``any``: some draw of the eight exact (the ceiling of any rule that picks among them);
* ``vote``: the structure most draws share (ties to the unmirrored draw's), exact;
* ``agreement``: the unmirrored draw's exact rate by how many of the eight share its structure
  (minimal grid and occupancy), i.e. how well agreement tells a right structure from a wrong one.
"""

from __future__ import annotations

import argparse
import collections
import itertools
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SIGNS = tuple(itertools.product((1, -1), repeat=3))


def draws_of_pair(loaded, s, k: int) -> list[dict]:
    """The eight mirror draws of held-out pair ``k`` of shard ``s``: ``exact`` and the structure ``key``
    (None where the extraction refused the cloud)."""
    import numpy as np

    from polycubenet.cleanup import remove_outliers
    from polycubenet.errors import PolycubeError
    from polycubenet.inference import generate
    from polycubenet.polycube import compress, same_structure
    from polycubenet.structure import extract

    cp = np.asarray(s["cond_points"][k], np.float32)
    cn = np.asarray(s["cond_normals"][k], np.float32)
    order = np.random.default_rng(k).permutation(len(cp))  # the evaluation's anchor order
    gt, genus = s.polycube(k), int(s["genus"][k])
    signs = [np.asarray(sg, np.float32) for sg in SIGNS]
    clouds = generate([cp * sg for sg in signs], len(cp), model=loaded, steps=1, seed=0,
                      anchors=[np.hstack([cp * sg, cn * sg])[order] for sg in signs])
    out = []
    for sg, cloud in zip(signs, clouds):
        P, N = cloud[:, :3].astype(float) * sg, cloud[:, 3:].astype(float) * sg
        try:
            P, N, _ = remove_outliers(P, N)
            poly = extract(P, N, genus=genus, part=f"pair {int(s['seeds'][k])}")
        except PolycubeError:
            out.append({"exact": False, "key": None})
            continue
        _, occ = compress([poly.xs, poly.ys, poly.zs], poly.occupancy)
        out.append({"exact": bool(int(poly.meta["genus"]) == genus and same_structure(poly, gt, atol=0.02)),
                    "key": f"{occ.shape}:{np.packbits(occ.ravel()).tobytes().hex()}"})
    return out


def summarise(rows: list[list[dict]]) -> dict:
    """``single``, ``any``, ``vote`` rates and the ``agreement`` table of the module docstring."""
    single = [r[0]["exact"] for r in rows]
    anyx = [any(d["exact"] for d in r) for r in rows]
    vote, by_share = [], collections.defaultdict(list)
    for r in rows:
        keys = collections.Counter(d["key"] for d in r if d["key"] is not None)
        own = r[0]["key"]
        by_share[keys[own] if own is not None else 0].append(r[0]["exact"])
        if not keys:
            vote.append(False)
            continue
        top = max(keys.values())
        pick = own if own is not None and keys[own] == top else keys.most_common(1)[0][0]
        vote.append(next(d["exact"] for d in r if d["key"] == pick))
    n = len(rows)
    return {"pairs": n, "single": sum(single) / n, "any": sum(anyx) / n, "vote": sum(vote) / n,
            "agreement": {str(k): {"pairs": len(v), "exact": sum(v) / len(v)} for k, v in sorted(by_share.items())}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True, help="held-out shard folder")
    ap.add_argument("--count", type=int, default=128)
    ap.add_argument("--json", help="write the summary and the per-pair draws here")
    args = ap.parse_args(argv)

    from polycubenet.atomic import write_json
    from polycubenet.evaluate import _pairs
    from polycubenet.inference import load_model

    loaded = load_model(args.checkpoint, "cpu")
    rows, t0 = [], time.perf_counter()
    for i, (s, k) in enumerate(_pairs(args.data, args.count)):
        rows.append(draws_of_pair(loaded, s, k))
        if (i + 1) % 16 == 0:
            print(f"[mirror] {i + 1}/{args.count} pairs, {time.perf_counter() - t0:.0f} s", flush=True)
    if not rows:
        raise SystemExit(f"no held-out pairs in {args.data}")
    res = summarise(rows)
    print(f"{'pairs':>6} {'single':>7} {'any of 8':>9} {'vote':>6}")
    print(f"{res['pairs']:>6} {res['single']:>7.3f} {res['any']:>9.3f} {res['vote']:>6.3f}")
    print("draws sharing the unmirrored draw's structure -> its exact rate")
    for share, v in res["agreement"].items():
        print(f"  {share} of 8: {v['pairs']:>4} pairs, exact {v['exact']:.3f}")
    if args.json:
        write_json(args.json, {"checkpoint": args.checkpoint, "data": args.data, **res,
                               "rows": [[d["exact"] for d in r] for r in rows]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
