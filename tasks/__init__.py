"""Thin Prefect tasks, one per pipeline stage; each calls one function of
:mod:`polycubenet.library`, writes its result under ``<work>/<part-hash>/`` and returns
the path (see :mod:`tasks.mesh`).  :mod:`tasks.common` holds the cache policy and the
retry rule they share; :mod:`tasks.train` the training steps."""
