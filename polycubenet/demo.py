"""Run the stages that exist today over a folder of parts (the README's ``make demo``).

For every part: load and validate (:func:`polycubenet.io.load_part`), put it in
the canonical frame, Poisson-disk sample it, and write per part::

    <out>/<part>/part.npz        validated surface in the canonical frame (+ metadata)
    <out>/<part>/transform.json  canonical frame -> original coordinates
    <out>/<part>/sample.npz      SurfaceSample (points, normals, face ids, barycentrics)
    <out>/<part>/sample.png      the sample, coloured by the dominant normal axis

and ``<out>/manifest.json`` with one row per part (status, stage reached,
error, timings).  A bad part is recorded as failed with its error and the batch
goes on.

Until the model (and the classical fallback) can produce a polycube for a real part,
the back half of the spine is shown on ``--synthetic K`` generated parts whose
ground-truth polycube, with noise and outliers, stands in for the model's output
(:class:`polycubenet.pipeline.OracleSource`): each is meshed end to end into
``<out>/synthetic/<name>/`` (``hex.vtu``, ``hex.inp``, ``quality.json``,
``quality.png``, ``preview.png``, ``polycube.npz``).  The orchestrated version of the
full job is ``flows/mesh_library.py``.

Usage::

    python -m polycubenet.demo examples/parts -o out/demo [--points 4096] [--seed 0] [--synthetic 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from .atomic import atomic_path, write_json
from .errors import PartError
from .frame import canonicalize

#: what ``discover`` picks up; STEP/IGES are preferred over a mesh export of the same part
PART_SUFFIXES = (".step", ".stp", ".iges", ".igs", ".stl", ".obj", ".ply", ".off", ".glb")


def discover(inputs: list[str | Path], prefer_cad: bool = True) -> list[Path]:
    """Part files under ``inputs`` (files or folders, recursively), sorted.

    With ``prefer_cad`` a mesh file whose stem also exists as a STEP/IGES file in
    the same folder is skipped, so a part exported both ways is meshed once.
    """
    found: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found += [p for p in sorted(item.rglob("*")) if p.suffix.lower() in PART_SUFFIXES and p.is_file()]
        else:
            found.append(item)
    if prefer_cad:
        cad = {(p.parent, p.stem) for p in found if p.suffix.lower() in (".step", ".stp", ".iges", ".igs")}
        found = [p for p in found if p.suffix.lower() in (".step", ".stp", ".iges", ".igs") or (p.parent, p.stem) not in cad]
    return sorted(dict.fromkeys(found))


def plot_sample(points: np.ndarray, normals: np.ndarray, path: Path, title: str) -> Path:
    """Scatter ``points (N, 3)`` coloured by their dominant normal axis (red x, green y, blue z)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = np.abs(normals)
    fig = plt.figure(figsize=(5, 5), dpi=110)
    ax = fig.add_subplot(projection="3d")
    ax.scatter(points[:, 0], points[:, 1], points[:, 2], c=np.clip(colours, 0, 1), s=1.5, depthshade=True)
    ax.set_box_aspect(np.ptp(points, axis=0) + 1e-9)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, bbox_inches="tight", format="png")
    plt.close(fig)
    return path


