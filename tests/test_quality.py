"""Scaled Jacobian (against VTK), degenerate elements, boundary topology and the quality report."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from polycubenet import tol
from polycubenet.data import HexMesh
from polycubenet.hexmesh import (
    boundary_quads,
    boundary_vertex_mask,
    enclosed_volume,
    hex_volumes,
    quads_to_triangles,
)
from polycubenet.quality import (
    degenerate_mask,
    far_spots,
    quality_report,
    scaled_jacobian,
    scaled_jacobian_and_degenerate,
    thin_features,
    vtk_scaled_jacobian,
)

UNIT = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64
)
ONE = np.arange(8)[None, :]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def structured(n: int, size: float = 1.0) -> HexMesh:
    """An n x n x n block of cubes filling [0, size]^3, in VTK order."""
    g = np.linspace(0.0, size, n + 1)
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)

    def idx(i, j, k):
        return (i * (n + 1) + j) * (n + 1) + k

    i, j, k = (a.ravel() for a in np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij"))
    hexes = np.stack(
        [
            idx(i, j, k), idx(i + 1, j, k), idx(i + 1, j + 1, k), idx(i, j + 1, k),
            idx(i, j, k + 1), idx(i + 1, j, k + 1), idx(i + 1, j + 1, k + 1), idx(i, j + 1, k + 1),
        ],
        axis=1,
    )  # fmt: skip
    return HexMesh(pts, hexes)


def cube_surface(lo=0.0, hi=1.0):
    import trimesh

    m = trimesh.creation.box(bounds=[[lo] * 3, [hi] * 3])
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


# --------------------------------------------------------------------------- scaled Jacobian


def test_matches_vtk_on_random_distorted_hexes():
    rng = np.random.default_rng(12345)
    n = 3000
    # perturbations of the unit cube, from mild to wild (many inverted), plus random scale/offset
    sigma = rng.choice([0.05, 0.2, 0.45], size=n)[:, None, None]
    X = UNIT[None] + rng.normal(size=(n, 8, 3)) * sigma
    X = X * rng.uniform(0.01, 100.0, size=(n, 1, 1)) + rng.normal(size=(n, 1, 3)) * 10
    pts = X.reshape(-1, 3)
    hexes = np.arange(8 * n).reshape(n, 8)
    ours, deg = scaled_jacobian_and_degenerate(pts, hexes)
    ref = vtk_scaled_jacobian(pts, hexes)
    assert not deg.any()
    assert (ours < 0).sum() > 100, "the sample must contain inverted hexes"
    assert (ours > 0.5).sum() > 100
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-9)
    assert np.all(np.abs(ours) <= 1.0 + 1e-12)


def test_unit_cube_and_rigid_box_are_one():
    assert scaled_jacobian(UNIT, ONE)[0] == pytest.approx(1.0, abs=1e-15)
    # a rotated, translated, anisotropic box is still 1
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    box = (UNIT * [3.0, 0.1, 7.0]) @ R.T + [5, -2, 1]
    assert scaled_jacobian(box, ONE)[0] == pytest.approx(1.0, abs=1e-14)


@pytest.mark.parametrize("shear", [0.25, 1.0, 3.0])
def test_sheared_hex_analytic(shear):
    # top face shifted by `shear` in x: a parallelepiped; every corner frame has det 1 and
    # lengths 1, 1, sqrt(1 + shear^2)
    X = UNIT.copy()
    X[4:, 0] += shear
    expected = 1.0 / np.sqrt(1.0 + shear**2)
    assert scaled_jacobian(X, ONE)[0] == pytest.approx(expected, abs=1e-14)
    assert vtk_scaled_jacobian(X, ONE)[0] == pytest.approx(expected, abs=1e-14)


def test_inverted_hexes_are_negative():
    mirrored = UNIT[[4, 5, 6, 7, 0, 1, 2, 3]]  # top and bottom swapped: inside out
    assert scaled_jacobian(mirrored, ONE)[0] == pytest.approx(-1.0)
    tangled = UNIT.copy()
    tangled[6] = [0.2, 0.2, 0.2]  # corner 6 pushed through the opposite corner
    sj = scaled_jacobian(tangled, ONE)[0]
    assert sj < 0
    assert sj == pytest.approx(vtk_scaled_jacobian(tangled, ONE)[0], abs=1e-12)
    r = quality_report(HexMesh(tangled, ONE))
    assert (r.inverted_count, r.degenerate_count, r.valid) == (1, 0, False)
    assert any("inverted" in w for w in r.warnings)


def test_collapsed_edge_is_finite_and_degenerate():
    X = UNIT.copy()
    X[1] = X[0]  # edge 0-1 collapsed to a point
    assert vtk_scaled_jacobian(X, ONE)[0] > 1e29  # VTK's sentinel, for the record
    sj, deg = scaled_jacobian_and_degenerate(X, ONE)
    assert np.isfinite(sj[0]) and sj[0] == 0.0
    assert deg[0]
    # a nearly collapsed edge (below EDGE_COLLAPSE_REL x mean edge) counts too
    Y = UNIT.copy()
    Y[1] = Y[0] + [0.1 * tol.EDGE_COLLAPSE_REL, 0, 0]
    assert degenerate_mask(Y, ONE)[0]
    assert np.isfinite(scaled_jacobian(Y, ONE)[0])
    # in a mesh: one good hex, one collapsed
    pts = np.vstack([UNIT + [2, 0, 0], X])
    r = quality_report(HexMesh(pts, np.array([np.arange(8), np.arange(8, 16)])))
    assert r.degenerate_count == 1 and r.inverted_count == 0
    assert r.valid is False
    assert r.sj_min == 0.0
    assert any("degenerate" in w for w in r.warnings)
    json.dumps(r.to_dict(), allow_nan=False)


def test_flat_hex_is_degenerate():
    X = UNIT.copy()
    X[4:, 2] = 0.0  # the whole hex squashed into a plane: edges vertical to it collapse
    sj, deg = scaled_jacobian_and_degenerate(X, ONE)
    assert deg[0] and np.isfinite(sj[0])
    Z = UNIT.copy()
    Z[6] = [1.5, 1.5, 0.0]  # corner 6 moved into the bottom plane: flat at corner 2 only (no short edge)
    sj, deg = scaled_jacobian_and_degenerate(Z, ONE)
    assert abs(sj[0]) < tol.SJ_DEGENERATE and deg[0]


# --------------------------------------------------------------------------- topology


def test_boundary_quads_of_2x2x2_block():
    m = structured(2, size=2.0)
    quads, owner = boundary_quads(m.hexes, return_hex=True)
    assert quads.shape == (24, 4) and quads.dtype == np.int64
    assert len(np.unique(np.sort(quads, axis=1), axis=0)) == 24
    tris = quads_to_triangles(quads)
    assert enclosed_volume(m.points, tris) == pytest.approx(8.0)  # > 0: outward
    # each quad's normal points away from the block centre
    P = m.points[quads]
    normal = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, P.mean(axis=1) - 1.0) > 0)
    # ... and away from its own hex
    hex_centre = m.points[m.hexes[owner]].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normal, P.mean(axis=1) - hex_centre) > 0)
    mask = boundary_vertex_mask(m.hexes, len(m.points))
    assert mask.sum() == 26 and not mask[13]  # 27 vertices, the centre is interior
    np.testing.assert_allclose(hex_volumes(m.points, m.hexes), 1.0)


def test_hex_volume_exact_for_trilinear():
    X = UNIT.copy()
    X[6] = [1.5, 1.5, 1.5]  # non-planar faces: trilinear volume = 1 + 0.5^3... check against fine sampling
    v = hex_volumes(X, ONE)[0]
    # Monte Carlo-free check: midpoint rule on a fine parametric grid
    t = (np.arange(40) + 0.5) / 40
    u, w, s = (a.ravel() for a in np.meshgrid(t, t, t, indexing="ij"))
    from polycubenet.hexmesh import _shape_gradients

    J = np.einsum("ki,qkj->qij", X, _shape_gradients(np.stack([u, w, s], 1)))
    assert v == pytest.approx(np.linalg.det(J).mean(), rel=1e-4)
    assert hex_volumes(UNIT[[4, 5, 6, 7, 0, 1, 2, 3]], ONE)[0] == pytest.approx(-1.0)


# --------------------------------------------------------------------------- report


def test_report_cube_vs_its_surface():
    m = structured(3)
    r = quality_report(m, cube_surface(), n_samples=20_000)
    assert r.valid and r.warnings == []
    assert r.hex_count == 27 and r.point_count == 64 and r.boundary_quad_count == 54
    assert r.sj_min == pytest.approx(1.0) and r.sj_avg == pytest.approx(1.0) and r.sj_p01 == pytest.approx(1.0)
    assert r.inverted_count == 0 and r.degenerate_count == 0
    assert r.volume == pytest.approx(1.0)
    assert r.surface["hausdorff"] < 1e-6 and r.surface["mean"] < 1e-6
    assert sum(r.hist_counts) == 27 and r.hist_counts[-1] == 27 and len(r.hist_edges) == 21
    d = r.to_dict()
    json.dumps(d, allow_nan=False)
    assert "sj" not in d and "mesh" not in d


def test_report_measures_distance_to_a_larger_cube():
    # hex mesh of [0,1]^3 against the surface of [-0.05, 1.05]^3: the farthest surface point is a
    # corner of the big cube, 0.05*sqrt(3) from the small one; relative to the diagonal 1.1*sqrt(3)
    r = quality_report(structured(2), cube_surface(-0.05, 1.05), n_samples=20_000)
    s = r.surface
    assert s["surface_to_hex_max"] == pytest.approx(0.05 / 1.1, rel=1e-4)
    assert s["hex_to_surface_max"] == pytest.approx(0.05 / (1.1 * np.sqrt(3)), rel=1e-3)
    assert s["hausdorff"] == pytest.approx(0.05 / 1.1, rel=1e-4)
    assert s["diagonal"] == pytest.approx(1.1 * np.sqrt(3))
    assert r.valid  # elements are fine; the distance only warns
    assert any("Hausdorff" in w for w in r.warnings)


def _boxes(*bounds):
    """One triangle surface of several boxes (``[[lo], [hi]]`` each), outward, not merged."""
    import trimesh

    parts = [trimesh.creation.box(bounds=b) for b in bounds]
    V = np.concatenate([p.vertices for p in parts])
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    F = np.concatenate([p.faces + o for p, o in zip(parts, offsets)])
    return np.asarray(V, float), np.asarray(F, np.int64)


def test_thin_features_reads_a_plates_wall_and_the_gap_beside_it():
    plate = _boxes([[0, 0, 0], [10, 10, 0.2]])
    t = thin_features(*plate, below=1.0)
    assert t["gaps"] is None
    assert t["walls"]["median"] == pytest.approx(0.2, rel=1e-3)
    assert t["walls"]["area_fraction"] == pytest.approx(200 / 208, abs=0.02)  # both big faces, not the rims
    assert thin_features(*plate, below=0.1) == {"walls": None, "gaps": None}  # nothing thinner than 0.1
    assert thin_features(*cube_surface(0.0, 10.0), below=1.0) == {"walls": None, "gaps": None}
    two = _boxes([[0, 0, 0], [10, 10, 4]], [[0, 0, 4.3], [10, 10, 8]])  # a 0.3 slot between two blocks
    t = thin_features(*two, below=1.0)
    assert t["walls"] is None and t["gaps"]["median"] == pytest.approx(0.3, rel=1e-3)


def test_a_valid_mesh_off_a_part_with_features_thinner_than_its_hexes_says_so():
    """The unit cube meshed in 4^3 hexes (edge 0.25) against a part that also has a plate 0.02 thick floating
    0.1 above it: valid, off the part, and the warning names the thin wall and the gap and the hex size; the
    same mesh against a larger plain cube warns of the distance only."""
    part = _boxes([[0, 0, 0], [1, 1, 1]], [[0, 0, 1.1], [1, 1, 1.12]])
    r = quality_report(structured(4), part, n_samples=20_000)
    assert r.valid and any("Hausdorff" in w for w in r.warnings)
    why = [w for w in r.warnings if "thinner than the mesh's hexes" in w]
    assert len(why) == 1 and "walls about 0.02 thick" in why[0] and "gaps about 0.1 thick" in why[0]
    assert "edge about 0.25" in why[0]
    plain = quality_report(structured(4), cube_surface(-0.05, 1.05), n_samples=20_000)
    assert any("Hausdorff" in w for w in plain.warnings)
    assert not any("thinner" in w for w in plain.warnings)


def test_a_mesh_off_the_part_says_where_on_both_sides_and_draws_it(tmp_path):
    """The unit cube in 4^3 hexes with its (1, 1, 1) corner node pulled out by 0.15 on each axis, against a part
    that is the cube plus a 0.2-wide post 0.3 tall on its top: farthest first, the post's top (the part not
    reached, 0.3 off), the pulled corner (the mesh beyond the part, 0.15 * sqrt(3) off) and the part's corner
    inside it, with their places in the part's coordinates, one warning sentence and deviation.png."""
    m = structured(4)
    X = m.points.copy()
    corner = np.flatnonzero(np.all(np.isclose(X, 1.0), axis=1))
    X[corner] += 0.15
    part = _boxes([[0, 0, 0], [1, 1, 1]], [[0.4, 0.4, 1.0], [0.6, 0.6, 1.3]])
    r = quality_report(HexMesh(X, m.hexes), part, n_samples=20_000)
    diag = np.sqrt(2 + 1.3**2)
    spots = r.surface["spots"]
    # the third: the part's own corner, left inside the bulged corner hex
    assert [s["side"] for s in spots] == ["part", "mesh", "part"]
    post, pulled, inside = spots
    assert post["max"] == pytest.approx(0.3 / diag, rel=0.02)
    assert np.allclose(post["centre"][:2], 0.5, atol=0.02) and 1.0 < post["centre"][2] < 1.3
    assert post["size"][0] == pytest.approx(0.2, abs=0.02)  # the post's width
    assert pulled["max"] == pytest.approx(0.15 * np.sqrt(3) / diag, rel=0.02)
    assert min(pulled["centre"]) > 0.9 and min(inside["centre"]) > 0.8 and inside["max"] < pulled["max"]
    where = [w for w in r.warnings if w.startswith("Where")]
    assert len(where) == 1 and "the part not reached" in where[0] and "the mesh beyond the part" in where[0]
    paths = r.write(tmp_path / "q")
    assert _is_png(paths["deviation"]) and _png_not_blank(paths["deviation"])
    d = json.loads(paths["json"].read_text())
    assert [s["side"] for s in d["surface"]["spots"]] == ["part", "mesh", "part"]


