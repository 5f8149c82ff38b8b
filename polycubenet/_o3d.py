"""open3d, always imported after pymeshlab.

When open3d is first used in one thread and pymeshlab is imported later in another (the flow's
thread runner does exactly that: the pull-back's raycasting, then a load's self-intersection
test), the process aborts at exit in libEGL's destructor (``malloc_consolidate(): unaligned
fastbin chunk detected``, rc 134) after all output is written.  Imported in this order that
pair does not (``tests/test_io.py``).  Other native libraries first loaded in a thread after
open3d ran in another (gmsh, some of prefect's) still can, which is why the command line leaves
without running the C destructors (``flows.cli.leave``).  Every open3d import in the library
goes through here::

    from ._o3d import open3d as o3d
"""

import pymeshlab  # noqa: F401  (first: see the module docstring)
import open3d

__all__ = ["open3d"]
