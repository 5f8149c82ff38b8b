"""Shared fixtures: small known shapes built in memory (no files from outside the repo)."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


def _box(lo, hi):
    import trimesh

    return trimesh.creation.box(bounds=[lo, hi])


@pytest.fixture(scope="session")
def l_block():
    """An L-shaped block (genus 0), as (V, F) with refined triangles: extents 3 x 1 x 2 after union."""
    import trimesh

    a = _box([0, 0, 0], [3, 1, 1])
    b = _box([0, 0, 1], [1, 1, 2])
    m = trimesh.boolean.union([a, b], engine="manifold")
    m = m.subdivide().subdivide()
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


@pytest.fixture(scope="session")
def torus():
    import trimesh

    m = trimesh.creation.torus(1.0, 0.35, major_sections=48, minor_sections=24)
    return np.asarray(m.vertices, float), np.asarray(m.faces, np.int64)


@pytest.fixture(scope="session")
def l_block_canonical(l_block):
    """The L-block centred and scaled to diagonal 1, axes kept (canonical frame without rotation)."""
    from polycubenet.frame import canonicalize

    V, F = l_block
    Vc, _ = canonicalize(V, F, rotate=False)
    return Vc, F


@pytest.fixture(scope="module")
def tiny_net():
    """The ``tiny`` PolycubeNet preset, seeded, with a non-zero output layer (it starts at zero,
    which would make every prediction trivially equal)."""
    import torch

    from polycubenet.model import PolycubeNet, preset

    torch.manual_seed(0)
    net = PolycubeNet(preset("tiny")).eval()
    with torch.no_grad():
        torch.nn.init.normal_(net.denoiser.out.weight, std=0.1)
    return net


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """Keep a fatal-signal report armed through the interpreter's teardown.

    pytest's faulthandler plugin disarms at unconfigure, so a crash while the interpreter
    finalises (native libraries' destructors, daemon threads) used to end the run with a bare
    "Segmentation fault" and no trace.  Armed again here, the same crash prints every thread's
    Python stack to stderr; the exit status is untouched."""
    import faulthandler
    import sys

    if sys.__stderr__ is not None:
        faulthandler.enable(file=sys.__stderr__, all_threads=True)
