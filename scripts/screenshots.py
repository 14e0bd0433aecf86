"""README screenshots of a running demo (see scripts/screenshots.sh, which starts it).

A scripted annotator submits the synthetic truth masks of the first few frames through the API
(so there are lifted labels to prefill from, review and show in 3D), then headless Chromium
takes: the annotator after "Prefill from 3D", the reviewer's side-by-side panels, the admin
console, the 3D viewer opened on a frame, and the grid preview (``occufly grid-preview`` of the
voxelized scene).

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
    for _ in range(n):
        r = ann.post(f"/api/scenes/{sid}/next")
        if r.status_code == 204:
            break
        f = r.json()
        m = Image.open(source / "truth" / "masks" / f"{Path(f['name']).stem}.png")
        ids = np.asarray(m.convert("L") if m.mode not in ("L", "P") else m)
        r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(ids),
                    headers={"Content-Type": "image/png",
                             "If-Match": str(f["current_version"] or "none")})
        r.raise_for_status()
        done.append(f)
    wait(lambda: (lambda s: s.status_code == 200 and not s.json()["pending_fill"]
                  and len(s.json()["included_versions"]) >= len(done))(
        adm.get(f"/api/scenes/{sid}/labels/status")), 600, "the lifted labels")
    return sid, done


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
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM)
        # annotator: the next frame, prefilled from the 3D labels of the frames before it
        ctx = b.new_context(viewport={"width": 1440, "height": 900})
        page = ctx.new_page()
        login(page, args.url, "annotator", pw["annotator"])
        page.goto(f"{args.url}/#/annotate?scene={sid}")
        page.click("#next-frame")
        page.wait_for_function("() => window.__occufly && window.__occufly.page.stats.openMs !== null")
        page.click("#prefill")
        page.wait_for_function("() => Number(document.querySelector('#painted').dataset.share) > 0")
        page.click("#scene-progress summary")
        page.wait_for_selector("#progress-table")
        page.wait_for_timeout(600)
        shots["annotator"] = args.out / "annotator.png"
        page.screenshot(path=str(shots["annotator"]))
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
        ctx.close()
        b.close()
    shots["grid_preview"] = args.out / "grid_preview.png"
    subprocess.run([str(Path(sys.executable).with_name("occufly")), "grid-preview", str(args.workspace),
                    "--out", str(shots["grid_preview"])], check=True, stdout=subprocess.DEVNULL)
    for k, v in shots.items():
        print(f"{k}: {v}")


if __name__ == "__main__":
    main()
