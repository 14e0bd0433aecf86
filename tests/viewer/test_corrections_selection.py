"""The viewer's vectorised selection tools (app.viewer.selection) and the scene grid's level of
detail (app.viewer.grid_lod), against analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from app.viewer import grid_lod
from app.viewer import selection as sel
from app.viewer.scene_builder import matrix_to_quat, points_in_screen_rect, surface_mask


def _nadir():
    # a camera 50 m above the origin looking down (-z world), image x = world x, y = -world y
    R = np.array([[1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]])  # camera axes in world
    return np.array([0.0, 0.0, 50.0]), matrix_to_quat(R), np.deg2rad(60.0), 1.5


def test_polygon_matches_rectangle_and_a_concave_lasso():
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(-40, 40, (20000, 2)), np.zeros(20000)].astype(np.float32)
    pos, wxyz, fov, asp = _nadir()
    rect = sel.rectangle(xyz, pos, wxyz, fov, asp, (0.3, 0.2), (0.7, 0.6))
    ref = points_in_screen_rect(xyz, pos, wxyz, fov, asp, (0.3, 0.2), (0.7, 0.6))
    assert rect.sum() > 1000 and (rect == ref).mean() > 0.999
    # an L-shaped lasso: the rectangle minus its top-right quarter
    L = np.array([[0.3, 0.2], [0.5, 0.2], [0.5, 0.4], [0.7, 0.4], [0.7, 0.6], [0.3, 0.6]])
    u, v, front = sel.project_to_screen(xyz, pos, wxyz, fov, asp)
    got = sel.lasso(xyz, pos, wxyz, fov, asp, L)
    quarter = (u > 0.5) & (v < 0.4)
    assert (got == (ref & ~quarter)).mean() > 0.999
    assert not (got & quarter).any()
    behind = xyz + np.float32([0, 0, 100])  # above the camera: never selected
    assert not sel.lasso(behind, pos, wxyz, fov, asp, L).any()
    with pytest.raises(ValueError):
        sel.points_in_polygon(u, v, L[:2])


def test_grow_takes_the_connected_region_of_one_class():
    # two grass patches 10 m apart and a road strip touching the first
    g = np.arange(0, 5, 0.5)
    xx, yy = np.meshgrid(g, g)
    a = np.c_[xx.ravel(), yy.ravel(), np.zeros(xx.size)]
    b = a + [10, 0, 0]
    road = a + [0, 5, 0]
    xyz = np.r_[a, b, road].astype(np.float32)
    lab = np.r_[np.full(len(a), 6), np.full(len(b), 6), np.full(len(road), 1)].astype(np.uint8)
    region = sel.grow(xyz, lab, seed=3, voxel=1.0)
    assert region.sum() == len(a) and region[: len(a)].all()
    region_b = sel.grow(xyz, lab, seed=len(a) + 5, voxel=1.0)
    assert region_b.sum() == len(b) and region_b[len(a): 2 * len(a)].all()


def test_brush_hits_the_first_surface_along_the_ray_and_filters_and_modes():
    g = np.arange(-5, 5.01, 0.25)
    xx, yy = np.meshgrid(g, g)
    ground = np.c_[xx.ravel(), yy.ravel(), np.zeros(xx.size)]
    roof = ground[(np.abs(ground[:, 0]) < 2) & (np.abs(ground[:, 1]) < 2)] + [0, 0, 6]
    xyz = np.r_[ground, roof].astype(np.float32)
    picked = sel.brush(xyz, [0.0, 0.0, 50.0], [0.0, 0.0, -1.0], radius=1.0)
    assert picked.sum() > 10 and (xyz[picked, 2] == 6).all()  # the roof, not the ground
    h = sel.height_above_ground(xyz, cell=20.0)
    f = sel.Filters(min_height=3.0)
    assert (f.mask(xyz, None, None, h) == (xyz[:, 2] > 3)).all()
    labels = np.r_[np.full(len(ground), 6), np.full(len(roof), 17)].astype(np.uint8)
    assert sel.Filters(classes={17}).mask(xyz, labels, None).sum() == len(roof)
    cur = np.array([1, 2, 3])
    assert sel.combine(cur, [3, 4], "add").tolist() == [1, 2, 3, 4]
    assert sel.combine(cur, [3, 4], "subtract").tolist() == [1, 2]
    assert sel.combine(cur, [4, 3], "replace").tolist() == [3, 4]
    assert sel.class_counts(labels, np.arange(len(xyz))) == {6: len(ground), 17: len(roof)}


def test_grid_lod_fits_the_budget_and_leaves_no_holes():
    lab = np.zeros((128, 128, 32), np.uint8)
    lab[:, :, :4] = 6  # ground slab
    lab[20:60, 30:70, 4:20] = 16  # a building
    lab[5, 5, 5] = 255
    occ = (lab != 0) & (lab != 255)
    assert surface_mask(occ).sum() > 20_000
    coarse, level = grid_lod.lod_level(lab, max_boxes=5_000)
    assert level >= 1 and surface_mask(coarse > 0).sum() <= 5_000
    f = 2 ** level
    ijk = np.argwhere(occ)  # every occupied voxel lies in an occupied coarse voxel
    assert (coarse[ijk[:, 0] // f, ijk[:, 1] // f, ijk[:, 2] // f] > 0).all()
    # majority: a block of the building keeps the building's class
    assert coarse[40 // f, 50 // f, 10 // f] == 16
    assert grid_lod.coarsen(np.array([[[6, 6], [6, 0]], [[16, 255], [0, 0]]], np.uint8))[0, 0, 0] == 6


def test_combine_is_the_set_operation_for_sorted_and_unsorted_picks():
    """combine skips the sort of a pick that is sorted already (the tools' picks, 1 M ids and
    more); an unsorted pick with repeats gives the same sets."""
    rng = np.random.default_rng(5)
    for mode in sel.MODES:
        for _ in range(60):
            cur = np.unique(rng.integers(0, 100, rng.integers(0, 60)))
            pick = rng.integers(0, 100, rng.integers(0, 60))
            want = {"replace": np.unique(pick), "add": np.union1d(cur, pick),
                    "subtract": np.setdiff1d(cur, pick)}[mode]
            assert np.array_equal(sel.combine(cur, pick, mode), want)
            assert np.array_equal(sel.combine(cur, np.unique(pick), mode), want)
