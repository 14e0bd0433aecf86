"""Per-application state: settings, database, mask store, live lifting and the job runner."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session, sessionmaker

from app.config import Settings

if TYPE_CHECKING:
    from app.annotations.lifting import LiftingManager
    from app.jobs.runner import JobRunner
    from app.storage import BlobStore


@dataclass
class AppContext:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: BlobStore
    lifting: LiftingManager
    jobs: JobRunner
    scene_cache: dict = field(default_factory=dict)

    def load_scene(self, workspace: str):
        """Scene.load with a per-process cache keyed by workspace path and header mtime."""
        import os

        from occufly.scene import Scene

        header = os.path.join(workspace, "scene.json")
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
