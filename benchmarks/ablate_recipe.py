"""Recipe ablation at equal CPU time: one row per change against today's recipe.

    python benchmarks/ablate_recipe.py --data TRAIN --heldout HELDOUT --cpu-minutes 15 \\
        --init polycubenet/checkpoints/polycubenet-cpu.pt --rows baseline v_ztsnr ot points256 \\
        --jobs 2 --out /tmp/ablate --json benchmarks/results/ablate_recipe.json

Every row trains the ``cpu`` preset from the same starting weights (``--init``; a fresh
model without it) on the same shards for the same CPU time of its own process (one torch
thread), then is evaluated on the same held-out pairs with the same sampler settings.
CPU time, not wall time, is what is held equal: rows may run side by side (``--jobs``) on
a shared machine without favouring one another.  The table gives CPU-minutes, steps
reached, held-out Chamfer (median, fraction of the diagonal), exact structure, genus
match and the extraction refusal rate; the JSON keeps every row's evaluation.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: one row per change (train flags added to the common ones); ``baseline`` is today's recipe
ROWS: dict[str, list[str]] = {
    "baseline": [],
    "v_ztsnr": ["--prediction", "v", "--schedule", "cosine_ztsnr"],
    "min_snr5": ["--min-snr", "5"],
    "ot": ["--pairing", "ot"],
    "points256": ["--points", "256"],
    "genus2": ["--max-genus", "2"],
    "batch24": ["--batch", "24"],
    # anchored points (ModelConfig.anchored): each generated point is a part point moved onto the polycube
    "anchored": ["--preset", "cpu-anchored"],
    "anchored_v": ["--preset", "cpu-anchored", "--prediction", "v", "--schedule", "cosine_ztsnr"],
    # anchors that carry the part's normal (ModelConfig.anchor_normals)
    "anchored_vn": ["--preset", "cpu-anchored-normals", "--prediction", "v", "--schedule", "cosine_ztsnr"],
    # timesteps drawn towards the noisy end, where a few-step sampler decides the shape
    "anchored_vn_tbias3": ["--preset", "cpu-anchored-normals", "--prediction", "v", "--schedule", "cosine_ztsnr",
                           "--t-bias", "3"],
    # t always at the noisy end: a one-step regression of the polycube from the anchors (sampled in 1 step)
    "anchored_vn_regress": ["--preset", "cpu-anchored-normals", "--prediction", "v", "--schedule", "cosine_ztsnr",
                            "--t-bias", "1000"],
    # displacements 4x larger in network units (gain 32): about the scale of the unit normals beside them
    "anchored_vn_gain32": ["--preset", "cpu-anchored-normals", "--prediction", "v", "--schedule", "cosine_ztsnr",
                           "--anchor-gain", "32"],
}
# the shipped recipe (anchor normals, one-step regression) at two batch sizes, for continuing a trained file
ROWS.update({f"regress_b{b}": ROWS["anchored_vn_regress"] + ["--batch", str(b)] for b in (12, 48)})


#: rows sampled with their own number of DDIM steps (a row trained only at t = T - 1 knows no other step)
ROW_EVAL_STEPS = {name: 1 for name, flags in ROWS.items() if "--t-bias" in flags and flags[flags.index("--t-bias") + 1] == "1000"}


def run_row(name: str, args) -> dict:
    out = Path(args.out) / name
    cmd = [sys.executable, "-m", "polycubenet.train", "--data", args.data, "--out", str(out), "--preset", "cpu",
           "--steps", str(args.steps), "--batch", str(args.batch), "--points", str(args.points), "--lr", str(args.lr),
           "--warmup", str(args.warmup), "--threads", "1", "--max-cpu-minutes", str(args.cpu_minutes),
           "--ckpt-every", "100", "--log-every", "50", "--no-progress"]
    if args.init:
        cmd += ["--init", args.init]
    extra = list(ROWS[name])
    # a row's own flags override the common ones (argparse keeps the last)
    cmd += extra
    t0 = time.time()
    log = out.with_suffix(".log")
    out.parent.mkdir(parents=True, exist_ok=True)
    if not (out / "last.pt").exists() or args.retrain:
        with open(log, "w") as fh:
            subprocess.run(cmd, check=True, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    train_wall = time.time() - t0
    ev_json = out / "eval.json"
    ev_cmd = [sys.executable, "-m", "polycubenet.evaluate", "--checkpoint", str(out / "last.pt"), "--data",
              args.heldout, "--count", str(args.count), "--n-out", str(args.n_out), "--steps", str(ROW_EVAL_STEPS.get(name, args.eval_steps)),
              "--json", str(ev_json), "--device", "cpu"]
    if not ev_json.exists() or args.retrain:  # a row already trained and evaluated is only read back
        with open(log, "a") as fh:
            subprocess.run(ev_cmd, check=True, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT,
                           env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})
    ev = json.loads(ev_json.read_text())
    import torch

    ck = torch.load(out / "last.pt", map_location="cpu", weights_only=False)
    low = [r for r in ev["rows"] if r["genus"] <= 2]
    return {
        "row": name, "flags": extra, "steps": int(ck["step"]), "eval_steps": ROW_EVAL_STEPS.get(name, args.eval_steps), "cpu_minutes": round(args.cpu_minutes, 1),
        "train_wall_s": round(train_wall, 1), "chamfer_median": ev["chamfer_median"],
        "exact": ev["exact_structure_rate"], "genus_match": ev["genus_match_rate"],
        "refused": ev["extract_failed_rate"], "same_cells": ev.get("same_cells_rate"), "label_accuracy": ev.get("label_accuracy_median"),
        "label_accuracy_part_normals": ev.get("label_accuracy_part_normals_median"), "n_generated": ev.get("n_generated"),
        "exact_genus_le2": sum(r["exact"] for r in low) / max(1, len(low)),
        "genus_match_le2": sum(r["genus_match"] for r in low) / max(1, len(low)),
        "pairs": ev["pairs"], "eval": str(ev_json),
    }


def identity_chamfer(heldout: str, count: int) -> float:
    """Median Chamfer of the held-out pairs' own condition samples to their polycube: the reference a model
    has to beat (the same pairs and the same measure as ``evaluate``)."""
    import numpy as np

    from polycubenet.evaluate import _pairs, chamfer

    return float(np.median([chamfer(np.asarray(s["cond_points"][k], float), np.asarray(s["target_points"][k], float))
                            for s, k in _pairs(heldout, count)]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--heldout", required=True)
    ap.add_argument("--init", help="starting checkpoint of every row (default: a fresh model)")
    ap.add_argument("--rows", nargs="+", default=["baseline", "v_ztsnr", "ot", "points256"], choices=sorted(ROWS))
    ap.add_argument("--cpu-minutes", type=float, default=15.0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--steps", type=int, default=4000, help="the cosine lr schedule's length (runs stop on CPU time)")
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--points", type=int, default=512)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--count", type=int, default=64, help="held-out pairs")
    ap.add_argument("--n-out", type=int, default=4096)
    ap.add_argument("--eval-steps", type=int, default=32)
    ap.add_argument("--retrain", action="store_true")
    ap.add_argument("--out", required=True)
    ap.add_argument("--json", required=True)
    args = ap.parse_args(argv)
    with ThreadPoolExecutor(args.jobs) as ex:
        rows = list(ex.map(lambda r: run_row(r, args), args.rows))
    identity = identity_chamfer(args.heldout, args.count)
    print(f"{'row':<10} {'CPU min':>7} {'steps':>6} {'Chamfer':>8} {'exact':>6} {'genus':>6} {'refused':>7} "
          f"{'exact g<=2':>10} {'genus g<=2':>10} {'labels':>6} {'same cells':>10}")
    for r in rows:
        print(f"{r['row']:<10} {r['cpu_minutes']:>7.1f} {r['steps']:>6} {r['chamfer_median']:>8.4f} {r['exact']:>6.2f} "
              f"{r['genus_match']:>6.2f} {r['refused']:>7.2f} {r['exact_genus_le2']:>10.2f} {r['genus_match_le2']:>10.2f} "
              f"{r['label_accuracy'] if r['label_accuracy'] is not None else float('nan'):>6.3f} "
              f"{r['same_cells'] if r.get('same_cells') is not None else float('nan'):>10.2f}")
    print(f"{'identity':<10} {'':>7} {'':>6} {identity:>8.4f}   (the part's own samples as the polycube cloud)")
    snap = rows[0].get("label_accuracy_part_normals")
    if snap is not None:
        print(f"labels: fraction of generated normals on the right axis and sign; the part's own normals snapped: {snap:.3f}")
    from polycubenet.atomic import write_json

    write_json(args.json, {"settings": {k: v for k, v in vars(args).items()}, "rows": rows,
                           "chamfer_identity_median": identity})
    return 0


if __name__ == "__main__":
    sys.exit(main())
