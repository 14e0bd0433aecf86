"""Review: render-back agreement, accept/reject, review items with comment threads."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, QhullError
from sqlalchemy import func, or_, select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from app import pipeline
from app.annotations import service as annotations
from app.annotations.models import MaskVersion
from app.context import AppContext
from app.db import utcnow
from app.errors import Conflict, Forbidden, Invalid, NotFound, TooManyAttempts
from app.notifications.service import notify_frame_people
from app.review.disk_cache import DiskCache, decode, encode
from app.review.models import ReviewComment, ReviewItem, SuspectMark
from app.scenes.membership import check_member
from app.scenes.models import Frame, Scene
from app.shared_limits import ITEM_COMMENTS, REVIEW_QUOTA, serialise
from app.users.models import User
from occufly import render
from occufly.lifting import VoteStore, load_labels
from occufly.lifting import loo as lifting_loo
from occufly.lifting.suspects import SuspectParams, find_suspects
from occufly.render import scene_point_spacing
from occufly.workspace import Workspace

log = logging.getLogger("occufly.review")


# ---- render-back and agreement --------------------------------------------------------------
def _mask_array(ctx: AppContext, scene: Scene, sha256: str) -> np.ndarray:
    return pipeline.stored_mask_ids(ctx.store.get(sha256), ctx.load_scene(scene.workspace).taxonomy)


rendered = annotations.rendered  # the prefill render lives with the annotations


class _ReviewCache:
    """The last few frames' review computations (figures, neighbours, disagreement PNG; the
    LOO, confident-LOO and self renderings are spent in them), keyed by the
    frame, its mask and the stamps (mtime, size) of every file they are computed from: the
    votes, the frame's own votes, the labels and the corrections. The reviewer page asks for
    the agreement and the disagreement image of a frame at once: they share one computation
    (a second request for a key being computed waits for it).

    With ``shared`` (a :class:`~app.review.disk_cache.DiskCache`) and a ``data_dir``, a value
    not in this process's memory is read from, or computed once into, the data dir's shared
    folder: the other API processes, the lifting worker's after-fill refresh and the
    prefetch threads of every process then compute each frame's review once between them."""

    def __init__(self, size: int = 3, shared: DiskCache | None = None) -> None:
        self.size = size
        self.shared = shared
        self._lock = threading.Lock()
        self._items: OrderedDict = OrderedDict()
        self._busy: dict = {}

    def get(self, key, compute, data_dir=None, valid=None):  # noqa: ANN001
        """The value of ``key``, computed once (concurrent callers wait for it). ``valid``:
        called after a computation; where it returns False the value is returned but not
        kept (its inputs changed while it was computed)."""
        if self.shared is not None and data_dir is not None:
            local = compute

            def compute():  # noqa: ANN202
                return self.shared.get(data_dir, key, local, valid=valid)
        while True:
            with self._lock:
                if key in self._items:
                    self._items.move_to_end(key)
                    return self._items[key]
                ev = self._busy.get(key)
                if ev is None:
                    ev = self._busy[key] = threading.Event()
                    break
            ev.wait()
        try:
            val = compute()
            if valid is None or valid():
                self._remember(key, val)
            return val
        finally:
            with self._lock:
                self._busy.pop(key, None)
            ev.set()

    def _remember(self, key, value) -> None:  # noqa: ANN001
        with self._lock:
            self._items[key] = value
            self._items.move_to_end(key)
            while len(self._items) > self.size:
                self._items.popitem(last=False)

    def put(self, key, value, data_dir=None) -> None:  # noqa: ANN001
        """Store a value computed elsewhere (in memory, and in the shared folder)."""
        self._remember(key, value)
        if self.shared is not None and data_dir is not None:
            self.shared.put(data_dir, key, value)

    def peek(self, key, data_dir=None):  # noqa: ANN001
        """The value of ``key`` in memory or in the shared folder, else None (nothing is
        computed)."""
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        if self.shared is None or data_dir is None:
            return None
        v = self.shared.read(data_dir, key)
        if v is not None:
            self._remember(key, v)
        return v

    def has(self, key, data_dir=None) -> bool:  # noqa: ANN001
        with self._lock:
            if key in self._items:
                return True
        return self.shared is not None and data_dir is not None and self.shared.has(data_dir, key)

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


# the review list's top frames whose review is computed in the background after each fill
# (refresh_agreement); the caches keep them and the frame open beside them
PREFETCH_FRAMES = 4
_CACHE = _ReviewCache(PREFETCH_FRAMES + 2, shared=DiskCache("review"))
_RENDER_CACHE = _ReviewCache(PREFETCH_FRAMES + 2, shared=DiskCache("review_render"))
# the part of each review that needs no labels (review_images): it outlives fills
_LOO_CACHE = _ReviewCache(PREFETCH_FRAMES + 2, shared=DiskCache("review_loo"))
# the suspects list of the scenes' current labels (issue 38: seconds of CPU on a survey, so it
# is computed after each fill, not when a reviewer opens the tab); its own cache, so that the
# frames warmed after it do not push it out; shared between processes and kept on disk, so an
# API process that did not run the fill, or one started after it (a restart, a deploy), reads
# it instead of computing it again (a survey's list: ~65 s of CPU)
_SUSPECT_CACHE = _ReviewCache(4, shared=DiskCache("suspects"))


def _stamp(*paths: Path) -> tuple:
    out = []
    for p in paths:
        try:
            st = os.stat(p)
            out.append((st.st_mtime_ns, st.st_size))
        except OSError:
            out.append(None)
    return tuple(out)


# the frames whose votes can reach a frame's leave-one-out labels (static geometry: ~0.1-0.2 s
# on a survey frame), keyed by the scene's files' stamps: in this process's memory and in
# the processes' shared folder (the after-fill refresh computes them for the list's frames)
_REACH: OrderedDict = OrderedDict()
_REACH_SIZE = 8192
_REACH_LOCK = threading.Lock()
_REACH_DISK = DiskCache("reach", max_bytes=64 * 2**20)


def _reaching_frames(ctx: AppContext, scene: Scene, frame: Frame) -> np.ndarray | None:
    w = Workspace(scene.workspace)
    rk = (str(scene.workspace), frame.index, _stamp(w.scene_json, w.points_xyz))
    with _REACH_LOCK:
        if rk in _REACH:
            _REACH.move_to_end(rk)
            return _REACH[rk]

    def compute() -> dict:
        ws_scene = ctx.load_scene(scene.workspace)
        g = lifting_loo.frames_reaching(ws_scene, frame.index,
                                        lifting_loo.loo_point_ids(ws_scene, frame.index))
        return {"frames": None if g is None else [int(x) for x in g]}

    got = _REACH_DISK.get(ctx.settings.data_dir, rk, compute)["frames"]
    g = None if got is None else np.asarray(got, np.int64)
    with _REACH_LOCK:
        _REACH[rk] = g
        while len(_REACH) > _REACH_SIZE:
            _REACH.popitem(last=False)
    return g


