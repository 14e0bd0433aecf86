"""Readers of real ODM, Metashape and Pix4D exports (../shared/data): the facts each README lists."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from occufly.errors import InputFormatError
from occufly.io import crs as crsmod
from occufly.io.metashape import read_metashape
from occufly.io.odm import read_odm
from occufly.io.pix4d import read_pix4d
from tests.harness import SHARED_DATA, shared_data

DATA = SHARED_DATA
ODM = DATA / "odm-ortomosaico"
MS_LOCAL = DATA / "metashape-bitbyt3r-local" / "cameras.xml"
MS_WHEAT = DATA / "metashape-easyidp-wheat-tanashi" / "chunk_doc.xml"
PIX4D = DATA / "pix4d-easyidp-dji"


@pytest.fixture(autouse=True, scope="module")  # module scope: before the module's fixtures
def _shared_data_present() -> None:
    """Every test here reads ../shared/data: without it they fail (naming it), never skip."""
    for p in (ODM, MS_LOCAL, MS_WHEAT, PIX4D):
        shared_data(str(p.relative_to(SHARED_DATA)))


def centers(model) -> np.ndarray:
    return np.array([-im.T_cam_world[:3, :3].T @ im.T_cam_world[:3, 3] for im in model.images])


# ---- OpenDroneMap ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def odm():
    return read_odm(ODM)


def _geojson_centres():
    geo = json.loads((ODM / "odm_report" / "shots.geojson").read_text())
    return {f["properties"]["filename"]: np.array(f["properties"]["translation"])
            for f in geo["features"]}


def test_odm_shots_cameras_and_crs(odm):
    assert odm.kind == "odm" and len(odm.images) == 76
    assert crsmod.crs_label(odm.crs) == "WGS 84 / UTM zone 17N (EPSG:32617)"
    assert odm.meta["pose_frame"] == "utm_offset"
    cam = odm.images[0].camera
    assert cam.model == "BROWN" and (cam.width, cam.height) == (4896, 3672)
    s = 4896.0
    np.testing.assert_allclose(cam.focal, [0.7447595407084062 * s] * 2)
    # OpenSfM's pixel-centre convention -> COLMAP's: + half a pixel
    np.testing.assert_allclose(cam.principal_point,
                               [2448 + 0.014447241716532003 * s, 1836 - 0.008205488201053405 * s])


def test_odm_centres_equal_shots_geojson(odm):
    """Fact 1: C = -R^T t + offset equals shots.geojson translation (to 1e-9 m in the file)."""
    geo = _geojson_centres()
    d = [np.linalg.norm(c - geo[im.name]) for c, im in zip(centers(odm), odm.images, strict=True)]
    assert max(d) < 1e-6


def test_odm_topocentric_gps_maps_exactly_onto_coords_txt(odm):
    """gps_position stayed topocentric: ENU -> ECEF -> UTM 17N (pyproj) reproduces the
    coords.txt GPS lines (UTM minus offset) to < 1 mm -- the README's similarity fit leaves 1e-4."""
    ref = odm.meta["reference_lla"]
    names = [im.name for im in odm.images]
    topo = np.array([odm.meta["gps_position_topocentric"][n] for n in names])
    utm = crsmod.transform_points(
        crsmod.enu_to_ecef(topo, ref["latitude"], ref["longitude"], ref["altitude"]),
        crsmod.ecef_crs(), odm.crs)
    coords = np.array([odm.meta["gps_utm"][n] for n in names])
    assert np.abs(utm - coords).max() < 1e-3


def test_odm_centres_against_gps(odm):
    """Fact 2: same-frame |C - coords.txt GPS| median 0.728 m, max 2.622 m; cameras look down."""
    names = [im.name for im in odm.images]
    d = np.linalg.norm(centers(odm) - np.array([odm.meta["gps_utm"][n] for n in names]), axis=1)
    assert np.median(d) == pytest.approx(0.728, abs=0.001)
    assert d.max() == pytest.approx(2.622, abs=0.001)
    z = np.array([im.T_cam_world[2, 2] for im in odm.images])
    assert z.min() == pytest.approx(-0.99984, abs=1e-5) and z.max() == pytest.approx(-0.91116, abs=1e-5)


