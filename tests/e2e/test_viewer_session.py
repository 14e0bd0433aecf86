"""Issue 40 in Chromium: a long viewer session keeps its one socket (defect 4), the viewer opens
at the frame's camera (defect 8), a forced reconnect keeps the selection and the panel, and
"File as proposal" turns the relabel into a proposal on the frame (defect 2).

The app is served a second time, on its own port, exactly as ``occufly serve`` serves it
(``app.serving.uvicorn_options``: the h11 protocol with the header and body timers) -- the
suite's ``live`` server is plain uvicorn, which is why no browser test ever saw the drops.

Why 5 s / 30 s instead of a 5-minute session: the old code closed every viewer socket
``OCCUFLY_BODY_IDLE_TIMEOUT_S`` after it opened, whatever the traffic. With the timeout at 5 s
and the session held 30 s (camera moves, a lasso, a relabel) the old code opens the socket
>= 6 times -- the same failure the 30 s default shows in 5 minutes, in a tenth of the time,
so the full suite stays fast. ``OCCUFLY_TEST_VIEWER_SESSION_S`` / ``..._IDLE_S`` lengthen it
(the 5-minute run with the default 30 s timeout, beside a CPU stress process, is in the
closing note of issue 40).
"""

from __future__ import annotations

import asyncio
import os
import time

import numpy as np
import pytest

from app.serving import TimedH11Protocol, uvicorn_options
from app.viewer import scene_builder as sb
from app.viewer.markdown_escape import md_text
from tests.e2e.conftest import REPO, grey_png, import_own_scene
from tests.harness import ThreadServer

pytestmark = pytest.mark.e2e
DOCS = REPO / "docs" / "screenshots"
TREE, ROAD = 8, 1
IDLE_S = float(os.environ.get("OCCUFLY_TEST_VIEWER_IDLE_S", "5"))
SESSION_S = float(os.environ.get("OCCUFLY_TEST_VIEWER_SESSION_S", "30"))


def _wait(pred, timeout=30.0, what="condition"):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        v = pred()
        if v is not None and v is not False and not (isinstance(v, (list, dict)) and not v):
            return v
        time.sleep(0.2)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")


@pytest.fixture(scope="module")
def served(live, tmp_path_factory):
    """The live app again, on a port of its own, served like ``occufly serve``; a scene with
    one submitted frame (all grass) and its first fill."""
    mp = pytest.MonkeyPatch()
    mp.setenv("OCCUFLY_BODY_IDLE_TIMEOUT_S", str(IDLE_S))  # read at each request
    sid = import_own_scene(live, "viewer_session")
    ann, rev = live.client("annotator"), live.client("reviewer")
    f = ann.post(f"/api/scenes/{sid}/next").json()
    m = np.full((f["height"], f["width"]), 6, np.uint8)
    r = ann.put(f"/api/frames/{f['id']}/mask?kind=submitted", content=grey_png(m),
                headers={"If-Match": "none", "Content-Type": "image/png"})
    assert r.status_code == 200, r.text
    _wait(lambda: str(f["id"]) in rev.get(f"/api/scenes/{sid}/labels/status").json()
          .get("filled_versions", {}), 90, "the first fill")
    with ThreadServer(live.app, lifespan="off", **uvicorn_options(None)) as srv:
        yield {"srv": srv, "sid": sid, "frame": f}
    mp.undo()


def _open(new_page, served, live):
    svc = live.app.state.viewer
    before = {id(c) for c in svc.client_states()}
    page = new_page("reviewer", viewport=(1200, 800))  # logs in on live (cookies: any port)
    opens: list[float] = []
    page.on("websocket", lambda ws: opens.append(time.monotonic()))
    page.goto(f"{served['srv'].url}/viewer/?scene={served['sid']}&frame={served['frame']['id']}")

    def mine():
        return next((c for c in svc.client_states() if id(c) not in before
                     and c.scene_id == str(served["sid"]) and c.ready.is_set()), None)

    return page, opens, _wait(mine, 60, "the viewer"), mine