def _loo_key(ctx: AppContext, scene: Scene, frame: Frame, v) -> tuple:  # noqa: ANN001
    """The key of what a frame's review computes without the scene's labels (the
    leave-one-out figures, the neighbours, the disagreement overlay): the frame, its mask
    version and the stamps of every file that is computed from -- the frame's own votes, the
    vote files of the frames that can vote at its leave-one-out points
    (:func:`occufly.lifting.loo.frames_reaching`; a neighbour's votes withdrawn on a
    rejection change them), the vote counts' file (its inode and size: replaced wholesale by
    a rebuild) and the corrections. A save of a frame that cannot reach this one's points,
    and a fill, leave it valid. Where the reaching frames cannot be bounded (a distorted
    camera), the vote counts' stamp instead: any save invalidates it."""
    w = Workspace(scene.workspace)
    reach = _reaching_frames(ctx, scene, frame)
    try:
        st = os.stat(w.votes)
        votes = (st.st_ino, st.st_size)
    except OSError:
        votes = None
    if reach is None:
        votes = (votes, _stamp(w.votes))
    else:
        votes = (votes, _stamp(*(w.lifting_frame(int(g)) for g in reach)))
    return (str(scene.workspace), frame.index, v.id, v.sha256, votes,
            _stamp(w.lifting_frame(frame.index), w.corrections_dir / "overrides.npz"))


def _review_key(ctx: AppContext, scene: Scene, frame: Frame, v) -> tuple:  # noqa: ANN001
    """The key of a frame's whole review: :func:`_loo_key` and the stamps of the labels and
    their stats (the self-agreement, the labels' rendering)."""
    w = Workspace(scene.workspace)
    return (_loo_key(ctx, scene, frame, v), _stamp(w.labels_path, w.labels_stats_path))


def _votes_settled(scene: Scene) -> bool:
    """Whether no vote update is under way in the scene (the vote state is not marked dirty):
    an update writes the frame's vote file first, then the counts, so a key read while one
    is under way may name a vote file whose counts are not in yet."""
    try:
        st = json.loads(Workspace(scene.workspace).lifting_state.read_text())
    except (OSError, ValueError):
        return False
    return not st.get("dirty", False)  # as VoteStore.open reads it


def review_images(ctx: AppContext, session: Session, scene: Scene, frame: Frame) -> dict:
    """The frame's review (``version``, ``figures``, ``neighbours``, ``disagreement_png``;
    :func:`compute_review`), cached in two parts: what needs no labels under
    :func:`_loo_key` (a save of a frame that cannot reach it and a fill leave it), the whole
    under :func:`_review_key`. After a fill only the self-agreement and the labels' rendering
    are computed again (:func:`compute_self`)."""
    v = annotations.current_version(session=session, frame=frame)
    key = _review_key(ctx, scene, frame, v)
    settled = _votes_settled(scene)  # after the key: an update begun before it shows here
    data_dir = ctx.settings.data_dir

    def valid() -> bool:
        # cached only if no update was under way when the key was read and none of the
        # files it names changed during the computation (else it is answered, not kept)
        return settled and _review_key(ctx, scene, frame, v) == key

    def valid_loo() -> bool:
        return settled and _loo_key(ctx, scene, frame, v) == key[0]

    def compute() -> dict:
        ws_scene = ctx.load_scene(scene.workspace)
        rkey = _render_key(scene, frame)  # before the labels are read: never newer than them
        labels = annotations.current_labels(ctx, scene)
        if labels is None:
            raise NotFound(f"scene {scene.id} has no lifted labels yet")

        def mask() -> np.ndarray:
            return _mask_array(ctx, scene, v.sha256)

        part = _LOO_CACHE.peek(key[0], data_dir)
        if part is None:
            out = compute_review(ws_scene, scene.workspace, frame.index, mask, labels)
            part = {k: out[k] for k in ("figures", "neighbours", "disagreement_png")}
            part["figures"] = {k: x for k, x in part["figures"].items() if k not in SELF_FIGURES}
            if valid_loo():
                _LOO_CACHE.put(key[0], part, data_dir)
            own = {k: out["figures"][k] for k in SELF_FIGURES if k in out["figures"]}
        else:
            out = compute_self(ws_scene, frame.index, mask, labels)
            own = out["figures"]
        if out.get("render_png") is not None:
            _RENDER_CACHE.put(rkey, out["render_png"], data_dir)
        return {"version": v.id, "figures": {**part["figures"], **own},
                "neighbours": part["neighbours"], "disagreement_png": part["disagreement_png"]}

    return _CACHE.get(key, compute, data_dir, valid=valid)


# the figures of a review computed from the scene's labels (the rest needs none)
SELF_FIGURES = ("self_agreement", "self_pixels")


def compute_self(ws_scene, frame_index: int,  # noqa: ANN001
                 mask: np.ndarray | Callable[[], np.ndarray], labels: np.ndarray) -> dict:
    """The part of a frame's review that the scene's labels decide, alone (the rest is
    cached: :func:`review_images`): ``figures`` (``self_agreement``, ``self_pixels``) and,
    for a full-size mask, the labels' rendering as the page's /render PNG (``render_png``,
    else None) -- one label render, no leave-one-out labels."""
    mask = mask() if callable(mask) else mask
    img = render.render_many_for_mask(ws_scene, [np.asarray(labels, np.uint8)], frame_index,
                                      mask.shape)[0]
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="occufly-review") as pool:
        cam = ws_scene.frames[frame_index].camera
        png_fut = (pool.submit(pipeline.encode_png, np.asarray(img, np.uint8))
                   if mask.shape == (cam.height, cam.width) else None)
        figures = lifting_loo.self_figures(mask, img, ws_scene)
        return {"figures": figures, "render_png": None if png_fut is None else png_fut.result()}


def compute_review(ws_scene, workspace: str | Path, frame_index: int,  # noqa: ANN001
                   mask: np.ndarray | Callable[[], np.ndarray], labels: np.ndarray) -> dict:
    """What a frame's review shows, computed (:func:`review_images` caches it): the figures
    of ``mask`` (or of what the callable ``mask`` returns: it is decoded beside the
    leave-one-out labels) against the labels decided without the frame's votes (``figures``), the
    frames whose votes contradict it (``neighbours``), the disagreement overlay
    (``disagreement_png``) and, for a full-size mask, the labels' rendering as the page's
    /render PNG (``render_png``, else None).

    The leave-one-out labels, the renderings and the neighbours come from
    :func:`occufly.lifting.loo.review_renders` (what needs no labels beside the labels); the
    /render PNG's deflate runs beside the overlay and the figures."""
    mask, _loo, imgs, nb = lifting_loo.review_renders(workspace, ws_scene, frame_index, mask,
                                                      self_labels=labels, neighbours=True)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="occufly-review") as pool:
        cam = ws_scene.frames[frame_index].camera
        png_fut = None
        if mask.shape == (cam.height, cam.width):
            # the labels' full-size rendering is the page's /render image (render_png): the
            # same pixels (render_many_for_mask), so that request need not render it again
            png_fut = pool.submit(pipeline.encode_png, np.asarray(imgs["self"], np.uint8))
        # the disagreement image is encoded once, with the figures: the page asks for both,
        # and an entry keeps a few MB instead of the frame-sized renderings
        # (as a palette PNG: the RGBA overlay's pixels at a quarter of the bytes to encode)
        idx = render.disagreement_indices(mask, imgs["loo"], ws_scene.taxonomy)
        png = pipeline.encode_png_palette(idx, render.disagreement_palette(ws_scene.taxonomy))
        # the figures once, with the entry: a cached agreement request only reads them
        figures = lifting_loo.loo_agreement(mask, imgs["loo"], ws_scene,
                                            self_rendered=imgs["self"],
                                            confident_rendered=imgs["confident"])
        del imgs, idx
        return {"figures": figures, "neighbours": nb, "disagreement_png": png,
                "render_png": None if png_fut is None else png_fut.result()}


