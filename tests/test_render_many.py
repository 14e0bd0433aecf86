"""render_many_for_mask: several label sets over one geometry, each equal to its own render."""

from __future__ import annotations

import numpy as np

from occufly.camera import Camera, look_at
from occufly.render import render_for_mask, render_many_for_mask
from occufly.scene import Frame, Scene
from occufly.taxonomy import default_taxonomy
from tests.lift_scene import make_scene

TAX = default_taxonomy()


def _labels(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    ids = np.array([int(i) for i in TAX.ids], np.uint8)
    out = ids[rng.integers(0, len(ids), n)]
    out[rng.random(n) < 0.2] = 0  # unlabelled points still occlude
    return out


def test_many_equal_their_own_renders_small_scene():
    scene, truth = make_scene()
    other = _labels(scene.n_points, 1)
    for fi in (3, 9):
        h, w = scene.frames[fi].camera.height, scene.frames[fi].camera.width
        for shape in ((h, w), (h // 2, w // 2)):
            a, b = render_many_for_mask(scene, [truth, other], fi, shape)
            assert np.array_equal(a, render_for_mask(scene, truth, fi, shape)[0])
            assert np.array_equal(b, render_for_mask(scene, other, fi, shape)[0])


def _big_scene(seed: int, extra_poses: tuple = ()) -> Scene:
    """A cloud above the cull threshold (a 48 m plane at 8 cm with a raised disc) and > 4 MP
    frames over it (rendered coarser, upsampled): one looking down at (3, 0), then
    ``extra_poses``."""
    rng = np.random.default_rng(seed)
    sp = 0.08
    g = np.arange(-24, 24, sp)
    gx, gy = np.meshgrid(g, g)
    xyz = np.column_stack([gx.ravel() + rng.uniform(-0.02, 0.02, gx.size),
                           gy.ravel(), np.where(np.hypot(gx, gy).ravel() < 5, 3.0, 0.0)])
    xyz = xyz.astype(np.float32)
    cam = Camera("PINHOLE", 2736, 1824, np.array([1824.0, 1824.0, 1368.0, 912.0]))
    poses = [look_at([3.0, 0.0, 30.0], [3.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)), *extra_poses]
    scene = Scene(frames=[Frame(f"f{i}.jpg", cam, T) for i, T in enumerate(poses)], xyz=xyz,
                  rgb=np.zeros_like(xyz, np.uint8), taxonomy=TAX)
    scene.meta["point_spacing"] = sp
    return scene


def test_many_equal_their_own_renders_culled_and_coarse():
    """A cloud above the cull threshold and a > 4 MP frame (rendered coarser, upsampled)."""
    scene = _big_scene(0)
    assert scene.n_points > 200_000
    la, lb = _labels(scene.n_points, 2), _labels(scene.n_points, 3)
    for shape in ((1824, 2736), (912, 1368)):
        a, b = render_many_for_mask(scene, [la, lb], 0, shape)
        assert a.shape == shape
        assert np.array_equal(a, render_for_mask(scene, la, 0, shape)[0])
        assert np.array_equal(b, render_for_mask(scene, lb, 0, shape)[0])


def test_geometry_computed_first_gives_the_same_images():
    """The depth pass computed before the labels (``frame_geometry``, as a review computes it
    beside the leave-one-out labels) then the label pass: the same images bit for bit, dense
    and sparse label sets, culled and coarsened, full and half size; a geometry of another
    frame or size is refused."""
    import pytest

    from occufly.render import frame_geometry

    rng = np.random.default_rng(4)
    scene = _big_scene(4, (look_at([-2.0, 1.0, 25.0], [0.0, 0.0, 0.0], up=(0.0, 1.0, 0.0)),))
    la = _labels(scene.n_points, 5)
    ids = np.sort(rng.choice(scene.n_points, scene.n_points // 3, replace=False))
    sparse = (ids, la[ids])
    for fi in (0, 1):
        for shape in ((1824, 2736), (912, 1368)):
            want = render_many_for_mask(scene, [la, sparse], fi, shape)
            geo = frame_geometry(scene, fi, shape)
            assert geo is not None and (geo.k > 1) == (shape[0] == 1824)
            got = render_many_for_mask(scene, [la, sparse], fi, shape, geometry=geo)
            assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
    with pytest.raises(ValueError, match="geometry of"):
        render_many_for_mask(scene, [la], 1, (912, 1368),
                             geometry=frame_geometry(scene, 0, (912, 1368)))
    small, truth = make_scene()
    h, w = small.frames[3].camera.height, small.frames[3].camera.width
    geo = frame_geometry(small, 3, (h, w))
    assert np.array_equal(render_many_for_mask(small, [truth], 3, (h, w), geometry=geo)[0],
                          render_for_mask(small, truth, 3, (h, w))[0])


def test_agreement_counts_match_a_plain_reference():
    """The compiled pair count behind ``agreement``: class x class pixels only (0, 255 and
    ids outside the taxonomy left out of the score, 255 in the mask not counted as painted)."""
    from occufly.render import agreement

    rng = np.random.default_rng(4)
    ids = np.array([int(i) for i in TAX.ids], np.uint8)
    pool = np.concatenate([ids, np.uint8([0, 0, 255, 250])])
    mask = pool[rng.integers(0, len(pool), (123, 77))]
    ren = np.where(rng.random(mask.shape) < 0.6, mask, pool[rng.integers(0, len(pool), mask.shape)])
    res = agreement(mask, ren.astype(np.uint8), TAX)
    is_cls = np.isin(mask, ids)
    both = is_cls & np.isin(ren, ids)
    assert res["pixels"] == int(both.sum())
    assert res["agree"] == int((both & (mask == ren)).sum())
    assert res["mask_pixels"] == int(is_cls.sum())
    for c in TAX.classes:
        pc = res["per_class"].get(c.name)
        if pc is None:
            continue
        assert pc["mask_pixels"] == int((both & (mask == c.id)).sum())
        assert pc["painted_pixels"] == int((mask == c.id).sum())
        assert pc["agree"] == int((both & (mask == c.id) & (ren == c.id)).sum())
    assert {v["id"] for v in res["per_class"].values() if v["painted_pixels"]} == set(np.unique(mask[is_cls]).tolist())


def test_a_class_nobody_else_sees_is_listed_with_no_figures():
    """A frame whose painting the rendering does not label anywhere (no independent views):
    every painted class is still listed, with its painted pixels and no recall / IoU."""
    from occufly.render import agreement

    mask = np.zeros((40, 50), np.uint8)
    a, b = (int(c.id) for c in TAX.classes[:2])
    mask[:10], mask[20:25] = a, b
    res = agreement(mask, np.zeros_like(mask), TAX)
    assert res["pixels"] == 0 and res["agreement"] is None
    got = {v["id"]: v for v in res["per_class"].values()}
    assert set(got) == {a, b}
    assert got[a]["painted_pixels"] == 500 and got[b]["painted_pixels"] == 250
    for v in got.values():
        assert v["mask_pixels"] == 0 and v["recall"] is None and v["iou"] is None


def test_pair_counts_split_over_threads_equal_one_pass():
    """count_pairs_many over two or three threads (a 20 MP review's figures): the same
    integers as one pass, whatever the split; below the split's threshold one thread."""
    from occufly.confusion import _MIN_PAIRS_PER_WORKER, count_pairs_many

    rng = np.random.default_rng(3)
    pool = np.concatenate([np.asarray(TAX.ids, np.uint8), np.uint8([0, 255, 200])])
    h, w = 1201, 2011  # 2.4 M pixels: up to two runs of at least _MIN_PAIRS_PER_WORKER
    assert h * w >= 2 * _MIN_PAIRS_PER_WORKER
    mask = pool[rng.integers(0, len(pool), (h, w))]
    preds = [np.where(rng.random(mask.shape) < 0.6, mask, pool[rng.integers(0, len(pool), mask.shape)])
             .astype(np.uint8) for _ in range(3)]
    one = count_pairs_many(TAX.ids, mask, preds)
    for workers in (2, 3, 64):
        got = count_pairs_many(TAX.ids, mask, preds, workers=workers)
        assert len(got) == 3
        for g, o in zip(got, one, strict=True):
            assert g.dtype == np.int64 and np.array_equal(g, o)
    assert sum(int(o.sum()) for o in one) == 3 * h * w
    small = count_pairs_many(TAX.ids, mask[:10], [p[:10] for p in preds], workers=4)
    assert all(int(s.sum()) == 10 * w for s in small)


def test_one_pass_counts_equal_separate_agreements():
    """loo_agreement counts the mask against its LOO, confident and self renderings in one
    compiled pass: the same figures as one ``agreement`` call per rendering."""
    from occufly.confusion import Confusion, count_pairs_many
    from occufly.lifting.loo import loo_agreement
    from occufly.render import agreement

    rng = np.random.default_rng(7)
    ids = np.array([int(i) for i in TAX.ids], np.uint8)
    pool = np.concatenate([ids, np.uint8([0, 0, 255])])
    mask = pool[rng.integers(0, len(pool), (60, 90))]
    ren, conf, own = (np.where(rng.random(mask.shape) < 0.7, mask, pool[rng.integers(0, len(pool), mask.shape)])
                      .astype(np.uint8) for _ in range(3))
    c = Confusion(TAX.ids)
    for got, p in zip(count_pairs_many(TAX.ids, mask, [ren, conf, own]), (ren, conf, own), strict=True):
        assert np.array_equal(got, c.add_all_pairs(mask, p))

    class _S:
        taxonomy = TAX

    out = loo_agreement(mask, ren, _S, self_rendered=own, confident_rendered=conf)
    a, s = agreement(mask, ren, TAX), agreement(mask, own, TAX)
    assert out["agreement"] == a["agreement"] and out["per_class"] == a["per_class"]
    assert out["self_agreement"] == s["agreement"] and out["painted_pixels"] == a["mask_pixels"]
    both = np.isin(conf, ids) & (np.isin(mask, ids) | (mask == 0))
    assert out["area_pixels"] == int(both.sum())
    assert out["area_agree"] == int((both & (mask == conf)).sum())


def test_upsample_kernel_equals_the_broadcast_upsample():
    from occufly.render import _upsample
    from occufly.splat import upsample_u8

    img = np.random.default_rng(1).integers(0, 255, (7, 11)).astype(np.uint8)
    for k, h, w in ((3, 21, 33), (3, 23, 35), (3, 19, 31), (1, 7, 11), (4, 30, 45)):
        assert np.array_equal(upsample_u8(img, k, h, w), _upsample(img, k, h, w)), (k, h, w)


def test_compiled_projection_equals_the_numpy_projection(monkeypatch):
    """The one-pass compiled projection + splat (undistorted cameras) gives the images, depth
    and the multi-set images of the numpy projection it replaced, bit for bit: the small
    scene's frames at full and half size, and a culled > 4 MP frame rendered coarser."""
    import occufly.render as R
    from occufly.render import render_labels

    scene, truth = make_scene()
    other = _labels(scene.n_points, 5)
    cases = [(scene, fi, shape) for fi in (0, 3, 9)
             for shape in ((scene.frames[fi].camera.height, scene.frames[fi].camera.width),
                           (scene.frames[fi].camera.height // 2, scene.frames[fi].camera.width // 2))]
    rng = np.random.default_rng(4)
    g = np.arange(-24, 24, 0.08)
    gx, gy = np.meshgrid(g, g)
    xyz = np.column_stack([gx.ravel() + rng.uniform(-0.02, 0.02, gx.size), gy.ravel(),
                           np.where(np.hypot(gx, gy).ravel() < 5, 3.0, 0.0)]).astype(np.float32)
    cam = Camera("PINHOLE", 2736, 1824, np.array([1824.0, 1830.0, 1370.5, 911.0]))
    T = look_at([3.0, 1.0, 30.0], [2.0, 0.0, 0.0], up=(0.0, 1.0, 0.0))
    big = Scene(frames=[Frame("f.jpg", cam, T)], xyz=xyz, rgb=np.zeros_like(xyz, np.uint8),
                taxonomy=TAX)
    big.meta["point_spacing"] = 0.08
    cases.append((big, 0, (1824, 2736)))
    n_compiled = 0
    for sc, fi, shape in cases:
        la = truth if sc is scene else _labels(sc.n_points, 6)
        lb = other if sc is scene else _labels(sc.n_points, 7)
        got = {}
        for compiled in (True, False):
            monkeypatch.setattr(R, "COMPILED_PROJECTION", compiled)
            s = sc.frames[fi].camera.width // shape[1]
            got[compiled] = (render_for_mask(sc, la, fi, shape)[0],
                             render_labels(sc, la, fi, scale=1.0 / s)[1],
                             render_many_for_mask(sc, [la, lb], fi, shape))
        a, b = got[True], got[False]
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        assert all(np.array_equal(x, y) for x, y in zip(a[2], b[2], strict=True))
        assert (a[0] > 0).mean() > 0.3  # something was rendered
        n_compiled += not sc.frames[fi].camera.has_distortion
    assert n_compiled >= 3  # the compiled path was taken


def test_sparse_label_sets_equal_their_dense_arrays(monkeypatch):
    """A label set given as (sorted ids, values) renders as the (N,) array holding them (the
    review's leave-one-out labels, no (N,) array built): the small scene (no cull) and a
    culled > 4 MP frame rendered coarser, through the compiled and the numpy projection; ids
    out of order take the dense path and give the same image."""
    import occufly.render as R
    from occufly.splat import sparse_at

    scene, truth = make_scene()
    rng = np.random.default_rng(8)
    g = np.arange(-24, 24, 0.08)
    gx, gy = np.meshgrid(g, g)
    xyz = np.column_stack([gx.ravel(), gy.ravel() + rng.uniform(-0.02, 0.02, gx.size),
                           np.where(np.hypot(gx, gy).ravel() < 5, 3.0, 0.0)]).astype(np.float32)
    cam = Camera("PINHOLE", 2736, 1824, np.array([1824.0, 1824.0, 1368.0, 912.0]))
    big = Scene(frames=[Frame("f.jpg", cam, look_at([3.0, 0.0, 30.0], [3.0, 0.0, 0.0],
                                                    up=(0.0, 1.0, 0.0)))],
                xyz=xyz, rgb=np.zeros_like(xyz, np.uint8), taxonomy=TAX)
    big.meta["point_spacing"] = 0.08
    for sc, fi, shape in ((scene, 3, (scene.frames[3].camera.height, scene.frames[3].camera.width)),
                          (big, 0, (1824, 2736))):
        n = sc.n_points
        ids = np.sort(rng.choice(n, n // 3, replace=False)).astype(np.int64)
        vals = _labels(len(ids), 9)
        dense = np.zeros(n, np.uint8)
        dense[ids] = vals
        other = _labels(n, 10)
        vals2 = np.where(rng.random(len(ids)) < 0.5, vals, 0).astype(np.uint8)
        dense2 = np.zeros(n, np.uint8)
        dense2[ids] = vals2
        for compiled in (True, False):
            monkeypatch.setattr(R, "COMPILED_PROJECTION", compiled)
            want = render_many_for_mask(sc, [dense, other, dense2], fi, shape)
            got = render_many_for_mask(sc, [(ids, vals), other, (ids, vals2)], fi, shape)
            assert all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
            assert (got[0] > 0).any()
        perm = rng.permutation(len(ids))  # unsorted ids: the dense fallback, the same image
        got = render_many_for_mask(sc, [(ids[perm], vals[perm])], fi, shape)
        assert np.array_equal(got[0], want[0])
    out = np.zeros(3, np.uint8)
    assert sparse_at(np.array([1, 4, 9]), np.array([5, 6, 7], np.uint8), np.array([0, 4, 9]), out)
    assert out.tolist() == [0, 6, 7]
    assert not sparse_at(np.array([4, 1]), np.array([5, 6], np.uint8), np.array([0, 4, 9]), out)
    assert not sparse_at(np.array([1, 4]), np.array([5, 6], np.uint8), np.array([4, 0, 9]), out)
    from occufly.splat import sparse_at_columns

    out2 = np.full((3, 3), 9, np.uint8)
    assert sparse_at_columns(np.array([1, 4, 9]), np.array([[5, 1], [6, 2], [7, 3]], np.uint8),
                             np.array([0, 4, 9]), out2, np.array([2, 0]))
    assert out2.tolist() == [[0, 9, 0], [2, 9, 6], [3, 9, 7]]


def test_compiled_finish_and_overlay_lookup_equal_the_numpy_ones(monkeypatch):
    """render_many's class images finished by one compiled sweep, and the overlay's palette
    indices by a compiled table lookup, against the numpy masks and casts they replaced."""
    import occufly.render as R

    scene, truth = make_scene()
    other = _labels(scene.n_points, 12)
    fi = 12  # half its pixels see no point
    shape = (scene.frames[fi].camera.height, scene.frames[fi].camera.width)
    rng = np.random.default_rng(13)
    mask = np.array([int(i) for i in TAX.ids] + [0, 255, 200], np.uint8)[
        rng.integers(0, len(TAX.ids) + 3, shape)]
    got = {}
    for flag in (True, False):
        monkeypatch.setattr(R, "COMPILED_FINISH", flag)
        imgs = render_many_for_mask(scene, [truth, other], fi, shape)
        got[flag] = imgs + [R.disagreement_indices(mask, imgs[0], TAX),
                            R.disagreement_indices(mask[:, ::2], imgs[1][:, ::2], TAX)]
    assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(got[True], got[False], strict=True))
    assert (got[True][0] == 0).any() and (got[True][2] == R.DISAGREE_GAP).any()
    assert ((got[True][2] != 0) & (got[True][2] != R.DISAGREE_GAP)).any()


def test_recorded_projection_equals_projecting_twice(monkeypatch):
    """The label pass over the points the depth pass recorded gives the images and depth of
    the label pass that projects the cloud again: the small scene's frames and a culled,
    coarser > 4 MP frame, one label set and several (one of them sparse)."""
    import occufly.render as R
    from occufly.render import render_labels

    scene, truth = make_scene()
    rng = np.random.default_rng(14)
    g = np.arange(-24, 24, 0.08)
    gx, gy = np.meshgrid(g, g)
    xyz = np.column_stack([gx.ravel() + rng.uniform(-0.02, 0.02, gx.size), gy.ravel(),
                           np.where(np.hypot(gx, gy).ravel() < 5, 3.0, 0.0)]).astype(np.float32)
    cam = Camera("PINHOLE", 2736, 1824, np.array([1824.0, 1830.0, 1370.5, 911.0]))
    big = Scene(frames=[Frame("f.jpg", cam, look_at([3.0, 1.0, 30.0], [2.0, 0.0, 0.0],
                                                    up=(0.0, 1.0, 0.0)))],
                xyz=xyz, rgb=np.zeros_like(xyz, np.uint8), taxonomy=TAX)
    big.meta["point_spacing"] = 0.08
    for sc, fi, shape in [(scene, 3, (scene.frames[3].camera.height, scene.frames[3].camera.width)),
                          (scene, 12, (scene.frames[12].camera.height // 2,
                                       scene.frames[12].camera.width // 2)),
                          (big, 0, (1824, 2736))]:
        la = truth if sc is scene else _labels(sc.n_points, 15)
        ids = np.sort(rng.choice(sc.n_points, sc.n_points // 4, replace=False))
        got = {}
        for rec in (True, False):
            monkeypatch.setattr(R, "RECORD_PROJECTION", rec)
            s = sc.frames[fi].camera.width // shape[1]
            got[rec] = [render_for_mask(sc, la, fi, shape)[0],
                        render_labels(sc, la, fi, scale=1.0 / s)[1],
                        *render_many_for_mask(sc, [la, (ids, la[ids])], fi, shape)]
        assert all(np.array_equal(a, b) for a, b in zip(got[True], got[False], strict=True))
        assert (got[True][0] > 0).mean() > 0.3
