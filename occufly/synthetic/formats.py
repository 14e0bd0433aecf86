"""The synthetic scene written as each photogrammetry tool exports it (``synth --format``).

One render of the procedural survey (:func:`occufly.synthetic.generate`) through a lens with
realistic Brown distortion (``FULL_OPENCV`` in COLMAP terms: k1, k2, k3 radial, p1, p2
tangential, fx != fy, principal point off centre), georeferenced in UTM zone 32N (EPSG:32632),
is written in each tool's own conventions, so one exact truth tests every importer:

``colmap``     ``images/``, ``sparse/*.bin`` (FULL_OPENCV), ``dense/fused.ply`` (+ ``.vis``,
               + ``fused.ply.prj``: the CRS), ``dense/stereo/depth_maps/``
``odm``        ``images/``, ``opensfm/reconstruction.json`` (brown camera normalised by
               max(w, h), OpenSfM pixel-centre convention; poses rewritten into UTM minus the
               ``coords.txt`` offset as ODM does) + ``reconstruction.topocentric.json`` (the
               topocentric original), ``reference_lla.json``, ``camera_models.json``,
               ``cameras.json``, ``img_list.txt``, ``odm_georeferencing/coords.txt`` +
               ``odm_georeferenced_model.laz`` (with its CRS record), ``odm_report/shots.geojson``
``metashape``  ``images/``, ``cameras.xml`` (Export Cameras: f, cx/cy offsets from the image
               centre, b1 = fx - fy, k1-k3, p1/p2 in Metashape's order; camera-to-chunk
               transforms, a chunk similarity to ECEF, ``<reference>`` WGS 84), ``dense_cloud.laz``
``pix4d``      ``images/``, ``1_initial/params/synthetic_{calibrated_camera_parameters.txt,
               offset.xyz, wkt.prj, pmatrix.txt}``, ``2_densification/point_cloud/
               synthetic_group1_densified_point_cloud.laz``

Every format has the same ``truth/`` (masks, point labels, scene grid). The dense cloud is the
same points in every format, on the LAS millimetre grid (the COLMAP ``fused.ply`` holds those
values too), so imports can be compared point for point. GPS positions (ODM ``gps_position``,
``coords.txt``, Metashape camera ``<reference>``) carry seeded noise of 0.5 m / 0.3 m (sigma,
horizontal / vertical) like a consumer receiver; the poses are exact.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from occufly.camera import Camera
from occufly.errors import OccuflyError, WorkspaceError
from occufly.fsutil import atomic_directory
from occufly.io import crs as crsmod
from occufly.io.colmap import read_sparse_model
from occufly.io.colmap_dense import write_fused_ply
from occufly.io.ply import read_ply
from occufly.io.pointcloud import read_point_cloud
from occufly.io.pointcloud_export import LAS_SCALE, write_semantic_las
from occufly.progress import ProgressFn, noop
from occufly.synthetic.generate import generate
from occufly.synthetic.presets import get_preset

FORMATS = ("colmap", "odm", "metashape", "pix4d")
CRS_EPSG = 32632
PIX4D_PROJECT = "synthetic"
# a consumer drone lens (cf. the DJI / Sony calibrations in ../shared/data), barrel distortion
LENS = {"k1": -0.045, "k2": 0.032, "k3": -0.008, "p1": 0.0012, "p2": -0.0009,
        "fx_over_fy": 1.0008, "cx_shift": 0.013, "cy_shift": -0.009}


def lens_camera(preset) -> Camera:
    """The preset's camera (same field of view) with the distortion of :data:`LENS`."""
    f = (preset.width / 2) / math.tan(math.radians(preset.hfov_deg) / 2)
    L = LENS
    return Camera("FULL_OPENCV", preset.width, preset.height, [
        f * L["fx_over_fy"], f, preset.width * (0.5 + L["cx_shift"]),
        preset.height * (0.5 + L["cy_shift"]), L["k1"], L["k2"], L["p1"], L["p2"], L["k3"],
        0.0, 0.0, 0.0])


def _is_nonempty_dir(p: Path) -> bool:
    return p.exists() and (not p.is_dir() or any(p.iterdir()))


