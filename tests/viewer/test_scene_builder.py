"""What the viewer sends: node names, counts per class, colours per mode, LOD bounds, geometry."""

from __future__ import annotations

import numpy as np
import pytest
from viewer_fixtures import COUNTS, ORIGIN, build_tiny

from app.viewer import scene_builder as sb
from app.viewer.refresh import changed_classes
from occufly.errors import WorkspaceError
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()


def names_counts(nodes):
    return {nd.name: len(nd.point_ids) for nd in nodes}


def test_one_node_per_class_with_exact_counts(tiny):
    data = sb.ViewerData.load(tiny.ws)
    nodes = sb.build_point_nodes(data, mode="semantic")
    assert names_counts(nodes) == {
        "/points/unlabelled": 40, "/points/grass": 600, "/points/building": 300,
        "/points/person": 5, "/points/vehicle": 55,
    }
    for nd in nodes:
        assert np.all(tiny.labels[nd.point_ids] == nd.class_id)
        assert nd.xyz.dtype == np.float32 and nd.colors.dtype == np.uint8
        np.testing.assert_array_equal(nd.xyz, tiny.scene.xyz[nd.point_ids])


def test_rgb_only_fallback_without_lifting(tmp_path):
    t = build_tiny(tmp_path / "w")
    for f in ("labels", "confidence", "origin"):
        (t.ws / "lifting" / f"{f}.npy").unlink()
    data = sb.ViewerData.load(t.ws)
    assert data.labels is None
    nodes = sb.build_point_nodes(data, mode="semantic")  # semantic falls back to RGB
    assert names_counts(nodes) == {"/points/unlabelled": sum(COUNTS.values())}
    np.testing.assert_array_equal(nodes[0].colors, t.scene.rgb[nodes[0].point_ids])


def test_wrong_label_length_names_the_file(tiny):
    np.save(tiny.ws / "lifting" / "labels.npy", np.zeros(7, np.uint8))
    with pytest.raises(WorkspaceError, match=r"lifting/labels\.npy.*\(1000,\)"):
        sb.ViewerData.load(tiny.ws)


def test_colours_per_mode(tiny):
    data = sb.ViewerData.load(tiny.ws)
    idx = np.arange(tiny.scene.n_points)
    np.testing.assert_array_equal(sb.point_colours(data, "rgb", idx), tiny.scene.rgb)
    sem = sb.point_colours(data, "semantic", idx)
    assert tuple(sem[np.flatnonzero(tiny.labels == 6)[0]]) == (0, 255, 0)  # grass
    assert tuple(sem[np.flatnonzero(tiny.labels == 16)[0]]) == (255, 0, 0)  # building
    assert tuple(sem[np.flatnonzero(tiny.labels == 0)[0]]) == (0, 0, 0)  # unlabelled
    conf = sb.point_colours(data, "confidence", idx)  # confidence is linspace(0, 1)
    assert tuple(conf[0]) == (120, 0, 40) and tuple(conf[-1]) == (255, 230, 0)
    assert np.all(np.diff(conf[:, 1].astype(int)) >= 0)  # green grows with confidence
    org = sb.point_colours(data, "origin", idx)  # origin is arange % 4
    for code in range(4):
        assert np.all(org[code::4] == sb.ORIGIN_COLOURS[code])


def test_disagreement_colours_with_direct_votes(tiny):
    data = sb.ViewerData.load(tiny.ws)
    direct = tiny.labels.copy()
    direct[:10] = 0  # no vote
    flip = np.arange(10, 20)
    direct[flip] = np.where(tiny.labels[flip] == 6, 16, 6)  # vote differs from final label
    data.direct = direct
    col = sb.point_colours(data, "disagreement", np.arange(tiny.scene.n_points))
    assert np.all(col[:10] == sb.NO_VOTE_COLOUR)
    assert np.all(col[10:20] == sb.DISAGREE_COLOUR)
    rest = tiny.labels[20:] != 0  # unlabelled points have no vote either
    assert np.all(col[20:][rest] == sb.AGREE_COLOUR)
    assert np.all(col[20:][~rest] == sb.NO_VOTE_COLOUR)


