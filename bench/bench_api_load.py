"""Load benchmark: annotators saving full-resolution masks against a live server, two load models.

``--models b2b``: the saturation figure. Every annotator leases a frame and submits masks back
to back (taking the frame back with ``/reopen`` between submits): only submitted, accepted or
imported versions vote, drafts are never lifted, so this is the heaviest lifting load the
API can produce.

``--models realistic``: annotators at a working cadence. Each one leases a frame, asks for the
prefill (``GET /frames/{fid}/prefill``), saves a draft every 10-30 s of painting and submits
after 2-4 minutes on the frame, then takes the next frame. ``--factor F`` divides every think
time by F (F = 1: real time); the lifting side then sees the submit rate of ``F x N``
annotators, and the report says so (``equivalent_annotators``). Annotators start at random
points of their first frame, so submits are spread from the start.

Lifting "lag" is measured on submits (the versions that vote): ``votes lag`` = the queue
entry's ``applied_at - created_at`` (its votes counted; the entry is created in the save's
transaction), ``labels lag`` = the first ``labels_updated`` event that counts the version
minus ``created_at`` (includes the fill debounce, ``OCCUFLY_FILL_DEBOUNCE_S``). ``lag_slope``
is the least-squares slope of votes lag against submit time: about 0 while lifting keeps up,
about ``1 - capacity / submit rate`` when the lag grows without bound; the knee is the
smallest load with a slope above 0.2 and submits still pending when saving stops.

For each configuration it starts ``occufly serve --workers A`` (A API processes plus one
lifting worker) and ``L - 1`` more ``python -m app.lifting`` processes (PostgreSQL only),
with ``--scenes`` scenes (annotator i works on scene i mod S: lifting workers share scenes,
not frames), waits for the queue to drain, reads every acknowledged version back byte for
byte. It reports save p50/p95/max, prefill latency, CPU seconds per save of the server
processes (API and lifting separately, psutil), lags p50/p95/max, ``lost`` and ``corrupted``.

The scene is fabricated by default (``_workspace``: ``--points`` points on a plane, ``--frames``
frames, imported through the app). ``--source PROJECT`` loads against a real project instead
(what ``occufly import`` takes, e.g. an ``occufly synth`` folder; read-only): the app's own
import job imports it into the bench's data dir, or, with ``--workspace WS`` (a workspace
``occufly import PROJECT -w WS`` made), copies that workspace, which the import job takes as
a source too (app.pipeline.import_scene) and is much faster than importing again. Only the
frames at the scene's largest size are handed out (the survey preset: its 20 full-size
5472 x 3648 frames; ``--handout N``: the first N of them) and the masks are theirs: the
project's synthetic truth masks (``truth/masks/<stem>.png``), a first draft with the top third
of the rows painted, later drafts two thirds, a submit all of it (``_mask`` for a frame
without one). When ``next`` has no frame left, a realistic annotator takes back the frame it
submitted longest ago (``/reopen``) and goes on with it (``reopened``). Every run's JSON names
its ``workspace`` (fabricated, or the source, points, frames, frames handed out), the server
processes' peak RSS (``peak_rss_mb``; ``--min-available-mb``: below that much available host
memory the server is stopped and the run reported ``aborted``) and the load average during
the load (``load_avg_1min_during``).

    .venv/bin/python bench/bench_api_load.py --models realistic,b2b --mp 12,20 \
        --lifting-workers 1,2 [--annotators 20] [--factor 1] [--seconds 240]
        [--b2b-seconds 60] [--scenes 2] [--api-workers 2] [--out docs/bench/x.json]
    .venv/bin/python bench/bench_api_load.py --knee 4,8,16 --seconds 90  # factor sweep
    .venv/bin/python bench/bench_api_load.py --models realistic --lifting-workers 1 --scenes 1 \
        --source /data/synth_survey --workspace /data/ws_survey  # a survey-sized scene
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import random
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _app_harness import Cpu as _Cpu  # noqa: E402
from _app_harness import Mem as _Mem  # noqa: E402
from _app_harness import app_env, start_server, stop_server  # noqa: E402
from _app_harness import login as _login  # noqa: E402
from _app_harness import pct as _pct  # noqa: E402
from _app_harness import pg_database as _pg_database  # noqa: E402
from _app_harness import seed as _seed  # noqa: E402
from _app_harness import truth_dir as _truth_dir  # noqa: E402


def _workspace(path: Path, n_frames: int, width: int, height: int, n_points: int = 20000
               ) -> None:
    from PIL import Image

    from occufly.camera import Camera, look_at
    from occufly.scene import Frame, Scene, Visibility

    rng = np.random.default_rng(0)
    xyz = np.column_stack([rng.uniform(-50, 50, n_points), rng.uniform(-50, 50, n_points),
                           np.zeros(n_points)]).astype(np.float32)
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
    rng = np.random.default_rng(seed)
    m = np.full((height, width), 6, np.uint8)  # grass
    for cls in (1, 8, 16, 13):  # a few rectangles of road / tree / building / vehicle
        x0, y0 = rng.integers(0, width // 2), rng.integers(0, height // 2)
        m[y0:y0 + rng.integers(50, height // 2), x0:x0 + rng.integers(50, width // 2)] = cls
    return _encode(m)


def _encode(m: np.ndarray) -> bytes:
    """A mask of class ids as the clients send it (``--upload``)."""
    from PIL import Image

    if UPLOAD == "editor":  # what the editor uploads (frontend/js/core/png.js: None / Up rows)
        from occufly.io.masks import encode_mask_png

        return encode_mask_png(m)
    buf = io.BytesIO()  # "pil1": PIL at compress level 1, what the runs before 2026-12-04 sent
    Image.fromarray(m).save(buf, format="PNG", compress_level=1)
    return buf.getvalue()


UPLOAD = "editor"  # --upload


MP = {12: (4000, 3000), 20: (5472, 3648)}


def _ids_digest(png: bytes) -> str:
    """sha256 of a mask's decoded class ids (the server stores masks re-encoded)."""
    from PIL import Image

    return hashlib.sha256(np.asarray(Image.open(io.BytesIO(png))).tobytes()).hexdigest()


