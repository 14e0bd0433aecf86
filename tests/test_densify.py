"""Densification and scene voxelisation (issue 4): analytic cases, exact references, files."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from occufly.densify.carve import (
    CarveParams,
    alpha_silhouette,
    carve_instance,
    circumradius,
    fibonacci_sphere,
    rasterize_triangles,
)
from occufly.densify.dbscan import dbscan, partition_agreement
from occufly.densify.evaluate import evaluate_grids
from occufly.densify.ground import sample_triangles, voxelize_ground
from occufly.densify.pipeline import DensifyOptions, densify, load_point_labels
from occufly.densify.preview import surface_mask
from occufly.densify.voxelize import grid_spec_for, majority_vote
from occufly.errors import InputFormatError
from occufly.grid import SceneGrid
from occufly.taxonomy import default_taxonomy

TAX = default_taxonomy()
IDS = {c.name: c.id for c in TAX.classes}
UTM = np.array([512_345.0, 5_412_678.0, 230.0])


def box_surface(rng, lo, hi, n, *, bottom=False):
    """(n', 3) float64 points uniformly on the faces of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    p = rng.uniform(lo, hi, (n, 3))
    ax = rng.integers(0, 3, n)
    side = rng.integers(0, 2, n)
    p[np.arange(n), ax] = np.where(side == 1, hi[ax], lo[ax])
    if not bottom:
        p = p[~((ax == 2) & (side == 0))]
    return p


def box_voxels(spec, lo, hi):
    """Set of linear keys of the voxels an axis-aligned box intersects."""
    a = np.floor((np.asarray(lo) - spec.local_origin) / spec.voxel_size).astype(int)
    b = np.floor((np.asarray(hi) - spec.local_origin) / spec.voxel_size).astype(int)
    g = np.stack(np.meshgrid(*[np.arange(a[d], b[d] + 1) for d in range(3)], indexing="ij"), -1).reshape(-1, 3)
    return set(spec.linear(g).tolist())


# ---- voxel basics --------------------------------------------------------------------------
def test_majority_vote_counts_and_tie_order():
    prio = TAX.priority_lut()
    keys = np.array([5, 5, 5, 9, 9, 2], np.int64)
    labs = np.array([IDS["road"], IDS["grass"], IDS["road"], IDS["road"], IDS["grass"], IDS["tree"]], np.uint8)
    k, lab, n = majority_vote(keys, labs, prio)
    assert k.tolist() == [2, 5, 9]
    assert n.tolist() == [1, 3, 2]
    # key 9 ties road/grass: grass is more frequent in the taxonomy, so it wins
    assert lab.tolist() == [IDS["tree"], IDS["road"], IDS["grass"]]


def test_grid_spec_is_snapped_to_world_lattice_and_indexes_utm_points():
    xyz = np.array([[0.1, 0.2, 0.3], [10.0, 4.9, 2.0]], np.float32)
    spec = grid_spec_for(xyz.min(0), xyz.max(0), UTM + 0.3, 0.5, pad=1)
    assert np.allclose(spec.origin / 0.5, np.round(spec.origin / 0.5))
    ijk, inside = spec.ijk_of_local(xyz)
    assert inside.all()
    world = UTM + 0.3 + xyz.astype(np.float64)
    assert np.array_equal(ijk, np.floor((world - spec.origin) / 0.5).astype(int))
    assert np.allclose(spec.local_origin, spec.origin - (UTM + 0.3))


# ---- DBSCAN ----------------------------------------------------------------------------------
def _blobs(rng, n_per=1500, k=5, noise=150):
    parts, truth = [], []
    for c in range(k):
        ctr = np.array([c * 11.0, (c % 2) * 8.0, 0.0])
        parts.append(box_surface(rng, ctr, ctr + [4.0, 2.0, 1.5], n_per, bottom=True))
        truth.append(np.full(len(parts[-1]), c))
    parts.append(rng.uniform([-20, -20, 15], [70, 30, 40], (noise, 3)))
    truth.append(np.full(noise, -1))
    return np.concatenate(parts).astype(np.float32), np.concatenate(truth)


def test_dbscan_equals_exact_open3d_dbscan():
    import open3d as o3d

    xyz, truth = _blobs(np.random.default_rng(1))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz.astype(np.float64)))
    ref = np.asarray(pc.cluster_dbscan(eps=1.0, min_points=40))
    assert ref.max() + 1 == 5 and (ref < 0).sum() == 150  # the reference itself is sane
    for cell in (0.0, None):  # exact point-level mode and the default eps/4 cells
        lab = dbscan(xyz, 1.0, 40, cell=cell)
        assert lab.max() + 1 == 5
        assert np.array_equal(lab < 0, ref < 0)
        assert partition_agreement(lab, ref) == 1.0
        assert partition_agreement(lab, truth) == 1.0


def test_dbscan_min_points_and_chain_connectivity():
    # a chain of points 0.9 apart is one cluster at eps=1 and all noise at eps=0.8
    x = np.arange(30) * 0.9
    xyz = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1).astype(np.float32)
    for cell in (0.0, None):
        lab = dbscan(xyz, 1.0, 3, cell=cell)
        assert set(lab.tolist()) == {0}
        assert (dbscan(xyz, 0.8, 2, cell=cell) == -1).all()
    # min_points counts the point itself (Open3D / scikit-learn convention)
    pair = np.array([[0, 0, 0], [0.5, 0, 0]], np.float32)
    assert (dbscan(pair, 1.0, 2, cell=0) == 0).all()
    assert (dbscan(pair, 1.0, 3, cell=0) == -1).all()
    assert len(dbscan(np.zeros((0, 3), np.float32), 1.0, 5)) == 0


