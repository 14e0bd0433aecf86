"""Render-back: z-buffered splats, depth, scale; agreement, confusion, disagreement image."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.camera import Camera, look_at
from occufly.render import (
    agreement,
    disagreement_image,
    estimate_point_spacing,
    merge_agreements,
    render_for_mask,
    render_labels,
)
from occufly.scene import Frame, Scene
from occufly.taxonomy import default_taxonomy
from tests.lift_scene import GRASS, ROAD, ROOF, make_scene, truth_mask

TAX = default_taxonomy()


def _plane_scene():
    """A 40 x 40 m ground grid (0.25 m) with a roof slab at z = 5 over [15, 25]^2, nadir camera."""
    g = np.arange(0.125, 40, 0.25)
    gx, gy = np.meshgrid(g, g)
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    labels = np.where(ground[:, 0] < 20, GRASS, ROAD).astype(np.uint8)
    r = np.arange(15.125, 25, 0.25)
    rx, ry = np.meshgrid(r, r)
    roof = np.column_stack([rx.ravel(), ry.ravel(), np.full(rx.size, 5.0)])
    xyz = np.vstack([ground, roof]).astype(np.float32)
    labels = np.concatenate([labels, np.full(len(roof), ROOF, np.uint8)])
    cam = Camera("PINHOLE", 200, 200, np.array([200.0, 200.0, 100.0, 100.0]))
    T = look_at([20.0, 20.0, 20.0], [20.0, 20.0, 0.0], up=(0.0, 1.0, 0.0))
    scene = Scene(frames=[Frame("f.jpg", cam, T)], xyz=xyz, rgb=np.zeros_like(xyz, np.uint8))
    return scene, labels


def test_spacing_estimate():
    scene, _ = _plane_scene()
    assert estimate_point_spacing(scene.xyz) == pytest.approx(0.25, rel=0.15)


def test_render_depth_labels_and_occlusion():
    scene, labels = _plane_scene()
    cls, depth = render_labels(scene, labels, 0)
    assert cls.shape == (200, 200) and depth.shape == (200, 200)
    # the camera sees [0, 40]^2 exactly at the ground: 200 px over 40 m, 5 px per metre
    # roof over [15, 25] at depth 15 projects to pixels 100 +- 200 * 5 / 15
    half = 200 * 5 / 15
    inner = slice(int(100 - half) + 2, int(100 + half) - 2)
    assert (cls[inner, inner] == ROOF).all()
    assert np.allclose(depth[inner, inner], 15.0, atol=1e-4)
    # ground outside the roof: grass left (x < 20 -> u < 100), road right, depth 20
    assert (cls[5:25, 5:95] == GRASS).all() and (cls[5:25, 105:195] == ROAD).all()
    assert np.allclose(depth[5:25, 5:195], 20.0, atol=1e-4)
    assert (cls > 0).all()  # no holes: the splats close the surface
    # the unlabelled roof still occludes (renders 0 where it is in front)
    lab2 = labels.copy()
    lab2[labels == ROOF] = 0
    cls2, depth2 = render_labels(scene, lab2, 0)
    assert (cls2[inner, inner] == 0).all() and np.allclose(depth2[inner, inner], 15.0, atol=1e-4)


def test_render_reduced_scale():
    scene, labels = _plane_scene()
    cls, depth = render_labels(scene, labels, 0, scale=0.25)
    assert cls.shape == (50, 50)
    assert cls[25, 25] == ROOF and cls[2, 2] == GRASS and cls[2, 47] == ROAD
    assert depth[2, 2] == pytest.approx(20.0, abs=1e-4)
    cls_m, _ = render_for_mask(scene, labels, 0, (100, 100))
    assert cls_m.shape == (100, 100)


def test_agreement_counts_and_confusion():
    mask = np.array([[6, 6, 1, 0], [16, 16, 255, 6]], np.uint8)
    rend = np.array([[6, 1, 1, 6], [16, 0, 16, 16]], np.uint8)
    a = agreement(mask, rend, TAX)
    # both labelled: (0,0) 6/6, (0,1) 6/1, (0,2) 1/1, (1,0) 16/16, (1,3) 6/16 -> 3 of 5
    assert a["pixels"] == 5 and a["agree"] == 3
    assert a["agreement"] == pytest.approx(0.6)
    assert a["mask_pixels"] == 6 and a["coverage"] == pytest.approx(5 / 6)
    ids = a["confusion"]["ids"]
    m = np.array(a["confusion"]["matrix"])
    assert m[ids.index(6), ids.index(1)] == 1 and m[ids.index(6), ids.index(16)] == 1
    assert m.sum() == 5
    assert a["per_class"]["grass"]["iou"] == pytest.approx(1 / 3)
    assert a["per_class"]["road"]["iou"] == pytest.approx(1 / 2)
    tot = merge_agreements([a, a])
    assert tot["agreement"] == pytest.approx(0.6) and tot["pixels"] == 10
    img = disagreement_image(mask, rend, TAX)
    assert img.shape == (2, 4, 4)
    assert tuple(img[0, 1]) == (*TAX[1].rgb, 230)  # shows the rendered class where wrong
    assert img[0, 0, 3] == 0 and img[1, 2, 3] == 0 and img[0, 3, 3] == 0
    assert tuple(img[1, 1]) == (128, 128, 128, 96)  # painted but nothing rendered
    with pytest.raises(ValueError):
        agreement(mask, rend[:, :3], TAX)


def test_truth_labels_render_close_to_truth_masks():
    scene, truth = make_scene()
    results = []
    for fi in (5, 9, 16, 18):
        m = truth_mask(scene.frames[fi])
        cls, _ = render_labels(scene, truth, fi)
        results.append(agreement(m, cls, TAX))
        # wrong labels are measurably wrong
        assert agreement(m, np.where(cls > 0, ROAD, 0).astype(np.uint8), TAX)["agreement"] < 0.5
    tot = merge_agreements(results)
    assert tot["agreement"] >= 0.95 and tot["coverage"] >= 0.9


def test_splat_kernels_match_a_plain_reference():
    """The compiled splat passes against per-fragment numpy: nearest depth per pixel, then
    among the front fragments the smallest (d2 * 65536 << 8 | label) key, in float32 as the
    renderer rounds them; overlapping points, splats leaving the image, equal depths."""
    from occufly.splat import splat_pass

    rng = np.random.default_rng(5)
    h, w, m = 30, 40, 400
    uv = np.stack([rng.uniform(-5, w + 5, m), rng.uniform(-5, h + 5, m)], axis=1)
    z = rng.choice(np.float32([2.0, 2.0, 2.5, 3.0, 7.0]), m).astype(np.float32)
    size = rng.integers(1, 9, m).astype(np.int64)
    col0 = np.ceil(uv[:, 0] - size / 2.0 - 0.5).astype(np.int64)
    row0 = np.ceil(uv[:, 1] - size / 2.0 - 0.5).astype(np.int64)
    lab = rng.integers(1, 30, m).astype(np.uint8)
    tol = np.float32(0.3)
    depth = np.full(h * w, np.inf, np.float32)
    best = np.full(h * w, np.iinfo(np.uint64).max, np.uint64)
    splat_pass(depth, best, uv, z, size, col0, row0, lab, tol, h, w, False)
    assert (best == np.iinfo(np.uint64).max).all()  # the depth pass leaves the keys alone
    splat_pass(depth, best, uv, z, size, col0, row0, lab, tol, h, w, True)
    want_d = np.full(h * w, np.inf, np.float32)
    frags = []
    for i in range(m):
        for dy in range(size[i]):
            for dx in range(size[i]):
                r, c = row0[i] + dy, col0[i] + dx
                if 0 <= r < h and 0 <= c < w:
                    frags.append((r * w + c, i, r, c))
                    want_d[r * w + c] = min(want_d[r * w + c], z[i])
    want_b = np.full(h * w, np.iinfo(np.uint64).max, np.uint64)
    for p, i, r, c in frags:
        zf = want_d[p]
        if z[i] <= zf + (tol + np.float32(0.005) * zf):
            d2 = np.float32((c + 0.5 - uv[i, 0]) ** 2 + (r + 0.5 - uv[i, 1]) ** 2)
            key = (int(np.uint64(min(d2 * np.float32(65536.0), np.float32(2.0**31)))) << 8) | int(lab[i])
            want_b[p] = min(int(want_b[p]), key)
    assert np.array_equal(depth, want_d)
    assert np.array_equal(best, want_b)
    assert np.isfinite(depth).sum() > 0.5 * h * w  # the case is not trivially empty


def _disagreement_rgba_reference(mask, rendered, taxonomy):
    """The overlay as it was computed before the palette version (boolean masks per case)."""
    valid = taxonomy.valid_lut()
    m_lab, r_lab = valid[mask], valid[rendered]
    out = np.zeros(mask.shape + (4,), dtype=np.uint8)
    dis = m_lab & r_lab & (mask != rendered)
    out[dis, :3] = taxonomy.colour_lut()[rendered[dis]]
    out[dis, 3] = 230
    out[m_lab & ~r_lab] = (128, 128, 128, 96)
    return out


def test_disagreement_palette_png_decodes_to_the_rgba_overlay():
    import io

    from PIL import Image

    from app.pipeline import encode_png_palette
    from occufly.render import disagreement_indices, disagreement_palette

    rng = np.random.default_rng(5)
    ids = np.concatenate([[0, 255, 200, 77], np.asarray(TAX.ids)])  # 200, 77: no class
    mask = rng.choice(ids, (300, 410)).astype(np.uint8)
    rend = rng.choice(ids, (300, 410)).astype(np.uint8)
    rend[:50] = mask[:50]  # agreement
    ref = _disagreement_rgba_reference(mask, rend, TAX)
    assert np.array_equal(disagreement_image(mask, rend, TAX), ref)
    assert (ref[..., 3] == 230).any() and (ref[..., 3] == 96).any() and (ref[..., 3] == 0).any()
    png = encode_png_palette(disagreement_indices(mask, rend, TAX), disagreement_palette(TAX))
    with Image.open(io.BytesIO(png)) as im:
        assert im.mode == "P"
        assert np.array_equal(np.asarray(im.convert("RGBA")), ref)
