"""benchmarks/stretch_draws.py: a stretched view of the part, its cloud mapped back to the part's frame."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import stretch_draws  # noqa: E402


def _part():
    from polycubenet.frame import canonicalize
    from polycubenet.io import load_part

    part = load_part(ROOT / "examples/parts/l_block.stl")
    Vc, _ = canonicalize(part.vertices, part.faces)
    return Vc, part.faces


def test_no_stretch_is_the_pipeline_s_own_draw():
    from model_failures import learned_cloud

    from polycubenet.inference import load_model
    from polycubenet.sampling import poisson_disk

    loaded = load_model(None, "cpu")
    Vc, F = _part()
    plain = learned_cloud(loaded, Vc, F, poisson_disk(Vc, F, 4096, seed=0), 4096, 1, seed=3)
    np.testing.assert_allclose(stretched_draw := stretch_draws.stretched_draw(loaded, Vc, F, (1, 1, 1), 3), plain,
                               atol=1e-5)
    assert stretched_draw.shape == (4096, 6)


def test_a_stretched_draw_comes_back_in_the_part_s_frame():
    from polycubenet.inference import load_model

    loaded = load_model(None, "cpu")
    Vc, F = _part()
    cloud = stretch_draws.stretched_draw(loaded, Vc, F, (2.0, 1.0, 1.0), 0)
    np.testing.assert_allclose(np.linalg.norm(cloud[:, 3:], axis=1), 1.0, atol=1e-5)
    extent, part_extent = np.ptp(cloud[:, :3], axis=0), np.ptp(Vc, axis=0)
    # the cloud covers the part as it is, not the stretched part (x twice as long against y and z)
    assert np.all(np.abs(extent / part_extent - 1) < 0.1), (extent, part_extent)
