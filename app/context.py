"""Per-process state: settings, database, mask store, event bus, lifting, job queue.

Nothing here is the truth of anything shared: leases, versions, jobs, sessions, the lifting
queue and events live in the database, arrays in the workspaces; any number of processes
can each hold an AppContext over the same database and data directory.

The context names what it needs of the job queue, of lifting and of the event bus as
Protocols (:class:`JobQueue`, :class:`Lifting`, :class:`Events`); the composition root
(:mod:`app.bootstrap`) builds the concrete services with explicit arguments and hands them
in, so nothing here imports them.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.blobs import BlobStore
from app.config import Settings
from occufly.scene import Scene
from occufly.workspace import Workspace


class JobQueue(Protocol):
    """What the app asks of the job runner (:class:`app.jobs.runner.JobRunner`)."""

    def start(self) -> None: ...
    def submit(self, job_id: int) -> None: ...
    def wait(self, job_id: int, timeout: float = 60.0) -> None: ...
    def shutdown(self, wait: bool = True) -> None: ...


class Lifting(Protocol):
    """What the app asks of lifting (:class:`app.lifting.client.LiftingClient`)."""

    mode: str
    service: Any  # the in-process lifting service, or None

    @property
    def enabled(self) -> bool: ...
    def start(self) -> None: ...
    def stop(self) -> None: ...
    def enqueue(self, session: Session, frame: Any, version_id: int | None) -> None: ...
    def notify(self, scene_id: int, frame_id: int, *, version_id: int | None = None,
               mask: Any = None) -> None: ...
    def status(self, scene_id: int) -> dict: ...
    def model(self, session: Session, scene_id: int) -> str: ...
    def set_model(self, session: Session, scene_id: int, model: str) -> bool: ...
    def wait_idle(self, scene_id: int, timeout: float = 10.0, *,
                  include_fill: bool = False) -> bool: ...
    def state_for(self, scene_id: int, workspace: str) -> Any: ...
    def included_versions(self, scene_id: int, workspace: str) -> dict | None: ...


class Events(Protocol):
    """What the app asks of the event bus (:class:`app.events.EventBus`)."""

    def publish(self, kind: str, scene_id: int | None = None, **payload: Any) -> Any: ...
    def subscribe(self, kind: str, fn: Callable[[Any], None]) -> None: ...
    def close(self) -> None: ...


class SceneCache:
    """:meth:`Scene.load` with a per-process cache keyed by workspace path and header mtime."""

    def __init__(self) -> None:
        self.entries: dict[str, tuple[int | None, Scene]] = {}

    def load(self, workspace: str) -> Scene:
        header = Workspace(workspace).scene_json
        try:
            mtime = os.stat(header).st_mtime_ns
        except OSError:
            mtime = None
        hit = self.entries.get(workspace)
        if hit and hit[0] == mtime:
            return hit[1]
        scene = Scene.load(workspace)
        self.entries[workspace] = (mtime, scene)
        return scene

    def pop(self, workspace: str, default: Any = None) -> Any:
        return self.entries.pop(workspace, default)


@dataclass
class AppContext:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: BlobStore
    lifting: Lifting
    jobs: JobQueue | None
    events: Events | None = None
    scene_cache: SceneCache = field(default_factory=SceneCache)

    def load_scene(self, workspace: str) -> Scene:
        """The workspace's scene, loaded once per process (until its header changes)."""
        return self.scene_cache.load(workspace)