def test_class_quotas_keep_rare_classes_and_hit_the_budget():
    counts = np.zeros(256, np.int64)
    counts[[6, 16, 11, 13]] = [1_000_000, 300_000, 5, 2_000]
    q = sb.class_quotas(counts, 100_000)
    assert q.sum() == 100_000 and np.all(q <= counts)
    assert q[11] == 5 and q[13] == 2_000  # rare classes whole
    assert q[6] > q[16] > q[13]  # big classes keep their relative weight
    # proportional above the floor: grass/building ratio close to 1e6/3e5
    assert abs((q[6] - 6250) / (q[16] - 6250) - (1e6 - 6250) / (3e5 - 6250)) < 0.01
    np.testing.assert_array_equal(sb.class_quotas(counts, 10**7), counts)


@pytest.mark.parametrize("budget", [1, 7, 100, 999, 1000])
def test_stratified_subsample_bounds(tiny, budget):
    n = tiny.scene.n_points
    idx = sb.stratified_subsample(tiny.labels, n, budget, seed=1)
    assert len(idx) == min(budget, n)
    assert len(np.unique(idx)) == len(idx) and np.all(np.diff(idx) > 0)
    assert idx.min() >= 0 and idx.max() < n
    np.testing.assert_array_equal(idx, sb.stratified_subsample(tiny.labels, n, budget, seed=1))
    if budget >= 100:  # the 5 persons survive any reasonable LOD
        assert (tiny.labels[idx] == 11).sum() == 5


def test_lod_nodes_sum_to_budget(tiny):
    data = sb.ViewerData.load(tiny.ws)
    nodes = sb.build_point_nodes(data, max_points=200)
    counts = names_counts(nodes)
    assert sum(counts.values()) == 200
    assert counts["/points/person"] == 5
    assert set(counts) == {"/points/unlabelled", "/points/grass", "/points/building",
                           "/points/person", "/points/vehicle"}


def test_sent_to_viser_in_float32(tiny):
    import viser

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        data = sb.ViewerData.load(tiny.ws)
        nodes = sb.build_point_nodes(data)
        handles = sb.send_point_nodes(server.scene, nodes, point_size=0.1)
        h = handles[6]
        assert h.precision == "float32" and h.points.dtype == np.float32
        ids = nodes[[nd.class_id for nd in nodes].index(6)].point_ids
        # local x is ~1000 m: float16 would be off by up to 0.25 m, float32 keeps < 1 mm
        np.testing.assert_allclose(h.points, tiny.scene.xyz[ids], atol=1e-3)
        assert np.abs(h.points.astype(np.float16).astype(np.float32) - tiny.scene.xyz[ids]).max() > 0.05
        assert server.scene.get_handle_by_name("/points/person") is not None
    finally:
        server.stop()


def _look_down_wxyz():
    # camera axes in world: x right = +x, y down = -y, z forward = -z
    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])
    return sb.matrix_to_quat(R)


def test_points_in_screen_rect_analytic():
    wxyz = _look_down_wxyz()
    fov, aspect = np.deg2rad(90.0), 2.0  # tan(45) = 1: half-height 10 m and half-width 20 m at 10 m
    xyz = np.array([[0, 0, 0], [19, 0, 0], [-19, 9, 0], [21, 0, 0], [0, 11, 0], [0, 0, 20]], np.float32)
    inside = sb.points_in_screen_rect(xyz, np.array([0, 0, 10.0]), wxyz, fov, aspect, (0, 0), (1, 1))
    assert inside.tolist() == [True, True, True, False, False, False]  # last is behind the camera
    # (u, v) of (10, 5, 0): u = .5 + 10/20/2 = .75, v = .5 - 5/10/2 = .25 (world +y is image up)
    one = np.array([[10, 5, 0]], np.float32)
    assert sb.points_in_screen_rect(one, np.array([0, 0, 10.0]), wxyz, fov, aspect, (.74, .24), (.76, .26))[0]
    assert not sb.points_in_screen_rect(one, np.array([0, 0, 10.0]), wxyz, fov, aspect, (.76, .24), (.8, .26))[0]


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    for R in Rotation.random(5, random_state=1).as_matrix():
        np.testing.assert_allclose(sb.quat_to_matrix(sb.matrix_to_quat(R)), R, atol=1e-12)
    assert rng is not None


