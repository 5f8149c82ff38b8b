"""A picture of synthetic pairs: each shape beside its polycube (matplotlib, headless).

``python -m polycubenet.synth.preview --out docs/synth_pairs.png --count 6 --seed 0``
draws pairs ``0 .. count-1`` of the dataset with that seed (the same geometry
``python -m polycubenet.synth --seed S`` writes).  Rendering uses the Agg canvas and
``Poly3DCollection`` with flat Lambert shading, so it needs no display and no GPU.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from .pairs import SynthPair, make_pair
from .shards import pair_seed

_LIGHT = np.array([0.35, -0.55, 0.76])
_SHAPE_RGB = np.array([0.36, 0.55, 0.78])
_POLY_RGB = np.array([0.93, 0.62, 0.30])


def _shade(V: np.ndarray, F: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    lam = np.clip(n @ (_LIGHT / np.linalg.norm(_LIGHT)), 0.0, 1.0)
    c = rgb[None, :] * (0.35 + 0.65 * lam[:, None])
    return np.clip(np.column_stack([c, np.ones(len(F))]), 0.0, 1.0)


def _draw(ax, V: np.ndarray, F: np.ndarray, rgb: np.ndarray, title: str, lo: np.ndarray, hi: np.ndarray) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    colors = _shade(V, F, rgb)
    # edges painted in the face colour hide the hairline seams between triangles
    coll = Poly3DCollection(V[F], facecolors=colors, edgecolors=colors, linewidths=0.2)
    ax.add_collection3d(coll)
    mid, half = 0.5 * (lo + hi), 0.5 * np.max(hi - lo)
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
    ax.set_zlim(mid[2] - half, mid[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=28, azim=-58)
    ax.set_axis_off()
    ax.set_title(title, fontsize=8)


def render_pairs(pairs: list[SynthPair], path: str | Path, *, columns: int = 2, dpi: int = 110) -> Path:
    """Draw ``pairs`` (shape | polycube, ``columns`` pairs per row) to a PNG, atomically.

    Parameters
    ----------
    pairs : list of SynthPair
    path : str or Path, ``.png``
    columns : int, pairs per row
    dpi : int

    Returns
    -------
    Path
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not pairs:
        raise ValueError("nothing to draw")
    rows = (len(pairs) + columns - 1) // columns
    fig = Figure(figsize=(5.0 * columns, 2.8 * rows))
    FigureCanvasAgg(fig)
    for i, p in enumerate(pairs):
        Vs, F = p.shape_vertices, p.faces
        # the refined polycube mesh: small triangles keep matplotlib's depth sorting right
        Vp, Fp = p.polycube_vertices, p.faces
        lo = np.minimum(Vs.min(0), Vp.min(0))
        hi = np.maximum(Vs.max(0), Vp.max(0))
        r, c = divmod(i, columns)
        kinds = sorted(set(p.deformation.kinds) - {"round_hole", "round_edge"})
        extra = []
        if "round_hole" in p.deformation.kinds:
            extra.append("holes")
        if "round_edge" in p.deformation.kinds:
            extra.append("edges")
        ax = fig.add_subplot(rows, 2 * columns, r * 2 * columns + 2 * c + 1, projection="3d")
        _draw(ax, Vs, F, _SHAPE_RGB, f"#{i} {p.meta['style']}: " + ", ".join(extra + kinds), lo, hi)
        ax = fig.add_subplot(rows, 2 * columns, r * 2 * columns + 2 * c + 2, projection="3d")
        _draw(ax, Vp, Fp, _POLY_RGB, f"polycube, genus {p.genus}", lo, hi)
    fig.subplots_adjust(left=0.0, right=1.0, bottom=0.0, top=0.95, wspace=0.0, hspace=0.12)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    return path


def preview(out: str | Path, count: int = 6, seed: int = 0, columns: int = 2, *, cad_features: bool = False,
            whole_slants: bool = False, max_strength: float | None = None, full_slants: float = 0.0,
            cut_slants: bool = False) -> Path:
    """Render pairs ``0 .. count-1`` of the dataset ``seed`` (made with ``cad_features`` /
    ``whole_slants`` / ``max_strength`` / ``full_slants`` / ``cut_slants``, as ``python -m polycubenet.synth``
    makes them) to ``out``."""
    pairs = [make_pair(pair_seed(seed, i), n_cond=16, n_target=16, sampler="uniform", cad_features=cad_features,
                       whole_slants=whole_slants, max_strength=max_strength, full_slants=full_slants,
                       cut_slants=cut_slants)
             for i in range(count)]
    return render_pairs(pairs, out, columns=columns)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polycubenet.synth.preview", description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="docs/synth_pairs.png", help="PNG to write")
    ap.add_argument("--count", type=int, default=6, help="number of pairs")
    ap.add_argument("--seed", type=int, default=0, help="dataset seed")
    ap.add_argument("--columns", type=int, default=2, help="pairs per row")
    ap.add_argument("--cad-features", action="store_true", help="the pairs of a set made with --cad-features")
    ap.add_argument("--whole-slants", action="store_true", help="the pairs of a set made with --whole-slants")
    ap.add_argument("--max-strength", type=float, default=None, help="the pairs of a set made with --max-strength")
    ap.add_argument("--full-slants", type=float, default=0.0, help="the pairs of a set made with --full-slants")
    ap.add_argument("--cut-slants", action="store_true", help="the pairs of a set made with --cut-slants")
    args = ap.parse_args(argv)
    path = preview(args.out, args.count, args.seed, args.columns, cad_features=args.cad_features,
                   whole_slants=args.whole_slants, max_strength=args.max_strength, full_slants=args.full_slants,
                   cut_slants=args.cut_slants)
    print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
