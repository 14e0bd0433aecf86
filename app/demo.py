"""Seeding a working demo: a synthetic scene imported, frames selected, one user per role.

``seed(settings)`` is what ``occufly demo`` runs before serving; tests and the browser e2e
suite call it too (with a smaller preset or an existing source folder).
"""

from __future__ import annotations

from pathlib import Path

from app.config import Settings

DEMO_USERS = ("admin", "reviewer", "annotator")


def demo_password(role: str) -> str:
    return f"occufly-{role}"


def _copy_truth_grid(source: Path, ws: Path) -> None:
    """A synthetic scene's exact grid goes with its workspace, for the eval job (grid metrics)."""
    from occufly.fsutil import atomic_write_bytes
    from occufly.workspace import Workspace

    src, dst = source / "truth" / "scene_grid.npz", Workspace(ws).truth_grid_path
    if src.is_file() and ws.is_dir() and not dst.is_file():
        dst.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(dst, src.read_bytes())


def seed(settings: Settings, source_dir: Path | None = None, *, preset: str = "small",
         seed_value: int = 0, name: str | None = None, app=None, select: bool = True,  # noqa: ANN001
         passwords: dict[str, str] | None = None, progress=None,  # noqa: ANN001
         dev_passwords: bool | None = None) -> dict:
    """Import ``source_dir`` (default: synthesize ``preset`` under the data dir), select
    frames, and create users admin/reviewer/annotator, made members of the scene. Idempotent:
    existing users and a scene of the same name are kept. Returns {scene_id, users: {name:
    password, or None for an account that already existed}, selection}.

    New accounts get random passwords unless ``dev_passwords`` (default: the settings'
    development mode) asks for the well-known ``occufly-<role>`` ones.
    """
    import secrets

    from sqlalchemy import select as sql_select

    from app.jobs import service as jobs
    from app.main import close, create_app
    from app.scenes import service as scenes
    from app.scenes.models import Scene
    from app.users import service as users

    own_app = app is None
    app = app or create_app(settings)
    ctx = app.state.ctx
    try:
        if source_dir is None:
            source_dir = settings.import_roots[0] / f"synthetic_{preset}_{seed_value}"
            if not (source_dir / "truth").is_dir():
                from occufly.synthetic import generate

                generate(source_dir, preset=preset, seed=seed_value, progress=progress,
                         overwrite=True)
        source = scenes.resolve_import_path(settings, str(source_dir))
        name = name or f"{Path(source).name}"
        creds = {}
        with ctx.sessions() as s:
            well_known = settings.is_dev if dev_passwords is None else dev_passwords
            for role in DEMO_USERS:
                pw = (passwords or {}).get(role) or (
                    demo_password(role) if well_known else secrets.token_urlsafe(12))
                if users.get_by_name(session=s, username=role) is None:
                    users.create_user(session=s, username=role, password=pw, role=role)
                    creds[role] = pw
                else:
                    creds[role] = (passwords or {}).get(role) or (
                        demo_password(role) if well_known else None)
            scene = s.scalar(sql_select(Scene).where(Scene.name == name))
            if scene is None:
                scene = scenes.create_scene(session=s, settings=settings, name=name, source=source)
                job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                                  params={"source": str(source), "cloud": None, "depth_maps": None})
                ctx.jobs.submit(job.id)
                ctx.jobs.wait(job.id, timeout=3600)
                s.refresh(job)
                if job.status != "done":
                    from occufly.errors import WorkspaceError

                    raise WorkspaceError(f"demo import of {source} failed: {job.message}")
            s.refresh(scene)
            scene_id = scene.id
            member_ids = [users.get_by_name(session=s, username=r).id for r in DEMO_USERS
                          if r != "admin"]
            scenes.set_members(session=s, scene=scene, user_ids=member_ids, replace=False)
            _copy_truth_grid(Path(source), Path(scene.workspace))
            selection = scene.selection
            if select and selection is None:
                job = jobs.create(session=s, kind="selection", scene_id=scene_id, user_id=None,
                                  params={"cell": "auto", "mode": "greedy", "target_coverage": 0.99})
                ctx.jobs.submit(job.id)
                ctx.jobs.wait(job.id, timeout=3600)
                s.refresh(job)
                selection = job.result
        sel = selection or {}
        return {"scene_id": scene_id, "source": str(source), "users": creds,
                "selection": {k: sel.get(k) for k in ("frames", "ratio", "coverage")}}
    finally:
        if own_app:
            close(app)
