"""The scene's quality report for the admin page (``GET /api/scenes/{sid}/quality``): computed
in the background, never in the request that asks for it.

The report takes one leave-one-out decision per annotated frame (:mod:`occufly.lifting.quality`):
a second on the ``small`` scene, minutes on a survey with 200 annotated frames. So a request
for the current labels (the workspace's stamp: labels, vote state, corrections; plus the point
truth file's) is answered from

1. this process's cache or the shared file ``<data dir>/cache/quality/scene_<id>.json`` when
   they hold the report of the current stamp (``cached: true``);
2. otherwise a computation of the current stamp is started (or joined) in a background thread
   and the request waits for it up to ``Settings.quality_wait_s``: done in time, the fresh
   report (``cached: false``);
3. still running: the last report computed for this scene, whatever its stamp, marked
   ``stale: true`` with ``computing: true`` (the page shows it and polls);
4. no report ever: ``None`` -- the route answers 202 ``{"computing": true}``.

One computation per scene at a time across API processes: the thread holds an exclusive lock
on ``scene_<id>.lock`` beside the file while it computes; a thread that waited for another
process's computation reads its result instead of computing the same stamp again. The thread
runs at the lifting fill's lowered priority (``OCCUFLY_FILL_NICE``): a save or a review
request waits on its own thread, the report does not.
"""

from __future__ import annotations

import fcntl
import json
import logging
import threading
import time
from pathlib import Path

from app.context import AppContext
from app.lifting.service import lower_thread_priority
from app.scenes.models import Scene
from occufly.fsutil import atomic_write_text
from occufly.lifting import quality as lifting_quality
from occufly.workspace import Workspace

log = logging.getLogger(__name__)

_CACHE: dict[tuple[int, str, str], dict] = {}
_CACHE_LOCK = threading.Lock()
_CACHE_MAX = 8
#: per (data dir, scene id): the thread computing its report in this process, the key asked for
_RUNNING: dict[tuple[str, int], threading.Thread] = {}
_WANTED: dict[tuple[str, int], tuple[str, str]] = {}


def _dir(ctx: AppContext) -> Path:
    return Path(ctx.settings.data_dir) / "cache" / "quality"


def _cache_file(ctx: AppContext, scene_id: int) -> Path:
    return _dir(ctx) / f"scene_{scene_id}.json"


def _key(ws: Path) -> tuple[str, str]:
    """(labels stamp, point truth file's mtime:size or '-')."""
    stamp = Workspace(ws).stamp()
    try:  # the truth kept with a workspace can arrive later (the calibration then shows)
        tst = (Workspace(ws).truth_dir / lifting_quality.TRUTH_POINTS).stat()
        truth_key = f"{tst.st_mtime_ns}:{tst.st_size}"
    except OSError:
        truth_key = "-"
    return stamp, truth_key


def _stored(ctx: AppContext, scene_id: int) -> tuple[list | None, dict | None]:
    """The shared file's (key, report), or (None, None)."""
    try:
        stored = json.loads(_cache_file(ctx, scene_id).read_text())
        return stored.get("key"), stored.get("report")
    except (OSError, ValueError, AttributeError):
        return None, None


def _remember(scene_id: int, key: tuple[str, str], report: dict) -> None:
    with _CACHE_LOCK:
        for k in [k for k in _CACHE if k[0] == scene_id]:
            del _CACHE[k]
        while len(_CACHE) >= _CACHE_MAX:
            del _CACHE[next(iter(_CACHE))]
        _CACHE[(scene_id, *key)] = report


def _current(ctx: AppContext, scene_id: int, key: tuple[str, str]) -> dict | None:
    with _CACHE_LOCK:
        hit = _CACHE.get((scene_id, *key))
    if hit is None:
        skey, report = _stored(ctx, scene_id)
        if report is not None and skey == list(key):
            _remember(scene_id, key, report)
            hit = report
    return hit