def generate_formats(out: str | Path, formats: list[str] | tuple[str, ...], *,
                     preset: str = "small", seed: int = 0, progress: ProgressFn | None = None,
                     overwrite: bool = False, nested: bool | None = None) -> dict:
    """Render the scene once and write it in every format of ``formats``.

    With one format (``nested`` False, the default then) the project is ``out`` itself; with
    several, ``out/<format>``. The whole output appears atomically or not at all.
    """
    formats = list(dict.fromkeys(formats))
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise OccuflyError(f"--format {', '.join(bad) or '(none)'}: expected one of "
                           f"{', '.join(FORMATS)}")
    out = Path(out)
    if _is_nonempty_dir(out) and not overwrite:
        raise WorkspaceError(f"{out}: exists and is not empty (use --force to replace it)")
    nested = len(formats) > 1 if nested is None else nested
    report = progress or noop
    P = get_preset(preset)
    cam = lens_camera(P)
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    with atomic_directory(out, overwrite=True) as tmp:
        base = tmp / ".base"
        summary = generate(base, preset=preset, seed=seed, camera=cam,
                           progress=lambda f, m="": report(0.8 * f, m))
        timings["render"] = round(time.perf_counter() - t0, 3)
        src = _BaseScene(base, cam, seed)
        for i, fmt in enumerate(formats):
            t1 = time.perf_counter()
            dest = tmp / fmt if nested else tmp
            dest.mkdir(exist_ok=True)
            {"colmap": src.write_colmap, "odm": src.write_odm, "metashape": src.write_metashape,
             "pix4d": src.write_pix4d}[fmt](dest)
            src.copy_common(dest)
            timings[fmt] = round(time.perf_counter() - t1, 3)
            report(0.8 + 0.2 * (i + 1) / len(formats), f"writing {fmt}")
        shutil.rmtree(base)
    return {**summary, "out": str(out), "formats": formats, "crs": f"EPSG:{CRS_EPSG}",
            "camera": cam.to_dict(), "format_timings": timings,
            "import": {f: import_hint(out / f if nested else out, f) for f in formats}}


def import_hint(root: Path, fmt: str) -> str:
    """The command that imports a synthetic project of this format."""
    if fmt == "metashape":
        return f"occufly import {root / 'cameras.xml'} --cloud {root / 'dense_cloud.laz'} -w WS"
    return f"occufly import {root} -w WS"


