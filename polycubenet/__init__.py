"""PolycubeNet: all-hex meshing of CAD parts through learned (and classical) polycubes.

The library is a chain of pure functions over small dataclasses of numpy arrays
(see ``README.md``, section *Architecture*).  It never imports an orchestrator:
Prefect tasks and flows live in the top-level ``tasks/`` and ``flows/`` packages.
"""

__version__ = "0.1.0"
