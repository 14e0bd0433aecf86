import json
from pathlib import Path

import numpy as np
import pytest

from occufly.cli import main
from occufly.errors import InputFormatError, WorkspaceError
from occufly.io.colmap_dense import read_depth_map, read_fused_vis, write_fused_vis
from occufly.io.importer import import_scene, source_coordinates
from occufly.io.ply import write_ply
from occufly.io.pointcloud import read_point_cloud, write_las
from occufly.scene import Scene
from tests.harness import SHARED_DATA, shared_data
from tests.recon_builder import make_reconstruction

CUP = SHARED_DATA / "colmap-dense-cup"


@pytest.fixture
def cup() -> Path:
    return shared_data("colmap-dense-cup")  # fails, naming the folder, when it is absent


def test_import_colmap_dense_cup(tmp_path, capsys, cup):
    ws = tmp_path / "ws"
    # a COLMAP model in SfM units with no GPS and no georeferencing is refused, saying how to
    # fix it, and leaves nothing behind (it was imported in arbitrary units before)
    assert main(["import", str(CUP), "--workspace", str(ws), "--json"]) == 2
    err = capsys.readouterr().err
    assert "units are unknown" in err and "--scale" in err and "0 of 2 geotagged" in err
    assert not ws.exists()
    assert main(["import", str(CUP), "--workspace", str(ws), "--json", "--scale", "1"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == 2 and out["points"] == 58
    assert out["meta"]["visibility_source"] == "fused.ply.vis"
    scene = Scene.load(ws)
    offsets, idx = read_fused_vis(CUP / "fused.ply.vis", 58)
    assert scene.visibility.offsets[-1] == len(idx) == 116
    # the depth maps COLMAP wrote agree with the projected points
    for f, frame in enumerate(scene.frames):
        ids, uv, z = scene.visibility.frame(f)
        dm = read_depth_map(CUP / "stereo" / "depth_maps" / f"{frame.name}.geometric.bin")
        assert dm.shape == (frame.camera.height, frame.camera.width)
        d = dm[uv[:, 1].astype(int), uv[:, 0].astype(int)]
        ok = d > 0
        assert ok.mean() > 0.9
        rel = np.abs(z[ok] - d[ok]) / d[ok]
        assert np.median(rel) < 0.005


def test_vis_writer_is_byte_identical_to_colmap(cup):
    offsets, idx = read_fused_vis(CUP / "fused.ply.vis")
    out = Path("/tmp") / f"vis-{np.random.randint(1 << 30)}"
    write_fused_vis(out, offsets, idx)
    assert out.read_bytes() == (CUP / "fused.ply.vis").read_bytes()
    out.unlink()


@pytest.mark.parametrize("text", [True, False])
def test_import_georeferenced_depth_test(tmp_path, text):
    truth = make_reconstruction(tmp_path / "rec", text=text, depth_maps=True)
    scene = import_scene(tmp_path / "rec", tmp_path / "ws")
    assert scene.meta["georeferenced"] and scene.meta["visibility_source"].startswith("depth test against MVS")
    # UTM survives: world = origin + local to well under a millimetre
    np.testing.assert_allclose(scene.xyz_world(), truth["xyz"], atol=1e-3, rtol=0)
    assert np.abs(scene.origin).max() > 1e5
    for f in range(len(scene.frames)):
        ids = np.sort(scene.visibility.frame(f)[0])
        expected = np.flatnonzero(truth["seen"][f])
        # roof points hide the ground below them: the test must find exactly the true set
        inter = len(np.intersect1d(ids, expected))
        assert inter / len(expected) > 0.98 and inter / len(ids) > 0.98
    alts = sorted({fr.nominal_altitude for fr in scene.frames})
    assert alts == [30, 40]


def test_import_rendered_depth_without_depth_maps(tmp_path):
    truth = make_reconstruction(tmp_path / "rec", depth_maps=False)
    scene = import_scene(tmp_path / "rec", tmp_path / "ws")
    assert "rendered" in scene.meta["visibility_source"]
    for f in range(len(scene.frames)):
        ids = scene.visibility.frame(f)[0]
        expected = np.flatnonzero(truth["seen"][f])
        inter = len(np.intersect1d(ids, expected))
        assert inter / len(expected) > 0.9 and inter / len(ids) > 0.9


def test_import_uses_vis_file(tmp_path):
    truth = make_reconstruction(tmp_path / "rec", vis=True, depth_maps=False)
    scene = import_scene(tmp_path / "rec", tmp_path / "ws")
    assert scene.meta["visibility_source"] == "fused.ply.vis"
    for f in range(len(scene.frames)):
        np.testing.assert_array_equal(np.sort(scene.visibility.frame(f)[0]), np.flatnonzero(truth["seen"][f]))


def test_import_las_and_laz_clouds(tmp_path):
    truth = make_reconstruction(tmp_path / "rec")
    xyz, rgb = read_point_cloud(tmp_path / "rec" / "dense" / "fused.ply")
    for suffix in ("las", "laz"):
        cloud = tmp_path / f"cloud.{suffix}"
        write_las(cloud, xyz, rgb)
        scene = import_scene(tmp_path / "rec", tmp_path / f"ws-{suffix}", cloud=cloud)
        assert scene.n_points == len(truth["xyz"])
        np.testing.assert_allclose(scene.xyz_world(), truth["xyz"], atol=1e-3, rtol=0)


def test_non_georeferenced_model_is_levelled(tmp_path):
    make_reconstruction(tmp_path / "rec", georef=False, n_cams=4)
    # tilt the whole reconstruction: the importer must find up again
    from scipy.spatial.transform import Rotation

    R = Rotation.from_euler("xyz", [25, -40, 70], degrees=True).as_matrix()
    rec = tmp_path / "rec"
    xyz, rgb = read_point_cloud(rec / "dense" / "fused.ply")
    write_ply(rec / "dense" / "fused.ply", {"x": (xyz @ R.T)[:, 0], "y": (xyz @ R.T)[:, 1],
                                            "z": (xyz @ R.T)[:, 2]})
    import pycolmap

    model = pycolmap.Reconstruction(str(rec / "sparse"))
    model.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(R), np.zeros(3)))
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        (rec / "sparse" / f).unlink()
    model.write_text(str(rec / "sparse"))
    import shutil

    shutil.rmtree(rec / "dense" / "stereo")
    with pytest.raises(InputFormatError, match="units are unknown"):
        import_scene(rec, tmp_path / "ws")  # no GPS, no georeferencing, no --scale
    scene = import_scene(rec, tmp_path / "ws", scale=1.0)
    assert not scene.meta["georeferenced"]
    # after levelling the ground is horizontal again: z spread of ground points ~ 0
    z = np.asarray(scene.xyz[:, 2])
    ground = z < np.percentile(z, 50)
    assert np.ptp(z[ground]) < 0.05
    for fr in scene.frames:
        assert fr.direction[2] < -0.99  # nadir cameras look down
    back = source_coordinates(scene, scene.xyz)
    np.testing.assert_allclose(back, xyz @ R.T, atol=1e-3)


