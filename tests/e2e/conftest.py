"""End-to-end fixtures: the real app (``app.main.create_app``) served by uvicorn on a free
loopback port, seeded through its own REST API (admin imports a reconstruction, runs the
selection), and Debian's Chromium driven by Playwright.

Seed data: the synthetic ``tiny`` scene (``occufly.synthetic.generate``, made once per run:
the ``synth_tiny`` fixture of tests/conftest.py). The server is tests.harness.ThreadServer.
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from tests.harness import ThreadServer, synth_copy

REPO = Path(__file__).resolve().parents[2]
ARTIFACTS = REPO / "test-artifacts"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--no-first-run", "--disable-sync"]
PASSWORDS = {"admin": "admin-password-1", "reviewer": "reviewer-password-1",
             "annotator": "annotator-password-1"}
ROLES = {"admin": "admin", "reviewer": "reviewer", "annotator": "annotator"}


def build_source(root: Path, synth_tiny: Path) -> tuple[Path, str]:
    """The synthetic ``tiny`` scene (made once per run, see tests/conftest.py) as a folder of
    ``root`` (a copy); returns (folder, description)."""
    return synth_copy(synth_tiny, root / "tiny"), "synthetic tiny"


def png_ids(data: bytes) -> np.ndarray:
    """Decode a mask PNG to (H, W) uint8 ids; fails unless it is single-channel 8-bit."""
    im = Image.open(io.BytesIO(data))
    assert im.mode == "L", f"mask PNG must be single-channel 8-bit, got mode {im.mode}"
    return np.asarray(im)


def grey_png(ids: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(ids.astype(np.uint8), mode="L").save(buf, format="PNG")
    return buf.getvalue()


@dataclass
class Live:
    base_url: str
    app: object
    source_kind: str
    scene_id: int = 0
    clients: dict[str, httpx.Client] = field(default_factory=dict)

    def client(self, role: str) -> httpx.Client:
        """An httpx client logged in as the seeded user of that role (bearer token)."""
        if role not in self.clients:
            c = httpx.Client(base_url=self.base_url, timeout=60)
            r = c.post("/api/auth/login", json={"username": role, "password": PASSWORDS[role]})
            r.raise_for_status()
            c.headers["Authorization"] = f"Bearer {r.json()['token']}"
            self.clients[role] = c
        return self.clients[role]

    def wait_job(self, job: dict, timeout: float = 120.0) -> dict:
        c = self.client("admin")
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            j = c.get(f"/api/jobs/{job['id']}").json()
            if j["status"] not in ("queued", "running"):
                return j
            time.sleep(0.2)
        raise AssertionError(f"job {job['id']} ({job['kind']}) did not finish in {timeout} s")

    def labels_status(self, scene_id: int, role: str = "admin") -> dict:
        """``GET /api/scenes/{scene_id}/labels/status`` as ``role``. Anything but 200 fails at
        once with the answer's body: a 500 is a defect to see, not a reason to poll again."""
        r = self.client(role).get(f"/api/scenes/{scene_id}/labels/status")
        assert r.status_code == 200, (f"labels/status of scene {scene_id} answered "
                                      f"{r.status_code}: {r.text[:2000]}")
        return r.json()

    def wait_until(self, fn, timeout: float = 30.0, what: str = "condition"):
        t_end = time.monotonic() + timeout
        last = None
        while time.monotonic() < t_end:
            last = fn()
            if last:
                return last
            time.sleep(0.25)
        raise AssertionError(f"timed out waiting for {what} (last value {last!r})")


@pytest.fixture(scope="session")
def live(tmp_path_factory, synth_tiny):
    from app.config import Settings
    from app.main import create_app
    from app.users import service as users

    root = tmp_path_factory.mktemp("e2e")
    imports = root / "imports"
    imports.mkdir()
    source, kind = build_source(imports, synth_tiny)
    settings = Settings(data_dir=root / "data", env="development", import_roots=[imports],
                        fill_debounce_s=0.3, fill_settle_s=0, job_workers=2, frontend_dir=REPO / "frontend")
    app = create_app(settings)
    with app.state.ctx.sessions() as s:
        for name, role in ROLES.items():
            users.create_user(session=s, username=name, password=PASSWORDS[name], role=role)
    # keep-alive longer than any pause between a test's requests: with uvicorn's 5 s the
    # server may close an idle connection just as a client reuses it ("connection reset by
    # peer" on the next request, seen in a full run)
    with ThreadServer(app, timeout_keep_alive=600) as server:
        lv = Live(base_url=server.url, app=app, source_kind=kind)
        admin = lv.client("admin")
        r = admin.post("/api/scenes/import", json={"name": "e2e_scene", "source": str(source)})
        assert r.status_code in (200, 202), r.text
        job = lv.wait_job(r.json())
        assert job["status"] == "done", job
        lv.scene_id = job["scene_id"]
        grant_members(lv, lv.scene_id)
        r = admin.post(f"/api/scenes/{lv.scene_id}/selection",
                       json={"cell": 12.0, "mode": "stratified", "target_coverage": 0.99})
        assert r.status_code in (200, 202), r.text
        job = lv.wait_job(r.json())
        assert job["status"] == "done", job
        yield lv
        for c in lv.clients.values():
            c.close()


