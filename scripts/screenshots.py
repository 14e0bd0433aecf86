"""README screenshots of a running demo (see scripts/screenshots.sh, which starts it).

A scripted annotator submits the synthetic truth masks of the first few frames through the API
(so there are lifted labels to prefill from, review and show in 3D), then headless Chromium
takes: the annotator after "Prefill from 3D", the annotator with the smart tools in use
(GrabCut box refined with scribbles; intelligent scissors with the live preview) on an object
of the frame's truth mask, the reviewer's side-by-side panels, the admin console (and its
annotation-effort curve when the page has one), the 3D viewer opened on a frame, and the grid
preview (``occufly grid-preview`` of the voxelized scene). PNGs are written palette-quantized
when that keeps them readable and small (< 400 KB).

    .venv/bin/python scripts/screenshots.py --url http://127.0.0.1:9450 --source SYNTH_DIR \
        --workspace WS --out docs/screenshots
"""

from __future__ import annotations

import argparse
import io
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
            "--no-first-run", "--disable-sync", "--disable-background-networking"]


def client(url: str, user: str, password: str) -> httpx.Client:
    c = httpx.Client(base_url=url, timeout=120)
    r = c.post("/api/auth/login", json={"username": user, "password": password})
    r.raise_for_status()
    c.headers["Authorization"] = f"Bearer {r.json()['token']}"
    return c


def wait(fn, timeout: float, what: str):  # noqa: ANN001, ANN201
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        v = fn()
        if v:
            return v
        time.sleep(0.5)
    raise SystemExit(f"screenshots: timed out waiting for {what}")


def grey_png(ids: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(ids.astype(np.uint8), mode="L").save(buf, format="PNG")
    return buf.getvalue()


def seed_masks(url: str, pw: dict, source: Path, n: int) -> tuple[int, list[dict]]:
    adm = client(url, "admin", pw["admin"])
    sid = adm.get("/api/scenes").json()[0]["id"]
    ann = client(url, "annotator", pw["annotator"])
    done = []
    for i in range(n):
        if i >= n // 2:  # like a real annotator: the later frames start from the 3D prefill
            wait_lifted(adm, sid, len(done))
        r = ann.post(f"/api/scenes/{sid}/next")
        if r.status_code == 204:
            break
        f = r.json()
        if i >= n // 2:
            ann.get(f"/api/frames/{f['id']}/prefill").raise_for_status()
        m = Image.open(source / "truth" / "masks" / f"{Path(f['name']).stem}.png")
        ids = np.asarray(m.convert("L") if m.mode not in ("L", "P") else m)
        r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
                    headers={"Content-Type": "image/png",
                             "If-Match": str(f["current_version"] or "none")})
        r.raise_for_status()
        done.append(f)
    wait_lifted(adm, sid, len(done))
    return sid, done


def wait_lifted(adm: httpx.Client, sid: int, n: int) -> None:
    wait(lambda: (lambda s: s.status_code == 200 and not s.json()["pending_fill"]
                  and len(s.json()["included_versions"]) >= n)(
        adm.get(f"/api/scenes/{sid}/labels/status")), 600, "the lifted labels")


def lease_frame_with_object(url: str, pw: dict, sid: int, source: Path) -> tuple[dict, int, np.ndarray]:
    """Lease the annotator's next frame that shows an object the smart tools can cut out
    (frames without one are skipped and released again): (frame, class id, object mask)."""
    ann = client(url, "annotator", pw["annotator"])
    classes = ann.get(f"/api/scenes/{sid}").json()["taxonomy"]["classes"]
    skipped: list[int] = []
    fallback = None
    while True:
        r = ann.post(f"/api/scenes/{sid}/next", params={"skip": skipped} if skipped else None)
        if r.status_code == 204:
            break
        f = r.json()
        got = pick_object(source, f["name"], classes)
        if got and got[0] < len(SMART_CLASSES) - 1:  # a building / roof / vehicle, not a tree
            return f, got[1], got[2]
        if got and fallback is None:
            fallback = (f, got[1], got[2])
        skipped.append(f["id"])
        ann.post(f"/api/frames/{f['id']}/release")
    if fallback is None:
        raise SystemExit(f"screenshots: no selected frame shows one of {SMART_CLASSES}")
    f = fallback[0]
    r = ann.post(f"/api/scenes/{sid}/next", params={"skip": [x for x in skipped if x != f["id"]]})
    r.raise_for_status()
    return r.json(), fallback[1], fallback[2]


