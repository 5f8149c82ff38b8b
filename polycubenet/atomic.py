"""Atomic file writes: write to a temporary file in the target folder, then rename.

A reader never sees a half-written file, and a killed process leaves at most a
``.tmp-*`` file behind (never the final name). :func:`load_npz` is the matching
reader, safe to call from many threads at once.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
from pathlib import Path
from typing import Iterator

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success.

    ``suffix`` defaults to the final suffix of ``path`` so that writers that pick a
    format from the extension (meshio, matplotlib) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".tmp-{path.stem}-", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    os.chmod(tmp, 0o644)  # mkstemp creates 0600; outputs are meant to be shared
    try:
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def save_npz(path: str | Path, **arrays) -> Path:
    """Write ``arrays`` to ``path`` (``.npz``, uncompressed) atomically; return the path."""
    path = Path(path)
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return path


_NPZ_READ_LOCK = threading.Lock()


def load_npz(path: str | Path, keys=None) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` file at ``path`` (or only ``keys``), read into memory.

    Reads are serialised across threads. numpy parses each member's header with
    ``ast.literal_eval``, and CPython 3.11 keeps the AST constructor's recursion depth in
    state shared by all threads: when a garbage collection inside one parse runs a
    finalizer and another thread parses meanwhile, one of them fails with ``SystemError: AST
    constructor recursion depth mismatch`` (python/cpython#106905). The threaded runner
    loads cached stages from several workers at once, so every cached read goes through
    here.
    """
    with _NPZ_READ_LOCK, np.load(path, allow_pickle=False) as z:
        names = z.files if keys is None else [k for k in keys if k in z.files]
        return {k: z[k] for k in names}


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


def write_json(path: str | Path, obj) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    return write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")
