"""Issue 17, "measure the promise" on real saved masks: each submit records how much the mask
differs from the prefill its author started from; the hand-out order; the prefill's closed
render holes (on both databases where the app is involved)."""

from __future__ import annotations

import io
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from occufly.render import close_holes
from occufly.scene import Visibility
from tests.app.conftest import H, W, png


def _ids(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)))


def _lease(env, hdr, scene, who="annotator") -> int:  # noqa: ANN001
    r = env.client.post(f"/api/scenes/{scene['id']}/next", headers=hdr[who])
    assert r.status_code == 200, r.text
    return r.json()["id"]


def _submit(env, hdr, fid, mask, who="annotator", prefill=None, if_match="none"):  # noqa: ANN001
    extra = {"X-Prefill-Id": str(prefill)} if prefill is not None else {}
    r = env.client.put(f"/api/frames/{fid}/mask?kind=submitted", content=png(mask),
                       headers={**hdr[who], "If-Match": if_match, **extra})
    assert r.status_code == 200, r.text
    return r.json()


def test_submit_records_pixels_changed_versus_the_authors_prefill(world):
    env, hdr, scene, _frames = world
    sid = scene["id"]
    assert env.client.get(f"/api/scenes/{sid}/effort", headers=hdr["admin"]).json()["submissions"] == []
    # 1st frame: no lifted labels yet, painted from an empty mask -> changed = painted
    f1 = _lease(env, hdr, scene)
    m1 = np.zeros((H, W), np.uint8)
    m1[:, : W // 2] = 6
    m1[:5, -5:] = 255  # "ignore" is painted too
    _submit(env, hdr, f1, m1)
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=20)

    # 2nd frame: the annotator takes the prefill, corrects a block and submits
    f2 = _lease(env, hdr, scene)
    r = env.client.get(f"/api/frames/{f2}/prefill", headers=hdr["annotator"])
    assert r.status_code == 200 and r.headers.get("X-Prefill-Id")
    pre = _ids(r.content)
    assert pre.shape == (H, W) and (pre > 0).any()
    # another user's prefill of the same frame is not what this annotator started from
    assert env.client.get(f"/api/frames/{f2}/prefill", headers=hdr["reviewer"]).status_code == 200
    m2 = pre.copy()
    m2[pre == 0] = 6  # paints what the prefill left empty
    m2[2:12, 3:23] = 1  # and corrects a 10 x 20 block to road
    expected = int((m2 != pre).sum())
    assert 0 < expected < int((m2 > 0).sum())
    _submit(env, hdr, f2, m2, prefill=r.headers["X-Prefill-Id"])

    e = env.client.get(f"/api/scenes/{sid}/effort", headers=hdr["admin"]).json()
    a, b = e["submissions"]
    assert (a["n"], a["frame_id"], a["prefilled"]) == (1, f1, False)
    assert a["painted_px"] == a["changed_px"] == int((m1 > 0).sum())
    assert a["pixels"] == H * W and a["painted_share"] == pytest.approx((m1 > 0).mean())
    assert (b["n"], b["frame_id"], b["prefilled"], b["author"]) == (2, f2, True, "annotator")
    assert b["painted_px"] == int((m2 > 0).sum()) and b["changed_px"] == expected
    assert b["changed_share"] == pytest.approx(expected / (H * W))
    t = e["totals"]
    assert (t["submissions"], t["prefilled"]) == (2, 1)
    assert t["painted_px"] == a["painted_px"] + b["painted_px"]
    assert t["changed_px"] == a["changed_px"] + b["changed_px"]
    assert t["reduction_x"] == pytest.approx(t["painted_px"] / t["changed_px"])
    assert t["median_changed_of_painted_from_6th"] is None  # fewer than 6 submissions
    # drafts are not submissions; only admins read the curve
    f3 = _lease(env, hdr, scene)
    r = env.client.put(f"/api/frames/{f3}/mask?kind=draft", content=png(m1),
                       headers={**hdr["annotator"], "If-Match": "none"})
    assert r.status_code == 200
    assert len(env.client.get(f"/api/scenes/{sid}/effort", headers=hdr["admin"]).json()["submissions"]) == 2
    for who in ("annotator", "reviewer"):
        assert env.client.get(f"/api/scenes/{sid}/effort", headers=hdr[who]).status_code == 403