def test_workspace_roundtrip_identical(tmp_path):
    make_reconstruction(tmp_path / "rec")
    scene = import_scene(tmp_path / "rec", tmp_path / "ws")
    scene.save(tmp_path / "ws2")
    a, b = Scene.load(tmp_path / "ws"), Scene.load(tmp_path / "ws2")
    for name in ("xyz", "rgb"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    for name in ("offsets", "point_ids", "uv", "depth"):
        np.testing.assert_array_equal(getattr(a.visibility, name), getattr(b.visibility, name))
    assert [f.to_dict() for f in a.frames] == [f.to_dict() for f in b.frames]
    assert a.meta == b.meta and a.taxonomy == b.taxonomy
    np.testing.assert_array_equal(a.origin, b.origin)
    assert isinstance(a.xyz, np.memmap)
    with pytest.raises(WorkspaceError, match="already exists"):
        scene.save(tmp_path / "ws2")


# ---- bad input: one clear error, no half-written workspace ----------------------------------
def _expect_error(tmp_path, rec, match, **kw):
    ws = tmp_path / "ws-bad"
    with pytest.raises(InputFormatError, match=match):
        import_scene(rec, ws, **kw)
    assert not ws.exists()
    assert not [p for p in tmp_path.iterdir() if ".partial" in p.name]


def test_missing_colmap_file(tmp_path):
    make_reconstruction(tmp_path / "rec")
    (tmp_path / "rec" / "sparse" / "points3D.txt").unlink()
    _expect_error(tmp_path, tmp_path / "rec", "no COLMAP model")


def test_malformed_colmap_file(tmp_path):
    make_reconstruction(tmp_path / "rec")
    (tmp_path / "rec" / "sparse" / "cameras.txt").write_text("1 PINHOLE 96 64 oops\n")
    _expect_error(tmp_path, tmp_path / "rec", "malformed COLMAP model")


def test_ply_without_coordinates(tmp_path):
    make_reconstruction(tmp_path / "rec")
    write_ply(tmp_path / "rec" / "dense" / "fused.ply", {"red": np.zeros(5, np.uint8)})
    _expect_error(tmp_path, tmp_path / "rec", r"no x/y/z property")


def test_nan_coordinates(tmp_path):
    make_reconstruction(tmp_path / "rec")
    xyz, _ = read_point_cloud(tmp_path / "rec" / "dense" / "fused.ply")
    xyz[7, 1] = np.nan
    write_ply(tmp_path / "rec" / "dense" / "fused.ply", {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    _expect_error(tmp_path, tmp_path / "rec", r"NaN or infinite coordinates \(first: point 7\)")


def test_images_do_not_match_model(tmp_path):
    make_reconstruction(tmp_path / "rec")
    (tmp_path / "rec" / "images" / "img_001.png").unlink()
    _expect_error(tmp_path, tmp_path / "rec", "does not match the model.*img_001.png")


def test_image_of_wrong_size(tmp_path):
    from PIL import Image

    make_reconstruction(tmp_path / "rec")
    Image.new("RGB", (10, 10)).save(tmp_path / "rec" / "images" / "img_000.png")
    _expect_error(tmp_path, tmp_path / "rec", "is 10x10 but its camera")


def test_laz_without_backend(tmp_path, monkeypatch):
    make_reconstruction(tmp_path / "rec")
    xyz, rgb = read_point_cloud(tmp_path / "rec" / "dense" / "fused.ply")
    write_las(tmp_path / "c.laz", xyz, rgb)
    import laspy

    monkeypatch.setattr(laspy.LazBackend, "detect_available", classmethod(lambda cls: ()))
    _expect_error(tmp_path, tmp_path / "rec", "no LAZ backend", cloud=tmp_path / "c.laz")


def test_truncated_depth_map(tmp_path):
    make_reconstruction(tmp_path / "rec")
    p = next((tmp_path / "rec" / "dense" / "stereo" / "depth_maps").iterdir())
    p.write_bytes(p.read_bytes()[:-10])
    _expect_error(tmp_path, tmp_path / "rec", "truncated or padded")


def test_depth_map_with_nan_inf_and_negative_values_reads_them_as_no_depth(tmp_path):
    from occufly.io.colmap_dense import write_depth_map

    d = np.arange(12, dtype=np.float32).reshape(3, 4) + 1.0
    d[0, 1], d[1, 2], d[2, 3] = np.nan, np.inf, -5.0
    write_depth_map(tmp_path / "d.bin", d)
    got = read_depth_map(tmp_path / "d.bin")
    want = d.copy()
    want[0, 1] = want[1, 2] = want[2, 3] = 0.0
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.float32 and got.flags.c_contiguous


def test_cli_reports_error_in_one_line(tmp_path, capsys):
    assert main(["import", str(tmp_path / "nowhere"), "--workspace", str(tmp_path / "ws")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "reconstruction folder not found" in err[0]