def test_partition_agreement_detects_a_split():
    a = np.array([0, 0, 0, 0, 1, 1, -1])
    assert partition_agreement(a, np.array([3, 3, 3, 3, 7, 7, -1])) == 1.0
    assert partition_agreement(a, np.array([3, 3, 4, 4, 7, 7, -1])) == pytest.approx(5 / 7)
    assert partition_agreement(a, np.array([0, 0, 0, 0, 1, 1, 2])) == pytest.approx(6 / 7)


# ---- carving -------------------------------------------------------------------------------
def test_fibonacci_sphere_is_unit_and_spread():
    d = fibonacci_sphere(24)
    assert d.shape == (24, 3)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.linalg.norm(d.mean(axis=0)) < 0.05
    cos = d @ d.T - 2 * np.eye(24)
    min_angle = np.degrees(np.arccos(cos.max()))
    assert min_angle > 35  # 24 well-spread points: nearest neighbours ~ 40 degrees apart


def test_circumradius_and_rasterized_triangle_area():
    tri = np.array([[[0, 0], [40, 0], [0, 30]]], float)  # right triangle, hypotenuse 50
    assert circumradius(tri)[0] == pytest.approx(25.0)
    uv = tri[0] + 0.5  # vertices at pixel centres (0,0), (40,0), (0,30)
    m = alpha_silhouette(uv, (64, 64), alpha=1 / 25.5)  # circumradius 25 < 25.5: kept
    # Pick's theorem: area 600, 80 lattice points on the boundary -> 561 inside + 80 = 641
    assert int(m.sum()) == 641
    assert m[5, 5] and not m[29, 39]
    assert alpha_silhouette(uv, (64, 64), alpha=1 / 24.5).sum() == 3  # dropped: vertices only
    # scan conversion equals a brute-force pixel-centre test on random triangles
    rng = np.random.default_rng(0)
    tris = rng.uniform(-5, 45, (30, 3, 2))
    got = rasterize_triangles(tris, (40, 40))
    yy, xx = np.mgrid[0:40, 0:40] + 0.5
    want = np.zeros((40, 40), bool)
    for t in tris:
        d = [(t[(e + 1) % 3, 0] - t[e, 0]) * (yy - t[e, 1]) - (t[(e + 1) % 3, 1] - t[e, 1]) * (xx - t[e, 0])
             for e in range(3)]
        want |= (np.minimum.reduce(d) >= 0) | (np.maximum.reduce(d) <= 0)
    assert (got != want).sum() <= 3  # only pixel centres exactly on an edge may differ


def test_alpha_shape_convention_bridges_small_gaps_only():
    g = np.stack(np.meshgrid(np.arange(10), np.arange(10)), -1).reshape(-1, 2) * 4.0 + 2.0
    # points every 4 px: triangles have circumradius ~2.83 px
    full = alpha_silhouette(g, (48, 48), alpha=1 / 3.0)  # keep circumradius < 3 px
    assert full[2:38, 2:38].mean() > 0.99
    sparse = alpha_silhouette(g, (48, 48), alpha=1 / 2.5)  # circumradius < 2.5 px: points only
    assert sparse.sum() == 100
    # two far-apart squares are not joined by large triangles
    two = np.concatenate([g[:20] * 0.25, g[:20] * 0.25 + [36, 36]])
    sil = alpha_silhouette(two, (48, 48), alpha=1 / 3.0)
    assert not sil[20:30, 20:30].any()


def test_alpha_silhouette_degenerate_inputs_do_not_crash():
    line = np.stack([np.arange(10) + 0.5, np.full(10, 3.5)], 1)
    sil = alpha_silhouette(line, (8, 16), alpha=0.05)
    assert sil.sum() == 10 and sil[3].sum() == 10
    assert alpha_silhouette(np.zeros((0, 2)), (4, 4), 0.05).sum() == 0


def test_carving_a_box_gives_exactly_its_voxels():
    rng = np.random.default_rng(2)
    lo, hi = np.array([10.1, 10.1, 0.1]), np.array([14.1, 12.1, 1.6])
    pts = box_surface(rng, lo, hi, 20000)  # no bottom face, like an aerial survey
    spec = grid_spec_for(np.zeros(3), np.array([30.0, 30.0, 10.0]), np.zeros(3), 0.5)
    keys = carve_instance(pts.astype(np.float32), spec)
    truth = box_voxels(spec, lo, hi)
    assert set(keys.tolist()) == truth  # 9 x 5 x 4 = 180 voxels, solid inside
    assert len(truth) == 180
    # the points alone only give the shell
    own = np.unique(spec.linear(spec.ijk_of_local(pts)[0]))
    assert len(own) < len(truth) - 20


