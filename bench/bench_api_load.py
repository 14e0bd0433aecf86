"""Load benchmark: 20 concurrent annotators saving full-resolution masks against a live server.

For each database (SQLite file, PostgreSQL) it starts ``uvicorn app.main:create_app`` on
loopback in a subprocess, lets N annotators each lease a frame (``POST /next``) and save
masks in a loop (bounded by ``--saves`` per annotator and ``--seconds``), then reads back
every acknowledged version and compares it byte for byte with what was sent.

Prints one JSON object: per backend p50/p95/max save latency, saves/s, acknowledged,
lost (acknowledged but unreadable) and corrupted (read back different) counts, plus the
latency of a trivial authenticated GET measured in the same run as a baseline (ratio).

    .venv/bin/python bench/bench_api_load.py [--annotators 20] [--saves 5] [--width 4000]
        [--height 3000] [--backends sqlite,postgresql]
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


def run_backend(name: str, url: str, args: argparse.Namespace, tmp: Path) -> dict:
    import httpx

    data = tmp / name
    env = dict(os.environ, OCCUFLY_DATA_DIR=str(data), OCCUFLY_DATABASE_URL=url,
               OCCUFLY_IMPORT_ROOTS=str(tmp / "src"), OCCUFLY_SECRET_KEY=uuid.uuid4().hex * 2,
               OCCUFLY_ARGON2_MEMORY_KIB="8192", OCCUFLY_ARGON2_TIME_COST="1",
               OCCUFLY_MAX_UPLOAD_MB="256", OCCUFLY_FILL_DEBOUNCE_S="30")
    sid = _seed(env, args.annotators, tmp / "src" / "ws")
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "uvicorn", "--factory", "app.main:create_app", "--host",
         "127.0.0.1", "--port", str(port), "--log-level", "warning"],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
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
                r = c.post("/api/auth/login", json={"username": f"ann{i:02d}", "password": PASSWORD})
                r.raise_for_status()
                r = c.post(f"/api/scenes/{sid}/next")
                if r.status_code != 200:
                    errors.append(f"ann{i}: next {r.status_code}")
                    return
                fid = r.json()["id"]
                current = "none"
                barrier.wait()
                for k in range(args.saves):
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
            c.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
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
        # read every acknowledged version back
        lost = corrupted = 0
        with httpx.Client(base_url=base, timeout=120) as c:
            c.post("/api/auth/login", json={"username": "admin", "password": PASSWORD})
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
            "acknowledged": len(acked), "readback_checked": len(acked), "lost": lost, "corrupted": corrupted,
            "errors": errors[:5], "n_errors": len(errors),
        }
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--annotators", type=int, default=20)
    ap.add_argument("--saves", type=int, default=5, help="saves per annotator")
    ap.add_argument("--seconds", type=float, default=120, help="stop saving after this long")
    ap.add_argument("--width", type=int, default=4000)
    ap.add_argument("--height", type=int, default=3000)
    ap.add_argument("--distinct", type=int, default=6, help="distinct mask payloads")
    ap.add_argument("--backends", default="sqlite,postgresql")
    ap.add_argument("--postgres-url", default=os.environ.get(
        "OCCUFLY_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"))
    args = ap.parse_args()
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url

    out: dict = {"benchmark": "api_load"}
    with tempfile.TemporaryDirectory(prefix="occufly-bench-") as d:
        tmp = Path(d)
        _workspace(tmp / "src", args.annotators + 2, args.width, args.height)
        for backend in args.backends.split(","):
            if backend == "sqlite":
                out["sqlite"] = run_backend("sqlite", f"sqlite:///{tmp / 'sqlite.db'}", args, tmp)
            else:
                base = make_url(args.postgres_url)
                name = f"occufly_bench_{uuid.uuid4().hex[:8]}"
                admin = create_engine(base, isolation_level="AUTOCOMMIT")
                with admin.connect() as c:
                    c.execute(text(f'CREATE DATABASE "{name}"'))
                try:
                    url = base.set(database=name).render_as_string(hide_password=False)
                    out["postgresql"] = run_backend("postgresql", url, args, tmp)
                finally:
                    with admin.connect() as c:
                        c.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
                    admin.dispose()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
