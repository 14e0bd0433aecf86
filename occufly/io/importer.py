"""Import a reconstruction on disk into a scene workspace.

Input: a COLMAP model (``SOURCE``, ``SOURCE/sparse`` or ``SOURCE/sparse/0``; text or binary),
an OpenDroneMap/WebODM project, a Metashape camera XML or a Pix4D project (``fmt``, detected
when None: :mod:`occufly.io.sources`, which also states the CRS rules),
the images (``SOURCE/images`` unless given), a dense cloud (``--cloud``; else
``SOURCE/dense/fused.ply`` or ``SOURCE/fused.ply``; else the sparse points), optional MVS
depth maps (``--depth-maps``; else ``SOURCE[/dense]/stereo/depth_maps``).

Coordinates. A model is *georeferenced* when its coordinates are UTM-scale (any camera centre
or point farther than 10 km from the origin) or the cloud is LAS/LAZ; its world is taken as
z-up. The scene stores a float64 origin (the rounded centre of the cloud's bounding box) and
float32 local coordinates, so 6-7 digit UTM metres keep sub-millimetre precision.

A model that is not georeferenced has an arbitrary world frame (COLMAP's is the first
camera's). Its up axis is estimated from the flight: drone surveys fly in horizontal planes,
so up is the normal of the plane best fitting the camera centres (smallest singular vector),
signed so the cameras look down (up . mean viewing direction < 0), provided it lies within 30
degrees of minus the mean viewing direction. When the centres are close to collinear (one
flight line), disagree with the viewing directions, or there are fewer than three frames, up is
minus the mean viewing direction. The scene is then *levelled*: its world frame is rotated so up is +z. The
rotation is kept in ``scene.meta["levelling_rotation"]`` (x_levelled = R @ x_source) so
exports can return to the source frame (:func:`source_coordinates`).

Visibility (``visibility=``, CLI ``--visibility``): by default every frame that sees a point --
the reconstruction's own lists (``fused.ply.vis`` next to COLMAP's ``fused.ply``, tracks when
the cloud is the sparse model) united with a depth test against the MVS depth maps, or against
depth rendered from the cloud where a frame has none (:mod:`occufly.visibility`). ``vis`` keeps
the lists alone, ``depth`` the depth test alone. A cloud with non-finite coordinates, or one no
frame sees, is an error naming the file (the cloud readers reject non-finite points).

Nothing is written unless the whole import succeeds: the workspace appears complete or not at
all.
"""

from __future__ import annotations

import logging
import os
import stat
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from occufly.camera import make_pose
from occufly.errors import InputFormatError, UnsafePathError, WorkspaceError, check_name
from occufly.fsutil import PathNotConfined, atomic_directory, confined, require_memory
from occufly.io import crs as crsmod
from occufly.io.colmap_dense import find_depth_map, read_depth_map, read_fused_vis
from occufly.io.exif import read_geotags
from occufly.io.georef import MIN_GPS_CAMERAS, align_to_gps
from occufly.io.pointcloud import read_point_cloud
from occufly.io.sources import into_cloud_crs, read_source, resolve_image_names
from occufly.progress import ProgressFn, noop
from occufly.scene import Frame, Scene, assign_altitudes
from occufly.taxonomy import Taxonomy, default_taxonomy
from occufly.visibility import VISIBILITY_MODES, FrameLists, compute_visibility
from occufly.workspace import Workspace

log = logging.getLogger(__name__)

GEOREF_THRESHOLD_M = 10_000.0
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".JPG", ".JPEG", ".PNG")