def cached_review(ctx: AppContext, scene: Scene, frame: Frame, session: Session,
                  data_dir=None) -> bool:  # noqa: ANN001
    """Whether the frame's current mask's review computation is in this process's cache, or
    with ``data_dir`` in the processes' shared one (tests, the background warm-up)."""
    v = annotations.current_version(session=session, frame=frame)
    return _CACHE.has(_review_key(ctx, scene, frame, v), data_dir)


def frame_agreement(ctx: AppContext, session: Session, scene: Scene, frame: Frame) -> dict:
    """Leave-one-out agreement of the frame's current mask (``agreement``, None with
    ``status="not_enough_independent_views"`` when the independent coverage is below
    ``settings.min_independent_coverage``), the old self-agreement apart, the independent
    coverage and painted share; stored on the frame (the review list sorts by it)."""
    r = review_images(ctx, session, scene, frame)
    vid, res = r["version"], r["figures"]
    value = res["agreement"]
    enough = res["independent_coverage"] >= ctx.settings.min_independent_coverage
    status = "ok" if enough and value is not None else "not_enough_independent_views"
    if status != "ok":
        value = None
    frame.agreement = value
    frame.self_agreement = res.get("self_agreement")
    frame.independent_coverage = float(res["independent_coverage"])
    frame.painted_share = float(res["painted_share"])
    frame.review_score = res["review_score"]
    session.commit()
    per_class = {str(k): v for k, v in (res.get("per_class") or {}).items()}
    return {"agreement": value, "status": status, "loo_agreement": res["agreement"],
            "self_agreement": res.get("self_agreement"),
            "independent_coverage": float(res["independent_coverage"]),
            "painted_share": float(res["painted_share"]),
            "independent_pixels": int(res["independent_pixels"]),
            "painted_pixels": int(res["painted_pixels"]),
            "min_independent_coverage": float(ctx.settings.min_independent_coverage),
            "review_score": res["review_score"], "area_agreement": res["area_agreement"],
            "area_share": float(res["area_share"]), "shift_gain": float(res["shift_gain"]),
            "pixels": int(res["independent_pixels"]), "per_class": per_class, "version": vid,
            "neighbours": _neighbours_out(session, scene, r["neighbours"])}


def _neighbours_out(session: Session, scene: Scene, rows: list[dict]) -> list[dict]:
    """The frames whose votes contradict this one's (:func:`occufly.lifting.loo.
    disagreeing_neighbours`), with their ids and names."""
    if not rows:
        return []
    by_index = {f.index: f for f in session.scalars(
        select(Frame).where(Frame.scene_id == scene.id,
                            Frame.index.in_([r["frame_index"] for r in rows])))}
    out = []
    for r in rows:
        f = by_index.get(r["frame_index"])
        if f is not None:
            out.append({"frame_id": f.id, "name": f.name, **r})
    return out


def disagreement_png(ctx: AppContext, session: Session, scene: Scene, frame: Frame) -> bytes:
    """The disagreement overlay of the mask against the leave-one-out rendering (PNG)."""
    return review_images(ctx, session, scene, frame)["disagreement_png"]


def render_png(ctx: AppContext, scene: Scene, frame: Frame, *, downscale: int = 1) -> bytes:
    """The lifted labels rendered into the frame (:func:`rendered`), PNG; full size cached
    per labels stamp (the reviewer page fetches it with the agreement)."""
    if downscale != 1:
        return pipeline.encode_png(rendered(ctx, scene, frame, downscale=downscale))
    return _RENDER_CACHE.get(_render_key(scene, frame),
                             lambda: pipeline.encode_png(rendered(ctx, scene, frame)),
                             ctx.settings.data_dir)


def _render_key(scene: Scene, frame: Frame) -> tuple:
    w = Workspace(scene.workspace)
    return (str(scene.workspace), frame.index,
            _stamp(w.labels_path, w.labels_stats_path, w.corrections_dir / "overrides.npz"))


def _list_order(session: Session, scene: Scene, limit: int) -> list[Frame]:
    """The frames with a current submitted / reviewed mask in the review list's order
    (``GET /scenes/{sid}/frames?sort=disagreement``: ranking score, highest first)."""
    return list(session.scalars(
        select(Frame).where(Frame.scene_id == scene.id, Frame.current_version_id.is_not(None),
                            Frame.state.in_(("submitted", "accepted", "rejected")))
        .order_by(Frame.review_score.is_(None), Frame.review_score.desc(),
                  Frame.agreement.is_(None), Frame.agreement,
                  Frame.independent_coverage.is_(None), Frame.independent_coverage,
                  Frame.index).limit(limit)))


_PREFETCH_LOCK = threading.Lock()
_PREFETCH_BUSY: set = set()  # (scene id, frame id) being computed in the background
PREFETCH_NEXT = 2  # frames after the one opened whose review is computed in the background


def _warm(ctx: AppContext, scene_id: int, frame_ids: list[int], *,
          suspects: bool = False) -> None:
    """Compute the review (figures, disagreement PNG, labels rendering) of ``frame_ids`` in
    the cache, in order, skipping those already there (a background thread's body); with
    ``suspects`` the scene's suspects list first."""
    try:
        with ctx.sessions() as s:
            scene = s.get(Scene, scene_id)
            if suspects and scene is not None:
                _warm_suspects(ctx, scene)
            for fid in frame_ids:
                f = s.get(Frame, fid)
                if scene is None or f is None or f.current_version_id is None:
                    continue
                try:
                    if not cached_review(ctx, scene, f, s, ctx.settings.data_dir):
                        frame_agreement(ctx, s, scene, f)
                    render_png(ctx, scene, f)
                except Exception:  # noqa: BLE001 - best effort: the request computes it then
                    s.rollback()
    except Exception:  # noqa: BLE001 - the database went away (shutdown): nothing to warm
        pass
    finally:
        with _PREFETCH_LOCK:
            for fid in frame_ids:
                _PREFETCH_BUSY.discard((scene_id, fid))


