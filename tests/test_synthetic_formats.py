"""One synthetic truth through every importer: ``synth --format colmap|odm|metashape|pix4d``.

Each format is the same lens-distorted survey in UTM 32N, written in that tool's conventions.
Imported, every format must give the COLMAP import's cameras (< 1 mm), project the truth
points to the same pixels (< 0.05 px), and lifting the same truth masks must give identical
point labels (with the same visibility rule: the depth test, since only COLMAP exports lists).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from occufly.camera import pose_in_world, transform
from occufly.errors import InputFormatError
from occufly.io.importer import import_scene
from occufly.scene import Scene
from occufly.synthetic.formats import FORMATS, generate_formats

OTHERS = ("odm", "metashape", "pix4d")


def _source(root: Path, fmt: str) -> tuple[Path, dict]:
    if fmt == "metashape":
        return root / fmt / "cameras.xml", {"cloud": root / fmt / "dense_cloud.laz"}
    return root / fmt, {}


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    root = tmp_path_factory.mktemp("formats") / "synth"
    summary = generate_formats(root, FORMATS, preset="tiny", seed=0)
    return root, summary


@pytest.fixture(scope="module")
def imported(synth, tmp_path_factory):
    root, _ = synth
    base = tmp_path_factory.mktemp("formats-ws")
    empty = base / "no-depth-maps"
    empty.mkdir()
    scenes = {}
    for fmt in FORMATS:
        src, kw = _source(root, fmt)
        if fmt == "colmap":  # the same visibility rule as the others: depth rendered from the cloud
            kw = {"visibility": "depth", "depth_maps": empty}
        scenes[fmt] = import_scene(src, base / fmt, **kw)
    return base, scenes


def _world_poses(scene: Scene) -> list[np.ndarray]:
    return [pose_in_world(f.T_cam_world, scene.origin) for f in scene.frames]


def test_layouts_are_each_tools(synth):
    root, summary = synth
    assert summary["crs"] == "EPSG:32632" and summary["camera"]["model"] == "FULL_OPENCV"
    for f in FORMATS:
        assert (root / f / "truth" / "point_labels.npy").is_file() and (root / f / "images").is_dir()
    assert (root / "colmap" / "dense" / "fused.ply.prj").is_file()
    rec = json.loads((root / "odm" / "opensfm" / "reconstruction.json").read_text())
    cam = next(iter(rec[0]["cameras"].values()))
    assert cam["projection_type"] == "brown" and cam["focal_x"] < 1  # normalised by max(w, h)
    assert (root / "odm" / "opensfm" / "reconstruction.topocentric.json").is_file()
    assert (root / "odm" / "odm_georeferencing" / "coords.txt").read_text().startswith("WGS84 UTM 32N\n")
    xml = (root / "metashape" / "cameras.xml").read_text()
    assert "<b1>" in xml and "<cx>" in xml and "<scale locked" in xml
    assert (root / "pix4d" / "1_initial" / "params" / "synthetic_wkt.prj").is_file()


def test_generated_projects_pass_the_import_roots_checks(synth):
    """Each format's project imports in the web app too: no symlink out of the folder and no
    hard-linked file (app imports refuse both, occufly.io.importer.confine_tree)."""
    from occufly.io.importer import confine_tree

    root, _ = synth
    linked = [p for p in root.rglob("*") if p.is_file() and p.stat().st_nlink > 1]
    assert linked == []
    for f in FORMATS:
        assert confine_tree(root / f, [root]) > 10


def test_every_format_gives_the_colmap_cameras_and_pixels(imported):
    _, scenes = imported
    ref = scenes["colmap"]
    T_ref = _world_poses(ref)
    pts = ref.xyz_world()[::5]
    for fmt in OTHERS:
        sc = scenes[fmt]
        assert sc.meta["format"] == fmt
        assert sc.crs["epsg"] == 32632 and ref.crs["epsg"] == 32632
        assert [f.name for f in sc.frames] == [f.name for f in ref.frames]
        T = _world_poses(sc)
        dc = max(np.linalg.norm(-a[:3, :3].T @ a[:3, 3] + b[:3, :3].T @ b[:3, 3])
                 for a, b in zip(T, T_ref, strict=True))
        assert dc < 1e-3, (fmt, dc)
        du = 0.0
        for fa, fb, a, b in zip(sc.frames, ref.frames, T, T_ref, strict=True):
            ua, _ = fa.camera.project(transform(a, pts))
            ub, zb = fb.camera.project(transform(b, pts))
            ok = (zb > 0) & fb.camera.in_image(ub)
            du = max(du, float(np.abs(ua[ok] - ub[ok]).max()))
        assert du < 0.05, (fmt, du)
        # the same cloud, the same local frame
        np.testing.assert_array_equal(np.asarray(sc.xyz), np.asarray(ref.xyz))
        np.testing.assert_array_equal(sc.origin, ref.origin)
    # the lens is really distorted: a pinhole with the same K misses by pixels near the border
    cam = ref.frames[0].camera
    assert cam.model == "FULL_OPENCV" and cam.has_distortion
    corner = cam.unproject(np.array([[1.0, 1.0]]), 1.0)
    pin = cam.K @ corner[0]
    assert np.abs(pin[:2] - 1.0).max() > 2.0


def test_lifting_the_same_masks_gives_identical_labels(synth, imported):
    from occufly.io.masks import read_mask
    from occufly.lifting import VoteStore

    root, _ = synth
    base, scenes = imported
    masks = sorted((root / "colmap" / "truth" / "masks").glob("*.png"))[::5]
    truth = np.load(root / "colmap" / "truth" / "point_labels.npy")
    labels = {}
    for fmt, sc in scenes.items():
        state = VoteStore.open(base / fmt, sc)
        for p in masks:
            fi = sc.frame_index(p.stem)
            state.apply_frame(fi, read_mask(p, sc.frames[fi], sc.taxonomy), name=str(p))
        labels[fmt] = np.asarray(state.fill_and_denoise(write=False).labels)
        state.close()
    # the labelled points are right; points no frame sees (the scene's far edges) stay
    # unlabelled. (Before the lens model's valid radius, Camera.valid_radius, points ~68
    # degrees off a camera's axis were folded into the middle of its image and voted with
    # whatever was painted there: right by chance on this grass scene, 0.9605 of all points
    # then, 0.9464 now; of the labelled points 0.9893 then, 0.9891 now; the direct votes
    # 0.9820 then, 0.9887 now.)
    lab = labels["colmap"]
    has = lab > 0
    assert has.mean() > 0.9 and (lab[has] == truth[has]).mean() > 0.98
    for fmt in OTHERS:
        assert np.array_equal(labels[fmt], labels["colmap"]), fmt


def test_export_points_carry_the_crs(imported, tmp_path):
    import laspy

    from occufly.io.crs import cloud_crs
    from occufly.io.pointcloud_export import export_scene_points

    _, scenes = imported
    sc = scenes["odm"]
    labels = np.zeros(sc.n_points, np.uint8)
    for ext in ("las", "laz", "ply"):
        out = tmp_path / f"sem.{ext}"
        info = export_scene_points(sc, labels, out)
        assert info["crs"] == "WGS 84 / UTM zone 32N (EPSG:32632)"
        assert os.stat(out).st_mode & 0o777 == 0o666 & ~_umask()
        if ext != "ply":
            las = laspy.read(out)
            assert las.header.parse_crs().to_epsg() == 32632
            # the input (ODM LAZ, point format 7) is kept
            assert las.header.point_format.id == info["point_format"] == 7
        else:
            assert cloud_crs(out)[0].to_epsg() == 32632  # side-car sem.prj
            assert f"comment origin {float(sc.origin[0])!r}" in out.read_bytes()[:2000].decode("latin-1")


def test_las_export_carries_asprs_codes_class_ids_and_the_class_table(imported, tmp_path):
    """classification = ASPRS codes (ground 2, trees 5, buildings 6, ...), the full id in
    ``class_id``, confidence in ``confidence``, and the class table in the VLRs."""
    import laspy

    from occufly.io.pointcloud_export import export_scene_points, read_class_table

    _, scenes = imported
    sc = scenes["odm"]
    tax = sc.taxonomy
    ids = np.concatenate([[0], tax.ids])
    labels = ids[np.arange(sc.n_points) % len(ids)].astype(np.uint8)
    conf = np.linspace(0, 1, sc.n_points).astype(np.float32)
    out = tmp_path / "sem.laz"
    info = export_scene_points(sc, labels, out, confidence=conf)
    assert info["asprs"]["building"] == info["asprs"]["roof"] == 6
    assert info["asprs"]["tree"] == 5 and info["asprs"]["water"] == 9
    las = laspy.read(out)
    cls = np.asarray(las.classification)
    cid = np.asarray(las.class_id)
    assert np.array_equal(cid, labels)  # no class is lost where two share an ASPRS code
    expect = {0: 1, tax.by_name("road").id: 11, tax.by_name("grass").id: 3,
              tax.by_name("building").id: 6, tax.by_name("roof").id: 6,
              tax.by_name("cable_tower").id: 15, tax.by_name("walkway").id: 64}
    for raw, code in expect.items():
        assert set(np.unique(cls[cid == raw]).tolist()) == {code}, (raw, code)
    assert np.abs(np.asarray(las.confidence) - conf).max() <= 0.5 / 255 + 1e-6
    vlrs = {(v.user_id, v.record_id): v for v in las.header.vlrs}
    table = vlrs[("LASF_Spec", 0)].lookups  # laspy parses the LAS 1.4 Classification Lookup
    assert table[1] == "Unclassified" and table[2] == "Ground" and table[6] == "Building"
    assert table[64] == "walkway" and table[5] == "High Vegetation"
    ct = read_class_table(out)
    assert {c["name"]: c["asprs"] for c in ct["classes"]}["tree"] == 5
    assert {c["id"] for c in ct["classes"]} == set(tax.ids.tolist())


def test_copc_export_reads_back_with_laspys_copc_reader(imported, tmp_path):
    import laspy

    from occufly.io.pointcloud_export import export_scene_points, read_class_table

    _, scenes = imported
    sc = scenes["odm"]
    ids = np.concatenate([[0], sc.taxonomy.ids])
    labels = ids[np.arange(sc.n_points) % len(ids)].astype(np.uint8)
    out = tmp_path / "sem.copc.laz"
    info = export_scene_points(sc, labels, out, confidence=np.full(sc.n_points, 0.5, np.float32))
    assert info["format"] == "copc.laz" and info["copc"]["points"] == sc.n_points
    # copc-lib writes the WKT as an EVLR, which laspy's full reader parses
    assert laspy.read(out).header.parse_crs().to_epsg() == 32632
    with laspy.CopcReader.open(out) as rd:
        pts = rd.query()
        assert len(pts) == sc.n_points
        coarse = rd.query(level=0)
        assert 0 < len(coarse) <= len(pts)
        got = np.column_stack([pts.X, pts.Y, pts.Z, np.asarray(pts.class_id)])
    ref = laspy.read(export_scene_points(sc, labels, tmp_path / "ref.laz")["path"])
    want = np.column_stack([ref.X, ref.Y, ref.Z, np.asarray(ref.class_id)])
    assert np.array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])
    assert read_class_table(out)["taxonomy"] == sc.taxonomy.name


def _umask() -> int:
    m = os.umask(0o022)
    os.umask(m)
    return m


def test_info_shows_the_crs(imported, capsys):
    from occufly.cli import main

    base, _ = imported
    assert main(["info", str(base / "pix4d"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["crs"] == {"name": "WGS 84 / UTM zone 32N", "epsg": 32632}


# ---- bad input ----------------------------------------------------------------------------------
def _no_workspace(ws: Path) -> None:
    assert not ws.exists()
    assert not [p for p in ws.parent.iterdir() if p.name.startswith(f".{ws.name}") or ".partial" in p.name]


def test_local_cameras_and_georeferenced_cloud_cannot_be_related(synth, tmp_path):
    root, _ = synth
    xml = (root / "metashape" / "cameras.xml").read_text()
    a, b = xml.index("    <transform>\n      <rotation"), xml.index("</transform>\n    <reference>")
    xml = xml[:a] + xml[b + len("</transform>\n"):]
    a, b = xml.index("<reference>GEOGCS"), xml.index("</reference>\n  </chunk>")
    xml = xml[:a] + '<reference>LOCAL_CS["Local Coordinates (m)",LOCAL_DATUM["Local Datum",0],' \
        'UNIT["metre",1]]' + xml[b:]
    p = tmp_path / "cameras.xml"
    p.write_text(xml)
    ws = tmp_path / "ws"
    with pytest.raises(InputFormatError, match=r"cameras.xml: the cameras are in a local frame.*"
                       r"dense_cloud.laz is in WGS 84 / UTM zone 32N \(EPSG:32632\)"):
        import_scene(p, ws, cloud=root / "metashape" / "dense_cloud.laz",
                     images=root / "metashape" / "images")
    _no_workspace(ws)


def test_cloud_without_crs_and_geographic_reference(synth, tmp_path):
    """Metashape's <reference> is WGS 84 (degrees); a PLY without .prj: say so, suggest --crs."""
    from occufly.io.colmap_dense import write_fused_ply
    from occufly.io.pointcloud import read_point_cloud

    root, _ = synth
    xyz, rgb = read_point_cloud(root / "metashape" / "dense_cloud.laz")
    ply = tmp_path / "dense.ply"
    write_fused_ply(ply, xyz, None, rgb)
    ws = tmp_path / "ws"
    with pytest.raises(InputFormatError, match=r"dense.ply: its CRS WGS 84.* is geographic.*--crs"):
        import_scene(root / "metashape" / "cameras.xml", ws, cloud=ply)
    _no_workspace(ws)
    with pytest.raises(InputFormatError, match=r"dense_cloud.laz: declares WGS 84 / UTM zone 32N.*--crs says"):
        import_scene(root / "metashape" / "cameras.xml", ws,
                     cloud=root / "metashape" / "dense_cloud.laz", crs="EPSG:32633")
    _no_workspace(ws)