def test_surface_mask_of_a_cube():
    occ = np.zeros((5, 5, 5), bool)
    occ[1:4, 1:4, 1:4] = True
    s = sb.surface_mask(occ)
    assert s.sum() == 26 and not s[2, 2, 2]


def test_scene_grid_nodes_in_local_coordinates(tiny, tiny_grid):
    nodes = sb.scene_grid_nodes(tiny_grid, ORIGIN, TAX)
    by = {nd.name: nd for nd in nodes}
    assert set(by) == {"/grid/scene/building", "/grid/scene/person"}
    assert len(by["/grid/scene/building"].centers) == 26  # surface only
    np.testing.assert_allclose(by["/grid/scene/person"].centers, [[10.5, 20.5, 0.5]])
    assert by["/grid/scene/building"].color == (255, 0, 0)
    all_nodes = sb.scene_grid_nodes(tiny_grid, ORIGIN, TAX, surface_only=False)
    assert len({nd.name: nd for nd in all_nodes}["/grid/scene/building"].centers) == 27


def test_camera_grid_nodes_masks_and_pose():
    X, Y, Z = 8, 6, 4
    labels = np.zeros((X, Y, Z), np.uint8)
    invalid = np.zeros((X, Y, Z), bool)
    occluded = np.zeros((X, Y, Z), bool)
    labels[4, 3, 0] = 13  # centre voxel, first layer: camera coords (.5, .5, .5) * r
    labels[4, 3, 2] = 13
    occluded[4, 3, 2] = True  # behind the first
    labels[0, 0, 0] = 255
    invalid[0, 0, 0] = True
    surface = labels == 13
    T = np.eye(4)
    T[:3, 3] = [-100.0, 0.0, 0.0]  # camera centre at world x = +100
    nodes = sb.camera_grid_nodes(labels, invalid, occluded, surface, T, 0.5, TAX)
    by = {nd.name: nd for nd in nodes}
    assert set(by) == {"/grid/frame/vehicle", "/grid/frame/_occluded", "/grid/frame/_invalid"}
    np.testing.assert_allclose(by["/grid/frame/vehicle"].centers, [[100.25, 0.25, 0.25]])
    np.testing.assert_allclose(by["/grid/frame/_occluded"].centers, [[100.25, 0.25, 1.25]])
    np.testing.assert_allclose(by["/grid/frame/_invalid"].centers, [[98.25, -1.25, 0.25]])


def test_frusta_pose_fov_and_state_colours(tiny):
    states = {0: "accepted", 1: sb.viewer_state(True, "unassigned")}
    nodes = sb.frustum_nodes(tiny.scene, states)
    assert [nd.name for nd in nodes] == ["/cameras/f0", "/cameras/f1"]
    np.testing.assert_allclose(nodes[0].position, [990.0, 0.0, 40.0], atol=1e-9)
    assert nodes[0].fov == pytest.approx(2 * np.arctan(150 / 300))
    assert nodes[0].aspect == pytest.approx(4 / 3)
    assert nodes[0].color == (0, 180, 60) and nodes[1].color == (40, 120, 255)
    R = sb.quat_to_matrix(nodes[0].wxyz)  # camera z axis points down
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-9)
    assert sb.viewer_state(True, "submitted") == "annotated"
    assert sb.viewer_state(False, "unassigned") == "not_selected"
    assert sb.viewer_state(True, "rejected") == "rejected"
    with pytest.raises(ValueError, match="frame state"):
        sb.frustum_nodes(tiny.scene, {0: "bogus"})


