"""Seeding a working demo: a synthetic scene imported, frames selected, one user per role.

``seed(settings)`` is what ``occufly demo`` runs before serving; tests and the browser e2e
suite call it too (with a smaller preset or an existing source folder).
"""

from __future__ import annotations

import contextlib
import secrets
import time
from pathlib import Path

from sqlalchemy import select as sql_select
from tqdm import tqdm

from app.config import Settings
from app.jobs import service as jobs
from app.main import close, create_app
from app.scenes import service as scenes
from app.scenes.models import Scene
from app.users import service as users
from occufly.errors import WorkspaceError
from occufly.fsutil import atomic_write_bytes
from occufly.synthetic import generate
from occufly.workspace import Workspace

DEMO_USERS = ("admin", "reviewer", "annotator")


def demo_password(role: str) -> str:
    return f"occufly-{role}"


def _copy_truth_grid(source: Path, ws: Path) -> None:
    """A synthetic scene's exact grid goes with its workspace, for the eval job (grid metrics)."""
    src, dst = source / "truth" / "scene_grid.npz", Workspace(ws).truth_grid_path
    if src.is_file() and ws.is_dir() and not dst.is_file():
        dst.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(dst, src.read_bytes())
    # and its point truth, so the quality report measures the calibration (ECE; issue 23)
    src, dst = source / "truth" / "point_labels.npy", Workspace(ws).truth_dir / "point_labels.npy"
    if src.is_file() and ws.is_dir() and not dst.is_file():
        dst.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(dst, src.read_bytes())


class DemoSteps:
    """Numbered steps on ``stream`` as they happen: a line when each starts, a progress bar
    (tqdm on a terminal; a line per quarter otherwise, e.g. in docker logs), and a line with
    its time when it ends. Every write is flushed, so nothing waits in a buffer.
    ``DemoSteps(None)`` is silent (tests, library callers)."""

    def __init__(self, stream=None, total: int = 4, *, tty: bool | None = None) -> None:  # noqa: ANN001
        self.stream = stream
        self.total = total
        self.n = 0
        self.tty = (bool(getattr(stream, "isatty", lambda: False)()) if tty is None else tty)
        self.times: dict[str, float] = {}

    def say(self, text: str) -> None:
        if self.stream is not None:
            print(text, file=self.stream, flush=True)

    def step(self, label: str):  # noqa: ANN201 - a context manager yielding a ProgressFn
        @contextlib.contextmanager
        def run():
            self.n += 1
            tag = f"[{self.n}/{self.total}]"
            self.say(f"{tag} {label} ...")
            t0 = time.perf_counter()
            bar = None
            if self.stream is not None and self.tty:
                bar = tqdm(total=1000, desc=f"    {label}", file=self.stream, leave=False,
                           bar_format="{desc} {bar} {percentage:3.0f}% {elapsed}")
            state = {"last": 0, "quarter": 0}

            def progress(fraction: float, message: str = "") -> None:
                f = max(0.0, min(1.0, float(fraction)))
                if bar is not None:
                    n = int(f * 1000)
                    if n > state["last"]:
                        bar.update(n - state["last"])
                        state["last"] = n
                elif int(f * 4) > state["quarter"] and f < 1.0:
                    state["quarter"] = int(f * 4)
                    self.say(f"    {label}: {100 * f:3.0f} %{f' ({message})' if message else ''}")

            try:
                yield progress
            finally:
                if bar is not None:
                    bar.close()
                dt = time.perf_counter() - t0
                self.times[label] = dt
                self.say(f"{tag} {label}: done in {dt:.1f} s")

        return run()


def _run_job(ctx, session, job, progress) -> None:  # noqa: ANN001
    """Run a job to its end, feeding its stored progress to ``progress`` twice a second."""
    ctx.jobs.submit(job.id)
    t_end = time.monotonic() + 3600
    while True:
        try:
            ctx.jobs.wait(job.id, timeout=0.5)
            break
        except TimeoutError:
            if time.monotonic() > t_end:
                raise
            session.refresh(job)
            progress(job.progress or 0.0, job.message or "")
    session.refresh(job)
    progress(1.0, job.message or "")