def test_missing_images_are_listed(synth, tmp_path):
    root, _ = synth
    src = tmp_path / "odm"
    shutil.copytree(root / "odm", src, copy_function=os.link)
    gone = sorted((src / "images").iterdir())[3:5]
    for g in gone:
        g.unlink()
    ws = tmp_path / "ws"
    with pytest.raises(InputFormatError, match=rf"2 of \d+ images are missing: {gone[0].name}, {gone[1].name}"):
        import_scene(src, ws)
    _no_workspace(ws)


def test_detection_and_forced_format(synth):
    from occufly.io.sources import detect_format

    root, _ = synth
    assert [detect_format(_source(root, f)[0]) for f in FORMATS] == list(FORMATS)
    assert detect_format(root / "metashape") == "metashape"  # the folder holding the XML
    with pytest.raises(InputFormatError, match="not an ODM project"):
        import_scene(root / "pix4d", root.parent / "ws-x", fmt="odm")


def test_grid_and_manifest_carry_crs(tmp_path):
    from occufly.export import export_dataset
    from occufly.grid import SceneGrid
    from occufly.io.crs import crs_record, parse_crs
    from tests.export_fixtures import SPEC, make_workspace

    rec = crs_record(parse_crs("EPSG:32632", "test"))
    g = SceneGrid(np.zeros((2, 2, 2), np.uint8), [512480.0, 5403120.0, 263.0], 0.5, crs=rec["wkt"])
    assert parse_crs(SceneGrid.load(g.save(tmp_path / "g.npz")).crs, "g").to_epsg() == 32632
    ws = make_workspace(tmp_path / "exp", n_frames=2)
    header = json.loads((ws / "scene.json").read_text())
    header["crs"] = rec
    (ws / "scene.json").write_text(json.dumps(header))
    out = tmp_path / "dataset"
    export_dataset(ws, out, spec=SPEC, workers=1, frames=[1])
    manifest = json.loads(next((out / "OccuFly_Dataset").glob("*/manifest.json")).read_text())
    assert manifest["provenance"]["crs"]["epsg"] == 32632
    assert manifest["provenance"]["scene_origin"] == header["origin"]


