"""Where the held-out exact-structure figure is lost: the extraction, or the model's own error, and of what kind.

    python benchmarks/model_limits.py --data HELDOUT --ceiling 0,0.003,0.006,0.01 \\
        [--checkpoint F --draws 4] [--count 256] [--json benchmarks/results/model_limits.json]

* ``--ceiling``: the ground-truth polycube cloud of each held-out pair (the shard's target points and normals,
  2048 of them, as many as the evaluation's generated clouds), each point moved by isotropic Gaussian noise of
  standard deviation sigma (a fraction of the canonical diagonal), then filtered and extracted with the pair's
  genus exactly as ``python -m polycubenet.evaluate`` treats a generated cloud. sigma = 0 is the extraction's
  ceiling at this resolution; the sigma at which the exact rate falls to the model's says how large an
  unstructured error the model's structured one is worth.
* ``--checkpoint F --draws K``: the evaluation's one-step clouds, each anchor's point averaged over K noise
  draws (generator seeds ``seed + 1000 j``) before the extraction, beside one draw. If the exact rate and the
  Chamfer do not move, the model's error is not its noise (which averaging removes) but its bias.

Prints one table row per reading (exact, exact by the ground truth's thinnest slab, planes added / missed).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _summary(rows: list[dict]) -> dict:
    import numpy as np

    from polycubenet.evaluate import by_thinnest_slab

    return {"pairs": len(rows), "exact": float(np.mean([r["exact"] for r in rows])),
            "exact_by_thinnest_slab": by_thinnest_slab(rows),
            "planes_added": int(sum(r["planes_added"] or 0 for r in rows)),
            "planes_missed": int(sum(r["planes_missed"] or 0 for r in rows))}


def ceiling(data: str, count: int, sigma: float) -> dict:
    """Exact structure of the held-out pairs' ground-truth clouds with noise ``sigma``, extracted."""
    import numpy as np

    from polycubenet.evaluate import _pairs, _structure, thinnest_slab

    rows = []
    for s, k in _pairs(data, count):
        rng = np.random.default_rng(int(s["seeds"][k]))
        P = np.asarray(s["target_points"][k], float)
        P = P + rng.normal(0.0, sigma, P.shape)
        gt = s.polycube(k)
        row = {"gt_thinnest_slab": thinnest_slab(gt)}
        row.update(_structure(P, np.asarray(s["target_normals"][k], float), gt, int(s["genus"][k]), "ground truth"))
        rows.append(row)
    return _summary(rows)


def averaged_draws(checkpoint: str, data: str, count: int, draws: int) -> dict:
    """``python -m polycubenet.evaluate``'s reading with each anchor's point the mean of ``draws`` draws."""
    import numpy as np

    from polycubenet.evaluate import evaluate
    from polycubenet.inference import generate

    def mean_of_draws(conds, n, seed=0, **kw):
        outs = [generate(conds, n, seed=seed + 1000 * j, **kw) for j in range(draws)]
        res = []
        for i in range(len(conds)):
            a = np.stack([o[i] for o in outs])
            nrm = a[..., 3:].mean(0)
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-12
            res.append(np.hstack([a[..., :3].mean(0), nrm]).astype(np.float32))
        return res

    out = evaluate(checkpoint, data, count, n_out=4096, steps=1, seed=0, progress=False, generator=mean_of_draws)
    keep = ("exact_structure_rate", "exact_structure_rate_genus_le2", "exact_by_thinnest_slab", "planes_added",
            "planes_missed", "chamfer_median")
    return {k: out[k] for k in keep} | {"pairs": out["pairs"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="held-out shard folder (e.g. the seed-2 pairs)")
    ap.add_argument("--count", type=int, default=256)
    ap.add_argument("--ceiling", default=None, help="comma-separated noise sigmas for the ground-truth clouds")
    ap.add_argument("--checkpoint", default=None)
    ap.add_argument("--draws", type=int, default=0, help="with --checkpoint: also the mean of this many draws")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    res: dict = {"data": a.data, "count": a.count, "readings": {}}
    t0 = time.perf_counter()

    def show(name: str, r: dict) -> None:
        rate = r.get("exact", r.get("exact_structure_rate"))
        b = r["exact_by_thinnest_slab"]
        bins = " / ".join("-" if v["exact"] is None else f"{100 * v['exact']:.1f}" for v in b.values())
        print(f"| {name} | {r['pairs']} | {100 * rate:.1f} % | {bins} | {r['planes_added']} / {r['planes_missed']} |",
              flush=True)

    print("| reading | pairs | exact | by thinnest slab (< 0.03 / 0.03-0.05 / >= 0.05) | planes added / missed |")
    print("|---|---|---|---|---|")
    for sig in ([float(x) for x in a.ceiling.split(",")] if a.ceiling else []):
        r = res["readings"][f"ground truth, sigma {sig:g}"] = ceiling(a.data, a.count, sig)
        show(f"ground truth, sigma {sig:g}", r)
    if a.checkpoint:
        res["checkpoint"] = a.checkpoint
        for k in sorted({1, a.draws} - {0}):
            r = res["readings"][f"model, mean of {k} draw(s)"] = averaged_draws(a.checkpoint, a.data, a.count, k)
            show(f"model, mean of {k} draw(s)", r)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
