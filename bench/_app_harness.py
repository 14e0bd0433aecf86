"""Shared by the benchmarks that drive the real app over HTTP (bench_api_load,
bench_review_scale): the app's environment for a scratch data dir and database, a seeded
database (users, scenes imported by the app's own import job, members, the frames handed
out), the server started as real processes (``occufly serve``, extra lifting workers) and
stopped, the server processes' CPU and memory (psutil), a scratch PostgreSQL database, the
synthetic truth masks of a project."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent

PASSWORD = "bench-password-1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def truth_dir(source: Path, workspace: Path | None) -> Path | None:
    """The synthetic truth masks of the project (``<project>/truth/masks``, one
    ``<image stem>.png`` of raw class ids per frame, as bench/bench_survey.py reads them):
    ``source``'s own, else those of the project the workspace's frame images come from."""
    for cand in (source, workspace):
        if cand is not None and (cand / "truth" / "masks").is_dir():
            return cand / "truth" / "masks"
    from occufly.workspace import Workspace

    for ws in (workspace, source):
        if ws is not None and Workspace(ws).exists():
            frames = json.loads(Workspace(ws).scene_json.read_text()).get("frames") or []
            img = next((f.get("image_path") for f in frames if f.get("image_path")), None)
            if img and (Path(img).parent.parent / "truth" / "masks").is_dir():
                return Path(img).parent.parent / "truth" / "masks"
    return None


class Mem:
    """Once a second while the server runs: the RSS of its processes (API processes,
    lifting workers: psutil; mapped file pages count in every process that touches them, so
    the sum over-counts shared pages; ``server_anon`` leaves the resident file pages out),
    the memory the host has available, the 1-min load."""

    def __init__(self, roots: list[int], floor_mb: float = 0.0) -> None:
        """``floor_mb``: when the host has less available, stop the server (SIGTERM to its
        process groups) before the kernel's OOM killer picks something (a shared machine)."""
        import psutil

        self.psutil = psutil
        self.pids = list(roots)
        self.floor = floor_mb * 2**20
        self.tripped: dict | None = None
        self.t_begin = time.monotonic()
        self.roots = []
        for pid in roots:
            try:
                self.roots.append(psutil.Process(pid))
            except psutil.NoSuchProcess:
                pass
        self.peak = {"api": 0, "lifting": 0, "server": 0, "largest_process": 0,
                     "api_anon": 0, "lifting_anon": 0, "server_anon": 0}
        self.min_avail = float("inf")
        self.load: list[tuple[float, float]] = []  # (monotonic, 1-min load average)
        self.role: dict[int, str] = {}
        self.per_process: dict[int, list] = {}  # pid -> [role, peak rss, peak anon]
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._loop, daemon=True)
        self._t.start()

    def _tick(self) -> None:
        procs = {}
        for r in self.roots:
            try:
                for q in [r, *r.children(recursive=True)]:
                    procs[q.pid] = q
            except self.psutil.Error:
                continue
        sums = {"api": 0, "lifting": 0}
        anon = {"api": 0, "lifting": 0}
        for q in procs.values():
            try:
                if q.pid not in self.role:
                    self.role[q.pid] = "lifting" if "app.lifting" in " ".join(q.cmdline()) else "api"
                mi = q.memory_info()
            except self.psutil.Error:
                continue
            rss = mi.rss
            anon[self.role[q.pid]] += rss - getattr(mi, "shared", 0)  # less resident file pages
            pp = self.per_process.setdefault(q.pid, [self.role[q.pid], 0, 0])
            pp[1], pp[2] = max(pp[1], rss), max(pp[2], rss - getattr(mi, "shared", 0))
            sums[self.role[q.pid]] += rss
            self.peak["largest_process"] = max(self.peak["largest_process"], rss)
        for k, v in sums.items():
            self.peak[k] = max(self.peak[k], v)
        self.peak["server"] = max(self.peak["server"], sums["api"] + sums["lifting"])
        for k, v in anon.items():
            self.peak[f"{k}_anon"] = max(self.peak[f"{k}_anon"], v)
        self.peak["server_anon"] = max(self.peak["server_anon"], anon["api"] + anon["lifting"])
        avail = self.psutil.virtual_memory().available
        self.min_avail = min(self.min_avail, avail)
        self.load.append((time.monotonic(), os.getloadavg()[0]))
        if avail < self.floor and self.tripped is None:
            import signal

            self.tripped = {"after_s": round(time.monotonic() - self.t_begin, 1),
                            "available_mb": round(avail / 2**20),
                            "server_rss_mb": round((sums["api"] + sums["lifting"]) / 2**20)}
            for pid in self.pids:
                try:
                    os.killpg(pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._tick()
            self._stop.wait(1.0)

    def stop(self, t0: float, t1: float) -> dict:
        """Peaks so far (MB) and the load average sampled between ``t0`` and ``t1``."""
        self._stop.set()
        self._t.join(timeout=10)
        during = [x for t, x in self.load if t0 <= t <= t1]
        return {"memory_guard": self.tripped,
                "peak_rss_mb": {k: round(v / 2**20) for k, v in self.peak.items()},
                "peak_rss_anon_mb_per_process": sorted(
                    ([r, round(a / 2**20), round(b / 2**20)] for r, a, b in
                     self.per_process.values()), key=lambda x: -x[1]),
                "min_available_mb": round(self.min_avail / 2**20),
                "load_avg_1min_during": {"first": round(during[0], 2),
                                         "mean": round(float(np.mean(during)), 2),
                                         "max": round(max(during), 2)} if during else None}


def seed(env: dict, n_annotators: int, src: Path, n_scenes: int, *,
         largest_only: bool = False, handout: int = 0,
         choose: Callable | None = None, users_extra: dict[str, str] | None = None
         ) -> tuple[list[int], dict]:
    """Users (``admin``, ``ann00``.., ``users_extra``: name -> role), ``n_scenes`` scenes
    imported from ``src`` by the app's own import job, members.

    Every frame is selected (handed out); with ``largest_only`` only the frames at the scene's
    largest frame size (the survey preset: its 20 full-size 5472 x 3648 frames, the rest are
    rendered at 1/12 of that), at most ``handout`` of them (0: all; the first by index);
    ``choose(ctx, session, scene)`` instead marks the frames to hand out itself. Returns the
    scene ids and what was imported (points, frames, frames handed out, their size, the
    import's wall time)."""
    from sqlalchemy import func, select, update

    from app.config import Settings
    from app.jobs import service as jobs
    from app.jobs.models import Job
    from app.main import close, create_app
    from app.scenes import service as scenes
    from app.scenes.models import Frame
    from app.users import service as users

    settings = Settings.from_env(env)
    app = create_app(settings)
    ctx = app.state.ctx
    sids: list[int] = []
    info: dict = {"import_source": str(src), "import_s": [], "scenes": [], "handed_out": {}}
    with ctx.sessions() as s:
        users.create_user(session=s, username="admin", password=PASSWORD, role="admin")
        for i in range(n_annotators):
            users.create_user(session=s, username=f"ann{i:02d}", password=PASSWORD,
                              role="annotator")
        for name, role in (users_extra or {}).items():
            users.create_user(session=s, username=name, password=PASSWORD, role=role)
    for k in range(n_scenes):
        with ctx.sessions() as s:
            scene = scenes.create_scene(session=s, settings=settings, name=f"bench{k}", source=src)
            job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                              params={"source": str(src)})
            sids.append(scene.id)
        t0 = time.monotonic()
        ctx.jobs.submit(job.id)
        ctx.jobs.wait(job.id, timeout=7200)
        info["import_s"].append(round(time.monotonic() - t0, 1))
        with ctx.sessions() as s:
            j = s.get(Job, job.id)
            if j.status != "done":
                raise RuntimeError(f"import of {src} into scene {scene.id}: {j.status}: "
                                   f"{j.message}")
    with ctx.sessions() as s:
        for k, sid in enumerate(sids):
            if choose is not None:
                choose(ctx, s, s.get(scenes.Scene, sid))
            else:
                q = update(Frame).where(Frame.scene_id == sid)
                if largest_only:
                    area = s.scalar(select(func.max(Frame.width * Frame.height))
                                    .where(Frame.scene_id == sid))
                    ids = select(Frame.id).where(Frame.scene_id == sid,
                                                 Frame.width * Frame.height == area)
                    if handout:
                        ids = ids.order_by(Frame.index).limit(handout)
                    q = q.where(Frame.id.in_(list(s.scalars(ids))))
                s.execute(q.values(selected=True))
            s.commit()
            sc = s.get(scenes.Scene, sid)
            sizes = s.execute(select(Frame.width, Frame.height, func.count())
                              .where(Frame.scene_id == sid, Frame.selected.is_(True))
                              .group_by(Frame.width, Frame.height)).all()
            info["handed_out"].update({n: (w, h) for n, w, h in s.execute(
                select(Frame.name, Frame.width, Frame.height)
                .where(Frame.scene_id == sid, Frame.selected.is_(True)))})
            info["scenes"].append({"id": sid, "points": sc.n_points, "frames": sc.n_frames,
                                   "frames_handed_out": sum(n for _, _, n in sizes),
                                   "handed_out_sizes": {f"{w}x{h}": n for w, h, n in sizes}})
            # annotators see only the scenes they are members of: annotator i -> scene i mod S
            ids = [users.get_by_name(session=s, username=f"ann{i:02d}").id
                   for i in range(n_annotators) if i % n_scenes == k]
            ids += [users.get_by_name(session=s, username=n).id for n in users_extra or {}]
            scenes.set_members(session=s, scene=s.get(scenes.Scene, sid), user_ids=ids,
                               replace=True)
    close(app)
    return sids, info