def test_carving_keeps_concavity_wider_than_alpha_radius():
    # two 6 m towers 80 m apart on a 2 m slab ("U" seen from the side): an empty disk of
    # radius 1/alpha = 20 m fits in the gap, so its middle above the slab stays empty
    rng = np.random.default_rng(3)
    a = box_surface(rng, [0, 0, 0], [6, 6, 12], 8000)
    b = box_surface(rng, [86, 0, 0], [92, 6, 12], 8000)
    s = box_surface(rng, [0, 0, 0], [92, 6, 2], 12000)
    pts = np.concatenate([a, b, s]).astype(np.float32)
    spec = grid_spec_for(pts.min(0), pts.max(0), np.zeros(3), 0.5)
    keys = carve_instance(pts, spec, CarveParams())
    c = spec.centers_local(spec.unravel(keys))
    gap = (c[:, 0] > 31) & (c[:, 0] < 61) & (c[:, 2] > 3)
    assert gap.sum() == 0
    assert ((c[:, 0] < 6) & (c[:, 2] > 6)).sum() > 100


# ---- ground ----------------------------------------------------------------------------------
def test_triangle_samples_respect_spacing():
    v = np.array([[0, 0, 0], [3.0, 0, 0], [0, 2.0, 1.0]])
    s = np.concatenate(list(sample_triangles(v, np.array([[0, 1, 2]]), 0.25, chunk=50)))
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    w = rng.dirichlet([1, 1, 1], 5000)
    q = w @ v
    d, _ = cKDTree(s).query(q)
    assert d.max() <= 0.25 / np.sqrt(3) + 1e-9  # within the circumradius of a lattice cell
    assert np.allclose(s.min(0), [0, 0, 0]) and np.allclose(s.max(0), [3, 2, 1])


def _plane(rng, size=40.0, density=60, hole=None):
    n = int(size * size * density)
    xy = rng.uniform(0, size, (n, 2))
    if hole is not None:
        xy = xy[np.hypot(xy[:, 0] - hole[0], xy[:, 1] - hole[1]) > hole[2]]
    z = np.full(len(xy), 0.2) + rng.normal(0, 0.01, len(xy))
    return np.c_[xy, z].astype(np.float32)


def test_poisson_fills_a_hole_and_votes_ground_classes():
    rng = np.random.default_rng(4)
    xyz = _plane(rng, density=25, hole=(20.0, 20.0, 1.6))
    lab = np.where(xyz[:, 0] < 20, IDS["road"], IDS["grass"]).astype(np.uint8)
    spec = grid_spec_for(np.array([0, 0, 0.0]), np.array([40, 40, 1.0]), np.zeros(3), 0.5)
    prio = TAX.priority_lut()
    pts_only = voxelize_ground(spec, xyz, lab, prio, poisson=False)
    full = voxelize_ground(spec, xyz, lab, prio, poisson=True)
    assert full.stats["method"] == "poisson"
    ijk = spec.unravel(full.keys)
    # the 3.2 m hole: its centre column is empty with points only, filled with Poisson
    col = lambda keys: set(map(tuple, spec.unravel(keys)[:, :2].tolist()))  # noqa: E731
    hole_cols = {(i, j) for i in range(40, 44) for j in range(40, 44)}  # x, y in [19, 21) m
    assert not hole_cols & col(pts_only.keys)
    assert hole_cols <= col(full.keys)
    # labels: columns left of x = 20 m are road, right are grass
    x = spec.centers_local(ijk)[:, 0]
    assert (full.labels[x < 19.5] == IDS["road"]).all()
    assert (full.labels[x > 20.5] == IDS["grass"]).all()
    # the surface stays one layer thick (z = 0.2 lies in one voxel), no bubble survives and
    # beyond the data's rim the surface reaches at most 2 m and only where it continues the
    # data's plane (a flat plane here: the one layer above) ...
    assert set(ijk[:, 2].tolist()) == {int(np.floor((0.2 - spec.local_origin[2]) / 0.5))}
    xy = spec.centers_local(ijk)[:, :2]
    assert xy.min() > -2.5 and xy.max() < 42.5
    # ... and a hole inside is filled up to max_extrapolation (2 m) from the data: a 3.2 m
    # hole closes with the default, stays open in the middle with a 0.3 m limit
    from occufly.densify.ground import PoissonParams

    tight = voxelize_ground(spec, xyz, lab, prio, params=PoissonParams(max_extrapolation=0.3, rim_extrapolation=0.3))
    assert not hole_cols <= col(tight.keys)


# ---- evaluation ------------------------------------------------------------------------------
def test_eval_aligns_by_world_origin_and_counts_exactly():
    lab = np.zeros((6, 5, 4), np.uint8)
    lab[1:3, 1:3, 0] = IDS["road"]
    lab[4, 4, 3] = IDS["vehicle"]
    truth = SceneGrid(lab, UTM, 0.5)
    # same content in a larger grid shifted by (-2, -1, 0) voxels
    big = np.zeros((10, 8, 4), np.uint8)
    big[2:8, 1:6, :] = lab
    pred = SceneGrid(big, UTM - [1.0, 0.5, 0.0], 0.5)
    r = evaluate_grids(pred, truth, TAX)
    assert r["completion_iou"] == 1.0 and r["miou"] == 1.0
    assert r["per_class_iou"]["road"] == 1.0 and r["per_class_iou"]["tree"] is None
    # one FP road voxel outside the truth extent, one FN vehicle voxel
    big[0, 0, 0] = IDS["road"]
    big[6, 5, 3] = 0
    r = evaluate_grids(SceneGrid(big, pred.origin, 0.5), truth, TAX, region="union")
    assert r["per_class_iou"]["road"] == pytest.approx(4 / 5)
    assert r["per_class_iou"]["vehicle"] == 0.0
    assert r["completion_iou"] == pytest.approx(4 / 6)
    assert r["miou"] == pytest.approx(0.4)
    # default: only the truth's extent is judged; the outside voxel is counted, not an FP
    r = evaluate_grids(SceneGrid(big, pred.origin, 0.5), truth, TAX)
    assert r["per_class_iou"]["road"] == 1.0 and r["pred_voxels_outside_truth"] == 1
    assert r["completion_iou"] == pytest.approx(4 / 5) and r["miou"] == pytest.approx(0.5)
    with pytest.raises(InputFormatError, match="lattice"):
        evaluate_grids(SceneGrid(big, pred.origin + 0.2, 0.5), truth, TAX)
    with pytest.raises(InputFormatError, match="voxel size"):
        evaluate_grids(SceneGrid(big, pred.origin, 0.25), truth, TAX)