SMART_CLASSES = ("roof", "building", "vehicle", "truck", "tree")  # objects worth cutting out


def pick_object(source: Path, frame_name: str, classes: list[dict]):  # noqa: ANN201
    """(rank in SMART_CLASSES, class id, (H, W) bool) of a compact object in the frame's truth
    mask: a connected component of a SMART_CLASSES class, away from the border, of a size
    that shows well; None if there is none."""
    import cv2

    m = Image.open(source / "truth" / "masks" / f"{Path(frame_name).stem}.png")
    ids = np.asarray(m.convert("L") if m.mode not in ("L", "P") else m)
    H, W = ids.shape
    by_name = {c["name"]: c["id"] for c in classes}
    best = None
    for rank, name in enumerate(SMART_CLASSES):
        if name not in by_name:
            continue
        n, lab, stats, _ = cv2.connectedComponentsWithStats((ids == by_name[name]).astype(np.uint8), 8)
        for k in range(1, n):
            x, y, w, h, area = stats[k]
            if x < 8 or y < 8 or x + w > W - 8 or y + h > H - 8 or not (0.004 * H * W <= area <= 0.12 * H * W):
                continue
            if area / (w * h) < 0.45:  # compact, not a thin diagonal
                continue
            cs, _ = cv2.findContours((lab == k).astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            if area / max(1.0, cv2.contourArea(cv2.convexHull(max(cs, key=len)))) < 0.9:
                continue  # one convex object, not two cars side by side
            score = (area / (w * h) >= 0.9, -rank, area)  # box-like (one car, not two) first
            if best is None or score > best[0]:
                best = (score, by_name[name], lab == k)
    return None if best is None else (-best[0][1], best[1], best[2])


def smart_tool_shots(page, obj: np.ndarray, cls: int, out: Path) -> dict:  # noqa: ANN001
    """The annotator with GrabCut (box + scribbles, refining) and with the intelligent
    scissors (anchors snapped to the object's edges, the live preview to the cursor)."""
    import cv2

    ov = page.locator(".layer-overlay").bounding_box()
    ys, xs = np.nonzero(obj)
    x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    # zoom so the object fills about half of the view, centred
    page.evaluate(f"""() => {{ const v = window.__occufly.page.editor.view;
        const r = v.overlay.getBoundingClientRect();
        v.fit(); const want = 0.5 * Math.min(r.width / {x1 - x0 + 40}, r.height / {y1 - y0 + 40});
        v.zoomAt(want / v.scale, r.width / 2, r.height / 2);
        const [sx, sy] = v.toScreen({cx}, {cy}); v.panBy(r.width / 2 - sx, r.height / 2 - sy); }}""")
    page.evaluate(f"() => window.__occufly.page.editor.selectClass({cls})")

    def at(x: float, y: float) -> tuple[float, float]:
        sx, sy = page.evaluate(f"() => window.__occufly.page.editor.view.toScreen({x}, {y})")
        return ov["x"] + sx, ov["y"] + sy

    shots = {}
    m = max(8, int(0.25 * max(x1 - x0, y1 - y0)))
    page.keyboard.press("g")
    page.mouse.move(*at(x0 - m, y0 - m))
    page.mouse.down()
    page.mouse.move(*at(x1 + m, y1 + m), steps=8)
    page.mouse.up()
    page.wait_for_selector("#status:has-text('pixels of the box given the class')", timeout=60_000)
    # a foreground scribble along the object's middle, a background one along the box's corner
    inner = cv2.erode(obj.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    row = int(cy) if inner[int(cy)].any() else int(np.nonzero(inner.any(axis=1))[0].mean())
    cols = np.nonzero(inner[row])[0]
    page.mouse.move(*at(cols.min() + 1.5, row + 0.5))
    page.mouse.down()
    page.mouse.move(*at(cols.max() - 0.5, row + 0.5), steps=10)
    page.mouse.up()
    page.wait_for_selector("#status:has-text('(1 scribble)')", timeout=60_000)
    yb = y1 + m / 2  # along the bottom margin of the box, under the object
    page.mouse.move(*at(x0 - m / 2, yb))
    page.mouse.down(button="right")
    page.mouse.move(*at(x1 + m / 2, yb), steps=10)
    page.mouse.up(button="right")
    page.wait_for_selector("#status:has-text('(2 scribbles)')", timeout=60_000)
    page.mouse.move(*at(x1 + m + 4, cy))
    page.wait_for_timeout(500)
    shots["annotator_grabcut"] = out / "annotator_grabcut.png"
    page.screenshot(path=str(shots["annotator_grabcut"]))
    page.keyboard.press("Escape")  # cancel: the mask as before the box
    # scissors: anchors on the object's outline, the preview to the next one
    cs, _ = cv2.findContours(obj.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    ring = max(cs, key=len).reshape(-1, 2)
    anchors = [ring[int(k * len(ring) / 8)] for k in range(8)]
    page.keyboard.press("i")
    for x, y in anchors[:6]:
        page.mouse.click(*at(x + 0.5, y + 0.5))
        page.wait_for_timeout(250)
    nx, ny = anchors[6]
    page.mouse.move(*at(nx + 0.5, ny + 0.5), steps=6)
    page.wait_for_function(f"""() => {{ const p = window.__occufly.page.editor.tools.scissors.preview;
        return p && p.to[0] === {int(nx)} && p.to[1] === {int(ny)}; }}""", timeout=60_000)
    page.wait_for_function("""() => window.__occufly.page.editor.tools.scissors.anchors
        .every((a, i) => i === 0 || a.seg.path)""", timeout=60_000)
    page.wait_for_timeout(300)
    shots["annotator_scissors"] = out / "annotator_scissors.png"
    page.screenshot(path=str(shots["annotator_scissors"]))
    page.keyboard.press("Escape")
    return shots


def shrink(path: Path, limit: int = 400_000) -> None:
    """Re-save a PNG over ``limit`` bytes with a 256-colour palette (dithered)."""
    if path.stat().st_size <= limit:
        return
    with Image.open(path) as im:
        q = im.convert("RGB").quantize(256, dither=Image.Dither.FLOYDSTEINBERG)
    q.save(path, optimize=True)


def login(page, url: str, user: str, password: str) -> None:  # noqa: ANN001
    page.goto(f"{url}/#/login")
    page.fill("#username", user)
    page.fill("#password", password)
    page.click("button[type=submit]")
    page.wait_for_selector(f"#whoami:has-text('{user}')")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--source", type=Path, required=True, help="the synthetic scene folder")
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots")
    ap.add_argument("--frames", type=int, default=6, help="truth masks submitted first")
    args = ap.parse_args()
    pw = {r: f"occufly-{r}" for r in ("admin", "reviewer", "annotator")}
    args.out.mkdir(parents=True, exist_ok=True)
    sid, done = seed_masks(args.url, pw, args.source, args.frames)
    adm = client(args.url, "admin", pw["admin"])
    job = adm.post(f"/api/scenes/{sid}/voxelize").json()
    wait(lambda: adm.get(f"/api/jobs/{job['id']}").json()["status"] not in ("queued", "running"),
         900, "voxelize")
    job = adm.post(f"/api/scenes/{sid}/eval").json()
    wait(lambda: adm.get(f"/api/jobs/{job['id']}").json()["status"] not in ("queued", "running"),
         900, "eval")
    shots = {}
    frame, cls, obj = lease_frame_with_object(args.url, pw, sid, args.source)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM)
        # annotator: the next frame, prefilled from the 3D labels of the frames before it
        ctx = b.new_context(viewport={"width": 1440, "height": 900})
        page = ctx.new_page()
        login(page, args.url, "annotator", pw["annotator"])
        page.goto(f"{args.url}/#/annotate?scene={sid}&frame={frame['id']}")
        page.wait_for_function("() => window.__occufly && window.__occufly.page.stats.openMs !== null")
        page.click("#prefill")
        page.wait_for_function("() => Number(document.querySelector('#painted').dataset.share) > 0")
        page.click("#scene-progress summary")
        page.wait_for_selector("#progress-table")
        page.wait_for_timeout(600)
        shots["annotator"] = args.out / "annotator.png"
        page.screenshot(path=str(shots["annotator"]))
        # then the smart tools on the same frame from an empty mask (the prefill undone, so no
        # draft of this frame was saved before its prefill); both are cancelled after the shot
        page.click("#scene-progress summary")
        page.keyboard.press("Control+z")
        page.wait_for_function("() => Number(document.querySelector('#painted').dataset.share) === 0")
        shots.update(smart_tool_shots(page, obj, cls, args.out))
        ctx.close()
        # reviewer: side by side, per-class agreement open
        ctx = b.new_context(viewport={"width": 1440, "height": 900})
        page = ctx.new_page()
        login(page, args.url, "reviewer", pw["reviewer"])
        page.goto(f"{args.url}/#/review?scene={sid}&frame={done[-1]['id']}")
        page.wait_for_selector("#agreement[data-value]")
        page.wait_for_timeout(800)
        shots["reviewer"] = args.out / "reviewer.png"
        page.screenshot(path=str(shots["reviewer"]))
        # 3D viewer opened on that frame
        page.goto(f"{args.url}/viewer/?scene={sid}&frame={done[-1]['id']}")
        page.wait_for_function("() => document.body.innerText.includes('showing')", timeout=120_000)
        page.wait_for_timeout(6000)  # software WebGL: let the points draw
        # viser's "software WebGL" notice is about this headless browser, not the page
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        page.wait_for_timeout(500)
        shots["viewer"] = args.out / "viewer.png"
        page.screenshot(path=str(shots["viewer"]))
        ctx.close()
        # admin: selection, jobs, metrics
        ctx = b.new_context(viewport={"width": 1440, "height": 900})
        page = ctx.new_page()
        login(page, args.url, "admin", pw["admin"])
        page.goto(f"{args.url}/#/admin?scene={sid}")
        page.wait_for_selector("#coverage-plot")
        page.wait_for_selector("#metrics")
        page.evaluate("document.querySelector('#sec-selection').scrollIntoView({block: 'start'})")
        page.wait_for_timeout(800)
        shots["admin"] = args.out / "admin.png"
        page.screenshot(path=str(shots["admin"]))
        # the annotation-effort curve of the submitted masks, where the admin page has one
        if page.locator("#sec-effort").count():
            page.wait_for_selector("#effort-plot", timeout=60_000)
            page.evaluate("document.querySelector('#sec-effort').scrollIntoView({block: 'start'})")
            page.wait_for_timeout(800)
            shots["admin_effort"] = args.out / "admin_effort.png"
            page.screenshot(path=str(shots["admin_effort"]))
        ctx.close()
        b.close()
    shots["grid_preview"] = args.out / "grid_preview.png"
    subprocess.run([str(Path(sys.executable).with_name("occufly")), "grid-preview", str(args.workspace),
                    "--out", str(shots["grid_preview"])], check=True, stdout=subprocess.DEVNULL)
    for k, v in shots.items():
        shrink(v)
        print(f"{k}: {v} ({v.stat().st_size // 1024} KB)")


if __name__ == "__main__":
    main()
