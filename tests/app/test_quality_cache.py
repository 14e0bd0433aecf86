"""The admin page's quality report is computed in the background (issue 38: minutes on a survey),
never in the request: 202 before the first report, the last report marked stale while the
current one is computed, one computation per scene across processes (a file lock)."""

from __future__ import annotations

import dataclasses
import fcntl
import threading
import time
from pathlib import Path

from app.review import quality_cache
from app.scenes.models import Scene
from occufly.lifting import quality as lifting_quality
from tests.app.conftest import mask_png


def _submit(env, hdr, sid, who, cls):  # noqa: ANN001, ANN202
    fid = env.client.post(f"/api/scenes/{sid}/next", headers=hdr[who]).json()["id"]
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=mask_png(cls),
                       headers={**hdr[who], "If-Match": "none"})
    assert r.status_code in (200, 201), r.text
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=120, include_fill=True)
    return fid


class _Slow:
    """quality_report held until released; counts the computations."""

    def __init__(self, monkeypatch) -> None:  # noqa: ANN001
        self.release = threading.Event()
        self.calls = 0
        real = lifting_quality.quality_report

        def slow(*a, **k):  # noqa: ANN002, ANN003, ANN202
            self.calls += 1
            assert self.release.wait(60)
            return real(*a, **k)

        monkeypatch.setattr(lifting_quality, "quality_report", slow)


def _get(env, hdr, sid):  # noqa: ANN001, ANN202
    return env.client.get(f"/api/scenes/{sid}/quality", headers=hdr["admin"])


def _wait_current(env, hdr, sid, timeout=120.0):  # noqa: ANN001, ANN202
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        r = _get(env, hdr, sid)
        if r.status_code == 200 and not r.json()["stale"]:
            return r.json()
        time.sleep(0.1)
    raise AssertionError("the quality report was never computed")


def test_first_report_is_202_then_computed_once_in_the_background(world, monkeypatch):
    env, hdr, scene, _ = world
    sid = scene["id"]
    quality_cache._CACHE.clear()
    _submit(env, hdr, sid, "annotator", 6)
    env.app.state.ctx.settings = dataclasses.replace(env.settings, quality_wait_s=0.3)
    slow = _Slow(monkeypatch)
    t0 = time.monotonic()
    r = _get(env, hdr, sid)
    assert r.status_code == 202, r.text
    assert r.json()["computing"] is True and "being computed" in r.json()["message"]
    assert time.monotonic() - t0 < 5  # the request did not wait for the report
    assert _get(env, hdr, sid).status_code == 202  # asked again: still the one computation
    slow.release.set()
    q = _wait_current(env, hdr, sid)
    assert q["annotated_frames"] == 1 and q["computing"] is False
    assert slow.calls == 1
    assert _get(env, hdr, sid).json()["cached"] is True


def test_new_labels_show_the_last_report_as_stale_until_the_new_one_is_ready(world, monkeypatch):
    env, hdr, scene, _ = world
    sid = scene["id"]
    quality_cache._CACHE.clear()
    env.app.state.ctx.settings = dataclasses.replace(env.settings, quality_wait_s=120)
    _submit(env, hdr, sid, "annotator", 6)
    first = _get(env, hdr, sid).json()
    assert first["annotated_frames"] == 1 and first["stale"] is False
    _submit(env, hdr, sid, "annotator2", 8)  # new labels: a new stamp
    env.app.state.ctx.settings = dataclasses.replace(env.settings, quality_wait_s=0.2)
    slow = _Slow(monkeypatch)
    r = _get(env, hdr, sid)
    assert r.status_code == 200, r.text
    st = r.json()
    assert st["stale"] is True and st["computing"] is True
    assert st["labels_stamp"] == first["labels_stamp"] != st["current_stamp"]
    assert st["annotated_frames"] == 1  # the last report's figures, said to be old
    slow.release.set()
    q = _wait_current(env, hdr, sid)
    assert q["annotated_frames"] == 2 and q["labels_stamp"] == st["current_stamp"]
    assert slow.calls == 1


def test_a_computation_held_by_another_process_is_not_repeated(world, monkeypatch):
    env, hdr, scene, _ = world
    sid = scene["id"]
    quality_cache._CACHE.clear()
    _submit(env, hdr, sid, "annotator", 6)
    env.app.state.ctx.settings = dataclasses.replace(env.settings, quality_wait_s=0.3)
    d = env.settings.data_dir / "cache" / "quality"
    d.mkdir(parents=True, exist_ok=True)
    calls = []
    real = lifting_quality.quality_report
    monkeypatch.setattr(lifting_quality, "quality_report",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    # "another API process" computing this scene's report: it holds the scene's lock, then
    # stores the report of the current stamp in the shared file and lets go
    with open(d / f"scene_{sid}.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert _get(env, hdr, sid).status_code == 202
        time.sleep(0.5)
        assert calls == []  # this process waits for the lock, it does not compute beside it
        ctx = env.app.state.ctx
        with ctx.sessions() as s:
            ws = Path(s.get(Scene, sid).workspace)
        quality_cache._compute(ctx, sid, ws)  # the other process's work
        assert len(calls) == 1
        quality_cache._CACHE.clear()  # ... made in another process: only the file holds it
        fcntl.flock(lock, fcntl.LOCK_UN)
    q = _wait_current(env, hdr, sid)
    assert q["annotated_frames"] == 1
    assert len(calls) == 1  # read from the shared file, not computed again
