"""The lifting service: mask versions in, lifted point labels and ``labels_updated`` events out.

- :mod:`app.lifting.models` -- ``lift_queue`` (durable "frame F of scene S has version V",
  written in the save's transaction), ``lift_status`` (per scene: fill state, last error,
  labels stamp), ``events``.
- :mod:`app.lifting.service` -- :class:`LiftingService`, the worker: applies the queue in
  version order, exactly once per version, fills (incrementally), publishes; resumes after a
  crash. Several workers share the scenes on PostgreSQL (advisory locks, one owner per scene).
- :mod:`app.lifting.client` -- :class:`LiftingClient` (``ctx.lifting`` in every API process):
  enqueue, wake, status from the database, read-only views of the votes.
- events go through :mod:`app.events` (the bus and the catalogue of every event); the lifting
  service publishes ``labels_updated`` and ``votes_applied``.
- :mod:`app.lifting.worker` -- ``occufly lifting-worker`` / ``python -m app.lifting``: the
  service as its own process.
"""
