"""The review's after-fill refresh runs in a niced child process (issue 38: on the survey it held
the fill thread 12.8 min and took the interpreter's lock from the votes): the fill is released
at once, ``wait_idle(include_fill=True)`` still waits for the refresh, what the child computes
reaches the API, refreshes are coalesced and a stop ends the child."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from app import bootstrap
from app.review import service as review
from app.review.refresher import ReviewRefresher
from app.scenes.models import Frame, Scene
from tests.app.conftest import H, W, png

# where the test entries below leave their traces (a child process inherits the environment)
TRACE = "OCCUFLY_TEST_REFRESH_TRACE"


def _put(path: Path, text: str) -> None:
    """Write a trace file whole (a rename): the test polls for it by name and reads it at
    once, and a plain write showed it empty for a moment (a flake under load)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.replace(path)


def blocking_entry(settings, scene_id: int, stop: threading.Event) -> None:  # noqa: ANN001
    """A refresh that records its process and niceness, then waits for ``<trace>/release``
    (or a stop); in a child process."""
    d = Path(os.environ[TRACE])
    n = len(list(d.glob("run-*")))
    _put(d / f"run-{n}-{scene_id}", f"{os.getpid()} {os.nice(0)}")
    while not (d / "release").exists():
        if stop.wait(0.02):
            _put(d / f"stopped-{n}", "1")
            return


def ignoring_entry(settings, scene_id: int, stop: threading.Event) -> None:  # noqa: ANN001, ARG001
    """A refresh that never looks at its stop event (one frame's LOO running long)."""
    d = Path(os.environ[TRACE])
    _put(d / "started", str(os.getpid()))
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    time.sleep(120)


def _wait(cond, timeout: float = 30.0) -> bool:  # noqa: ANN001
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


@pytest.fixture
def trace(tmp_path: Path, monkeypatch) -> Path:  # noqa: ANN001
    d = tmp_path / "trace"
    d.mkdir()
    monkeypatch.setenv(TRACE, str(d))
    return d


def test_coalesced_niced_child_and_busy(trace: Path):
    r = ReviewRefresher(SimpleNamespace(), blocking_entry, nice=7)
    try:
        assert not r.busy(1)
        r(SimpleNamespace(scene_id=1), threading.Event())  # returns at once
        assert r.busy(1) and not r.busy(2)
        assert _wait(lambda: list(trace.glob("run-0-1")))
        # three more fills of scene 1 while it runs: one more refresh, not three
        for _ in range(3):
            r.request(1)
        r.request(2)
        pid, nice = map(int, (trace / "run-0-1").read_text().split())
        assert pid != os.getpid()
        assert nice == min(19, os.nice(0) + 7)  # the child runs niced
        assert r.busy(1) and r.busy(2)
        assert not r.wait_idle(timeout=0.2)
        (trace / "release").write_text("")
        assert r.wait_idle(timeout=60)
        runs = sorted(p.name.split("-", 2)[2] for p in trace.glob("run-*"))
        assert runs == ["1", "1", "2"], runs
        assert r.runs == 3 and r.failures == 0
        assert not r.busy(1) and not r.busy(2)
    finally:
        r.close()


def test_close_stops_the_child_between_frames(trace: Path):
    r = ReviewRefresher(SimpleNamespace(), blocking_entry)
    r.request(5)
    assert _wait(lambda: list(trace.glob("run-0-5")))
    pid = int((trace / "run-0-5").read_text().split()[0])
    t0 = time.monotonic()
    r.close()
    assert time.monotonic() - t0 < 10
    assert (trace / "stopped-0").exists()  # SIGTERM set its stop event: it returned cleanly
    assert not _alive(pid)
    r.request(5)  # closed: nothing more starts
    assert not r.busy(5)


def test_close_kills_a_child_that_does_not_stop(trace: Path):
    r = ReviewRefresher(SimpleNamespace(), ignoring_entry, term_wait_s=0.5)
    r.request(1)
    assert _wait(lambda: (trace / "started").exists())
    pid = int((trace / "started").read_text())
    t0 = time.monotonic()
    r.close()
    assert time.monotonic() - t0 < 8
    assert _wait(lambda: not _alive(pid), 5)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie not yet reaped counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def _submit(env, hdr, fid: int, m: np.ndarray) -> None:  # noqa: ANN001
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(m),
                       headers={**hdr["admin"], "If-Match": "none"})
    assert r.status_code == 200, r.text


@pytest.fixture
def blocking_refresh(trace: Path, monkeypatch) -> Path:  # noqa: ANN001
    """The app's refresh entry replaced by :func:`blocking_entry` (before the app is built:
    request it before ``world``)."""
    monkeypatch.setattr(bootstrap, "run_review_refresh", blocking_entry)
    return trace


