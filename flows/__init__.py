"""Prefect flows that wire the stage tasks (:mod:`tasks`) into the service.

* :mod:`flows.mesh_library` -- mesh every part under folders/globs: cached stages, batched
  diffusion, per-part stages on a Dask cluster, classical fallback, manifest, report, artifacts;
* :mod:`flows.retry_failed` -- re-run only the failed parts of an output folder;
* :mod:`flows.scan_drops` -- mesh what is new or changed in a drop folder (nightly);
* :mod:`flows.train` -- data, training (torchrun / DDP), evaluation, publication;
* :mod:`flows.runners` -- the task runners (local Dask cluster or a scheduler address);
* :mod:`flows.cli` -- the ``polycubenet`` command line.
"""