def _start_warm(ctx: AppContext, scene_id: int, frame_ids: list[int], *,
                suspects: bool = False) -> None:
    with _PREFETCH_LOCK:
        todo = [f for f in frame_ids if (scene_id, f) not in _PREFETCH_BUSY]
        _PREFETCH_BUSY.update((scene_id, f) for f in todo)
    if todo or suspects:
        threading.Thread(target=_warm, args=(ctx, scene_id, todo), kwargs={"suspects": suspects},
                         daemon=True, name="occufly-review-prefetch").start()


def prefetch_next(ctx: AppContext, session: Session, scene: Scene, frame: Frame) -> None:
    """The reviewer opened ``frame``: compute the review of the ``PREFETCH_NEXT`` frames after
    it in the review list in a background thread, so that N (next frame) finds them computed."""
    rows = _list_order(session, scene, 200)
    ids = [f.id for f in rows]
    if frame.id in ids:
        i = ids.index(frame.id)
        _start_warm(ctx, scene.id, ids[i + 1:i + 1 + PREFETCH_NEXT])


# scenes of at least this many points have their review path warmed when a server process
# starts (warm_process_start); smaller ones cost a first request little
WARM_MIN_POINTS = 5_000_000


def warm_process_start(ctx: AppContext) -> threading.Thread | None:
    """A server process's first review of a survey-sized scene paid 11-12 s, then (compiled
    point bins) 2.3-3.1 s, against 0.9-1.1 s for the next: the frustum cull's bins of the
    whole cloud, numba's cached kernels, the first reads of the votes and features. This
    starts a background thread that runs one review computation (not cached: the process's
    state is what it is for) of the review list's top frame of the largest ready scene of at
    least :data:`WARM_MIN_POINTS` points with lifted labels. Returns the thread, or None
    when there is no such scene or frame."""
    try:
        with ctx.sessions() as s:
            pick = None
            for scene in s.scalars(select(Scene).where(Scene.status == "ready",
                                                       Scene.n_points >= WARM_MIN_POINTS)
                                   .order_by(Scene.n_points.desc(), Scene.id)):
                if not Workspace(scene.workspace).labels_path.is_file():
                    continue
                top = _list_order(s, scene, 1)
                v = annotations.current_version(session=s, frame=top[0]) if top else None
                if v is not None:
                    pick = (scene.workspace, top[0].index, v.sha256, scene.id)
                    break
    except Exception:  # noqa: BLE001 - no database yet (a first start): nothing to warm
        log.debug("review warm-up: no scene", exc_info=True)
        return None
    if pick is None:
        return None

    def run() -> None:
        workspace, index, sha, scene_id = pick
        t = time.perf_counter()
        try:
            with ctx.sessions() as s:
                scene = s.get(Scene, scene_id)
                if scene is None:
                    return
                ws_scene = ctx.load_scene(workspace)
                labels = annotations.current_labels(ctx, scene)  # as review_images reads them
                if labels is None:
                    return
                compute_review(ws_scene, workspace, index,
                               lambda: _mask_array(ctx, scene, sha), labels)
            log.info("review warm-up of scene %s (frame %d): %.1f s", scene_id, index,
                     time.perf_counter() - t)
        except Exception:  # noqa: BLE001 - best effort: the first request computes it then
            log.warning("review warm-up of scene %s failed", scene_id, exc_info=True)

    th = threading.Thread(target=run, daemon=True, name="occufly-review-warm-start")
    th.start()
    return th


def warm_on_labels(ctx: AppContext):  # noqa: ANN201
    """A ``labels_updated`` subscriber for a server process that does not run the lifting
    worker (``OCCUFLY_LIFTING=external``, or another process owns it): the worker refreshes
    the stored figures in its own process, this computes the list's top
    ``PREFETCH_FRAMES`` into this process's cache, in a background thread."""

    def on_event(msg) -> None:  # noqa: ANN001
        if msg.scene_id is None:
            return
        with ctx.sessions() as s:
            scene = s.get(Scene, msg.scene_id)
            if scene is None:
                return
            top = [f.id for f in _list_order(s, scene, PREFETCH_FRAMES)]
        _start_warm(ctx, msg.scene_id, top, suspects=True)

    return on_event


AGREEMENT_REFRESH_FRAMES = 200  # frames whose stored agreement a fill recomputes


def refresh_after_fill(ctx: AppContext, msg, stop: threading.Event) -> None:  # noqa: ANN001
    """The ``labels_updated`` subscriber of the process whose lifting service owns the scene
    (wired by :func:`app.bootstrap.build_lifting_service`; by default it runs
    :func:`refresh_scene` in a child process instead: :mod:`app.review.refresher`)."""
    refresh_scene(ctx, msg.scene_id, stop)


def refresh_scene(ctx: AppContext, scene_id: int, stop: threading.Event) -> None:
    """After a fill: the suspects list, then the stored per-frame agreement of submitted /
    reviewed frames against the new labels, leaving the review list's top frames computed in
    the review cache (:func:`refresh_agreement`); stops between two frames when ``stop``
    is set."""
    with ctx.sessions() as s:
        scene = s.get(Scene, scene_id)
        if scene is not None:
            _warm_suspects(ctx, scene)
            refresh_agreement(ctx, s, scene, stop=stop, log=log)


def refresh_agreement(ctx: AppContext, session: Session, scene: Scene, *,
                      limit: int = AGREEMENT_REFRESH_FRAMES,
                      stop: threading.Event | None = None, log=None) -> list[int]:  # noqa: ANN001
    """After a fill (the lifting worker's ``labels_updated`` subscriber): recompute the stored
    agreement of every submitted / reviewed frame (the list's sort) and leave the review of
    the top ``PREFETCH_FRAMES`` of the list computed in the cache, so that opening them
    costs no computation (issue 40, defect 6). The frames are computed in reverse list order
    (the top last, so they stay in the LRU cache); where the new scores change the top, its
    new members are computed again. Returns the frame ids left warm, top first."""

    def one(f: Frame, *, warm: bool) -> None:
        try:
            frame_agreement(ctx, session, scene, f)
            if warm:  # the labels' rendering the page shows beside the mask
                render_png(ctx, scene, f)
        except Exception:  # noqa: BLE001 - a frame that cannot be rendered keeps its value
            if log is not None:
                log.warning("agreement of frame %s failed", f.id, exc_info=True)
            session.rollback()

    frames = _list_order(session, scene, limit)
    for i in range(len(frames) - 1, -1, -1):
        if stop is not None and stop.is_set():
            return []
        one(frames[i], warm=i < PREFETCH_FRAMES)
    top = _list_order(session, scene, PREFETCH_FRAMES)  # the new scores' top
    for f in reversed(top):
        if stop is not None and stop.is_set():
            return []
        if not cached_review(ctx, scene, f, session, ctx.settings.data_dir) \
                or not _RENDER_CACHE.has(_render_key(scene, f), ctx.settings.data_dir):
            one(f, warm=True)
    return [f.id for f in top]