def test_a_prefill_at_another_resolution_is_compared_on_the_masks_grid(world):
    env, hdr, scene, _frames = world
    sid = scene["id"]
    f1 = _lease(env, hdr, scene)
    _submit(env, hdr, f1, np.full((H, W), 6, np.uint8))
    assert env.app.state.ctx.lifting.wait_idle(sid, timeout=20)
    f2 = _lease(env, hdr, scene)
    r = env.client.get(f"/api/frames/{f2}/prefill?downscale=2", headers=hdr["annotator"])
    half = _ids(r.content)
    assert half.shape == (H // 2, W // 2)
    full = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)
    m = full.copy()
    m[m == 0] = 6
    m[:4, :4] = 1
    _submit(env, hdr, f2, m, prefill=r.headers["X-Prefill-Id"])
    b = env.client.get(f"/api/scenes/{sid}/effort", headers=hdr["admin"]).json()["submissions"][-1]
    assert b["prefilled"] and b["changed_px"] == int((m != full).sum())


def _lifted_first_frame(env, hdr, scene) -> int:  # noqa: ANN001
    f1 = _lease(env, hdr, scene)
    _submit(env, hdr, f1, np.full((H, W), 6, np.uint8))
    assert env.app.state.ctx.lifting.wait_idle(scene["id"], timeout=20)
    return f1


def test_an_undone_prefill_does_not_count(world):
    """Issue 28 item 5: the editor asked for a prefill, undid it and painted from scratch:
    the submit names no prefill, so the mask is not "started from the 3D prefill"."""
    env, hdr, scene, _frames = world
    _lifted_first_frame(env, hdr, scene)
    f2 = _lease(env, hdr, scene)
    r = env.client.get(f"/api/frames/{f2}/prefill", headers=hdr["annotator"])
    assert r.status_code == 200 and r.headers.get("X-Prefill-Id")
    m = np.full((H, W), 6, np.uint8)  # identical to the prefill: painted by hand after undo
    _submit(env, hdr, f2, m)  # no X-Prefill-Id: the editor dropped it with the undo
    e = env.client.get(f"/api/scenes/{scene['id']}/effort", headers=hdr["admin"]).json()
    b = e["submissions"][-1]
    assert b["frame_id"] == f2 and not b["prefilled"]
    assert b["changed_px"] == b["painted_px"] == H * W
    assert e["totals"]["prefilled"] == 0 and e["totals"]["reduction_x"] == pytest.approx(1.0)


def test_a_named_prefill_must_be_the_authors_of_this_frame(world):
    env, hdr, scene, _frames = world
    _lifted_first_frame(env, hdr, scene)
    f2 = _lease(env, hdr, scene)
    other = env.client.get(f"/api/frames/{f2}/prefill", headers=hdr["admin"]).headers["X-Prefill-Id"]
    r = env.client.put(f"/api/frames/{f2}/mask?kind=submitted", content=png(np.full((H, W), 6, np.uint8)),
                       headers={**hdr["annotator"], "If-Match": "none", "X-Prefill-Id": other})
    assert r.status_code == 422 and f"X-Prefill-Id {other}" in r.json()["detail"]
    assert env.client.get(f"/api/frames/{f2}", headers=hdr["admin"]).json()["current_version"] is None


def test_a_prefill_of_the_frames_own_mask_is_not_recorded(world):
    """A reopened frame's prefill renders the labels its own submitted mask voted for: it
    gives the annotator's work back and saves nothing, so it is not handed out as a prefill
    the submit could name."""
    env, hdr, scene, _frames = world
    f1 = _lifted_first_frame(env, hdr, scene)
    r = env.client.post(f"/api/frames/{f1}/reopen", headers=hdr["annotator"])
    assert r.status_code == 200, r.text
    r = env.client.get(f"/api/frames/{f1}/prefill", headers=hdr["annotator"])
    assert r.status_code == 200 and (_ids(r.content) == 6).mean() > 0.5
    assert r.headers.get("X-Prefill-Own-Mask") == "1" and "X-Prefill-Id" not in r.headers
    with env.app.state.ctx.sessions() as s:
        from sqlalchemy import func, select

        from app.annotations.models import Prefill

        assert s.scalar(select(func.count(Prefill.id)).where(Prefill.frame_id == f1)) == 0