def test_odm_frame_decided_from_gps_without_geojson(tmp_path, odm):
    """Without shots.geojson the frame is decided by GPS residuals: still UTM-offset, same poses."""
    src = tmp_path / "odm"
    shutil.copytree(ODM, src)
    (src / "odm_report" / "shots.geojson").unlink()
    m = read_odm(src)
    assert m.meta["pose_frame"] == "utm_offset"
    np.testing.assert_allclose(centers(m), centers(odm), atol=1e-9)


def test_odm_topocentric_reconstruction_maps_to_utm(tmp_path, odm):
    """A topocentric reconstruction (as OpenSfM writes it) ends up at the same UTM centres,
    through ECEF; here rebuilt from the fixture by moving the shots into the ENU frame."""
    src = tmp_path / "odm"
    shutil.copytree(ODM, src)
    (src / "odm_report" / "shots.geojson").unlink()
    (src / "odm_georeferencing" / "coords.txt").unlink()
    rec = json.loads((ODM / "opensfm" / "reconstruction.json").read_text())
    ref = odm.meta["reference_lla"]
    from scipy.spatial.transform import Rotation

    C = centers(odm)
    ecef = crsmod.transform_points(C, odm.crs, crsmod.ecef_crs())
    R_enu = crsmod.enu_rotation(ref["latitude"], ref["longitude"])
    o = crsmod.enu_to_ecef(np.zeros((1, 3)), ref["latitude"], ref["longitude"], 0.0)[0]
    enu = (ecef - o) @ R_enu.T
    for (_name, shot), c in zip(sorted(rec[0]["shots"].items()), enu, strict=True):
        R = Rotation.from_rotvec(shot["rotation"]).as_matrix()
        shot["translation"] = (-R @ c).tolist()  # same rotation: ~0.5 deg off, irrelevant here
    (src / "opensfm" / "reconstruction.json").write_text(json.dumps(rec))
    m = read_odm(src)
    assert m.meta["pose_frame"] == "topocentric" and crsmod.crs_label(m.crs).endswith("(EPSG:4978)")
    back = crsmod.transform_points(centers(m), m.crs, odm.crs)
    np.testing.assert_allclose(back, C, atol=1e-4)


def test_odm_webodm_assets_download(tmp_path, odm):
    """No opensfm/: cameras.json (its own key, without 'v2 ') + shots.geojson give the same poses."""
    src = tmp_path / "webodm"
    (src / "odm_report").mkdir(parents=True)
    (src / "odm_georeferencing").mkdir()
    shutil.copy(ODM / "cameras.json", src)
    shutil.copy(ODM / "odm_report" / "shots.geojson", src / "odm_report")
    shutil.copy(ODM / "odm_georeferencing" / "coords.txt", src / "odm_georeferencing")
    m = read_odm(src)
    a = {im.name: im for im in m.images}
    for im in odm.images:
        np.testing.assert_allclose(a[im.name].T_cam_world, im.T_cam_world, atol=1e-6)
        assert a[im.name].camera == im.camera


def test_odm_webodm_downscaled_cameras_json_rescaled(tmp_path):
    src = tmp_path / "webodm"
    (src / "odm_report").mkdir(parents=True)
    (src / "odm_georeferencing").mkdir()
    cams = json.loads((ODM / "cameras.json").read_text())
    for c in cams.values():
        c["width"], c["height"] = 2448, 1836  # a half-size download
    (src / "cameras.json").write_text(json.dumps(cams))
    shutil.copy(ODM / "odm_report" / "shots.geojson", src / "odm_report")
    shutil.copy(ODM / "odm_georeferencing" / "coords.txt", src / "odm_georeferencing")
    m = read_odm(src)
    cam = m.images[0].camera
    assert (cam.width, cam.height) == (4896, 3672)
    np.testing.assert_allclose(cam.focal[0], 0.7447595407084062 * 4896)
    assert any("rescaled" in n for n in m.notes)


