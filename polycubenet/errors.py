"""Exceptions of the meshing spine.

Two families, both *final* for a part (retrying does not help):

- :class:`PartError`: the input part itself cannot be meshed (unreadable file,
  open surface, non-manifold, ...).  Every message names the file and the problem.
- :class:`PolycubeError`: a polycube (learned or classical) failed validation.

Anything else raised by the library is a bug or a transient failure.
"""

from __future__ import annotations

from pathlib import Path


class PolycubeNetError(Exception):
    """Base class of every error this library raises on purpose."""


class PartError(PolycubeNetError):
    """The part cannot be meshed.  ``path`` is the file, ``reason`` a readable sentence."""

    def __init__(self, path: str | Path | None, reason: str):
        self.path = None if path is None else str(path)
        self.reason = reason
        where = f"{self.path}: " if self.path else ""
        super().__init__(f"{where}{reason}")

    def __reduce__(self):  # picklable across processes (Dask, Prefect results)
        return (type(self), (self.path, self.reason))


class UnreadableFileError(PartError):
    """The file is missing, empty, truncated or not in the format it claims."""


class UnknownFormatError(PartError):
    """The file extension is not one we read."""


class NotTriangularError(PartError):
    """Faces are not triangles after loading."""


class InvalidCoordinatesError(PartError):
    """Vertex coordinates contain NaN or infinity."""


class EmptyMeshError(PartError):
    """No vertices or no (non-degenerate) faces."""


class OpenBoundaryError(PartError):
    """The surface has boundary edges: a hex mesh needs a closed solid."""


class NonManifoldError(PartError):
    """An edge is shared by more than two faces, or a vertex is a non-manifold pinch."""


class MultipleComponentsError(PartError):
    """Several disconnected components (pass ``keep_largest=True`` to keep the largest)."""


class SelfIntersectionError(PartError):
    """The surface crosses itself: it bounds no well-defined solid."""


class DegenerateVolumeError(PartError):
    """The enclosed volume is zero (flat) or the surface is self-inconsistent."""


class TooLargeError(PartError):
    """More faces than the configured limit."""


class PolycubeError(PolycubeNetError):
    """A polycube failed validation; ``reason`` says which check."""

    def __init__(self, reason: str, part: str | None = None):
        self.reason = reason
        self.part = part
        where = f"{part}: " if part else ""
        super().__init__(f"{where}{reason}")

    def __reduce__(self):
        return (type(self), (self.reason, self.part))