def _copy(src: Path, dst: Path) -> None:
    """A real copy, not a hard link: the web app's imports refuse hard-linked files (a link in
    an import root may be any file of its disk; occufly.io.importer.refuse_hard_link), and a
    generated project must import there like one from the real tool."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy2(src, dst)


def _copy_tree(src: Path, dst: Path) -> None:
    for p in sorted(src.rglob("*")):
        if p.is_file():
            _copy(p, dst / p.relative_to(src))


def _f(v: float) -> str:
    return repr(float(v))


class _BaseScene:
    """The rendered COLMAP workspace, read back once: poses, cloud, camera, GPS."""

    def __init__(self, base: Path, camera: Camera, seed: int) -> None:
        self.base = base
        self.camera = camera
        self.crs = crsmod._pyproj().CRS.from_epsg(CRS_EPSG)
        model = read_sparse_model(base)
        self.names = [im.name for im in model.images]
        self.T_utm = [im.T_cam_world for im in model.images]
        self.C_utm = np.array([-T[:3, :3].T @ T[:3, 3] for T in self.T_utm])
        self.sparse_xyz, self.sparse_rgb = model.xyz, model.rgb
        xyz, self.rgb = read_point_cloud(base / "dense" / "fused.ply")
        # the LAS millimetre grid, computed exactly as laspy decodes it (X * scale + offset)
        self.las_offset = np.floor(xyz.min(axis=0))
        X = np.rint((xyz - self.las_offset) / LAS_SCALE).astype(np.int64)
        self.xyz = X.astype(np.float64) * LAS_SCALE + self.las_offset
        rng = np.random.default_rng([seed, 0x6B5])
        noise = rng.normal(0.0, 1.0, (len(self.names), 3)) * np.array([0.5, 0.5, 0.3])
        self.gps_utm = self.C_utm + noise
        c = self.C_utm.mean(axis=0)
        to_geo = crsmod._pyproj().Transformer.from_crs(self.crs.to_3d(), 4979, always_xy=True)
        lon, lat, _ = to_geo.transform(c[0], c[1], 0.0)
        self.ref_lla = {"latitude": float(lat), "longitude": float(lon), "altitude": 0.0}
        self._to_geo = to_geo

    # ---- shared ---------------------------------------------------------------------------
    def copy_common(self, dest: Path) -> None:
        _copy_tree(self.base / "images", dest / "images")
        _copy_tree(self.base / "truth", dest / "truth")

    def write_cloud_las(self, path: Path) -> None:
        write_semantic_las(path, self.xyz, np.zeros(len(self.xyz), np.uint8), self.rgb,
                           crs=self.crs)

    def _opencv(self) -> dict:
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = self.camera.params[:9]
        return {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "k1": k1, "k2": k2, "k3": k3,
                "p1": p1, "p2": p2}

    # ---- COLMAP ---------------------------------------------------------------------------
    def write_colmap(self, dest: Path) -> None:
        _copy_tree(self.base / "sparse", dest / "sparse")
        _copy_tree(self.base / "dense" / "stereo", dest / "dense" / "stereo")
        _copy(self.base / "dense" / "fused.ply.vis", dest / "dense" / "fused.ply.vis")
        normals = read_ply(self.base / "dense" / "fused.ply").normals
        if normals is None:
            normals = np.zeros_like(self.xyz)
        write_fused_ply(dest / "dense" / "fused.ply", self.xyz, normals, self.rgb, double=True)
        (dest / "dense" / "fused.ply.prj").write_text(self.crs.to_wkt(version="WKT1_ESRI"))

    # ---- OpenDroneMap ---------------------------------------------------------------------
    def write_odm(self, dest: Path) -> None:
        c, W, H = self._opencv(), self.camera.width, self.camera.height
        s = float(max(W, H))
        key = f"synthetic occufly-lens {W} {H} brown 0.85"
        cam = {"projection_type": "brown", "width": W, "height": H,
               "focal_x": c["fx"] / s, "focal_y": c["fy"] / s,
               "c_x": (c["cx"] - W / 2.0) / s, "c_y": (c["cy"] - H / 2.0) / s,
               "k1": c["k1"], "k2": c["k2"], "p1": c["p1"], "p2": c["p2"], "k3": c["k3"]}
        offset = np.array([round(float(self.C_utm[:, 0].mean())),
                           round(float(self.C_utm[:, 1].mean())), 0.0])
        ecef = crsmod.crs_mapping(self.crs, crsmod.ecef_crs())
        T_ecef, _ = crsmod.map_poses(self.T_utm, ecef)
        R_enu = crsmod.enu_rotation(self.ref_lla["latitude"], self.ref_lla["longitude"])
        o_ecef = crsmod.enu_to_ecef(np.zeros((1, 3)), self.ref_lla["latitude"],
                                    self.ref_lla["longitude"], 0.0)[0]

        def ecef_to_enu(x: np.ndarray) -> np.ndarray:
            return (np.asarray(x, np.float64).reshape(-1, 3) - o_ecef) @ R_enu.T

        gps_topo = ecef_to_enu(ecef(self.gps_utm))
        shots_utm, shots_topo = {}, {}
        for i, name in enumerate(self.names):
            R, t = self.T_utm[i][:3, :3], self.T_utm[i][:3, 3]
            common = {"camera": "v2 " + key, "orientation": 1, "capture_time": 1.7e9 + 2.0 * i,
                      "gps_dop": 5.0, "gps_position": gps_topo[i].tolist(), "vertices": [],
                      "faces": [], "scale": 1.0, "covariance": [], "merge_cc": 0}
            # ODM's georeferenced reconstruction: x_cam = R (x_utm - offset) + t'
            shots_utm[name] = {"rotation": Rotation.from_matrix(R).as_rotvec().tolist(),
                               "translation": (t + R @ offset).tolist(), **common}
            Te = T_ecef[i]
            R_topo = Te[:3, :3] @ R_enu.T  # x_cam = Re (o + R_enu^T e) + te
            t_topo = Te[:3, :3] @ o_ecef + Te[:3, 3]
            shots_topo[name] = {"rotation": Rotation.from_matrix(R_topo).as_rotvec().tolist(),
                                "translation": t_topo.tolist(), **common}
        pts_off = self.sparse_xyz - offset
        pts_topo = ecef_to_enu(ecef(self.sparse_xyz)) if len(self.sparse_xyz) else pts_off

        def recon(shots, pts):
            return [{"cameras": {"v2 " + key: cam}, "shots": shots,
                     "points": {str(k): {"color": self.sparse_rgb[k].astype(float).tolist(),
                                         "coordinates": pts[k].tolist()} for k in range(len(pts))},
                     "biases": {"v2 " + key: {"rotation": [0.0, 0.0, 0.0],
                                              "translation": [0.0, 0.0, 0.0], "scale": 1.0}},
                     "rig_cameras": {"v2 " + key: {"rotation": [0.0, 0.0, 0.0],
                                                   "translation": [0.0, 0.0, 0.0]}},
                     "rig_instances": {n: {"translation": s_["translation"],
                                           "rotation": s_["rotation"],
                                           "rig_camera_ids": {n: "v2 " + key}}
                                       for n, s_ in shots.items()},
                     "reference_lla": self.ref_lla}]

        osfm = dest / "opensfm"
        osfm.mkdir(parents=True)
        (osfm / "reconstruction.json").write_text(json.dumps(recon(shots_utm, pts_off), indent=1))
        (osfm / "reconstruction.topocentric.json").write_text(
            json.dumps(recon(shots_topo, pts_topo), indent=1))
        (osfm / "reference_lla.json").write_text(json.dumps(self.ref_lla, indent=4))
        prior = dict(cam, focal_x=0.85, focal_y=0.85, c_x=0.0, c_y=0.0,
                     k1=0.0, k2=0.0, p1=0.0, p2=0.0, k3=0.0)
        (osfm / "camera_models.json").write_text(json.dumps({"v2 " + key: prior}, indent=4))
        (dest / "cameras.json").write_text(json.dumps({key: cam}, indent=4))
        (dest / "img_list.txt").write_text("".join(f"{n}\n" for n in self.names))
        geo = dest / "odm_georeferencing"
        geo.mkdir()
        gps_off = self.gps_utm - offset
        zone = CRS_EPSG - 32600
        (geo / "coords.txt").write_text(
            f"WGS84 UTM {zone}N\n{int(offset[0])} {int(offset[1])}\n"
            + "".join(f"{_f(g[0])} {_f(g[1])} {_f(g[2])}\n" for g in gps_off))
        self.write_cloud_las(geo / "odm_georeferenced_model.laz")
        rep = dest / "odm_report"
        rep.mkdir()
        feats = []
        for i, name in enumerate(self.names):
            lon, lat, _ = self._to_geo.transform(*self.C_utm[i][:2], 0.0)
            feats.append({"type": "Feature", "properties": {
                "filename": name, "camera": "v2 " + key, "focal": cam["focal_x"], "width": W,
                "height": H, "capture_time": shots_utm[name]["capture_time"],
                "translation": self.C_utm[i].tolist(), "rotation": shots_utm[name]["rotation"]},
                "geometry": {"type": "Point", "coordinates": [lon, lat, float(self.C_utm[i][2])]}})
        (rep / "shots.geojson").write_text(json.dumps({"type": "FeatureCollection",
                                                      "features": feats}))

    # ---- Metashape ------------------------------------------------------------------------
    def write_metashape(self, dest: Path) -> None:
        c, W, H = self._opencv(), self.camera.width, self.camera.height
        ecef = crsmod.crs_mapping(self.crs, crsmod.ecef_crs())
        T_ecef, _ = crsmod.map_poses(self.T_utm, ecef)
        # the chunk frame: an arbitrary similarity of ECEF (Metashape's internal frame)
        R_enu = crsmod.enu_rotation(self.ref_lla["latitude"], self.ref_lla["longitude"])
        a = math.radians(25.0)
        Rz = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        R_ch = R_enu.T @ Rz  # chunk -> ECEF rotation
        s_ch = 1.7
        T_ch = ecef(self.C_utm.mean(axis=0, keepdims=True))[0]
        lines = ['<?xml version="1.0" encoding="UTF-8"?>', '<document version="1.5.0">',
                 '  <chunk label="Chunk 1" enabled="true">', '    <sensors next_id="1">',
                 '      <sensor id="0" label="OccuFly synthetic lens" type="frame">',
                 f'        <resolution width="{W}" height="{H}"/>',
                 '        <calibration type="frame" class="adjusted">',
                 f'          <resolution width="{W}" height="{H}"/>',
                 f'          <f>{_f(c["fy"])}</f>', f'          <cx>{_f(c["cx"] - W / 2.0)}</cx>',
                 f'          <cy>{_f(c["cy"] - H / 2.0)}</cy>',
                 f'          <b1>{_f(c["fx"] - c["fy"])}</b1>',
                 f'          <k1>{_f(c["k1"])}</k1>', f'          <k2>{_f(c["k2"])}</k2>',
                 f'          <k3>{_f(c["k3"])}</k3>',
                 # Metashape's p1 multiplies (r^2 + 2x^2) in x: OpenCV's p2, and vice versa
                 f'          <p1>{_f(c["p2"])}</p1>', f'          <p2>{_f(c["p1"])}</p2>',
                 '        </calibration>', '      </sensor>', '    </sensors>',
                 f'    <cameras next_id="{len(self.names)}" next_group_id="0">']
        to_geo = crsmod._pyproj().Transformer.from_crs(self.crs.to_3d(), 4979, always_xy=True)
        for i, name in enumerate(self.names):
            Te = T_ecef[i]
            R_wc = Te[:3, :3].T
            C_e = -R_wc @ Te[:3, 3]
            M = np.eye(4)
            M[:3, :3] = R_ch.T @ R_wc
            M[:3, 3] = R_ch.T @ (C_e - T_ch) / s_ch
            lon, lat, h = to_geo.transform(*self.gps_utm[i])
            lines += [f'      <camera id="{i}" sensor_id="0" label="{Path(name).stem}">',
                      f'        <transform>{" ".join(_f(v) for v in M.ravel())}</transform>',
                      f'        <reference x="{_f(lon)}" y="{_f(lat)}" z="{_f(h)}" enabled="true"/>',
                      '      </camera>']
        geogcs = crsmod._pyproj().CRS.from_epsg(4326).to_wkt(version="WKT1_GDAL")
        lines += ['    </cameras>', '    <transform>',
                  f'      <rotation locked="true">{" ".join(_f(v) for v in R_ch.ravel())}</rotation>',
                  f'      <translation locked="true">{" ".join(_f(v) for v in T_ch)}</translation>',
                  f'      <scale locked="true">{_f(s_ch)}</scale>', '    </transform>',
                  f'    <reference>{geogcs}</reference>', '  </chunk>', '</document>', '']
        (dest / "cameras.xml").write_text("\n".join(lines))
        self.write_cloud_las(dest / "dense_cloud.laz")

    # ---- Pix4D ----------------------------------------------------------------------------
    def write_pix4d(self, dest: Path) -> None:
        c, W, H = self._opencv(), self.camera.width, self.camera.height
        params = dest / "1_initial" / "params"
        params.mkdir(parents=True)
        offset = np.floor(self.C_utm.mean(axis=0))
        K = np.array([[c["fx"], 0.0, c["cx"]], [0.0, c["fy"], c["cy"]], [0.0, 0.0, 1.0]])
        out = ["fileName imageWidth imageHeight ", "camera matrix K [3x3]",
               "radial distortion [3x1]", "tangential distortion [2x1]",
               "camera position t [3x1]", "camera rotation R [3x3]",
               "camera model m = K [R|-Rt] X", ""]
        pm = []
        for i, name in enumerate(self.names):
            R = self.T_utm[i][:3, :3]
            t = self.C_utm[i] - offset
            out.append(f"{name} {W} {H}")
            out += [" ".join(_f(v) for v in row) for row in K]
            out.append(f"{_f(c['k1'])} {_f(c['k2'])} {_f(c['k3'])}")
            out.append(f"{_f(c['p1'])} {_f(c['p2'])}")
            out.append(" ".join(_f(v) for v in t))
            out += [" ".join(_f(v) for v in row) for row in R]
            P = K @ np.column_stack([R, -R @ t])
            pm.append(f"{name} " + " ".join(f"{v:.6f}" for v in P.ravel()) + " ")
        p = PIX4D_PROJECT
        (params / f"{p}_calibrated_camera_parameters.txt").write_text("\n".join(out) + "\n")
        (params / f"{p}_offset.xyz").write_text(" ".join(f"{v:.3f}" for v in offset))
        (params / f"{p}_wkt.prj").write_text(self.crs.to_wkt(version="WKT1_ESRI"))
        (params / f"{p}_pmatrix.txt").write_text("\n".join(pm) + "\n")
        pc = dest / "2_densification" / "point_cloud"
        pc.mkdir(parents=True)
        self.write_cloud_las(pc / f"{p}_group1_densified_point_cloud.laz")