def test_las_crs_from_wkt_or_geotiff_keys_and_point_formats(tmp_path):
    """LAS 1.4 carries the CRS as a WKT VLR, LAS 1.2 as GeoTIFF keys: both are read back."""
    import laspy

    from occufly.io.crs import cloud_crs, parse_crs
    from occufly.io.pointcloud_export import choose_point_format, write_semantic_las

    crs = parse_crs("EPSG:32632", "test")
    xyz = np.random.default_rng(0).uniform(0, 50, (20, 3)) + [512480.0, 5403120.0, 263.0]
    labels = np.arange(20, dtype=np.uint8)
    for fmt, vlr in ((7, "WktCoordinateSystemVlr"), (3, "GeoKeyDirectoryVlr")):
        p = tmp_path / f"c{fmt}.las"
        write_semantic_las(p, xyz, labels, np.zeros((20, 3), np.uint8), crs=crs, point_format=fmt)
        las = laspy.read(p)
        assert las.header.point_format.id == fmt
        assert vlr in [type(v).__name__ for v in las.header.vlrs]
        assert cloud_crs(p)[0].to_epsg() == 32632
        assert np.array_equal(np.asarray(las.classification), labels)
    assert choose_point_format(8, labels) == 8
    assert choose_point_format(3, labels) == 3  # ids <= 31 fit the 5-bit classification
    assert choose_point_format(3, np.array([36], np.uint8)) == 7  # 36 does not
    assert choose_point_format(6, labels) == 7 and choose_point_format(None, labels) == 7


