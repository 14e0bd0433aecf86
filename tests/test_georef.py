"""Issue 26 defect 1: a geotagged, non-georeferenced COLMAP model made metric from its photos'
GPS (real DJI Toledo files: the README's facts), the robust similarity, DJI XMP parsing."""

from __future__ import annotations

import numpy as np
import pytest

from occufly.io.exif import read_geotag
from occufly.io.georef import GeorefParams, robust_similarity, umeyama
from tests.harness import SHARED_DATA, shared_data

TOLEDO = SHARED_DATA / "colmap-dji-toledo"


def _rot(a, b, c):
    ca, sa, cb, sb, cc, sc = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(c), np.sin(c)
    Rz = np.array([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rx = np.array([[1, 0, 0], [0, cc, -sc], [0, sc, cc]])
    return Rz @ Ry @ Rx


def test_umeyama_exact_and_ransac_rejects_outliers():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(30, 3)) * [5, 2, 0.1]
    R, s, t = _rot(0.7, 0.1, -0.2), 12.5, np.array([274900.0, 4603200.0, 119.0])
    dst = s * src @ R.T + t
    s1, R1, t1 = (v[0] for v in umeyama(src[None], dst[None]))
    assert s1 == pytest.approx(s, rel=1e-9) and np.allclose(R1, R, atol=1e-9)
    assert np.allclose(t1, t, atol=1e-6)
    bad = dst.copy()
    bad[[2, 11, 17]] += [40.0, -25.0, 10.0]  # three GPS fixes 30-50 m off
    s2, R2, _, inl = robust_similarity(src, bad, GeorefParams())
    assert sorted(np.flatnonzero(~inl)) == [2, 11, 17]
    assert s2 == pytest.approx(s, rel=1e-6) and np.allclose(R2, R, atol=1e-6)
    s3 = umeyama(src[None], bad[None])[0][0]  # without rejection the scale is off
    assert abs(s3 - s) > 0.05


def test_dji_xmp_read(tmp_path):
    from PIL import Image

    xmp = (b'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF><rdf:Description '
           b'drone-dji:RelativeAltitude="+50.20" drone-dji:GimbalPitchDegree="-90.0" '
           b'drone-dji:RtkFlag="50" drone-dji:RtkStdLon="0.012"><drone-dji:RtkStdHgt>0.031'
           b'</drone-dji:RtkStdHgt></rdf:Description></rdf:RDF></x:xmpmeta>')
    p = tmp_path / "a.jpg"
    Image.new("RGB", (8, 8)).save(p, xmp=xmp)
    g = read_geotag(p)
    assert g.relative_altitude == pytest.approx(50.2) and g.gimbal_pitch == -90.0
    assert g.rtk_flag == 50 and g.rtk_std_lon == pytest.approx(0.012)
    assert g.rtk_std_hgt == pytest.approx(0.031) and not g.has_gps


def test_toledo_import_is_metric(tmp_path):
    from occufly.io.importer import import_scene

    shared_data("colmap-dji-toledo")
    g = read_geotag(TOLEDO / "images" / "DJI_0061.JPG")
    assert g.lat == pytest.approx(41.5485962, abs=1e-7)
    assert g.lon == pytest.approx(-83.6986488, abs=1e-7)
    assert g.altitude == 119.7 and g.focal_35mm == 20 and g.model == "FC350"

    scene = import_scene(TOLEDO, tmp_path / "ws", visibility="vis")
    meta = scene.meta
    geo = meta["georeferencing"]
    assert meta["georeferenced"] is True and scene.crs["epsg"] == 32617
    assert geo["scale"] == pytest.approx(12.9906, abs=2e-3)
    assert geo["rms_m"] == pytest.approx(1.365, abs=0.01)
    assert geo["median_m"] == pytest.approx(1.325, abs=0.01)
    assert geo["max_m"] == pytest.approx(2.011, abs=0.01)
    assert geo["inliers"] == 22 and len(geo["residuals_m"]) == 22
    # camera centres land on their UTM positions (README table, DJI_0061)
    f = next(fr for fr in scene.frames if fr.name == "DJI_0061.JPG")
    c = -f.T_cam_world[:3, :3].T @ f.T_cam_world[:3, 3] + scene.origin
    assert np.allclose(c, [274921.605, 4603176.409, 119.7], atol=geo["residuals_m"]["DJI_0061.JPG"] + 1e-3)
    # the sparse points: median height 55.3 m (README fact 2)
    z = scene.xyz[:, 2].astype(np.float64) + scene.origin[2]
    assert np.median(z) == pytest.approx(55.3, abs=0.2)
    focal = [w for w in meta["import_warnings"] if "focal" in w]
    assert len(focal) == 1 and "1.70" in focal[0] and "783.7" in focal[0]


def test_metashape_folder_imports_with_its_cloud(tmp_path):
    """Defect 2: ``synth --format metashape`` output imports with no flags (the cloud beside
    cameras.xml is found); several clouds are listed; none says what was looked for."""
    import shutil

    from occufly.errors import InputFormatError
    from occufly.io.importer import import_scene
    from occufly.synthetic.formats import generate_formats

    root = tmp_path / "synth"
    generate_formats(root, ("metashape",), preset="tiny", seed=0, nested=True)
    src = root / "metashape"
    scene = import_scene(src, tmp_path / "ws", visibility="depth")
    assert scene.meta["cloud"].endswith("dense_cloud.laz") and scene.crs["epsg"] == 32632
    assert scene.n_points > 1000  # the dense cloud, not the sparse points
    shutil.copy(src / "dense_cloud.laz", src / "other.las")
    with pytest.raises(InputFormatError, match="several point clouds.*dense_cloud.laz, other.las"):
        import_scene(src, tmp_path / "ws2")
    (src / "other.las").unlink()
    (src / "dense_cloud.laz").unlink()
    with pytest.raises(InputFormatError, match=r"no \.las/\.laz/\.ply file beside cameras.xml"):
        import_scene(src, tmp_path / "ws3")