def test_far_spots_groups_samples_by_place_farthest_first():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 0.01, (50, 3))  # a spot at the origin, 0.02 off
    b = rng.uniform(0, 0.01, (30, 3)) + [0.5, 0.0, 0.0]  # one 0.5 away, 0.05 off
    spots = far_spots(np.vstack([a, b]), np.r_[np.full(50, 0.02), np.full(30, 0.05)], diagonal=1.0)
    assert [s["samples"] for s in spots] == [30, 50]
    assert spots[0]["max"] == 0.05 and spots[0]["centre"][0] == pytest.approx(0.505, abs=0.01)
    assert far_spots(np.zeros((0, 3)), np.zeros(0), diagonal=1.0) == []


def test_mirrored_mesh_is_flagged():
    m = structured(2)
    r = quality_report(HexMesh(m.points, m.hexes[:, [4, 5, 6, 7, 0, 1, 2, 3]]))
    assert not r.valid and r.inverted_count == 8 and r.sj_max == pytest.approx(-1.0)
    assert any("negative" in w for w in r.warnings)


def test_empty_mesh_report():
    r = quality_report(HexMesh(np.zeros((0, 3)), np.zeros((0, 8), np.int64)))
    assert not r.valid and r.sj_min is None and r.warnings
    json.dumps(r.to_dict(), allow_nan=False)