def run_part(path: Path, out: Path, n_points: int, seed: int) -> dict:
    """All existing stages for one part; returns its manifest row (never raises PartError)."""
    from .io import load_part
    from .sampling import poisson_disk

    row: dict = {"part": path.name, "path": str(path), "status": "failed", "stage": "load", "error": None, "timings": {}}
    part_dir = out / path.stem
    try:
        t0 = time.perf_counter()
        part = load_part(path)
        row["timings"]["load"] = time.perf_counter() - t0
        row.update(genus=part.meta.get("genus"), faces=int(len(part.faces)), repairs=part.meta.get("repairs", []))

        row["stage"] = "frame"
        t0 = time.perf_counter()
        Vc, transform = canonicalize(part.vertices, part.faces)
        part.vertices = Vc
        row["timings"]["frame"] = time.perf_counter() - t0

        row["stage"] = "sample"
        t0 = time.perf_counter()
        sample = poisson_disk(Vc, part.faces, n_points, seed=seed)
        row["timings"]["sample"] = time.perf_counter() - t0

        row["stage"] = "write"
        part.save(part_dir / "part.npz")
        write_json(part_dir / "transform.json", transform.to_dict())
        sample.save(part_dir / "sample.npz")
        plot_sample(sample.points, sample.normals, part_dir / "sample.png", f"{path.name}: genus {row['genus']}, {n_points} points")
        row["status"] = "sampled"
        row["stage"] = "sample"
    except PartError as exc:
        row["error"] = f"{type(exc).__name__}: {exc}"
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polycubenet.demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("inputs", nargs="+", help="part files or folders")
    ap.add_argument("-o", "--out", required=True, type=Path)
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synthetic", type=int, default=0, help="also mesh this many synthetic parts end to end")
    args = ap.parse_args(argv)

    from tqdm import tqdm

    parts = discover(args.inputs)
    if not parts:
        print(f"no parts found under {args.inputs}", file=sys.stderr)
        return 2
    rows = []
    bar = tqdm(parts, unit="part", file=sys.stderr)
    for p in bar:
        bar.set_postfix_str(p.name)
        rows.append(run_part(p, args.out, args.points, args.seed))
        bar.set_description(f"ok {sum(r['status'] != 'failed' for r in rows)} failed {sum(r['status'] == 'failed' for r in rows)}")
    print(f"\n{'part':<28}{'status':<9}{'genus':>6}{'faces':>8}{'load s':>8}{'sample s':>10}  error")
    for r in rows:
        t = r["timings"]
        print(
            f"{r['part']:<28}{r['status']:<9}{str(r.get('genus', '')):>6}{str(r.get('faces', '')):>8}"
            f"{t.get('load', float('nan')):>8.2f}{t.get('sample', float('nan')):>10.2f}  {r['error'] or ''}"
        )
    if args.synthetic:
        rows += run_synthetic(args.out / "synthetic", args.synthetic, args.seed)
    write_json(args.out / "manifest.json", {"parts": rows})
    print(f"\nmanifest: {args.out / 'manifest.json'}")
    return 0


def run_synthetic(out: Path, count: int, seed: int) -> list[dict]:
    """Mesh ``count`` synthetic parts end to end with the oracle polycube; print a table."""
    from .errors import PolycubeError
    from .io import write_surface
    from .pipeline import OracleSource, PipelineConfig, mesh_surface
    from .synth import make_pair

    rows = []
    print(f"\nsynthetic parts meshed end to end (oracle polycube, noise 0.5%, 2% outliers) -> {out}")
    print(f"{'part':<14}{'genus':>6}{'hexes':>7}{'SJ min':>8}{'SJ avg':>8}{'Haus %':>8}{'time s':>8}  status")
    for i in range(count):
        pair_seed = 7000 + seed * 100 + i
        pair = make_pair(pair_seed, n_cond=64, n_target=64)
        name = f"synth-{pair_seed}"
        t0 = time.perf_counter()
        try:
            res = mesh_surface(pair.shape_vertices, pair.faces, OracleSource(pair.polycube), PipelineConfig(seed=seed),
                               name=name, part_meta={"genus": pair.genus}, canonical=True)
        except (PartError, PolycubeError) as exc:
            rows.append({"part": name, "status": "failed", "stage": getattr(exc, "stage", None), "error": str(exc), "timings": {}})
            print(f"{name:<14}{pair.genus:>6}  failed at {getattr(exc, 'stage', '?')}: {exc}")
            continue
        d = out / name
        res.write(d, formats=("vtu", "inp"))
        write_surface(pair.shape_vertices, pair.faces, d / "part.stl")
        row = res.row()
        rows.append(row)
        print(f"{name:<14}{pair.genus:>6}{row['hexes']:>7}{row['sj_min']:>8.3f}{row['sj_avg']:>8.3f}"
              f"{100 * row['hausdorff']:>8.2f}{time.perf_counter() - t0:>8.1f}  {'valid' if row['valid'] else 'INVALID (flagged)'}")
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
