"""The synthetic aerial scene: files, exact truth, determinism, COLMAP readability."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from occufly.camera import Camera, camera_center, project_world
from occufly.cli import main as cli_main
from occufly.grid import SceneGrid
from occufly.io.colmap_dense import read_depth_map, read_fused_ply, read_fused_vis
from occufly.synthetic import PRESETS, generate
from occufly.synthetic.flight import make_camera, plan_flight
from occufly.synthetic.primitives import Box
from occufly.synthetic.render import Renderer
from occufly.synthetic.truth import column_terrain_range, survey_views
from occufly.synthetic.world import BUILDING, ROOF, WATER, build_world
from occufly.taxonomy import default_taxonomy

SEED = 0


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> dict:
    """Generate ``tiny`` once through the CLI (``--json``) and return its paths and truth."""
    out = tmp_path_factory.mktemp("synth") / "tiny"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = cli_main(["synth", str(out), "--preset", "tiny", "--seed", str(SEED), "--json"])
    assert rc == 0
    summary = json.loads(buf.getvalue())
    meta = json.loads((out / "truth" / "meta.json").read_text())
    world = build_world(PRESETS["tiny"], SEED)
    return {"out": out, "summary": summary, "meta": meta, "world": world,
            "renderer": Renderer(world, SEED), "offset": np.array(meta["world_offset"])}


def _colmap(out: Path):
    import pycolmap

    return pycolmap.Reconstruction(str(out / "sparse"))


def _local_poses(rec, offset: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """(name, (4, 4) local world-to-camera) for the images sorted by image id."""
    poses = []
    for iid in sorted(rec.images):
        im = rec.image(iid)
        T = np.eye(4)
        T[:3, :4] = im.cam_from_world().matrix()
        T[:3, 3] = T[:3, 3] + T[:3, :3] @ offset  # world -> local translation
        poses.append((im.name, T))
    return poses


def _camera(rec) -> Camera:
    cam = rec.camera(1)
    return Camera("PINHOLE", cam.width, cam.height, np.asarray(cam.params))


# ---- layout, summary -------------------------------------------------------------------------
def test_layout_counts_and_classes(synth):
    out, s, meta = synth["out"], synth["summary"], synth["meta"]
    n = s["frames"]
    assert 30 <= n <= 40 and meta["frames"] == meta["n_frames"] == n
    assert meta["n_points"] == s["points"]
    images = sorted((out / "images").iterdir())
    assert [p.name for p in images] == [f"frame_{i:06d}.png" for i in range(n)]
    assert len(list((out / "truth" / "masks").glob("*.png"))) == n
    assert len(list((out / "dense" / "stereo" / "depth_maps").glob("*.geometric.bin"))) == n
    all_ids = sorted(int(i) for i in default_taxonomy().ids)
    for where in ("world", "masks", "points", "grid"):
        assert meta["classes_present"][where] == all_ids, where
    assert s["classes_present"] == meta["classes_present"]
    assert 20_000 <= s["points"] <= 60_000
    # the flight: 3 altitudes, two perpendicular passes, nadir and both oblique pitches
    fd = meta["frames_detail"]
    assert {f["nominal_altitude"] for f in fd} == {50, 40, 30}
    assert {f["pass"] for f in fd} == {0, 1}
    assert {f["pitch_deg"] for f in fd} == {-90.0, -75.0, -70.0}
    for f in fd:
        assert abs(f["altitude_above_ground"] - f["nominal_altitude"]) < 3.0
        assert f["center_world"][0] > 500_000 and f["center_world"][1] > 5_400_000


def test_refuses_nonempty_out_and_leaves_nothing_when_interrupted(synth, tmp_path, capsys):
    rc = cli_main(["synth", str(synth["out"]), "--preset", "tiny"])
    assert rc == 2
    assert "not empty" in capsys.readouterr().err

    target = tmp_path / "interrupted"

    def boom(fraction: float, _msg: str = "") -> None:
        if fraction > 0.2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        generate(target, preset="tiny", seed=SEED, progress=boom)
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []  # no .partial leftovers


# ---- COLMAP model -----------------------------------------------------------------------------
def test_colmap_model_is_readable_and_consistent(synth):
    rec = _colmap(synth["out"])
    meta = synth["meta"]
    assert rec.num_images() == meta["frames"]
    assert sorted(rec.images) == list(range(1, meta["frames"] + 1))
    cam = rec.camera(1)
    assert cam.model.name == "PINHOLE" and (cam.width, cam.height) == (240, 160)
    # horizontal field of view ~73 deg, 3:2
    assert abs(2 * np.degrees(np.arctan(cam.width / 2 / cam.params[0])) - 73.0) < 0.01
    for iid in rec.images:
        im = rec.image(iid)
        fd = meta["frames_detail"][iid - 1]
        assert im.name == fd["name"]
        np.testing.assert_allclose(im.projection_center(), fd["center_world"], atol=1e-6)
    # sparse points re-project onto their observations (poses + georeference consistent)
    errs = []
    for p in rec.points3D.values():
        for el in p.track.elements:
            im = rec.image(el.image_id)
            uv = cam.img_from_cam(im.cam_from_world() * p.xyz)
            errs.append(np.linalg.norm(uv - im.points2D[el.point2D_idx].xy))
    assert len(errs) > 500 and max(errs) < 1e-3


# ---- exact truth ------------------------------------------------------------------------------
def test_masks_equal_reraycast_classes(synth):
    rec = _colmap(synth["out"])
    camera = _camera(rec)
    R = synth["renderer"]
    rng = np.random.default_rng(7)
    total = interior_bad = disagree = 0
    for name, T in _local_poses(rec, synth["offset"]):
        mask = np.array(Image.open(synth["out"] / "truth" / "masks" / f"{Path(name).stem}.png"))
        assert mask.shape == (camera.height, camera.width) and mask.dtype == np.uint8
        r = rng.integers(1, camera.height - 1, 300)
        c = rng.integers(1, camera.width - 1, 300)
        rays = camera.unproject(np.column_stack([c + 0.5, r + 0.5]), 1.0)
        dirs = rays @ T[:3, :3]
        o = np.broadcast_to(camera_center(T), dirs.shape)
        hit = R.cast(o.astype(np.float32), dirs.astype(np.float32))
        xyz = o + hit["t_hit"][:, None] * dirs
        cls = R.classify(hit["prim"], np.nan_to_num(xyz))
        got = mask[r, c]
        # pixels whose 3x3 neighbourhood is one class must match exactly; boundary pixels may
        # differ by float rounding of the pose round trip through the COLMAP file
        nb = np.stack([mask[r + dr, c + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
        uniform = np.all(nb == nb[0], axis=0)
        interior_bad += int(np.sum(uniform & (got != cls)))
        disagree += int(np.sum(got != cls))
        total += len(r)
    assert interior_bad == 0
    assert disagree / total < 0.002


def test_roof_corners_project_onto_roof_pixels(synth):
    rec = _colmap(synth["out"])
    camera = _camera(rec)
    out = synth["out"]
    world = synth["world"]
    roofs = [p for p in world.prims if p.cls == ROOF]
    assert any(isinstance(p, Box) for p in roofs), "the first building has a flat roof"
    hits = 0
    for roof in roofs:
        if isinstance(roof, Box):  # flat: the corners of the top face, 0.4 m inside
            hx, hy, hz = roof.size / 2
            top = roof.center[2] + hz
            corners = np.array([[roof.center[0] + sx * (hx - 0.4), roof.center[1] + sy * (hy - 0.4), top]
                                for sx in (-1, 1) for sy in (-1, 1)])
        else:  # gable: points on the ridge, 0.5 m in from its ends
            lx, _, h = roof.size
            c, s = np.cos(roof.yaw), np.sin(roof.yaw)
            corners = np.array([roof.base + [t * c, t * s, h] for t in (-(lx / 2 - 0.5), 0.0, lx / 2 - 0.5)])
        for name, T in _local_poses(rec, synth["offset"]):
            xc = corners @ T[:3, :3].T + T[:3, 3]
            uv, z = camera.project(xc)
            ok = (z > 0) & camera.in_image(uv)
            if not ok.any():
                continue
            stem = Path(name).stem
            mask = np.array(Image.open(out / "truth" / "masks" / f"{stem}.png"))
            depth = read_depth_map(out / "dense" / "stereo" / "depth_maps" / f"{name}.geometric.bin")
            ij = np.floor(uv[ok]).astype(int)
            d = depth[ij[:, 1], ij[:, 0]]
            unoccluded = (d > 0) & (np.abs(d - z[ok]) < 0.03 * z[ok])  # nothing in front
            assert np.all(mask[ij[unoccluded, 1], ij[unoccluded, 0]] == ROOF)
            hits += int(unoccluded.sum())
    assert hits >= 10


def test_depth_maps_noise_matches_configuration(synth):
    rec = _colmap(synth["out"])
    camera = _camera(rec)
    R = synth["renderer"]
    sigma = synth["meta"]["depth_noise"]["relative_sigma"]
    rel, invalid, valid_truth = [], 0, 0
    for name, T in _local_poses(rec, synth["offset"])[::3]:
        res = R.render(camera, T, np.random.default_rng(0))
        dn = read_depth_map(synth["out"] / "dense" / "stereo" / "depth_maps" / f"{name}.geometric.bin")
        assert dn.shape == res.depth.shape
        both = (res.depth > 0) & (dn > 0)
        rel.append(np.abs(dn[both] - res.depth[both]) / res.depth[both])
        assert not np.any((dn > 0) & (res.depth == 0))  # no depth where there is no surface
        invalid += int(np.sum((res.depth > 0) & (dn == 0)))
        valid_truth += int(np.sum(res.depth > 0))
    rel = np.concatenate(rel)
    # |N(0, sigma)| has median 0.6745 sigma
    assert 0.6745 * sigma * 0.9 < np.median(rel) < 0.6745 * sigma * 1.1
    assert 0.005 < invalid / valid_truth < 0.10


def test_point_labels_aligned_with_fused_cloud(synth):
    out, meta, world = synth["out"], synth["meta"], synth["world"]
    xyz, rgb, normals = read_fused_ply(out / "dense" / "fused.ply")
    labels = np.load(out / "truth" / "point_labels.npy")
    offsets, frames = read_fused_vis(out / "dense" / "fused.ply.vis", len(xyz))
    assert labels.dtype == np.uint8 and len(labels) == len(xyz) == meta["points"]
    assert xyz.dtype == np.float64 and xyz[:, 0].min() > 500_000 and xyz[:, 1].min() > 5_400_000
    counts = np.diff(offsets)
    assert counts.min() >= 1  # every point has its contributing image(s)
    assert np.all(np.bincount(frames, minlength=meta["frames"]) > 0)  # every frame sees points
    local = xyz - synth["offset"]
    # roof points lie on a roof: inside a roof primitive's footprint, at its height
    roof_pts = local[labels == ROOF]
    assert len(roof_pts) > 200
    on_roof = np.zeros(len(roof_pts), bool)
    for p in world.prims:
        if p.cls == ROOF:
            lo, hi = p.aabb()
            on_roof |= np.all((roof_pts >= lo - 0.5) & (roof_pts <= hi + 0.5), axis=1)
    assert on_roof.mean() > 0.98
    # building points lie on a building wall box; water points on the pond, at terrain height
    bld = local[labels == BUILDING]
    on_bld = np.zeros(len(bld), bool)
    for p in world.prims:
        if p.cls == BUILDING:
            lo, hi = p.aabb()
            on_bld |= np.all((bld >= lo - 0.5) & (bld <= hi + 0.5), axis=1)
    assert len(bld) > 100 and on_bld.mean() > 0.98
    wat = local[labels == WATER]
    assert len(wat) > 20
    # fused points are cell means: within one fusion voxel of a water raster cell
    tol = PRESETS["tiny"].fuse_voxel
    near_water = np.zeros(len(wat), bool)
    for dx in (-tol, 0.0, tol):
        for dy in (-tol, 0.0, tol):
            near_water |= world.ground.lookup(wat[:, 0] + dx, wat[:, 1] + dy) == WATER
    assert near_water.all()
    assert np.abs(wat[:, 2] - world.ground_z(wat[:, 0], wat[:, 1])).max() < 0.5
    # labels agree with the truth grid around the point
    grid = SceneGrid.load(out / "truth" / "scene_grid.npz")
    ijk = np.floor((xyz - grid.origin) / grid.voxel_size).astype(int)
    agree = np.zeros(len(xyz), bool)
    for d in np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1]), -1).reshape(-1, 3):
        q = np.clip(ijk + d, 0, np.array(grid.shape) - 1)
        agree |= grid.labels[q[:, 0], q[:, 1], q[:, 2]] == labels
    assert agree.mean() > 0.97


def test_scene_grid_building_is_solid_with_expected_count(synth):
    grid = SceneGrid.load(synth["out"] / "truth" / "scene_grid.npz")
    world, offset = synth["world"], synth["offset"]
    assert grid.voxel_size == 0.5
    assert grid.labels.dtype == np.uint8 and grid.labels.ndim == 3
    # the grid covers the whole world
    lo, hi = world.bounds
    g_lo, g_hi = grid.bounds
    assert np.all(g_lo <= lo + offset) and np.all(g_hi >= hi + offset)
    vs = grid.voxel_size
    local_origin = grid.origin - offset
    z_lo, _ = column_terrain_range(world, local_origin, np.array(grid.shape), vs)
    k_lo = np.floor((z_lo - local_origin[2]) / vs).astype(int)  # first voxel the terrain touches
    boxes = [p for p in world.prims if p.cls == BUILDING and isinstance(p, Box) and p.yaw == 0.0]
    assert boxes
    n_buried = 0
    for b in boxes:
        lo_w = b.center - b.size / 2 + offset
        hi_w = b.center + b.size / 2 + offset
        centres = [grid.origin[k] + (np.arange(grid.shape[k]) + 0.5) * vs for k in range(3)]
        ins = [np.flatnonzero((centres[k] >= lo_w[k]) & (centres[k] <= hi_w[k])) for k in range(3)]
        block = grid.labels[np.ix_(*ins)]
        buried = ins[2][None, None, :] < k_lo[np.ix_(ins[0], ins[1])][:, :, None]
        # the box is sunk into the terrain: its buried part is empty like the soil around it
        assert buried.any()
        n_buried += int(buried.sum())
        assert np.all(block[buried] == 0), "voxels wholly below the terrain are empty"
        assert np.all(block[~buried] == BUILDING), "every voxel centre inside the box above ground is building"
        n_inside = int((~buried).sum())
        # around it: at most one extra layer of boundary voxels (the wall surfaces)
        s = [slice(max(i[0] - 1, 0), i[-1] + 2) for i in ins]
        n_bld = int(np.sum(grid.labels[s[0], s[1], s[2]] == BUILDING))
        nx, ny, nz = (len(i) for i in ins)
        boundary = (nx + 2) * (ny + 2) * (nz + 2) - nx * ny * nz
        assert n_inside <= n_bld <= n_inside + boundary
    assert n_buried > 0
    # the flat roof slab sits on top of its building
    for p in world.prims:
        if p.cls == ROOF and isinstance(p, Box):
            top = grid.lookup((p.center + offset)[None])
            assert top[0] == ROOF


def test_scene_grid_marks_columns_outside_the_survey_invalid(synth):
    """Columns whose terrain point fewer than min_views images see, or with no fused point within
    2 m, are 255; all others not."""
    from scipy.spatial import cKDTree

    grid = SceneGrid.load(synth["out"] / "truth" / "scene_grid.npz")
    world, offset, meta = synth["world"], synth["offset"], synth["meta"]
    P = PRESETS["tiny"]
    camera = make_camera(P)
    frames = plan_flight(P, world, camera)
    local_origin = grid.origin - offset
    views = survey_views(world, local_origin, np.array(grid.shape), grid.voxel_size, camera,
                         [f.T_cam_world for f in frames])
    invalid = grid.labels == 255
    col_invalid = invalid.all(axis=2)
    assert np.array_equal(invalid.any(axis=2), col_invalid), "invalid is a whole-column property"
    # observed: brute force, nearest fused point (plan view) of every column centre
    xyz, _, _ = read_fused_ply(synth["out"] / "dense" / "fused.ply")
    X, Y, _ = grid.shape
    cx = local_origin[0] + (np.arange(X) + 0.5) * grid.voxel_size
    cy = local_origin[1] + (np.arange(Y) + 0.5) * grid.voxel_size
    GX, GY = np.meshgrid(cx, cy, indexing="ij")
    d, _ = cKDTree(np.asarray(xyz, np.float64)[:, :2] - offset[:2]).query(np.column_stack([GX.ravel(), GY.ravel()]))
    observed = (d <= 2.0).reshape(X, Y)
    expected = (views < P.min_views) | ~observed
    # the exact rule and the brute force may differ only for centres within ~2 cm of 2 m
    borderline = np.abs(d.reshape(X, Y) - 2.0) < 0.05
    assert np.array_equal(col_invalid[~borderline], expected[~borderline])
    assert 0 < col_invalid.sum() < 0.5 * col_invalid.size  # the rim, never most of the world
    assert (views < P.min_views).sum() > 0 and (~observed & (views >= P.min_views)).sum() > 0
    assert meta["truth_grid"]["invalid_columns"] == int(col_invalid.sum())
    # brute-force check of a few columns against an independent projection of the terrain point
    rng = np.random.default_rng(1)
    for i, j in zip(rng.integers(0, grid.shape[0], 40), rng.integers(0, grid.shape[1], 40), strict=True):
        x = local_origin[0] + (i + 0.5) * grid.voxel_size
        y = local_origin[1] + (j + 0.5) * grid.voxel_size
        p = np.array([[x, y, float(world.ground_z(np.array([x]), np.array([y]))[0])]])
        n = sum(bool(project_world(camera, f.T_cam_world, p)[2][0]) for f in frames)
        if not borderline[i, j]:
            assert ((n < P.min_views) or not observed[i, j]) == col_invalid[i, j]


# ---- determinism ------------------------------------------------------------------------------
def test_same_seed_identical_bytes_different_seed_differs(synth, synth_tiny):
    # two separate generations of tiny, seed 0: the CLI's (``synth``) and the run's shared one
    # (tests/conftest.py: ``generate(preset="tiny", seed=0)``)
    assert SEED == 0
    again = synth_tiny
    out = synth["out"]
    rels = ["dense/fused.ply", "dense/fused.ply.vis", "truth/point_labels.npy", "truth/scene_grid.npz",
            "truth/objects.json", "sparse/points3D.bin", "sparse/images.bin"]
    rels += [f"truth/masks/{p.name}" for p in sorted((out / "truth" / "masks").iterdir())]
    rels += [f"images/{p.name}" for p in sorted((out / "images").iterdir())[::5]]
    rels += [f"dense/stereo/depth_maps/{p.name}" for p in sorted((out / "dense/stereo/depth_maps").iterdir())[::5]]
    for rel in rels:
        assert (out / rel).read_bytes() == (again / rel).read_bytes(), rel

    # another seed: another world, other images
    P = PRESETS["tiny"]
    w1 = build_world(P, SEED + 1)
    w0 = synth["world"]
    assert [p.to_dict() for p in w1.prims] != [p.to_dict() for p in w0.prims]
    cam = make_camera(P)
    f1 = plan_flight(P, w1, cam)[0]
    r1 = Renderer(w1, SEED + 1).render(cam, f1.T_cam_world, np.random.default_rng([SEED + 1, 1, 0]))
    m0 = np.array(Image.open(out / "truth" / "masks" / "frame_000000.png"))
    assert not np.array_equal(r1.cls, m0)


# ---- the importer reads it as a real reconstruction ---------------------------------------
def test_import_reports_frames_and_points_of_the_truth(synth, tmp_path):
    from occufly.io.importer import import_scene

    scene = import_scene(synth["out"], tmp_path / "ws")
    s = scene.summary()
    assert s["frames"] == synth["meta"]["frames"]
    assert s["points"] == synth["meta"]["points"]
    assert s["visibility"]["frames_without_points"] == 0
    np.testing.assert_allclose(scene.origin + scene.xyz.mean(axis=0),
                               read_fused_ply(synth["out"] / "dense" / "fused.ply")[0].mean(axis=0), atol=1e-3)


def test_visibility_lists_images_that_see_the_point(synth):
    """Each (point, image) pair of fused.ply.vis projects into that image onto a depth that
    agrees with the point (contributing images are within one fusion cell of it)."""
    out, meta = synth["out"], synth["meta"]
    rec = _colmap(out)
    camera = _camera(rec)
    poses = _local_poses(rec, synth["offset"])
    xyz, _, _ = read_fused_ply(out / "dense" / "fused.ply")
    local = xyz - synth["offset"]
    offsets, frames = read_fused_vis(out / "dense" / "fused.ply.vis", len(xyz))
    pt = np.repeat(np.arange(len(xyz)), np.diff(offsets))
    inside = agree = total = 0
    for f, (name, T) in enumerate(poses):
        m = pt[frames == f]
        uv, z, vis = project_world(camera, T, local[m])
        depth = read_depth_map(out / "dense" / "stereo" / "depth_maps" / f"{name}.geometric.bin")
        ij = np.floor(uv[vis]).astype(int)
        d = depth[ij[:, 1], ij[:, 0]]
        tol = meta["preset_params"]["vis_tolerance"]
        agree += int(np.sum((d > 0) & (np.abs(d - z[vis]) <= tol * z[vis])))
        inside += int(vis.sum())
        total += len(m)
    assert total == len(frames)
    assert inside / total > 0.99
    assert agree / total > 0.9