def _is_png(path, min_bytes=2000):
    data = path.read_bytes()
    return data[:8] == PNG_MAGIC and len(data) > min_bytes


def _png_not_blank(path):
    from PIL import Image

    img = np.asarray(Image.open(path).convert("RGB"))
    return img.shape[0] > 100 and img.shape[1] > 100 and np.ptp(img) > 0 and len(np.unique(img.reshape(-1, 3), axis=0)) > 10


def test_write_pictures_and_json(tmp_path):
    m = structured(3)
    X = m.points.copy()
    X[21] += [0.1, -0.1, 0.2]  # distort one interior vertex so colours vary
    r = quality_report(HexMesh(X, m.hexes), cube_surface(), n_samples=5_000)
    paths = r.write(tmp_path / "q")
    for name in ("quality.json", "quality.png", "preview.png"):
        assert (tmp_path / "q" / name).is_file()
    assert _is_png(paths["histogram"]) and _is_png(paths["preview"])
    assert _png_not_blank(paths["preview"]) and _png_not_blank(paths["histogram"])
    d = json.loads(paths["json"].read_text())
    assert d["hex_count"] == 27 and d["preview_backend"] in ("pyvista", "matplotlib")
    assert d["sj_min"] == pytest.approx(r.sj_min)
    assert "spots" not in d["surface"] and not (tmp_path / "q" / "deviation.png").exists()  # on the part
    assert not list((tmp_path / "q").glob(".tmp-*"))  # atomic writes leave no temp files


