"""The flow's stage functions (polycubenet.library) keep the classical polycube's exact map:
registration is replaced by it and the pullback is the pipeline's classical one."""

import numpy as np
import trimesh

from polycubenet import library
from polycubenet.pipeline import PipelineConfig


def test_classical_stages_use_the_exact_map(l_block, tmp_path):
    V, F = l_block
    part = tmp_path / "l_block.stl"
    trimesh.Trimesh(V, F, process=False).export(part)
    cfg = PipelineConfig(n_sample=2048, n_polycube=4096, target_hexes=400)
    loaded = library.load_sample(part, tmp_path / "loaded.npz", cfg)
    cloud = library.polycube_cloud("classical", part, loaded, tmp_path / "cloud.npz", cfg)
    ext = library.cleanup_extract(cloud, loaded, tmp_path / "extract.npz", cfg)
    corr = library.register(ext, loaded, tmp_path / "register.npz", cfg)
    arrays, meta = library._load_arrays(corr)
    assert meta["method"] == "classical exact map"
    assert {"polycube_vertices", "surface_vertices", "surface_faces"} <= set(arrays)
    hexc = library.partition_pullback(ext, corr, loaded, tmp_path / "hex.npz", cfg)
    with np.load(hexc) as z:
        pts = z["points"]
    assert len(pts) > 100
    # the boundary of the mesh lies on the part (canonical frame): an exact map, not a registration
    part_c, _, _, _ = library.read_loaded(loaded)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(trimesh.sample.sample_surface_even(trimesh.Trimesh(part_c.vertices, part_c.faces), 4000, seed=0)[0]).query(pts)
    assert np.quantile(d, 0.5) < 0.02


def test_learned_or_oracle_clouds_still_register_by_cpd(tmp_path):
    # a cloud file without the exact-map arrays goes through CPD (Correspondence record)
    from polycubenet.data import PolycubeCloud

    P = np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3))
    path = PolycubeCloud(P, np.tile([1.0, 0, 0], (50, 1)), meta={}).save(tmp_path / "c.npz")
    assert library._exact_map_arrays(path) == {}