def test_odm_partial_reconstructions_take_largest(tmp_path):
    src = tmp_path / "odm"
    shutil.copytree(ODM, src)
    rec = json.loads((ODM / "opensfm" / "reconstruction.json").read_text())
    small = {"cameras": rec[0]["cameras"], "shots": dict(list(rec[0]["shots"].items())[:3]),
             "points": {}}
    (src / "opensfm" / "reconstruction.json").write_text(json.dumps([small, rec[0]]))
    m = read_odm(src)
    assert len(m.images) == 76
    assert any("2 partial reconstructions" in n and "#0: 3 shots" in n for n in m.notes)


@pytest.mark.parametrize("proj", ["spherical", "equirectangular", "dual"])
def test_odm_unsupported_projection(tmp_path, proj):
    src = tmp_path / "odm"
    shutil.copytree(ODM, src)
    rec = json.loads((ODM / "opensfm" / "reconstruction.json").read_text())
    next(iter(rec[0]["cameras"].values()))["projection_type"] = proj
    (src / "opensfm" / "reconstruction.json").write_text(json.dumps(rec))
    with pytest.raises(InputFormatError, match=f"reconstruction.json.*projection type '{proj}'"):
        read_odm(src)


def test_odm_fisheye_camera(tmp_path):
    from occufly.io.odm import opensfm_camera

    cam = opensfm_camera({"projection_type": "fisheye", "width": 4000, "height": 3000,
                          "focal": 0.5, "k1": -0.01, "k2": 0.002}, "x")
    assert cam.model == "OPENCV_FISHEYE"
    np.testing.assert_allclose(cam.params, [2000, 2000, 2000, 1500, -0.01, 0.002, 0, 0])


# ---- Metashape -------------------------------------------------------------------------------
def test_metashape_local_export_cameras():
    m = read_metashape(MS_LOCAL)
    assert m.kind == "metashape" and len(m.images) == 94
    assert m.crs is None and m.local_frame and m.meta["reference"] == "local (no CRS)"
    assert len({im.camera for im in m.images}) == 94  # one sensor per camera
    cam = m.images[0].camera
    assert cam.model == "METASHAPE" and (cam.width, cam.height) == (5184, 3456)
    # no <cx>/<cy>: the principal point is the image centre; fx = f + b1, skew = b2
    assert cam.principal_point == (2592.0, 1728.0)
    assert cam.focal == pytest.approx((8397.0800252741 + 0.256163863908223, 8397.0800252741))
    assert cam.skew == pytest.approx(-22.8315524998528)
    # no chunk transform: the camera centre is the last column of <transform>
    import xml.etree.ElementTree as ET

    el = next(c for c in ET.parse(MS_LOCAL).getroot().iter("camera") if c.get("label") == "001")
    M = np.array([float(v) for v in el.find("transform").text.split()]).reshape(4, 4)
    assert m.images[0].name == "001"
    np.testing.assert_allclose(centers(m)[0], M[:3, 3], atol=1e-12)
    np.testing.assert_allclose(m.images[0].T_cam_world[:3, :3], M[:3, :3].T, atol=1e-12)


def test_metashape_wheat_chunk_to_wgs84():
    """ECEF = s R C_chunk + T -> WGS 84 within median 1.79 m / max 3.27 m of the cameras'
    reference lon/lat; ellipsoid height minus reference z median +4.89 m."""
    import pyproj

    m = read_metashape(MS_WHEAT)
    assert len(m.images) == 138 and m.crs.to_epsg() == 4978 and m.output_crs.to_epsg() == 4326
    cam = m.images[0].camera
    np.testing.assert_allclose(cam.principal_point, [2304 + 48.037918055786299, 1728 - 73.278107967250861])
    lonlath = crsmod.transform_points(centers(m), m.crs, pyproj.CRS.from_epsg(4979))
    ref = np.array([m.meta["reference_positions"][im.name] for im in m.images])
    _, _, dist = pyproj.Geod(ellps="WGS84").inv(lonlath[:, 0], lonlath[:, 1], ref[:, 0], ref[:, 1])
    assert np.median(dist) == pytest.approx(1.79, abs=0.01)
    assert dist.max() == pytest.approx(3.27, abs=0.01)
    assert np.median(lonlath[:, 2] - ref[:, 2]) == pytest.approx(4.89, abs=0.01)
    # a drone survey: every camera looks down (local up from the ENU frame at each camera)
    up = np.array([crsmod.enu_rotation(la, lo)[2] for lo, la in lonlath[:, :2]])
    look = np.array([im.T_cam_world[2, :3] for im in m.images])
    assert (np.einsum("ij,ij->i", up, look) < -0.9).all()


