"""OccuFly Studio web application (FastAPI).

Layout: ``config`` (``OCCUFLY_*`` settings), ``db`` (engine, naming convention, Alembic
upgrade), ``security`` (argon2id, session tokens, login throttling), ``errors`` (the one
domain-exception -> HTTP mapping), ``deps`` (``SessionDep``, ``CurrentUser``, role aliases,
``SceneDep``/``FrameDep``), ``pipeline`` (the only place that calls ``occufly.*``),
``storage`` (content-addressed mask store), and one package per domain -- ``users``,
``scenes``, ``annotations`` (leases, versioned masks, live lifting), ``review``, ``jobs`` --
each with models / schemas / service / routes. ``main.create_app(settings)`` builds the app;
``demo.seed(settings)`` makes a ready-to-use demo. ``viewer`` is the 3D review viewer.

Guarantees:
- A mask version acknowledged with 200 is stored (PNG, atomically, under its sha256) and in
  the database; a stale ``If-Match`` gets 409 and the upload is still kept as a ``conflict``
  version. Nothing is stored for a rejected upload (4xx).
- ``POST /api/scenes/{id}/next`` never leases one frame to two annotators (conditional
  UPDATE, race free on SQLite and PostgreSQL).
- Jobs survive restarts as ``interrupted`` and can be resumed.
"""