# ---- the whole densification on a small analytic scene ----------------------------------------
def _scene(rng):
    """Ground plane with two classes, two vehicles, a ground obstacle; and the solid truth."""
    ground = _plane(rng, size=40.0, density=40)
    glab = np.where(ground[:, 1] < 20, IDS["road"], IDS["parking_lot"]).astype(np.uint8)
    cars = [(np.array([8.1, 8.1, 0.3]), np.array([12.6, 10.1, 1.8])),
            (np.array([25.1, 28.1, 0.3]), np.array([29.6, 30.1, 1.8]))]
    cp = [box_surface(rng, lo, hi, 12000) for lo, hi in cars]
    obst = rng.uniform([30.1, 5.1, 0.3], [30.4, 5.4, 1.3], (200, 3))
    xyz = np.concatenate([ground, *cp, obst]).astype(np.float32)
    labels = np.concatenate([glab, np.full(sum(len(c) for c in cp), IDS["vehicle"]),
                             np.full(len(obst), IDS["ground_obstacle"])]).astype(np.uint8)
    return xyz, labels, cars


def test_densify_precedence_carving_and_report():
    rng = np.random.default_rng(5)
    xyz, labels, cars = _scene(rng)
    res = densify(xyz, labels, TAX, scene_origin=UTM, options=DensifyOptions(poisson=False))
    g, rep = res.grid, res.report
    from occufly.densify.pipeline import spec_of_grid

    spec = spec_of_grid(g, UTM)
    flat = g.labels.reshape(-1)
    for lo, hi in cars:  # each car is carved solid and labelled vehicle
        truth = np.array(sorted(box_voxels(spec, lo, hi)))
        inner = truth[spec.centers_local(spec.unravel(truth))[:, 2] > 0.5]
        assert (flat[inner] == IDS["vehicle"]).all()
    assert rep["instances"]["vehicle"]["instances"] == 2
    assert rep["voxels_per_class"]["ground_obstacle"] >= 1
    assert rep["voxels_per_class"]["vehicle"] == rep["voxels_per_stage"]["instance_carved"] or (
        rep["voxels_per_class"]["vehicle"] >= 2 * 9 * 4 * 3
    )
    assert set(rep["timings_s"]) >= {"groups", "instances", "other", "ground", "aggregate", "total"}
    assert np.allclose(g.origin / 0.5, np.round(g.origin / 0.5))
    # ablation: without carving the cars are hollow shells
    shell = densify(xyz, labels, TAX, scene_origin=UTM, options=DensifyOptions(carve=False, poisson=False))
    assert shell.grid.class_counts()[IDS["vehicle"]] < g.class_counts()[IDS["vehicle"]]
    # precedence: a vehicle point inside a road voxel wins that voxel
    both = np.array([[5.1, 35.1, 0.21], [5.2, 35.2, 0.22], [5.3, 35.3, 0.23]], np.float32)
    r2 = densify(np.concatenate([xyz, both]), np.concatenate([labels, [IDS["road"], IDS["road"], IDS["person"]]]).astype(np.uint8),
                 TAX, scene_origin=UTM, options=DensifyOptions(poisson=False))
    assert r2.grid.lookup(UTM + both[2].astype(float))[0] == IDS["person"]


def test_surface_density_and_auto_min_points_scale(caplog):
    from occufly.densify.pipeline import REFERENCE_SURFACE_DENSITY, surface_density

    rng = np.random.default_rng(8)
    plane = np.c_[rng.uniform(0, 30, (27000, 2)), np.zeros(27000)].astype(np.float32)  # 30 / m^2
    assert surface_density(plane) == pytest.approx(30.0, rel=0.15)
    # a sparse car (~40 points/m^2): the table's minPts (500 within 1 m) makes it noise ...
    car = box_surface(rng, [5.1, 5.1, 0.1], [9.6, 7.1, 1.6], 1500).astype(np.float32)
    lab = np.full(len(car), IDS["vehicle"], np.uint8)
    fixed = _bad(car, lab, caplog, min_points_scale=1.0)
    assert fixed.report["instances"]["vehicle"]["instances"] == 0
    assert any("--min-points-scale auto" in m for m in fixed.report["warnings"])
    # ... "auto" (the default) scales minPts by density / reference and carves one instance
    auto = _bad(car, lab, caplog)
    assert DensifyOptions().min_points_scale is None
    st = auto.report["instances"]["vehicle"]
    scale = auto.report["options"]["min_points_scale"]
    assert scale == pytest.approx(auto.report["options"]["surface_density_per_m2"] / REFERENCE_SURFACE_DENSITY)
    assert st["min_points"] == max(2, round(500 * scale)) and st["instances"] == 1
    assert auto.grid.class_counts()[IDS["vehicle"]] > fixed.grid.class_counts()[IDS["vehicle"]]