def evaluate_scene(*, ctx: AppContext, scene_id: int, frames: list[int] | None = None,
                   progress=None) -> dict:
    """Leave-one-out 2D agreement of every frame with a current mask (the eval job); frames
    without enough independent views are listed with agreement None and left out of the
    pixel-weighted total."""
    with ctx.sessions() as s:
        scene = s.get(Scene, scene_id)
        q = select(Frame).where(Frame.scene_id == scene_id, Frame.current_version_id.is_not(None))
        if frames:
            q = q.where(Frame.index.in_(frames))
        rows = list(s.scalars(q.order_by(Frame.index)))
        per_frame = []
        total_px = self_w = 0
        agree_px = self_px = 0.0
        for i, f in enumerate(rows):
            if progress:
                progress(i / max(len(rows), 1), f"agreement {f.name}")
            r = frame_agreement(ctx, s, scene, f)
            per_frame.append({"frame_id": f.id, "index": f.index, "name": f.name,
                              "agreement": r["agreement"], "pixels": r["pixels"],
                              "status": r["status"], "self_agreement": r["self_agreement"],
                              "independent_coverage": r["independent_coverage"],
                              "painted_share": r["painted_share"],
                              "review_score": r["review_score"]})
            if r["agreement"] is not None:
                total_px += r["pixels"]
                agree_px += r["agreement"] * r["pixels"]
            if r["self_agreement"] is not None:
                self_w += r["painted_pixels"]
                self_px += r["self_agreement"] * r["painted_pixels"]
    return {"table": "agreement_2d", "frames": per_frame, "n_frames": len(per_frame),
            "pixels": total_px, "agreement": agree_px / total_px if total_px else None,
            "self_agreement": self_px / self_w if self_w else None,
            "n_not_enough_independent_views": sum(
                f["status"] == "not_enough_independent_views" for f in per_frame)}


def _suspect_rows(ctx: AppContext, scene: Scene) -> list[dict]:
    """Every suspect of the scene's current labels, ranked, with its point ids (``_points``),
    cached per stamp of the votes, labels and corrections."""
    w = Workspace(scene.workspace)
    key = ("suspects", str(scene.workspace),
           _stamp(w.votes, w.labels_path, w.labels_stats_path, w.corrections_dir / "overrides.npz"))

    def compute() -> list[dict]:
        labels = annotations.current_labels(ctx, scene)
        if labels is None:
            raise NotFound(f"scene {scene.id} has no lifted labels yet")
        ws_scene = ctx.load_scene(scene.workspace)
        st = VoteStore.open(scene.workspace, ws_scene, read_only=True)
        # voxels at least 1.5 point spacings wide, so neighbouring points connect
        params = SuspectParams(voxel=max(1.0, 1.5 * scene_point_spacing(ws_scene)))
        rows = find_suspects(ws_scene, st.votes, labels, params)
        names = {int(c.id): c.name for c in ws_scene.taxonomy.classes}
        views: dict = {}
        out = []
        for r in rows:
            r = dict(r)
            pts = r.pop("point_ids")
            # a key that survives a re-ranking: the region's smallest point id (a reviewer's
            # done / dismissed marks are stored against it)
            r["key"] = f"p{int(pts.min())}" if len(pts) else f"r{r['id']}"
            r["class_names"] = {k: names.get(int(k), k) for k in r["classes"]}
            if r["kind"] == "island":
                r["island_of_name"] = names.get(r["island_of"], str(r["island_of"]))
                r["inside_name"] = names.get(r["inside"], str(r["inside"]))
            r["n_frames"] = len(r["frames"])
            r["frames"] = r["frames"][:50]
            r["outline"] = _outline(ws_scene, views, r["best_frame"], pts)
            # for the 3D jump (suspect_points): raw int64 bytes, stored as such (base64) in
            # the shared cache, not as a JSON list of numbers
            r["_points"] = np.asarray(pts, "<i8").tobytes()
            out.append(r)
        # the form every process reads back from the shared cache (JSON: a dict's integer
        # keys become strings), here too, so the computing process answers the same
        return decode(encode(out))

    return _SUSPECT_CACHE.get(key, compute, ctx.settings.data_dir)


def _warm_suspects(ctx: AppContext, scene: Scene) -> None:
    """Compute the scene's suspects list into the cache (after a fill; best effort)."""
    try:
        _suspect_rows(ctx, scene)
    except Exception:  # noqa: BLE001 - no labels yet / a workspace mid-update: the tab computes it
        log.debug("suspects of scene %s not warmed", scene.id, exc_info=True)


def suspects(ctx: AppContext, scene: Scene, *, limit: int = 100) -> dict:
    """Ranked contested regions of the scene's labels (:mod:`occufly.lifting.suspects`);
    each with its size, classes, the frames that see it (frame ids and indices), the best
    frame, bounding box and centroid (scene-local metres)."""
    rows = _suspect_rows(ctx, scene)[:limit]
    with ctx.sessions() as s:
        fid = dict(s.execute(select(Frame.index, Frame.id).where(Frame.scene_id == scene.id)).all())
        marks = suspect_marks(s, scene.id)
    out = []
    for r in rows:
        r = {k: v for k, v in r.items() if k != "_points"}
        r["frame_ids"] = [fid.get(i) for i in r["frames"]]
        r["best_frame_id"] = fid.get(r["best_frame"]) if r["best_frame"] is not None else None
        r["mark"] = marks.get(r["key"])
        out.append(r)
    n_open = sum(r["mark"] is None for r in out)
    return {"scene_id": scene.id, "n": len(out), "n_open": n_open, "suspects": out}


def suspect_points(ctx: AppContext, scene: Scene, key: str) -> np.ndarray | None:
    """The point ids (sorted int64) of the suspect ``key`` of the scene's current ranking
    (the 3D viewer selects them: ``/viewer/?scene=&frame=&suspect=``); None when no suspect
    of the current labels has that key (the labels changed since the list was read) or the
    scene has no labels yet."""
    try:
        rows = _suspect_rows(ctx, scene)
    except NotFound:
        return None
    for r in rows:
        if r.get("key") == key:
            return np.sort(np.frombuffer(r["_points"], "<i8").astype(np.int64))
    return None


SUSPECT_MARKS = ("done", "dismissed")


def suspect_marks(session: Session, scene_id: int) -> dict[str, dict]:
    """{suspect key: {"status", "by", "at"}} of a scene's marked suspects."""
    rows = session.execute(
        select(SuspectMark, User.username).outerjoin(User, User.id == SuspectMark.author_id)
        .where(SuspectMark.scene_id == scene_id)).all()
    return {m.key: {"status": m.status, "by": name, "at": m.updated_at.isoformat() + "Z"}
            for m, name in rows}


