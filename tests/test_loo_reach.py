"""What a frame's leave-one-out labels are decided at (``loo.loo_point_ids``: the points its
review can show, not the whole frustum cull) and which frames can change them
(``loo.frames_reaching``: the review cache's key), on the synthetic tiny survey with the
render's cull forced on."""

from __future__ import annotations

import numpy as np
import pytest

from occufly import render
from occufly.lifting import VoteStore
from occufly.lifting import loo as L
from occufly.lifting.knn import LiftParams
from occufly.scene import Scene


@pytest.fixture(scope="module")
def lifted(tmp_path_factory, synth_tiny):
    from occufly.io.importer import import_scene
    from occufly.io.masks import read_mask
    from occufly.selection import select_frames

    root = tmp_path_factory.mktemp("reach")
    import_scene(synth_tiny, root / "ws")
    scene = Scene.load(root / "ws")
    sel = select_frames(scene, mode="greedy", target_coverage=0.99)
    st = VoteStore.open(root / "ws", scene)
    rng = np.random.default_rng(3)
    for fi in sel.frames:
        f = scene.frames[fi]
        m = read_mask(synth_tiny / "truth" / "masks" / f"{f.name.rsplit('.', 1)[0]}.png", f,
                      scene.taxonomy)
        m = m.copy()
        # a wrong block in some masks: points the other frames decide differently
        if fi % 2:
            y, x = rng.integers(0, m.shape[0] // 2), rng.integers(0, m.shape[1] // 2)
            m[y:y + m.shape[0] // 3, x:x + m.shape[1] // 3] = 1
        st.set_mask(fi, m, version="v")
    st.fill_and_denoise()
    st.close()
    return root / "ws", scene, list(sel.frames)


def _whole_cull(scene: Scene, f: int, params=None) -> np.ndarray:  # noqa: ANN001
    """The points the labels were decided at before: the cull's bins and the visible points."""
    fr = scene.frames[f]
    cand = render.frustum_candidates(scene, fr.camera, fr.T_cam_world)
    return np.union1d(cand, np.asarray(scene.visibility.frame_ids(f), np.int64))


def _same_renders(scene: Scene, f: int, got, want, *, labelled: float) -> None:  # noqa: ANN001
    """Frame f's LOO and confident renderings of two label sets are identical, and more than
    ``labelled`` of the LOO image's pixels have a label."""
    cam = scene.frames[f].camera
    a = L.render_review(scene, got, (cam.height, cam.width))
    b = L.render_review(scene, want, (cam.height, cam.width))
    assert (a["loo"] > 0).mean() > labelled
    for k in ("loo", "confident"):
        assert np.array_equal(a[k], b[k]), (f, k)


def test_the_points_decided_render_as_the_whole_cull(lifted, monkeypatch):
    """With the plain vote (a point's label depends on its own votes and its fill sources
    only) the labels decided at ``loo_point_ids`` render exactly as those decided over the
    whole cull: nothing dropped can splat into the image or fill a point it shows."""
    path, scene, sel = lifted
    monkeypatch.setattr(render, "_CULL_MIN_POINTS", 0)
    # a fill radius of 1 m: the tiny scene's frames see 10-20 m of ground, 3 m reach most of it
    p = LiftParams(robust=False, fill_radius=1.0)
    fewer = 0
    frames = sel[:4] + [f for f in range(len(scene.frames)) if f not in sel][:4]
    for f in frames:
        got = L.loo_labels(path, scene, f, params=p)
        assert np.array_equal(got.point_ids, L.loo_point_ids(scene, f, params=p))
        with monkeypatch.context() as mp:
            mp.setattr(L, "loo_point_ids", _whole_cull)
            want = L.loo_labels(path, scene, f, params=p)
        assert np.isin(got.point_ids, want.point_ids).all()
        fewer += len(want.point_ids) - len(got.point_ids)
        _same_renders(scene, f, got, want, labelled=0.5)
    assert fewer > 0  # the cull's bins hold points the image cannot show


def test_frames_reaching_holds_every_frame_that_sees_a_point(lifted, monkeypatch):
    path, scene, sel = lifted
    monkeypatch.setattr(render, "_CULL_MIN_POINTS", 0)
    F = len(scene.frames)
    left_out = 0
    for f in range(0, F, max(1, F // 12)):
        ids = L.loo_point_ids(scene, f)
        g = L.frames_reaching(scene, f, ids)
        assert g is not None and f not in set(g.tolist())
        assert np.all(np.diff(g) > 0)
        for h in sorted(set(range(F)) - set(g.tolist()) - {f}):
            left_out += 1
            # a frame left out sees none of the points: it cannot vote at them
            assert not np.isin(scene.visibility.frame_ids(h), ids).any(), (f, h)
    assert left_out > 0  # not every frame reaches every other


def test_frames_reaching_without_a_bound(lifted):
    path, scene, sel = lifted
    assert len(L.frames_reaching(scene, 0, np.zeros(0, np.int64))) == 0
    nan = Scene.load(path)
    nan.xyz = np.full((scene.n_points, 3), np.nan, np.float32)
    assert L.frames_reaching(nan, 0, np.arange(5)) is None  # no finite point to bound


@pytest.fixture(scope="module")
def distorted(tmp_path_factory):
    """The tiny scene written as a COLMAP project (FULL_OPENCV: a drone lens's distortion),
    imported, its truth masks lifted."""
    from occufly.io.importer import import_scene
    from occufly.synthetic.formats import generate_formats

    root = tmp_path_factory.mktemp("reach-distorted")
    generate_formats(root / "synth", ("colmap",), preset="tiny", seed=0)
    empty = root / "no-depth-maps"
    empty.mkdir()
    import_scene(root / "synth", root / "ws", visibility="depth", depth_maps=empty)
    scene = Scene.load(root / "ws")
    assert scene.frames[0].camera.has_distortion
    rng = np.random.default_rng(5)
    st = VoteStore.open(root / "ws", scene)
    frames = list(range(0, len(scene.frames), 2))
    for fi in frames:
        cam = scene.frames[fi].camera
        # blocks of classes: points the other frames decide differently here and there
        m = np.full((cam.height, cam.width), 6, np.uint8)
        y, x = rng.integers(0, cam.height // 2), rng.integers(0, cam.width // 2)
        m[y:y + cam.height // 3, x:x + cam.width // 3] = 1
        st.set_mask(fi, m, version="v")
    st.fill_and_denoise()
    st.close()
    return root / "ws", scene, frames


def test_a_distorted_frames_points_render_as_every_point(distorted, monkeypatch):
    """A distorted camera is not culled: before, its labels were decided at every point of
    the cloud. Decided at the points whose projection reaches the image, the seen points and
    their fill sources, they render the same (plain vote), from fewer points."""
    path, scene, frames = distorted
    monkeypatch.setattr(render, "_CULL_MIN_POINTS", 0)
    p = LiftParams(robust=False, fill_radius=1.0)
    fewer = 0
    for f in frames[:3] + [f + 1 for f in frames[:3]]:
        got = L.loo_labels(path, scene, f, params=p)
        with monkeypatch.context() as mp:
            mp.setattr(L, "loo_point_ids",
                       lambda sc, fi, params=None: np.arange(sc.n_points, dtype=np.int64))
            want = L.loo_labels(path, scene, f, params=p)
        assert np.isin(np.asarray(scene.visibility.frame_ids(f)), got.point_ids).all()
        fewer += len(want.point_ids) - len(got.point_ids)
        _same_renders(scene, f, got, want, labelled=0.3)
    assert fewer > 0


def test_a_distorted_cameras_cull_renders_as_every_point(distorted, monkeypatch):
    """A distorted camera projects nothing beyond its lens model's valid radius, so the render
    culls it by that cone (before: no cull, every point projected): the same images."""
    path, scene, frames = distorted
    monkeypatch.setattr(render, "_CULL_MIN_POINTS", 0)
    labels = np.asarray(VoteStore.open(path, scene).direct_labels())
    culled = 0
    for f in range(0, len(scene.frames), 3):
        fr = scene.frames[f]
        cand = render.frustum_candidates(scene, fr.camera, fr.T_cam_world)
        assert cand is not None
        culled += scene.n_points - len(cand)
        got = render.render_labels(scene, labels, f)
        with monkeypatch.context() as mp:
            mp.setattr(render, "frustum_candidates", lambda *a, **k: None)
            want = render.render_labels(scene, labels, f)
        assert (got[0] > 0).mean() > 0.3
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1]), f
    assert culled > 0