PAINTED = (1 / 3, 2 / 3, 1.0)  # the rows painted in a first draft, later drafts, a submit


def _real_masks(truth: Path | None, frames: dict[str, tuple[int, int]]
                ) -> tuple[dict[str, list[bytes]], int]:
    """What the annotators upload on a real scene: per handed-out frame, its truth mask with
    the top third of the rows painted (a first draft), two thirds (later drafts), all of it
    (a submit); the rest 0 (unpainted). A frame without a truth mask gets ``_mask`` at its
    size. Returns the payloads by frame name and how many frames had a truth mask."""
    from PIL import Image

    out, found = {}, 0
    for k, (name, (w, h)) in enumerate(sorted(frames.items())):
        p = truth / f"{Path(name).stem}.png" if truth is not None else None
        if p is not None and p.is_file():
            full = np.asarray(Image.open(p))
            if full.shape != (h, w):
                raise RuntimeError(f"{p}: {full.shape[1]}x{full.shape[0]}, frame {name} is {w}x{h}")
            found += 1
            bodies = []
            for frac in PAINTED:
                m = full.copy()
                m[int(round(h * frac)):] = 0
                bodies.append(_encode(m))
            out[name] = bodies
        else:
            out[name] = [_mask(w, h, 1000 + 3 * k + j) for j in range(len(PAINTED))]
    return out, found