def test_odm_topocentric_reconstruction_imports_to_the_same_cameras(synth, imported, tmp_path):
    """OpenSfM's own topocentric reconstruction (no coords.txt, no shots.geojson): poses go
    ENU -> ECEF -> the LAZ's UTM 32N through the local Jacobian and still match COLMAP's."""
    root, _ = synth
    _, scenes = imported
    src = tmp_path / "odm"
    shutil.copytree(root / "odm", src, copy_function=os.link)
    (src / "opensfm" / "reconstruction.json").unlink()
    (src / "opensfm" / "reconstruction.topocentric.json").rename(src / "opensfm" / "reconstruction.json")
    (src / "odm_report" / "shots.geojson").unlink()
    (src / "odm_georeferencing" / "coords.txt").unlink()
    sc = import_scene(src, tmp_path / "ws", visibility="depth")
    assert sc.meta["crs_handling"]["cameras_transformed"] is True
    ref = scenes["colmap"]
    pts = ref.xyz_world()[::25]
    for fa, fb in zip(sc.frames, ref.frames, strict=True):
        a, b = pose_in_world(fa.T_cam_world, sc.origin), pose_in_world(fb.T_cam_world, ref.origin)
        assert np.linalg.norm(-a[:3, :3].T @ a[:3, 3] + b[:3, :3].T @ b[:3, 3]) < 1e-3
        ua, _ = fa.camera.project(transform(a, pts))
        ub, zb = fb.camera.project(transform(b, pts))
        ok = (zb > 0) & fb.camera.in_image(ub)
        assert np.abs(ua[ok] - ub[ok]).max() < 0.05