def test_metashape_unaligned_disabled_and_missing_calibration(tmp_path):
    text = MS_LOCAL.read_text()
    # camera 001 loses its transform, camera 002 is disabled
    a = text.index('label="001">')
    t0 = text.index("<transform>", a)
    t1 = text.index("</transform>", a) + len("</transform>")
    text = text[:t0] + text[t1:]
    text = text.replace('label="002">', 'label="002" enabled="false">', 1)
    p = tmp_path / "cams.xml"
    p.write_text(text)
    m = read_metashape(p)
    assert len(m.images) == 92
    assert m.meta["unaligned"] == ["001"] and m.meta["disabled"] == ["002"]
    assert any("not aligned, skipped: 001" in n for n in m.notes)
    # a sensor without calibration, used by an aligned camera: error naming file and sensor
    s0 = text.index('<sensor id="8"')
    c0 = text.index("<calibration", s0)
    c1 = text.index("</calibration>", s0) + len("</calibration>")
    p.write_text(text[:c0] + text[c1:])
    with pytest.raises(InputFormatError, match=r"cams.xml: sensor 8 .* has no <calibration>.*camera .003."):
        read_metashape(p)


def test_metashape_not_xml_and_wrong_root(tmp_path):
    p = tmp_path / "x.xml"
    p.write_text("<document><chunk>")
    with pytest.raises(InputFormatError, match="x.xml: not valid XML"):
        read_metashape(p)
    p.write_text("<kml/>")
    with pytest.raises(InputFormatError, match="root element <kml>"):
        read_metashape(p)


# ---- Pix4D -----------------------------------------------------------------------------------
def test_pix4d_params_and_pmatrix():
    """t is relative to the offset (DJI_0172 t = 15.94 -29.03 15.15); K [R | -R t] equals the
    pmatrix row of every image to 4e-8 relative (after normalising P[2, 3])."""
    m = read_pix4d(PIX4D)
    assert m.kind == "pix4d" and len(m.images) == 168 and m.crs is None
    off = np.array([368109.0, 3956043.0, 96.0])
    assert m.meta["offset"] == off.tolist()
    im = m.images[0]
    assert im.name == "DJI_0172.JPG" and (im.camera.width, im.camera.height) == (5472, 3648)
    np.testing.assert_allclose(centers(m)[0] - off, [15.94074806386806, -29.02692220459498,
                                                     15.15422636680995], atol=1e-9)
    pm = {}
    for ln in (PIX4D / "1_initial" / "params" / "pix4d.origin_pmatrix.txt").read_text().splitlines():
        p = ln.split()
        pm[p[0]] = np.array([float(v) for v in p[1:]]).reshape(3, 4)
    worst = 0.0
    for im in m.images:
        T = im.T_cam_world.copy()
        T[:3, 3] += T[:3, :3] @ off  # back to offset-relative world
        P = im.camera.K @ T[:3]
        a, b = P / P[2, 3], pm[im.name] / pm[im.name][2, 3]
        worst = max(worst, np.abs(a - b).max() / np.abs(b).max())
    assert worst < 4e-8
    # the .cam file's principal point offset in pixels is relative to W/2, H/2
    assert im.camera.principal_point[0] - 2736 == pytest.approx(70.80399985351096)


