"""Lifting: incremental votes, tie order, masks, bad input, kNN fill/denoise, export, CLI."""

from __future__ import annotations

import io
import json
import time

import numpy as np
import pytest
from PIL import Image

from occufly.errors import MaskError
from occufly.io.masks import encode_mask_png, read_mask, write_mask
from occufly.lifting import (
    ORIGIN_DENOISED,
    ORIGIN_DIRECT,
    ORIGIN_FILLED,
    LiftParams,
    VoteStore,
    fill_and_denoise,
    fill_and_denoise_exact,
    load_labels,
)
from occufly.metrics import evaluate_points
from occufly.scene import Scene
from occufly.selection import select_frames
from occufly.taxonomy import default_taxonomy
from tests.lift_scene import BUILDING, GRASS, ROAD, make_scene, truth_mask

TAX = default_taxonomy()


@pytest.fixture(scope="module")
def built():
    return make_scene()


@pytest.fixture()
def ws(tmp_path, built):
    scene, truth = built
    scene.save(tmp_path / "ws")
    return tmp_path / "ws", Scene.load(tmp_path / "ws"), truth


def _expected_votes(scene, fi, mask):
    """(point ids, raw ids) a mask gives by direct lookup, computed independently."""
    pids, uv, _ = scene.visibility.frame(fi)
    s = scene.frames[fi].camera.width // mask.shape[1]
    raw = mask[(np.asarray(uv)[:, 1] // s).astype(int), (np.asarray(uv)[:, 0] // s).astype(int)]
    keep = (raw != 0) & (raw != 255)
    return np.asarray(pids)[keep], raw[keep]


# ---- votes -------------------------------------------------------------------------------
def test_votes_are_the_mask_pixels(ws):
    path, scene, truth = ws
    st = VoteStore.open(path, scene)
    mask = truth_mask(scene.frames[5])
    stats = st.set_mask(5, mask, version="v1")
    pids, raw = _expected_votes(scene, 5, mask)
    direct = st.direct_labels()
    assert np.array_equal(direct[pids], raw)
    unseen = np.ones(scene.n_points, bool)
    unseen[pids] = False
    assert (direct[unseen] == 0).all()
    assert int(np.asarray(st.votes).sum()) == len(pids) == stats["votes_added"]
    assert stats["points_touched"] == len(pids)
    # the truth mask agrees with the analytic labels on almost all of the points it sees
    assert (raw == truth[pids]).mean() > 0.9
    assert st.included_versions() == {5: "v1"}


def test_replace_and_remove_subtract_exactly(ws, tmp_path):
    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    st.set_mask(0, truth_mask(scene.frames[0]), version="a")
    st.set_mask(5, truth_mask(scene.frames[5]), version="b")
    grass = np.full((scene.frames[0].camera.height, scene.frames[0].camera.width), GRASS, np.uint8)
    stats = st.set_mask(0, grass, version="c")  # replace
    assert stats["votes_removed"] > 0 and stats["votes_added"] > 0
    st.remove_mask(5)
    # the same final content built from scratch in a second workspace
    scene.save(tmp_path / "ws2")
    fresh = VoteStore.open(tmp_path / "ws2", Scene.load(tmp_path / "ws2"))
    fresh.set_mask(0, grass, version="c")
    assert np.array_equal(np.asarray(st.votes), np.asarray(fresh.votes))
    assert st.included_versions() == {0: "c"}
    # reopening from disk gives the same state
    again = VoteStore.open(path)
    assert np.array_equal(np.asarray(again.votes), np.asarray(fresh.votes))
    assert again.included_versions() == {0: "c"}
    again.remove_mask(0)
    assert int(np.asarray(again.votes).sum()) == 0
    assert (again.direct_labels() == 0).all()
    assert again.remove_mask(0)["removed"] is False


def test_ties_follow_taxonomy_order(ws):
    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    h, w = scene.frames[0].camera.height, scene.frames[0].camera.width
    st.set_mask(4, np.full((h, w), GRASS, np.uint8))
    st.set_mask(5, np.full((h, w), ROAD, np.uint8))
    both = np.intersect1d(scene.visibility.frame(4)[0], scene.visibility.frame(5)[0])
    assert len(both) > 100
    order = list(TAX.tie_order)
    winner = GRASS if order.index(GRASS) < order.index(ROAD) else ROAD
    assert winner == GRASS  # grass is more frequent than road in the default table
    assert (st.direct_labels()[both] == winner).all()
    # a third vote breaks the tie the other way
    st.set_mask(6, np.full((h, w), ROAD, np.uint8))
    three = np.intersect1d(both, scene.visibility.frame(6)[0])
    assert len(three) > 0 and (st.direct_labels()[three] == ROAD).all()


def test_downscaled_mask_votes(ws):
    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    mask2 = truth_mask(scene.frames[10], scale=2)
    assert mask2.shape == (60, 80)
    st.set_mask(10, mask2)
    pids, raw = _expected_votes(scene, 10, mask2)
    assert np.array_equal(st.direct_labels()[pids], raw)


def _state_bytes(st):
    return np.asarray(st.votes).tobytes(), st.included_versions()


def test_bad_masks_raise_and_leave_state_unchanged(ws, tmp_path):
    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    st.set_mask(3, truth_mask(scene.frames[3]), version="ok")
    before = _state_bytes(st)
    frame = scene.frames[3]
    h, w = frame.camera.height, frame.camera.width
    bad = {
        "wrong_size.png": encode_mask_png(np.full((h - 1, w), GRASS, np.uint8)),
        "not_png.png": b"GIF89a this is not a png",
        "jpeg.png": _jpeg_bytes(h, w),
        "bad_colour.png": _png_rgb(np.full((h, w, 3), (1, 2, 3), np.uint8)),
        "bad_id.png": encode_mask_png(np.full((h, w), 10, np.uint8)),
        "non_integer_scale.png": encode_mask_png(np.full((h // 3 + 1, w // 3), GRASS, np.uint8)),
    }
    for name, data in bad.items():
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(MaskError, match=name):
            read_mask(p, frame, TAX)
        with pytest.raises(MaskError, match="upload-x"):
            read_mask(data, frame, TAX, name="upload-x")
    # arrays handed to set_mask directly are validated too
    with pytest.raises(MaskError, match="not in taxonomy"):
        st.set_mask(3, np.full((h, w), 10, np.uint8), name="m.png")
    with pytest.raises(MaskError, match="m.png"):
        st.set_mask(3, np.full((h, w + 2), GRASS, np.uint8), name="m.png")
    with pytest.raises(MaskError, match="not in the scene"):
        st.set_mask(999, np.full((h, w), GRASS, np.uint8), name="ghost.png")
    with pytest.raises(MaskError, match="not in the scene"):
        st.remove_mask(-1)
    assert _state_bytes(st) == before
    assert _state_bytes(VoteStore.open(path)) == before


def _png_rgb(rgb):
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return buf.getvalue()


def _jpeg_bytes(h, w):
    buf = io.BytesIO()
    Image.fromarray(np.zeros((h, w), np.uint8)).save(buf, format="JPEG")
    return buf.getvalue()


def test_mask_encodings_round_trip(ws, tmp_path):
    _, scene, _ = ws
    frame = scene.frames[5]
    ids = truth_mask(frame)
    ids[:5, :5] = 255
    ids[5:10, :5] = 0
    write_mask(tmp_path / "m.png", ids)
    assert np.array_equal(read_mask(tmp_path / "m.png", frame, TAX), ids)
    # RGB colours of the taxonomy (black = unpainted) decode to the same ids
    rgb = TAX.colour_lut()[np.where(ids == 255, 0, ids)]
    got = read_mask(_png_rgb(rgb), frame, TAX)
    assert np.array_equal(got, np.where(ids == 255, 0, ids))
    # 16-bit single channel with ids <= 255
    buf = io.BytesIO()
    Image.fromarray(ids.astype(np.uint16)).save(buf, format="PNG")
    assert np.array_equal(read_mask(buf.getvalue(), frame, TAX), ids)


def test_interrupted_update_is_repaired_on_open(ws):
    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    st.set_mask(2, truth_mask(scene.frames[2]))
    st.set_mask(7, truth_mask(scene.frames[7]))
    good = np.asarray(st.votes).copy()
    # simulate a crash in the middle of an update: dirty flag set, counts half-written
    st._write_state(dirty=True)
    st.votes[:100] += 3
    st.votes.flush()
    del st
    again = VoteStore.open(path)
    assert np.array_equal(np.asarray(again.votes), good)
    assert json.loads((path / "lifting" / "state.json").read_text())["dirty"] is False


# ---- fill and denoise --------------------------------------------------------------------
def test_fill_is_inverse_distance_weighted_and_bounded():
    rng = np.random.default_rng(1)
    a = rng.uniform([0, 0, 0], [1, 1, 0.01], (200, 3))
    b = rng.uniform([5, 0, 0], [6, 1, 0.01], (200, 3))
    q = np.array([[1.6, 0.5, 0.0], [4.2, 0.5, 0.0], [30.0, 0.5, 0.0]])
    xyz = np.vstack([a, b, q]).astype(np.float32)
    direct = np.concatenate([np.full(200, ROAD), np.full(200, BUILDING), np.zeros(3)]).astype(np.uint8)
    params = LiftParams(fill_k=400, fill_radius=10.0, denoise_k=5, denoise_radius=10.0)
    for method in ("voxel", "exact"):
        # the far pass is opt-in since issue 23 (fill_far=True; it was the default, and this
        # test ran it without naming it): same assertions as before
        res = fill_and_denoise(xyz, direct, TAX, params=LiftParams(**{**params.__dict__, "method": method,
                                                                      "fill_far": True}))
        # with k covering both clusters, the nearer cluster wins only through 1/d weights
        assert res.labels[400] == ROAD and res.labels[401] == BUILDING, method
        # beyond the radius: the far pass fills it from the nearest cluster (24 m vs 29 m away)
        assert res.labels[402] == BUILDING and res.origin[402] == ORIGIN_FILLED, method
        assert res.origin[400] == ORIGIN_FILLED and res.origin[0] == ORIGIN_DIRECT
        # with the far pass off (the default) it stays unlabelled
        bounded = fill_and_denoise(xyz, direct, TAX,
                                   params=LiftParams(**{**params.__dict__, "method": method, "fill_far": False}))
        assert bounded.labels[402] == 0 and bounded.origin[402] == 0, method
        assert np.array_equal(bounded.labels[:402], res.labels[:402])
    # same sizes, unweighted, the tie would go to building (more frequent): weights matter
    assert list(TAX.tie_order).index(BUILDING) < list(TAX.tie_order).index(ROAD)


def test_denoise_relabels_isolated_noise():
    rng = np.random.default_rng(2)
    xyz = np.column_stack([rng.uniform(0, 20, 20000), rng.uniform(0, 20, 20000),
                           np.zeros(20000)]).astype(np.float32)
    direct = np.full(20000, GRASS, np.uint8)
    noisy = rng.choice(20000, 100, replace=False)
    direct[noisy] = BUILDING
    for method in ("voxel", "exact"):
        res = fill_and_denoise(xyz, direct, TAX, params=LiftParams(method=method))
        assert (res.labels == GRASS).all(), method
        assert (res.origin[noisy] == ORIGIN_DENOISED).all()
        others = np.setdiff1d(np.arange(20000), noisy)
        assert (res.origin[others] == ORIGIN_DIRECT).all()
        assert res.confidence[others].min() > 0.9


@pytest.mark.parametrize("k", [(100, 200), (10, 30)])
def test_voxel_method_matches_exact_baseline(built, k):
    scene, truth = built
    rng = np.random.default_rng(3)
    direct = truth.copy()
    flip = rng.random(len(direct)) < 0.05
    direct[flip] = rng.choice(TAX.ids, int(flip.sum()))
    direct[rng.random(len(direct)) < 0.1] = 0
    p = dict(fill_k=k[0], denoise_k=k[1])
    fast = fill_and_denoise(scene.xyz, direct, TAX, params=LiftParams(**p))
    exact = fill_and_denoise_exact(scene.xyz, direct, TAX, params=LiftParams(**p))
    assert (fast.labels == exact.labels).mean() >= 0.99
    assert np.array_equal(fast.origin > 0, exact.origin > 0)
    if k[1] == 30:  # dense enough for whole voxels to be certified
        assert fast.stats["certified_voxels"] > 0
        assert fast.stats["block_denoise_points"] < 0.8 * len(direct)


def test_lift_truth_masks_of_selected_frames(ws):
    path, scene, truth = ws
    sel = select_frames(scene, mode="greedy", target_coverage=0.99)
    assert sel.coverage >= 0.99
    st = VoteStore.open(path, scene)
    for fi in sel.frames:
        st.set_mask(fi, truth_mask(scene.frames[fi]), version=str(fi))
    res = st.fill_and_denoise()
    ev = evaluate_points(res.labels, truth, TAX, res.origin)
    assert ev["accuracy"] >= 0.97
    assert ev["per_class"]["grass"]["iou"] > 0.98
    assert ev["per_class"]["building"]["iou"] > 0.8
    loaded = load_labels(path)
    assert np.array_equal(np.asarray(loaded.labels), res.labels)
    assert np.array_equal(np.asarray(loaded.origin), res.origin)
    assert loaded.stats["annotated_frames"] == len(sel.frames)
    # lifting wrong masks is measurably wrong
    st2 = VoteStore.open(path, scene)
    for fi in sel.frames:
        st2.set_mask(fi, np.full_like(truth_mask(scene.frames[fi]), ROAD))
    bad = evaluate_points(st2.fill_and_denoise().labels, truth, TAX)
    assert bad["accuracy"] < 0.2


def test_evaluate_points_analytic():
    truth = np.array([6, 6, 6, 16, 16, 0, 255], np.uint8)
    pred = np.array([6, 6, 16, 16, 0, 6, 6], np.uint8)
    ev = evaluate_points(pred, truth, TAX)
    assert ev["evaluated"] == 5 and ev["unlabelled"] == 1
    assert ev["accuracy"] == pytest.approx(3 / 5)
    assert ev["per_class"]["grass"]["iou"] == pytest.approx(2 / 3)
    assert ev["per_class"]["building"]["iou"] == pytest.approx(1 / 3)
    assert ev["miou"] == pytest.approx(0.5)


# ---- export and CLI ----------------------------------------------------------------------
def test_export_round_trips_georeferenced(built, tmp_path):
    import laspy

    from occufly.io.pointcloud_export import export_scene_points, read_semantic_ply

    scene, truth = built
    world = scene.xyz_world()
    assert world[:, 1].min() > 5e6  # UTM-like northing
    for ext in ("ply", "las", "laz"):
        out = tmp_path / f"cloud.{ext}"
        info = export_scene_points(scene, truth, out)
        assert info["points"] == scene.n_points
        if ext == "ply":
            d = read_semantic_ply(out)
            xyz = np.column_stack([d["x"], d["y"], d["z"]])
            labels = d["label"]
            assert np.array_equal(xyz, world)
        else:
            las = laspy.read(out)
            xyz = np.column_stack([las.x, las.y, las.z])
            labels = np.asarray(las.class_id)  # the full id; classification holds ASPRS codes
            assert np.array_equal(np.asarray(las.classification), scene.taxonomy.asprs_lut()[truth])
            assert np.abs(xyz - world).max() <= 0.0005 + 1e-9
            assert list(las.header.scales) == [0.001] * 3
            assert las.header.point_format.id == 7
        assert np.array_equal(labels, truth)
    assert not list(tmp_path.glob(".*.tmp"))


def test_cli_select_lift_agreement_eval_export(ws, tmp_path, capsys):
    from occufly.cli import main

    path, scene, truth = ws
    assert main(["select", str(path), "--mode", "greedy", "--json"]) == 0
    sel = json.loads(capsys.readouterr().out)
    assert sel["coverage"] >= 0.99 and (path / "selection.json").is_file()
    masks, held = tmp_path / "masks", tmp_path / "held"
    for fi in sel["frames"]:
        write_mask(masks / f"{scene.frames[fi].stem}.png", truth_mask(scene.frames[fi]))
    others = [i for i in range(len(scene.frames)) if i not in sel["frames"]]
    for fi in others:
        write_mask(held / f"{scene.frames[fi].stem}.png", truth_mask(scene.frames[fi]))
    assert main(["lift", str(path), "--masks", str(masks), "--json"]) == 0
    lift = json.loads(capsys.readouterr().out)
    assert lift["updated"] == len(sel["frames"]) and lift["labels"]["points"] == scene.n_points
    np.save(tmp_path / "truth.npy", truth)
    assert main(["eval-points", str(path), "--truth", str(tmp_path / "truth.npy"), "--json"]) == 0
    ev = json.loads(capsys.readouterr().out)
    assert ev["accuracy"] >= 0.97
    assert main(["agreement", str(path), "--masks", str(held), "--out", str(tmp_path / "dis"),
                 "--json"]) == 0
    ag = json.loads(capsys.readouterr().out)
    assert ag["held_out"]["frames"] == len(others) and ag["agreement"] >= 0.95
    assert len(list((tmp_path / "dis").glob("*.disagreement.png"))) == len(others)
    assert main(["export-points", str(path), str(tmp_path / "o.laz"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["points"] == scene.n_points
    # a mask for an unknown frame: error naming the file, votes unchanged
    before = np.asarray(VoteStore.open(path).votes).copy()
    write_mask(masks / "no_such_frame.png", truth_mask(scene.frames[0]))
    assert main(["lift", str(path), "--masks", str(masks)]) == 2
    assert "no_such_frame.png" in capsys.readouterr().err
    assert np.array_equal(np.asarray(VoteStore.open(path).votes), before)


# ---- the synthetic tiny scene (generator + importer, exact truth) -------------------------
@pytest.fixture(scope="module")
def tiny(tmp_path_factory, synth_tiny):
    from occufly.io.importer import import_scene

    root = tmp_path_factory.mktemp("tiny")
    syn = synth_tiny  # generate(preset="tiny", seed=0), once per run (read-only)
    scene = import_scene(syn, root / "ws")
    truth = np.load(syn / "truth" / "point_labels.npy")
    masks = {i: read_mask(syn / "truth" / "masks" / f"{f.stem}.png", f, scene.taxonomy)
             for i, f in enumerate(scene.frames)}
    return root / "ws", Scene.load(root / "ws"), truth, masks


def test_tiny_scene_lifting_quality(tiny):
    from occufly.render import agreement, merge_agreements, render_labels

    path, scene, truth, masks = tiny
    sel = select_frames(scene, mode="greedy", target_coverage=0.99)
    assert sel.coverage >= 0.99 and sel.ratio < 0.6
    st = VoteStore.open(path, scene)
    for fi in sel.frames:
        st.set_mask(fi, masks[fi], version="truth")
    direct = st.direct_labels()
    voted = direct > 0
    assert voted.mean() >= 0.98
    assert (direct[voted] == truth[voted]).mean() >= 0.99
    res = st.fill_and_denoise()
    ev = evaluate_points(res.labels, truth, scene.taxonomy, res.origin)
    assert ev["accuracy"] >= 0.97, ev["by_origin"]
    held = [i for i in range(len(scene.frames)) if i not in set(sel.frames)][::3]
    ag = merge_agreements([agreement(masks[i], render_labels(scene, res.labels, i)[0],
                                     scene.taxonomy) for i in held])
    assert ag["agreement"] >= 0.88 and ag["coverage"] >= 0.8
    # masks swapped between frames lift to measurably wrong labels
    st2 = VoteStore.open(path, scene)
    frames = list(sel.frames)
    for fi, other in zip(frames, frames[1:] + frames[:1], strict=True):
        m = masks[other]
        st2.set_mask(fi, m if m.shape == masks[fi].shape else masks[fi][::-1])
    bad = evaluate_points(st2.fill_and_denoise().labels, truth, scene.taxonomy)
    assert bad["accuracy"] < ev["accuracy"] - 0.2


# ---- the public state API (what the lifting service uses) --------------------------------
def test_public_state_api_snapshot_resume_read_only(ws):
    from occufly.errors import WorkspaceError
    from occufly.lifting import VoteSnapshot, fill_snapshot

    path, scene, truth = ws
    with pytest.raises(WorkspaceError, match="no lifting state"):
        VoteStore.open(path, scene, read_only=True)
    st = VoteStore.open(path, scene)
    for fi in (1, 4, 9):
        st.apply_frame(fi, truth_mask(scene.frames[fi]), version=f"v{fi}")
    assert st.version_of(4) == "v4" and st.version_of(2) is None
    snap = st.snapshot()
    assert isinstance(snap, VoteSnapshot) and snap.versions == {1: "v1", 4: "v4", 9: "v9"}
    assert np.array_equal(snap.direct, st.direct_labels())
    # the snapshot is a copy: later updates do not change it, and a fill of it ignores them
    st.apply_frame(12, np.full_like(truth_mask(scene.frames[12]), ROAD), version="v12")
    assert not np.array_equal(snap.direct, st.direct_labels())
    res = st.fill_and_denoise(snapshot=snap)
    assert res.stats["versions"] == {"1": "v1", "4": "v4", "9": "v9"}
    assert np.array_equal(np.asarray(st.labels().labels), res.labels)
    alone = fill_snapshot(scene, snap, params=LiftParams())
    assert np.array_equal(alone.labels, res.labels)
    assert np.array_equal(alone.confidence, res.confidence)
    st.remove_frame(12)
    assert 12 not in st.included_versions()
    assert np.array_equal(st.direct_labels(), snap.direct)
    votes = np.asarray(st.votes).copy()
    st.close()
    # a worker restarted on the same workspace resumes with the same counts and versions
    again = VoteStore.open(path, scene)
    assert np.array_equal(np.asarray(again.votes), votes)
    assert again.included_versions() == {1: "v1", 4: "v4", 9: "v9"}
    # a reader never writes: read-only counts, refused updates, refused dirty states
    ro = VoteStore.open(path, scene, read_only=True)
    assert np.array_equal(ro.direct_labels(), snap.direct)
    with pytest.raises(WorkspaceError, match="read-only"):
        ro.apply_frame(2, truth_mask(scene.frames[2]))
    with pytest.raises(WorkspaceError, match="read-only"):
        ro.fill_and_denoise()
    assert not ro.votes.flags.writeable
    again._write_state(dirty=True)
    with pytest.raises(WorkspaceError, match="interrupted"):
        VoteStore.open(path, scene, read_only=True)


def test_boundary_vote_weighting(ws):
    from occufly.errors import WorkspaceError
    from occufly.lifting import boundary_weights

    m = np.full((20, 30), GRASS, np.uint8)
    m[:, 15:] = ROAD
    w = boundary_weights(m, px=3)
    assert w[0, 14] == 1 and w[0, 15] == 1  # on the class change
    assert w[0, 12] == 1 and w[0, 11] == 2  # chessboard distance 2 -> 1, 3 -> 2
    assert w[0, 9] == 2 and w[0, 8] == 3 and w[0, 0] == 3
    assert (boundary_weights(np.full((4, 4), GRASS, np.uint8)) == 3).all()
    path, scene, truth = ws
    st = VoteStore.open(path, scene, vote_weighting="boundary")
    mask = truth_mask(scene.frames[5])
    stats = st.apply_frame(5, mask, version="v1")
    pids, raw = _expected_votes(scene, 5, mask)
    s = scene.frames[5].camera.width // mask.shape[1]
    _, uv, _ = scene.visibility.frame(5)
    uv = np.asarray(uv)
    keep = np.isin(mask[(uv[:, 1] // s).astype(int), (uv[:, 0] // s).astype(int)], [0, 255],
                   invert=True)
    wexp = boundary_weights(mask)[(uv[keep, 1] // s).astype(int), (uv[keep, 0] // s).astype(int)]
    assert int(np.asarray(st.votes).sum()) == int(wexp.sum()) == stats["votes_added"]
    assert int(wexp.sum()) > len(pids) and (wexp == 1).any()
    # the winner is the mask's class either way (one view)
    assert np.array_equal(st.labels_of_points(pids), raw)
    st.close()
    again = VoteStore.open(path, scene)
    assert again.vote_weighting == "boundary"
    again._write_state(dirty=True)
    rebuilt = VoteStore.open(path, scene)  # recount from the per-frame files, with weights
    assert int(np.asarray(rebuilt.votes).sum()) == int(wexp.sum())
    with pytest.raises(WorkspaceError, match="'boundary' votes"):
        VoteStore.open(path, scene, vote_weighting="plain")
    rebuilt.remove_frame(5)
    assert int(np.asarray(rebuilt.votes).sum()) == 0


def test_ties_are_left_to_the_fill():
    # a line of road points with one point tied road:grass (1:1); grass comes first in the
    # tie order, but every neighbour is road -- the fill decides, not the table
    xyz = np.column_stack([np.arange(50) * 0.1, np.zeros(50), np.zeros(50)]).astype(np.float32)
    direct = np.full(50, ROAD, np.uint8)
    margin = np.ones(50, np.float32)
    top = np.full(50, 3, np.uint16)
    direct[25], margin[25], top[25] = GRASS, 0.0, 1
    on = fill_and_denoise(xyz, direct, TAX, params=LiftParams(method="exact"), vote_margin=margin,
                          vote_top=top)
    off = fill_and_denoise(xyz, direct, TAX, params=LiftParams(method="exact", tie_fill=False,
                                                               denoise_keep_share=0.0),
                           vote_margin=margin, vote_top=top)
    assert on.labels[25] == ROAD and on.origin[25] == ORIGIN_FILLED
    assert off.labels[25] == GRASS  # tie order kept, and the keep rule keeps it
    for method in ("voxel", "exact"):
        r = fill_and_denoise(xyz, direct, TAX, params=LiftParams(method=method),
                             vote_margin=margin, vote_top=top)
        assert r.labels[25] == ROAD


# ---- robust decision (imperfect annotators) and the incremental vote update ---------------
def test_robust_decision_survives_degraded_masks(tiny):
    """Degraded masks (occufly.synthetic.degrade defaults) of the greedy frames: the robust
    decision (annotator model + point classifier, the default) lifts them far better than
    the plain vote majority did (measured: seed 0 0.759 -> 0.933, seed 1 0.825 -> 0.952),
    and stays close to the exact-mask figure with exact masks; tiny objects reach an IoU
    floor the decision before the neighbourhood prior did not."""
    from occufly.lifting import RobustParams
    from occufly.synthetic.degrade import degrade_masks

    path, scene, truth, masks = tiny
    sel = select_frames(scene, mode="greedy", target_coverage=0.99)
    exact = {fi: masks[fi] for fi in sel.frames}
    # the decision before the tiny-object work: scene-wide prior only, unanimous training
    # points only, the fill's two-view confirmation
    before = RobustParams(local_voxel=0, min_strong=0, confirm_views=None)
    acc, tiny_iou = {}, {}
    for name, mm in (("exact", exact), ("deg0", degrade_masks(exact, scene.taxonomy, seed=0)),
                     ("deg1", degrade_masks(exact, scene.taxonomy, seed=1))):
        st = VoteStore.open(path, scene)
        for fi in list(st.included_versions()):
            st.remove_frame(fi)
        for fi in sel.frames:
            st.set_mask(fi, mm[fi], version=name)
        for mode, params in (("plain", LiftParams(robust=False)), ("robust", LiftParams()),
                             ("before", LiftParams(robust_params=before))):
            res = st.fill_and_denoise(params=params, write=False)
            ev = evaluate_points(res.labels, truth, scene.taxonomy)
            acc[name, mode] = ev["accuracy"]
            tiny_iou[name, mode] = np.mean([ev["per_class"][c]["iou"] if c in ev["per_class"]
                                            else 0.0 for c in ("person", "bicycle",
                                                               "ground_obstacle")])
            if mode != "plain":
                assert res.stats["robust"] and res.stats["robust_points_changed"] > 0
        st.close()
    import shutil

    shutil.rmtree(path / "lifting")  # the module's tiny workspace as the other tests found it
    assert acc["exact", "robust"] >= 0.98
    for name in ("deg0", "deg1"):
        assert acc[name, "robust"] >= 0.92, acc
        assert acc[name, "robust"] >= acc[name, "plain"] + 0.01, acc
        # tiny objects (about 10 px blobs, shifted off themselves and skipped in half the
        # views): the neighbourhood prior, the majority training and the confirmation of the
        # robust decision keep them (measured: mean IoU of person, bicycle and ground
        # obstacle 0.03 / 0.08 before, 0.27 / 0.27 now)
        assert tiny_iou[name, "robust"] >= 0.2, tiny_iou
        assert tiny_iou[name, "before"] < 0.15, tiny_iou


def test_robust_features_cached_and_read_only_never_writes(ws):
    from occufly.lifting.robust import FEATURE_NAMES, cached_features, point_features
    from occufly.workspace import Workspace

    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    st.set_mask(0, truth_mask(scene.frames[0]), version="a")
    st.set_mask(5, truth_mask(scene.frames[5]), version="b")
    d = Workspace(path).lifting_dir
    st.fill_and_denoise(write=False)  # write=False: no feature cache either
    assert not (d / "features.npy").exists()
    res = st.fill_and_denoise()
    assert res.stats["robust"] and (d / "features.npy").is_file()
    f = cached_features(path, scene.xyz, scene.rgb)
    assert f.shape == (scene.n_points, len(FEATURE_NAMES)) and f.dtype == np.float16
    assert np.array_equal(np.asarray(f), point_features(scene.xyz, scene.rgb))
    assert np.isfinite(np.asarray(f, np.float32)).all()
    # a cloud that changed (same count, other coordinates) is not served the stale cache
    moved = np.asarray(scene.xyz) + np.float32(1.5)
    assert np.array_equal(cached_features(path, moved, scene.rgb, read_only=True),
                          point_features(moved, scene.rgb))
    # the plain decision is still there, and unvoted points never get a label from it
    plain = st.fill_and_denoise(params=LiftParams(robust=False), write=False)
    assert not plain.stats["robust"]
    snap = st.snapshot()
    assert snap.second_col is not None and snap.second_col.dtype == np.int8
    voted = snap.direct > 0
    assert (snap.second[~voted] == 0).all()


def test_robust_annotator_model_learns_asymmetric_confusion():
    from occufly.lifting.robust import RobustParams, estimate_confusion

    # true classes 0 (common) and 1 (rare); views of class 1 vote 0 a third of the time,
    # views of class 0 never vote 1 -- a 1:1 tie on a point is then evidence for class 1
    rng = np.random.default_rng(0)
    C, n = 3, 60_000
    t = (rng.random(n) < 0.1).astype(np.int64)
    votes = np.zeros((n, C), np.uint16)
    for _ in range(3):
        v = np.where((t == 1) & (rng.random(n) < 1 / 3), 0, t)
        votes[np.arange(n), v] += 1
    c1 = np.argmax(votes, axis=1)
    n1 = votes[np.arange(n), c1]
    rest = votes.copy()
    rest[np.arange(n), c1] = 0
    c2 = np.where(rest.max(axis=1) > 0, np.argmax(rest, axis=1), -1)
    n2 = rest.max(axis=1)
    pi, prior = estimate_confusion(c1, n1, c2, n2, C, RobustParams(diag_prior=1.0))
    assert pi[1, 0] == pytest.approx(1 / 3, abs=0.05)
    assert pi[0, 1] < 0.01
    assert prior[1] == pytest.approx(0.1, abs=0.02)


def test_packed_winner_equals_tie_order_majority():
    from occufly.lifting.classes import ClassColumns

    cls = ClassColumns(TAX)
    rng = np.random.default_rng(3)
    for hi, dt in ((3, np.uint16), (4000, np.uint16), (70_000, np.uint32)):
        c = rng.integers(0, hi, (5000, cls.C)).astype(dt)
        c[rng.random(c.shape) < 0.8] = 0
        c[:50] = 0
        c[50:100, :] = c[50:100, :1]  # all columns equal: the tie order decides
        assert np.array_equal(cls.winner(c), cls.majority(c)[0])


def test_incremental_vote_update_matches_a_recount(ws):
    """Random first saves, replacements (also with the same mask), removals: the counts equal
    a recount of the per-frame files and points_changed the direct labels that changed."""
    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    rng = np.random.default_rng(5)
    ids = TAX.ids
    for step in range(14):
        fi = int(rng.integers(0, 6))
        h, w = scene.frames[fi].camera.height, scene.frames[fi].camera.width
        before = st.direct_labels()
        if step % 5 == 4:
            r = st.remove_frame(fi)
        else:
            mask = ids[rng.integers(0, 3, (h // 8 + 1, w // 8 + 1))].repeat(8, 0).repeat(8, 1)
            mask = np.ascontiguousarray(mask[:h, :w]).astype(np.uint8)
            mask[rng.random((h, w)) < 0.1] = 0
            r = st.apply_frame(fi, mask, version=str(step))
            if step % 3 == 0:  # the same mask again: nothing changes
                again = st.apply_frame(fi, mask, version=str(step))
                assert again["points_changed"] == 0
                assert again["points_touched"] == r["votes_added"]
        after = st.direct_labels()
        assert r["points_changed"] == int(np.count_nonzero(before != after))
        counts = np.asarray(st.votes).copy()
        st.rebuild()
        assert np.array_equal(np.asarray(st.votes), counts)


def test_robust_neighbourhood_votes_are_block_sums():
    """local_votes: each voted point's voxel and the two leading vote classes summed over
    the 3x3x3 voxels around it, compared with a brute-force sum over the points."""
    from occufly.lifting.robust import local_votes

    rng = np.random.default_rng(7)
    n, C, e = 3000, 5, 0.5
    xyz = rng.uniform(0, 4, (n, 3)).astype(np.float32)
    c1 = rng.integers(-1, C, n).astype(np.int16)
    n1 = np.where(c1 >= 0, rng.integers(1, 4, n), 0).astype(np.uint16)
    c2 = np.where((c1 >= 0) & (rng.random(n) < 0.4), (c1 + 1) % C, -1).astype(np.int8)
    n2 = np.where(c2 >= 0, 1, 0).astype(np.uint16)
    voted = np.flatnonzero(n1 > 0)
    vox, block = local_votes(xyz, voted, c1, n1, c2, n2, C, e)
    q = np.floor((xyz[voted] - xyz[voted].min(axis=0)) / e).astype(np.int64)
    for i in rng.choice(len(voted), 60, replace=False):
        near = np.flatnonzero(np.abs(q - q[i]).max(axis=1) <= 1)
        want = np.zeros(C)
        for j in voted[near]:
            want[c1[j]] += n1[j]
            if c2[j] >= 0:
                want[c2[j]] += n2[j]
        assert np.allclose(block[vox[i]], want)


@pytest.mark.parametrize("case", ["random", "duplicates", "few"])
def test_block_knn_kernel_counts_the_exact_k_nearest(case):
    """The compiled boundary kernel against a plain numpy brute force: per point, the class
    counts of its k nearest (ties at the k-th included) within the radius, and whether the
    block was full -- on a random cloud, on coincident points (all distances 0) and on a
    block with fewer than k candidates."""
    from occufly.lifting.blockknn import block_votes
    from occufly.lifting.knn import VoxelGrid

    rng = np.random.default_rng(7)
    n, k, radius, C = {"random": (3000, 40, 1.5, 5), "duplicates": (300, 50, 1.0, 3),
                       "few": (30, 50, 2.0, 4)}[case]
    xyz = (rng.random((n, 3)) * 6).astype(np.float32)
    if case == "duplicates":
        xyz[:] = xyz[0]
    cols = rng.integers(0, C, n).astype(np.int64)
    grid = VoxelGrid(xyz, 1.0, pad=2)
    vox = grid.inverse
    order = np.argsort(vox, kind="stable").astype(np.int64)
    vs = vox[order]
    starts = np.searchsorted(vs, np.arange(grid.n_voxels))
    ends = np.searchsorted(vs, np.arange(grid.n_voxels), side="right")
    todo = np.arange(grid.n_voxels, dtype=np.int64)
    offs = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)]
    nb = np.ascontiguousarray(np.stack([grid.neighbour(todo, *o) for o in offs], axis=1))
    only = rng.random(n) < 0.7
    ro = xyz.view()
    ro.flags.writeable = False
    q, votes, kth, full = block_votes(ro, cols, order, starts, ends, todo, nb, only, True, k,
                                      radius * radius, C)
    assert sorted(q.tolist()) == np.flatnonzero(only).tolist()
    for r, p in enumerate(q):
        blk = np.isin(vox, nb[np.searchsorted(todo, vox[p])])
        cand = np.flatnonzero(blk)
        d2 = ((xyz[cand].astype(np.float64) - xyz[p]) ** 2).sum(1)
        kk = min(k, len(cand))
        want_kth = np.sort(d2)[kk - 1]
        sel = d2 <= min(want_kth, radius * radius)
        assert kth[r] == want_kth
        assert full[r] == (kk == k)
        assert np.array_equal(votes[r], np.bincount(cols[cand[sel]], minlength=C))


@pytest.mark.parametrize("seed", [0, 1])
def test_fill_is_the_exact_knn_where_the_cloud_is_sparse(seed):
    """The fill's k-d tree holds only the voted points near the points to fill; in a sparse
    cloud (fine voxels, most of them empty) it must still hold every voted point within the
    fill radius: the fill equals a k-NN vote against all voted points. (The near set was once
    a dilation through occupied voxels only; here it kept a fraction of the neighbours.)"""
    from scipy.spatial import cKDTree

    from occufly.lifting.classes import ClassColumns
    from occufly.lifting.knn import VoxelGrid, _fill, knn_vote

    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 40, (3000, 3)).astype(np.float32)
    xyz[:, 2] *= 0.2
    cls = ClassColumns(TAX)
    direct = np.where(rng.random(len(xyz)) < 0.5, rng.choice([ROAD, BUILDING, GRASS], len(xyz)), 0)
    dcols = cls.col_of[direct.astype(np.uint8)].astype(np.int64)
    p = LiftParams(fill_k=20, fill_radius=3.0)
    edge = 0.4
    grid = VoxelGrid(xyz, edge, pad=int(np.ceil(p.fill_radius / edge)) + 1)
    filled, agree, dist = _fill(xyz, dcols, grid, p, cls, {}, lambda f, m: None)
    lab, un = np.flatnonzero(dcols >= 0), np.flatnonzero(dcols < 0)
    near = np.empty(len(un), np.float32)
    c, s = knn_vote(cKDTree(xyz[lab]), dcols[lab], xyz[un], p.fill_k, p.fill_radius, cls,
                    weighted=True, nearest=near)
    assert (c >= 0).mean() > 0.9
    assert np.array_equal(filled[un], c)
    assert np.array_equal(agree[un], s) and np.array_equal(dist[un], near)


def test_snapshot_without_the_lock_equals_the_locked_one(ws, monkeypatch):
    """A fill's snapshot taken with the update lock held only at both ends (the pass over
    the counts without it): updates that land meanwhile -- before the pass, during it (a
    thread applying masks while the pass reads), after it, a removal, a rebuild -- are
    recomputed at the finish, so the snapshot equals the one taken under the lock then."""
    import threading

    path, scene, _ = ws
    st = VoteStore.open(path, scene)
    rng = np.random.default_rng(9)

    def mask(fi):
        h, w = scene.frames[fi].camera.height, scene.frames[fi].camera.width
        m = TAX.ids[rng.integers(0, 4, (h // 6 + 1, w // 6 + 1))].repeat(6, 0).repeat(6, 1)
        return np.ascontiguousarray(m[:h, :w]).astype(np.uint8)

    for fi in range(4):
        st.apply_frame(fi, mask(fi), version=f"a{fi}")

    def same(a, b):
        assert a.versions == b.versions
        for f in ("direct", "margin", "top", "second_col", "second"):
            x, y = getattr(a, f), getattr(b, f)
            assert x.dtype == y.dtype and np.array_equal(x.view(np.uint8), y.view(np.uint8)), f

    lock = threading.Lock()
    # updates between the begin and the pass, and between the pass and the finish
    with lock:
        st.snapshot_begin()
    st.apply_frame(1, mask(1), version="b1")
    rows = st.snapshot_rows()
    st.remove_frame(2)
    st.apply_frame(5, mask(5), version="b5")
    with lock:
        got = st.snapshot_finish(rows)
    same(got, st.snapshot())
    assert 2 not in got.versions and got.versions[5] == "b5"
    # a thread applying masks while the pass reads the counts (slowed so that they overlap)
    orig = VoteStore._direct
    started = threading.Event()

    def slow_direct(self, *a, **k):
        started.set()
        time.sleep(0.3)
        return orig(self, *a, **k)

    monkeypatch.setattr(VoteStore, "_direct", slow_direct)
    with lock:
        st.snapshot_begin()

    def writer():
        started.wait(5)
        for fi in (0, 3, 4):
            with lock:
                st.apply_frame(fi, mask(fi), version=f"c{fi}")

    t = threading.Thread(target=writer)
    t.start()
    rows = st.snapshot_rows()
    t.join()
    with lock:
        got = st.snapshot_finish(rows)
    monkeypatch.setattr(VoteStore, "_direct", orig)
    same(got, st.snapshot())
    assert got.versions[4] == "c4"
    # a rebuild meanwhile rewrites every row
    with lock:
        st.snapshot_begin()
    rows = st.snapshot_rows()
    st.votes[:5] = 0  # damage, then repair by a recount from the frame files
    st.rebuild()
    with lock:
        same(st.snapshot_finish(rows), st.snapshot())
    with pytest.raises(RuntimeError, match="snapshot_begin"):
        st.snapshot_finish(rows)