@pytest.mark.review_process
def test_the_fill_is_released_while_the_refresh_runs(blocking_refresh: Path, world):  # noqa: ANN001
    """The fill ends (labels/status idle) while the refresh still runs in its child;
    ``wait_idle(include_fill=True)`` waits for it."""
    trace = blocking_refresh
    env, hdr, scene, frames = world
    lifting = env.app.state.ctx.lifting
    (refresher,) = lifting.service.on_owned_labels
    assert isinstance(refresher, ReviewRefresher)
    _submit(env, hdr, frames[0]["id"], np.full((H, W), 6, np.uint8))
    assert _wait(lambda: list(trace.glob("run-0-*")))  # the fill ended and handed over
    st = env.client.get(f"/api/scenes/{scene['id']}/labels/status", headers=hdr["admin"]).json()
    assert not st["fill_running"]
    assert lifting.service.busy(scene["id"])["refreshing"]
    assert not lifting.wait_idle(scene["id"], timeout=0.3, include_fill=True)
    (trace / "release").write_text("")
    assert lifting.wait_idle(scene["id"], timeout=60, include_fill=True)
    assert not lifting.service.busy(scene["id"])["refreshing"]


@pytest.mark.review_process
def test_the_child_refresh_reaches_the_api(world):
    """The real refresh in its child process: the stored agreement (the review list's sort)
    and the review cache are written there and read by the API process."""
    env, hdr, scene, frames = world
    ids = [f["id"] for f in sorted(frames, key=lambda f: f["index"])]
    for fid in ids[:3]:
        _submit(env, hdr, fid, np.full((H, W), 6, np.uint8))
    _submit(env, hdr, ids[3], np.full((H, W), 1, np.uint8))  # the grass painted as road
    lifting = env.app.state.ctx.lifting
    assert lifting.wait_idle(scene["id"], timeout=120, include_fill=True)
    (refresher,) = lifting.service.on_owned_labels
    assert refresher.runs >= 1 and refresher.failures == 0
    with env.app.state.ctx.sessions() as s:  # written by the child, no request asked for it
        stored = {f.id: f.agreement for f in s.query(Frame).filter(Frame.id.in_(ids))}
    assert stored[ids[3]] is not None and stored[ids[3]] < 0.2
    assert stored[ids[1]] > 0.9 and all(stored[i] > 0.5 for i in ids[:3])
    with env.app.state.ctx.sessions() as s:
        sc = s.get(Scene, scene["id"])
        assert all(review.cached_review(env.app.state.ctx, sc, s.get(Frame, i), s,
                                          env.settings.data_dir)
                   for i in ids)
    fl = env.client.get(f"/api/scenes/{scene['id']}/frames?sort=disagreement",
                        headers=hdr["reviewer"]).json()
    assert fl[0]["id"] == ids[3]
    # the child computed the quality report of the new labels: the admin page reads it
    q = env.client.get(f"/api/scenes/{scene['id']}/quality", headers=hdr["admin"])
    assert q.status_code == 200, q.text
    assert q.json()["cached"] is True and q.json()["stale"] is False
    assert q.json()["loo"]["frames"] == 4


_PARENT = r"""
import sys, threading, time
from types import SimpleNamespace
from app.review.refresher import ReviewRefresher
from tests.app.test_review_refresh_process import blocking_entry
r = ReviewRefresher(SimpleNamespace(), blocking_entry)
r.request(1)
time.sleep(600)
"""


def test_a_child_whose_parent_died_exits(trace: Path):
    """The lifting worker killed (OOM, SIGKILL): its refresh child does not run on alone."""
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]
    parent = subprocess.Popen([sys.executable, "-c", _PARENT], cwd=repo,
                              env={**os.environ, "PYTHONPATH": str(repo)})
    try:
        assert _wait(lambda: list(trace.glob("run-0-1")), 60)
        child = int((trace / "run-0-1").read_text().split()[0])
        assert _alive(child)
    finally:
        parent.kill()
        parent.wait()
    assert _wait(lambda: not _alive(child), 10)


def test_the_refresh_settings_are_read_and_checked():
    from app.config import ConfigError, Settings

    dev = {"OCCUFLY_ENV": "development"}
    s = Settings.from_env(dev)
    assert s.review_refresh_process is True and s.review_refresh_nice == 10
    s = Settings.from_env({**dev, "OCCUFLY_REVIEW_REFRESH_PROCESS": "0",
                           "OCCUFLY_REVIEW_REFRESH_NICE": "19"})
    assert s.review_refresh_process is False and s.review_refresh_nice == 19
    for bad in ("20", "-1"):
        with pytest.raises(ConfigError, match="OCCUFLY_REVIEW_REFRESH_NICE must be 0..19"):
            Settings.from_env({**dev, "OCCUFLY_REVIEW_REFRESH_NICE": bad})
    with pytest.raises(ConfigError, match="OCCUFLY_REVIEW_REFRESH_PROCESS must be a number"):
        Settings.from_env({**dev, "OCCUFLY_REVIEW_REFRESH_PROCESS": "yes"})