def set_suspect_mark(session: Session, *, scene: Scene, key: str, status: str | None,
                     user: User) -> dict | None:
    """Mark suspect ``key`` of ``scene`` done / dismissed, or clear its mark (``status`` None).
    The same mark again is a no-op (who set it and when stay). Returns the mark now held."""
    if status is not None and status not in SUSPECT_MARKS:
        raise Invalid(f"status: expected one of {', '.join(SUSPECT_MARKS)} or null, got {status!r}")
    m = session.execute(select(SuspectMark).where(
        SuspectMark.scene_id == scene.id, SuspectMark.key == key)).scalar_one_or_none()
    if status is None:
        if m is not None:
            session.delete(m)
            session.commit()
        return None
    if m is None:
        m = SuspectMark(scene_id=scene.id, key=key, status=status, author_id=user.id,
                        updated_at=utcnow())
        session.add(m)
    elif m.status != status:
        m.status, m.author_id, m.updated_at = status, user.id, utcnow()
    else:
        return suspect_marks(session, scene.id)[key]
    try:
        session.commit()
    except IntegrityError:  # two reviewers marked it at once: the first one's mark stands
        session.rollback()
    return suspect_marks(session, scene.id).get(key)


def _outline(ws_scene, views: dict, frame_index: int | None, pts: np.ndarray) -> list:  # noqa: ANN001
    """Convex hull, in the pixels of frame ``frame_index``, of the points of ``pts`` that frame
    sees (the visibility's projections; [] when it sees fewer than 3). ``views`` caches each
    frame's sorted visibility."""
    if frame_index is None:
        return []
    if frame_index not in views:
        ids, uv, _d = ws_scene.visibility.frame(frame_index)
        ids = np.asarray(ids, np.int64)
        order = np.argsort(ids, kind="stable")
        views[frame_index] = (ids[order], np.asarray(uv, np.float64)[order])
    ids, uv = views[frame_index]
    if not len(ids):
        return []
    pos = np.minimum(np.searchsorted(ids, pts), len(ids) - 1)
    xy = uv[pos[ids[pos] == pts]]
    if len(xy) < 3:
        return []
    try:
        hull = ConvexHull(xy)
    except QhullError:  # all on a line
        return []
    return [[round(float(x), 1), round(float(y), 1)] for x, y in xy[hull.vertices]]


# ---- decisions ------------------------------------------------------------------------------
def decide(*, session: Session, ctx: AppContext, frame: Frame, user: User, decision: str,
           comment: str | None, version: int) -> Frame:
    """Accept or reject the frame's current mask version (recorded as reviewed_version_id and
    as the version's state, with its decider: ``MaskVersion.kind`` / ``decided_by_id``).

    The decision is one conditional UPDATE on (state, current_version_id): a mask saved
    between the reviewer's look and the click makes it a 409 instead of accepting a version
    nobody reviewed. ``version`` names the version the reviewer looked at: a version that
    is not the frame's current one is a 409 naming both (issue 40: a decision pressed on one
    frame's mask never lands on another's).

    Deciding the version the frame's last decision already decided the same way is a no-op
    (a double click, a retried request): the frame is returned unchanged, nothing is stored
    (no second comment) and ``frame.decision_noop`` is True (the route then audits nothing).
    Accepting makes the version the frame's voting version; rejecting withdraws the frame's
    votes (queued for lifting only when the voting version changes).
    """
    frame.decision_noop = False
    if frame.state not in ("submitted", "accepted", "rejected"):
        raise Conflict(f"frame {frame.id} is {frame.state}; only submitted frames can be reviewed")
    if frame.current_version_id is None:
        raise Conflict(f"frame {frame.id} has no mask to review")
    if version != frame.current_version_id:
        raise Conflict(f"frame {frame.id}'s current mask is version {frame.current_version_id}, "
                       f"not the version {version} you decided on; look at it again",
                       current_version=frame.current_version_id, sent_version=version)
    target = "accepted" if decision == "accept" else "rejected"
    if frame.state == target and frame.reviewed_version_id == frame.current_version_id:
        frame.decision_noop = True
        return frame
    vid = frame.current_version_id
    now = utcnow()
    values: dict = dict(reviewed_by_id=user.id, reviewed_at=now, reviewed_version_id=vid)
    if decision == "accept":
        values.update(state="accepted", assignee_id=None, lease_expires_at=None)
    else:
        # back to the annotator's own queue first; others may take it after the hold expires
        values.update(state="rejected", assignee_id=frame.last_annotator_id,
                      lease_expires_at=(now + timedelta(seconds=ctx.settings.reject_hold_seconds)
                                        if frame.last_annotator_id else None))
    res = session.execute(update(Frame).where(
        Frame.id == frame.id, Frame.state == frame.state,
        Frame.current_version_id == vid).values(**values)
        .execution_options(synchronize_session=False))
    if res.rowcount != 1:
        session.rollback()
        session.refresh(frame)
        raise Conflict(f"frame {frame.id} changed while you reviewed it (now {frame.state}, "
                       f"version {frame.current_version_id}); look at it again",
                       current_version=frame.current_version_id)
    # the version's state; a conflict version can never be current, a draft can be (an
    # admin's draft of a submitted frame): deciding on it makes it accepted / rejected too
    session.execute(update(MaskVersion).where(MaskVersion.id == vid).values(
        kind=target, decided_by_id=user.id, decided_at=now)
        .execution_options(synchronize_session=False))
    annotations.set_voting(session=session, ctx=ctx, frame=frame,
                           version_id=vid if decision == "accept" else None)
    if comment:
        item = ReviewItem(scene_id=frame.scene_id, frame_id=frame.id, author_id=user.id,
                          status="open" if decision == "reject" else "resolved",
                          resolved_at=None if decision == "reject" else now)
        session.add(item)
        session.flush()
        session.add(ReviewComment(item_id=item.id, author_id=user.id,
                                  text=f"[{decision}] {comment}"))
    if decision == "reject":  # the annotator learns of it (issue 25: notifications)
        notify_frame_people(session, frame=frame, actor=user, kind="rejected",
                            text=f"{user.username} rejected {frame.name}"
                                 + (f": {comment}" if comment else ""))
    session.commit()
    ctx.lifting.notify(frame.scene_id, frame.id)
    session.refresh(frame)
    return frame


def undo_decision(*, session: Session, ctx: AppContext, frame: Frame, user: User,
                  decision: str, version: int) -> Frame:
    """Take back a decision (the page's Undo, issue 40): the frame, ``decision``-ed on its
    current ``version`` and not touched since, is submitted again -- waiting for review, its
    version voting as a submitted one, the decider cleared. A frame that moved on (another
    decision, a new mask, its annotator took the rejected frame back) is a 409 saying so.
    The decision's comments stay in the frame's thread (the reviewer resolves them); the
    annotator of a withdrawn rejection is told."""
    target = "accepted" if decision == "accept" else "rejected"
    if version != frame.current_version_id:
        raise Conflict(f"frame {frame.id}'s current mask is version {frame.current_version_id}, "
                       f"not the version {version} the decision was on; nothing undone",
                       current_version=frame.current_version_id, sent_version=version)
    if frame.state != target or frame.reviewed_version_id != version:
        raise Conflict(f"frame {frame.id} is {frame.state} now, not {target} on version "
                       f"{version}: the decision cannot be undone any more",
                       current_version=frame.current_version_id, state=frame.state)
    res = session.execute(update(Frame).where(
        Frame.id == frame.id, Frame.state == target, Frame.current_version_id == version,
        Frame.reviewed_version_id == version).values(
        state="submitted", reviewed_by_id=None, reviewed_at=None, reviewed_version_id=None,
        assignee_id=None, lease_expires_at=None).execution_options(synchronize_session=False))
    if res.rowcount != 1:
        session.rollback()
        session.refresh(frame)
        raise Conflict(f"frame {frame.id} changed meanwhile (now {frame.state}, version "
                       f"{frame.current_version_id}); nothing undone",
                       current_version=frame.current_version_id, state=frame.state)
    # back to its state before the decision: an imported mask is "imported" again
    source = session.scalar(select(MaskVersion.source).where(MaskVersion.id == version)) or ""
    session.execute(update(MaskVersion).where(MaskVersion.id == version).values(
        kind="imported" if source.startswith("imported") else "submitted",
        decided_by_id=None, decided_at=None)
        .execution_options(synchronize_session=False))
    annotations.set_voting(session=session, ctx=ctx, frame=frame, version_id=version)
    if decision == "reject":
        notify_frame_people(session, frame=frame, actor=user, kind="rejected",
                            text=f"{user.username} withdrew the rejection of {frame.name}: "
                                 "it waits for review again")
    session.commit()
    ctx.lifting.notify(frame.scene_id, frame.id)
    session.refresh(frame)
    return frame


