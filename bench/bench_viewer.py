"""Viewer benchmark at survey scale: the 3D review in headless Chromium (SwiftShader WebGL).

Opens ``/viewer/?scene=bench`` through the app's proxy, once per point sending scheme, in a
fresh browser each (so the tab's memory is its own), on the same workspace in the same run:

- ``legacy``: the old path, a 150 k preview then one node per class of the whole LOD;
- ``progressive``: the level of detail of :mod:`app.viewer.point_lod` (a coarse level, then
  region tiles from the middle out).

For each it reports

- ``first_points_s``: page opened -> the first frame drawn with points (``--first-by-probe``:
  the frame probe below, the canvas changed from the first frame; no screenshot is taken
  until the level of detail is sent) or else the first screenshot with points on it (the canvas crop
  clear of the panels has a pixel standard deviation > 20);
- ``full_lod_s``: page opened -> the first screenshot taken after the server sent the last
  chunk of the level of detail and the browser received it (``lod_sent_s`` / ``lod_received_s``);
- ``connected_s`` / ``first_sent_s``: page opened -> the viewer has the tab's client / has
  sent its first points (server side);
- ``orbit``: frames three.js renders per second (counted by a WebGL ``clear`` hook) while the
  view orbits the scene for ``--orbit-s`` seconds (camera moved at 30 Hz, each step signalled
  as the browser's camera message is: see :func:`orbit_fps`), and the points drawn meanwhile;
- ``memory``: the tab's renderer and the GPU process (SwiftShader keeps the buffers there):
  RSS and peak RSS (VmHWM) from /proc, and the page's JS heap (performance.memory);
- ``lasso``: a screen lasso (the selection tool's own function) chosen to hold ~``--lasso``
  points, relabelled to *water* (blue) through a file-backed corrections hook, then undone:
  ``relabel_drawn_s`` / ``undo_drawn_s``: the call -> the first frame the browser finished
  with the region blue (not blue) and the whole level of detail drawn, seen by a frame probe
  (:data:`PROBE_HOOK`: the region's pixels read from the WebGL drawing buffer after each
  frame, no screenshot); ``relabel_visible_s`` / ``undo_visible_s``: the call -> a screenshot
  taken then has returned showing it (a screenshot costs frames of its own: seconds under
  software WebGL; until 2026-12-06 the bench polled with screenshots, which is what the older
  ``*_visible_s`` figures measured); ``trace_relabel`` / ``trace_undo``: the timeline of each
  (the viewer's refreshes, what the proxy sent, the frames the page rendered, the probe,
  the screenshots); ``selection_drawn_s``: lasso closed -> selection highlighted (cyan);
- ``toggle_p50_s``: a class checkbox clicked in the browser until the server sees it.

With ``--grid`` (issue 38's "scene grid display"), after the orbit, ``grids``:

- ``scene``: the "Scene grid" box ticked in the browser, from the default view -> the boxes
  drawn (``first_boxes_s``, ``drawn_s``: the frame probe in reference mode, the share of the
  canvas that changed from the frame before the tick; ``visible_s``: a screenshot has
  returned), the level of detail (:mod:`app.viewer.grid_lod`: ``lod_level``, ``boxes``,
  ``box_edge_m``), ``ws_bytes`` the proxy sent meanwhile, the server's wall and thread CPU
  to build the nodes and for the whole ``send_grids``, ``orbit`` fps with the grid shown (the
  points-only ``orbit`` above is the baseline of the same run) and the tab's ``memory``;
- ``camera``: the same for one frame's camera grid alone (``--grid-frame``; default the
  first selected frame), chosen in the "Camera grid of frame" dropdown (set on the server,
  as the browser's message does), seen from the default view's angle on the grid's middle.

``--workspace WS`` opens an existing workspace (lifted labels, ``occufly voxelize``'s grid)
instead of the fabricated points, hard-linked into the bench's data dir (``--tmp-dir``, on
WS's file system) as scene ``bench`` (:func:`link_workspace`); nothing is written into WS.

Prints one JSON object (its last line of stdout). ``--shots DIR`` saves the progressive run's
screenshots (first points, full LOD, the 1 M selection, the grids). Usage:
``python bench/bench_viewer.py --points 8000000``;
``python bench/bench_viewer.py --workspace WS --tmp-dir DIR --schemes progressive --toggles 0
--lasso 0 --grid --shots docs/screenshots``.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import resource
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "viewer"))

from viewer_live import CHROMIUM_ARGS, REVIEWER, LiveServer, make_app  # noqa: E402

from app.viewer import corrections_panel  # noqa: E402
from app.viewer import selection as sel  # noqa: E402
from app.viewer.demo_scene import make_demo_workspace  # noqa: E402
from occufly.lifting.corrections import write_overrides  # noqa: E402

WATER = 14
ADAPTIVE_GRID_MATERIAL = "toon3"  # scene_builder.GRID_MATERIAL of the adaptive path
BLUE = np.array([0, 0, 255])
VIEW = (1000, 700)


SHOT_LOG: list[tuple[float, float]] = []  # (start, end) wall-clock of every screenshot
REFRESH_LOG: list[tuple[float, float]] = []  # (start, end) of every viewer refresh_now


def shot(page, path: Path | None = None) -> np.ndarray:
    from PIL import Image

    a = time.time()
    b = page.screenshot(timeout=180_000)
    SHOT_LOG.append((a, time.time()))
    if path is not None:
        path.write_bytes(b)
    return np.asarray(Image.open(io.BytesIO(b)).convert("RGB"), np.int16)


def has_points(img: np.ndarray) -> bool:
    h, w = img.shape[:2]
    return float(img[h // 4:, : int(0.6 * w)].mean(axis=2).std()) > 20


class FileCorrections:
    """relabel / undo / redo / stack hooks writing the net override layer the app writes
    (occufly.lifting.corrections), an in-memory edit stack instead of the database."""

    def __init__(self, ws: Path) -> None:
        self.ws, self.edits, self.undone = ws, [], []

    def _write(self) -> None:
        if self.edits:
            ids = np.concatenate([e[0] for e in self.edits])
            lab = np.concatenate([np.full(len(e[0]), e[1], np.uint8) for e in self.edits])
        else:
            ids, lab = np.zeros(0, np.int64), np.zeros(0, np.uint8)
        write_overrides(self.ws, ids, lab)

    def relabel(self, scene_id, point_ids, to_class, comment, user, frame_index=None) -> dict:
        self.edits.append((np.asarray(point_ids, np.int64), int(to_class)))
        self.undone.clear()
        self._write()
        return {"id": len(self.edits), "n_points": len(point_ids)}

    def undo(self, scene_id, user) -> dict:
        e = self.edits.pop()
        self.undone.append(e)
        self._write()
        return {"id": len(self.edits) + 1, "n_points": len(e[0])}

    def redo(self, scene_id, user) -> dict:
        self.edits.append(self.undone.pop())
        self._write()
        return {"id": len(self.edits), "n_points": len(self.edits[-1][0])}

    def stack(self, scene_id, user) -> dict:
        return {"undo": len(self.edits) or None, "redo": len(self.undone) or None}

    def hooks(self) -> dict:
        return {"relabel": self.relabel, "undo": self.undo, "redo": self.redo,
                "stack": self.stack}


def _proc_tree(root_pid: int) -> list[int]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                ppid = int(Path(f"/proc/{d}/stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            kids.setdefault(ppid, []).append(int(d))
    out, todo = [], [root_pid]
    while todo:
        p = todo.pop()
        for c in kids.get(p, []):
            out.append(c)
            todo.append(c)
    return out


def browser_cpu_s() -> float:
    """CPU seconds (user + sys) of this process's children so far: Chromium's processes."""
    tick, total = os.sysconf("SC_CLK_TCK"), 0
    for pid in _proc_tree(os.getpid()):
        try:
            f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        total += int(f[11]) + int(f[12])  # utime, stime
    return total / tick


def tab_memory(page) -> dict:
    """RSS / peak RSS (MB) of Chromium's renderer(s) and GPU process, and the JS heap."""
    out: dict = {"renderer_rss_mb": 0.0, "renderer_peak_mb": 0.0, "gpu_rss_mb": 0.0,
                 "gpu_peak_mb": 0.0}
    for pid in _proc_tree(os.getpid()):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
            status = Path(f"/proc/{pid}/status").read_text()
        except OSError:
            continue
        kb = {ln.split(":")[0]: int(ln.split()[1]) for ln in status.splitlines()
              if ln.startswith(("VmRSS", "VmHWM"))}
        kind = ("renderer" if "--type=renderer" in cmd else
                "gpu" if "--type=gpu-process" in cmd else None)
        if kind is None or "VmRSS" not in kb:
            continue
        out[f"{kind}_rss_mb"] += kb["VmRSS"] / 1024
        out[f"{kind}_peak_mb"] += kb.get("VmHWM", 0) / 1024
    heap = page.evaluate("() => performance.memory ? performance.memory.usedJSHeapSize : null")
    out["js_heap_mb"] = None if heap is None else heap / 2**20
    out["tab_total_rss_mb"] = out["renderer_rss_mb"] + out["gpu_rss_mb"]
    out["tab_total_peak_mb"] = out["renderer_peak_mb"] + out["gpu_peak_mb"]
    return {k: (round(v, 1) if isinstance(v, float) else v) for k, v in out.items()}


