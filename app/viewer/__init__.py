"""3D review viewer (viser), reached only through the app under ``/viewer/``.

Integration (the backend calls exactly this from ``create_app``)::

    from app import viewer
    viewer.mount(app, settings=settings, authorize=authorize)

``mount(fastapi_app, *, settings, authorize, identify=None, scenes=None, frame_states=None,
frame_mask=None, on_review_item=None, max_points=None, prefix="/viewer") -> None``

- ``authorize(request_or_websocket) -> bool`` (sync or async): True for a logged-in reviewer
  or admin (cookie ``occufly_session`` or bearer). It may also raise ``HTTPException(401/403)``.
  False gives 401 when the request carries no credentials, else 403; websockets are closed
  with code 1008.
- ``identify(request_or_websocket) -> user`` (optional): the user object handed to
  ``on_review_item``; default ``websocket.state.user`` if ``authorize`` set it, else None.
- ``scenes() -> {scene_id: (name, workspace_path)}`` (optional): the scenes a reviewer can
  open; default: every workspace (a folder with ``scene.json``) up to three levels below
  ``settings.data_dir``, id = folder name. Open a scene with ``/viewer/?scene=<id>``.
- ``can_open(user, scene_id) -> bool`` (optional): whether the ticket's user may open a scene;
  the scene dropdown lists only those, and opening any other is refused (the app: admins
  every scene, reviewers the scenes they are members of). Default: every scene.
- ``frame_states(scene_id) -> {frame_index: state}`` (optional) with state one of
  ``not_selected | selected | annotated | accepted | rejected`` (see
  :func:`app.viewer.scene_builder.viewer_state` to map the API's ``selected`` + ``state``).
- ``frame_mask(scene_id, frame_index) -> (h, w) uint8 | None`` (optional): current mask,
  shown in the side panel when a frustum is clicked.
- ``on_review_item(scene_id, point_ids, comment, user)``: called when a reviewer files a
  review item from a rectangle selection; default ``app.review.service.create_item_from_3d``
  if that exists.
- ``max_points``: LOD default (else ``settings.viewer_max_points``, else 2,000,000). Scenes
  showing more than 4x ``settings.viewer_preview_points`` (default 150,000) first get a
  stratified preview of that size, then the full LOD.

- ``corrections`` (optional): ``{"relabel", "undo", "redo", "stack"}`` callables of the
  app's corrections service (:func:`app.corrections.service.viewer_hooks`): the "Correct
  labels" panel relabels the selection through them.

- ``subscribe(kind, fn)`` (optional): an event source (the app passes
  ``ctx.events.subscribe``); the viewer subscribes to ``labels_updated`` and ``grid_updated``
  and refreshes open viewers of that scene on each event. Without one (a bare data
  directory), it watches the workspaces' change stamp every 2 s instead.

Live update: ``app.state.viewer.refresh(scene_id, classes=None)`` re-sends the affected class
nodes to open viewers (called on every ``labels_updated`` event).

The viser server binds 127.0.0.1 on a free port, starts in the background when the app
starts (or on the first ``/viewer/`` request) and never creates a share link.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from starlette.concurrency import run_in_threadpool

from app.viewer import scene_builder
from app.viewer.proxy import add_routes
from app.viewer.scene_builder import DEFAULT_MAX_POINTS
from app.viewer.server import ViewerService
from app.viewer.state import default_scenes

__all__ = ["mount", "ViewerService", "scene_builder"]

log = logging.getLogger(__name__)


def _default_review_hook() -> Callable[..., Any] | None:
    try:
        from app.review import service as review_service  # the app's, when mounted inside it
    except ImportError:
        return None
    return getattr(review_service, "create_item_from_3d", None)


def _start_quietly(service: ViewerService) -> None:
    try:
        service.start()
    except Exception:  # noqa: BLE001 - the rest of the app must still come up
        log.exception("viewer: viser server did not start; /viewer/ will retry")


def mount(fastapi_app: Any, *, settings: Any, authorize: Callable[[Any], Any],
          identify: Callable[[Any], Any] | None = None,
          scenes: Callable[[], Any] | None = None,
          frame_states: Callable[[str], Any] | None = None,
          frame_mask: Callable[[str, int], Any] | None = None,
          on_review_item: Callable[..., Any] | None = None,
          max_points: int | None = None, prefix: str = "/viewer",
          subscribe: Callable[[str, Callable[[Any], None]], None] | None = None,
          can_open: Callable[[Any, str], bool] | None = None,
          corrections: dict[str, Callable[..., Any]] | None = None,
          socket_leases: Any = None) -> None:
    """Add the ``/viewer/`` proxy routes and the viser server's lifecycle to ``fastapi_app``.

    The service is available as ``fastapi_app.state.viewer`` (a :class:`ViewerService`).
    """
    if max_points is None:
        max_points = int(getattr(settings, "viewer_max_points", DEFAULT_MAX_POINTS))
    if scenes is None:
        scenes = default_scenes(Path(getattr(settings, "data_dir", "data")))
    service = ViewerService(
        scenes=scenes, frame_states=frame_states, frame_mask=frame_mask,
        on_review_item=on_review_item if on_review_item is not None else _default_review_hook(),
        max_points=max_points,
        preview_points=int(getattr(settings, "viewer_preview_points", 150_000)),
        watch_interval_s=None if subscribe is not None else 2.0,
        can_open=can_open,
        corrections=corrections,  # relabel / undo / redo from 3D (app.corrections)
        prefs_path=Path(getattr(settings, "data_dir", "data")) / "viewer_prefs.json",
        max_sockets_per_user=getattr(settings, "viewer_sockets_per_user", None),
        socket_leases=socket_leases,  # the cap counted in the database (app.shared_limits)
    )
    if subscribe is not None:
        def _on_event(msg: Any) -> None:
            service.on_labels_updated(str(msg.scene_id), (msg.payload or {}).get("stamp"))

        subscribe("labels_updated", _on_event)
        subscribe("grid_updated", _on_event)
    fastapi_app.state.viewer = service
    add_routes(fastapi_app, service, authorize=authorize, identify=identify, prefix=prefix)

    inner = fastapi_app.router.lifespan_context

    @asynccontextmanager
    async def lifespan(app: Any):  # noqa: ANN202

        async with inner(app) as state:
            # start viser in the background so the app is up at once; a /viewer/ request
            # that arrives first waits for the same start (ViewerService.start is locked)
            starter = threading.Thread(target=_start_quietly, args=(service,),
                                       name="viewer-start", daemon=True)
            starter.start()
            try:
                yield state
            finally:
                await run_in_threadpool(starter.join)
                await run_in_threadpool(service.stop)

    fastapi_app.router.lifespan_context = lifespan