# ---- bad input -----------------------------------------------------------------------------------
def _bad(xyz, labels, caplog, **kw):
    with caplog.at_level(logging.WARNING, logger="occufly.densify"):
        res = densify(np.asarray(xyz, np.float32), np.asarray(labels, np.uint8), TAX, options=DensifyOptions(**kw))
    return res


def test_instance_with_three_points_is_binned_with_warning(caplog):
    xyz = [[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.05]]
    # the table's minPts (10): DBSCAN noise, binned
    res = _bad(xyz, [IDS["person"]] * 3, caplog, min_points_scale=1.0)
    assert res.grid.class_counts() == {IDS["person"]: 1}
    assert any("noise" in m for m in res.report["warnings"])
    assert any("person" in r.message for r in caplog.records)
    # auto minPts (scaled down to 2 on this sparse input): one cluster, too small to carve, binned
    res = _bad(xyz, [IDS["person"]] * 3, caplog)
    assert res.grid.class_counts() == {IDS["person"]: 1}
    assert any("degenerate" in m and "3 distinct points" in m for m in res.report["warnings"])


def test_flat_and_collinear_instances_fall_back_to_direct_binning(caplog):
    rng = np.random.default_rng(6)
    flat = np.c_[rng.uniform(0, 4, (8000, 2)), np.full(8000, 1.2)]  # a horizontal plate
    line = np.c_[np.linspace(10, 20, 2000), np.full(2000, 3.0), np.full(2000, 1.0)]
    xyz = np.concatenate([flat, line])
    labels = [IDS["vehicle"]] * 8000 + [IDS["bicycle"]] * 2000
    res = _bad(xyz, labels, caplog)
    msgs = " ".join(res.report["warnings"])
    assert "flat" in msgs and "collinear" in msgs
    spec_counts = res.grid.class_counts()
    direct = _bad(xyz, labels, caplog, carve=False).grid.class_counts()
    assert spec_counts == direct  # exactly the direct voxelization
    assert spec_counts[IDS["vehicle"]] == 64 and spec_counts[IDS["bicycle"]] == 21


def test_ground_with_too_few_points_for_poisson_is_binned(caplog):
    xyz = np.c_[np.arange(20) * 0.5 + 0.1, np.full(20, 0.1), np.full(20, 0.1)]
    res = _bad(xyz, [IDS["grass"]] * 20, caplog)
    assert res.grid.class_counts() == {IDS["grass"]: 20}
    assert any("Poisson" in m for m in res.report["warnings"])
    assert res.report["ground"]["method"] == "points"


def test_empty_classes_unknown_ids_and_no_labels(caplog):
    xyz = np.array([[0.1, 0.1, 0.1], [3.1, 0.1, 0.1], [6.1, 0.1, 0.1]])
    res = _bad(xyz, [IDS["tree"], 77, 0], caplog)  # every other class is empty
    assert res.grid.class_counts() == {IDS["tree"]: 1}
    assert any("77" in m for m in res.report["warnings"])
    with pytest.raises(InputFormatError, match="no point carries a class"):
        densify(np.asarray(xyz, np.float32), np.zeros(3, np.uint8), TAX)
    with pytest.raises(InputFormatError, match="expected shape"):
        densify(np.asarray(xyz, np.float32), np.zeros(4, np.uint8), TAX)


def test_load_point_labels_checks_file(tmp_path):
    p = tmp_path / "l.npy"
    with pytest.raises(InputFormatError, match="not found"):
        load_point_labels(p, 3)
    np.save(p, np.array([1, 2], np.uint8))
    with pytest.raises(InputFormatError, match=r"expected shape \(3,\)"):
        load_point_labels(p, 3)
    np.save(p, np.array([1.0, 2.0, 3.0]))
    with pytest.raises(InputFormatError, match="integer"):
        load_point_labels(p, 3)
    np.save(p, np.array([1, 2, 16], np.int64))
    assert load_point_labels(p, 3).dtype == np.uint8


# ---- preview and CLI round trip through real files ------------------------------------------------
def test_surface_mask_of_a_solid_cube():
    lab = np.zeros((6, 6, 6), np.uint8)
    lab[1:5, 1:5, 1:5] = 8
    assert surface_mask(lab).sum() == 64 - 8


