"""Geometric tolerances in one place.

All lengths are *relative to the bounding-box diagonal* unless the name says
otherwise; the canonical frame (:mod:`polycubenet.frame`) makes that diagonal 1.
"""

from __future__ import annotations

#: vertices closer than this (relative to the diagonal) are merged on load
MERGE_REL = 1e-9
#: a triangle whose area is below AREA_REL * diagonal**2 is degenerate
AREA_REL = 1e-14
#: enclosed volume below VOLUME_REL * diagonal**3 counts as zero
VOLUME_REL = 1e-9
#: default maximum face count accepted by ``load_part``
MAX_FACES = 5_000_000
#: a hex corner whose edge is shorter than this (relative to the mean edge) is collapsed
EDGE_COLLAPSE_REL = 1e-12
#: an axis-aligned normal deviates from its axis by at most this (unit vector components)
AXIS_NORMAL = 1e-9
#: a hex whose scaled Jacobian has magnitude below this is degenerate (flat at a corner);
#: the scaled Jacobian is scale-free, so this is an absolute number
SJ_DEGENERATE = 1e-10
#: a hex boundary farther than this from the input surface (Hausdorff, relative to the
#: input's bounding-box diagonal) is flagged in the quality report (the benchmark bar)
HAUSDORFF_REL_MAX = 0.01
#: default triangle size when meshing a CAD (STEP/IGES) file, relative to the diagonal
CAD_MESH_SIZE_REL = 0.02
#: sewing tolerance for CAD faces that arrive unsewn (IGES, surface-only STEP), relative to the diagonal
CAD_SEW_REL = 1e-6
#: the most a CAD solid's surface area may change when it is healed (OpenCASCADE ShapeFix) before the heal is
#: undone, relative
CAD_HEAL_AREA_REL = 1e-3

# --- outlier removal (polycubenet.cleanup) -------------------------------------------
#: Phase I radius: tau = this * median L1 nearest-neighbour distance
OUTLIER_TAU_FACTOR = 3.0
#: Phase II threshold: median + this * robust sigma of the nearest-neighbour distances
OUTLIER_MAD_FACTOR = 4.0
#: the robust sigma is at least this fraction of the median (blue noise has a tiny MAD)
OUTLIER_MAD_FLOOR_REL = 0.1
#: Phase II never prunes more than this fraction of the points
OUTLIER_MAX_FRACTION = 0.05

# --- registration (polycubenet.registration) -----------------------------------------
#: CPD stops when sigma^2 falls below this (canonical units, diagonal 1, squared)
CPD_SIGMA2_MIN = 1e-12
#: ICP stops when the update (rotation in radians, relative scale, translation) is below this
ICP_STEP_MIN = 1e-12

#: a surface whose self-crossing triangles make more than this fraction of its area is refused
#: (SelfIntersectionError: overlapping shells, a face pushed through another); below it (local folds
#: and slivers: rockerarm 0.02 %, 11 of 30 synthetic parts up to 0.15 %) they are left as they are
#: and recorded in the part's repairs -- the hex mesh is checked for validity anyway
SELF_INTERSECTION_AREA = 1e-2
#: a part point stands on a slanted face (a slanted end, chamfer or ramp, which a polycube meets at an axis
#: plane) when its normal is more than this many degrees from every axis: the training's slant weight and the
#: held-out measure of how far the model takes such faces (``train.slant_weights``, ``evaluate.point_moves``)
SLANT_DEG = 15.0