def _compute(ctx: AppContext, scene_id: int, ws: Path) -> None:
    """Compute the report of the workspace's current stamp and store it (file + this
    process), unless another process stored it while this one waited for the lock."""
    key = _key(ws)
    if _current(ctx, scene_id, key) is not None:
        return
    ws_scene = ctx.load_scene(str(ws))
    t0 = time.perf_counter()
    q = lifting_quality.quality_report(
        ws, ws_scene, truth=lifting_quality.workspace_truth(ws, ws_scene.n_points), policy={
            "include": ["accepted", "submitted", "imported"],
            "note": "the live labels: every voting version (submitted, accepted, imported)"})
    q["labels_stamp"] = key[0]
    log.info("quality report of scene %s computed in %.1f s", scene_id, time.perf_counter() - t0)
    try:
        atomic_write_text(_cache_file(ctx, scene_id), json.dumps({"key": list(key), "report": q}))
    except OSError:  # a read-only data dir: the in-process cache still holds it
        log.warning("quality report of scene %s: cannot write the shared cache", scene_id)
    _remember(scene_id, key, q)


def compute_locked(ctx: AppContext, scene_id: int, ws: Path) -> None:
    """Compute and store the report of the workspace's current stamp, once across processes
    (a process that waited for another's computation of the same stamp reads it). The
    review's after-fill refresh calls it in its child process (:func:`app.bootstrap.
    run_review_refresh`), so the admin page finds the report of the new labels computed."""
    d = _dir(ctx)
    d.mkdir(parents=True, exist_ok=True)
    with open(d / f"scene_{scene_id}.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another process's computation first
        try:
            _compute(ctx, scene_id, ws)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def _worker(ctx: AppContext, scene_id: int, ws: Path) -> None:
    lower_thread_priority(ctx.settings.fill_nice)
    job = (str(ctx.settings.data_dir), scene_id)
    try:
        while True:
            with _CACHE_LOCK:
                wanted = _WANTED.get(job)
            compute_locked(ctx, scene_id, ws)
            with _CACHE_LOCK:
                newest = _WANTED.get(job)
            # asked again for newer labels while this one ran (and nobody computed them): go on
            if newest != wanted and newest is not None and _current(ctx, scene_id, newest) is None:
                continue
            with _CACHE_LOCK:
                if _WANTED.get(job) == newest:
                    _RUNNING.pop(job, None)
                    return
    except Exception:  # noqa: BLE001 - a failed report is logged; the next request retries
        log.exception("quality report of scene %s failed", scene_id)
        with _CACHE_LOCK:
            _RUNNING.pop(job, None)


def _start(ctx: AppContext, scene_id: int, ws: Path, key: tuple[str, str]) -> threading.Thread:
    job = (str(ctx.settings.data_dir), scene_id)
    with _CACHE_LOCK:
        _WANTED[job] = key
        th = _RUNNING.get(job)
        if th is None or not th.is_alive():
            th = threading.Thread(target=_worker, args=(ctx, scene_id, ws), daemon=True,
                                  name=f"occufly-quality-{scene_id}")
            _RUNNING[job] = th
            th.start()
        return th


def scene_quality(ctx: AppContext, scene: Scene, *, wait_s: float | None = None) -> dict | None:
    """The quality report of the scene's live labels (see the module docstring): the current
    one (``cached`` true / false), the last one (``stale``, ``computing``), or None while the
    first is computed."""
    ws = Path(scene.workspace)
    key = _key(ws)
    hit = _current(ctx, scene.id, key)
    if hit is not None:
        return {**hit, "cached": True, "stale": False, "computing": False}
    wait = ctx.settings.quality_wait_s if wait_s is None else wait_s
    end = time.monotonic() + wait
    _start(ctx, scene.id, ws, key)
    while True:
        hit = _current(ctx, scene.id, key)
        if hit is not None:
            return {**hit, "cached": False, "stale": False, "computing": False}
        if time.monotonic() >= end:
            break
        time.sleep(min(0.05, max(0.0, end - time.monotonic())))
    with _CACHE_LOCK:
        last = next((v for k, v in reversed(_CACHE.items()) if k[0] == scene.id), None)
    if last is None:
        _skey, last = _stored(ctx, scene.id)
    if last is None:
        return None
    return {**last, "cached": True, "stale": True, "computing": True,
            "current_stamp": key[0]}
