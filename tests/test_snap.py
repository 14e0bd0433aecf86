"""Issue 37: image-guided boundary snapping of a mask before it votes (occufly.lifting.snap)
and the ``snap`` vote weighting that applies it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from occufly.lifting import VoteStore
from occufly.lifting.snap import frame_image, snap_band, snap_frame_mask, snap_mask
from occufly.scene import Scene
from occufly.taxonomy import EMPTY, INVALID
from tests.lift_scene import make_scene, truth_mask

A, B, C = 3, 7, 12  # three class ids


def _image(regions: np.ndarray, seed: int = 0, noise: float = 6.0) -> np.ndarray:
    """(h, w, 3) uint8 photo of a label image: one flat colour per label plus pixel noise."""
    rng = np.random.default_rng(seed)
    pal = {A: (60, 140, 60), B: (90, 90, 95), C: (40, 40, 200), EMPTY: (120, 120, 120),
           INVALID: (200, 200, 200)}
    img = np.zeros(regions.shape + (3,), np.float32)
    for k, col in pal.items():
        img[regions == k] = col
    img += rng.normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def _scene_regions(h: int = 120, w: int = 160) -> np.ndarray:
    m = np.full((h, w), A, np.uint8)
    m[:, w // 2:] = B
    yy, xx = np.ogrid[:h, :w]
    m[(yy - h // 3) ** 2 + (xx - w // 4) ** 2 <= (h // 6) ** 2] = C
    return m


def test_a_shifted_boundary_is_snapped_back_onto_the_edge():
    truth = np.full((80, 120), A, np.uint8)
    truth[:, 60:] = B
    img = _image(truth)
    for shift in (-2, -1, 1, 2):
        painted = np.full_like(truth, A)
        painted[:, 60 + shift:] = B
        out = snap_mask(painted, img, band=3)
        assert (painted != truth).sum() == 80 * abs(shift)
        assert np.array_equal(out, truth), shift


def test_a_shifted_disc_is_snapped_back():
    truth = _scene_regions()
    img = _image(truth, seed=1)
    painted = np.roll(truth, (2, -2), axis=(0, 1))  # the disc and the A/B boundary move 2 px
    painted[:2, :] = truth[:2, :]  # no wrapped-around strips
    painted[:, -2:] = truth[:, -2:]
    out = snap_mask(painted, img, band=3)
    before = (painted != truth).sum()
    assert before > 300
    assert (out != truth).sum() <= 0.05 * before


def test_no_op_on_a_mask_that_follows_the_edges():
    truth = _scene_regions()
    for seed in range(3):
        out = snap_mask(truth, _image(truth, seed=seed, noise=10.0), band=3)
        assert np.array_equal(out, truth)


def test_no_edge_in_the_photo_moves_nothing():
    """A boundary the photo does not show (a look-alike pair, one colour) stays where it was
    painted: the colour check sees no class closer than the other."""
    painted = np.full((60, 90), A, np.uint8)
    painted[:, 47:] = B
    flat = np.full((60, 90, 3), 100, np.uint8)
    assert np.array_equal(snap_mask(painted, flat, band=3), painted)


def test_a_blob_narrower_than_the_band_survives():
    painted = np.full((60, 90), A, np.uint8)
    painted[30:33, 40:43] = C  # 3 x 3: no pixel farther than 4 px from the background
    painted[10:12, 5:80] = B  # a 2 px wide strip (a cable)
    for img in (_image(painted), np.full((60, 90, 3), 90, np.uint8), _image(np.full_like(painted, A))):
        out = snap_mask(painted, img, band=4)
        assert (out[30:33, 40:43] == C).all()
        assert (out[10:12, 5:80] == B).all()


def test_a_blob_whose_photo_is_shifted_follows_it_but_keeps_its_core():
    truth = np.full((60, 90), A, np.uint8)
    truth[28:36, 40:48] = C
    painted = np.full_like(truth, A)
    painted[30:38, 42:50] = C  # painted 2 px off
    out = snap_mask(painted, _image(truth), band=3)
    assert (out == C).sum() > 0.5 * (truth == C).sum()
    assert (out != truth).sum() < (painted != truth).sum()


def test_classes_not_present_are_never_introduced():
    rng = np.random.default_rng(5)
    m = rng.choice(np.array([A, B, C], np.uint8), size=(12, 16))
    m = np.repeat(np.repeat(m, 8, axis=0), 8, axis=1)
    img = rng.integers(0, 256, m.shape + (3,), dtype=np.uint8)  # edges everywhere
    for band in (1, 2, 3, 5):
        out = snap_mask(m, img, band=band)
        assert set(np.unique(out)) <= set(np.unique(m))
    only_a = np.full((40, 40), A, np.uint8)
    assert np.array_equal(snap_mask(only_a, img[:40, :40], band=3), only_a)


def test_unpainted_and_ignored_pixels_stay_as_they_are_and_never_spread():
    truth = _scene_regions()
    img = _image(truth, seed=2)
    painted = np.roll(truth, 2, axis=1)
    yy, xx = np.ogrid[: truth.shape[0], : truth.shape[1]]
    hole = (yy - 90) ** 2 / 15 ** 2 + (xx - 70) ** 2 / 25 ** 2 <= 1  # across the A/B boundary
    painted[hole] = EMPTY
    painted[:10, 100:140] = INVALID
    out = snap_mask(painted, img, band=3)
    assert np.array_equal(out == EMPTY, painted == EMPTY)
    assert np.array_equal(out == INVALID, painted == INVALID)


def test_shape_and_dtype_are_kept():
    truth = _scene_regions(50, 70)
    for dt in (np.uint8, np.int32):
        out = snap_mask(truth.astype(dt), _image(truth), band=2)
        assert out.shape == truth.shape and out.dtype == np.uint8
    grey = cv2.cvtColor(_image(truth), cv2.COLOR_BGR2GRAY)
    assert snap_mask(truth, grey, band=2).shape == truth.shape
    with pytest.raises(ValueError, match="differ in size"):
        snap_mask(truth, _image(truth)[:-1], band=2)
    assert snap_band((320, 480)) == 2 and snap_band((3648, 5472)) == 23


def test_large_masks_are_snapped_on_a_subsample():
    """Over max_pixels the watershed runs on every f-th row and column; the decisions come
    back to the full mask, and a 1 px line the subsample misses keeps its pixels."""
    truth = np.full((240, 360), A, np.uint8)
    truth[:, 180:] = B
    img = _image(truth)
    painted = np.full_like(truth, A)
    painted[:, 186:] = B  # 6 px off
    painted[100, 10:170] = C  # a 1 px line on an odd row: not in the subsample of every 2nd
    out = snap_mask(painted, img, band=8, max_pixels=240 * 360 // 4)
    assert (out[:, :178] != B).all() and (out[:, 182:] == B).all()
    assert (out[100, 10:170] == C).all()
    assert out.dtype == np.uint8 and out.shape == truth.shape


def test_frame_image_reads_the_photo_at_the_mask_resolution(tmp_path):
    truth = _scene_regions(120, 160)
    big = cv2.resize(_image(truth), (640, 480), interpolation=cv2.INTER_NEAREST)
    for ext in ("png", "jpg"):
        p = tmp_path / f"photo.{ext}"
        cv2.imwrite(str(p), big)
        img = frame_image(p, (120, 160))
        assert img.shape == (120, 160, 3) and img.dtype == np.uint8
        assert np.abs(img.astype(int) - _image(truth).astype(int)).mean() < 12
    assert frame_image(tmp_path / "missing.png", (120, 160)) is None
    assert frame_image(None, (120, 160)) is None


@pytest.fixture(scope="module")
def built():
    return make_scene()


def test_snap_vote_weighting_votes_the_snapped_mask(tmp_path, built):
    scene0, _ = built
    scene0.save(tmp_path / "ws")
    scene = Scene.load(tmp_path / "ws")
    fi = 5
    truth = truth_mask(scene.frames[fi])
    photo = tmp_path / "frame5.png"
    cv2.imwrite(str(photo), _image(truth, noise=4.0))
    scene.frames[fi].image_path = str(photo)
    painted = np.roll(truth, 2, axis=1)
    st = VoteStore.open(tmp_path / "ws", scene, vote_weighting="snap")
    assert st.vote_weighting == "snap"
    pids, cols, wts = st.frame_votes(fi, painted)
    plain = VoteStore.open(tmp_path / "plain", _save(scene0, tmp_path / "plain"),
                           vote_weighting="plain")
    snapped = snap_frame_mask(scene.frames[fi], painted)
    assert (snapped != painted).any()
    p2, c2, w2 = plain.frame_votes(fi, snapped)
    assert np.array_equal(pids, p2) and np.array_equal(cols, c2) and (wts == 1).all()
    st.apply_frame(fi, painted, version="v1")
    assert int(np.asarray(st.votes).sum()) == len(pids)
    assert st.snapshot().vote_unit == 1
    # a frame without a readable photo votes its mask as painted
    p3, c3, _ = st.frame_votes(9, truth_mask(scene.frames[9]))
    p4, c4, _ = plain.frame_votes(9, truth_mask(scene.frames[9]))
    assert np.array_equal(p3, p4) and np.array_equal(c3, c4)
    st.close()
    assert VoteStore.open(tmp_path / "ws", scene).vote_weighting == "snap"


def _save(scene, path):
    scene.save(path)
    return Scene.load(path)


def test_abstain_variant_unpaints_what_snapping_would_move(tmp_path, monkeypatch):
    import occufly.lifting.snap as snap_mod

    truth = _scene_regions()
    photo = tmp_path / "p.png"
    cv2.imwrite(str(photo), _image(truth))
    painted = np.roll(truth, 2, axis=1)

    class _Frame:
        image_path = str(photo)

    moved = snap_frame_mask(_Frame(), painted)
    monkeypatch.setattr(snap_mod, "SNAP_ABSTAIN", True)
    out = snap_frame_mask(_Frame(), painted)
    assert (moved != painted).any()
    assert np.array_equal(out == EMPTY, moved != painted)
    assert np.array_equal(out[out != EMPTY], painted[out != EMPTY])