def _lift_lag(url: str, submits: list[dict], t_stop: float, timeout: float,
              fill_wait: float | None = None) -> dict:
    """Wait for the lifting queue to drain; per acknowledged submit: votes lag (queue entry
    created -> applied) and labels lag (-> first labels_updated event counting it)."""
    from sqlalchemy import create_engine, func, select

    from app.lifting.models import Event, LiftQueueEntry

    eng = create_engine(url)
    with eng.connect() as c:  # submits still waiting when the annotators stopped
        pending_at_stop = c.scalar(select(func.count()).select_from(LiftQueueEntry)
                                   .where(LiftQueueEntry.status == "pending"))
    t0 = time.monotonic()
    try:
        while True:
            with eng.connect() as c:
                pending = c.scalar(select(func.count()).select_from(LiftQueueEntry)
                                   .where(LiftQueueEntry.status == "pending"))
            if pending == 0 or time.monotonic() - t0 > timeout:
                break
            time.sleep(0.5)
        drain_s = time.monotonic() - t0
        from app.lifting.models import LiftStatus

        t_fill = time.monotonic()
        fill_wait = timeout if fill_wait is None else fill_wait
        while time.monotonic() - t_fill < fill_wait:  # the last fills publish their labels
            with eng.connect() as c:
                busy = c.scalar(select(func.count()).select_from(LiftStatus).where(
                    LiftStatus.fill_state != "idle"))
            if not busy:
                break
            time.sleep(0.5)
        time.sleep(1.0)
        with eng.connect() as c:
            rows = {r.version_id: r for r in c.execute(select(
                LiftQueueEntry.version_id, LiftQueueEntry.status, LiftQueueEntry.created_at,
                LiftQueueEntry.applied_at, LiftQueueEntry.applied_by, LiftQueueEntry.scene_id,
                LiftQueueEntry.frame_index))}
            events = c.execute(select(Event.scene_id, Event.created_at, Event.payload)
                               .where(Event.kind == "labels_updated").order_by(Event.id)).all()
    finally:
        eng.dispose()
    votes, labels, t_sub, missing, statuses, by = [], [], [], 0, {}, {}
    for sub in submits:
        r = rows.get(sub["version"])
        if r is None:
            missing += 1
            continue
        statuses[r.status] = statuses.get(r.status, 0) + 1
        by.setdefault(r.scene_id, set()).add(r.applied_by)
        if r.applied_at is None:
            continue
        votes.append((r.applied_at - r.created_at).total_seconds())
        t_sub.append(sub["t"])
        for ev in events:
            if ev.scene_id != r.scene_id or ev.created_at < r.created_at:
                continue
            tag = (ev.payload.get("versions") or {}).get(str(r.frame_index))
            if tag is not None and str(tag).isdigit() and int(tag) >= r.version_id:
                labels.append((ev.created_at - r.created_at).total_seconds())
                break
    slope = None
    if len(votes) >= 3 and np.ptp(t_sub) > 0:
        slope = round(float(np.polyfit(np.asarray(t_sub), np.asarray(votes), 1)[0]), 3)
    return {"votes_lag_s": [round(v, 3) for v in votes],
            "labels_lag_s": [round(v, 3) for v in labels],
            "votes_lag_p50_s": _pct(votes, 50), "votes_lag_p95_s": _pct(votes, 95),
            "votes_lag_max_s": round(max(votes), 3) if votes else None,
            "labels_lag_p50_s": _pct(labels, 50), "labels_lag_p95_s": _pct(labels, 95),
            "labels_lag_max_s": round(max(labels), 3) if labels else None,
            "labels_lag_counted": len(labels), "lag_slope": slope,
            "pending_at_stop": int(pending_at_stop), "pending_after_drain": int(pending),
            "drain_s": round(drain_s, 1), "lift_entries": statuses,
            "missing_from_lift_queue": missing,
            "lifting_workers_per_scene": {str(k): len(v) for k, v in by.items()}}


