"""Issue 38's "Review on the survey" budgets, measured over the app's HTTP API the way the
reviewer's and the admin's pages ask for them.

The budgets: the review list and the suspects list of a survey with 200 submitted masks open
in <= 1 s; a frame (20 MP) opens in <= 1 s the first time and <= 0.3 s for the next frame in
the list; the admin page's quality section in <= 2 s.

The app runs as real processes (``occufly serve``, bench/_app_harness.py, as in
bench/bench_api_load.py) on a scratch data dir and database (SQLite, or ``--db postgresql``:
a scratch database on ``--postgres-url``'s server, dropped after). The scene is imported by
the app's own import job from ``--source`` (an ``occufly synth`` folder; ``--workspace``: a
workspace already imported from it, which the job copies) or from the synthetic ``--preset``
(generated and imported once into ``--root``, bench/_scene.py). ``--masks N`` frames are
handed out: the full-size frames first (the survey preset's 20 frames of 5472 x 3648), then
the scene's stratified selection (``occufly select``), then frames evenly spread over the
rest; an annotator leases each (``POST /scenes/{sid}/next``) and submits the frame's
synthetic truth mask (``PUT /frames/{fid}/mask?kind=submitted``, encoded as the editor
encodes it). The bench then polls ``GET /scenes/{sid}/labels/status`` (as the editor does)
until every submitted version is in the filled labels, and waits until the server is idle
(its processes use < 5 % of a core over 5 s: the post-fill refresh of the stored agreement,
the suspects list and the review list's top frames, done by the server after each fill).

What is timed, request for request as the pages make them (frontend/js/pages/reviewer.js,
admin.js), with 6 connections at most in flight (a browser's per-host limit on HTTP/1.1):

- ``review_list``: the page's start with ``state=submitted``: ``GET /scenes``, then
  ``GET /scenes/{sid}/frames?sort=disagreement&state=submitted``.
- ``suspects``: the Suspects tab: ``GET /scenes/{sid}/suspects``, then ``GET /scenes/{sid}``.
- ``open_frame``: ``openFrame``: ``GET /frames/{fid}``, then at once ``GET /scenes/{sid}``,
  ``/frames/{fid}/agreement``, ``/scenes/{sid}/review-items``,
  ``/frames/{fid}/image?size=preview`` (the full image if that is 404), ``/frames/{fid}/mask``,
  ``/frames/{fid}/render``, ``/frames/{fid}/disagreement``; the frame is usable when all have
  answered (their bodies read). ``GET /frames/{fid}/projected-items``, which the page sends
  after that without waiting for it, is timed apart. The page prefetches nothing: the
  server does (``app.review.service.prefetch_next``: the agreement request of a frame
  starts the review of the next ``PREFETCH_NEXT`` frames of the list in a background
  thread). So "next in the list" is the reviewer pressing N ``--dwell`` seconds after the
  previous frame became usable (the time spent looking at it).
  Frames opened: the list's top (``top``), then N ``--next`` times (``next``), then frames
  clicked in the list that nothing prefetched (``click``: the full-size frames first, then
  frames from the middle of the list), then the first two opened again (``reopen``: warm).
- ``quality``: the admin page's quality section: ``GET /scenes/{sid}/quality``, asked again
  every 3 s while it answers ``computing`` (admin.js); ``first_answer_s`` (the section shows
  something: a report, stale or not, or "computing") and ``report_s`` (the current report).

Each item: wall seconds (first = cold, then ``--reps`` - 1 warm repeats for the lists and the
quality section), bytes received, the server processes' CPU seconds during it (psutil; the
server's background threads included), per request its status, start offset, seconds, bytes.
Summaries per budget: p50 / max, first vs warm, met / missed. The load average at the start
and the end, the server's peak RSS. One JSON object on stdout (``--json PATH``: written too).

    .venv/bin/python bench/bench_review_scale.py --preset small --masks 60
    .venv/bin/python bench/bench_review_scale.py --table out.json   # the budgets, markdown
    .venv/bin/python bench/bench_review_scale.py --source /data/synth_survey \\
        --workspace /data/ws_survey --masks 200 [--db postgresql] --json out.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from _app_harness import (  # noqa: E402
    Cpu,
    Mem,
    app_env,
    login,
    pct,
    pg_database,
    seed,
    start_server,
    stop_server,
    truth_dir,
)
from _scene import ensure_scene  # noqa: E402

BUDGET_S = {"review_list": 1.0, "suspects": 1.0, "open_frame_first": 1.0,
            "open_frame_next": 0.3, "quality": 2.0}
BROWSER_CONNECTIONS = 6  # a browser's connections per host (HTTP/1.1)
QUALITY_POLL_S = 3.0  # admin.js: loadQuality again while computing
QUALITY_TIMEOUT = [1800.0]  # --quality-timeout: stop polling (the report is then "not ready")


def _choose(n_masks: int, truth: Path | None, info: dict):  # noqa: ANN202
    """The frames to hand out (``seed``'s ``choose``): the largest frames where the scene has
    frames of several sizes, the stratified selection, then frames evenly spread over the
    rest, those with a truth mask only (when the project has them), ``n_masks`` in all."""

    def choose(ctx, session, scene) -> None:  # noqa: ANN001
        from sqlalchemy import select

        from app import pipeline
        from app.scenes import service as scenes
        from app.scenes.models import Frame

        ws_scene = ctx.load_scene(scene.workspace)
        rows = session.execute(select(Frame.index, Frame.name, Frame.width, Frame.height)
                               .where(Frame.scene_id == scene.id).order_by(Frame.index)).all()
        ok = {i for i, name, _w, _h in rows
              if truth is None or (truth / f"{Path(name).stem}.png").is_file()}
        area = {i: w * h for i, _n, w, h in rows}
        full = [i for i in sorted(ok) if len(set(area.values())) > 1
                and area[i] == max(area.values())]
        sel = pipeline.select_frames(ws_scene)
        order = list(dict.fromkeys(full + [int(i) for i in sel["frames"] if int(i) in ok]))
        rest = [i for i in sorted(ok) if i not in set(order)]
        need = max(0, n_masks - len(order))
        if need and rest:
            pick = np.unique(np.linspace(0, len(rest) - 1, min(need, len(rest))).round()
                             .astype(int))
            order += [rest[k] for k in pick]
        chosen = sorted(order[:n_masks])
        scenes.apply_selection(session=session, scene=scene,
                               result={**sel, "frames": chosen}, ws_scene=ws_scene)
        info.update({"handed_out": len(chosen), "full_size_handed_out":
                     sum(1 for i in chosen if i in set(full)),
                     "from_stratified_selection": sum(1 for i in chosen
                                                      if i in set(map(int, sel["frames"]))),
                     "frames_with_truth_mask": len(ok)})

    return choose


class Client:
    """An httpx client with a browser's connection limit, each GET timed and its body read;
    ``log`` collects (path, status, start offset, seconds, bytes) of the current action."""

    def __init__(self, base: str, username: str) -> None:
        import httpx

        self.c = httpx.Client(base_url=base, timeout=600, limits=httpx.Limits(
            max_connections=BROWSER_CONNECTIONS, max_keepalive_connections=BROWSER_CONNECTIONS))
        login(self.c, username)
        self.pool = ThreadPoolExecutor(BROWSER_CONNECTIONS + 2)
        self.lock = threading.Lock()
        self.t0 = time.perf_counter()
        self.log: list[dict] = []

    def begin(self) -> None:
        self.t0 = time.perf_counter()
        self.log = []

    def send(self, method: str, path: str, **kw):  # noqa: ANN201
        """A request; sent once more where the server closed a kept-alive connection as it
        left (uvicorn closes idle ones after 5 s; a browser retries such a request too)."""
        import httpx

        try:
            return self.c.request(method, path, **kw)
        except (httpx.RemoteProtocolError, httpx.ReadError, httpx.ConnectError):
            return self.c.request(method, path, **kw)

    def get(self, path: str, name: str | None = None):  # noqa: ANN201
        t = time.perf_counter()
        r = self.send("GET", path)
        dt = time.perf_counter() - t
        with self.lock:
            self.log.append({"req": name or path, "status": r.status_code,
                             "at_s": round(t - self.t0, 3), "s": round(dt, 3),
                             "bytes": len(r.content)})
        return r

    def close(self) -> None:
        self.pool.shutdown(wait=True)
        self.c.close()


def _action(cl: Client, cpu: Cpu, fn) -> dict:  # noqa: ANN001
    """Run ``fn()`` (the requests of one page action); its wall time, bytes, server CPU."""
    c0 = cpu.read()
    cl.begin()
    extra = fn() or {}
    wall = time.perf_counter() - cl.t0
    c1 = cpu.read()
    return {"s": round(wall, 3), "bytes": sum(x["bytes"] for x in cl.log),
            "server_cpu_s": round(sum(c1.values()) - sum(c0.values()), 3),
            "statuses": sorted({x["status"] for x in cl.log}), "requests": list(cl.log),
            **extra}


def review_list(cl: Client, sid: int) -> dict:
    """reviewer.js start() + loadList() with the state filter ``submitted``."""
    cl.get("/api/scenes")
    r = cl.get(f"/api/scenes/{sid}/frames?sort=disagreement&state=submitted",
               "/api/scenes/{sid}/frames?sort=disagreement&state=submitted")
    return {"rows": len(r.json()) if r.status_code == 200 else None}


def suspects(cl: Client, sid: int) -> dict:
    """reviewer.js loadSuspects(): the list, then the scene (its taxonomy)."""
    r = cl.get(f"/api/scenes/{sid}/suspects", "/api/scenes/{sid}/suspects")
    cl.get(f"/api/scenes/{sid}", "/api/scenes/{sid}")
    return {"suspects": r.json().get("n") if r.status_code == 200 else None}


def open_frame(cl: Client, fid: int) -> dict:
    """reviewer.js openFrame(fid): the frame, then its seven requests at once; usable when
    they have all answered. projected-items (not waited for by the page) is timed apart."""
    fr = cl.get(f"/api/frames/{fid}", "/api/frames/{fid}").json()
    sid, has_mask = fr["scene_id"], fr.get("current_version") is not None

    def image() -> None:
        r = cl.get(f"/api/frames/{fid}/image?size=preview", "/api/frames/{fid}/image?size=preview")
        if r.status_code in (204, 404):
            cl.get(f"/api/frames/{fid}/image", "/api/frames/{fid}/image")

    jobs = [lambda: cl.get(f"/api/scenes/{sid}", "/api/scenes/{sid}")]
    if has_mask:
        jobs.append(lambda: cl.get(f"/api/frames/{fid}/agreement", "/api/frames/{fid}/agreement"))
    jobs += [lambda: cl.get(f"/api/scenes/{sid}/review-items", "/api/scenes/{sid}/review-items"),
             image]
    if has_mask:
        jobs.append(lambda: cl.get(f"/api/frames/{fid}/mask", "/api/frames/{fid}/mask"))
    jobs.append(lambda: cl.get(f"/api/frames/{fid}/render", "/api/frames/{fid}/render"))
    if has_mask:
        jobs.append(lambda: cl.get(f"/api/frames/{fid}/disagreement",
                                   "/api/frames/{fid}/disagreement"))
    for f in [cl.pool.submit(j) for j in jobs]:
        f.result()
    usable = time.perf_counter() - cl.t0
    t = time.perf_counter()
    p = cl.send("GET", f"/api/frames/{fid}/projected-items")
    return {"frame_id": fid, "name": fr["name"], "size": f"{fr['width']}x{fr['height']}",
            "mp": round(fr["width"] * fr["height"] / 1e6, 1), "usable_s": round(usable, 3),
            "projected_items": {"status": p.status_code,
                                "s": round(time.perf_counter() - t, 3)}}


def quality(cl: Client, sid: int) -> dict:
    """admin.js loadQuality(): asked again every 3 s while the report is being computed."""
    first = None
    polls = 0
    while True:
        r = cl.get(f"/api/scenes/{sid}/quality", "/api/scenes/{sid}/quality")
        polls += 1
        body = r.json() if r.status_code in (200, 202) else {}
        if first is None:
            first = time.perf_counter() - cl.t0
            first_kind = ("report" if not body.get("computing") else
                          "stale report" if body.get("loo") or body.get("votes") else
                          "computing" if r.status_code in (200, 202) else f"{r.status_code}")
        if r.status_code not in (200, 202) or not body.get("computing"):
            break
        if time.perf_counter() - cl.t0 > QUALITY_TIMEOUT[0]:
            break
        time.sleep(QUALITY_POLL_S)
    return {"first_answer_s": round(first, 3), "first_answer": first_kind,
            "report_s": round(time.perf_counter() - cl.t0, 3), "polls": polls,
            "cached": body.get("cached"), "ready": not body.get("computing")}


def _summary(rows: list[dict], key: str = "s") -> dict:
    xs = [r[key] for r in rows]
    return {"n": len(xs), "first_s": xs[0] if xs else None, "p50_s": pct(xs, 50),
            "max_s": round(max(xs), 3) if xs else None,
            "warm_p50_s": pct(xs[1:], 50), "bytes_first": rows[0]["bytes"] if rows else None,
            "server_cpu_s_first": rows[0]["server_cpu_s"] if rows else None,
            "server_cpu_s_p50": pct([r["server_cpu_s"] for r in rows], 50)}


def _verdict(x: float | None, budget: float) -> str:
    return "n/a" if x is None else "met" if x <= budget else "missed"


def _wait_lifted(cl: Client, sid: int, submitted: dict[int, int], timeout: float) -> dict:
    """Poll labels/status every 2 s until every submitted version is in the filled labels
    and no fill is pending or running."""
    t0 = time.monotonic()
    polls = []
    while time.monotonic() - t0 < timeout:
        t = time.perf_counter()
        st = cl.send("GET", f"/api/scenes/{sid}/labels/status").json()
        polls.append(time.perf_counter() - t)
        filled = st.get("filled_versions") or {}
        done = sum(1 for fid, v in submitted.items()
                   if filled.get(str(fid)) is not None and filled[str(fid)] >= v)
        if done == len(submitted) and not st.get("pending_fill") and not st.get("fill_running"):
            return {"lifted_s": round(time.monotonic() - t0, 1), "status_polls": len(polls),
                    "status_poll_p50_s": pct(polls, 50), "status_poll_max_s": round(max(polls), 3)}
        time.sleep(2.0)
    raise RuntimeError(f"labels of {len(submitted)} submitted masks not filled after "
                       f"{timeout:.0f} s (last status: {json.dumps(st)[:400]})")


def _wait_idle(cpu: Cpu, timeout: float, window: float = 5.0, share: float = 0.05) -> dict:
    """Wait until the server's processes used < ``share`` of a core over ``window`` seconds
    (its post-fill background work done); how long that took and the CPU it used."""
    t0 = time.monotonic()
    c0 = sum(cpu.read().values())
    while time.monotonic() - t0 < timeout:
        a = sum(cpu.read().values())
        time.sleep(window)
        b = sum(cpu.read().values())
        if b - a < share * window:
            return {"idle_after_s": round(time.monotonic() - t0, 1),
                    "background_cpu_s": round(b - c0, 1)}
    return {"idle_after_s": None, "timeout_s": timeout,
            "background_cpu_s": round(sum(cpu.read().values()) - c0, 1)}


def run(args: argparse.Namespace, url: str, data: Path) -> dict:
    from occufly.io.masks import encode_mask_png

    source, workspace = args.source, args.workspace
    env = app_env(data, url, [r for r in (source, workspace) if r is not None],
                  api_workers=args.api_workers, debounce=args.debounce)
    truth = truth_dir(source, workspace)
    if truth is None:
        raise SystemExit(f"{source}: no synthetic truth masks (truth/masks) to submit")
    chosen: dict = {}
    t0 = time.monotonic()
    sids, info = seed(env, 1, workspace or source, 1, choose=_choose(args.masks, truth, chosen),
                      users_extra={"rev": "reviewer"})
    handed_out = info.pop("handed_out")
    # every mask encoded before the server starts (as the editor encodes it): the submits
    # then come as fast as the server takes them, and the fill debounce covers them
    from PIL import Image

    bodies = {}
    for name, (w, h) in handed_out.items():
        ids = np.asarray(Image.open(truth / f"{Path(name).stem}.png"))
        if ids.shape != (h, w):
            raise RuntimeError(f"truth mask of {name}: {ids.shape[1]}x{ids.shape[0]}, the "
                               f"frame is {w}x{h}")
        bodies[name] = encode_mask_png(ids)
    sid = sids[0]
    out: dict = {"scene": {**info["scenes"][0], "import_s": info["import_s"][0], **chosen,
                           "source": str(source), "workspace": str(workspace) if workspace
                           else None, "truth_masks": str(truth) if truth else None},
                 "setup_s": round(time.monotonic() - t0, 1)}
    procs, base = start_server(env, api_workers=args.api_workers)
    mem = Mem([p.pid for p in procs], args.min_available_mb)
    t_run0 = time.monotonic()
    try:
        cpu = Cpu([p.pid for p in procs])
        time.sleep(2.0)  # the lifting worker takes its slot
        # ---- the annotator submits every handed-out frame's truth mask ----------------------
        ann = Client(base, "ann00")
        saves, submitted, mp_saved = [], {}, []
        t_sub = time.monotonic()
        c_sub = cpu.read()
        while True:
            r = ann.send("POST", f"/api/scenes/{sid}/next")
            if r.status_code == 204:
                break
            r.raise_for_status()
            fr = r.json()
            body = bodies[fr["name"]]
            cur = "none" if fr.get("current_version") is None else str(fr["current_version"])
            t = time.perf_counter()
            p = ann.send("PUT", f"/api/frames/{fr['id']}/mask?kind=submitted", content=body,
                          headers={"If-Match": cur, "Content-Type": "image/png"})
            saves.append(time.perf_counter() - t)
            p.raise_for_status()
            submitted[fr["id"]] = int(p.json()["version"])
            mp_saved.append(fr["width"] * fr["height"] / 1e6)
        c_done = cpu.read()
        out["submit"] = {"masks": len(submitted), "wall_s": round(time.monotonic() - t_sub, 1),
                         "save_p50_s": pct(saves, 50), "save_max_s": round(max(saves), 3),
                         "masks_20mp": sum(1 for m in mp_saved if m >= 19),
                         "mask_megapixels": round(sum(mp_saved), 1),
                         "server_cpu_s": round(sum(c_done.values()) - sum(c_sub.values()), 1)}
        print(f"submitted {len(submitted)} masks in {out['submit']['wall_s']} s",
              file=sys.stderr, flush=True)
        out["lifting"] = _wait_lifted(ann, sid, submitted, args.lift_timeout)
        c_lift = cpu.read()
        out["lifting"]["server_cpu_s"] = round(sum(c_lift.values()) - sum(c_done.values()), 1)
        print(f"lifted: {out['lifting']}", file=sys.stderr, flush=True)
        out["after_fill"] = _wait_idle(cpu, args.idle_timeout)
        print(f"idle: {out['after_fill']}", file=sys.stderr, flush=True)
        ann.close()
        # ---- the reviewer ----------------------------------------------------------------------
        rev = Client(base, "rev")
        res: dict = {"review_list": [], "suspects": [], "frames": [], "quality": []}
        for _ in range(args.reps):
            res["review_list"].append(_action(rev, cpu, lambda: review_list(rev, sid)))
        order = [r["id"] for r in rev.send("GET",
            f"/api/scenes/{sid}/frames?sort=disagreement&state=submitted").json()]
        for _ in range(args.reps):
            res["suspects"].append(_action(rev, cpu, lambda: suspects(rev, sid)))
        opened: list[int] = []

        def visit(fid: int, how: str) -> None:
            a = _action(rev, cpu, lambda: open_frame(rev, fid))
            a["how"] = how
            a["list_position"] = order.index(fid) if fid in order else None
            res["frames"].append(a)
            opened.append(fid)
            print(f"  {how} frame {fid} ({a['size']}): {a['usable_s']} s", file=sys.stderr,
                  flush=True)
            time.sleep(args.dwell)  # the reviewer looks at it (the server prefetches)

        if order:
            visit(order[0], "top")
            for k in range(1, min(args.next + 1, len(order))):
                visit(order[k], "next")
            sizes = {r["id"]: r["width"] * r["height"] for r in rev.send("GET",
                f"/api/scenes/{sid}/frames?state=submitted").json()}
            big = max(sizes.values())
            # frames nothing prefetched: not opened, not among the PREFETCH_NEXT after an
            # opened one (the server warms those), the full-size frames first
            from app.review.service import PREFETCH_NEXT

            def cold(f: int, taken: list[int]) -> bool:
                i = order.index(f)
                return all(not 0 <= i - order.index(g) <= PREFETCH_NEXT for g in taken)

            picks: list[int] = []
            cands = [f for f in order if sizes.get(f) == big and len(set(sizes.values())) > 1]
            cands += order[len(order) // 2:] + order[1:len(order) // 2]
            for f in cands:
                if len(picks) < args.clicks and f not in picks and cold(f, opened + picks):
                    picks.append(f)
            for fid in picks:
                visit(fid, "click")
            for fid in opened[:2]:
                visit(fid, "reopen")
        rev.close()
        adm = Client(base, "admin")
        for _ in range(args.reps):
            res["quality"].append(_action(adm, cpu, lambda: quality(adm, sid)))
        adm.close()
        # ---- summaries ----------------------------------------------------------------------
        fr = res["frames"]
        first = [f for f in fr if f["how"] in ("top", "click")]
        nxt = [f for f in fr if f["how"] == "next"]
        q = res["quality"]
        summ = {
            "review_list": {**_summary(res["review_list"]), "budget_s": BUDGET_S["review_list"],
                            "rows": res["review_list"][0].get("rows")},
            "suspects": {**_summary(res["suspects"]), "budget_s": BUDGET_S["suspects"],
                         "suspects": res["suspects"][0].get("suspects")},
            "open_frame_first": {**_summary(first, "usable_s"),
                                 "budget_s": BUDGET_S["open_frame_first"],
                                 "by_mp": {str(m): pct([f["usable_s"] for f in first
                                                        if f["mp"] == m], 50)
                                           for m in sorted({f["mp"] for f in first})}},
            "open_frame_clicked": {**_summary([f for f in fr if f["how"] == "click"],
                                              "usable_s"),
                                   "budget_s": BUDGET_S["open_frame_first"],
                                   "note": "clicked in the list, nothing prefetched it"},
            "open_frame_next": {**_summary(nxt, "usable_s"),
                                "budget_s": BUDGET_S["open_frame_next"], "dwell_s": args.dwell},
            "open_frame_reopen": _summary([f for f in fr if f["how"] == "reopen"], "usable_s"),
            "quality": {"first_answer_s": q[0]["first_answer_s"] if q else None,
                        "first_answer": q[0]["first_answer"] if q else None,
                        "report_s_first": q[0]["report_s"] if q else None,
                        "warm_p50_s": pct([x["report_s"] for x in q[1:]], 50),
                        "max_s": round(max(x["report_s"] for x in q), 3) if q else None,
                        "server_cpu_s_first": q[0]["server_cpu_s"] if q else None,
                        "budget_s": BUDGET_S["quality"]},
        }
        for k in ("review_list", "suspects", "open_frame_first", "open_frame_clicked",
                  "open_frame_next"):
            summ[k]["first"] = _verdict(summ[k]["first_s"], summ[k]["budget_s"])
            summ[k]["max"] = _verdict(summ[k]["max_s"], summ[k]["budget_s"])
        summ["quality"]["first_answer_verdict"] = _verdict(summ["quality"]["first_answer_s"], 2.0)
        summ["quality"]["report_verdict"] = _verdict(summ["quality"]["report_s_first"], 2.0)
        summ["quality"]["max"] = _verdict(summ["quality"]["max_s"], 2.0)
        out["budgets"] = summ
        out["measured"] = res
        out.update(mem.stop(t_run0, time.monotonic()))
        return out
    finally:
        mem.stop(0.0, 0.0)
        stop_server(procs)


def table(out: dict) -> str:
    """The budgets of a run as a markdown table (``--table JSON``)."""
    b = out["budgets"]

    def s(x) -> str:  # noqa: ANN001
        return "--" if x is None else f"{x:.2f} s"

    rows = ["| what | first (cold) | p50 | max | warm p50 | bytes (first) | server CPU (first) "
            "| budget | met? |", "|---|---|---|---|---|---|---|---|---|"]
    names = {"review_list": "review list (state=submitted)", "suspects": "suspects tab",
             "open_frame_first": "open a frame, first time (the list's top, then clicked)",
             "open_frame_clicked": "open a frame, first time: clicked ones only (cold)",
             "open_frame_next": f"next frame in the list (N after {b['open_frame_next'].get('dwell_s')} s)"}
    for k, label in names.items():
        if k not in b:
            continue
        x = b[k]
        rows.append(f"| {label} | {s(x['first_s'])} | {s(x['p50_s'])} | {s(x['max_s'])} | "
                    f"{s(x['warm_p50_s'])} | {x['bytes_first'] or 0:,} | "
                    f"{s(x['server_cpu_s_first'])} | <= {x['budget_s']:g} s | "
                    f"first {x['first']}, max {x['max']} |")
    r = b["open_frame_reopen"]
    rows.append(f"| a frame opened again | {s(r['first_s'])} | {s(r['p50_s'])} | "
                f"{s(r['max_s'])} | {s(r['warm_p50_s'])} | {r['bytes_first'] or 0:,} | "
                f"{s(r['server_cpu_s_first'])} | -- | -- |")
    q = b["quality"]
    rows.append(f"| admin quality section: first answer ({q['first_answer']}) | "
                f"{s(q['first_answer_s'])} | | | | | {s(q['server_cpu_s_first'])} | <= 2 s | "
                f"{q['first_answer_verdict']} |")
    rows.append(f"| admin quality section: the current report | {s(q['report_s_first'])} | | "
                f"{s(q['max_s'])} | {s(q['warm_p50_s'])} | | | <= 2 s | {q['report_verdict']} |")
    by = b["open_frame_first"].get("by_mp") or {}
    extra = ", ".join(f"{m} MP: {v:.2f} s" for m, v in by.items())
    return "\n".join(rows) + (f"\n\nFirst opens by frame size (p50): {extra}." if extra else "")


def main() -> None:
    if sys.argv[1:2] == ["--table"]:
        print(table(json.loads(Path(sys.argv[2]).read_text())))
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--preset", help="a synthetic preset (generated and imported once into "
                                      "--root, bench/_scene.py): small, bench, ...")
    src.add_argument("--source", type=Path, help="an `occufly synth` project (read-only)")
    ap.add_argument("--workspace", type=Path, default=None,
                    help="with --source: a workspace imported from it; the app's import job "
                         "copies it instead of importing the project again")
    ap.add_argument("--root", type=Path, default=Path("/tmp/occufly_bench"),
                    help="--preset: where the scenes are cached")
    ap.add_argument("--data", type=Path, default=None,
                    help="the app's scratch data dir goes under this folder (default: a "
                         "temporary folder under --root); removed after the run")
    ap.add_argument("--masks", type=int, default=200, help="submitted masks")
    ap.add_argument("--db", choices=("sqlite", "postgresql"), default="sqlite")
    ap.add_argument("--postgres-url", default=os.environ.get(
        "OCCUFLY_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"))
    ap.add_argument("--api-workers", type=int, default=1,
                    help="API processes (1: the lifting worker runs in it, as `occufly serve`)")
    ap.add_argument("--reps", type=int, default=5, help="repetitions of the lists and quality")
    ap.add_argument("--next", type=int, default=4, help="frames opened with N after the top")
    ap.add_argument("--clicks", type=int, default=4,
                    help="frames opened by a click in the list (full-size ones first)")
    ap.add_argument("--dwell", type=float, default=10.0,
                    help="seconds the reviewer looks at a frame before the next action")
    ap.add_argument("--debounce", type=float, default=5.0, help="OCCUFLY_FILL_DEBOUNCE_S")
    ap.add_argument("--lift-timeout", type=float, default=3600.0)
    ap.add_argument("--idle-timeout", type=float, default=1800.0)
    ap.add_argument("--quality-timeout", type=float, default=1800.0,
                    help="stop asking for the quality report after this long")
    ap.add_argument("--min-available-mb", type=float, default=1024)
    ap.add_argument("--keep", action="store_true",
                    help="keep the data dir and the SQLite database (to profile against)")
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    args = ap.parse_args()
    if args.workspace and not args.source:
        ap.error("--workspace needs --source")
    QUALITY_TIMEOUT[0] = args.quality_timeout
    load_start = os.getloadavg()
    out: dict = {"benchmark": "review_scale", "argv": sys.argv[1:], "cpu_count": os.cpu_count(),
                 "db": args.db, "api_workers": args.api_workers,
                 "load_avg_start": [round(x, 2) for x in load_start]}
    if args.preset:
        args.root.mkdir(parents=True, exist_ok=True)
        args.source, args.workspace = ensure_scene(args.root, args.preset)
        out["preset"] = args.preset
    args.source = args.source.absolute()
    args.workspace = args.workspace.absolute() if args.workspace else None
    parent = args.data or args.root
    parent.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="review-scale-", dir=parent) as d:
        d = tempfile.mkdtemp(prefix="review-scale-kept-", dir=parent) if args.keep else d
        data = Path(d) / "data"
        if args.db == "sqlite":
            out.update(run(args, f"sqlite:///{Path(d) / 'app'}.db", data))
        else:
            with pg_database(args.postgres_url) as url:
                out.update(run(args, url, data))
        if args.keep:
            out["kept"] = {"data_dir": str(data), "database": f"sqlite:///{Path(d) / 'app'}.db"
                           if args.db == "sqlite" else "dropped"}
    out["wall_s"] = round(time.monotonic() - t0, 1)
    out["load_avg_end"] = [round(x, 2) for x in os.getloadavg()]
    text = json.dumps(out)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