# counts the frames three.js renders (one clear() per frame): viser renders on demand, so
# requestAnimationFrame alone also counts frames that draw nothing
# and keeps the wall-clock time (ms since the epoch) of the last 400 of them for the trace
RENDER_HOOK = """(() => { const w = window; w.__renders = 0; w.__renderTimes = [];
  for (const C of [self.WebGLRenderingContext, self.WebGL2RenderingContext]) { if (!C) continue;
    const clear = C.prototype.clear;
    C.prototype.clear = function (m) { w.__renders++; w.__renderTimes.push(Date.now());
      if (w.__renderTimes.length > 400) w.__renderTimes.shift();
      return clear.call(this, m); }; } })();"""


def orbit_fps(page, svc, st, seconds: float, hz: float = 30.0, warm_s: float = 5.0) -> dict:
    """Frames rendered per second while the view orbits the scene centre.

    The camera is moved by the server at ``hz`` (viser camera updates), and each step is
    signalled to the viewer as the browser's own camera message is when a reviewer drags
    (``camera_moved``, what viser's camera ``on_update`` calls); frames are counted after
    ``warm_s`` of orbiting (a frame of the full level still in flight when the motion starts
    takes seconds under software WebGL). Playwright's mouse is not
    used: each synthetic mouse event waits until the renderer acknowledges it, which under
    software WebGL stalls the driver for seconds, not the page."""
    cam = st.client.camera
    c = np.asarray(cam.look_at, np.float64)
    p0 = np.asarray(cam.position, np.float64) - c
    rad, a0 = float(np.hypot(p0[0], p0[1])), float(np.arctan2(p0[1], p0[0]))
    t0 = t1 = time.perf_counter()
    k = 0
    n0 = None
    nxt = t0
    while n0 is None or time.perf_counter() - t1 < seconds:  # (that evaluate may block)
        if n0 is None and time.perf_counter() - t0 >= warm_s:  # the frame in flight is done
            n0, f0 = page.evaluate("() => [window.__renders, (window.__frames || []).length]")
            t1 = time.perf_counter()
        a = a0 + 0.03 * k
        with st.client.atomic():
            cam.position = tuple(c + np.array([rad * np.cos(a), rad * np.sin(a), p0[2]]))
            cam.look_at = tuple(c)
        if svc.lod_scheme != "legacy":
            svc.camera_moved(st)
        k += 1
        nxt = max(nxt + 1.0 / hz, time.perf_counter())
        time.sleep(max(0.0, nxt - time.perf_counter()))
    n1, f1 = page.evaluate("() => [window.__renders, (window.__frames || []).length]")
    dt = time.perf_counter() - t1
    # fps: animation frames that rendered (PROBE_HOOK's __frames); viser clears the canvas
    # several times a frame (4 under these runs), so the WebGL clear() count the figures
    # before 2026-12-06 16:00 called fps ("clears_per_s") was that many times the frames
    return {"fps": round((f1 - f0) / dt, 2), "frames": f1 - f0,
            "clears_per_s": round((n1 - n0) / dt, 2), "clears": n1 - n0,
            "seconds": round(dt, 2), "warm_s": warm_s, "camera_updates": k}


def rest_frames(page, seconds: float) -> dict:
    """The frames the page renders at rest (the level of detail shown, the camera still:
    viser keeps rendering) over ``seconds``: their count and the median and largest interval
    between frame starts -- how long a change waits for the frame in flight."""
    w0 = time.time()
    page.wait_for_timeout(int(1000 * seconds))
    starts = [t / 1000 for t in page.evaluate("() => window.__frames || []") if t / 1000 >= w0]
    gaps = np.diff(starts) if len(starts) > 1 else np.zeros(0)
    return {"seconds": seconds, "frames": len(starts),
            "interval_median_s": round(float(np.median(gaps)), 3) if len(gaps) else None,
            "interval_max_s": round(float(gaps.max()), 3) if len(gaps) else None}


