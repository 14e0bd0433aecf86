"""Viewer benchmark: open /viewer/ through the app and time the first complete 2 M point cloud.

Headless Chromium (SwiftShader WebGL) on loopback, the app's proxy in front of viser. Measures

- ``proxy.first_cloud_s``: from ``page.goto('/viewer/?scene=bench')`` to the last websocket
  frame of the initial scene arriving in the browser (all class nodes received);
- ``proxy.ws_bytes`` / ``page_bytes``: bytes the browser received;
- the same through a *direct* viser connection (no proxy, no ticket) as the baseline measured
  in the same run, and the ratio proxy / direct;
- ``bytes_per_point`` and the ratio to the raw float32 xyz + uint8 rgb payload (15 B/point);
- responsiveness while an "annotator" rewrites the labels every 0.5 s (each rewrite triggers a
  live refresh): latency of a class toggle clicked in the browser until the server sees it.

Prints one JSON object. Usage: ``python bench/bench_viewer.py [--points 2000000]``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
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

from viewer_live import CHROMIUM_ARGS, REVIEWER, LiveServer, fake_client, make_app  # noqa: E402

from app.viewer.demo_scene import make_demo_workspace  # noqa: E402
from app.viewer.server import ViewerService  # noqa: E402
from app.viewer.state import default_scenes  # noqa: E402
from occufly.fsutil import atomic_save_npy  # noqa: E402


def png_std(b: bytes) -> float:
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(b)).convert("L"), np.float32)
    h, w = img.shape
    # the left 60 % below the top quarter: clear of the GUI panel and the notification
    return float(img[h // 4:, : int(0.6 * w)].std())


def open_in_browser(browser, srv: LiveServer, svc: ViewerService, *, quiet_s: float = 1.0,
                    timeout_s: float = 300.0) -> dict:
    """Open /viewer/ through the proxy; time the last websocket frame of the initial load
    (measured in the proxy, which forwards every byte the browser gets) and the first
    non-blank canvas screenshot."""
    ctx = browser.new_context(viewport={"width": 1000, "height": 700})
    ctx.add_cookies([{"name": "occufly_session", "value": REVIEWER, "url": srv.url}])
    page = ctx.new_page()
    n_before = len(svc.proxy_stats)
    t0 = time.perf_counter()
    resp = page.goto(srv.url + "/viewer/?scene=bench")
    page_bytes = len(resp.body()) if resp is not None else 0
    st = None
    while st is None and time.perf_counter() - t0 < timeout_s:
        st = next(iter(svc.client_states()), None)
        page.wait_for_timeout(50)
    if st is None or not st.ready.wait(timeout_s):
        raise RuntimeError("viewer did not load the scene")
    t_sent = time.perf_counter() - t0
    stats = svc.proxy_stats[n_before]
    preview = svc.preview_points if st.sent_points > 4 * svc.preview_points else 0
    need = 15 * (st.sent_points + preview)  # float32 xyz + uint8 rgb per point
    while (stats["bytes"] < need or stats["last"] is None
           or time.perf_counter() - stats["last"] < quiet_s):
        if time.perf_counter() - t0 > timeout_s:
            raise RuntimeError(f"only {stats['bytes']} of >= {need} bytes arrived")
        page.wait_for_timeout(50)
    first_cloud = stats["last"] - t0
    first_preview = next((t - t0 for t, b in stats["log"] if b >= 15 * preview), None) \
        if preview else None
    first_picture = None
    while time.perf_counter() - t0 < timeout_s:
        # page screenshot (no element-stability wait: software WebGL frames are slow)
        if png_std(page.screenshot(timeout=120_000)) > 20:  # crop: see png_std
            first_picture = time.perf_counter() - t0
            break
        page.wait_for_timeout(200)
    out = {
        "first_cloud_s": round(first_cloud, 3),
        "preview_points": preview,
        "first_preview_s": None if first_preview is None else round(first_preview, 3),
        "server_sent_s": round(t_sent, 3),
        "first_picture_s": None if first_picture is None else round(first_picture, 3),
        "ws_bytes": int(stats["bytes"]),
        "ws_frames": int(stats["frames"]),
        "page_bytes": page_bytes,
        "points_sent": st.sent_points,
    }
    return {"stats": out, "ctx": ctx, "page": page, "state": st}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--toggles", type=int, default=6)
    args = ap.parse_args()
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        t = time.perf_counter()
        make_demo_workspace(root / "bench", args.points, seed=1, with_grid=False)
        gen_s = time.perf_counter() - t
        app = make_app(root)
        svc = app.state.viewer
        result: dict = {"bench": "viewer", "points": args.points, "generate_s": round(gen_s, 2)}
        with LiveServer(app) as srv:
            # baseline in the same run: a socket-level client straight to viser (no proxy,
            # no browser) vs the same client through the app's proxy
            direct = ViewerService(scenes=default_scenes(root), max_points=args.points,
                                   require_ticket=False)
            direct.start()
            need = 15 * args.points  # float32 xyz + uint8 rgb per point (plus a preview)
            base = asyncio.run(fake_client(f"ws://127.0.0.1:{direct.port}/", {},
                                           min_bytes=need, max_s=300))
            direct.stop()
            via = asyncio.run(fake_client(
                f"ws://127.0.0.1:{srv.port}/viewer",
                {"Cookie": f"occufly_session={REVIEWER}; occufly_viewer_scene=bench"},
                min_bytes=need, max_s=300))
            result["socket_direct"] = {"s": round(base["last_s"], 3), "bytes": base["bytes"]}
            result["socket_via_proxy"] = {"s": round(via["last_s"], 3), "bytes": via["bytes"]}
            result["ratio_proxy_vs_direct_time"] = round(via["last_s"] / base["last_s"], 3)
            while svc.client_states():  # the socket client has gone
                time.sleep(0.05)
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path="/usr/bin/chromium",
                                            args=CHROMIUM_ARGS)
                run = open_in_browser(browser, srv, svc)
                prox = run["stats"]
                result["browser_via_proxy"] = prox
                raw = 15 * prox["points_sent"]
                result["bytes_per_point"] = round(prox["ws_bytes"] / max(prox["points_sent"], 1), 2)
                result["ratio_bytes_vs_raw_xyz32_rgb8"] = round(prox["ws_bytes"] / raw, 3)
                quiet = responsiveness(run["page"], run["state"], root, args.toggles,
                                       with_saves=False)
                busy = responsiveness(run["page"], run["state"], root, args.toggles)
                result["toggle_latency_idle_s"] = quiet
                result["toggle_latency_during_saves_s"] = busy
                result["ratio_toggle_p50_saves_vs_idle"] = round(busy["p50"] / quiet["p50"], 2)
                run["ctx"].close()
                browser.close()
        print(json.dumps(result))


def responsiveness(page, st, root: Path, toggles: int, *, with_saves: bool = True) -> dict:
    """Click a class checkbox while an 'annotator' rewrites the labels every 0.5 s (each
    rewrite is picked up by the live refresh); latency = click until the server sees it."""
    labels = np.load(root / "bench" / "lifting" / "labels.npy")
    stop = threading.Event()
    saves = {"n": 0}

    def annotator() -> None:
        lab = labels.copy()
        person = np.flatnonzero(lab == 11)
        while not stop.is_set():
            lab[person] = 36 if saves["n"] % 2 == 0 else 11
            atomic_save_npy(root / "bench" / "lifting" / "labels.npy", lab)
            saves["n"] += 1
            stop.wait(0.5)

    th = threading.Thread(target=annotator, daemon=True)
    if with_saves:
        th.start()
    lat = []
    row = page.locator("div.mantine-Flex-root", has=page.get_by_text("road (", exact=False))
    box = row.locator("input").last.element_handle()
    try:
        for i in range(toggles):
            want_hidden = i % 2 == 0
            t1 = time.perf_counter()
            box.evaluate("e => e.click()")  # JS click: no wait for rAF-stable layout
            while (st.class_visible.get(1, True) == want_hidden
                   and time.perf_counter() - t1 < 20):
                page.wait_for_timeout(5)
            lat.append(time.perf_counter() - t1)
            page.wait_for_timeout(300)
    finally:
        stop.set()
        if with_saves:
            th.join()
    return {"p50": round(statistics.median(lat), 3), "max": round(max(lat), 3),
            "label_saves": saves["n"]}


if __name__ == "__main__":
    main()
