"""End to end in headless Chromium through the app's /viewer/ proxy.

Screenshots go to test-artifacts/viewer/. WebGL runs on SwiftShader (--use-angle=swiftshader).
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from playwright.sync_api import sync_playwright
from viewer_live import CHROMIUM_ARGS, REVIEWER, LiveServer, make_app

from app.viewer import scene_builder as sb
from app.viewer.demo_scene import make_demo_workspace
from occufly.camera import Camera, make_pose, project_world
from occufly.fsutil import atomic_save_npy

pytestmark = pytest.mark.e2e
ART = Path(__file__).resolve().parents[2] / "test-artifacts" / "viewer"
STATES = {0: "accepted", 1: "rejected", 2: "annotated", 3: "selected"}


def wait_for(pred, timeout: float, step: float = 0.1):
    t0 = time.time()
    while time.time() - t0 < timeout:
        v = pred()
        if v is not None and v is not False and (not isinstance(v, (int, set, list)) or v):
            return v
        time.sleep(step)
    return pred()


def png(b: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(b)).convert("RGB")).astype(np.int16)


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    root = tmp_path_factory.mktemp("viewer_e2e")
    make_demo_workspace(root / "demo", 60_000, seed=5, voxel_size=4.0)
    filed: list[tuple] = []
    masks: list[tuple] = []

    def on_item(scene_id, point_ids, comment, user):
        filed.append((scene_id, point_ids, comment, user))
        return {"id": len(filed)}

    def frame_mask(scene_id, fi):
        masks.append((scene_id, fi))
        m = np.zeros((60, 80), np.uint8)
        m[:, :40] = 6
        m[:, 40:] = 16
        return m

    app = make_app(root, on_review_item=on_item, frame_states=lambda sid: STATES,
                   frame_mask=frame_mask)
    ART.mkdir(parents=True, exist_ok=True)
    with LiveServer(app) as srv, sync_playwright() as p:
        browser = p.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        yield {"srv": srv, "app": app, "browser": browser, "ws": root / "demo", "filed": filed,
               "masks": masks}
        browser.close()


def test_unauthenticated_viewer_page_is_refused(env):
    ctx = env["browser"].new_context()
    page = ctx.new_page()
    resp = page.goto(env["srv"].url + "/viewer/")
    assert resp.status == 401
    assert "log in" in page.content()
    ctx.close()


def test_reviewer_sees_scene_toggles_classes_selects_and_gets_live_updates(env):
    srv, svc = env["srv"], env["app"].state.viewer
    ctx = env["browser"].new_context(viewport={"width": 1000, "height": 700})
    ctx.add_cookies([{"name": "occufly_session", "value": REVIEWER, "url": srv.url}])
    page = ctx.new_page()
    page.goto(srv.url + "/viewer/?scene=demo")
    st = wait_for(lambda: next(iter(svc.client_states()), None), 20)
    assert st is not None and wait_for(st.ready.is_set, 20)
    assert st.scene_id == "demo" and st.sent_points == 60_000
    canvas = page.locator("canvas").first

    def settle_shot(name: str, prev: np.ndarray | None = None) -> np.ndarray:
        time.sleep(0.8)
        img = png(canvas.screenshot())
        for _ in range(10):  # wait until two consecutive frames agree (render done)
            time.sleep(0.4)
            nxt = png(canvas.screenshot())
            if np.abs(nxt - img).mean() < 0.05:
                break
            img = nxt
        Image.fromarray(img.astype(np.uint8)).save(ART / f"{name}.png")
        return img

    # 1. the scene is drawn: many non-background pixels, real variance
    img0 = wait_for(lambda: (lambda im: im if im[im.shape[0] // 4:, : int(0.6 * im.shape[1])].std() > 20
                             else None)(settle_shot("01_semantic")), 20)
    assert img0 is not None, "canvas stayed blank"
    scene_area = img0[img0.shape[0] // 4:, : int(0.6 * img0.shape[1])]  # clear of GUI panels
    bg = np.median(img0.reshape(-1, 3), axis=0)
    drawn = (np.abs(scene_area - bg).sum(axis=2) > 30).mean()
    assert drawn > 0.10, f"only {drawn:.1%} of the canvas differs from the background"
    grass_px = (np.abs(img0 - np.array([0, 255, 0])).sum(axis=2) < 60).mean()
    assert grass_px > 0.02  # semantic colour of grass is on screen

    # 2. toggling a class in the side panel changes the picture
    page.get_by_text("grass (", exact=False).first.click()
    assert wait_for(lambda: st.class_visible.get(6) is False, 5)
    img1 = settle_shot("02_grass_hidden")
    changed = (np.abs(img1 - img0).sum(axis=2) > 30).mean()
    assert changed > 0.02, f"hiding grass changed only {changed:.2%} of the pixels"
    grass_after = (np.abs(img1 - np.array([0, 255, 0])).sum(axis=2) < 60).mean()
    assert grass_after < grass_px / 5

    # 3. colour mode from the dropdown
    page.get_by_text("grass (", exact=False).first.click()  # back on
    assert wait_for(lambda: st.class_visible.get(6) is True, 5)
    # 4. click the apex of frame 0's frustum (accepted, green): the panel shows it and its mask
    cam = st.client.camera
    R = sb.quat_to_matrix(cam.wxyz)
    pc = R.T @ (st.data.scene.frames[0].center - np.asarray(cam.position))
    t = np.tan(cam.fov / 2)
    u, v = 0.5 + pc[0] / (pc[2] * t * cam.aspect) / 2, 0.5 + pc[1] / (pc[2] * t) / 2
    box = canvas.bounding_box()
    assert 0.05 < u < 0.6 and 0.25 < v < 0.95  # on screen, clear of the panels
    page.mouse.click(box["x"] + u * box["width"], box["y"] + v * box["height"])
    assert wait_for(lambda: st.frame_index == 0, 5), "frustum click did not arrive"
    page_text = wait_for(lambda: "accepted" in page.inner_text("body") and page.inner_text("body"), 5)
    assert page_text and "img_0000" in page_text
    assert env["masks"] == [("demo", 0)]
    assert st.gui["mask"] is not None  # the mask image is in the side panel

    # 4b. "Show cameras" (Camera folder): only the selected/annotated frames, none, all again
    n_all = len(st.data.scene.frames)
    assert len(st.frustum_handles) == n_all
    assert f"{n_all} of {n_all} cameras shown" in page.inner_text("body")

    def show_cameras(choice: str) -> None:
        sel = page.get_by_label("Show cameras")
        sel.click()
        page.get_by_role("option", name=choice, exact=True).click()

    show_cameras("selected and annotated")
    assert wait_for(lambda: sorted(st.frustum_handles) == sorted(STATES), 10), sorted(st.frustum_handles)
    assert wait_for(lambda: f"{len(STATES)} of {n_all} cameras shown" in page.inner_text("body"), 5)
    show_cameras("none")
    assert wait_for(lambda: not st.frustum_handles, 10), sorted(st.frustum_handles)
    svc.focus_frame(st, 5)  # "Open in 3D" on a hidden camera shows and highlights it
    assert sorted(st.frustum_handles) == [5] and st.highlighted == 5
    assert st.frustum_handles[5].color == sb.HIGHLIGHT_COLOUR
    show_cameras("all")
    # the handles are replaced first, then the focused one highlighted again (GUI thread)
    assert wait_for(lambda: len(st.frustum_handles) == n_all
                    and st.frustum_handles[5].color == sb.HIGHLIGHT_COLOUR, 10)
    assert st.highlighted == 5

    # 5. the scene voxel grid as instanced boxes, toggled from the panel
    page.get_by_text("Voxel grids").click()
    grid_box = page.locator("div.mantine-Flex-root", has=page.get_by_text("Scene grid")).locator("input").last
    grid_box.evaluate("e => e.click()")  # JS click: boxes make software frames slow
    assert wait_for(lambda: "/grid/scene/building" in st.grid_handles, 10)
    # (no screenshot here: lit boxes take >10 s per software-rendered frame; see
    # examples/02_voxel_grids.py for a look)
    assert len(st.grid_handles["/grid/scene/building"].batched_positions) > 0
    grid_box.evaluate("e => e.click()")
    assert wait_for(lambda: not st.grid_handles, 10)

    # 6. rectangle select from a nadir camera, file a review item
    svc.move_to_camera(st, 4)
    cam = st.client.camera
    assert wait_for(lambda: np.allclose(cam.position, st.data.scene.frames[4].center, atol=1e-3), 5)
    assert cam.fov == pytest.approx(2 * np.arctan(300 / 700), rel=1e-3)  # demo camera 800x600, f=700
    settle_shot("03_nadir")
    page.get_by_text("Select points (drag a rectangle)").click()
    assert wait_for(lambda: "Drag" in st.gui["sel_info"].content, 5)
    time.sleep(0.7)  # let the rect-select filter reach the browser before the drag starts
    box = canvas.bounding_box()
    x0, y0 = box["x"] + 0.40 * box["width"], box["y"] + 0.40 * box["height"]
    x1, y1 = box["x"] + 0.60 * box["width"], box["y"] + 0.60 * box["height"]
    page.mouse.move(x0, y0)
    page.mouse.down()
    page.mouse.move((x0 + x1) / 2, (y0 + y1) / 2, steps=5)
    page.mouse.move(x1, y1, steps=5)
    page.mouse.up()
    page.screenshot(path=str(ART / "04_after_drag.png"))
    assert wait_for(lambda: len(st.selection) > 0, 10), st.gui["sel_info"].content
    sel = set(st.selection.tolist())
    # independent check: project the sent points with a pinhole camera built from the
    # browser camera (vertical fov, canvas aspect) and keep those inside the dragged box
    W, H = 1000, int(round(1000 / cam.aspect))
    fy = (H / 2) / np.tan(cam.fov / 2)
    pin = Camera("PINHOLE", W, H, np.array([fy, fy, W / 2, H / 2]))
    R = sb.quat_to_matrix(cam.wxyz)
    T_cam_world = make_pose(R.T, -R.T @ np.asarray(cam.position))
    ids = np.concatenate([nd.point_ids for nd in st.point_nodes.values()])
    uv, _, vis = project_world(pin, T_cam_world, np.asarray(st.data.scene.xyz[ids], np.float64))
    inside = vis & (uv[:, 0] >= 0.4 * W) & (uv[:, 0] <= 0.6 * W) & (uv[:, 1] >= 0.4 * H) & (uv[:, 1] <= 0.6 * H)
    expected = set(ids[inside].tolist())
    jaccard = len(sel & expected) / len(sel | expected)
    assert len(expected) > 100 and jaccard > 0.9, (len(sel), len(expected), jaccard)
    row = page.locator("div.mantine-Flex-root", has=page.locator("label", has_text="Comment"))
    row.locator("input").last.fill("roof looks like road here")
    assert wait_for(lambda: st.gui["comment"].value == "roof looks like road here", 5)
    page.get_by_text("File review item").click()
    assert wait_for(lambda: len(env["filed"]) == 1, 5)
    scene_id, point_ids, comment, user = env["filed"][0]
    assert scene_id == "demo" and set(point_ids) == sel
    assert comment == "roof looks like road here"
    assert user == {"username": "rita", "role": "reviewer"}

    # 7. live: a mask save relabels vehicles as trucks on disk; the viewer follows
    ws = env["ws"]
    labels = np.load(ws / "lifting" / "labels.npy")
    n_vehicle = int((labels == 13).sum())
    labels[labels == 13] = 36
    t0 = time.time()
    atomic_save_npy(ws / "lifting" / "labels.npy", labels)
    assert wait_for(lambda: 36 in st.point_nodes and 13 not in st.point_nodes, 8), "no live update"
    latency = time.time() - t0
    assert len(st.point_nodes[36].point_ids) == n_vehicle
    assert set(st.class_boxes) >= {36} and 13 not in st.class_boxes
    print(f"live update latency {latency:.2f} s")
    ctx.close()
