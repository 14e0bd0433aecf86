"""Load benchmark: 20 concurrent annotators saving full-resolution masks against a live server.

For each database (SQLite file, PostgreSQL) and each ``--workers`` count it starts
``occufly serve --workers N`` on loopback in a subprocess (N = 1: one process with the
lifting worker in its threads, the default deployment; N > 1: N stateless API processes plus
the lifting worker as its own process), lets the annotators each lease a frame (``POST
/next``) and save masks in a loop (bounded by ``--saves`` per annotator, 0 = unbounded, and
``--seconds``), waits for the lifting queue to drain, then reads back every acknowledged
version and compares it byte for byte with what was sent.

Prints one JSON object: per backend and worker count p50/p95/max save latency, saves/s,
lifting lag (save acknowledged -> its votes applied, from the ``lift_queue`` rows: p50/p95/
max), acknowledged, lost (acknowledged but unreadable, or missing from the lifting queue) and
corrupted (read back different) counts, the latency of a trivial authenticated GET measured
in the same run as a baseline, and ``workers_<N>_vs_1`` throughput ratios.

    .venv/bin/python bench/bench_api_load.py [--annotators 20] [--saves 0] [--seconds 60]
        [--width 4000] [--height 3000] [--backends postgresql] [--workers 1,4]
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

PASSWORD = "bench-password-1"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _workspace(path: Path, n_frames: int, width: int, height: int) -> None:
    from PIL import Image

    from occufly.camera import Camera, look_at
    from occufly.scene import Frame, Scene, Visibility

    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-50, 50, 20000), rng.uniform(-50, 50, 20000),
                           np.zeros(20000)]).astype(np.float32)
    f = 0.8 * width
    cam = Camera("PINHOLE", width, height, np.array([f, f, width / 2, height / 2]))
    frames, parts = [], []
    (path / "images").mkdir(parents=True)
    img = Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    for i in range(n_frames):
        c = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), 50.0])
        T = look_at(c, c * [1, 1, 0], up=(0.0, 1.0, 0.0))
        frames.append(Frame(name=f"f{i:03d}.png", camera=cam, T_cam_world=T,
                            image_path=str(path / "images" / "small.png"), altitude=50.0,
                            nominal_altitude=50))
        xc = xyz.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
        uv = xc[:, :2] / xc[:, 2:3] * f + [width / 2, height / 2]
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
        parts.append((np.nonzero(ok)[0].astype(np.int32), uv[ok].astype(np.float32),
                      xc[ok, 2].astype(np.float32)))
    img.save(path / "images" / "small.png")
    Scene(frames=frames, xyz=xyz, rgb=np.zeros_like(xyz, dtype=np.uint8),
          visibility=Visibility.from_parts(parts)).save(path / "ws")


def _mask(width: int, height: int, seed: int) -> bytes:
    from PIL import Image

    rng = np.random.default_rng(seed)
    m = np.full((height, width), 6, np.uint8)  # grass
    for cls in (1, 8, 16, 13):  # a few rectangles of road / tree / building / vehicle
        x0, y0 = rng.integers(0, width // 2), rng.integers(0, height // 2)
        m[y0:y0 + rng.integers(50, height // 2), x0:x0 + rng.integers(50, width // 2)] = cls
    buf = io.BytesIO()
    Image.fromarray(m).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


def _seed(env: dict, n_annotators: int, src: Path) -> int:
    from sqlalchemy import update

    from app.config import Settings
    from app.jobs import service as jobs
    from app.main import close, create_app
    from app.scenes import service as scenes
    from app.scenes.models import Frame
    from app.users import service as users

    settings = Settings.from_env(env)
    app = create_app(settings)
    ctx = app.state.ctx
    with ctx.sessions() as s:
        users.create_user(session=s, username="admin", password=PASSWORD, role="admin")
        for i in range(n_annotators):
            users.create_user(session=s, username=f"ann{i:02d}", password=PASSWORD,
                              role="annotator")
        scene = scenes.create_scene(session=s, settings=settings, name="bench", source=src)
        job = jobs.create(session=s, kind="import", scene_id=scene.id, user_id=None,
                          params={"source": str(src)})
        sid = scene.id
    ctx.jobs.submit(job.id)
    ctx.jobs.wait(job.id, timeout=600)
    with ctx.sessions() as s:
        s.execute(update(Frame).where(Frame.scene_id == sid).values(selected=True))
        s.commit()
        # annotators see only the scenes they are members of
        ids = [users.get_by_name(session=s, username=f"ann{i:02d}").id for i in range(n_annotators)]
        scenes.set_members(session=s, scene=s.get(scenes.Scene, sid), user_ids=ids, replace=True)
    close(app)
    return sid


def _login(c, username: str) -> None:  # noqa: ANN001
    """Bearer token, no cookie (cookie-authenticated writes need an Origin, like a browser)."""
    r = c.post("/api/auth/login", json={"username": username, "password": PASSWORD})
    r.raise_for_status()
    c.cookies.clear()
    c.headers["Authorization"] = f"Bearer {r.json()['token']}"


def _lift_lag(url: str, acked: list[tuple[int, int, str]], timeout: float) -> dict:
    """Wait for the lifting queue to drain; lag = applied_at - created_at of each acked
    version's queue entry (created in the save's transaction, so <= the acknowledgement)."""
    from sqlalchemy import create_engine, func, select

    from app.lifting.models import LiftQueueEntry

    eng = create_engine(url)
    t0 = time.monotonic()
    try:
        while True:
            with eng.connect() as c:
                pending = c.scalar(select(func.count()).select_from(LiftQueueEntry)
                                   .where(LiftQueueEntry.status == "pending"))
            if pending == 0 or time.monotonic() - t0 > timeout:
                break
            time.sleep(0.5)
        with eng.connect() as c:
            rows = {r.version_id: r for r in c.execute(select(
                LiftQueueEntry.version_id, LiftQueueEntry.status, LiftQueueEntry.created_at,
                LiftQueueEntry.applied_at))}
    finally:
        eng.dispose()
    lags, missing, statuses = [], 0, {}
    for _fid, v, _sha in acked:
        r = rows.get(v)
        if r is None:
            missing += 1
            continue
        statuses[r.status] = statuses.get(r.status, 0) + 1
        if r.applied_at is not None:
            lags.append((r.applied_at - r.created_at).total_seconds())
    lag_ms = np.array(lags) * 1000
    return {"lift_lag_p50_ms": round(float(np.percentile(lag_ms, 50)), 1) if lags else None,
            "lift_lag_p95_ms": round(float(np.percentile(lag_ms, 95)), 1) if lags else None,
            "lift_lag_max_ms": round(float(lag_ms.max()), 1) if lags else None,
            "lift_pending_after_drain": int(pending), "lift_drain_s": round(time.monotonic() - t0, 1),
            "lift_entries": statuses, "missing_from_lift_queue": missing}


def run_backend(name: str, url: str, args: argparse.Namespace, tmp: Path,
                workers: int = 1) -> dict:
    import httpx

    data = tmp / f"{name}_w{workers}"
    env = dict(os.environ, OCCUFLY_DATA_DIR=str(data), OCCUFLY_DATABASE_URL=url,
               OCCUFLY_IMPORT_ROOTS=str(tmp / "src"), OCCUFLY_SECRET_KEY=uuid.uuid4().hex * 2,
               OCCUFLY_ARGON2_MEMORY_KIB="8192", OCCUFLY_ARGON2_TIME_COST="1",
               OCCUFLY_MAX_UPLOAD_MB="256", OCCUFLY_FILL_DEBOUNCE_S="30")
    sid = _seed(env, args.annotators, tmp / "src" / "ws")
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "occufly.cli", "serve", "--workers", str(workers), "--host",
         "127.0.0.1", "--port", str(port)],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
        start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(300):
            try:
                if httpx.get(f"{base}/api/health", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        else:
            raise RuntimeError("server did not come up: " + proc.stderr.read(2000).decode())
        masks = [_mask(args.width, args.height, s) for s in range(args.distinct)]
        lat: list[float] = []
        acked: list[tuple[int, int, str]] = []  # (frame, version, sha256)
        errors: list[str] = []
        lock = threading.Lock()
        barrier = threading.Barrier(args.annotators)

        def annotator(i: int) -> None:
            with httpx.Client(base_url=base, timeout=120) as c:
                _login(c, f"ann{i:02d}")
                r = c.post(f"/api/scenes/{sid}/next")
                if r.status_code != 200:
                    errors.append(f"ann{i}: next {r.status_code}")
                    return
                fid = r.json()["id"]
                current = "none"
                barrier.wait()
                k = -1
                while args.saves <= 0 or k + 1 < args.saves:
                    k += 1
                    if time.monotonic() > deadline:
                        break
                    body = masks[(i * 7 + k) % len(masks)]
                    kind = "submitted" if k == args.saves - 1 else "draft"
                    t0 = time.perf_counter()
                    r = c.put(f"/api/frames/{fid}/mask?kind={kind}", content=body,
                              headers={"If-Match": current, "Content-Type": "image/png"})
                    dt = time.perf_counter() - t0
                    with lock:
                        if r.status_code == 200:
                            lat.append(dt)
                            v = r.json()["version"]
                            acked.append((fid, v, hashlib.sha256(body).hexdigest()))
                            current = str(v)
                        else:
                            errors.append(f"ann{i}: PUT {r.status_code} {r.text[:100]}")
                            return

        # baseline in the same run: one writer alone (admin, on a frame nobody leases)
        single: list[float] = []
        with httpx.Client(base_url=base, timeout=120) as c:
            _login(c, "admin")
            frames = c.get(f"/api/scenes/{sid}/frames").json()
            fid_single = frames[-1]["id"]
            current = "none"
            for k in range(5):
                t1 = time.perf_counter()
                r = c.put(f"/api/frames/{fid_single}/mask", content=masks[k % len(masks)],
                          headers={"If-Match": current, "Content-Type": "image/png"})
                single.append(time.perf_counter() - t1)
                r.raise_for_status()
                current = str(r.json()["version"])
                acked.append((fid_single, r.json()["version"],
                              hashlib.sha256(masks[k % len(masks)]).hexdigest()))
        deadline = time.monotonic() + args.seconds
        t0 = time.perf_counter()
        threads = [threading.Thread(target=annotator, args=(i,)) for i in range(args.annotators)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - t0
        lift = _lift_lag(url, acked, timeout=max(120.0, args.seconds * 2))
        # read every acknowledged version back
        lost = corrupted = 0
        with httpx.Client(base_url=base, timeout=120) as c:
            _login(c, "admin")
            for fid, v, sha in acked:
                r = c.get(f"/api/frames/{fid}/mask/versions/{v}")
                if r.status_code != 200:
                    lost += 1
                elif hashlib.sha256(r.content).hexdigest() != sha:
                    corrupted += 1
            base_lat = []
            for _ in range(50):
                t1 = time.perf_counter()
                c.get("/api/auth/me")
                base_lat.append(time.perf_counter() - t1)
        lat_ms = np.array(lat) * 1000
        return {
            "annotators": args.annotators, "mask": f"{args.width}x{args.height}",
            "mask_bytes_mean": int(np.mean([len(m) for m in masks])),
            "saves": len(lat), "load_avg_1min": round(os.getloadavg()[0], 1), "wall_s": round(wall, 2), "saves_per_s": round(len(lat) / wall, 2),
            "p50_ms": round(float(np.percentile(lat_ms, 50)), 1) if len(lat) else None,
            "p95_ms": round(float(np.percentile(lat_ms, 95)), 1) if len(lat) else None,
            "max_ms": round(float(lat_ms.max()), 1) if len(lat) else None,
            "single_writer_p50_ms": round(float(np.median(single) * 1000), 1),
            "p50_vs_single_writer": round(float(np.percentile(lat_ms, 50)) / (np.median(single) * 1000), 2)
            if len(lat) else None,
            "single_writer_saves_per_s": round(1.0 / float(np.median(single)), 2),
            "throughput_vs_single_writer": round((len(lat) / wall) * float(np.median(single)), 2),
            "baseline_get_me_p50_ms": round(float(np.median(base_lat) * 1000), 2),
            "acknowledged": len(acked), "readback_checked": len(acked),
            "lost": lost + lift["missing_from_lift_queue"], "corrupted": corrupted,
            "workers": workers, **lift,
            "errors": errors[:5], "n_errors": len(errors),
        }
    finally:
        import signal

        try:
            os.killpg(proc.pid, signal.SIGTERM)  # serve, its API workers, the lifting worker
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--annotators", type=int, default=20)
    ap.add_argument("--saves", type=int, default=0, help="saves per annotator (0: unbounded)")
    ap.add_argument("--seconds", type=float, default=60, help="stop saving after this long")
    ap.add_argument("--workers", default="1,4", help="API process counts to compare")
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=3000)
    ap.add_argument("--distinct", type=int, default=6, help="distinct mask payloads")
    ap.add_argument("--backends", default="postgresql")
    ap.add_argument("--postgres-url", default=os.environ.get(
        "OCCUFLY_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"))
    args = ap.parse_args()
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    out: dict = {"benchmark": "api_load"}
    with tempfile.TemporaryDirectory(prefix="occufly-bench-") as d:
        tmp = Path(d)
        _workspace(tmp / "src", args.annotators + 2, args.width, args.height)
        counts = [int(w) for w in args.workers.split(",") if w.strip()]
        for backend in args.backends.split(","):
            res: dict = {}
            for workers in counts:
                key = f"workers_{workers}"
                if backend == "sqlite":
                    db = tmp / f"sqlite_w{workers}.db"
                    res[key] = run_backend("sqlite", f"sqlite:///{db}", args, tmp, workers)
                    continue
                base = make_url(args.postgres_url)
                name = f"occufly_bench_{uuid.uuid4().hex[:8]}"
                admin = create_engine(base, isolation_level="AUTOCOMMIT")
                with admin.connect() as c:
                    c.execute(text(f'CREATE DATABASE "{name}"'))
                try:
                    url = base.set(database=name).render_as_string(hide_password=False)
                    res[key] = run_backend("postgresql", url, args, tmp, workers)
                finally:
                    with admin.connect() as c:
                        c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
                    admin.dispose()
            one = res.get("workers_1", {}).get("saves_per_s")
            for workers in counts:
                r = res[f"workers_{workers}"]
                if workers != 1 and one:
                    res[f"workers_{workers}_vs_1"] = {
                        "saves_per_s": round(r["saves_per_s"] / one, 2),
                        "p95_ms": round(r["p95_ms"] / res["workers_1"]["p95_ms"], 2)
                        if r.get("p95_ms") and res["workers_1"].get("p95_ms") else None}
            out[backend] = res
    out["cpu_count"] = os.cpu_count()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