def reviewed_versions(session: Session, scene_id: int) -> list[dict]:
    """Per frame with a mask: its state, current version and the version a reviewer decided
    on -- what an export records (accepted frames whose current version is not the reviewed
    one cannot exist: a new version resets the state)."""
    rows = session.execute(select(Frame.id, Frame.index, Frame.state, Frame.current_version_id,
                                  Frame.reviewed_version_id)
                           .where(Frame.scene_id == scene_id,
                                  Frame.current_version_id.is_not(None)).order_by(Frame.index))
    return [dict(frame_id=fid, index=idx, state=st, current_version=cur,
                 reviewed_version=rev if st in ("accepted", "rejected") else None,
                 accepted=st == "accepted" and rev == cur)
            for fid, idx, st, cur, rev in rows]


# ---- quotas on review items and comments (issue 36) -------------------------------------------
# Counted in the database under the user's lock (and, for a thread, the item's), in the
# transaction that adds the row: they hold across API processes (app.shared_limits). A
# reviewer's reject-with-comment (:func:`decide`) is not refused: one per decision; its
# comment counts towards the hour.
def _comment_quota(session: Session, settings, user_id: int,  # noqa: ANN001
                   item_id: int | None) -> None:
    now = utcnow()
    n, oldest = session.execute(select(func.count(), func.min(ReviewComment.created_at)).where(
        ReviewComment.author_id == user_id,
        ReviewComment.created_at > now - timedelta(hours=1))).one()
    cap = settings.comments_per_user_hour
    if n >= cap:
        wait = max(1, int((oldest + timedelta(hours=1) - now).total_seconds()) + 1)
        raise TooManyAttempts(
            f"comment quota: you wrote {n} comments in the last hour, at most {cap} an hour "
            f"(OCCUFLY_COMMENTS_PER_USER_HOUR); try again in {wait} s", retry_after=wait,
            comments_last_hour=int(n), quota=cap)
    if item_id is None:
        return
    n = session.scalar(select(func.count()).select_from(ReviewComment).where(
        ReviewComment.item_id == item_id)) or 0
    cap = settings.comments_per_item
    if n >= cap:
        raise Conflict(f"comment quota: review item {item_id} has {n} comments, at most {cap} "
                       "(OCCUFLY_COMMENTS_PER_ITEM); file a new review item",
                       comments=int(n), quota=cap)


def _item_quota(session: Session, settings, user_id: int, scene_id: int) -> None:  # noqa: ANN001
    n = session.scalar(select(func.count()).select_from(ReviewItem).where(
        ReviewItem.author_id == user_id, ReviewItem.scene_id == scene_id,
        ReviewItem.status == "open")) or 0
    cap = settings.open_review_items_per_user
    if n >= cap:
        raise TooManyAttempts(
            f"review item quota: you have {n} open review items in scene {scene_id}, at most "
            f"{cap} (OCCUFLY_OPEN_REVIEW_ITEMS_PER_USER); resolve some first",
            open_items=int(n), quota=cap)


def _check_quotas(session: Session, settings, user_id: int, *,  # noqa: ANN001
                  scene_id: int | None = None, item_id: int | None = None) -> None:
    """Take the locks (the item's first, then the user's: one order everywhere) and check; on
    a refusal the transaction is rolled back, which releases them."""
    if item_id is not None:
        serialise(session, ITEM_COMMENTS, item_id)
    serialise(session, REVIEW_QUOTA, user_id)
    try:
        if scene_id is not None:
            _item_quota(session, settings, user_id, scene_id)
        _comment_quota(session, settings, user_id, item_id)
    except Exception:
        session.rollback()
        raise


# ---- review items ---------------------------------------------------------------------------
def create_item(*, session: Session, scene: Scene, user: User, frame_id: int | None,
                pixel: list[int] | None, point_ids: list[int] | None, comment: str,
                settings) -> ReviewItem:  # noqa: ANN001
    """File a review item with its first comment (``settings``: the quotas)."""
    if frame_id is None and not point_ids:
        raise Invalid("a review item needs a frame_id (optionally with a pixel) or point_ids")
    if pixel is not None and frame_id is None:
        raise Invalid("pixel needs a frame_id")
    if frame_id is not None:
        frame = session.get(Frame, frame_id)
        if frame is None or frame.scene_id != scene.id:
            raise NotFound(f"frame {frame_id} is not in scene {scene.id}")
        if pixel is not None:
            x, y = pixel
            if not (0 <= x < frame.width and 0 <= y < frame.height):
                raise Invalid(f"pixel {pixel} is outside frame {frame_id} "
                              f"({frame.width}x{frame.height})")
    if point_ids:
        ids = np.asarray(point_ids, dtype=np.int64)
        if ids.min() < 0 or ids.max() >= scene.n_points:
            raise Invalid(f"point_ids must be in 0..{scene.n_points - 1}")
        point_ids = np.unique(ids).tolist()
    _check_quotas(session, settings, user.id, scene_id=scene.id)
    item = ReviewItem(scene_id=scene.id, frame_id=frame_id, author_id=user.id,
                      pixel_x=pixel[0] if pixel else None, pixel_y=pixel[1] if pixel else None,
                      point_ids=point_ids or None, status="open")
    session.add(item)
    session.flush()
    session.add(ReviewComment(item_id=item.id, author_id=user.id, text=comment))
    if frame_id is not None:  # the frame's annotator is told (issue 25: notifications)
        fr = session.get(Frame, frame_id)
        notify_frame_people(session, frame=fr, actor=user, kind="comment", item_id=item.id,
                            text=f"{user.username} commented on {fr.name}: {comment[:200]}")
    session.commit()
    return item


