"""A part's registration and mesh do not depend on how many BLAS threads the process has (polycubenet.threads)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from polycubenet.errors import PolycubeError
from polycubenet.pipeline import PipelineConfig, mesh_surface

ROOT = Path(__file__).resolve().parents[1]

# the L-block's samples against 1000 of the bracket's: a CPD whose M-step product (64 x 1000 by 1000 x 64) OpenBLAS
# sums differently with one and with two threads (the registration's hash differed before polycubenet.threads)
_ALIGN = """
import hashlib, numpy as np
from polycubenet.io import load_part
from polycubenet.frame import canonicalize
from polycubenet.sampling import poisson_disk
from polycubenet.registration import align
pa, pb = load_part("examples/parts/l_block.stl"), load_part("examples/parts/bracket.stl")
Va, _ = canonicalize(pa.vertices, pa.faces)
Vb, _ = canonicalize(pb.vertices, pb.faces)
s = poisson_disk(Va, pa.faces, 4096, seed=0)
c = poisson_disk(Vb, pb.faces, 4096, seed=1)
corr = align(s, c.points[:1000], c.normals[:1000])
m = hashlib.md5()
for k, v in sorted(vars(corr).items()):
    if isinstance(v, np.ndarray):
        m.update(np.ascontiguousarray(v).tobytes())
print(m.hexdigest())
"""


def _align_hash(threads: int) -> str:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads)}
    r = subprocess.run([sys.executable, "-c", _ALIGN], cwd=ROOT, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip().splitlines()[-1]


def test_the_registration_is_the_same_bit_for_bit_with_one_or_two_blas_threads():
    assert _align_hash(1) == _align_hash(2)


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_the_pipeline_holds_blas_at_one_thread_inside_and_restores_it_after(l_block_canonical):
    seen = []

    def source(sample, V, F, config):  # runs inside mesh_surface's stages
        seen.append(_blas_threads())
        raise PolycubeError("no polycube here", "probe")

    V, F = l_block_canonical
    with threadpool_limits(limits=2, user_api="blas"):
        if set(_blas_threads()) != {2}:
            pytest.skip("this OpenBLAS does not take two threads")
        with pytest.raises(PolycubeError):
            mesh_surface(V, F, source, PipelineConfig(polycube="learned"), part_meta={"genus": 0})
        assert seen and all(set(s) == {1} for s in seen), seen
        assert set(_blas_threads()) == {2}


def test_two_stages_side_by_side_keep_one_thread_until_the_last_leaves():
    """Part A's stage ends while part B's runs in another thread (the thread runner): B's products stay
    one-thread products.  A hold per stage would give the pools back to two threads when A left."""
    import hashlib
    import threading

    import numpy as np

    from polycubenet.threads import blas_held

    rng = np.random.default_rng(0)
    C, w = rng.random((4080, 64)), rng.random(4080)

    def product() -> str:  # the registration's M-step product, whose sums depend on the thread count
        return hashlib.md5((C.T @ (w[:, None] * C)).tobytes()).hexdigest()

    with threadpool_limits(limits=1, user_api="blas"):
        one = product()
    inside, a_left, seen = threading.Event(), threading.Event(), []

    def b():
        with blas_held():
            inside.set()
            a_left.wait(30)
            seen.append(product())

    with threadpool_limits(limits=2, user_api="blas"):
        if product() == one:
            pytest.skip("this OpenBLAS sums the product the same way with one and two threads")
        t = threading.Thread(target=b)
        with blas_held():
            t.start()
            assert inside.wait(30)
        a_left.set()
        t.join(30)
    assert seen == [one]
