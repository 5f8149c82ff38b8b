"""The data contracts of the spine: small dataclasses of numpy arrays.

Every box in the pipeline (see README, *Architecture*) is one of these.  Each has
``save(path)`` / ``load(path)`` to a single ``.npz`` written atomically, so a
stage's output either exists whole or not at all.

Shapes use numpydoc notation: ``points : (N, 3) float64``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np

from .atomic import load_npz, save_npz

T = TypeVar("T", bound="_NpzRecord")

_META_KEY = "__meta__"


class _NpzRecord:
    """Mixin: array fields go to the ``.npz`` as arrays, the ``meta`` dict as JSON."""

    _array_fields: ClassVar[tuple[str, ...]] = ()

    def save(self, path: str | Path) -> Path:
        arrays = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "meta":
                arrays[_META_KEY] = np.frombuffer(json.dumps(value, sort_keys=True).encode(), dtype=np.uint8)
            elif value is not None:
                arrays[f.name] = np.asarray(value)
        return save_npz(path, **arrays)

    @classmethod
    def load(cls: type[T], path: str | Path) -> T:
        z = load_npz(path)
        kwargs: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name == "meta":
                kwargs["meta"] = json.loads(bytes(z[_META_KEY]).decode()) if _META_KEY in z else {}
            else:
                kwargs[f.name] = z.get(f.name)
        return cls(**kwargs)


@dataclasses.dataclass
class Part(_NpzRecord):
    """A validated closed triangle surface.

    Attributes
    ----------
    vertices : (V, 3) float64
    faces : (F, 3) int64, oriented outward
    meta : dict
        ``path``, ``format``, ``units`` (or None), ``genus``, ``area``, ``volume``,
        ``repairs`` (list of sentences: what was repaired on load).
    """

    vertices: np.ndarray
    faces: np.ndarray
    meta: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class SurfaceSample(_NpzRecord):
    """Points on a triangle surface with an exact map back to it.

    Attributes
    ----------
    points : (N, 3) float64
    normals : (N, 3) float64, unit face normals
    face_ids : (N,) int64
    barycentrics : (N, 3) float64, rows sum to 1;
        ``points == (barycentrics[:, :, None] * V[F[face_ids]]).sum(1)``
    """

    points: np.ndarray
    normals: np.ndarray
    face_ids: np.ndarray
    barycentrics: np.ndarray
    meta: dict = dataclasses.field(default_factory=dict)


@dataclasses.dataclass
class PolycubeCloud(_NpzRecord):
    """A polycube as a point cloud (what the model generates), in the part's canonical frame.

    Attributes
    ----------
    points : (M, 3) float64
    normals : (M, 3) float64
    meta : dict, ``provenance`` ("learned" / "classical" / "oracle") and details
    anchors : (M, 3) float64 or None, the part point each point was generated from (an anchored
        model's cloud: its own map to the part, :mod:`polycubenet.anchormap`); None otherwise
    anchor_normals : (M, 3) float64 or None, the part's normal at each anchor (when the model takes them)
    """

    points: np.ndarray
    normals: np.ndarray
    meta: dict = dataclasses.field(default_factory=dict)
    anchors: np.ndarray | None = None
    anchor_normals: np.ndarray | None = None


@dataclasses.dataclass
class Polycube(_NpzRecord):
    """An explicit polycube: a rectilinear grid and the occupied cells.

    Attributes
    ----------
    xs, ys, zs : (nx+1,), (ny+1,), (nz+1,) float64, strictly increasing plane coordinates
    occupancy : (nx, ny, nz) bool
    meta : dict, ``provenance`` and ``genus``
    """

    xs: np.ndarray
    ys: np.ndarray
    zs: np.ndarray
    occupancy: np.ndarray
    meta: dict = dataclasses.field(default_factory=dict)

    @property
    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self.xs, self.ys, self.zs

    def to_meta(self) -> dict:
        """The polycube as plain JSON values (to ride in another record's ``meta``; :meth:`from_meta`)."""
        return {"xs": np.asarray(self.xs, float).tolist(), "ys": np.asarray(self.ys, float).tolist(),
                "zs": np.asarray(self.zs, float).tolist(), "occupancy": np.asarray(self.occupancy, np.uint8).tolist(),
                "meta": json.loads(json.dumps(self.meta, default=str))}

    @classmethod
    def from_meta(cls, d: dict) -> "Polycube":
        return cls(np.asarray(d["xs"], float), np.asarray(d["ys"], float), np.asarray(d["zs"], float),
                   np.asarray(d["occupancy"], bool), meta=dict(d.get("meta") or {}))


@dataclasses.dataclass
class HexMesh(_NpzRecord):
    """An all-hex mesh.

    Attributes
    ----------
    points : (P, 3) float64
    hexes : (H, 8) int64, VTK_HEXAHEDRON order (bottom face 0-1-2-3 counter-clockwise
        seen from the top, then the top face 4-5-6-7 above it)
    boundary : (P,) bool or None, True for vertices on the surface
    meta : dict
    """

    points: np.ndarray
    hexes: np.ndarray
    boundary: np.ndarray | None = None
    meta: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=np.float64)
        self.hexes = np.asarray(self.hexes, dtype=np.int64)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must be (P, 3); got shape {self.points.shape}")
        if self.hexes.ndim != 2 or self.hexes.shape[1] != 8:
            raise ValueError(f"hexes must be (H, 8); got shape {self.hexes.shape}")
        if self.hexes.size and (self.hexes.min() < 0 or self.hexes.max() >= len(self.points)):
            raise ValueError("hexes index outside points")