def test_cli_voxelize_eval_preview_round_trip(tmp_path):
    from PIL import Image

    from occufly.cli import main
    from occufly.scene import Scene

    rng = np.random.default_rng(7)
    xyz, labels, _ = _scene(rng)
    ws = tmp_path / "ws"
    Scene(frames=[], xyz=xyz, rgb=np.zeros_like(xyz, dtype=np.uint8), origin=UTM, taxonomy=TAX).save(ws)
    np.save(tmp_path / "labels.npy", labels)
    out = tmp_path / "out.json"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = main(["voxelize", str(ws), "--labels", str(tmp_path / "labels.npy"), "--json",
                   "--preview", str(tmp_path / "p.png")])
    assert rc == 0
    rep = json.loads(buf.getvalue())
    out.write_text(buf.getvalue())
    grid = SceneGrid.load(ws / "grid" / "scene_grid.npz")
    assert rep["voxels_per_class"]["vehicle"] == grid.class_counts()[IDS["vehicle"]]
    assert (ws / "grid" / "scene_grid_report.json").is_file()
    # evaluating the grid against itself (saved elsewhere) is perfect
    grid.save(tmp_path / "truth.npz")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["eval-grid", str(ws), "--truth", str(tmp_path / "truth.npz"), "--json"]) == 0
    ev = json.loads(buf.getvalue())
    assert ev["completion_iou"] == 1.0 and ev["miou"] == 1.0 and ev["classes_evaluated"] == 4
    # without --truth: WS/truth/scene_grid.npz, or exit 2 naming the missing file
    assert main(["eval-grid", str(ws), "--json"]) == 2
    grid.save(ws / "truth" / "scene_grid.npz")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["eval-grid", str(ws), "--json"]) == 0
    assert json.loads(buf.getvalue())["truth"] == str(ws / "truth" / "scene_grid.npz")
    img = np.asarray(Image.open(tmp_path / "p.png").convert("RGB"))
    assert img.shape[0] > 100 and img.shape[1] > 200
    vehicle_rgb = np.array(TAX[IDS["vehicle"]].rgb)
    # some pixels carry the (shaded) vehicle hue: teal, green == blue, no red
    teal = (img[..., 0] < 20) & (np.abs(img[..., 1].astype(int) - img[..., 2]) < 3) & (img[..., 1] > 40)
    assert teal.sum() > 50 and vehicle_rgb[0] == 0
    # a missing labels file is a user error: exit 2 with the path in the message
    assert main(["voxelize", str(ws), "--json"]) == 2


# ---- surface denoising, ground thinning, free space -------------------------------------------
def test_project_to_planes_removes_normal_noise_and_keeps_the_surface():
    from occufly.densify.smooth import project_to_planes

    rng = np.random.default_rng(11)
    n = 20_000
    xy = rng.uniform(0, 20, (n, 2))
    z_true = 0.1 * xy[:, 0] + 2.0  # a tilted plane
    xyz = np.column_stack([xy, z_true + rng.normal(0, 0.15, n)])
    out = project_to_planes(xyz, 1.0)
    res_before = xyz[:, 2] - z_true
    res_after = out[:, 2] - (0.1 * out[:, 0] + 2.0)
    assert res_before.std() > 0.14
    assert res_after.std() < 0.5 * res_before.std()  # k = 24 neighbours: ~0.4 measured
    assert abs(res_after.mean()) < 0.005  # no bias
    # points move (nearly) along the surface normal (-0.1, 0, 1), not along the surface
    d = out - xyz
    nrm = np.array([-0.1, 0.0, 1.0]) / np.linalg.norm([-0.1, 0.0, 1.0])
    along = np.abs(d @ nrm)
    tangential = np.linalg.norm(d - (d @ nrm)[:, None] * nrm, axis=1)
    assert np.median(tangential) < 0.25 * np.median(along)
    # too few neighbours within the radius: the point stays where it is
    lone = np.array([[100.0, 100.0, 100.0]])
    assert np.array_equal(project_to_planes(np.concatenate([xyz, lone]), 1.0)[-1], lone[0])


def test_plane_offsets_measure_distance_to_the_local_data_plane():
    from occufly.densify.smooth import plane_offsets

    rng = np.random.default_rng(14)
    xy = rng.uniform(0, 10, (5000, 2))
    data = np.column_stack([xy, 0.2 * xy[:, 0] + 1.0])  # z = 0.2 x + 1
    q = np.array([[5.0, 5.0, 2.0 + 0.5], [5.0, 5.0, 2.0], [11.0, 5.0, 3.2 + 1.0], [50.0, 50.0, 0.0]])
    off, nrm, ok = plane_offsets(data, q, 3.0)
    cos = 1 / np.sqrt(1 + 0.2**2)  # the normal's z component
    assert ok.tolist() == [True, True, True, False]
    assert abs(nrm[0, 2]) == pytest.approx(cos, abs=1e-6)
    vertical = off[:3] / nrm[:3, 2]
    assert vertical == pytest.approx([0.5, 0.0, 1.0], abs=1e-6)  # 1 m beyond the rim: still the plane
    assert off[3] == 0.0