def _lasso(page, st):
    canvas = page.locator("canvas").first
    page.get_by_role("button", name="Start selecting").click()  # tool: lasso
    _wait(lambda: st.armed is not None, 10, "lasso armed")
    time.sleep(0.7)  # the click filter reaches the browser
    box = canvas.bounding_box()
    for i, (u, v) in enumerate([(0.32, 0.30), (0.64, 0.30), (0.64, 0.66), (0.32, 0.66)]):
        for _try in range(3):  # a click the busy software renderer drops is clicked again
            page.mouse.click(box["x"] + u * box["width"], box["y"] + v * box["height"])
            try:
                _wait(lambda i=i: len(st.lasso) > i, 4, f"lasso vertex {i + 1}")
                break
            except AssertionError:
                continue
    assert len(st.lasso) == 4, st.lasso
    page.get_by_role("button", name="Close lasso").click()
    return _wait(lambda: st.selection.copy() if len(st.selection) else None, 15, "a selection")


def _relabel_to(page, st, name):
    page.get_by_role("combobox", name="Relabel to").click()
    page.get_by_role("option", name=name, exact=True).click()
    _wait(lambda: st.gui["to_class"].value == name, 10, f"'{name}' chosen")


def test_long_session_one_socket_frame_camera_relabel_and_proposal(live, served, new_page):
    sid, f = served["sid"], served["frame"]
    rev = live.client("reviewer")
    closed_before = TimedH11Protocol.closed_for_idle_body
    t0 = time.monotonic()
    page, opens, st, _ = _open(new_page, served, live)

    # defect 8: opened at the frame's camera -- pose and vertical fov -- as the *client*
    # reports it, its frustum highlighted, the other cameras hidden (toggle in the panel)
    fr = st.data.scene.frames[st.frame_index]
    assert st.highlighted == st.frame_index and md_text(fr.stem) in st.gui["cam_info"].content
    T = np.linalg.inv(np.asarray(fr.T_cam_world, np.float64))
    cam = st.client.camera
    fov = 2.0 * np.arctan2(fr.camera.height / 2.0, fr.camera.focal[1])

    def at_frame():
        R = sb.quat_to_matrix(cam.wxyz)
        return (np.allclose(cam.position, T[:3, 3], atol=1e-3)
                and abs(cam.fov - fov) < 1e-3
                and float(R[:, 2] @ T[:3, 2]) > 0.9999  # looks where the frame looks
                and float(R[:, 1] @ T[:3, 1]) > 0.999)  # same roll

    _wait(at_frame, 20, "the client's camera at the frame's camera")
    assert sorted(st.frustum_handles) == [st.frame_index]
    assert tuple(st.frustum_handles[st.frame_index].color) == sb.HIGHLIGHT_COLOUR
    assert st.gui["frusta"].value == "none" and "hidden" in st.gui["frusta_info"].content
    time.sleep(3.0)  # the points fade in
    DOCS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(DOCS / "viewer_frame.png"))

    # defect 4: the session lasts (camera reports flow), the socket is never reopened
    canvas = page.locator("canvas").first
    box = canvas.bounding_box()
    while time.monotonic() - t0 < SESSION_S - 10:
        page.mouse.move(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.5)
        page.mouse.wheel(0, 40)  # zoom a little: the client reports its camera
        time.sleep(2.0)
    # back to the frame's camera, then lasso -> relabel
    live.app.state.viewer.move_to_camera(st, st.frame_index)
    _wait(at_frame, 20, "the camera back at the frame")
    time.sleep(1.0)
    chosen = _lasso(page, st)
    _relabel_to(page, st, f"tree ({TREE})")
    page.get_by_role("button", name="Relabel selection").click()
    e = _wait(lambda: next((x for x in rev.get(f"/api/scenes/{sid}/corrections").json()
                            if x["n_points"] == len(chosen) and x["to_class"] == TREE), None),
              20, "the correction")
    assert e["frame_id"] == f["id"]
    while time.monotonic() - t0 < SESSION_S:
        time.sleep(0.5)
    page.evaluate("() => 1")  # let Playwright deliver pending websocket events
    assert len(opens) == 1, (f"the viewer opened its socket {len(opens)} times in "
                             f"{time.monotonic() - t0:.0f} s (at "
                             f"{[round(x - opens[0], 1) for x in opens]} s)")
    assert TimedH11Protocol.closed_for_idle_body == closed_before

    # defect 2: the relabel filed as a proposal on the frame the viewer was opened for
    _wait(lambda: e["id"] in rev.get(f"/api/scenes/{sid}/corrections/layer").json()["applied"],
          20, "the layer")
    page.get_by_role("button", name="File as proposal").click()
    props = _wait(lambda: rev.get(f"/api/frames/{f['id']}/proposals").json(), 20,
                  f"the proposal ({st.gui['propose_info'].content})")
    assert props[-1]["edit_id"] == e["id"] and props[-1]["changed_px"] > 0
    assert f"Proposal **{props[-1]['id']}** filed" in st.gui["propose_info"].content
    # an undone correction is refused, with the reason, and nothing is filed
    page.get_by_role("button", name="Undo my last correction").click()
    _wait(lambda: rev.get(f"/api/scenes/{sid}/corrections").json()[-1]["state"] == "undone",
          20, "undo")
    page.get_by_role("button", name="File as proposal").click()
    _wait(lambda: "refused" in st.gui["propose_info"].content, 10, "the refusal")
    assert "undone" in st.gui["propose_info"].content
    assert len(rev.get(f"/api/frames/{f['id']}/proposals").json()) == len(props)


