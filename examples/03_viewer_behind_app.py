"""03 - The review viewer behind a FastAPI app: /viewer/ proxied, only for authorised users.

A minimal app mounts ``app.viewer`` with a development ``authorize`` (cookie
``occufly_session=dev-reviewer``). Open http://127.0.0.1:8765/login to get the cookie, then
/viewer/?scene=demo. The viser port itself refuses connections without the app's ticket.

    .venv/bin/python examples/03_viewer_behind_app.py [--port 8765]
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import uvicorn
from fastapi import FastAPI
from fastapi.responses import RedirectResponse

from app import viewer
from app.viewer.demo_scene import make_demo_workspace


class Settings:
    def __init__(self, data_dir: Path) -> None:
        self.data_dir = data_dir
        self.viewer_max_points = 2_000_000


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, default=8765)
    ap.add_argument("--points", type=int, default=300_000)
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp())
    make_demo_workspace(root / "demo", args.points)
    app = FastAPI()

    @app.get("/login")
    def login() -> RedirectResponse:
        r = RedirectResponse("/viewer/?scene=demo")
        r.set_cookie("occufly_session", "dev-reviewer", httponly=True, samesite="lax")
        return r

    def authorize(conn) -> bool:  # noqa: ANN001 - Request or WebSocket
        ok = conn.cookies.get("occufly_session") == "dev-reviewer"
        if ok:
            conn.state.user = {"username": "dev", "role": "reviewer"}
        return ok

    def on_review_item(scene_id, point_ids, comment, user) -> None:  # noqa: ANN001
        print(f"review item: scene={scene_id} points={len(point_ids)} by {user}: {comment!r}")

    viewer.mount(app, settings=Settings(root), authorize=authorize, on_review_item=on_review_item)
    print(f"open http://127.0.0.1:{args.port}/login")
    uvicorn.run(app, host="127.0.0.1", port=args.port, log_level="warning")


if __name__ == "__main__":
    main()