def test_ground_thinning_has_no_bias_that_follows_the_voxel_lattice():
    """3-D cube thinning pulls centroids towards cube faces; the column thinning does not."""
    from occufly.densify.ground import thin_ground

    rng = np.random.default_rng(12)
    vs = 0.5
    for frac in (0.05, 0.25, 0.5, 0.75, 0.95):
        h = 10.0 + frac * vs
        xy = rng.uniform(0, 10, (40_000, 2))
        pts = np.column_stack([xy, h + rng.normal(0, 0.18, len(xy))])
        pts[0] = [0.0, 0.0, 9.0]  # pins the thinning lattice to z = 9 + k * vs
        cen, w = thin_ground(pts, vs, 2.0 * vs)
        assert w.sum() == len(pts)
        err = np.average(cen[1:, 2] - h, weights=w[1:])
        assert abs(err) < 0.01, (frac, err)
        assert np.abs(cen[w > 20, 2] - h).max() < 0.2
    # a second layer (a bridge deck 5 m above, sampled like the ground) stays a separate set
    # of centroids; a few mislabelled points on a wall (sparse, 1.5 m up) are dropped
    up = np.column_stack([rng.uniform(0, 5, (10_000, 2)), np.full(10_000, h + 5.0)])
    wall = np.column_stack([np.full(60, 7.6), rng.uniform(2, 8, 60), h + rng.uniform(1.2, 2.0, 60)])
    cen, w = thin_ground(np.concatenate([pts, up, wall]), vs, 2.0 * vs, min_support=0.25)
    assert (cen[:, 2] > h + 4.5).sum() > 80 and (np.abs(cen[:, 2] - h) < 0.3).sum() > 300
    assert not ((cen[:, 2] > h + 1.0) & (cen[:, 2] < h + 2.5)).any()
    cen0, _ = thin_ground(np.concatenate([pts, up, wall]), vs, 2.0 * vs)  # support rule off
    assert ((cen0[:, 2] > h + 1.0) & (cen0[:, 2] < h + 2.5)).sum() > 5


def _survey(xyz: np.ndarray):
    """Frames over a scene (nadir + obliques) and their z-buffer visibility of ``xyz``."""
    from occufly.camera import Camera, look_at, project_world
    from occufly.scene import Frame, Visibility
    from occufly.visibility import render_depth

    cam = Camera("PINHOLE", 400, 300, np.array([300.0, 300.0, 200.0, 150.0]))
    c = xyz.mean(axis=0)
    frames, parts = [], []
    for dx, dy in [(0, 0), (-25, 0), (25, 0), (0, -25), (0, 25), (-18, -18), (18, 18), (-18, 18), (18, -18)]:
        centre = c + np.array([dx, dy, 40.0])
        T = look_at(centre, c, up=(0.0, 1.0, 0.0))
        uv, z, vis = project_world(cam, T, xyz)
        idx = np.flatnonzero(vis)
        zbuf = render_depth(cam, uv[idx], z[idx], 1.0)
        front = z[idx] <= zbuf[uv[idx, 1].astype(int), uv[idx, 0].astype(int)] + 0.3
        idx = idx[front]
        frames.append(Frame(f"f{len(frames)}.jpg", cam, T))
        parts.append((idx.astype(np.int32), uv[idx], z[idx]))
    return frames, Visibility.from_parts(parts)


def test_free_space_removes_the_hull_between_two_merged_boxes_and_keeps_solids():
    from occufly.densify.freespace import FrameDepths
    from occufly.densify.pipeline import spec_of_grid

    rng = np.random.default_rng(13)
    ground = _plane(rng, size=40.0, density=40)
    # two buildings 3 m apart: one DBSCAN instance at eps 4 m, their hull bridges the gap
    boxes = [(np.array([10.1, 12.1, 0.0]), np.array([18.1, 28.1, 6.0])),
             (np.array([21.1, 12.1, 0.0]), np.array([29.1, 28.1, 9.0]))]
    walls = [box_surface(rng, lo, hi, 30_000) for lo, hi in boxes]
    xyz = np.concatenate([ground, *walls]).astype(np.float32)
    labels = np.concatenate([np.full(len(ground), IDS["road"]),
                             np.full(sum(len(w) for w in walls), IDS["building"])]).astype(np.uint8)
    frames, vis = _survey(xyz.astype(np.float64))
    opts = DensifyOptions(poisson=False, smooth_radius=0.0)
    plain = densify(xyz, labels, TAX, scene_origin=UTM, options=opts)
    views = FrameDepths(frames, vis, 0.5)
    free = densify(xyz, labels, TAX, scene_origin=UTM, options=opts, views=views)
    assert plain.report["instances"]["building"]["instances"] == 1
    assert free.report["options"]["free_space"] and not plain.report["options"]["free_space"]

    def gap_voxels(res):
        spec = spec_of_grid(res.grid, UTM)
        keys = np.flatnonzero(res.grid.labels.reshape(-1) == IDS["building"])
        c = spec.centers_local(spec.unravel(keys))
        return int(((c[:, 0] > 18.7) & (c[:, 0] < 20.5) & (c[:, 1] > 13) & (c[:, 1] < 27) & (c[:, 2] > 1)).sum())

    assert gap_voxels(plain) > 100  # the hull fills the alley between the buildings
    assert gap_voxels(free) < 0.1 * gap_voxels(plain)
    assert free.report["voxels_per_stage"]["instance_free_space_removed"] > 0
    # culling voxels by each frame's frustum box changes no vote
    rng2 = np.random.default_rng(3)
    c = rng2.uniform(xyz.min(axis=0) - 5, xyz.max(axis=0) + [5, 5, 30], (20_000, 3))
    f1, s1 = views.votes(c)
    views.frames = [(cam, T, r, (np.full(3, -1e9), np.full(3, 1e9))) for cam, T, r, _ in views.frames]
    f2, s2 = views.votes(c)
    assert f1.sum() > 1000 and s1.sum() > 100
    assert np.array_equal(f1, f2) and np.array_equal(s1, s2)
    # the buildings themselves stay solid: every voxel centre inside a box is still building
    spec = spec_of_grid(free.grid, UTM)
    flat = free.grid.labels.reshape(-1)
    for lo, hi in boxes:
        inner = np.array(sorted(box_voxels(spec, lo + 0.3, hi - 0.3)))
        inner = inner[spec.centers_local(spec.unravel(inner))[:, 2] > 0.5]
        assert (flat[inner] == IDS["building"]).mean() > 0.99


