"""Check our scaled Jacobian against the published HexGen reference meshes (and VTK itself).

For each ``<model>_reference_hex.vtu`` in the hexgen folder: read it (meshio), compute
min and average scaled Jacobian with :func:`polycubenet.quality.scaled_jacobian` and
with VTK (pyvista ``cell_quality``), compare with ``reference.json`` (``ref_min_sj``,
``ref_avg_sj``, ``ref_hexes``), print a table, write
``benchmarks/results/hexgen_quality.json`` and a full quality report (quality.json,
quality.png, preview.png) of each reference mesh against its ``.obj`` surface under
``benchmarks/results/hexgen_reference/<model>/``.

The tolerance is half a unit of the reference's last decimal: the reference values
carry at most 4 decimals -> 5e-5 (inferred from the file, so a 3-decimal file gives
5e-4).  Exits 1 when a value differs by more, when a hex count differs, or when our
value differs from VTK's by more than 1e-9.

    python benchmarks/check_hexgen_quality.py [HEXGEN_DIR] [--no-reports]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import meshio
import numpy as np
import trimesh

from polycubenet.atomic import write_json
from polycubenet.data import HexMesh
from polycubenet.quality import quality_report, scaled_jacobian_and_degenerate, vtk_scaled_jacobian

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DIR = ROOT / ".." / "shared" / "benchmark" / "hexgen"
VTK_ATOL = 1e-9


def _decimals(x: float) -> int:
    s = repr(float(x))
    return len(s.split(".")[1]) if "." in s and "e" not in s else 0


def read_hex_vtu(path: Path) -> HexMesh:
    """Hexahedra of a .vtu (meshio), all hexahedron blocks stacked."""
    m = meshio.read(path)
    blocks = [c.data for c in m.cells if c.type == "hexahedron"]
    if not blocks:
        raise ValueError(f"{path}: no hexahedron cells")
    return HexMesh(np.asarray(m.points, dtype=np.float64)[:, :3], np.vstack(blocks).astype(np.int64))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("hexgen_dir", nargs="?", type=Path, default=DEFAULT_DIR)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "hexgen_quality.json")
    ap.add_argument("--reports", type=Path, default=ROOT / "benchmarks" / "results" / "hexgen_reference")
    ap.add_argument("--no-reports", action="store_true", help="skip the per-model quality reports and pictures")
    ap.add_argument("--samples", type=int, default=200_000, help="surface samples per side for Hausdorff")
    args = ap.parse_args(argv)

    hexgen = args.hexgen_dir.resolve()
    ref = json.loads((hexgen / "reference.json").read_text())
    tol_min = 0.5 * 10.0 ** -max(_decimals(r["ref_min_sj"]) for r in ref.values())
    tol_avg = 0.5 * 10.0 ** -max(_decimals(r["ref_avg_sj"]) for r in ref.values())
    files = sorted(hexgen.glob("*_reference_hex.vtu"))
    if not files:
        print(f"no *_reference_hex.vtu in {hexgen}", file=sys.stderr)
        return 2

    rows, failures = [], []
    hdr = (
        f"{'model':<10} {'hexes':>6} {'ref min':>8} {'ours min':>9} {'vtk min':>9} {'ref avg':>8} {'ours avg':>9} "
        f"{'vtk avg':>9} {'|d min|':>8} {'|d avg|':>8} {'|ours-vtk|':>10} {'Hausd.%':>8} {'ok':>3}"
    )
    print(hdr)
    print("-" * len(hdr))
    for f in files:
        model = f.name[: -len("_reference_hex.vtu")]
        r = ref.get(model)
        if r is None:
            print(f"{model}: not in reference.json, skipped", file=sys.stderr)
            continue
        t0 = time.perf_counter()
        mesh = read_hex_vtu(f)
        sj, deg = scaled_jacobian_and_degenerate(mesh.points, mesh.hexes)
        t_sj = time.perf_counter() - t0
        vtk = vtk_scaled_jacobian(mesh.points, mesh.hexes)
        ours_min, ours_avg = float(sj.min()), float(sj.mean())
        vtk_min, vtk_avg = float(vtk.min()), float(vtk.mean())
        d_min, d_avg = abs(ours_min - r["ref_min_sj"]), abs(ours_avg - r["ref_avg_sj"])
        d_vtk = float(np.abs(sj - vtk).max()) if not deg.any() else float(np.abs(sj - vtk)[~deg].max())
        ok = (
            d_min <= tol_min + 1e-12
            and d_avg <= tol_avg + 1e-12
            and len(mesh.hexes) == r["ref_hexes"]
            and d_vtk <= VTK_ATOL
        )
        row = dict(
            model=model,
            hexes=int(len(mesh.hexes)),
            ref_hexes=int(r["ref_hexes"]),
            ref_min_sj=r["ref_min_sj"],
            ours_min_sj=ours_min,
            vtk_min_sj=vtk_min,
            ref_avg_sj=r["ref_avg_sj"],
            ours_avg_sj=ours_avg,
            vtk_avg_sj=vtk_avg,
            abs_diff_min=d_min,
            abs_diff_avg=d_avg,
            max_abs_diff_vs_vtk=d_vtk,
            degenerate=int(deg.sum()),
            sj_seconds=t_sj,
            ok=bool(ok),
        )
        if not args.no_reports:
            s = trimesh.load(hexgen / f"{model}.obj", force="mesh", process=False)
            rep = quality_report(mesh, (np.asarray(s.vertices), np.asarray(s.faces)), n_samples=args.samples)
            rep.write(args.reports / model)
            row.update(
                hausdorff_rel=rep.surface["hausdorff"],
                mean_dist_rel=rep.surface["mean"],
                valid=rep.valid,
                report=str((args.reports / model).relative_to(ROOT)) if args.reports.is_relative_to(ROOT) else str(args.reports / model),
            )
        rows.append(row)
        if not ok:
            failures.append(model)
        hd = f"{100 * row['hausdorff_rel']:>8.3f}" if "hausdorff_rel" in row else f"{'-':>8}"
        print(
            f"{model:<10} {row['hexes']:>6} {r['ref_min_sj']:>8.4f} {ours_min:>9.5f} {vtk_min:>9.5f} "
            f"{r['ref_avg_sj']:>8.4f} {ours_avg:>9.5f} {vtk_avg:>9.5f} {d_min:>8.1e} {d_avg:>8.1e} {d_vtk:>10.1e} "
            f"{hd} {'yes' if ok else 'NO':>3}"
        )

    summary = dict(
        hexgen_dir=str(hexgen),
        tolerance_min=tol_min,
        tolerance_avg=tol_avg,
        vtk_atol=VTK_ATOL,
        all_ok=not failures,
        failures=failures,
        rows=rows,
    )
    write_json(args.out, summary)
    print(f"tolerance vs reference: min {tol_min:g}, avg {tol_avg:g}; vs VTK {VTK_ATOL:g}")
    print(f"wrote {args.out}")
    if failures:
        print(f"MISMATCH: {', '.join(failures)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
