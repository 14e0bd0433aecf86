"""Visibility: union of the reconstruction's lists with the depth test, modes, compact
storage (uv/depth projected on demand), bad input (wrong-size depth maps, poses behind the
cloud, NaN and far-outlier points)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from occufly.cli import main
from occufly.errors import InputFormatError
from occufly.io.colmap_dense import (
    read_fused_vis,
    write_depth_map,
    write_fused_ply,
    write_fused_vis,
)
from occufly.io.importer import import_scene
from occufly.io.pointcloud import read_point_cloud
from occufly.scene import Scene, Visibility
from occufly.visibility import FrameLists, PointBins, compute_visibility, render_shape
from tests.harness import shared_data
from tests.recon_builder import make_reconstruction


def _thin_vis(rec, truth, keep_every=3):
    """Rewrite fused.ply.vis keeping one of every ``keep_every`` views of each point (like a
    fusion's lists, which name only the images fused into a point)."""
    lists = []
    for p in range(truth["seen"].shape[1]):
        fr = np.flatnonzero(truth["seen"][:, p])
        lists.append(fr[p % keep_every::keep_every] if len(fr) > 1 else fr)
    offsets = np.r_[0, np.cumsum([len(v) for v in lists])]
    write_fused_vis(rec / "dense" / "fused.ply.vis", offsets, np.concatenate(lists))
    return offsets


@pytest.fixture(scope="module")
def thin(tmp_path_factory):
    rec = tmp_path_factory.mktemp("thin") / "rec"
    truth = make_reconstruction(rec, vis=True, depth_maps=True, n_cams=5)
    offsets = _thin_vis(rec, truth)
    return rec, truth, offsets


def _sets(scene):
    return [set(np.asarray(scene.visibility.frame_ids(f)).tolist()) for f in range(len(scene.frames))]


def test_union_recovers_every_view_the_lists_miss(thin, tmp_path):
    rec, truth, offsets = thin
    union = import_scene(rec, tmp_path / "u")
    only_vis = import_scene(rec, tmp_path / "v", visibility="vis")
    only_depth = import_scene(rec, tmp_path / "d", visibility="depth")
    assert union.meta["visibility_mode"] == "union" and only_vis.meta["visibility_mode"] == "vis"
    assert union.meta["visibility_source"] == "fused.ply.vis"
    assert union.meta["visibility_depth_test"] == "depth test against MVS depth maps"
    seen = truth["seen"]
    assert only_vis.visibility.offsets[-1] == offsets[-1] < 0.5 * seen.sum()
    for f, (u, v, d) in enumerate(zip(_sets(union), _sets(only_vis), _sets(only_depth),
                                      strict=True)):
        assert u == v | d
        expected = set(np.flatnonzero(seen[f]).tolist())
        assert len(u & expected) / len(expected) > 0.98 and len(u & expected) / len(u) > 0.98
    st = union.meta["visibility_stats"]
    vpp = union.summary()["visibility"]["views_per_point"]
    assert vpp["mean"] == pytest.approx(seen.sum(axis=0).mean(), rel=0.03)
    assert st["views_per_point"]["mean"] == vpp["mean"]
    assert st["entries_only_in_depth_test"] > 0.5 * seen.sum()
    assert only_vis.summary()["visibility"]["views_per_point"]["mean"] < 0.5 * vpp["mean"]


def test_compact_storage_projects_what_was_stored(thin, tmp_path):
    rec, truth, _ = thin
    scene = import_scene(rec, tmp_path / "ws")
    vdir = tmp_path / "ws" / "visibility"
    assert not (vdir / "uv.npy").exists() and not (vdir / "depth.npy").exists()
    assert (vdir / "point_ids.npy").stat().st_size < 4 * scene.visibility.offsets[-1] + 200
    # the old layout (uv/depth stored) still loads and gives the same correspondences
    v = scene.visibility
    old = Scene(frames=scene.frames, xyz=np.asarray(scene.xyz), rgb=np.asarray(scene.rgb),
                origin=scene.origin, visibility=Visibility(v.offsets, v.point_ids, v.uv, v.depth),
                taxonomy=scene.taxonomy, meta=scene.meta)
    old.save(tmp_path / "old")
    assert (tmp_path / "old" / "visibility" / "uv.npy").is_file()
    back = Scene.load(tmp_path / "old")
    assert back.visibility.stores_projections and not scene.visibility.stores_projections
    for f in range(len(scene.frames)):
        a, b = scene.visibility.frame(f), back.visibility.frame(f)
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        ids, uv, z = a
        # projected on demand = the camera model applied to the point
        from occufly.camera import project_world

        fr = scene.frames[f]
        uv2, z2, _ = project_world(fr.camera, fr.T_cam_world, np.asarray(scene.xyz)[ids])
        np.testing.assert_allclose(uv, uv2, atol=1e-3)
        np.testing.assert_allclose(z, z2, rtol=1e-6)


def test_cli_visibility_flag_and_views_in_info(thin, tmp_path, capsys):
    rec, truth, _ = thin
    ws = tmp_path / "ws"
    assert main(["import", str(rec), "-w", str(ws), "--visibility", "vis", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["meta"]["visibility_mode"] == "vis"
    n_vis = out["visibility"]["correspondences"]
    assert main(["info", str(ws), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["visibility"]["views_per_point"] == out["visibility"]["views_per_point"]
    assert main(["import", str(rec), "-w", str(ws), "--force", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["visibility"]["correspondences"] > 2 * n_vis
    # --visibility vis without any lists: a clear error, exit 2, no workspace
    bare = tmp_path / "bare"
    make_reconstruction(bare, vis=False, depth_maps=False)
    assert main(["import", str(bare), "-w", str(tmp_path / "none"), "--visibility", "vis"]) == 2
    assert "--visibility vis needs" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_depth_map_of_the_wrong_size_is_named_and_replaced_by_rendering(tmp_path, caplog):
    rec = tmp_path / "rec"
    truth = make_reconstruction(rec, depth_maps=True)
    bad = rec / "dense" / "stereo" / "depth_maps" / f"{truth['names'][1]}.geometric.bin"
    write_depth_map(bad, np.full((10, 50), 30.0, np.float32))  # 50x10 for a 96x64 image
    with caplog.at_level(logging.WARNING):
        scene = import_scene(rec, tmp_path / "ws")
    st = scene.meta["visibility_stats"]
    assert st["frames_with_depth_maps"] == 2 and st["frames_rendered"] == 1
    assert any(str(bad) in w and "not a scaled copy" in w for w in st["warnings"])
    assert str(bad) in caplog.text
    ids = scene.visibility.frame_ids(1)
    expected = np.flatnonzero(truth["seen"][1])
    assert len(np.intersect1d(ids, expected)) / len(expected) > 0.9


def test_frame_behind_the_cloud_is_named(tmp_path):
    rec = tmp_path / "rec"
    truth = make_reconstruction(rec, depth_maps=False)
    scene = import_scene(rec, tmp_path / "ws")
    frames = list(scene.frames)
    # turn frame 2 around: it looks up, away from the ground
    T = frames[2].T_cam_world.copy()
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    frames[2].T_cam_world = flip @ T
    vis, st = compute_visibility(frames, np.asarray(scene.xyz), mode="depth")
    assert st["frames_seeing_nothing"] == 1
    assert any(frames[2].name in w and "check its pose" in w for w in st["warnings"])
    assert vis.counts_per_frame()[2] == 0 and vis.counts_per_frame()[0] > 0
    # all frames behind: the import is an error, not an empty workspace
    for im in ("images.txt",):
        p = rec / "sparse" / im
        lines = p.read_text().splitlines()
        out = []
        for ln in lines:
            parts = ln.split()
            if len(parts) == 10 and parts[-1].endswith(".png"):
                # camera 100 m below the ground, same orientation: everything is behind it
                parts[7] = repr(float(parts[7]) - 1000.0)
            out.append(" ".join(parts))
        p.write_text("\n".join(out) + "\n")
    with pytest.raises(InputFormatError, match="no frame sees any point"):
        import_scene(rec, tmp_path / "ws2")
    assert not (tmp_path / "ws2").exists()
    assert truth["seen"].any()


def test_nan_points_are_an_error_and_far_outliers_are_harmless(tmp_path):
    rec = tmp_path / "rec"
    truth = make_reconstruction(rec, depth_maps=False)
    ply = rec / "dense" / "fused.ply"
    xyz, rgb = read_point_cloud(ply)
    bad = xyz.copy()
    bad[7] = np.nan
    write_fused_ply(rec / "nan.ply", bad, None, rgb, double=True)
    with pytest.raises(InputFormatError, match=r"nan\.ply: 1 points have NaN.*point 7"):
        import_scene(rec, tmp_path / "ws", cloud=rec / "nan.ply")
    assert not (tmp_path / "ws").exists()
    far = np.vstack([xyz, xyz[:1] + [10_000.0, 0.0, 0.0], xyz[:1] + [0.0, 0.0, -10_000.0]])
    write_fused_ply(rec / "far.ply", far, None, np.vstack([rgb, rgb[:2]]), double=True)
    scene = import_scene(rec, tmp_path / "ws", cloud=rec / "far.ply")
    st = scene.meta["visibility_stats"]
    assert st["far_outlier_points"] == 2
    n = len(xyz)
    for f in range(len(scene.frames)):
        ids = scene.visibility.frame_ids(f)
        assert not np.isin([n, n + 1], ids).any()
        expected = np.flatnonzero(truth["seen"][f])
        inter = len(np.intersect1d(ids, expected))
        assert inter / len(expected) > 0.9 and inter / len(ids) > 0.9
    # the bins ignore the outliers (64 bins over the bulk, not over 10 km)
    bins = PointBins(np.asarray(scene.xyz))
    assert bins.cell < 2.0 and len(bins.loose) == 2


def test_render_shape_resolves_the_spacing():
    from occufly.camera import Camera

    cam = Camera("PINHOLE", 4000, 3000, [3000.0, 3000.0, 2000.0, 1500.0])
    # dense cloud (1 cm at 50 m: 0.6 px): full resolution
    assert render_shape(cam, 0.01, 50.0) == (3000, 4000)
    # sparse cloud (0.5 m at 50 m: 30 px apart): the raster shrinks so points are <= 2 px apart
    h, w = render_shape(cam, 0.5, 50.0)
    assert w == round(4000 / 15) and h == round(3000 / 15)
    # huge images are capped
    big = Camera("PINHOLE", 20000, 10000, [9000.0, 9000.0, 10000.0, 5000.0])
    assert max(render_shape(big, 0.001, 50.0)) == 4096


def test_union_on_the_colmap_cup_adds_nothing_wrong(tmp_path):

    cup = shared_data("colmap-dense-cup")
    scene = import_scene(cup, tmp_path / "ws", scale=1.0)  # SfM units, no GPS: scale declared
    offsets, idx = read_fused_vis(cup / "fused.ply.vis", 58)
    assert scene.visibility.offsets[-1] == len(idx)
    assert scene.meta["visibility_depth_test"] == "depth test against MVS depth maps"


# ---- streamed output, bounded memory, up-front refusal -----------------------------------------
def test_streamed_ids_are_byte_identical_to_the_in_memory_path(thin, tmp_path):
    """The import streams the point ids to disk frame by frame; the file is what np.save of
    the in-memory result writes, and the workspace holds exactly that file."""
    rec, _, _ = thin
    scene = import_scene(rec, tmp_path / "ws")
    xyz = np.asarray(scene.xyz)
    offsets, idx = read_fused_vis(rec / "dense" / "fused.ply.vis", len(xyz))
    depth_dir = rec / "dense" / "stereo" / "depth_maps"
    from occufly.io.colmap_dense import find_depth_map, read_depth_map

    def depth_for(f):
        return read_depth_map(find_depth_map(depth_dir, scene.frames[f].name))

    frames = list(scene.frames)
    mem, st_mem = compute_visibility(frames, xyz, lists=(offsets, idx), depth_for=depth_for)
    out = tmp_path / "ids.npy"
    streamed, st_str = compute_visibility(frames, xyz, lists=(offsets, idx), depth_for=depth_for,
                                          ids_out=out)
    assert isinstance(streamed.point_ids, np.memmap) and not isinstance(mem.point_ids, np.memmap)
    np.save(tmp_path / "mem.npy", mem.point_ids)
    assert out.read_bytes() == (tmp_path / "mem.npy").read_bytes()
    assert (tmp_path / "ws" / "visibility" / "point_ids.npy").read_bytes() == out.read_bytes()
    np.testing.assert_array_equal(mem.offsets, streamed.offsets)
    np.testing.assert_array_equal(mem.offsets, scene.visibility.offsets)
    assert st_mem["views_per_point"] == st_str["views_per_point"]
    assert st_str["estimated_correspondences_max"] >= st_str["correspondences"]
    # grouped lists (what the import passes, after freeing the per-point arrays): the same
    grouped = FrameLists.from_point_lists(len(frames), offsets, idx, chunk=7)
    g, _ = compute_visibility(frames, xyz, lists=grouped, depth_for=depth_for)
    np.testing.assert_array_equal(g.point_ids, mem.point_ids)


def test_npy_stream_writer_matches_np_save(tmp_path):
    from occufly.workspace import NpyStreamWriter

    for parts in ([], [np.zeros(0, np.int64)], [np.arange(5), np.arange(3) * 7, np.zeros(0)],
                  [np.arange(100_000) % 1000]):
        with NpyStreamWriter(tmp_path / "s.npy", np.int32) as w:
            for p in parts:
                w.append(p)
        full = np.concatenate(parts).astype(np.int32) if parts else np.zeros(0, np.int32)
        np.save(tmp_path / "r.npy", full)
        assert (tmp_path / "s.npy").read_bytes() == (tmp_path / "r.npy").read_bytes()
        assert w.count == len(full)
    np.testing.assert_array_equal(np.load(tmp_path / "s.npy"), np.arange(100_000) % 1000)


def test_frame_lists_are_a_stable_grouping_by_frame():
    rng = np.random.default_rng(3)
    n, F = 1000, 13
    counts = rng.integers(0, 9, n)
    offsets = np.r_[0, np.cumsum(counts)]
    fidx = rng.integers(0, F + 2, offsets[-1]).astype(np.uint32)  # some name no frame
    point_of = np.repeat(np.arange(n), counts)
    keep = fidx < F
    order = np.argsort(fidx[keep], kind="stable")
    expected = point_of[keep][order]
    for chunk in (1, 5, 64, 1 << 20):
        fl = FrameLists.from_point_lists(F, offsets, fidx, chunk=chunk)
        assert fl.point_ids.dtype == np.int32 and len(fl) == keep.sum()
        np.testing.assert_array_equal(fl.point_ids, expected)
        for f in range(F):
            np.testing.assert_array_equal(fl.frame(f), point_of[fidx == f])


def test_vis_reader_streams_in_windows(thin, tmp_path):
    """Windows smaller than one point's list widen; truncated and padded files are named."""
    rec, _, _ = thin
    p = rec / "dense" / "fused.ply.vis"
    ref = read_fused_vis(p)
    for w in (2, 3, 17):
        got = read_fused_vis(p, window_words=w)
        np.testing.assert_array_equal(got[0], ref[0])
        np.testing.assert_array_equal(got[1], ref[1])
        assert got[1].dtype == np.uint32
    raw = p.read_bytes()
    (tmp_path / "short.vis").write_bytes(raw[:-4])
    with pytest.raises(InputFormatError, match=r"short\.vis: truncated"):
        read_fused_vis(tmp_path / "short.vis", window_words=5)
    (tmp_path / "long.vis").write_bytes(raw + b"\0\0\0\0")
    with pytest.raises(InputFormatError, match=r"long\.vis: .*trailing"):
        read_fused_vis(tmp_path / "long.vis")


def test_an_import_that_cannot_fit_is_refused_up_front(thin, tmp_path, monkeypatch, capsys):
    """Too little memory or disk: exit 2 with the needed and available figures, before any
    workspace file exists (never an out-of-memory kill or a full disk halfway)."""
    import occufly.io.importer as imp

    rec, _, _ = thin
    est = imp.estimate_import_resources(n_points=1000, frames=import_scene(
        rec, tmp_path / "ok").frames, list_entries=5000)
    assert est["memory_bytes"] > imp.IMPORT_BASE_BYTES
    monkeypatch.setattr("occufly.fsutil.available_memory", lambda: 1 << 20)
    monkeypatch.setattr("occufly.fsutil.own_rss", lambda: 0)
    ws = tmp_path / "ws"
    assert main(["import", str(rec), "-w", str(ws)]) == 2
    err = capsys.readouterr().err
    assert "needs about" in err and "GB of memory" in err and "0.0 GB are available" in err
    assert not ws.exists() and not list(tmp_path.glob(".ws.*"))
    monkeypatch.undo()

    class Usage:
        free = 1000

    monkeypatch.setattr("shutil.disk_usage", lambda _p: Usage)
    assert main(["import", str(rec), "-w", str(ws)]) == 2
    err = capsys.readouterr().err
    assert "GB of disk" in err and "correspondences" in err and "are free there" in err
    assert not ws.exists() and not list(tmp_path.glob(".ws.*"))


def test_parallel_frames_give_the_same_workspace(tmp_path):
    """--workers 2: frame blocks computed by a process pool, written in frame order: the
    same bytes and statistics as one process (lists, MVS depth maps and a rendered frame)."""
    rec = tmp_path / "rec"
    truth = make_reconstruction(rec, vis=True, depth_maps=True, n_cams=5)
    _thin_vis(rec, truth)
    bad = sorted((rec / "dense" / "stereo" / "depth_maps").glob("*.geometric.bin"))[0]
    write_depth_map(bad, np.full((10, 50), 30.0, np.float32))  # one frame renders its depth
    one = import_scene(rec, tmp_path / "one")
    two = import_scene(rec, tmp_path / "two", workers=2)
    for name in ("offsets", "point_ids"):
        assert ((tmp_path / "one" / "visibility" / f"{name}.npy").read_bytes()
                == (tmp_path / "two" / "visibility" / f"{name}.npy").read_bytes())
    a, b = one.meta["visibility_stats"], two.meta["visibility_stats"]
    a.pop("seconds"), b.pop("seconds")
    assert a == b and a["frames_rendered"] == 1 and "point_spacing" in a
    assert a["entries_only_in_depth_test"] > 0 and a["entries_only_in_lists"] >= 0
    assert not list((tmp_path / "two").rglob(".visibility-*"))  # scratch files removed
    with pytest.raises(InputFormatError, match="--workers 0"):
        import_scene(rec, tmp_path / "zero", workers=0)
