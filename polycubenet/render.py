"""Off-screen pictures of hex meshes and their quality (PNG, written atomically).

Three pictures:

* :func:`plot_sj_histogram` -- the scaled-Jacobian histogram of a
  :class:`~polycubenet.quality.QualityReport` (matplotlib, no pyplot, Agg canvas).
* :func:`render_hex_quality` -- the mesh coloured by per-hex scaled Jacobian, next
  to a cut-away (the hexes on one side of a mid plane, whole cells kept) that shows
  the interior.  Backends, tried in order with ``backend="auto"``:

  1. ``"pyvista"``: VTK off-screen (``off_screen=True``); on a machine without a
     display VTK renders through EGL (we set ``VTK_DEFAULT_OPENGL_WINDOW`` to
     ``vtkEGLRenderWindow`` unless it is already set) or OSMesa.
  2. ``"matplotlib"``: the boundary quads as a ``Poly3DCollection`` (slower,
     no lighting, always available).

  A pyvista failure (an exception or a blank image) falls back to matplotlib.
  The environment variable ``POLYCUBENET_RENDER_BACKEND`` overrides ``"auto"``.

  One VTK render at a time per process (``_VTK_LOCK``): two threads rendering off-screen
  at once through Mesa corrupt the C heap (``munmap_chunk(): invalid pointer``, or a
  segmentation fault then or only later, when the interpreter frees memory at exit).  That
  was the intermittent exit-time crash of the test suite, whose flows export two parts at
  once in a thread pool.  pyvista's lazy imports are not thread-safe either, so they are
  made under the same lock.

* :func:`plot_deviation` -- where a mesh off its part leaves it: the part's samples the mesh does not
  reach and the mesh's samples beyond the part, by distance, with the report's spots numbered.

Colours: SJ in [0, 1] on a colour map; SJ < 0 (inverted) is drawn red.
"""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .hexmesh import boundary_quads

log = logging.getLogger(__name__)

#: colour map of the scaled Jacobian in [0, 1]; values below 0 use _BELOW
_CMAP = "viridis"
_BELOW = "red"
#: VTK off-screen rendering (and pyvista's lazy imports) is not thread-safe: one render at a time
_VTK_LOCK = threading.Lock()


def _figure(figsize):
    from matplotlib.figure import Figure  # no pyplot: no global backend state

    return Figure(figsize=figsize, dpi=100)