def test_matplotlib_fallback_renders(tmp_path):
    from polycubenet.render import render_hex_quality

    m = structured(2)
    sj = np.array([1.0, 0.5, -0.2, 0.9, 0.1, 0.7, 0.3, 0.8])
    out = tmp_path / "p.png"
    assert render_hex_quality(m.points, m.hexes, sj, out, backend="matplotlib", window_size=(500, 300)) == "matplotlib"
    assert _is_png(out) and _png_not_blank(out)


_RENDER_IN_THREADS = """
import sys
from concurrent.futures import ThreadPoolExecutor
import numpy as np
from polycubenet.render import render_hex_quality
pts = np.array([[0,0,0],[1,0,0],[1,1,0],[0,1,0],[0,0,1],[1,0,1],[1,1,1],[0,1,1]], float)
def job(i):
    return render_hex_quality(pts + i, np.arange(8)[None], np.array([0.5]), f"{sys.argv[1]}/r{i}.png", backend="pyvista")
with ThreadPoolExecutor(4) as ex:
    print(" ".join(ex.map(job, range(8))))
"""


def test_renders_from_several_threads_at_once_neither_crash_nor_corrupt_the_process(tmp_path):
    """Export tasks render previews from a thread pool.  VTK off-screen rendering from two threads at
    once corrupted the C heap (an abort, or a segmentation fault then or at interpreter exit: the
    test suite's intermittent exit-time crash); each try runs in its own process with an empty
    shader cache (the first-run state where it crashed most), and must exit 0 with every picture
    rendered by VTK (pyvista's lazy imports also raced)."""
    import subprocess
    import sys

    pytest.importorskip("pyvista")
    for k in range(3):
        cache = tmp_path / f"cache{k}"
        proc = subprocess.run([sys.executable, "-c", _RENDER_IN_THREADS, str(tmp_path)], capture_output=True,
                              text=True, timeout=300, env={**os.environ, "XDG_CACHE_HOME": str(cache)})
        assert proc.returncode == 0, (proc.returncode, proc.stderr[-2000:])
        assert proc.stdout.split() == ["pyvista"] * 8, proc.stdout + proc.stderr[-2000:]
    for i in range(8):
        assert (tmp_path / f"r{i}.png").stat().st_size > 0