def test_forced_reconnect_keeps_selection_and_panel_and_relabel_works(live, served, new_page):
    sid = served["sid"]
    rev = live.client("reviewer")
    svc = live.app.state.viewer
    page, opens, st, _ = _open(new_page, served, live)
    fr_index = st.frame_index
    time.sleep(1.0)
    chosen = _lasso(page, st)
    _relabel_to(page, st, f"road ({ROAD})")
    page.get_by_role("combobox", name="Tool").click()
    page.get_by_role("option", name="rectangle", exact=True).click()
    _wait(lambda: st.gui["tool"].value == "rectangle", 10, "the tool")
    counts = st.gui["counts"].content

    def camera_at_rest():  # the flight to the frame's camera may still be reporting
        a = np.asarray(st.client.camera.position).copy()
        time.sleep(0.6)
        return a if np.allclose(a, st.client.camera.position, atol=1e-6) else None

    pos = _wait(camera_at_rest, 30, "the camera at rest")

    # the server drops the socket (as a restart or a proxy would): viser's page reconnects
    ws = svc.server._websock_server
    conn = ws._live_connections[st.client.client_id]
    asyncio.run_coroutine_threadsafe(conn.close(1012, "restart"), ws._background_event_loop)
    st2 = _wait(lambda: next((c for c in svc.client_states() if c is not st
                              and c.scene_id == str(sid) and c.ready.is_set()), None),
                60, "the reconnected viewer")
    page.evaluate("() => 1")
    assert len(opens) == 2  # one reconnect
    assert np.array_equal(st2.selection, chosen)
    assert st2.gui["to_class"].value == f"road ({ROAD})"
    assert st2.gui["tool"].value == "rectangle"
    assert st2.gui["counts"].content == counts
    assert st2.frame_index == fr_index == st2.highlighted
    assert st2.gui["relabel_btn"].disabled is False
    # not flown back: the restored camera, as the browser reports it once it has applied it
    # (the server's copy of a camera is the browser's last report, which may still be the
    # scene's opening view right after the reconnect on a loaded machine)
    _wait(lambda: np.allclose(st2.client.camera.position, pos, atol=1e-3), 30,
          "the camera put back where it was before the reconnect")
    # the dropdowns are clickable after the reconnect, and relabel works
    page.get_by_role("combobox", name="Tool").click()
    page.get_by_role("option", name="lasso", exact=True).click()
    _wait(lambda: st2.gui["tool"].value == "lasso", 10, "the tool after the reconnect")
    _relabel_to(page, st2, f"tree ({TREE})")
    page.get_by_role("button", name="Relabel selection").click()
    e = _wait(lambda: next((x for x in rev.get(f"/api/scenes/{sid}/corrections").json()
                            if x["n_points"] == len(chosen) and x["to_class"] == TREE
                            and x["state"] == "active"), None), 20, "the relabel")
    assert e["author"] == "reviewer"
    _wait(lambda: len(st2.selection) == 0, 10, "the selection consumed by the relabel")

    # a reload of the page is a new tab state: opens fresh at the frame
    page.reload()
    st3 = _wait(lambda: next((c for c in svc.client_states() if c not in (st, st2)
                              and c.scene_id == str(sid) and c.ready.is_set()), None),
                60, "the reloaded viewer")
    assert len(st3.selection) == 0 and st3.gui["tool"].value == "lasso"
    assert st3.frame_index == fr_index