def create_item_from_3d(scene_id: int, point_ids, comment: str, user, *, sessions,
                        settings, frame_index: int | None = None) -> int:  # noqa: ANN001
    """Callback for the 3D viewer: file a review item on a set of point ids; returns its id.

    ``user`` is a User row or a user id; ``sessions`` the app's session factory
    (``ctx.sessions``) and ``settings`` its settings (the quotas; :func:`make_viewer_callback`
    binds both).
    """
    with sessions() as s:
        scene = s.get(Scene, int(scene_id))
        if scene is None:
            raise NotFound(f"scene {scene_id} does not exist")
        uid = user if isinstance(user, int) else getattr(user, "id", None)
        u = s.get(User, uid) if uid is not None else None
        if u is None or u.role not in ("reviewer", "admin"):
            raise Forbidden("only reviewers and admins file review items")
        # the frame the reviewer looked through, where known (issue 25)
        frame_id = None if frame_index is None else s.scalar(select(Frame.id).where(
            Frame.scene_id == scene.id, Frame.index == int(frame_index)))
        item = create_item(session=s, scene=scene, user=u, frame_id=frame_id, pixel=None,
                           point_ids=[int(i) for i in np.asarray(point_ids).reshape(-1)],
                           comment=comment, settings=settings)
        return item.id


def make_viewer_callback(ctx: AppContext):
    def on_review_item(scene_id, point_ids, comment, user, frame_index=None):  # noqa: ANN001
        return create_item_from_3d(scene_id, point_ids, comment, user, sessions=ctx.sessions,
                                   settings=ctx.settings, frame_index=frame_index)

    return on_review_item


def _visible_items(session: Session, scene: Scene, user: User):
    q = select(ReviewItem).where(ReviewItem.scene_id == scene.id)
    if user.role == "annotator":  # only items about frames they work(ed) on
        q = q.join(Frame, Frame.id == ReviewItem.frame_id).where(
            or_(Frame.assignee_id == user.id, Frame.last_annotator_id == user.id))
    return q


def projected_for(session: Session, user: User, items: list[dict]) -> list[dict]:
    """Of the review items projected into a frame (:func:`items_out` dicts of one scene)
    those ``user`` may see there: all for reviewers and admins; for an annotator the items
    about frames they work(ed) on (:func:`get_item`'s rule) and the scene's 3D items filed on
    points with no frame (what the annotator page's projection is for), never an item about
    another annotator's frame or its comments (issue 36)."""
    if user.role != "annotator":
        return items
    fids = {d["frame_id"] for d in items if d.get("frame_id") is not None}
    mine = set(session.scalars(select(Frame.id).where(
        Frame.id.in_(fids), or_(Frame.assignee_id == user.id,
                                Frame.last_annotator_id == user.id)))) if fids else set()
    return [d for d in items if d.get("frame_id") is None or d["frame_id"] in mine]


def list_items(*, session: Session, scene: Scene, user: User, status: str | None = None,
               frame_id: int | None = None) -> list[dict]:
    q = _visible_items(session, scene, user)
    if status:
        q = q.where(ReviewItem.status == status)
    if frame_id is not None:
        q = q.where(ReviewItem.frame_id == frame_id)
    items = list(session.scalars(q.order_by(ReviewItem.id)))
    return items_out(session, items)


def get_item(*, session: Session, item_id: int, user: User) -> ReviewItem:
    item = session.get(ReviewItem, item_id)
    if item is None:
        raise NotFound(f"review item {item_id} does not exist")

    check_member(session, user, item.scene_id)
    if user.role == "annotator":
        frame = session.get(Frame, item.frame_id) if item.frame_id else None
        if frame is None or user.id not in (frame.assignee_id, frame.last_annotator_id):
            raise Forbidden(f"review item {item_id} is not about your frames")
    return item


def add_comment(*, session: Session, item: ReviewItem, user: User, text: str,
                settings) -> ReviewItem:  # noqa: ANN001
    """Add a comment to ``item``'s thread (``settings``: the quotas)."""
    _check_quotas(session, settings, user.id, item_id=item.id)
    session.add(ReviewComment(item_id=item.id, author_id=user.id, text=text))
    frame = session.get(Frame, item.frame_id) if item.frame_id else None
    if frame is not None:  # the frame's annotator is told (issue 25: notifications)
        notify_frame_people(session, frame=frame, actor=user, kind="comment", item_id=item.id,
                            text=f"{user.username} commented on {frame.name}: {text[:200]}")
    session.commit()
    return item


def set_status(*, session: Session, item: ReviewItem, status: str) -> ReviewItem:
    item.status = status
    item.resolved_at = utcnow() if status == "resolved" else None
    session.commit()
    return item


def items_out(session: Session, items: list[ReviewItem]) -> list[dict]:
    """The API's view of review items (:class:`app.review.schemas.ReviewItemOut`): their
    comments in one query, the names of only the users who wrote them in another."""
    ids = [it.id for it in items]
    comments: dict[int, list[ReviewComment]] = {i: [] for i in ids}
    if ids:
        for c in session.scalars(select(ReviewComment).where(ReviewComment.item_id.in_(ids))
                                 .order_by(ReviewComment.id)):
            comments[c.item_id].append(c)
    authors = {it.author_id for it in items} | {c.author_id for cs in comments.values() for c in cs}
    authors.discard(None)
    names = dict(session.execute(select(User.id, User.username).where(User.id.in_(authors))).all()
                 ) if authors else {}
    out = []
    for item in items:
        pts = item.point_ids or None
        out.append(dict(
            id=item.id, scene_id=item.scene_id, frame_id=item.frame_id,
            pixel=[item.pixel_x, item.pixel_y] if item.pixel_x is not None else None,
            point_ids=pts, n_points=len(pts or []), status=item.status,
            author=names.get(item.author_id), created_at=item.created_at,
            resolved_at=item.resolved_at,
            comments=[dict(id=c.id, author=names.get(c.author_id), text=c.text,
                           created_at=c.created_at) for c in comments[item.id]]))
    return out


def item_out(session: Session, item: ReviewItem) -> dict:
    """One review item as the API shows it (:func:`items_out`)."""
    return items_out(session, [item])[0]


def export_record(ctx: AppContext, scene_id: int, workspace) -> dict:  # noqa: ANN001
    """What an export job records about review: per frame with a mask, the version the lifted
    labels were built from (``labels_version``), the frame's current version, the version a
    reviewer accepted, and ``reviewed`` = the labels use exactly the accepted version."""
    with ctx.sessions() as s:
        rows = reviewed_versions(s, scene_id)
    res = load_labels(workspace)
    used = {}
    for index, tag in ((res.stats.get("versions") if res is not None else None) or {}).items():
        used[int(index)] = int(tag) if tag is not None and str(tag).isdigit() else None
    frames = []
    for r in rows:
        lv = used.get(r["index"])
        frames.append({**r, "labels_version": lv,
                       "reviewed": r["accepted"] and lv is not None and lv == r["reviewed_version"]})
    return {"frames": frames, "n_frames": len(frames),
            "n_reviewed": sum(f["reviewed"] for f in frames),
            "unreviewed_frames": [f["index"] for f in frames if not f["reviewed"]]}
