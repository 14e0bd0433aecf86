"""Per-process state: settings, database, mask store, event bus, lifting client, job runner.

Nothing here is the truth of anything shared: leases, versions, jobs, sessions, the lifting
queue and events live in the database, arrays in the workspaces; any number of processes
can each hold an AppContext over the same database and data directory.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.config import Settings
from occufly.scene import Scene
from occufly.workspace import Workspace

if TYPE_CHECKING:
    from app.jobs.runner import JobRunner
    from app.lifting.client import LiftingClient
    from app.lifting.events import EventBus
    from app.storage import BlobStore


@dataclass
class AppContext:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: BlobStore
    lifting: LiftingClient
    jobs: JobRunner
    events: EventBus | None = None
    scene_cache: dict = field(default_factory=dict)

    def load_scene(self, workspace: str):
        """Scene.load with a per-process cache keyed by workspace path and header mtime."""
        header = Workspace(workspace).scene_json
        try:
            mtime = os.stat(header).st_mtime_ns
        except OSError:
            mtime = None
        hit = self.scene_cache.get(workspace)
        if hit and hit[0] == mtime:
            return hit[1]
        scene = Scene.load(workspace)
        self.scene_cache[workspace] = (mtime, scene)
        return scene