def seed(settings: Settings, source_dir: Path | None = None, *, preset: str = "small",
         seed_value: int = 0, name: str | None = None, app=None, select: bool = True,  # noqa: ANN001
         passwords: dict[str, str] | None = None, progress=None,  # noqa: ANN001
         dev_passwords: bool | None = None, steps: DemoSteps | None = None) -> dict:
    """Import ``source_dir`` (default: synthesize ``preset`` under the data dir), select
    frames, and create users admin/reviewer/annotator, made members of the scene. Idempotent:
    existing users and a scene of the same name are kept. Returns {scene_id, users: {name:
    password, or None for an account that already existed}, selection}.

    New accounts get random passwords unless ``dev_passwords`` (default: the settings'
    development mode) asks for the well-known ``occufly-<role>`` ones.
    """
    own_app = app is None
    app = app or create_app(settings)
    ctx = app.state.ctx
    steps = steps or DemoSteps(None)
    try:
        if source_dir is None:
            source_dir = settings.import_roots[0] / f"synthetic_{preset}_{seed_value}"
            if not (source_dir / "truth").is_dir():
                with steps.step(f"synthesizing the {preset} scene") as bar:
                    def both(f: float, m: str = "") -> None:
                        bar(f, m)
                        if progress is not None:
                            progress(f, m)

                    generate(source_dir, preset=preset, seed=seed_value, progress=both,
                             overwrite=True)
            else:
                steps.say(f"[{steps.n + 1}/{steps.total}] synthetic {preset} scene already at "
                          f"{source_dir}: reused")
                steps.n += 1
        source = scenes.resolve_import_path(settings, str(source_dir))
        name = name or f"{Path(source).name}"
        creds = {}
        with ctx.sessions() as s:
            well_known = settings.is_dev if dev_passwords is None else dev_passwords
            users_step = steps.step("creating the users admin, reviewer, annotator")
            users_step.__enter__()
            for role in DEMO_USERS:
                pw = (passwords or {}).get(role) or (
                    demo_password(role) if well_known else secrets.token_urlsafe(12))
                if users.get_by_name(session=s, username=role) is None:
                    users.create_user(session=s, username=role, password=pw, role=role)
                    creds[role] = pw
                else:
                    creds[role] = (passwords or {}).get(role) or (
                        demo_password(role) if well_known else None)
            users_step.__exit__(None, None, None)
            scene = s.scalar(sql_select(Scene).where(Scene.name == name))
            if scene is not None:
                steps.n += 1
                steps.say(f"[{steps.n}/{steps.total}] scene {name} already imported: reused")
            if scene is None:
                scene = scenes.create_scene(session=s, settings=settings, name=name, source=source)
                job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                                  params={"source": str(source), "cloud": None, "depth_maps": None})
                with steps.step(f"importing {Path(source).name}") as bar:
                    _run_job(ctx, s, job, bar)
                if job.status != "done":
                    raise WorkspaceError(f"demo import of {source} failed: {job.message}")
            s.refresh(scene)
            scene_id = scene.id
            member_ids = [users.get_by_name(session=s, username=r).id for r in DEMO_USERS
                          if r != "admin"]
            scenes.set_members(session=s, scene=scene, user_ids=member_ids, replace=False)
            _copy_truth_grid(Path(source), Path(scene.workspace))
            selection = scene.selection
            if selection is not None:
                steps.n += 1
                steps.say(f"[{steps.n}/{steps.total}] frames already selected: reused")
            if select and selection is None:
                job = jobs.create(session=s, kind="selection", scene_id=scene_id, user_id=None,
                                  params={"cell": "auto", "mode": "greedy", "target_coverage": 0.99})
                with steps.step("selecting frames (greedy, best cell of 23-28 m)") as bar:
                    _run_job(ctx, s, job, bar)
                selection = job.result
        sel = selection or {}
        return {"scene_id": scene_id, "source": str(source), "users": creds,
                "selection": {k: sel.get(k) for k in ("frames", "ratio", "coverage")}}
    finally:
        if own_app:
            close(app)