def lasso_polygon(st, cam, want: int) -> tuple[np.ndarray, int]:
    """A screen rectangle (as a lasso polygon) left of the panels holding ~``want`` points."""
    xyz = np.asarray(st.data.scene.xyz)
    step = max(1, len(xyz) // 1_000_000)
    sub = np.asarray(xyz[::step], np.float32)
    pos, wxyz, fov, asp = cam
    u, v, front = sel.project_to_screen(sub, pos, wxyz, fov, asp)
    cu, cv = 0.3, 0.6
    lo, hi = 0.005, 0.3
    for _ in range(20):
        half = (lo + hi) / 2
        n = int((front & (np.abs(u - cu) < half) & (np.abs(v - cv) < half * VIEW[0] / VIEW[1]))
                .sum()) * step
        lo, hi = (half, hi) if n < want else (lo, half)
    hv = half * VIEW[0] / VIEW[1]
    poly = np.array([[cu - half, cv - hv], [cu + half, cv - hv], [cu + half, cv + hv],
                     [cu - half, cv + hv]])
    return poly, n


def blue_share(img: np.ndarray, poly: np.ndarray, colour: np.ndarray = BLUE) -> float:
    """Share of the pixels inside the lasso's bounding box close to ``colour``."""
    h, w = img.shape[:2]
    (u0, v0), (u1, v1) = poly.min(axis=0), poly.max(axis=0)
    crop = img[int(v0 * h) + 2:int(v1 * h) - 2, int(u0 * w) + 2:int(u1 * w) - 2]
    return float((np.abs(crop - colour).sum(axis=2) < 60).mean())


def wait_shot(page, pred, timeout_s: float, t0: float) -> tuple[float | None, np.ndarray | None]:
    img = None
    while time.perf_counter() - t0 < timeout_s:
        img = shot(page)
        if pred(img):
            return time.perf_counter() - t0, img
        page.wait_for_timeout(100)
    return None, img


def trace_refreshes(svc) -> None:
    """Record the start and end of every refresh of the viewer (its refresh thread calls
    ``refresh_now``) in :data:`REFRESH_LOG`."""
    orig = type(svc).refresh_now

    def traced(self, *a, **kw):  # noqa: ANN001, ANN202
        t = time.time()
        try:
            return orig(self, *a, **kw)
        finally:
            REFRESH_LOG.append((t, time.time()))

    svc.refresh_now = traced.__get__(svc)


def timeline(page, stats: dict, t0: float, t_end: float) -> dict:
    """What happened between ``t0`` and ``t_end`` (wall clock), in seconds after ``t0``:
    the viewer's refreshes, the frames the proxy sent to the browser (count, MB, first and
    last), the WebGL frames the page started (the render hook's clear() times: several per
    frame), the frame probe's log (frame finished, colour share, background share) and the
    screenshots taken."""
    off = time.time() - time.perf_counter()
    msgs, prev = [], None
    for t, cum in list(stats.get("log", [])):
        if prev is not None and t0 <= t + off <= t_end:
            msgs.append((t + off - t0, cum - prev))
        prev = cum
    renders = [t / 1000 - t0 for t in page.evaluate("() => window.__renderTimes || []")
               if t0 <= t / 1000 <= t_end]

    def r(v: float) -> float:
        return round(v, 3)

    return {"refreshes": [[r(a - t0), r(b - t0)] for a, b in REFRESH_LOG if t0 <= a <= t_end],
            "ws_frames": len(msgs), "ws_mb": round(sum(b for _t, b in msgs) / 2**20, 2),
            "ws_first_last": [r(msgs[0][0]), r(msgs[-1][0])] if msgs else None,
            "ws_big": [[r(t), round(b / 2**20, 2)] for t, b in msgs if b > 1 << 20],
            "webgl_frames": [r(t) for t in renders],
            "probe": [[r(t / 1000 - t0), round(a, 3), round(b, 3), fi] for t, a, b, fi in
                      page.evaluate("() => window.__probeLog || []") if t0 <= t / 1000 <= t_end],
            "frame_starts": {i: r(t / 1000 - t0) for i, t in
                             enumerate(page.evaluate("() => window.__frames || []"))
                             if t0 <= t / 1000 <= t_end},
            "shots": [[r(a - t0), r(b - t0)] for a, b in SHOT_LOG if t0 <= a <= t_end]}


# the frame probe: after every animation frame that rendered, the pixels of a screen box are
# read from the WebGL2 drawing buffer (before the compositor takes it) into a pixel buffer
# behind a fence, and once the fence has passed (the frame is rasterised; polled every 10 ms,
# so the page's main thread is never held) the shares close to a colour and to the
# background (transparent: the page's white) are logged with that wall-clock time and the
# frame's index (a frame is finished at the latest when the next one starts, see
# wait_drawn): when the browser has *drawn* a change, without the screenshots that polled
# for it (each one is itself a frame of everything shown, seconds under software WebGL). The background share tells a frame of the whole level of
# detail from one of the coarse level alone (drawn while the camera moves or an update is
# on its way: its gaps show the background), which must not count as the change drawn.
PROBE_HOOK = """(() => { const w = window; w.__gl = null;
  const gc = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (t, a) { const c = gc.call(this, t, a);
    if (c && (t === 'webgl2' || t === 'webgl')) w.__gl = c; return c; };
  const raf = w.requestAnimationFrame.bind(w); w.__frames = [];
  w.requestAnimationFrame = (cb) => raf((ts) => { const n = w.__renders, t = Date.now();
    cb(ts);
    if (w.__renders !== n) { w.__frames.push(t); if (w.__probe) w.__probe(w.__frames.length - 1); } });
})();"""

ARM_PROBE = """([u0, v0, u1, v1, col, tol]) => { const w = window; w.__probeLog = [];
  w.__probeRef = null;
  const pending = []; let polling = false;
  const poll = () => { const gl = w.__gl;
    while (pending.length) { const p = pending[0];
      if (gl.getSyncParameter(p.sync, gl.SYNC_STATUS) !== gl.SIGNALED) break;
      pending.shift(); const t = Date.now(); const px = new Uint8Array(4 * p.n);
      gl.bindBuffer(gl.PIXEL_PACK_BUFFER, p.buf);
      gl.getBufferSubData(gl.PIXEL_PACK_BUFFER, 0, px);
      gl.bindBuffer(gl.PIXEL_PACK_BUFFER, null); gl.deleteBuffer(p.buf); gl.deleteSync(p.sync);
      let k = 0, bg = 0;
      // col null: the share of pixels changed from the first frame probed (the reference)
      const ref = col === null ? (w.__probeRef = w.__probeRef || px) : null;
      for (let i = 0; i < p.n; i++) { const r = px[4 * i], g = px[4 * i + 1], b = px[4 * i + 2];
        if (ref !== null) { if (Math.abs(r - ref[4 * i]) + Math.abs(g - ref[4 * i + 1])
                                + Math.abs(b - ref[4 * i + 2]) >= tol) k++; }
        else if (Math.abs(r - col[0]) + Math.abs(g - col[1]) + Math.abs(b - col[2]) < tol) k++;
        if (px[4 * i + 3] < 128 || 765 - r - g - b < tol) bg++; }
      w.__probeLog.push([t, k / p.n, bg / p.n, p.frame]); }
    polling = pending.length > 0; if (polling) setTimeout(poll, 10); };
  w.__probe = (frame) => { const gl = w.__gl; if (!gl) return;
    const W = gl.drawingBufferWidth, H = gl.drawingBufferHeight;
    const x0 = Math.floor(u0 * W), x1 = Math.ceil(u1 * W);
    const y0 = Math.floor((1 - v1) * H), y1 = Math.ceil((1 - v0) * H);
    const n = (x1 - x0) * (y1 - y0);
    // into a pixel buffer behind a fence: the main thread is not held while the GPU draws
    const buf = gl.createBuffer(); gl.bindBuffer(gl.PIXEL_PACK_BUFFER, buf);
    gl.bufferData(gl.PIXEL_PACK_BUFFER, 4 * n, gl.STREAM_READ);
    const rb = gl.getParameter(gl.READ_FRAMEBUFFER_BINDING);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
    gl.readPixels(x0, y0, x1 - x0, y1 - y0, gl.RGBA, gl.UNSIGNED_BYTE, 0);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, rb);
    gl.bindBuffer(gl.PIXEL_PACK_BUFFER, null);
    pending.push({buf, n, frame, sync: gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0)});
    gl.flush(); if (!polling) { polling = true; setTimeout(poll, 10); } };
  return w.__renders; }"""


def arm_probe(page, poly: np.ndarray, colour: np.ndarray | None) -> None:
    """Log, for every frame the page renders from now on, the share of the lasso's bounding
    box (2 px inside, as :func:`blue_share`) close to ``colour``; ``colour`` None: the share
    changed from the first frame logged (the reference: take a screenshot, which renders
    one, right after arming)."""
    (u0, v0), (u1, v1) = poly.min(axis=0), poly.max(axis=0)
    page.evaluate(ARM_PROBE, [float(u0) + 0.003, float(v0) + 0.003, float(u1) - 0.003,
                              float(v1) - 0.003,
                              None if colour is None else [int(c) for c in colour], 60])


def wait_drawn(page, pred, timeout_s: float, w0: float) -> tuple[float | None, list | None]:
    """(seconds after wall-clock ``w0`` at which the first frame whose probe (colour share,
    background share) satisfies ``pred`` was finished, that probe); (None, the last probe)
    after ``timeout_s``.

    Finished: the start of the page's next frame (Chromium begins one only when the one
    before is drawn) or the probe's fence, whichever came first. The fence alone reads
    late: the browser learns it has passed only with the next frame's swap, which under
    software WebGL can be a frame of all the points later."""
    last = None
    while time.time() - w0 < timeout_s:
        log, frames = page.evaluate("() => [window.__probeLog || [], window.__frames || []]")
        for t, share, bg, fi in log:
            last = [round(share, 3), round(bg, 3)]
            if t / 1000 >= w0 and pred(share, bg):
                return finished_at(t, fi, frames) - w0, last
        page.wait_for_timeout(100)
    return None, last


def finished_at(t_probe_ms: float, frame: int, frames: list) -> float:
    """Wall-clock seconds at which probed frame ``frame`` was finished: the start of the
    page's next frame or the probe's fence (``t_probe_ms``), whichever came first (see
    :func:`wait_drawn`)."""
    return min([t_probe_ms] + list(frames[frame + 1:frame + 2])) / 1000


def probed(page, wait_s: float = 30.0) -> tuple[float, float] | None:
    """(colour share, background share) of the last frame drawn (waiting for one)."""
    t = time.time()
    while time.time() - t < wait_s:
        log = page.evaluate("() => window.__probeLog || []")
        if log:
            return float(log[-1][1]), float(log[-1][2])
        page.wait_for_timeout(100)
    return None


def lasso_relabel(page, svc, st, want: int, shots: Path | None, stats: dict) -> dict:
    """Lasso ~``want`` points from the default view, relabel to water, undo; times until
    the browser has drawn each (frame probe: ``*_drawn_s``) and until a screenshot taken
    then shows it (``*_visible_s``), with the timeline of each step (``trace_*``)."""
    svc._place_camera(st)
    page.wait_for_timeout(1500)
    cam = st.client.camera
    camt = (np.asarray(cam.position), np.asarray(cam.wxyz), float(cam.fov), float(cam.aspect))
    poly, est = lasso_polygon(st, camt, want)
    base = blue_share(shot(page), poly)
    arm_probe(page, poly, BLUE)
    _b, bg0 = probed(page) or (0.0, 1.0)  # the whole LOD drawn: its gaps in the box
    cyan = np.array([0, 255, 255])
    arm_probe(page, poly, cyan)
    st.gui["sel_mode"].value = "replace"
    st.lasso, st.lasso_cam = [tuple(p) for p in poly], camt
    t0, w0 = time.perf_counter(), time.time()
    picked = corrections_panel.close_lasso(svc, st)
    t_sel = time.perf_counter() - t0
    t_hi, _p = wait_drawn(page, lambda s, bg: s > base + 0.1, 60, w0)
    if shots is not None:
        shot(page, shots / "viewer_scale_selection_1m.png")
    st.gui["to_class"].value = next(o for o in st.gui["to_class"].options
                                    if o.endswith(f"({WATER})"))
    page.wait_for_timeout(3000)  # the selection's frames are drawn
    arm_probe(page, poly, BLUE)
    probed(page)
    whole = bg0 + 0.05  # at most this much background: the whole level of detail is drawn
    t0, w0 = time.perf_counter(), time.time()
    corrections_panel.relabel(svc, st, st.gui["to_class"].value, "bench")
    t_call = time.perf_counter() - t0
    if args_sparse[0]:  # the change relative to the steady picture after it (see settled_drawn)
        t_drawn, p_rel = settled_drawn(page, w0, whole, base, rising=True)
    else:
        t_drawn, p_rel = wait_drawn(page, lambda s, bg: s > base + 0.1 and bg <= whole, 60, w0)
    img = shot(page, shots / "viewer_scale_relabelled.png" if shots is not None else None)
    t_vis = time.time() - w0
    trace_relabel = timeline(page, stats, w0, time.time())
    after = blue_share(img, poly)
    page.wait_for_timeout(3000)
    arm_probe(page, poly, BLUE)
    t0, w0 = time.perf_counter(), time.time()
    corrections_panel.undo_redo(svc, st, "undo")
    t_undo_call = time.perf_counter() - t0
    if args_sparse[0]:
        t_undo, p_undo = settled_drawn(page, w0, whole, base, rising=False)
    else:
        t_undo, p_undo = wait_drawn(page, lambda s, bg: s < base + 0.03 and bg <= whole, 60, w0)
    img = shot(page)
    t_undo_vis = time.time() - w0
    trace_undo = timeline(page, stats, w0, time.time())

    def r(v: float | None) -> float | None:
        return None if v is None else round(v, 3)

    return {"selected_points": int(len(picked)), "estimate": est,
            "close_lasso_s": r(t_sel), "selection_drawn_s": r(t_hi),
            "relabel_call_s": r(t_call), "relabel_drawn_s": r(t_drawn),
            "relabel_visible_s": r(t_vis) if after > base + 0.1 else None,
            "undo_call_s": r(t_undo_call), "undo_drawn_s": r(t_undo),
            "undo_visible_s": r(t_undo_vis) if blue_share(img, poly) < base + 0.03 else None,
            "blue_share_before_after": [round(base, 3), round(after, 3)],
            "probe_background_whole_lod": round(bg0, 3),
            "probe_at_drawn": {"relabel": p_rel, "undo": p_undo},
            "trace_relabel": trace_relabel, "trace_undo": trace_undo}


args_sparse = [False]  # --relabel-relative: set in main


def settled_drawn(page, w0: float, whole: float, base: float,
                  rising: bool) -> tuple[float | None, list | None]:
    """(seconds after wall-clock ``w0`` at which the first frame showed 80 % of the change
    the picture settles to, that probe), for a level of detail too sparse for the fixed
    ``base + 0.1`` blue share of :func:`wait_drawn` (a slow browser's resting level shows
    the lasso's box mostly as background: on the 32 M scene 150 k points gave 3 % blue).
    The change is the blue share's move from ``base`` (relabel) or to it (undo) in frames
    with the whole level of detail (background share <= ``whole``); settled: steady for
    3 s (:func:`settle`)."""
    final = settle(page, w0, span_s=3.0, tol=0.003, max_s=60.0)
    log, frames = page.evaluate("() => [window.__probeLog || [], window.__frames || []]")
    rows = [(finished_at(t, fi, frames), share, bg) for t, share, bg, fi in log
            if t / 1000 >= w0]
    if final is None or not rows:
        return None, None
    peak = max(share for _t, share, _bg in rows) if not rising else final
    for t, share, bg in rows:
        if bg > whole:
            continue
        if rising and final > base + 0.005 and share >= base + 0.8 * (final - base):
            return t - w0, [round(share, 3), round(bg, 3)]
        if not rising and share <= final + 0.2 * (peak - final):
            return t - w0, [round(share, 3), round(bg, 3)]
    return None, [round(final, 3), None]


def toggles(page, st, n: int) -> dict:
    """Click the road checkbox in the browser; latency until the server sees it."""
    lat = []
    row = page.locator("div.mantine-Flex-root", has=page.get_by_text("road (", exact=False))
    box = row.locator("input").last.element_handle(timeout=300_000)
    for i in range(n):
        want_hidden = i % 2 == 0
        t1 = time.perf_counter()
        box.evaluate("e => e.click()")  # JS click: no wait for rAF-stable layout
        while st.class_visible.get(1, True) == want_hidden and time.perf_counter() - t1 < 20:
            page.wait_for_timeout(5)
        lat.append(time.perf_counter() - t1)
        page.wait_for_timeout(300)
    return {"p50": round(statistics.median(lat), 3), "max": round(max(lat), 3)}


# ---- the voxel grids (issue 38: "the scene grid display") ---------------------------------
GRID_LOG: list[dict] = []  # one entry per traced call of the grid path (see trace_grids)
# what-if: keyword arguments the bench adds to every add_batched_meshes_simple of the grids
# (``--grid-what-if material=toon3``: not the app's code, a measured alternative)
GRID_MESH_OVERRIDES: dict = {}
CANVAS_BOX = np.array([[0.02, 0.25], [0.6, 0.98]])  # the canvas left of the panels (u, v)


def _boxes(nodes: list) -> dict:
    return {"nodes": len(nodes), "boxes": int(sum(len(nd.centers) for nd in nodes)),
            "edge_m": float(nodes[0].size) if nodes else None,
            "by_kind": {nd.name.rsplit("/", 1)[-1]: len(nd.centers) for nd in nodes}}


def trace_grids(svc) -> None:
    """Record wall and thread CPU of the viewer's grid path in :data:`GRID_LOG`: the whole
    ``send_grids`` (build + send, the callback of the "Scene grid" box and the frame
    dropdown), the scene grid's level of detail (:func:`grid_lod.scene_grid_nodes_lod`),
    a frame's camera grid sampled (``load_camera_grid``) and turned into nodes
    (``camera_grid_nodes``); the nodes' box counts (the functions are wrapped where
    scene_view looks them up, nothing else changes)."""
    from app.viewer import scene_builder, scene_view

    def wrap(mod, name: str, kind: str, summary) -> None:  # noqa: ANN001
        orig = getattr(mod, name)

        def traced(*a, **kw):  # noqa: ANN002, ANN003, ANN202
            t, c = time.time(), time.thread_time()
            out = orig(*a, **kw)
            GRID_LOG.append({"kind": kind, "start": t, "end": time.time(),
                             "cpu_s": time.thread_time() - c, **summary(out)})
            return out

        setattr(mod, name, traced)

    wrap(scene_view, "scene_grid_nodes_lod", "scene_build", _boxes)
    wrap(scene_view, "load_camera_grid", "camera_sample",
         lambda cg: {} if cg is None else {"shape": list(np.shape(cg[0]))})
    wrap(scene_builder, "camera_grid_nodes", "camera_build", _boxes)
    send_voxel_nodes = scene_builder.send_voxel_nodes

    class Overridden:  # the scene api, with GRID_MESH_OVERRIDES on the grids' meshes
        def __init__(self, api) -> None:  # noqa: ANN001
            self.api = api

        def add_batched_meshes_simple(self, *a, **kw):  # noqa: ANN002, ANN003, ANN202
            return self.api.add_batched_meshes_simple(*a, **(kw | GRID_MESH_OVERRIDES))

    scene_builder.send_voxel_nodes = lambda api, nodes, visible=None: send_voxel_nodes(
        Overridden(api) if GRID_MESH_OVERRIDES else api, nodes, visible)
    orig = type(svc).send_grids

    def send_grids(self, st):  # noqa: ANN001, ANN202
        t, c = time.time(), time.thread_time()
        try:
            return orig(self, st)
        finally:
            GRID_LOG.append({"kind": "send_grids", "start": t, "end": time.time(),
                             "cpu_s": time.thread_time() - c,
                             "handles": len(st.grid_handles)})

    svc.send_grids = send_grids.__get__(svc)


def settle(page, since: float, span_s: float = 3.0, tol: float = 0.005,
           max_s: float = 120.0, min_share: float = 0.0) -> float | None:
    """Wait until the armed probe's share has been steady (within ``tol``) and at least
    ``min_share`` over frames started after wall-clock ``since`` and spanning ``span_s`` (at
    least three frames); the page renders continuously (viser's render loop: a few frames a
    second on an idle page), so quiet is a steady picture, not an absence of frames (and
    frames without a change just sent go on for seconds under software WebGL: hence
    ``min_share``). Returns that share, or None after ``max_s``."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < max_s:
        log, frames = page.evaluate("() => [window.__probeLog || [], window.__frames || []]")
        ok = [(frames[fi] / 1000, share) for _t, share, _bg, fi in log
              if fi < len(frames) and frames[fi] / 1000 >= since]
        if len(ok) >= 3:
            last = ok[-1][1]
            k = len(ok) - 1
            while k > 0 and abs(ok[k - 1][1] - last) <= tol:
                k -= 1
            if len(ok) - k >= 3 and ok[-1][0] - ok[k][0] >= span_s and last >= min_share:
                return last
        page.wait_for_timeout(250)
    return None


def click_checkbox(page, label: str) -> float:
    """Click the GUI checkbox ``label`` in the browser (a JS click, as :func:`toggles`);
    returns the page's wall clock (s) at the click (the page's main thread, busy with
    software-rendered frames, takes the driver's call seconds later)."""
    row = page.locator("div.mantine-Flex-root", has=page.get_by_text(label, exact=True))
    box = row.locator("input").last.element_handle(timeout=300_000)
    return box.evaluate("e => { const t = Date.now(); e.click(); return t; }") / 1000


def view_at(st, centre: np.ndarray, extent: float) -> None:
    """The default view's angle (:meth:`SceneViewMixin._place_camera`) on ``centre``."""
    cam = st.client.camera
    with st.client.atomic():
        cam.up_direction = (0.0, 0.0, 1.0)
        cam.position = tuple(np.asarray(centre, np.float64)
                             + np.array([0.0, -0.9 * extent, 0.8 * extent]))
        cam.look_at = tuple(np.asarray(centre, np.float64))


def grid_shown(page, svc, st, stats: dict, kind: str, trigger, args,
               shot_path: Path | None) -> dict:
    """One grid display: ``trigger()`` (the box ticked / the frame chosen) -> the boxes
    drawn, seen by the frame probe in reference mode (:data:`ARM_PROBE` with no colour:
    the share of the canvas left of the panels that changed from the frame before).

    ``first_boxes_s``: the tick (the page's clock at the click; the call for the dropdown,
    ``tick_after_call_s`` after the driver's call) -> the first finished frame with >= 2 %
    of the box changed; ``drawn_s``: -> the first finished frame, started after the server
    had sent every node, within 2 % of the final picture's change (steady for 3 s after:
    :func:`settle`; ``drawn_after_call_s`` from the driver's call);
    ``visible_s``: -> a screenshot taken then has returned; server: when ``send_grids`` ran
    (seconds after the call), its and the build's wall and thread CPU (:func:`trace_grids`),
    the level of detail, the boxes sent; ``ws_bytes`` / ``ws_frames`` / ``ws_first_last_s``:
    what the proxy sent meanwhile; ``browser_cpu_s_to_steady``: Chromium's CPU from the
    call to the steady picture; ``orbit`` with the grid shown and the tab's ``memory``."""
    st.lod_done.wait(600)
    t = time.perf_counter()
    arm_probe(page, CANVAS_BOX, None)  # the view still moving or filling in: not steady
    steady = settle(page, time.time(), max_s=min(180.0, args.grid_timeout)) is not None
    waited = time.perf_counter() - t
    arm_probe(page, CANVAS_BOX, None)  # the reference: the next frame (the page renders
    ref = probed(page)  # continuously)
    n_log, b0 = len(GRID_LOG), int(stats["bytes"])
    c0, w0 = browser_cpu_s(), time.time()
    tick = trigger() or w0  # the page's clock at the click, or now
    sent = None
    while time.time() - w0 < args.grid_timeout:
        sent = next((e for e in GRID_LOG[n_log:] if e["kind"] == "send_grids"), None)
        if sent is not None:
            break
        page.wait_for_timeout(50)
    if sent is None:
        return {"error": f"send_grids not done in {args.grid_timeout} s"}
    steady_after = settle(page, sent["end"], max_s=args.grid_timeout, min_share=0.02)
    log, frames = page.evaluate("() => [window.__probeLog || [], window.__frames || []]")
    after = [(finished_at(t, fi, frames), share, frames[fi] / 1000 if fi < len(frames) else 0)
             for t, share, _bg, fi in log if t / 1000 >= w0]
    final = after[-1][1] if after else 0.0
    first = next((d for d, s, _f in after if s >= 0.02), None)
    drawn = next((d for d, s, f in after if f >= sent["end"] and s >= final - 0.02), None)
    c1 = browser_cpu_s()  # the drawing and the steady frames after it (not the screenshot)
    img = shot(page, shot_path)
    t_vis = time.time() - w0
    b1 = int(stats["bytes"])
    trace = timeline(page, stats, w0, time.time())
    build = [e for e in GRID_LOG[n_log:] if e["kind"] != "send_grids"]

    def r(v: float | None) -> float | None:
        return None if v is None else round(v, 3)

    out = {"kind": kind, "settled_before_s": round(waited, 2), "steady_before": steady,
           "tick_after_call_s": r(tick - w0), "steady_after": steady_after is not None,
           "first_boxes_s": r(first - tick if first else None),
           "drawn_s": r(drawn - tick if drawn else None),
           "drawn_after_call_s": r(drawn - w0 if drawn else None), "visible_s": r(t_vis),
           "changed_share_final": round(final, 3),
           "browser_cpu_s_to_steady": round(c1 - c0, 2), "wall_s_to_steady": r(
               max(t for t, _s, _f in after) - w0 if after else None),
           "reference_probe": None if ref is None else [round(v, 3) for v in ref],
           "has_points_after": has_points(img),
           "server": {"send_grids_after_s": [r(sent["start"] - w0), r(sent["end"] - w0)],
                      "send_grids_wall_s": r(sent["end"] - sent["start"]),
                      "send_grids_cpu_s": r(sent["cpu_s"]), "handles": sent["handles"],
                      "steps": [{k: (r(v) if isinstance(v, float) else v)
                                 for k, v in e.items() if k not in ("start", "end")}
                                | {"wall_s": r(e["end"] - e["start"])} for e in build]},
           "ws_bytes": b1 - b0, "ws_mb": round((b1 - b0) / 2**20, 2),
           "ws_frames": trace["ws_frames"], "ws_first_last_s": trace["ws_first_last"],
           "webgl_frames": len(trace["webgl_frames"]),
           "frame_starts_s": list(trace["frame_starts"].values())[:40]}
    step = next((e for e in build if e["kind"] in ("scene_build", "camera_build")), None)
    if step is not None:
        out["boxes"], out["box_edge_m"] = step["boxes"], step["edge_m"]
        if step["kind"] == "scene_build" and step["edge_m"]:  # level k: 2**k x the voxel
            out["lod_level"] = int(round(np.log2(step["edge_m"]
                                                 / float(st.data.grid.voxel_size))))
    page.wait_for_timeout(1000)
    out["orbit"] = orbit_fps(page, svc, st, args.orbit_s)
    out["memory"] = tab_memory(page)
    return out


def grid_frame(st, name: str | None) -> int:
    """The frame whose camera grid is shown: ``name`` (a stem or an index), else the first
    frame of the workspace's selection (``selection.json``), else the middle frame."""
    scene = st.data.scene
    if name is not None:
        return int(name) if name.isdigit() else scene.frame_index(name)
    sel_path = st.data.workspace / "selection.json" if st.data.workspace else None
    if sel_path is not None and sel_path.is_file():
        chosen = json.loads(sel_path.read_text()).get("frames") or []
        if chosen:
            return int(chosen[0])
    return len(scene.frames) // 2


def measure_grids(page, svc, st, stats: dict, args, shots: Path | None) -> dict:
    """The scene grid (the "Scene grid" box ticked in the browser, from the default view),
    then one frame's camera grid alone (the scene grid unticked; the frame chosen in the
    "Camera grid of frame" dropdown -- set on the server, as the browser's message does;
    seen from the default view's angle on the camera grid's middle)."""
    from occufly.sampling import FrameGridSpec

    d = st.data
    out: dict = {}
    if d.grid is not None:
        g = d.grid
        out["scene_grid"] = {"shape": list(np.shape(g.labels)),
                             "voxel_size": float(g.voxel_size)}
    svc._place_camera(st)
    out["scene"] = grid_shown(page, svc, st, stats, "scene", lambda: click_checkbox(
        page, "Scene grid"), args, shots / "viewer_scale_grid.png" if shots else None)
    out["scene"]["grid_info"] = st.gui["grid_info"].content

    def untick() -> None:
        click_checkbox(page, "Scene grid")  # off again
        t = time.perf_counter()
        while st.gui["grid_scene"].value and time.perf_counter() - t < 60:
            page.wait_for_timeout(50)

    untick()
    if args.grid_what_if:  # the scene grid again, drawn with other mesh options
        GRID_MESH_OVERRIDES.update(dict(kv.split("=", 1) for kv in args.grid_what_if.split(",")))
        svc._place_camera(st)
        try:
            out["scene_what_if"] = grid_shown(page, svc, st, stats, "scene", lambda: click_checkbox(
                page, "Scene grid"), args, shots / "viewer_scale_grid_what_if.png" if shots
                else None)
            out["scene_what_if"]["mesh_options"] = dict(GRID_MESH_OVERRIDES)
        finally:
            GRID_MESH_OVERRIDES.clear()
        untick()
    fi = grid_frame(st, args.grid_frame)
    fr = d.scene.frames[fi]
    spec = FrameGridSpec()
    T = np.linalg.inv(np.asarray(fr.T_cam_world, np.float64))
    depth = spec.shape[2] * spec.voxel_size
    centre = T[:3, 3] + T[:3, 2] * depth / 2  # the camera grid's middle, scene-local
    view_at(st, centre, 1.2 * depth)
    stem = fr.stem

    def choose() -> None:  # the browser's message is handled off the socket's thread
        threading.Thread(target=lambda: setattr(st.gui["grid_frame"], "value", stem),
                         daemon=True).start()

    out["camera"] = grid_shown(page, svc, st, stats, "camera", choose, args,
                               shots / "viewer_scale_camera_grid.png" if shots else None)
    out["camera"]["frame"] = {"index": fi, "stem": stem,
                              "size": [fr.camera.width, fr.camera.height]}
    st.gui["grid_frame"].value = "(none)"
    return out


DRAWN_LOG: list[tuple[float, float, int]] = []  # (end wall clock, seconds, points drawn)


def trace_drawn(svc) -> None:
    """Record every render round trip of the viewer (:meth:`SceneViewMixin._drawn`: the
    refinement's and a correction's) with the points the browser drew meanwhile, in
    :data:`DRAWN_LOG` (the draw times the resting level of detail is chosen from)."""
    orig = type(svc)._drawn

    def traced(self, st):  # noqa: ANN001, ANN202
        out = orig(self, st)
        if out is not None:
            DRAWN_LOG.append((time.time(), out, self._points_drawn(st)))
        return out

    svc._drawn = traced.__get__(svc)


def run_scheme(p, srv: LiveServer, svc, scheme: str, args, shots: Path | None) -> dict:
    # "progressive_keep_tiles": the new path with the tiles left shown during a correction's
    # update (ViewerService.hide_tiles_on_update off), to weigh that step on its own;
    # "progressive_full": the path before the adaptive resting level (every tile of the plan
    # sent whatever the browser's draw time: frame_budget_s None), before the motion level
    # (the whole coarse level drawn while moving) and before the grid's toon3 material and
    # motion hiding -- the baseline of issue 38's adaptive LOD
    from app.viewer import scene_builder

    base = scheme.removesuffix("_keep_tiles").removesuffix("_full")
    svc.lod_scheme = base
    svc.hide_tiles_on_update = not scheme.endswith("_keep_tiles")
    full = scheme.endswith("_full")
    svc.frame_budget_s = None if full else type(svc).frame_budget_s
    svc.hide_grid_on_motion = not full
    svc.motion_points = None if full else type(svc).motion_points  # the whole coarse level
    scene_builder.GRID_MATERIAL = "standard" if full else ADAPTIVE_GRID_MATERIAL
    with svc._lock:  # every scheme opens the scene cold (its data and plan made by its tab)
        svc._data.clear()
        svc._plans.clear()
    DRAWN_LOG.clear()
    browser = p.chromium.launch(executable_path="/usr/bin/chromium",
                                args=CHROMIUM_ARGS + ["--enable-precise-memory-info"])
    try:
        ctx = browser.new_context(viewport={"width": VIEW[0], "height": VIEW[1]})
        ctx.add_init_script(RENDER_HOOK)
        ctx.add_init_script(PROBE_HOOK)
        ctx.add_cookies([{"name": "occufly_session", "value": REVIEWER, "url": srv.url}])
        page = ctx.new_page()
        n_before = len(svc.proxy_stats)
        t0, t0_wall = time.perf_counter(), time.time()
        page.goto(srv.url + "/viewer/?scene=bench")
        st = None
        while st is None and time.perf_counter() - t0 < 300:
            st = next(iter(svc.client_states()), None)
            page.wait_for_timeout(20)
        t_conn = time.perf_counter() - t0
        if args.first_by_probe:  # no screenshots meanwhile: they are frames of their own and
            # would also be what the viewer's render round trips measure
            arm_probe(page, CANVAS_BOX, None)  # reference: the first frame (no points yet)
            t_drawn, _p = wait_drawn(page, lambda share, _bg: share >= 0.02, 600, t0_wall)
            page.evaluate("() => { window.__probe = null; }")
            t_first = t_drawn
        else:
            t_drawn = None
            t_first, _img = wait_shot(page, has_points, 600, t0)
            if shots is not None:
                shot(page, shots / "viewer_scale_first_points.png")
        if not st.lod_done.wait(600):
            raise RuntimeError("the level of detail was not sent in 600 s")
        lod_sent = st.lod_done_at - t0
        stats = svc.proxy_stats[n_before]
        while stats["last"] is None or stats["last"] < st.lod_done_at \
                or time.perf_counter() - stats["last"] < 0.5:
            page.wait_for_timeout(50)
        lod_recv = stats["last"] - t0
        shot(page, shots / "viewer_scale_full_lod.png" if shots else None)
        t_full = time.perf_counter() - t0
        out = {"connected_s": round(t_conn, 3),
               "first_sent_s": round(st.first_sent_at - t0, 3) if st.first_sent_at else None,
               "first_points_s": None if t_first is None else round(t_first, 3),
               "first_points_by": "frame probe" if args.first_by_probe else "screenshots",
               "lod_sent_s": round(lod_sent, 3), "lod_received_s": round(lod_recv, 3),
               "full_lod_s": round(t_full, 3), "points_shown": st.sent_points,
               "points_planned": len(st.lod_plan.ids) if st.lod_plan is not None else None,
               "lod_stopped": st.lod_stopped, "frame_budget_s": svc.frame_budget_s,
               "grid_material": scene_builder.GRID_MATERIAL,
               "render_round_trips": [[round(w - t0_wall, 3), round(dt, 3), n]
                                      for w, dt, n in DRAWN_LOG],
               "status": st.gui["status"].content,
               "ws_bytes": int(stats["bytes"]), "point_nodes": len(st.chunk_handles)
               or len(st.point_handles)}
        out["rest"] = rest_frames(page, args.rest_s)
        page.wait_for_timeout(1000)
        out["orbit"] = orbit_fps(page, svc, st, args.orbit_s)
        # drawn while moving: the coarse level (tiles hidden) or, on the old path, everything
        out["orbit"]["points_drawn"] = (st.lod_plan.n_coarse if st.lod_plan is not None
                                        and svc.motion_rest_s is not None else st.sent_points)
        out["memory_after_orbit"] = tab_memory(page)
        if args.grid:
            try:
                out["grids"] = measure_grids(page, svc, st, stats, args, shots)
            except Exception as e:  # noqa: BLE001
                out["grids"] = {"error": f"{type(e).__name__}: {str(e)[:300]}"}
        try:  # a step that fails (a timeout on a starved machine) is reported, not fatal
            if args.toggles:
                out["toggle_latency_s"] = toggles(page, st, args.toggles)
        except Exception as e:  # noqa: BLE001
            out["toggle_latency_s"] = {"error": f"{type(e).__name__}: {str(e)[:200]}"}
        if args.lasso:
            try:
                out["lasso"] = lasso_relabel(page, svc, st, args.lasso, shots, stats)
            except Exception as e:  # noqa: BLE001
                out["lasso"] = {"error": f"{type(e).__name__}: {str(e)[:200]}"}
        out["memory_end"] = tab_memory(page)
        ctx.close()
        while svc.client_states():
            time.sleep(0.05)
        return out
    finally:
        browser.close()


def link_workspace(src: Path, dst: Path) -> dict:
    """``dst``: a tree of hard links to workspace ``src``'s files (read-only use: the viewer
    reads them memory-mapped; whatever it writes -- the bench's correction layer -- is
    written atomically under a new name, replacing a link, never into ``src``'s files).

    Not the app's import of a workspace (``app.pipeline.import_scene``, which
    bench_api_load's ``--workspace`` goes through): that writes the scene's points and
    correspondences anew (~10 GB on the survey) and leaves the lifted labels and the voxel
    grid behind, the very things the viewer shows. Refuses another file system."""
    src, dst = Path(src).resolve(), Path(dst)
    if not (src / "scene.json").is_file():
        raise SystemExit(f"--workspace {src}: not a workspace (no scene.json)")
    if os.stat(src).st_dev != os.stat(dst.parent).st_dev:
        raise SystemExit(f"--workspace {src} and the bench's folder {dst.parent} are on "
                         "different file systems: no hard links (use --tmp-dir on the same one)")
    n, size = 0, 0
    for d, _dirs, files in os.walk(src):
        rel = Path(d).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for f in files:
            a = Path(d) / f
            if a.is_symlink():
                os.symlink(os.readlink(a), dst / rel / f)
                continue
            os.link(a, dst / rel / f)
            n += 1
            size += a.stat().st_size
    return {"files": n, "gb": round(size / 2**30, 2)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--workspace", type=Path, default=None,
                    help="an existing workspace (e.g. after occufly voxelize) instead of the "
                    "fabricated points: hard-linked into the bench's data dir as scene 'bench'")
    ap.add_argument("--tmp-dir", type=Path, default=None,
                    help="where the bench's data dir goes (on --workspace's file system)")
    ap.add_argument("--grid", action="store_true",
                    help="also measure the voxel grids: the scene grid, one frame's camera grid")
    ap.add_argument("--grid-frame", default=None,
                    help="the camera grid's frame (stem or index; default: the first selected)")
    ap.add_argument("--grid-timeout", type=float, default=600.0)
    ap.add_argument("--grid-npz", type=Path, default=None,
                    help="with --workspace: show this scene grid (.npz) instead of the "
                    "workspace's (linked into the bench's copy only)")
    ap.add_argument("--grid-what-if", default=None,
                    help="the scene grid once more with these add_batched_meshes_simple "
                    "options, e.g. material=toon3 (a measured alternative, not the app's)")
    ap.add_argument("--max-points", type=int, default=None, help="the viewer's LOD budget")
    ap.add_argument("--toggles", type=int, default=6)
    ap.add_argument("--orbit-s", type=float, default=5.0)
    ap.add_argument("--first-by-probe", action="store_true",
                    help="first points: the first frame drawn with them (the frame probe), "
                    "no screenshots until the level of detail is sent (the older figures "
                    "polled with screenshots)")
    ap.add_argument("--relabel-relative", action="store_true",
                    help="relabel / undo drawn: 80 %% of the change the picture settles to "
                    "(a sparse resting level), not a fixed 0.1 blue share")
    ap.add_argument("--rest-s", type=float, default=6.0,
                    help="frames counted at rest after the full level of detail")
    ap.add_argument("--lasso", type=int, default=1_000_000)
    ap.add_argument("--schemes", default="legacy,progressive")
    ap.add_argument("--shots", type=Path, default=None)
    args = ap.parse_args()
    args_sparse[0] = args.relabel_relative
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(dir=args.tmp_dir) as tmp:
        root = Path(tmp)
        t = time.perf_counter()
        if args.workspace is not None:
            source = {"workspace": str(args.workspace),
                      **link_workspace(args.workspace, root / "bench")}
            if args.grid_npz is not None:  # a scene grid from elsewhere (e.g. the synthetic
                grid = root / "bench" / "grid" / "scene_grid.npz"  # truth) in the copy only
                grid.parent.mkdir(exist_ok=True)
                grid.unlink(missing_ok=True)
                os.link(args.grid_npz, grid)
                source["scene_grid"] = str(args.grid_npz)
            args.points = int(json.loads((root / "bench" / "scene.json").read_text())
                              ["n_points"])
        else:
            make_demo_workspace(root / "bench", args.points, seed=1, with_grid=False)
            source = {"fabricated": "make_demo_workspace", "seed": 1}
        gen_s = time.perf_counter() - t
        kw = {"max_points": args.max_points} if args.max_points else {}
        app = make_app(root, corrections=FileCorrections(root / "bench").hooks(), **kw)
        svc = app.state.viewer
        trace_refreshes(svc)
        trace_drawn(svc)
        if args.grid:
            trace_grids(svc)
        result: dict = {"bench": "viewer_scale", "source": source, "points": args.points,
                        "max_points": svc.max_points, "coarse_points": svc.preview_points,
                        "tiles": svc.lod_tiles ** 2, "generate_s": round(gen_s, 2),
                        "cpus": os.cpu_count(), "load_avg_start": os.getloadavg()}
        with LiveServer(app) as srv, sync_playwright() as p:
            for scheme in args.schemes.split(","):
                result[scheme] = run_scheme(p, srv, svc, scheme, args,
                                            args.shots if scheme == "progressive" else None)
                print(json.dumps({scheme: result[scheme]}), file=sys.stderr, flush=True)
        result["load_avg_end"] = os.getloadavg()
        ru = resource.getrusage(resource.RUSAGE_SELF)  # the app's viewer and this driver
        result["bench_process"] = {"cpu_s": round(ru.ru_utime + ru.ru_stime, 1),
                                   "peak_rss_mb": round(ru.ru_maxrss / 1024)}
        for base in ("legacy", "progressive_full"):
            if base not in result or "progressive" not in result:
                continue
            old, new = result[base], result["progressive"]
            ratio = {}
            for k in ("first_points_s", "full_lod_s"):
                if old.get(k) and new.get(k):
                    ratio[k] = round(new[k] / old[k], 3)
            ratio["orbit_fps"] = round(new["orbit"]["fps"] / max(old["orbit"]["fps"], 1e-6), 2)
            lo, ln = old.get("lasso", {}), new.get("lasso", {})
            for k in ("relabel_drawn_s", "undo_drawn_s", "relabel_visible_s", "undo_visible_s"):
                if lo.get(k) and ln.get(k):
                    ratio[k] = round(ln[k] / lo[k], 3)
            result["ratio_new_vs_" + base] = ratio
        print(json.dumps(result))


if __name__ == "__main__":
    main()
