"""The shipped model's learning curve across sessions: cumulative CPU-hours (and GPU-hours, for the
runs made on a lent accelerator: ``scripts/device_train.sh``) -> held-out metrics.

    python benchmarks/plot_learning_curve.py [--curve benchmarks/results/learning_curve.jsonl] \\
        [--continue-curve benchmarks/results/learning_curve_continue.jsonl] \\
        [--features-curve benchmarks/results/learning_curve_features.jsonl] \\
        [--slant-curve benchmarks/results/learning_curve_slant_moves.jsonl] [--out docs/learning_curve.png]

Reads the points ``scripts/publish_checkpoint.sh`` appends (one per published checkpoint; a point
without ``cpu_hours`` is session 1's, 1.4 h), prints them as a table and plots the held-out median
Chamfer (with the identity reference: the part's own samples as the cloud), the genus-match rate for
pairs of genus <= 2 and the example parts accepted.  Beside them, the training line of the continue
file (``benchmarks/continue_curve.py``: every committed version re-measured with today's code, same held-out
pairs and command, no example parts), which goes on every session whether or not a file is published.
A third panel draws the same versions read on held-out pairs with machined features (``continue_curve.py
--data FEATURES``: ``python -m polycubenet.synth --cad-features --whole-slants``), exact structure per feature
class (slanted end, chamfer, neither: ``polycubenet.synth.shards.feature_class``), where the plain held-out
pairs have none of the slanted ends the never-seen parts fail on.  On it, dashed, the share of the way the
model takes the part's slanted faces toward their planes (``benchmarks/slant_moves.py --curve``; 1 puts them
onto the plane, less leaves a ramp the extraction reads as a staircase).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SESSION1_CPU_HOURS = 1.4  # recorded in MODEL_CARD.md; that checkpoint predates the cpu_hours field


def read_points(path) -> list[dict]:
    """The points of a curve file, one JSON object a line."""
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--curve", default=str(ROOT / "benchmarks/results/learning_curve.jsonl"))
    ap.add_argument("--continue-curve", default=str(ROOT / "benchmarks/results/learning_curve_continue.jsonl"))
    ap.add_argument("--features-curve", default=str(ROOT / "benchmarks/results/learning_curve_features.jsonl"))
    ap.add_argument("--slant-curve", default=str(ROOT / "benchmarks/results/learning_curve_slant_moves.jsonl"))
    ap.add_argument("--out", default=str(ROOT / "docs/learning_curve.png"))
    args = ap.parse_args(argv)
    slant = read_points(args.slant_curve) if Path(args.slant_curve).exists() else []
    slant.sort(key=lambda p: (p["cpu_hours"], p["gpu_hours"]))
    feat = read_points(args.features_curve) if Path(args.features_curve).exists() else []
    feat.sort(key=lambda p: (p["cpu_hours"], p["gpu_hours"]))
    cont = read_points(args.continue_curve) if Path(args.continue_curve).exists() else []
    cont.sort(key=lambda p: (p["cpu_hours"], p["gpu_hours"]))
    pts = read_points(args.curve)
    for p in pts:
        p["cpu_hours"] = p.get("cpu_hours") or SESSION1_CPU_HOURS
        p["gpu_hours"] = p.get("gpu_hours") or 0.0
    pts.sort(key=lambda p: (p["cpu_hours"], p["gpu_hours"]))
    print(f"{'CPU-h':>6} {'GPU-h':>5} {'recipe':<30} {'extract':>7} {'steps':>5} {'Chamfer':>8} {'identity':>8} {'labels':>6} "
          f"{'exact':>6} {'exact id':>8} {'genus<=2':>8} {'parts':>6}")
    for p in pts:
        d = p.get("diffusion") or {}
        recipe = (f"{d.get('prediction', 'eps')}/{d.get('schedule', 'cosine')}" + ("/anch" if p.get("anchored") else "")
                  + ("+normals" if p.get("anchor_normals") else ""))
        lab = p.get("label_accuracy")
        print(f"{p['cpu_hours']:>6.2f} {p['gpu_hours']:>5.2f} {recipe:<30} {p.get('extraction', 1):>7} {p['steps']:>5} {p['chamfer_median']:>8.4f} "
              f"{p.get('chamfer_identity') or float('nan'):>8.4f} {lab if lab is not None else float('nan'):>6.3f} "
              f"{p['exact']:>6.0%} {p['exact_identity'] if p.get('exact_identity') is not None else float('nan'):>8.0%} "
              f"{(p.get('genus_match_genus_le2') or 0):>8.0%} {p['parts_accepted']:>3}/{p['parts']}")
    if cont:
        print(f"\ncontinue file (benchmarks/continue_curve.py, {cont[0]['pairs']} held-out pairs, today's code)")
        print(f"{'CPU-h':>6} {'GPU-h':>5} {'commit':>8} {'Chamfer':>8} {'identity':>8} {'labels':>6} {'exact':>6} {'genus<=2':>8}")
        for p in cont:
            lab = p.get("label_accuracy")
            print(f"{p['cpu_hours']:>6.2f} {p['gpu_hours']:>5.2f} {p['commit'][:8]:>8} {p['chamfer_median']:>8.4f} "
                  f"{p['chamfer_identity']:>8.4f} {lab if lab is not None else float('nan'):>6.3f} {p['exact']:>6.0%} "
                  f"{(p.get('genus_match_genus_le2') or 0):>8.0%}")
    from polycubenet.synth.shards import FEATURE_CLASSES as classes

    if feat:
        print(f"\ncontinue file on pairs with machined features ({feat[0]['pairs']} pairs, exact structure)")
        print(f"{'CPU-h':>6} {'GPU-h':>5} {'commit':>8} {'Chamfer':>8} {'exact':>6}" + "".join(f"{c:>13}" for c in classes))
        for p in feat:
            by = p.get("exact_by_feature") or {}
            cells = "".join(f"{by[c]['exact']:>8.0%} /{by[c]['pairs']:>3}" if c in by else f"{'-':>13}" for c in classes)
            print(f"{p['cpu_hours']:>6.2f} {p['gpu_hours']:>5.2f} {p['commit'][:8]:>8} {p['chamfer_median']:>8.4f} "
                  f"{p['exact']:>6.0%}{cells}")
    if slant:
        print(f"\ncontinue file: share of the way slanted faces are moved ({slant[0]['pairs']} pairs, median per class)")
        print(f"{'CPU-h':>6} {'GPU-h':>5} {'commit':>8}" + "".join(f"{c:>13}" for c in classes) + f"{'err slanted':>12}")
        for p in slant:
            by = p.get("by_feature") or {}
            cells = "".join(f"{by[c]['moved_median']:>13.2f}" if by.get(c, {}).get("moved_median") is not None
                            else f"{'-':>13}" for c in classes)
            print(f"{p['cpu_hours']:>6.2f} {p['gpu_hours']:>5.2f} {p['commit'][:8]:>8}{cells}"
                  f"{p['all']['err_slanted_median']:>12.4f}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [p["cpu_hours"] for p in pts]
    fig, ax = plt.subplots(1, 3 if feat else 2, figsize=(13.5 if feat else 9, 3.2))
    ax[0].plot(x, [p["chamfer_median"] for p in pts], "o-", label="model")
    ident = [p.get("chamfer_identity") for p in pts]
    if any(v is not None for v in ident):
        ax[0].plot([xi for xi, v in zip(x, ident) if v is not None], [v for v in ident if v is not None], "k--",
                   label="identity (part samples)")
    if cont:
        ax[0].plot([p["cpu_hours"] for p in cont], [p["chamfer_median"] for p in cont], ".-", color="tab:gray",
                   label="continue file (not published)")
    ax[0].axhline(0.015, color="g", lw=0.8, label="target 1.5 %")
    ax[0].set_xlabel("cumulative CPU-hours")
    ax[0].set_ylabel("held-out Chamfer (median, diag.)")
    ax[0].legend(fontsize=7)
    ax[1].plot(x, [p["exact"] for p in pts], "o-", label="exact structure")
    idx = [(xi, p["exact_identity"]) for xi, p in zip(x, pts) if p.get("exact_identity") is not None]
    if idx:  # the same extraction on the part's own samples: what a model gets for free
        ax[1].plot(*zip(*idx), "kx--", label="exact, identity (no model)")
    ax[1].plot(x, [p.get("genus_match_genus_le2") or 0 for p in pts], "s-", label="genus match (genus <= 2)")
    ax[1].plot(x, [p["parts_accepted"] / max(1, p["parts"]) for p in pts], "^-", label="example parts accepted")
    if cont:
        cx = [p["cpu_hours"] for p in cont]
        ax[1].plot(cx, [p["exact"] for p in cont], ".-", color="tab:gray", label="exact, continue file")
        ax[1].plot(cx, [p.get("genus_match_genus_le2") or 0 for p in cont], ".:", color="tab:gray",
                   label="genus match, continue file")
    gpu_before = 0.0
    for xi, p in zip(x, pts):  # where accelerator time was added (at the CPU-hours it started from), once each
        if p["gpu_hours"] > gpu_before:
            gpu_before = p["gpu_hours"]
            ax[1].annotate(f"+{p['gpu_hours']:.2f} GPU-h", (xi, p["exact"]), fontsize=6, xytext=(-40, 8),
                           textcoords="offset points")
    ax[1].set_ylim(-0.05, 1.05)
    ax[1].set_xlabel("cumulative CPU-hours")
    ax[1].legend(fontsize=6, ncol=2, loc="lower right")
    if feat:
        fx = [p["cpu_hours"] for p in feat]
        ax[2].plot(fx, [p["exact"] for p in feat], "o-", color="k", label="all")
        for c, m in zip(classes, ("s-", "^-", "v-")):
            ax[2].plot(fx, [(p.get("exact_by_feature") or {}).get(c, {}).get("exact", float("nan")) for p in feat], m,
                       label=c)
        if slant:
            sx = [p["cpu_hours"] for p in slant]
            for c, col in (("slanted end", "tab:blue"), ("chamfer", "tab:orange")):
                ax[2].plot(sx, [(p.get("by_feature") or {}).get(c, {}).get("moved_median") or float("nan") for p in slant],
                           "--", color=col, label=f"{c}: share of the way moved")
        ax[2].set_ylim(-0.05, 1.05)
        ax[2].set_xlabel("cumulative CPU-hours")
        ax[2].set_ylabel("exact (solid), moved (dashed)" if slant else "exact structure, continue file")
        ax[2].set_title("held-out pairs with machined features", fontsize=8)
        ax[2].legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
