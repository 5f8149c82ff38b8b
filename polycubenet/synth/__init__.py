"""Synthetic training data: random polycubes, smooth invertible deformations, shards.

No public data set pairs CAD shapes with polycubes, so we make them.  A pair is a
random valid polycube (:mod:`.polycube`) pushed through a random composition of
smooth bijections (:mod:`.deform`: rounded holes, fillets and chamfers, ramps,
taper, shear, twist, bend, free-form lattice), put in the canonical frame
(:mod:`polycubenet.frame`), and sampled with exact point-to-point correspondence
(:mod:`.pairs`).  :mod:`.shards` writes many pairs per ``.npz`` reproducibly by seed;
``python -m polycubenet.synth`` is the command line and
``python -m polycubenet.synth.preview`` draws a picture of a few pairs.
"""

from .deform import DeformationMap, check_invertible, jacobian_determinants, random_deformation
from .pairs import SynthPair, make_pair, snap_rotation
from .polycube import (
    RandomPolycube,
    check_occupancy,
    convex_edges,
    edge_contacts,
    nonmanifold_vertices,
    polycube_quads,
    polycube_surface,
    random_polycube,
    solid_genus,
    surface_genus,
    transform_grid,
    validate_occupancy,
)
from .shards import Shard, iter_pairs, list_shards, load_shard, pair_seed, write_dataset, write_shard

__all__ = [
    "DeformationMap",
    "RandomPolycube",
    "Shard",
    "SynthPair",
    "check_invertible",
    "check_occupancy",
    "convex_edges",
    "edge_contacts",
    "iter_pairs",
    "jacobian_determinants",
    "list_shards",
    "load_shard",
    "make_pair",
    "nonmanifold_vertices",
    "pair_seed",
    "polycube_quads",
    "polycube_surface",
    "random_deformation",
    "random_polycube",
    "snap_rotation",
    "solid_genus",
    "surface_genus",
    "transform_grid",
    "validate_occupancy",
    "write_dataset",
    "write_shard",
]