def test_frame_depth_rasters_projected_on_demand_match_the_numpy_path():
    """A workspace's visibility stores only point ids (uv/depth projected on demand): the
    compiled per-frame raster equals the numpy projection's, pixel for pixel; a camera with
    distortion keeps the numpy path."""
    from occufly.camera import Camera
    from occufly.densify.freespace import FrameDepths
    from occufly.scene import Frame, Visibility

    rng = np.random.default_rng(4)
    xyz = np.concatenate([_plane(rng, size=40.0, density=20),
                          box_surface(rng, np.array([10.0, 12.0, 0.0]), np.array([18.0, 28.0, 6.0]), 5000)])
    xyz = xyz.astype(np.float32)
    frames, stored = _survey(xyz.astype(np.float64))
    frames[3] = Frame(frames[3].name, Camera("SIMPLE_RADIAL", 400, 300, np.array([300.0, 200.0, 150.0, 0.02])),
                      frames[3].T_cam_world)
    lazy = Visibility(stored.offsets, stored.point_ids)
    lazy.bind(frames, xyz)
    assert lazy.projected_on_demand() is not None

    class NumpyOnly:  # the same visibility, without the compiled path
        def projected_on_demand(self):
            return None

        def frame(self, f):
            return lazy.frame(f)

    fast, slow = FrameDepths(frames, lazy, 0.5), FrameDepths(frames, NumpyOnly(), 0.5)
    assert len(fast.frames) == len(slow.frames) == len(frames)
    for (c1, t1, r1, b1), (c2, t2, r2, b2) in zip(fast.frames, slow.frames, strict=True):
        assert np.array_equal(t1, t2)
        assert (c1.width, c1.height) == (c2.width, c2.height)
        assert np.array_equal(r1, r2) and np.isfinite(r1).mean() > 0.3
        assert np.array_equal(b1[0], b2[0]) and np.array_equal(b1[1], b2[1])


def test_a_grid_too_large_for_memory_is_a_clear_error_not_a_crash():
    xyz = np.array([[0.0, 0.0, 0.0], [100.0, 100.0, 30.0], [50.0, 50.0, 1.0]], np.float32)
    labels = np.array([IDS["grass"]] * 3, np.uint8)
    with pytest.raises(InputFormatError, match=r"voxel size 0.005 m: .* use a larger --voxel"):
        densify(xyz, labels, TAX, options=DensifyOptions(voxel_size=0.005))
    assert densify(xyz, labels, TAX, options=DensifyOptions(voxel_size=0.5)).grid.class_counts() == {IDS["grass"]: 3}


def test_class_counts_are_exact_across_chunks():
    lab = np.zeros((300, 300, 200), np.uint8)  # 18 M voxels: more than one 16 M chunk
    lab[0, 0, :7] = 6
    lab[-1, -1, -5:] = 16
    assert SceneGrid(lab, np.zeros(3), 0.5).class_counts() == {6: 7, 16: 5}


def test_voxelize_that_cannot_fit_in_memory_exits_2_before_writing(tmp_path, monkeypatch, capsys):
    from occufly.cli import main
    from occufly.densify import pipeline
    from occufly.scene import Scene

    rng = np.random.default_rng(7)
    xyz, labels, _ = _scene(rng)
    ws = tmp_path / "ws"
    Scene(frames=[], xyz=xyz, rgb=np.zeros_like(xyz, dtype=np.uint8), origin=UTM, taxonomy=TAX).save(ws)
    np.save(tmp_path / "labels.npy", labels)
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: 100 * 2**20)
    rc = main(["voxelize", str(ws), "--labels", str(tmp_path / "labels.npy")])
    assert rc == 2
    err = capsys.readouterr().err
    assert f"densifying {len(xyz):,} points" in err and "0.1 GB are available" in err
    assert not (ws / "grid" / "scene_grid.npz").exists()
    est = pipeline.densify_memory_estimate(10**6, 10**7) - pipeline.densify_memory_estimate(0, 0)
    assert est == 10**6 * pipeline.DENSIFY_BYTES_PER_POINT + 10**7 * pipeline.DENSIFY_BYTES_PER_VOXEL


def test_poisson_ground_mesh_is_reproducible():
    """The same ground cloud gives the same mesh bytes on every run (multi-threaded
    PoissonRecon gave a different mesh on each of three runs of this cloud)."""
    import hashlib

    from occufly.densify.ground import poisson_mesh

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 40, (40_000, 2))
    z = np.sin(xy[:, 0] / 6) + 0.3 * np.cos(xy[:, 1] / 5) + rng.normal(0, 0.02, len(xy))
    pts = np.c_[xy, z].astype(np.float32)
    digests = set()
    for _ in range(3):
        verts, tris, _stats = poisson_mesh(pts, 0.2)
        digests.add(hashlib.sha1(verts.tobytes() + tris.tobytes()).hexdigest())
    assert len(digests) == 1