def test_a_resubmission_counts_once(world):
    """Submitted, reopened, submitted again: one frame, one row (its first submission)."""
    env, hdr, scene, _frames = world
    f1 = _lease(env, hdr, scene)
    m = np.zeros((H, W), np.uint8)
    m[:, : W // 2] = 6
    v1 = _submit(env, hdr, f1, m)
    assert env.client.post(f"/api/frames/{f1}/reopen", headers=hdr["annotator"]).status_code == 200
    m2 = m.copy()
    m2[:4] = 1
    _submit(env, hdr, f1, m2, if_match=str(v1["version"]))
    e = env.client.get(f"/api/scenes/{scene['id']}/effort", headers=hdr["admin"]).json()
    assert [r["frame_id"] for r in e["submissions"]] == [f1]
    row = e["submissions"][0]
    assert row["version"] == v1["version"] and row["resubmissions"] == 1
    t = e["totals"]
    assert (t["submissions"], t["resubmissions"], t["painted_px"]) == (1, 1, int((m > 0).sum()))


def test_next_hands_frames_out_in_the_selections_handout_order(world):
    env, hdr, scene, _frames = world
    from app.scenes import service as scenes
    from app.scenes.models import Scene

    ctx = env.app.state.ctx
    with ctx.sessions() as s:
        row = s.get(Scene, scene["id"])
        ws = ctx.load_scene(row.workspace)
        order = scenes.handout_order(ws, [0, 1, 2, 3])
        scenes.apply_selection(session=s, scene=row, result={"frames": [0, 1, 2, 3]}, ws_scene=ws)
        assert s.get(Scene, scene["id"]).selection["handout_order"] == order
    assert sorted(order) == [0, 1, 2, 3]
    # the tiny scene's cameras line up along x: the first sees the most points, and every
    # later one the most points none before it sees
    seen, counts = set(), []
    for f in order:
        ids = set(ws.visibility.frame_ids(f).tolist())
        counts.append(len(ids - seen))
        seen |= ids
    assert counts[0] == max(len(set(ws.visibility.frame_ids(f).tolist())) for f in range(4))
    idx_of = {fr["id"]: fr["index"] for fr in env.client.get(
        f"/api/scenes/{scene['id']}/frames", headers=hdr["admin"]).json()}
    got = []
    for _ in order:
        fid = _lease(env, hdr, scene)
        got.append(idx_of[fid])
        _submit(env, hdr, fid, np.full((H, W), 6, np.uint8))
    assert got == order


def test_handout_order_takes_the_frame_with_the_most_unseen_points_next():
    # frame 0 sees points 0-59, 1 sees 50-79, 2 sees 100-139, 3 sees 0-29
    spans = [(0, 60), (50, 80), (100, 140), (0, 30)]
    parts = [(np.arange(a, b, dtype=np.int32), np.zeros((b - a, 2), np.float32),
              np.ones(b - a, np.float32)) for a, b in spans]
    ws = SimpleNamespace(visibility=Visibility.from_parts(parts), n_points=140)
    from app.scenes.service import handout_order

    # 60 new, then 40 new (frame 2) before 20 new (frame 1); frame 3 adds nothing
    assert handout_order(ws, [3, 2, 1, 0]) == [0, 2, 1, 3]
    assert handout_order(ws, [1, 3]) == [1, 3]  # a tie (30 new each) goes to the lower index
    assert handout_order(ws, [2]) == [2] and handout_order(ws, []) == []


def test_close_holes_fills_gaps_between_rendered_pixels_but_not_open_borders():
    cls = np.zeros((40, 60), np.uint8)
    depth = np.zeros((40, 60), np.float32)
    # a sparse block of rendered pixels every 4 px (holes of 3 px between them), two classes
    cls[10:31:4, 10:31:4] = 3
    cls[10:31:4, 40:49:4] = 7
    depth[cls > 0] = 5.0
    out, d, filled = close_holes(cls, depth, 2)
    inner = np.zeros_like(filled)
    inner[10:31, 10:31] = True
    inner[10:31, 40:49] = True
    assert filled[inner & (cls == 0)].all()  # every gap inside the sparse blocks is closed
    assert (out[10:31, 10:31] == 3).all() and (out[10:31, 40:49] == 7).all()
    assert (d[filled] == 5.0).all()
    # the open borders and the 9 px gap between the two blocks are wider than the closing
    assert not filled[:10].any() and not filled[:, :10].any() and not filled[:, 49:].any()
    assert not filled[:, 31:40].any()
    assert np.array_equal(out[cls > 0], cls[cls > 0])  # rendered pixels are never changed
    # radius 0 or nothing rendered: unchanged
    assert not close_holes(cls, depth, 0)[2].any()
    z = np.zeros_like(cls)
    assert not close_holes(z, np.zeros_like(depth), 3)[2].any()