def test_pix4d_truncated_block(tmp_path):
    d = tmp_path / "1_initial" / "params"
    shutil.copytree(PIX4D / "1_initial" / "params", d)
    p = d / "pix4d.origin_calibrated_camera_parameters.txt"
    lines = p.read_text().splitlines()
    p.write_text("\n".join(lines[:20]) + "\n")
    with pytest.raises(InputFormatError, match="calibrated_camera_parameters.txt:.*truncated"):
        read_pix4d(tmp_path)
    (d / "pix4d.origin_offset.xyz").unlink()
    with pytest.raises(InputFormatError, match="offset.xyz: missing"):
        read_pix4d(tmp_path)


def test_image_names_must_stay_inside_the_image_folder(tmp_path):
    from occufly.io.sources import read_source

    src = tmp_path / "odm"
    shutil.copytree(ODM, src)
    rec = json.loads((ODM / "opensfm" / "reconstruction.json").read_text())
    shots = rec[0]["shots"]
    shots["../../etc/secret.JPG"] = shots.pop(next(iter(shots)))
    (src / "opensfm" / "reconstruction.json").write_text(json.dumps(rec))
    with pytest.raises(InputFormatError, match=r"reconstruction.json: image name '../../etc/secret.JPG'"):
        read_source(src)
    xml = MS_LOCAL.read_text().replace('label="002">', 'label="001">', 1)
    p = tmp_path / "dup.xml"
    p.write_text(xml)
    with pytest.raises(InputFormatError, match=r"dup.xml: 1 image name\(s\) used by several cameras \(001\)"):
        read_source(p)


def _make_psx(root: Path, photo_dir: Path) -> Path:
    """A Metashape .psx project around the wheat chunk: project.zip -> 0/chunk.zip (the real
    doc.xml) -> 0/0/frame.zip with each camera's photo path (relative to the frame zip)."""
    import os
    import xml.etree.ElementTree as ET
    import zipfile

    files = root / "wheat.files"
    (files / "0" / "0").mkdir(parents=True)
    psx = root / "wheat.psx"
    psx.write_text('<?xml version="1.0" encoding="UTF-8"?>\n'
                   '<document version="1.2.0" path="{projectname}.files/project.zip"/>\n')
    with zipfile.ZipFile(files / "project.zip", "w") as z:
        z.writestr("doc.xml", '<document version="1.2.0"><chunks next_id="1">'
                              '<chunk id="0" path="0/chunk.zip"/></chunks></document>')
    text = MS_WHEAT.read_text()
    with zipfile.ZipFile(files / "0" / "chunk.zip", "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("doc.xml", text)
    ids = [(c.get("id"), c.get("label")) for c in ET.fromstring(text).find("cameras").iter("camera")]
    rel = os.path.relpath(photo_dir, files / "0" / "0")
    cams = "".join(f'<camera camera_id="{i}"><photo path="{rel}/{lab}.JPG"/></camera>'
                   for i, lab in ids)
    with zipfile.ZipFile(files / "0" / "0" / "frame.zip", "w") as z:
        z.writestr("doc.xml", f'<frame version="1.2.0"><cameras>{cams}</cameras></frame>')
    return psx


def test_metashape_psx_project(tmp_path):
    from occufly.io.sources import detect_format, read_source

    photos = tmp_path / "flight" / "photos"
    photos.mkdir(parents=True)
    psx = _make_psx(tmp_path / "proj", photos)
    assert detect_format(psx) == "metashape" and detect_format(psx.parent) == "metashape"
    m = read_source(psx)
    ref = read_metashape(MS_WHEAT)
    assert len(m.images) == 138 and m.images[0].name == "DJI_0001.JPG"
    assert m.default_images == photos.resolve()
    np.testing.assert_allclose(centers(m), centers(ref))
    (tmp_path / "proj" / "wheat.files" / "0" / "chunk.zip").write_bytes(b"PK not a zip")
    with pytest.raises(InputFormatError, match=r"chunk.zip: not a Metashape project zip"):
        read_source(psx)