def plot_sj_histogram(report, path: str | Path) -> Path:
    """Write the scaled-Jacobian histogram of ``report`` to ``path`` (PNG, atomic).

    Bars over [-1, 1] (log count axis, so a handful of bad hexes stays visible),
    vertical lines at min, 1st percentile and mean, and the report's warnings.

    Parameters
    ----------
    report : QualityReport
    path : path

    Returns
    -------
    Path
    """
    path = Path(path)
    edges = np.asarray(report.hist_edges, dtype=float)
    counts = np.asarray(report.hist_counts, dtype=float)
    fig = _figure((7.0, 4.2))
    ax = fig.add_subplot(1, 1, 1)
    centres = 0.5 * (edges[:-1] + edges[1:])
    colours = ["tab:red" if c < 0 else "tab:blue" for c in centres]
    ax.bar(centres, counts, width=np.diff(edges) * 0.95, color=colours, edgecolor="black", linewidth=0.3)
    if counts.any():
        ax.set_yscale("log")
        ax.set_ylim(0.5, counts.max() * 2.5)
    ax.set_xlim(-1.0, 1.0)
    ax.set_xlabel("scaled Jacobian (per hex)")
    ax.set_ylabel("hexes")
    if report.hex_count:
        for value, name, colour, ls in (
            (report.sj_min, "min", "tab:red", "-"),
            (report.sj_p01, "p01", "tab:orange", "--"),
            (report.sj_avg, "avg", "tab:green", "-."),
        ):
            ax.axvline(value, color=colour, linestyle=ls, linewidth=1.5, label=f"{name} = {value:.4f}")
        ax.legend(loc="upper left", fontsize=9)
    status = "VALID" if report.valid else "INVALID"
    ax.set_title(
        f"{status}: {report.hex_count} hexes, {report.inverted_count} inverted, "
        f"{report.degenerate_count} degenerate",
        color="black" if report.valid else "tab:red",
        fontsize=10,
    )
    if report.warnings:
        fig.text(0.01, 0.01, "\n".join(report.warnings)[:400], fontsize=7, color="tab:red", va="bottom", wrap=True)
        fig.subplots_adjust(bottom=0.12 + 0.04 * len(report.warnings))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def _cut_plane(points: np.ndarray, hexes: np.ndarray):
    """The cut-away plane: through the centre, normal along the longest bbox axis."""
    used = points[np.unique(hexes)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    axis = int(np.argmax(hi - lo))
    return axis, 0.5 * (lo + hi)


def _cut_mask(points, hexes, axis, centre) -> np.ndarray:
    """Hexes whose centroid is below the mid plane along ``axis`` (kept in the cut-away)."""
    c = points[hexes].mean(axis=1)
    keep = c[:, axis] <= centre[axis]
    if not keep.any():  # a single layer: keep everything
        keep[:] = True
    return keep


def _render_pyvista(points, hexes, sj, path: Path, title: str | None, window_size) -> None:
    with _VTK_LOCK:
        _render_pyvista_locked(points, hexes, sj, path, title, window_size)


def _render_pyvista_locked(points, hexes, sj, path: Path, title: str | None, window_size) -> None:
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    cells = np.hstack([np.full((len(hexes), 1), 8, dtype=np.int64), hexes]).ravel()
    grid = pv.UnstructuredGrid(cells, np.full(len(hexes), pv.CellType.HEXAHEDRON, dtype=np.uint8), points)
    grid.cell_data["SJ"] = sj
    axis, centre = _cut_plane(points, hexes)
    cut = grid.extract_cells(np.flatnonzero(_cut_mask(points, hexes, axis, centre)))

    kw = dict(
        scalars="SJ",
        cmap=_CMAP,
        clim=(0.0, 1.0),
        below_color=_BELOW,
        show_edges=True,
        edge_color="black",
        line_width=0.5,
        preference="cell",
    )
    view = np.array([1.0, 1.0, 1.0])  # look from +x+y+z; the cut face (normal +axis) faces it
    pl = pv.Plotter(off_screen=True, shape=(1, 2), window_size=window_size, border=False)
    try:
        pl.subplot(0, 0)
        pl.add_mesh(
            grid,
            scalar_bar_args=dict(
                title="scaled Jacobian (red: < 0)",
                vertical=False,
                position_x=0.2,
                position_y=0.03,
                width=0.6,
                height=0.07,
                n_labels=6,
                fmt="%.1f",
                below_label="",
                title_font_size=14,
                label_font_size=12,
            ),
            **kw,
        )
        pl.add_text("boundary", font_size=10)
        pl.camera_position = "iso"
        pl.camera.azimuth = 0.0
        pl.reset_camera()
        pl.camera.zoom(0.9)
        pl.subplot(0, 1)
        pl.add_mesh(cut, show_scalar_bar=False, **kw)
        pl.add_text(f"cut-away ({'xyz'[axis]} < mid)", font_size=10)
        pl.camera.position = tuple(centre + view)
        pl.camera.focal_point = tuple(centre)
        pl.camera.up = (0.0, 0.0, 1.0) if axis != 2 else (0.0, 1.0, 0.0)
        pl.reset_camera()
        pl.camera.zoom(0.9)
        if title:  # right panel, lower left, wrapped at commas
            pl.add_text(title.replace(", ", "\n"), position="lower_left", font_size=8)
        with atomic_path(path) as tmp:
            img = pl.screenshot(str(tmp), return_img=True)
            if img is None or np.ptp(np.asarray(img)) == 0:
                raise RuntimeError("pyvista rendered a blank image")
    finally:
        pl.close()


def _render_matplotlib(points, hexes, sj, path: Path, title: str | None, window_size) -> None:
    import matplotlib as mpl
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    cmap = mpl.colormaps[_CMAP].with_extremes(under=_BELOW)
    norm = mpl.colors.Normalize(0.0, 1.0)
    axis, centre = _cut_plane(points, hexes)
    keep = _cut_mask(points, hexes, axis, centre)
    fig = _figure((window_size[0] / 100, window_size[1] / 100))
    used = points[np.unique(hexes)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    half = 0.5 * (hi - lo).max()
    for k, (sub, name) in enumerate(((np.arange(len(hexes)), "boundary"), (np.flatnonzero(keep), "cut-away"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        quads, owner = boundary_quads(hexes[sub], return_hex=True)
        colours = cmap(norm(sj[sub][owner]))
        ax.add_collection3d(
            Poly3DCollection(points[quads], facecolors=colours, edgecolors="black", linewidths=0.1)
        )
        mid = 0.5 * (lo + hi)
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.view_init(elev=30, azim=45)
        ax.set_box_aspect((1, 1, 1), zoom=1.3)
        ax.set_axis_off()
        ax.set_title(name if k == 0 else f"cut-away ({'xyz'[axis]} < mid)", fontsize=9)
    sm = mpl.cm.ScalarMappable(norm=norm, cmap=cmap)
    fig.colorbar(sm, ax=fig.axes, orientation="horizontal", fraction=0.05, pad=0.02, label="scaled Jacobian",
                 extend="min")
    if title:
        fig.suptitle(title, fontsize=8)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def render_hex_quality(
    points,
    hexes,
    sj,
    path: str | Path,
    *,
    title: str | None = None,
    backend: str = "auto",
    window_size: tuple[int, int] = (1400, 700),
) -> str:
    """Render the hex mesh coloured by per-hex scaled Jacobian, with a cut-away, to a PNG.

    Parameters
    ----------
    points : (P, 3) float
    hexes : (H, 8) int
        VTK hexahedron connectivity, ``H >= 1``.
    sj : (H,) float
        Per-hex scaled Jacobian (colour; < 0 drawn red).
    path : path
        PNG written atomically.
    title : str, optional
        Caption drawn on the picture.
    backend : {"auto", "pyvista", "matplotlib"}
        ``"auto"`` tries pyvista and falls back to matplotlib.
    window_size : (int, int)
        Picture size in pixels.

    Returns
    -------
    str
        The backend that produced the picture: ``"pyvista"`` or ``"matplotlib"``.
    """
    points = np.asarray(points, dtype=np.float64)
    hexes = np.asarray(hexes, dtype=np.int64)
    sj = np.asarray(sj, dtype=np.float64)
    if len(hexes) == 0:
        raise ValueError("nothing to render: no hexes")
    path = Path(path)
    if backend == "auto":
        backend = os.environ.get("POLYCUBENET_RENDER_BACKEND", "auto")
    if backend in ("auto", "pyvista"):
        try:
            _render_pyvista(points, hexes, sj, path, title, window_size)
            return "pyvista"
        except Exception as exc:  # noqa: BLE001 - any VTK/EGL failure -> fallback
            if backend == "pyvista":
                raise
            log.warning("pyvista off-screen rendering failed (%s); falling back to matplotlib", exc)
    if backend not in ("auto", "matplotlib"):
        raise ValueError(f"unknown render backend {backend!r}")
    _render_matplotlib(points, hexes, sj, path, title, window_size)
    return "matplotlib"


def _deep(name: str):
    """Colour map ``name`` without its palest third (a spot just over the bar stays visible on grey)."""
    import matplotlib as mpl

    return mpl.colors.ListedColormap(mpl.colormaps[name](np.linspace(0.35, 1.0, 256)))


def plot_deviation(part_surface, mesh, far: dict, spots: list[dict], path: str | Path, *, diagonal: float,
                   bar: float | None = None, samples: int = 12_000) -> Path:
    """Where a hex mesh leaves its part, as a PNG (matplotlib, atomic): three views of the part (grey
    samples of its surface), the part's samples the hex boundary does not reach (reds) and the hex
    boundary's samples beyond the part (blues), coloured by distance, each spot numbered as the report
    lists it (:func:`polycubenet.quality.off_part_spots`).

    Parameters
    ----------
    part_surface : ((V, 3) float, (F, 3) int), the input surface
    mesh : HexMesh, drawn as its boundary quads' wire in the views
    far : dict, ``"part"`` / ``"mesh"`` -> (points ``(k, 3)``, distances ``(k,)`` relative to ``diagonal``)
    spots : list of dict, ``centre``, ``max``, ``side``
    path : path
    diagonal : float, the part's bounding-box diagonal
    bar : float, the Hausdorff bar (relative; default :data:`polycubenet.tol.HAUSDORFF_REL_MAX`)
    samples : int, grey samples of the part

    Returns
    -------
    Path
    """
    import matplotlib as mpl
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    from . import tol
    from .quality import _sample_triangles

    bar = tol.HAUSDORFF_REL_MAX if bar is None else bar
    path = Path(path)
    V, F = np.asarray(part_surface[0], float), np.asarray(part_surface[1])
    grey = _sample_triangles(V, F, samples, np.random.default_rng(0))
    parts = {k: (np.asarray(p, float).reshape(-1, 3), 100 * np.asarray(d, float)) for k, (p, d) in far.items()}
    top = max([d.max() for _, d in parts.values() if len(d)] + [100 * bar * 1.01])
    norm = mpl.colors.Normalize(100 * bar, top)
    quads = boundary_quads(np.asarray(mesh.hexes))
    edges = np.unique(np.sort(np.concatenate([quads[:, [0, 1]], quads[:, [1, 2]], quads[:, [2, 3]],
                                              quads[:, [3, 0]]]), axis=1), axis=0)
    X = np.asarray(mesh.points, float)
    lo, hi = V.min(axis=0), V.max(axis=0)
    mid, half = 0.5 * (lo + hi), 0.55 * (hi - lo).max()
    fig = _figure((15.0, 5.6))
    views = ((25, 35), (25, 215), (-35, 125))
    for k, (elev, azim) in enumerate(views):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        ax.scatter(*grey.T, s=0.3, c="0.75", alpha=0.35, depthshade=False)
        ax.add_collection3d(Line3DCollection(X[edges], colors="0.3", linewidths=0.2, alpha=0.3))
        for key, cmap in (("part", "Reds"), ("mesh", "Blues")):
            pts, d = parts.get(key, (np.zeros((0, 3)), np.zeros(0)))
            if len(pts):
                ax.scatter(*pts.T, s=6, c=d, cmap=_deep(cmap), norm=norm, depthshade=False)
        for i, sp in enumerate(spots):
            ax.text(*sp["centre"], f" {i + 1}", fontsize=10, color="black", weight="bold")
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect((1, 1, 1), zoom=1.45)
        ax.set_axis_off()
    fig.subplots_adjust(left=0.0, right=1.0, top=0.92, bottom=0.16, wspace=0.0)
    for x0, (key, cmap, label) in zip((0.08, 0.55), (("part", "Reds", "the part not reached, % of the diagonal"),
                                                     ("mesh", "Blues", "the mesh beyond the part, % of the diagonal"))):
        if len(parts.get(key, ((), ()))[1]):
            cax = fig.add_axes((x0, 0.1, 0.37, 0.03))
            fig.colorbar(mpl.cm.ScalarMappable(norm=norm, cmap=_deep(cmap)), cax=cax,
                         orientation="horizontal", label=label)
    said = "; ".join(f"{i + 1}: {100 * sp['max']:.2f}% ({sp['side']})" for i, sp in enumerate(spots))
    fig.suptitle(f"Where the mesh leaves the part (bar {100 * bar:g}% of the diagonal {diagonal:.4g}). {said}",
                 fontsize=9)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


__all__ = ["plot_sj_histogram", "render_hex_quality", "plot_deviation"]