def import_scene(
    source: str | Path,
    workspace: str | Path,
    *,
    cloud: str | Path | None = None,
    depth_maps: str | Path | None = None,
    images: str | Path | None = None,
    taxonomy: Taxonomy | str | Path | None = None,
    nominal_altitudes: list[float] | None = None,
    rel_tol: float = 0.02,
    visibility: str = "union",
    fmt: str | None = None,
    crs: str | None = None,
    scale: float | None = None,
    overwrite: bool = False,
    progress: ProgressFn | None = None,
    workers: int = 1,
    roots: list[str | Path] | None = None,
) -> Scene:
    """Read the reconstruction at ``source`` and write the workspace ``workspace``.

    visibility: ``union`` (default: the reconstruction's lists united with the depth test),
    ``vis`` (lists only) or ``depth`` (depth test only), see :mod:`occufly.visibility`.
    workers: processes computing the visibility's frames (1: in this process); the output
    is the same for any number.
    roots: when given (the web app: its import roots), every file the import
    reads -- the images (symlinks followed), the image folder a project file names (e.g. a
    Metashape ``.psx``'s absolute photo paths), the cloud, its ``.vis``, the depth maps --
    must resolve inside one of them (:func:`confine_inputs`); else UnsafePathError naming
    the project file and the path, before any image is opened.
    """
    if int(workers) < 1:
        raise InputFormatError(f"--workers {workers}: expected a number >= 1")
    if visibility not in VISIBILITY_MODES:
        raise InputFormatError(f"--visibility {visibility!r}: expected one of "
                               f"{', '.join(VISIBILITY_MODES)}")
    report = progress or noop
    t0 = time.perf_counter()
    source = Path(source)
    workspace = Path(workspace)
    if workspace.exists() and not overwrite and any(workspace.iterdir()):
        raise WorkspaceError(f"{workspace}: workspace already exists (use --force to replace it)")
    tax = _taxonomy_of(taxonomy)

    report(0.0, "reading the reconstruction")
    model, image_dir, cloud_path = _read_reconstruction(source, fmt, images, cloud, depth_maps,
                                                        roots)
    report(0.05, "reading point cloud")
    scene_crs, crs_info = into_cloud_crs(model, cloud_path, crs)
    xyz_w, rgb = _read_cloud(source, model, cloud_path)
    place = _place(source, model, image_dir, cloud_path, xyz_w, scene_crs, crs, scale)
    del xyz_w  # place.xyz_w is the (possibly rescaled) cloud
    # x_local = R (x_src - origin_src); the scene's world is the levelled frame, whose origin
    # offset is R @ origin_src (identity for georeferenced models)
    xyz_local = ((place.xyz_w - place.origin_src) @ place.R_level.T).astype(np.float32)
    frames = _local_frames(model, image_dir, place)

    report(0.15, "visibility")
    depth_dir = _find_depth_dir(source, depth_maps)
    vis_path = Path(str(cloud_path) + ".vis") if cloud_path is not None else None
    has_vis = vis_path is not None and vis_path.is_file()
    if visibility == "vis" and not has_vis and not (cloud_path is None and model.has_tracks):
        raise InputFormatError(
            f"{cloud_path}: --visibility vis needs the reconstruction's own visibility "
            f"({cloud_path.name}.vis or the sparse model's tracks) and there is none; use "
            "--visibility union or depth")
    list_entries = (max(0, (vis_path.stat().st_size - 8) // 4 - len(xyz_local)) if has_vis else 0)
    check_import_resources(workspace, n_points=len(xyz_local), frames=frames,
                           list_entries=list_entries, source=source)
    place.xyz_w = None  # the scene keeps the local copy

    depth_for = DepthMaps(depth_dir, [f.name for f in frames]) if depth_dir is not None else None

    # built in a temporary sibling folder renamed into place at the end: the visibility ids
    # are streamed into it frame by frame (memory: one frame, not the ~4 bytes per
    # correspondence of the whole scene), and a failed import leaves nothing behind
    with atomic_directory(workspace, overwrite=True) as tmp:
        wtmp = Workspace(tmp)
        wtmp.visibility_dir.mkdir()
        lists, lists_name = _reconstruction_lists(model, cloud_path, vis_path if has_vis else None,
                                                  len(xyz_local), len(frames))
        vis_mode = visibility if lists is not None else "depth"
        visibility_data, vis_stats = compute_visibility(
            frames, xyz_local, mode=vis_mode, lists=lists, lists_name=lists_name or "",
            depth_for=depth_for, rel_tol=rel_tol, progress=_sub_progress(report, 0.15, 0.9),
            ids_out=wtmp.visibility_array("point_ids"), workers=workers)
        del lists
        if vis_stats["correspondences"] == 0:
            raise InputFormatError(
                f"{source}: no frame sees any point of {cloud_path or 'the sparse cloud'} -- the "
                "poses and the cloud do not match (different coordinate frames?)")
        for w in vis_stats["warnings"]:
            log.warning("import %s: %s", source, w)

        scene = Scene(
            crs=crsmod.crs_record(place.scene_crs),
            frames=frames,
            xyz=xyz_local,
            rgb=np.ascontiguousarray(rgb, dtype=np.uint8),
            origin=place.R_level @ place.origin_src,
            visibility=visibility_data,
            taxonomy=tax,
            meta=_scene_meta(source, model, crs_info, cloud_path, image_dir, depth_dir, place,
                             lists_name, vis_mode, vis_stats),
        )
        report(0.9, "altitudes")
        assign_altitudes(scene, nominal_altitudes)
        scene.meta["import_seconds"] = round(time.perf_counter() - t0, 3)
        report(0.95, "writing workspace")
        scene.write_into(tmp)
        del scene, visibility_data
    report(1.0, "done")
    return Scene.load(workspace)


def _taxonomy_of(taxonomy: Taxonomy | str | Path | None) -> Taxonomy:
    if taxonomy is None:
        return default_taxonomy()
    return taxonomy if isinstance(taxonomy, Taxonomy) else Taxonomy.load(taxonomy)


def _read_reconstruction(source: Path, fmt: str | None, images, cloud, depth_maps, roots):  # noqa: ANN001
    """The reconstruction's model, its image folder and its dense cloud (None: the model's
    own points), every file checked (names, confinement to ``roots``, images) before use."""
    if roots is not None:  # no project file may be a symlink out (it would be read below)
        confine_tree(source, roots)
    model = read_source(source, fmt, images=Path(images) if images is not None else None)
    for note in model.notes:
        log.warning("import %s: %s", source, note)
    image_dir = _find_image_dir(source, images, model.default_images)
    resolve_image_names(image_dir, model)
    for im in model.images:  # frame names reach pages and the 3D viewer
        check_name(im.name, f"{model.path}: image")
    cloud_path = _find_cloud(source, cloud, model.default_cloud)
    if roots is not None:
        confine_inputs(roots, model.path, image_dir, [im.name for im in model.images],
                       cloud_path, _find_depth_dir(source, depth_maps))
    _check_images(image_dir, [im.name for im in model.images], model)
    return model, image_dir, cloud_path


def _read_cloud(source: Path, model, cloud_path: Path | None) -> tuple[np.ndarray, np.ndarray]:  # noqa: ANN001
    """(N, 3) source-frame points and (N, 3) uint8 colours: the dense cloud, else the model's."""
    if cloud_path is not None:
        xyz_w, rgb = read_point_cloud(cloud_path)
    else:
        if not len(model.xyz):
            raise InputFormatError(
                f"{source}: no dense cloud ({'dense/fused.ply' if model.kind == 'colmap' else model.kind + ' default'}) "
                f"and the {model.kind} model has no points: pass the dense cloud with --cloud"
            )
        xyz_w, rgb = model.xyz, model.rgb
    if len(xyz_w) == 0:
        raise InputFormatError(f"{cloud_path or source}: the point cloud is empty")
    return xyz_w, rgb


@dataclass
class _Placement:
    """Where the reconstruction goes in the scene: metric source points, CRS, levelling."""

    xyz_w: np.ndarray | None  # (N, 3) source frame (metric after georeferencing)
    scene_crs: object
    georef: bool
    georef_info: dict | None
    warnings: list[str]
    R_level: np.ndarray  # (3, 3) source -> levelled
    up_method: str
    origin_src: np.ndarray  # (3,) float64 source-frame centre, rounded


def _place(source: Path, model, image_dir: Path, cloud_path: Path | None, xyz_w: np.ndarray,  # noqa: ANN001
           scene_crs, crs: str | None, scale: float | None) -> _Placement:  # noqa: ANN001
    """Georeference an SfM model in arbitrary units (GPS or ``scale``) and level it (z up)."""
    centers_w = np.array([-im.T_cam_world[:3, :3].T @ im.T_cam_world[:3, 3] for im in model.images])
    las_cloud = cloud_path is not None and cloud_path.suffix.lower() in (".las", ".laz")
    georef_by_coords = bool(las_cloud or np.abs(centers_w).max() > GEOREF_THRESHOLD_M
                            or np.abs(xyz_w).max() > GEOREF_THRESHOLD_M)
    georef = bool(scene_crs is not None or georef_by_coords)
    import_warnings: list[str] = []
    georef_info: dict | None = None
    if model.kind == "colmap" and not georef_by_coords and (scene_crs is None or crs is not None):
        # an SfM model in arbitrary units: make it metric from the photos' GPS (or --scale)
        xyz_w, scene_crs, georef_info = _make_metric(model, image_dir, xyz_w, cloud_path,
                                                     scene_crs, scale, import_warnings)
        georef = scene_crs is not None
    for w in import_warnings:
        log.warning("import %s: %s", source, w)
    if georef:
        R_level, up_method = np.eye(3), "georeferenced: z up"
    else:
        R_level, up_method = _levelling_rotation(model)
    lo, hi = xyz_w.min(axis=0), xyz_w.max(axis=0)
    return _Placement(xyz_w=xyz_w, scene_crs=scene_crs, georef=georef, georef_info=georef_info,
                      warnings=import_warnings, R_level=R_level, up_method=up_method,
                      origin_src=np.round((lo + hi) / 2.0))


def _local_frames(model, image_dir: Path, place: _Placement) -> list[Frame]:  # noqa: ANN001
    """The model's images as frames with poses in the levelled, origin-shifted scene frame."""
    frames = []
    for im in model.images:
        R = im.T_cam_world[:3, :3]
        t = im.T_cam_world[:3, 3]
        # x_cam = R x_src + t = R (R_l^T x_local + o_src) + t
        T_local = make_pose(R @ place.R_level.T, t + R @ place.origin_src)
        frames.append(
            Frame(name=im.name, camera=im.camera, T_cam_world=T_local,
                  image_path=str((image_dir / im.name).resolve()))
        )
    return frames


def _reconstruction_lists(model, cloud_path: Path | None, vis_path: Path | None, n_points: int,  # noqa: ANN001
                          n_frames: int) -> tuple[FrameLists | None, str | None]:
    """The reconstruction's own 2D-3D lists (``fused.ply.vis`` or the sparse model's tracks)
    and what they are called; ``(None, None)`` when it has none."""
    if vis_path is not None:
        offsets, idx = read_fused_vis(vis_path, n_points)
        if len(idx) and int(idx.max()) >= n_frames:
            raise InputFormatError(
                f"{vis_path}: refers to image index {int(idx.max())} but the model has "
                f"{n_frames} registered images"
            )
        return FrameLists.from_point_lists(n_frames, offsets, idx), vis_path.name
    if cloud_path is None and model.has_tracks:
        return _tracks_as_lists(model, n_points), "COLMAP tracks"
    return None, None


def _scene_meta(source: Path, model, crs_info, cloud_path: Path | None, image_dir: Path,  # noqa: ANN001
                depth_dir: Path | None, place: _Placement, lists_name: str | None, vis_mode: str,
                vis_stats: dict) -> dict:
    """The scene's ``meta``: where it came from, its CRS and levelling, how visibility was made."""
    depth_desc = _depth_test_description(vis_mode, vis_stats)
    return {
        "source": str(source.resolve()),
        "format": model.kind,
        "sparse_model": str(model.path.resolve()),
        "crs": crsmod.crs_label(place.scene_crs) if place.scene_crs is not None else None,
        "crs_handling": crs_info,
        "import_notes": list(model.notes),
        "cloud": str(cloud_path.resolve()) if cloud_path else None,
        "images": str(image_dir.resolve()),
        "depth_maps": str(depth_dir.resolve()) if depth_dir else None,
        "georeferenced": place.georef,
        "georeferencing": place.georef_info,
        "import_warnings": place.warnings,
        "up_axis": place.up_method,
        "levelling_rotation": place.R_level.tolist(),
        "source_origin": place.origin_src.tolist(),
        # the reconstruction's own lists keep naming the source; the depth test apart
        "visibility_source": (lists_name if lists_name is not None and vis_mode != "depth"
                              else depth_desc),
        "visibility_mode": vis_mode,
        "visibility_depth_test": depth_desc,
        "visibility_stats": vis_stats,
    }


def _depth_test_description(vis_mode: str, vis_stats: dict) -> str | None:
    if vis_mode == "vis":
        return None
    if vis_stats["frames_rendered"] == 0:
        return "depth test against MVS depth maps"
    if vis_stats["frames_with_depth_maps"] == 0:
        return "depth test against depth rendered from the cloud"
    return "depth test against MVS depth maps and depth rendered from the cloud"


def refuse_hard_link(p: Path, where: str = "") -> None:
    """UnsafePathError when ``p`` (symlinks followed) is a regular file with more than one
    name (``st_nlink > 1``). A hard link inside an import root to a file outside it looks like
    any file there -- ``confined`` cannot tell -- so imports refuse every hard-linked file
    (COLMAP, ODM, Metashape and Pix4D workspaces do not make them); the message names the file
    and says what to do. ``where`` prefixes the message (the file the path came from)."""
    try:
        st = os.stat(p)
    except OSError:
        return  # a missing file is reported by whoever opens it
    if stat.S_ISREG(st.st_mode) and st.st_nlink > 1:
        raise UnsafePathError(
            f"{where}{p} is a hard link ({st.st_nlink} names for one file): a hard link in an "
            "import root may be a file from anywhere on its disk, so imports refuse hard "
            "links -- copy the file in instead (cp without -l or --preserve=links)")


def confine_tree(source: Path, roots) -> int:  # noqa: ANN001
    """``source`` (a project file or folder) and every symlink under it resolve inside
    ``roots``: a reader never opens a file elsewhere through a link in the project (a
    ``cameras.txt`` linked to ``/etc/shadow`` would show its first line in the error message).
    Walks without following links; returns the number of entries checked. UnsafePathError
    naming the link and where it leads."""
    source = Path(source)
    try:
        confined(source, roots)
    except PathNotConfined:
        raise UnsafePathError(f"{source} resolves to {os.path.realpath(source)}, outside the "
                              "import roots") from None
    if not source.is_dir():
        refuse_hard_link(source)
        return 1
    n = 0
    for dirpath, dirnames, filenames in os.walk(source, followlinks=False):
        for name in dirnames + filenames:
            n += 1
            p = Path(dirpath) / name
            if p.is_symlink():
                try:
                    confined(p, roots)
                except PathNotConfined:
                    raise UnsafePathError(
                        f"{p} is a symbolic link to {os.path.realpath(p)}, outside the import "
                        "roots; imports read only files inside them") from None
            refuse_hard_link(p)
    return n


def confine_inputs(roots, project: Path, image_dir: Path, names: list[str],  # noqa: ANN001
                   cloud_path: Path | None = None, depth_dir: Path | None = None) -> None:
    """Every file an import would read lies inside ``roots`` once resolved (symlinks
    followed): the image folder and each image, the cloud and its ``.vis``, the depth-map
    folder and the files in it. Raises UnsafePathError naming ``project`` (the file the path
    came from) and the first path that resolves outside, before anything is opened."""
    def check(p: Path, what: str) -> None:
        try:
            confined(p, roots)
        except PathNotConfined:
            raise UnsafePathError(
                f"{project}: {what} {p} resolves to {os.path.realpath(p)}, outside the import "
                "roots; imports read only files inside them") from None
        refuse_hard_link(p, f"{project}: {what} ")

    check(image_dir, "image folder")
    for n in names:
        check(image_dir / n, "image")
    if cloud_path is not None:
        check(cloud_path, "point cloud")
        vis = Path(str(cloud_path) + ".vis")
        if vis.exists() or vis.is_symlink():
            check(vis, "visibility file")
    if depth_dir is not None:
        check(depth_dir, "depth-map folder")
        for p in sorted(depth_dir.iterdir()):
            check(p, "depth map")


class DepthMaps:
    """Frame ``f``'s MVS depth map from ``depth_dir`` as (map, file name), or None (picklable,
    for the visibility's worker processes)."""

    def __init__(self, depth_dir: Path, names: list[str]) -> None:
        self.depth_dir = Path(depth_dir)
        self.names = list(names)

    def __call__(self, f: int):
        p = find_depth_map(self.depth_dir, self.names[f])
        return (read_depth_map(p), str(p)) if p is not None else None


# ---- resources -----------------------------------------------------------------------------------
#: bytes per point the import holds at its peak besides the visibility lists: the cloud as read
#: (float64 xyz + rgb) and its float32 local copy, the spatial bins and their sort, the per-point
#: flags and view counts (measured on bench: see README "How big, how long")
IMPORT_BYTES_PER_POINT = 80
#: bytes per visibility-list entry: the per-point lists as read (4) and grouped by frame (4)
IMPORT_BYTES_PER_LIST_ENTRY = 8
#: bytes per pixel of the largest frame (its depth map and rendered raster) and per candidate
#: point of a frame (projection in float64)
IMPORT_BYTES_PER_PIXEL = 12
IMPORT_BYTES_PER_CANDIDATE = 100
IMPORT_BASE_BYTES = 400 << 20


def estimate_import_resources(*, n_points: int, frames: list[Frame], list_entries: int) -> dict:
    """Up-front estimate of the import's peak memory (bytes): the cloud, the bins, the lists,
    and one frame -- its raster and its candidate points (the frame's share of the cloud, at
    worst all of it for a frame that sees the whole scene: bounded by ``n_points``). The
    visibility output is streamed to disk and costs no memory."""
    px = max((f.camera.width * f.camera.height for f in frames), default=0)
    # a frame's candidates: its footprint's share of the cloud; a nadir survey frame sees a
    # few percent of it -- take the larger of 10 % and 4 M points, at most all of them
    cand = min(n_points, max(n_points // 10, 4_000_000))
    mem = (IMPORT_BASE_BYTES + n_points * IMPORT_BYTES_PER_POINT
           + list_entries * IMPORT_BYTES_PER_LIST_ENTRY
           + px * IMPORT_BYTES_PER_PIXEL + cand * IMPORT_BYTES_PER_CANDIDATE)
    return {"memory_bytes": int(mem), "points": int(n_points), "frames": len(frames),
            "list_entries": int(list_entries), "largest_frame_pixels": int(px)}


def check_import_resources(workspace: Path, *, n_points: int, frames: list[Frame],
                           list_entries: int, source: Path) -> dict:
    """:func:`estimate_import_resources` against the memory available (what this process
    already holds counts as its own); an :class:`OccuflyError` naming both figures when it
    does not fit, before any workspace file is written. Disk is checked by the visibility
    pass once the spatial bins can count each frame's candidates
    (:func:`occufly.visibility.compute_visibility`, ``ids_out``)."""
    est = estimate_import_resources(n_points=n_points, frames=frames, list_entries=list_entries)
    est["available_bytes"] = require_memory(
        est["memory_bytes"], f"{source}: importing {n_points:,} points, {len(frames)} frames and "
        f"{list_entries:,} visibility-list entries", count_own=True,
        hint=f"nothing was written to {workspace}")["available_bytes"]
    return est


def source_coordinates(scene: Scene, xyz_local: np.ndarray) -> np.ndarray:
    """(N, 3) scene-local -> (N, 3) float64 in the source reconstruction's frame (e.g. UTM)."""
    R = np.asarray(scene.meta.get("levelling_rotation", np.eye(3)), dtype=np.float64)
    o_src = np.asarray(scene.meta.get("source_origin", scene.origin), dtype=np.float64)
    return np.asarray(xyz_local, dtype=np.float64) @ R + o_src


# ---- metric scale from GPS -----------------------------------------------------------------------
def _make_metric(model, image_dir: Path, xyz_w: np.ndarray, cloud_path: Path | None, scene_crs,
                 scale: float | None, warnings: list[str]):
    """A COLMAP model in SfM units -> metres: aligned to its photos' EXIF GPS
    (:mod:`occufly.io.georef`; the scene's CRS becomes the UTM zone or ``--crs``), else scaled
    by ``scale`` (``--scale``: metres per model unit; 1 for a model that is metric already).
    The model's poses and points (and ``xyz_w``, the cloud in the model's frame) are changed
    in place. Returns (xyz_w, CRS or None, georeferencing record for scene.meta)."""
    tags = read_geotags(image_dir, [im.name for im in model.images]) if scale is None else []
    warnings.extend(g.warning for g in tags if g.warning)  # values dropped (issue 36)
    n_gps = sum(1 for g in tags if g.has_gps and g.altitude is not None)
    if scale is None and n_gps >= MIN_GPS_CAMERAS:
        al = align_to_gps(model, tags, crs=scene_crs)
        for im in model.images:
            im.T_cam_world = al.apply_pose(im.T_cam_world)
        same = xyz_w is model.xyz
        if len(model.xyz):
            model.xyz = al.apply_points(model.xyz)
        xyz_w = model.xyz if same else al.apply_points(xyz_w)
        warnings.extend(al.warnings)
        rec = al.report()
        rec["geotags"] = {g.name: {k: v for k, v in g.to_dict().items() if v is not None}
                          for g in tags}
        return xyz_w, al.crs, rec
    if scale is not None:
        if not (float(scale) > 0 and np.isfinite(float(scale))):
            raise InputFormatError(f"--scale {scale}: expected metres per model unit (> 0)")
        s = float(scale)
        for im in model.images:
            im.T_cam_world = im.T_cam_world.copy()
            im.T_cam_world[:3, 3] *= s
        same = xyz_w is model.xyz
        if len(model.xyz):
            model.xyz = np.asarray(model.xyz, np.float64) * s
        xyz_w = model.xyz if same else np.asarray(xyz_w, np.float64) * s
        return xyz_w, scene_crs, {"method": "--scale", "scale": s,
                                  "crs": crsmod.crs_label(scene_crs) if scene_crs else None}
    if scene_crs is None:
        raise InputFormatError(
            f"{model.path}: the model's units are unknown: it is not georeferenced (no CRS, "
            f"no UTM-scale coordinates, no LAS cloud) and its images carry no GPS ({n_gps} of "
            f"{len(model.images)} geotagged, {MIN_GPS_CAMERAS} needed), so voxel grids cut from "
            "it would be in arbitrary units. Pass --scale S (metres per model unit; --scale 1 "
            "if it is metric already, e.g. after colmap model_aligner), or --crs with a "
            "georeferenced cloud, or the geotagged photos")
    return xyz_w, scene_crs, None


# ---- helpers -------------------------------------------------------------------------------------
def _sub_progress(report: ProgressFn, start: float, end: float) -> ProgressFn:
    return lambda frac, msg="": report(start + (end - start) * frac, msg)


def _find_image_dir(source: Path, images: str | Path | None, default: Path | None = None) -> Path:
    if images is not None:
        d = Path(images)
        if not d.is_dir():
            raise InputFormatError(f"{d}: image folder not found")
        return d
    for cand in (source / "images", source / "dense" / "images", default):
        if cand is None:
            continue
        if cand.is_dir():
            return cand
    raise InputFormatError(f"{source}: no image folder (expected {source}/images or --images DIR)")


def _check_images(image_dir: Path, names: list[str], model) -> None:
    missing = [n for n in names if not (image_dir / n).is_file()]
    if missing:
        raise InputFormatError(
            f"{image_dir}: does not match the model {model.path}: {len(missing)} of "
            f"{len(names)} images are missing: {', '.join(missing[:10])}"
            f"{' ...' if len(missing) > 10 else ''}"
        )
    for im in model.images:
        p = image_dir / im.name
        try:
            with Image.open(p) as img:
                size = img.size
        except Exception:  # noqa: BLE001 - PIL raises many types for broken files
            raise InputFormatError(f"{p}: not a readable image") from None
        if size != (im.camera.width, im.camera.height):
            raise InputFormatError(
                f"{p}: image is {size[0]}x{size[1]} but its camera in {model.path} is "
                f"{im.camera.width}x{im.camera.height}"
            )


def _find_cloud(source: Path, cloud: str | Path | None, default: Path | None = None) -> Path | None:
    if cloud is not None:
        p = Path(cloud)
        if not p.is_file():
            raise InputFormatError(f"{p}: point cloud file not found")
        return p
    for cand in (source / "dense" / "fused.ply", source / "fused.ply"):
        if cand.is_file():
            return cand
    return default


def _find_depth_dir(source: Path, depth_maps: str | Path | None) -> Path | None:
    if depth_maps is not None:
        d = Path(depth_maps)
        if not d.is_dir():
            raise InputFormatError(f"{d}: depth-map folder not found")
        return d
    for cand in (source / "dense" / "stereo" / "depth_maps", source / "stereo" / "depth_maps"):
        if cand.is_dir():
            return cand
    return None


def _levelling_rotation(model) -> tuple[np.ndarray, str]:
    dirs = np.array([im.T_cam_world[2, :3] for im in model.images])
    mean_dir = dirs.mean(axis=0)
    centers = np.array([-im.T_cam_world[:3, :3].T @ im.T_cam_world[:3, 3] for im in model.images])
    up = None
    method = ""
    if len(centers) >= 3:
        c = centers - centers.mean(axis=0)
        _, s, vt = np.linalg.svd(c, full_matrices=False)
        normal = vt[2] if np.dot(vt[2], mean_dir) < 0 else -vt[2]
        down = -mean_dir / max(np.linalg.norm(mean_dir), 1e-12)
        planar = s[1] > 0.2 * s[0] and s[2] < 0.5 * s[1]
        # trust the plane only where it agrees with the cameras looking down (within 30 deg)
        if planar and np.dot(normal, down) > np.cos(np.radians(30)):
            up = normal
            method = "normal of the plane through the camera centres"
    if up is None:
        if np.linalg.norm(mean_dir) < 1e-6:
            return np.eye(3), "unknown: kept the model's z axis"
        up = -mean_dir
        method = "minus the mean viewing direction"
    up = up / np.linalg.norm(up)
    if np.dot(up, mean_dir) > 0:
        up = -up
    # rotation taking `up` to +z (Rodrigues)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(up, z)
    c = float(np.dot(up, z))
    if np.linalg.norm(v) < 1e-12:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R = np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))
    return R, f"not georeferenced; up = {method}"


def _tracks_as_lists(model, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP tracks (sparse cloud) as per-point frame lists: (offsets (N + 1,), frames)."""
    index_of = {int(p): i for i, p in enumerate(model.point_ids)}
    lut_keys = np.array(list(index_of.keys()), dtype=np.int64)
    lut_vals = np.array(list(index_of.values()), dtype=np.int64)
    order = np.argsort(lut_keys)
    lut_keys, lut_vals = lut_keys[order], lut_vals[order]
    rows_p, rows_f = [], []
    for f, im in enumerate(model.images):
        pos = np.searchsorted(lut_keys, im.point3D_ids)
        ok = (pos < len(lut_keys)) & (lut_keys[np.minimum(pos, len(lut_keys) - 1)] == im.point3D_ids)
        rows_p.append(lut_vals[pos[ok]])
        rows_f.append(np.full(int(ok.sum()), f, np.int64))
    p = np.concatenate(rows_p) if rows_p else np.zeros(0, np.int64)
    fr = np.concatenate(rows_f) if rows_f else np.zeros(0, np.int64)
    order = np.argsort(p, kind="stable")
    p, fr = p[order], fr[order]
    offsets = np.searchsorted(p, np.arange(n_points + 1))
    return offsets, fr