def test_show_cameras_filter_keeps_the_focused_frame(tiny):
    nodes = sb.frustum_nodes(tiny.scene, {0: "accepted"})
    assert [nd.frame_index for nd in sb.filter_frustum_nodes(nodes, "all")] == [0, 1]
    assert [nd.frame_index for nd in sb.filter_frustum_nodes(nodes, "selected and annotated")] == [0]
    assert sb.filter_frustum_nodes(nodes, "none") == []
    # "Open in 3D" on a frame the filter hides still shows (and highlights) it
    assert [nd.frame_index for nd in sb.filter_frustum_nodes(nodes, "none", {1})] == [1]
    assert [nd.frame_index for nd in sb.filter_frustum_nodes(nodes, "selected and annotated", {1})] == [0, 1]
    with pytest.raises(ValueError, match="camera filter"):
        sb.filter_frustum_nodes(nodes, "some")
    assert sb.default_camera_filter(240) == "all"
    assert sb.default_camera_filter(2100) == "selected and annotated"


def test_changed_classes_detects_relabelled_points(tiny):
    old = sb.ViewerData.load(tiny.ws)
    labels = tiny.labels.copy()
    g = np.flatnonzero(labels == 6)[:3]
    labels[g] = 13  # three grass points become vehicle
    new = sb.ViewerData(old.scene, labels, old.confidence, old.origin, old.direct)
    assert changed_classes(old, new) == {6, 13}
    conf = np.array(old.confidence)
    conf[np.flatnonzero(labels == 11)[0]] = 0.0
    assert changed_classes(old, sb.ViewerData(old.scene, labels, conf, old.origin, old.direct)) == {6, 11, 13}
    assert changed_classes(old, sb.ViewerData(old.scene, None)) is None


def test_direct_votes_read_only_from_lifting_state(tiny):
    n, ids = tiny.scene.n_points, list(TAX.ids)
    votes = np.zeros((n, len(ids)), np.uint16)
    votes[0, ids.index(16)] = 3  # building wins 3:1
    votes[0, ids.index(6)] = 1
    votes[1, ids.index(13)] = 2
    np.save(tiny.ws / "lifting" / "votes.npy", votes)
    before = sorted(p.name for p in (tiny.ws / "lifting").iterdir())
    data = sb.ViewerData.load(tiny.ws)
    assert data.direct[0] == 16 and data.direct[1] == 13 and np.all(data.direct[2:] == 0)
    assert sorted(p.name for p in (tiny.ws / "lifting").iterdir()) == before  # nothing written
    np.save(tiny.ws / "lifting" / "votes.npy", votes[:10])  # wrong shape: ignored, not fatal
    assert sb.ViewerData.load(tiny.ws).direct is None


def test_stratified_subsample_is_uniform_within_each_class_across_chunks():
    """Across several 1 M-label chunks: each class gets its quota, only its own points, and
    its picks are spread over all of its members (not the first ones of a chunk)."""
    rng = np.random.default_rng(5)
    n = 2_500_000  # three chunks of the chunked pass
    labels = np.where(rng.random(n) < 0.7, 6, 16).astype(np.uint8)
    labels[rng.choice(n, 50, replace=False)] = 11
    idx = sb.stratified_subsample(labels, n, 100_000, seed=2)
    counts = np.bincount(labels, minlength=256)
    want = sb.class_quotas(counts, 100_000)
    got = np.bincount(labels[idx], minlength=256)
    assert np.array_equal(got, want) and got[11] == 50
    assert np.all(np.diff(idx) > 0)
    for cid in (6, 16):
        members = np.flatnonzero(labels == cid)
        picked = idx[labels[idx] == cid]
        # the picked share of each decile of the class's members is its quota's share
        dec = np.searchsorted(members, picked) * 10 // len(members)
        share = np.bincount(dec, minlength=10) / len(picked)
        assert np.abs(share - 0.1).max() < 0.01, (cid, share)