def grant_members(lv: Live, scene_id: int) -> None:
    """Make every seeded user a member of the scene (scenes are visible to their members
    only, where the app has scene membership)."""
    admin = lv.client("admin")
    ids = [u["id"] for u in admin.get("/api/users").json() if u["role"] != "admin"]
    r = admin.post(f"/api/scenes/{scene_id}/members", json={"user_ids": ids})
    assert r.status_code in (200, 404, 405), r.text  # 404/405: an app without membership


def import_own_scene(lv: Live, name: str) -> int:
    """Import the first source of the import root again as scene ``name`` (a module's own
    scene: its queue and submissions untouched by the other modules), grant every seeded user
    membership and run a stratified selection; returns the scene id."""
    admin = lv.client("admin")
    root = lv.app.state.ctx.settings.import_roots[0]
    source = next(p for p in sorted(root.iterdir()) if p.is_dir())
    r = admin.post("/api/scenes/import", json={"name": name, "source": str(source)})
    assert r.status_code in (200, 202), r.text
    job = lv.wait_job(r.json())
    assert job["status"] == "done", job
    scene_id = job["scene_id"]
    grant_members(lv, scene_id)
    r = admin.post(f"/api/scenes/{scene_id}/selection",
                   json={"cell": 12.0, "mode": "stratified", "target_coverage": 0.99})
    assert lv.wait_job(r.json())["status"] == "done"
    return scene_id


@pytest.fixture(scope="package")
def browser():
    # package scope: the sync API keeps an event loop running in this thread while it is
    # open, which would break later asyncio.run() users (the viewer tests) in the same run
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    setattr(item, f"rep_{rep.when}", rep)


@pytest.fixture()
def new_page(browser, live, request):
    """Factory: a fresh browser context + page logged in as `role` (via the login form).
    On failure every page of the test is screenshotted to test-artifacts/FAILED_*.png."""
    contexts = []
    pages = []
    errors: list[str] = []

    def make(role: str | None, *, viewport=(1366, 800)):
        ctx = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]},
                                  accept_downloads=True)
        contexts.append(ctx)
        page = ctx.new_page()
        page.on("pageerror", lambda e: errors.append(f"{role}: {e}"))
        page.set_default_timeout(20_000)
        # 4xx answers the page handles (e.g. 404 "no mask yet") are logged by Chromium as
        # "Failed to load resource"; any other console error fails the test.
        page.on("console", lambda m: m.type == "error" and not m.text.startswith("Failed to load resource")
                and errors.append(f"{role} console: {m.text}"))
        pages.append(page)
        if role is not None:
            login(page, live, role)
        return page

    yield make
    rep = getattr(request.node, "rep_call", None)
    if rep is not None and rep.failed:
        for i, p in enumerate(pages):
            try:
                shot(p, f"FAILED_{request.node.name}_{i}")
            except Exception:  # noqa: BLE001 - best effort
                pass
    for c in contexts:
        c.close()
    assert not errors, f"uncaught errors in the page: {errors}"


def wait_js(page, expression: str, *, timeout: float = 20_000, arg=None):
    """Wait until ``expression`` (a JS function or expression) is truthy in ``page``; returns
    its value. Polls from Python with ``page.evaluate``: Playwright's ``wait_for_function``
    re-runs its predicate from a requestAnimationFrame callback through ``eval``, which the
    app's CSP (``script-src 'self'``, no ``'unsafe-eval'``) refuses whenever the predicate is
    not true on its first, DevTools-initiated, call."""
    t_end = time.monotonic() + timeout / 1000.0
    last = None
    while True:
        last = page.evaluate(expression) if arg is None else page.evaluate(expression, arg)
        if last:
            return last
        if time.monotonic() > t_end:
            raise AssertionError(f"timed out after {timeout / 1000:g} s waiting for "
                                 f"{expression!r} in the page (last value {last!r})")
        page.wait_for_timeout(100)


def login(page, live: Live, role: str) -> None:
    page.goto(f"{live.base_url}/#/login")
    page.fill("#username", role)
    page.fill("#password", PASSWORDS[role])
    page.click("button[type=submit]")
    page.wait_for_selector(f"#whoami:has-text('{role}')")


def shot(page, name: str, *, full_page: bool = False) -> Path:
    ARTIFACTS.mkdir(exist_ok=True)
    p = ARTIFACTS / f"{name}.png"
    page.screenshot(path=str(p), full_page=full_page)
    return p