def run_config(backend: str, url: str, args: argparse.Namespace, tmp: Path, *, model: str,
               mp: int | None, lifting_workers: int, factor: float, seconds: float) -> dict:
    """One configuration; ``mp`` None: the scene comes from ``--source`` (``--workspace``)
    and the masks are of its frames' own size."""
    import httpx

    tag = f"{backend}_{model}_{mp}mp_l{lifting_workers}_f{factor:g}_{uuid.uuid4().hex[:4]}"
    data = tmp / tag
    roots = [tmp / "src"] + ([args.source] if args.source else []) + (
        [args.workspace] if args.workspace else [])
    env = app_env(data, url, roots, api_workers=args.api_workers, debounce=args.debounce)
    real = mp is None
    if real:  # the app imports the project, or copies the pre-built workspace (pipeline)
        src = args.workspace or args.source
    else:
        src = tmp / "src" / f"ws_{mp}"
    sids, scene_info = _seed(env, args.annotators, src, args.scenes, largest_only=real,
                             handout=args.handout)
    handed_out = scene_info.pop("handed_out")
    if real:
        width, height = max(handed_out.values(), key=lambda wh: wh[0] * wh[1])
        truth = _truth_dir(args.source, args.workspace)
        bank, n_truth = _real_masks(truth, handed_out)
        masks = [b for bodies in bank.values() for b in bodies]
        workspace = {"kind": "source", "source": str(args.source),
                     "workspace": str(args.workspace) if args.workspace else None,
                     **scene_info, "truth_masks": str(truth) if truth else None,
                     "frames_with_truth_mask": n_truth}
    else:
        width, height = MP[mp]
        bank = None
        masks = [_mask(width, height, s) for s in range(args.distinct)]
        workspace = {"kind": "fabricated (_workspace)", "points": args.points,
                     "frames": args.frames, **scene_info}
    digest = {id(m): _ids_digest(m) for m in masks}  # stored canonically: compare ids
    procs, base = start_server(env, api_workers=args.api_workers,
                               lifting_workers=lifting_workers)
    mem = _Mem([p.pid for p in procs], args.min_available_mb)
    try:
        time.sleep(2.0)  # the lifting workers take their slots
        saves: list[dict] = []  # {kind, s, version, fid, sha}
        prefill: list[tuple[float, int]] = []
        errors: list[str] = []
        lock = threading.Lock()
        barrier = threading.Barrier(args.annotators + 2)
        rng_all = random.Random(1)
        seeds = [rng_all.random() for _ in range(args.annotators)]
        reopened = [0]

        def body(i: int, k: int, name: str | None, stage: int) -> bytes:
            """The k-th save of annotator i; on a real scene the frame's own mask, ``stage``
            indexing PAINTED (0: first draft, 1: later drafts, 2: submit)."""
            if bank is None:
                return masks[(i * 7 + k) % len(masks)]
            return bank[name][stage]

        def put(c, fid: int, current: str, body: bytes, kind: str):  # noqa: ANN001, ANN202
            t0 = time.perf_counter()
            try:
                try:
                    r = c.put(f"/api/frames/{fid}/mask?kind={kind}", content=body,
                              headers={"If-Match": current, "Content-Type": "image/png"})
                except httpx.RemoteProtocolError:
                    # the server closed an idle keep-alive connection as the request left
                    # (uvicorn's 5 s keep-alive vs a 10-30 s cadence): sent again, as a
                    # browser does; If-Match makes a repeat of an applied save a 409
                    r = c.put(f"/api/frames/{fid}/mask?kind={kind}", content=body,
                              headers={"If-Match": current, "Content-Type": "image/png"})
            except httpx.HTTPError as e:
                with lock:
                    errors.append(f"PUT {kind}: {type(e).__name__} {e}")
                return None
            dt = time.perf_counter() - t0
            if r.status_code != 200:
                with lock:
                    errors.append(f"PUT {kind} {r.status_code} {r.text[:100]}")
                return None
            v = r.json()["version"]
            with lock:
                saves.append({"kind": kind, "s": dt, "version": v, "fid": fid,
                              "sha": digest[id(body)],
                              "t": time.monotonic() - t_start[0]})
            return str(v)

        def lease(c, i: int):  # noqa: ANN001, ANN202
            try:
                try:
                    r = c.post(f"/api/scenes/{sids[i % len(sids)]}/next")
                except httpx.RemoteProtocolError:  # idle keep-alive closed: once more
                    r = c.post(f"/api/scenes/{sids[i % len(sids)]}/next")
                if r.status_code == 204 and bank is not None:
                    return None, "empty", None  # every frame taken: realistic() reopens one
                if r.status_code != 200:
                    with lock:
                        errors.append(f"ann{i}: next {r.status_code} {r.text[:80]}")
                    return None, "none", None
                fr = r.json()
                t0 = time.perf_counter()
                p = c.get(f"/api/frames/{fr['id']}/prefill")
            except httpx.HTTPError as e:
                with lock:
                    errors.append(f"ann{i}: lease/prefill {type(e).__name__} {e}")
                return None, "none", None
            with lock:
                prefill.append((time.perf_counter() - t0, p.status_code))
            cur = "none" if fr.get("current_version") is None else str(fr["current_version"])
            return fr["id"], cur, fr["name"]

        def take_back(c, i: int, mine: list):  # noqa: ANN001, ANN202
            """A real scene has few frames of full size (the survey: 20 for 20 annotators):
            when ``next`` has none left, the annotator takes back the frame it submitted
            longest ago (``/reopen``, as in the editor) and goes on painting it."""
            if not mine:
                return None, "none", None
            fid, cur, name = mine.pop(0)
            try:
                r = c.post(f"/api/frames/{fid}/reopen")
            except httpx.HTTPError as e:
                r = None
                msg = f"{type(e).__name__} {e}"
            if r is None or r.status_code != 200:
                with lock:
                    errors.append(f"ann{i}: reopen {msg if r is None else r.status_code}")
                return None, "none", None
            with lock:
                reopened[0] += 1
            return fid, cur, name

        def b2b(i: int) -> None:
            with httpx.Client(base_url=base, timeout=300) as c:
                _login(c, f"ann{i:02d}")
                fid, current, name = lease(c, i)
                barrier.wait()
                if fid is None:
                    return
                k = 0
                while time.monotonic() < deadline[0]:
                    if k:
                        try:
                            c.post(f"/api/frames/{fid}/reopen")
                        except httpx.HTTPError as e:
                            with lock:
                                errors.append(f"reopen: {type(e).__name__} {e}")
                            return
                    current = put(c, fid, current, body(i, k, name, 2 - k % 2), "submitted")
                    if current is None:
                        return
                    k += 1

        def realistic(i: int) -> None:
            rng = random.Random(seeds[i])
            with httpx.Client(base_url=base, timeout=300) as c:
                _login(c, f"ann{i:02d}")
                barrier.wait()
                first = True
                k = 0
                mine: list = []  # (fid, submitted version, name), oldest first
                while time.monotonic() < deadline[0]:
                    fid, current, name = lease(c, i)
                    if current == "empty":
                        fid, current, name = take_back(c, i, mine)
                    if fid is None:
                        return
                    drafts = 0
                    on_frame = rng.uniform(120, 240) / factor  # minutes on a frame
                    if first:  # start somewhere inside the first frame: submits spread out
                        on_frame *= rng.random()
                        first = False
                    submit_at = time.monotonic() + on_frame
                    while True:
                        pause = rng.uniform(10, 30) / factor
                        if time.monotonic() + pause >= submit_at:
                            time.sleep(max(0.0, submit_at - time.monotonic()))
                            if time.monotonic() >= deadline[0]:
                                return
                            v = put(c, fid, current, body(i, k, name, 2), "submitted")
                            k += 1
                            if v is not None:
                                mine.append((fid, v, name))
                            break
                        time.sleep(pause)
                        if time.monotonic() >= deadline[0]:
                            return
                        nxt = put(c, fid, current, body(i, k, name, min(drafts, 1)), "draft")
                        k += 1
                        drafts += 1
                        if nxt is None:
                            return
                        current = nxt

        probe: list[tuple[float, float]] = []  # (GET /auth/me s, labels/status lag_s) 1/s

        def prober() -> None:  # what a client sees during the load: latency, the lag it is told
            with httpx.Client(base_url=base, timeout=300) as c:
                _login(c, "admin")
                barrier.wait()
                while time.monotonic() < deadline[0] and mem.tripped is None:
                    try:
                        t1 = time.perf_counter()
                        c.get("/api/auth/me")
                        dt = time.perf_counter() - t1
                        st = c.get(f"/api/scenes/{sids[0]}/labels/status").json()
                        probe.append((dt, float(st.get("lag_s", 0.0))))
                    except (httpx.HTTPError, ValueError):
                        probe.append((float("nan"), float("nan")))
                    time.sleep(1.0)

        target = b2b if model == "b2b" else realistic
        threads = [threading.Thread(target=target, args=(i,)) for i in range(args.annotators)]
        threads.append(threading.Thread(target=prober))
        for t in threads:
            t.start()
        t_start = [0.0]
        deadline = [float("inf")]
        barrier.wait()
        cpu = _Cpu([p.pid for p in procs])
        t_start[0] = time.monotonic()
        deadline[0] = t_start[0] + seconds
        for t in threads:
            t.join()
        wall = time.monotonic() - t_start[0]
        cpu_used = cpu.used()
        submits = [x for x in saves if x["kind"] == "submitted"]
        if mem.tripped is not None:  # the server was stopped: what the clients saw until then
            lat = [x["s"] for x in saves]
            return {"workspace": workspace, "model": model, "mask": f"{width}x{height}",
                    "annotators": args.annotators, "aborted": "host memory below "
                    f"--min-available-mb {args.min_available_mb:g}: server stopped",
                    "wall_s": round(wall, 1), "saves": len(saves), "submits": len(submits),
                    "save_p50_s": _pct(lat, 50), "save_p95_s": _pct(lat, 95),
                    **mem.stop(t_start[0], t_start[0] + wall),
                    "errors": errors[:5], "n_errors": len(errors)}
        lift = _lift_lag(url, submits, wall, timeout=max(300.0, seconds * 3),
                         fill_wait=30.0 if args.knee else None)  # the knee: votes lag
        cpu_total = cpu.used()  # including the drain
        lost = corrupted = 0
        with httpx.Client(base_url=base, timeout=300) as c:
            _login(c, "admin")
            for x in saves:
                r = c.get(f"/api/frames/{x['fid']}/mask/versions/{x['version']}")
                if r.status_code != 200:
                    lost += 1
                elif _ids_digest(r.content) != x["sha"]:
                    corrupted += 1
            base_lat = []
            for _ in range(30):
                t1 = time.perf_counter()
                c.get("/api/auth/me")
                base_lat.append(time.perf_counter() - t1)
        memory = mem.stop(t_start[0], t_start[0] + wall)  # includes the drain and read-back
        lat = [x["s"] for x in saves]
        lat_sub = [x["s"] for x in submits]
        pre_ok = [t for t, code in prefill if code == 200]
        n = max(1, len(saves))
        eq = args.annotators * (factor if model == "realistic" else float("nan"))
        return {
            "workspace": workspace,
            "model": model, "mask": f"{width}x{height}",
            "mp": mp if mp is not None else round(width * height / 1e6, 1),
            "annotators": args.annotators,
            "factor": factor if model == "realistic" else None,
            "equivalent_annotators": None if model == "b2b" else eq,
            "lifting_workers": lifting_workers, "api_workers": args.api_workers,
            "scenes": args.scenes, "seconds": seconds, "wall_s": round(wall, 1),
            "saves": len(saves), "submits": len(submits),
            "saves_per_s": round(len(saves) / wall, 3),
            "submits_per_s": round(len(submits) / wall, 3),
            "save_p50_s": _pct(lat, 50), "save_p95_s": _pct(lat, 95),
            "save_max_s": round(max(lat), 3) if lat else None,
            "submit_p95_s": _pct(lat_sub, 95),
            "prefill_p50_s": _pct(pre_ok, 50), "prefill_p95_s": _pct(pre_ok, 95),
            "prefills": len(prefill), "prefill_status": sorted({c for _, c in prefill}),
            "cpu_s_per_save_api": round(cpu_used["api"] / n, 3),
            "cpu_s_per_submit_lifting": round(cpu_total["lifting"] / max(1, len(submits)), 3),
            "cpu_util_during_load": round((cpu_used["api"] + cpu_used["lifting"]) / wall, 2),
            "baseline_get_me_p50_s": _pct(base_lat, 50),
            "during_get_me_p50_s": _pct([a for a, _ in probe if a == a], 50),
            "during_get_me_p95_s": _pct([a for a, _ in probe if a == a], 95),
            "told_lag_max_s": max((b for _, b in probe if b == b), default=None),
            "probe_failures": sum(1 for a, _ in probe if a != a),
            "mask_bytes_mean": int(np.mean([len(m) for m in masks])),
            "acknowledged": len(saves), "lost": lost + lift["missing_from_lift_queue"],
            "corrupted": corrupted, "load_avg_1min": round(os.getloadavg()[0], 1),
            **memory, "reopened": reopened[0],
            **lift, "errors": errors[:5], "n_errors": len(errors),
        }
    finally:
        mem.stop(0.0, 0.0)
        stop_server(procs)

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--annotators", type=int, default=20)
    ap.add_argument("--models", default="realistic,b2b", help="realistic and/or b2b")
    ap.add_argument("--mp", default="12", help="mask sizes: 12 (4000x3000), 20 (5472x3648)")
    ap.add_argument("--lifting-workers", default="1,2")
    ap.add_argument("--api-workers", type=int, default=2)
    ap.add_argument("--scenes", type=int, default=2)
    ap.add_argument("--factor", type=float, default=1.0,
                    help="realistic model: think times divided by this (1 = real time)")
    ap.add_argument("--seconds", type=float, default=240, help="realistic model: run length")
    ap.add_argument("--b2b-seconds", type=float, default=60, help="b2b model: run length")
    ap.add_argument("--knee", default="", help="realistic factors to sweep (e.g. 4,8,16)")
    ap.add_argument("--debounce", type=float, default=5.0, help="OCCUFLY_FILL_DEBOUNCE_S")
    ap.add_argument("--source", type=Path, default=None,
                    help="load against this project (what `occufly import` takes, e.g. an "
                         "`occufly synth` folder) instead of the fabricated workspace: the app "
                         "imports it (read-only) into its own data dir; only the frames at its "
                         "largest size are handed out and the masks are theirs (--mp ignored): "
                         "the synthetic truth masks (<project>/truth/masks) where there are")
    ap.add_argument("--workspace", type=Path, default=None,
                    help="with --source: a workspace already imported from it (`occufly import "
                         "SRC -w WS`); the app's import copies it instead of importing SRC again")
    ap.add_argument("--handout", type=int, default=0,
                    help="with --source: hand out at most this many of those frames (0: all; "
                         "e.g. 20 at bench scale to mirror the survey's 20 full-size frames)")
    ap.add_argument("--min-available-mb", type=float, default=1024,
                    help="stop the server (and report the run as aborted) when the host's "
                         "available memory falls below this")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--frames", type=int, default=120, help="frames per scene")
    ap.add_argument("--distinct", type=int, default=6, help="distinct mask payloads")
    ap.add_argument("--backend", default="postgresql", choices=("postgresql", "sqlite"))
    ap.add_argument("--upload", default="editor", choices=("editor", "pil1"),
                    help="mask encoding the clients send: the editor's (8-bit grey, rows None / "
                         "Up, deflate; the server stores it as it is) or PIL level 1 (the "
                         "server re-encodes it; the figures before 2026-12-04)")
    ap.add_argument("--out", default="", help="also write the JSON here")
    ap.add_argument("--postgres-url", default=os.environ.get(
        "OCCUFLY_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test"))
    args = ap.parse_args()
    if args.workspace and not args.source:
        ap.error("--workspace needs --source (the project it was imported from)")
    for a in ("source", "workspace"):
        if getattr(args, a) is not None:
            setattr(args, a, getattr(args, a).absolute())
            if not getattr(args, a).is_dir():
                ap.error(f"--{a} {getattr(args, a)}: no such folder")
    global UPLOAD
    UPLOAD = args.upload

    out: dict = {"benchmark": "api_load", "cpu_count": os.cpu_count(), "upload": args.upload,
                 "argv": sys.argv[1:], "runs": []}
    mps = [int(x) for x in args.mp.split(",") if x]
    if args.source:  # one size: the scene's own frames
        out["workspace"] = {"kind": "source", "source": str(args.source),
                            "workspace": str(args.workspace) if args.workspace else None,
                            "mp_requested": mps}
        mps = [None]
    else:
        out["workspace"] = {"kind": "fabricated (_workspace)", "points": args.points,
                            "frames": args.frames}
    lws = [int(x) for x in args.lifting_workers.split(",") if x]
    plan = []
    if args.knee:
        plan = [("realistic", mps[0], lw, float(f), args.seconds)
                for lw in lws for f in args.knee.split(",")]
    else:
        for model in args.models.split(","):
            for mp in mps:
                for lw in lws:
                    plan.append((model, mp, lw, args.factor if model == "realistic" else 1.0,
                                 args.seconds if model == "realistic" else args.b2b_seconds))
    with tempfile.TemporaryDirectory(prefix="occufly-bench-") as d:
        tmp = Path(d)
        for mp in sorted({p[1] for p in plan if p[1] is not None}):
            _workspace(tmp / "src" / f"ws_{mp}_raw", args.frames, *MP[mp], args.points)
            (tmp / "src" / f"ws_{mp}_raw" / "ws").rename(tmp / "src" / f"ws_{mp}")
        for model, mp, lw, factor, seconds in plan:
            if args.backend == "sqlite":
                if lw > 1:
                    continue  # SQLite: one lifting worker per data directory
                url = f"sqlite:///{tmp / uuid.uuid4().hex}.db"
                r = run_config("sqlite", url, args, tmp, model=model, mp=mp,
                               lifting_workers=lw, factor=factor, seconds=seconds)
            else:
                with _pg_database(args.postgres_url) as url:
                    r = run_config("postgresql", url, args, tmp, model=model, mp=mp,
                                   lifting_workers=lw, factor=factor, seconds=seconds)
            print(json.dumps(r), file=sys.stderr, flush=True)
            out["runs"].append(r)
            if args.out:
                Path(args.out).write_text(json.dumps(out, indent=1) + "\n")
    if args.knee:
        knee = [r for r in out["runs"] if (r["lag_slope"] or 0) > 0.2 and r["pending_at_stop"]]
        out["knee_equivalent_annotators"] = min(
            (r["equivalent_annotators"] for r in knee), default=None)
    print(json.dumps(out))
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