def test_direct_votes_are_counted_in_the_background(tiny, monkeypatch):
    """Loading a scene does not wait for the direct-vote labels (a pass over every point's
    vote counts, only the disagreement colours read them): the load returns while they are
    computed; the disagreement colours wait for them; a failed computation leaves the
    colours to the origin fallback instead of breaking the viewer. The computation starts
    only when asked (the viewer asks once a tab's points are on screen) or when read."""
    import threading

    n, ids = tiny.scene.n_points, list(TAX.ids)
    votes = np.zeros((n, len(ids)), np.uint16)
    votes[:, ids.index(6)] = 1
    np.save(tiny.ws / "lifting" / "votes.npy", votes)
    gate = threading.Event()
    real = sb.VoteStore.direct_labels

    def slow(self):
        assert gate.wait(10)
        return real(self)

    monkeypatch.setattr(sb.VoteStore, "direct_labels", slow)
    data = sb.ViewerData.load(tiny.ws)  # returns with the votes not counted yet
    assert isinstance(data.direct, sb.LazyLabels) and data.direct.shape == (n,)
    assert not data.direct.started and not data.direct._done.is_set()
    data.start_background()
    data.start_background()  # once
    assert data.direct.started and not data.direct._done.is_set()
    gate.set()
    col = sb.point_colours(data, "disagreement", np.arange(n))
    lab = np.asarray(tiny.labels)
    assert np.all(col[lab == 6] == sb.AGREE_COLOUR) and np.all(col[lab != 6] == sb.DISAGREE_COLOUR)

    def broken(self):
        raise ValueError("torn")

    monkeypatch.setattr(sb.VoteStore, "direct_labels", broken)
    data = sb.ViewerData.load(tiny.ws)
    assert not data.direct.started
    assert data.direct_array() is None  # a reader starts it
    with pytest.raises(ValueError, match="torn"):
        data.direct.get()
    org = np.asarray(data.origin)
    col = sb.point_colours(data, "disagreement", np.arange(n))
    assert np.all(col[org == 3] == sb.DISAGREE_COLOUR)


def test_frusta_of_many_cameras_equal_the_per_frame_poses():
    """frustum_nodes inverts the poses and converts the rotations of all frames in one
    batched call each: every node equals one frame's inverse and scipy's one-matrix conversion
    (a survey's 2,100 cameras took 0.3 s of per-frame calls before the first points), and
    matrix_to_quat (now the batch of one) the same."""
    from scipy.spatial.transform import Rotation

    from occufly.camera import Camera
    from occufly.scene import Frame, Scene

    rng = np.random.default_rng(3)
    cam = Camera("PINHOLE", 64, 48, np.array([50.0, 50.0, 32.0, 24.0]))
    frames = []
    for i, R in enumerate(Rotation.random(300, random_state=2).as_matrix()):
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, rng.normal(0, 50, 3)
        if i == 0:
            T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # w = 0: the sign rule
        frames.append(Frame(f"f{i}.jpg", cam, T))
    scene = Scene(frames=frames, xyz=np.zeros((1, 3), np.float32), rgb=np.zeros((1, 3), np.uint8),
                  taxonomy=TAX)
    nodes = sb.frustum_nodes(scene, {5: "selected"})
    assert len(nodes) == 300 and nodes[5].state == "selected"
    for fr, nd in zip(frames, nodes, strict=True):
        Twc = np.linalg.inv(np.asarray(fr.T_cam_world, np.float64))
        x, y, z, w = Rotation.from_matrix(Twc[:3, :3]).as_quat()  # one matrix, one call
        want = np.array([w, x, y, z])
        assert np.array_equal(nd.wxyz, want if w >= 0 else -want)
        assert np.array_equal(sb.matrix_to_quat(Twc[:3, :3]), nd.wxyz)
        assert np.array_equal(nd.position, Twc[:3, 3]) and nd.wxyz[0] >= 0
    assert sb.frustum_nodes(Scene(frames=[], xyz=np.zeros((1, 3), np.float32),
                                  rgb=np.zeros((1, 3), np.uint8), taxonomy=TAX)) == []