def login(c, username: str) -> None:  # noqa: ANN001
    """Bearer token, no cookie (cookie-authenticated writes need an Origin, like a browser)."""
    r = c.post("/api/auth/login", json={"username": username, "password": PASSWORD})
    r.raise_for_status()
    c.cookies.clear()
    c.headers["Authorization"] = f"Bearer {r.json()['token']}"


def pct(xs, q: float) -> float | None:
    return round(float(np.percentile(np.asarray(xs), q)), 3) if len(xs) else None


class Cpu:
    """CPU seconds of the server's process tree (API processes, lifting workers), the
    processes they start later included (the review refresh's child of the lifting worker,
    job processes): each read finds the roots' descendants again, and a descendant that
    exited and was waited for counts through its parent's ``children_*`` times. Role
    ``lifting``: an ``app.lifting`` worker and its descendants; ``api``: the rest."""

    def __init__(self, roots: list[int]) -> None:
        import psutil

        self.roots = []
        for pid in roots:
            try:
                self.roots.append(psutil.Process(pid))
            except psutil.Error:
                continue
        self.procs: dict[int, object] = {}
        self.start = self._read()

    def _role(self, p, inherited: str) -> str:  # noqa: ANN001
        try:
            return "lifting" if "app.lifting" in " ".join(p.cmdline()) else inherited
        except Exception:  # noqa: BLE001 - exited
            return inherited

    def _read(self) -> dict[str, float]:
        out = {"api": 0.0, "lifting": 0.0}
        seen: set[int] = set()

        def walk(p, inherited: str) -> None:  # noqa: ANN001
            if p.pid in seen:
                return
            seen.add(p.pid)
            self.procs[p.pid] = p
            role = self._role(p, inherited)
            try:
                t = p.cpu_times()
                kids = p.children()
            except Exception:  # noqa: BLE001 - exited
                return
            out[role] += t.user + t.system + t.children_user + t.children_system
            for k in kids:
                walk(k, role)

        for root in self.roots:
            walk(root, "api")
        return out

    def read(self) -> dict[str, float]:
        """CPU seconds (user + sys) so far, per role (``api``, ``lifting``)."""
        return self._read()

    def used(self) -> dict[str, float]:
        now = self._read()
        return {k: now[k] - self.start[k] for k in now}


