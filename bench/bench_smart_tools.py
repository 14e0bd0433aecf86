"""Server-side smart tools on a 5472x3648 (20 MP) frame: GrabCut box + scribbles and the
intelligent-scissors segment (``POST /api/frames/{fid}/grabcut`` / ``scissors``), called
through the real app in-process (FastAPI TestClient, SQLite), so decode, auth and PNG / JSON
encoding are included. Prints ONE JSON object:

* ``grabcut_box``: a 1800x1200 box -> seconds (median of 3) with the decoded-photo cache;
  baseline = the same call with the cache emptied first (every request decoded the 20 MP JPEG
  before the cache); ratio = baseline / cached.
* ``grabcut_scribbles``: the same box re-cut with 3 strokes (what each scribble costs).
* ``scissors_short`` / ``scissors_long``: a 150 px and a 2500 px segment (median of 5).
* ``scissors_full_res``: a 600 px segment worked on at full resolution (no downscale:
  baseline) vs the route's <= 512 px crop; ratio = baseline / route.
* ``preview``: 12 segments from one anchor to successive cursor positions, as the live
  preview asks them -> mean and max seconds per request.

CPU (user+sys of this process, all threads) is reported beside wall time.

Usage: .venv/bin/python bench/bench_smart_tools.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def cpu() -> float:
    t = os.times()
    return t.user + t.system


def timed(fn, n: int):  # noqa: ANN001, ANN201
    walls, cpus, out = [], [], None
    for _ in range(n):
        w0, c0 = time.perf_counter(), cpu()
        out = fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(cpu() - c0)
    return {"wall_s": round(statistics.median(walls), 3), "cpu_s": round(statistics.median(cpus), 3),
            "n": n}, out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keep", type=Path, default=None, help="keep the data directory here")
    args = ap.parse_args()

    from bench_browser import H, W, build_reconstruction
    from fastapi.testclient import TestClient

    from app.annotations import smart
    from app.config import Settings
    from app.main import close, create_app
    from app.users import service as users

    tmp = Path(args.keep or tempfile.mkdtemp(prefix="bench_smart_"))
    imports = tmp / "imports"
    imports.mkdir(parents=True, exist_ok=True)
    source = build_reconstruction(imports)
    app = create_app(Settings(data_dir=tmp / "data", env="development", import_roots=[imports],
                              live_lifting=False))
    with app.state.ctx.sessions() as s:
        users.create_user(session=s, username="admin", password="admin-password-1", role="admin")
    c = TestClient(app)
    tok = c.post("/api/auth/login", json={"username": "admin", "password": "admin-password-1"}).json()["token"]
    c.headers["Authorization"] = f"Bearer {tok}"
    job = c.post("/api/scenes/import", json={"name": "big", "source": str(source)}).json()
    app.state.ctx.jobs.wait(job["id"], timeout=600)
    sid = c.get(f"/api/jobs/{job['id']}").json()["scene_id"]
    frame = c.get(f"/api/scenes/{sid}/frames").json()[0]
    fid = frame["id"]
    assert (frame["width"], frame["height"]) == (W, H), frame

    def post(path: str, body: dict):  # noqa: ANN202
        r = c.post(f"/api/frames/{fid}/{path}", json=body)
        assert r.status_code == 200, r.text
        return r

    box = {"rect": [1800, 1000, 3600, 2200]}
    res: dict = {"frame": f"{W}x{H}"}

    def uncached():
        smart._photos.clear()
        return post("grabcut", box)

    base, _ = timed(uncached, 3)
    post("grabcut", box)  # warm the cache
    cached, r = timed(lambda: post("grabcut", box), 3)
    res["grabcut_box"] = {"cached": cached, "baseline_uncached": base,
                          "ratio": round(base["wall_s"] / cached["wall_s"], 2),
                          "png_bytes": len(r.content)}
    strokes = [{"kind": "fg", "points": [[2400, 1500], [3000, 1600]]},
               {"kind": "bg", "points": [[1900, 1100], [2000, 2100]]},
               {"kind": "bg", "points": [[3500, 1100], [3400, 2100], [3300, 2150]]}]
    sc, _ = timed(lambda: post("grabcut", {**box, "strokes": strokes}), 3)
    res["grabcut_scribbles"] = sc
    # the road edges of bench_browser.photo: rows 1500 / 1700, columns 2600 / 2760
    short, r = timed(lambda: post("scissors", {"start": [2000, 1500], "end": [2150, 1500]}), 5)
    res["scissors_short"] = {**short, "points": len(r.json()["path"]), "scale": r.json()["scale"]}
    long_, r = timed(lambda: post("scissors", {"start": [500, 1500], "end": [3000, 1500]}), 5)
    res["scissors_long"] = {**long_, "points": len(r.json()["path"]), "scale": r.json()["scale"]}
    with app.state.ctx.sessions() as s:
        from app.scenes.models import Frame

        f = s.get(Frame, fid)
        rgb = smart._photo(s, app.state.ctx, f)
    a, b = (2600, 1000), (2600, 1600)
    full, _ = timed(lambda: smart.scissors(rgb, a, b, side=10 ** 6), 1)
    route, _ = timed(lambda: smart.scissors(rgb, a, b), 3)
    res["scissors_full_res"] = {"route": route, "baseline_full_res": full,
                                "ratio": round(full["wall_s"] / route["wall_s"], 2)}
    walls = []
    c0 = cpu()
    for k in range(12):
        w0 = time.perf_counter()
        post("scissors", {"start": [2000, 1200], "end": [2100 + 40 * k, 1480 + 5 * k]})
        walls.append(time.perf_counter() - w0)
    res["preview"] = {"mean_s": round(statistics.mean(walls), 3), "max_s": round(max(walls), 3),
                      "cpu_per_request_s": round((cpu() - c0) / 12, 3)}
    c.close()
    close(app)
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