def pg_database(base_url: str):  # noqa: ANN202
    from contextlib import contextmanager

    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    @contextmanager
    def cm():  # noqa: ANN202
        base = make_url(base_url)
        name = f"occufly_bench_{uuid.uuid4().hex[:8]}"
        admin = create_engine(base, isolation_level="AUTOCOMMIT")
        with admin.connect() as c:
            c.execute(text(f'CREATE DATABASE "{name}"'))
        try:
            yield base.set(database=name).render_as_string(hide_password=False)
        finally:
            with admin.connect() as c:
                c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
            admin.dispose()

    return cm()


def app_env(data: Path, url: str, roots: list[Path], *, api_workers: int = 1,
            debounce: float = 5.0, **extra: str) -> dict:
    """The environment of a server on the scratch data dir ``data`` and database ``url``:
    ``roots`` the import roots, a fresh secret, cheap password hashing (the benchmarks log in
    often), uploads up to 256 MB, the fill debounce; the lifting worker runs in the API
    process with one API worker (``embedded``), beside them with more (``external``)."""
    return dict(os.environ, OCCUFLY_DATA_DIR=str(data), OCCUFLY_DATABASE_URL=url,
                OCCUFLY_IMPORT_ROOTS=os.pathsep.join(str(r) for r in roots),
                OCCUFLY_SECRET_KEY=uuid.uuid4().hex * 2,
                OCCUFLY_ARGON2_MEMORY_KIB="8192", OCCUFLY_ARGON2_TIME_COST="1",
                OCCUFLY_MAX_UPLOAD_MB="256", OCCUFLY_FILL_DEBOUNCE_S=str(debounce),
                OCCUFLY_LIFTING="external" if api_workers > 1 else "embedded", **extra)


def start_server(env: dict, *, api_workers: int = 1, lifting_workers: int = 1,
                 timeout: float = 120.0) -> tuple[list[subprocess.Popen], str]:
    """``occufly serve --workers api_workers`` (with one API worker the lifting worker runs
    in it, else beside them) and ``lifting_workers - 1`` more ``python -m app.lifting``
    processes, each in its own process group; returns them and the base URL once
    ``/api/health`` answers."""
    import httpx

    port = free_port()
    procs = [subprocess.Popen(
        [sys.executable, "-m", "occufly.cli", "serve", "--workers", str(api_workers),
         "--host", "127.0.0.1", "--port", str(port)],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        start_new_session=True)]
    for _ in range(lifting_workers - 1):
        procs.append(subprocess.Popen([sys.executable, "-m", "app.lifting"], cwd=REPO, env=env,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                      start_new_session=True))
    base = f"http://127.0.0.1:{port}"
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if httpx.get(f"{base}/api/health", timeout=1).status_code == 200:
                return procs, base
        except httpx.HTTPError:
            pass
        if procs[0].poll() is not None:
            break
        time.sleep(0.1)
    err = procs[0].stderr.read(2000).decode() if procs[0].poll() is not None else "timeout"
    stop_server(procs)
    raise RuntimeError("server did not come up: " + err)


def stop_server(procs: list[subprocess.Popen]) -> None:
    """SIGTERM to each process group (serve, its API workers, the lifting workers), SIGKILL
    to those still there after 30 s."""
    import signal

    for p in procs:
        try:
            os.killpg(p.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
