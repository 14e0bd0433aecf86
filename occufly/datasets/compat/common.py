"""What the per-codebase adapters share: the export's geometry and frame list, the 3D-2D
mapping, local frustums, the context-prior matrix, a left-right flip that is right for the
export's axis convention, and the depth-consistency check.

Everything here is numpy (no torch): the adapters convert at the end, the way each codebase
does. The functions are written from the codebases' documented contracts (docstrings and
call sites, see docs/ssc-porting.md), not copied from them; the numerical conventions they
fix are noted where they matter (float32 voxel centres, ``np.round`` to int64 pixels).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occufly.datasets.reader import SSCBenchReader
from occufly.errors import InputFormatError
from occufly.export.sscbench import read_calib

# what the adapters understand of the manifest's ``axes`` record
AXES_CAMERA_CENTRIC = {"image_left_right": 0, "image_top_bottom": 1, "optical_axis": 2}


class FlipRefused(InputFormatError):
    """A left-right flip was asked for an export whose axis convention the adapter cannot
    mirror correctly (no ``axes`` record, or image left-right is not a grid axis)."""


@dataclass
class ExportGeometry:
    """The export's frame-grid geometry (``occufly.yaml`` ``geometry``, manifest ``axes``)."""

    voxel_origin: np.ndarray          # (3,) camera-frame metres of voxel (0, 0, 0)'s corner
    voxel_size: float
    scene_size: tuple[float, float, float]
    grid_shape: tuple[int, int, int]
    n_classes: int
    class_names: tuple[str, ...]
    class_voxel_counts: np.ndarray    # (n_classes,) int64, train split (or all frames)
    image_sizes: dict[str, tuple[int, int]] = field(default_factory=dict)  # seq -> (W, H)
    axes: dict | None = None          # manifest "axes"; None: not recorded

    @property
    def lr_axis(self) -> int | None:
        """The grid axis an image left-right flip mirrors, or None when not known."""
        if self.axes is None:
            return None
        v = self.axes.get("image_left_right")
        return int(v) if isinstance(v, int) else None

    def class_weights(self) -> np.ndarray:
        """1 / log(frequency) -- the weighting the MonoScene family and CGFormer use (with
        +0.001 / +1e-6 in the log; the counts here are large, so both give the same)."""
        return 1.0 / np.log(self.class_voxel_counts.astype(np.float64) + 0.001)


def _axes_of(manifest: dict) -> dict | None:
    ax = manifest.get("axes")
    if isinstance(ax, dict):
        return ax
    # exports before the ``axes`` record: the convention text names the camera-centric grid
    conv = str(manifest.get("conventions", {}).get("frame_grid", ""))
    if conv.startswith("camera-centric, x right, y down, z forward"):
        return dict(AXES_CAMERA_CENTRIC, inferred_from="conventions.frame_grid")
    return None


def load_geometry(root: str | Path) -> ExportGeometry:
    root = Path(root)
    yp = root / "occufly.yaml"
    try:
        import yaml

        doc = yaml.safe_load(yp.read_text())
        g = doc["geometry"]
    except (OSError, KeyError, TypeError) as e:
        raise InputFormatError(f"{yp}: not an SSCBench-layout export's occufly.yaml with a "
                               f"geometry block ({e})") from None
    axes = None
    for mp in sorted((root / "manifests").glob("*.json")):
        try:
            axes = _axes_of(json.loads(mp.read_text()))
        except (OSError, ValueError):
            axes = None
        if axes is None:
            break  # one manifest without a known convention: refuse flips for all
    sizes = {s: (int(v["image_width"]), int(v["image_height"]))
             for s, v in (g.get("sequences") or {}).items()}
    return ExportGeometry(
        voxel_origin=np.asarray(g["voxel_origin"], dtype=np.float64),
        voxel_size=float(g["voxel_size"]),
        scene_size=tuple(float(v) for v in g["scene_size"]),
        grid_shape=tuple(int(v) for v in g["grid_shape"]),
        n_classes=int(g["n_classes"]),
        class_names=tuple(g["class_names"]),
        class_voxel_counts=np.asarray(g["class_voxel_counts"], dtype=np.int64),
        image_sizes=sizes, axes=axes)


def export_root(path: str | Path) -> Path:
    """The export root from any of the roots a codebase's config names (the export itself,
    ``<export>/dataset``, ``<export>/preprocess``, ``<export>/preprocess/labels``,
    ``<export>/depth_full`` ...): the nearest folder upwards holding ``occufly.yaml``."""
    p = Path(path).absolute()
    for q in (p, *p.parents):
        if (q / "occufly.yaml").is_file() and (q / "manifests").is_dir():
            return q
    raise InputFormatError(f"{path}: not inside an SSCBench-layout export (no occufly.yaml and "
                           "manifests/ above it); export with `occufly export --layout sscbench`")


@dataclass
class Scan:
    sequence: str
    frame_id: str
    P2: np.ndarray        # (3, 4) from the sequence's own calib.txt
    Tr: np.ndarray        # (4, 4)
    image_size: tuple[int, int]  # (W, H)


def list_scans(root: Path, split: str) -> list[Scan]:
    """The frames of ``split`` with their sequence's calibration (one calib.txt per sequence,
    read at each sequence -- the codebases read one fixed calibration for all)."""
    reader = SSCBenchReader(root, split=split)
    calib: dict[str, dict] = {}
    geom_sizes = load_geometry(root).image_sizes
    scans = []
    for k in reader.frames:
        if k.sequence not in calib:
            calib[k.sequence] = read_calib(root / "data_2d_raw" / k.sequence / "calib.txt")
        c = calib[k.sequence]
        size = geom_sizes.get(k.sequence)
        if size is None:
            from PIL import Image

            with Image.open(root / "data_2d_raw" / k.sequence / "image_00" / "data_rect"
                            / f"{k.frame_id}.png") as im:
                size = im.size
        scans.append(Scan(k.sequence, k.frame_id, c["P2"], c["Tr"], size))
    return scans


# ---- 3D-2D mapping -----------------------------------------------------------------------------
def voxel_centres(vox_origin: np.ndarray, voxel_size: float, scene_size) -> tuple[np.ndarray, tuple]:
    """(N, 3) float32 centres of the voxels of ``scene_size`` at ``voxel_size`` in C order of
    the (X, Y, Z) grid (``ceil(scene_size / voxel_size)`` voxels per axis)."""
    dims = np.ceil(np.asarray(scene_size, np.float64) / voxel_size).astype(int)
    o = np.asarray(vox_origin, np.float32).astype(np.float64)
    axes = [o[d] + voxel_size * np.arange(dims[d], dtype=np.float64) + voxel_size * 0.5
            for d in range(3)]
    g = np.meshgrid(*axes, indexing="ij")
    return np.stack([a.reshape(-1) for a in g], axis=1).astype(np.float32), tuple(int(v) for v in dims)


def vox2pix(T_velo_2_cam: np.ndarray, cam_k: np.ndarray, vox_origin: np.ndarray,
            voxel_size: float, img_W: int, img_H: int, scene_size) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> projected_pix (N, 2) int64 (rounded, half to even), fov_mask (N,) bool, pix_z (N,)
    float64: voxel centres moved by ``T_velo_2_cam`` and projected with ``cam_k``; in the FOV
    when 0 <= u < W, 0 <= v < H and z > 0."""
    pts, _ = voxel_centres(vox_origin, voxel_size, scene_size)
    T = np.asarray(T_velo_2_cam, np.float64)
    cam = pts.astype(np.float64) @ T[:3, :3].T + T[:3, 3]
    k = np.asarray(cam_k, np.float32).astype(np.float64)
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam[:, 0] * k[0, 0] / z + k[0, 2]
        v = cam[:, 1] * k[1, 1] / z + k[1, 2]
    u = np.where(np.isfinite(u), u, -1.0)
    v = np.where(np.isfinite(v), v, -1.0)
    pix = np.stack([np.round(u), np.round(v)], axis=1)
    pix = np.clip(pix, -2**62, 2**62).astype(np.int64)
    fov = (pix[:, 0] >= 0) & (pix[:, 0] < img_W) & (pix[:, 1] >= 0) & (pix[:, 1] < img_H) & (z > 0)
    return pix, fov, z


def local_frustums(projected_pix: np.ndarray, pix_z: np.ndarray, target: np.ndarray,
                   img_W: int, img_H: int, n_classes: int, size: int = 4
                   ) -> tuple[np.ndarray, np.ndarray]:
    """-> masks (size*size, X, Y, Z) bool, class_dists (size*size, n_classes) float64.

    Frustum (row r, column c) holds the voxels whose projection lies in image tile
    [c W/size, (c+1) W/size) x [r H/size, (r+1) H/size), in front of the camera, with a
    non-ignored label; its class histogram counts their labels. Order: rows outer, columns
    inner."""
    X, Y, Z = target.shape
    u = projected_pix[:, 0].astype(np.float64)
    v = projected_pix[:, 1].astype(np.float64)
    front = pix_z > 0
    # tile index by the same comparisons as [start, end) bounds (start = i / size * W)
    edges_x = np.array([i * 1.0 / size * img_W for i in range(size + 1)])
    edges_y = np.array([i * 1.0 / size * img_H for i in range(size + 1)])
    cx = np.searchsorted(edges_x, u, side="right") - 1
    cy = np.searchsorted(edges_y, v, side="right") - 1
    ok = front & (cx >= 0) & (cx < size) & (cy >= 0) & (cy < size) & (target.reshape(-1) != 255)
    tile = np.where(ok, cy * size + cx, -1)
    n = size * size
    masks = np.zeros((n, X * Y * Z), dtype=bool)
    sel = np.flatnonzero(ok)
    masks[tile[sel], sel] = True
    t = target.reshape(-1).astype(np.int64)
    dists = np.zeros((n, n_classes), dtype=np.float64)
    np.add.at(dists, (tile[sel], t[sel]), 1.0)
    return masks.reshape(n, X, Y, Z), dists


def cp_mega_matrix(target: np.ndarray, is_binary: bool = False) -> np.ndarray:
    """Context-prior relation matrix of a (X, Y, Z) label grid (MonoScene's CRP supervision):
    (4, N, M) uint8 (``is_binary``: (2, N, M)) for N voxels and M = (X/2)(Y/2)(Z/2) super
    voxels. For voxel n and super voxel m, with L = labels of m's 8 children that are not 255:
    relation 0 (non-empty, same) when some l in L equals label[n] != 0; 1 (non-empty,
    different) when some l != 0 differs from label[n] != 0; 2 (empty, empty) when label[n] ==
    l == 0; 3 (non-empty / empty) when label[n] != l and one of them is 0. Voxels labelled 255
    relate to nothing. Binary: 0 = some child differs, 1 = some child equals."""
    label = target.reshape(-1).astype(np.int64)
    sx, sy, sz = (s // 2 for s in target.shape)
    t = target[: 2 * sx, : 2 * sy, : 2 * sz].astype(np.int64)
    ch = t.reshape(sx, 2, sy, 2, sz, 2)
    # children in the order (0,0,0) (1,0,0) (0,1,0) (0,0,1) (1,1,0) (1,0,1) (0,1,1) (1,1,1)
    order = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)]
    kids = np.stack([ch[:, a, :, b, :, c] for a, b, c in order], axis=-1).reshape(-1, 8)  # (M, 8)
    M = kids.shape[0]
    valid_row = label != 255
    out = np.zeros((2 if is_binary else 4, label.size, M), dtype=np.uint8)
    # per super voxel, which child classes occur (a small set): loop over distinct classes
    classes = np.unique(kids[kids != 255])
    has = {int(c): (kids == c).any(axis=1) for c in classes}  # (M,) bool
    for c, hm in has.items():
        cols = np.flatnonzero(hm)
        if not len(cols):
            continue
        same = valid_row & (label == c)
        diff = valid_row & (label != c)
        if is_binary:
            out[0][np.ix_(np.flatnonzero(diff), cols)] = 1
            out[1][np.ix_(np.flatnonzero(same), cols)] = 1
            continue
        if c != 0:
            out[0][np.ix_(np.flatnonzero(same), cols)] = 1
            out[1][np.ix_(np.flatnonzero(diff & (label != 0)), cols)] = 1
            out[3][np.ix_(np.flatnonzero(diff & (label == 0)), cols)] = 1
        else:
            out[2][np.ix_(np.flatnonzero(same), cols)] = 1
            out[3][np.ix_(np.flatnonzero(diff), cols)] = 1
    return out


# ---- flips -------------------------------------------------------------------------------------
def flip_K(K: np.ndarray, width: int) -> np.ndarray:
    """K of the left-right mirrored image in the integer-pixel-centre convention: pixel u maps
    to W - 1 - u, so cx -> W - 1 - cx (a copy; K may be 3x3, 3x4 or 4x4)."""
    K2 = np.array(K, dtype=np.float64, copy=True)
    K2[0, 2] = width - 1 - K2[0, 2]
    return K2


def check_flip(geometry: ExportGeometry, where: str) -> int:
    """The grid axis to mirror for an image left-right flip, or raise :class:`FlipRefused`."""
    ax = geometry.lr_axis
    if ax is None or ax not in (0, 1, 2):
        raise FlipRefused(
            f"{where}: the export records no axis convention (manifest 'axes'), so a left-right "
            "flip cannot be mirrored onto the grid correctly; re-export with this version of "
            "occufly or turn the flip off")
    return ax


# ---- depth consistency --------------------------------------------------------------------------
def depth_consistency(target: np.ndarray, depth: np.ndarray, K: np.ndarray, image_size,
                      vox_origin, voxel_size: float, *, tol: float = 1.0, step: int = 1,
                      T_velo_2_cam: np.ndarray | None = None) -> dict:
    """Does the grid agree with the depth map? For every ``step``-th pixel of ``depth`` with
    depth > 0, march its ray (through the pixel centre, in the image's integer-pixel-centre K)
    in steps of voxel_size / 4 along z and take the first voxel labelled occupied (not 0 and
    not 255); the share of such pixels whose hit z is within ``tol`` metres of the depth.

    ``depth`` may be at a lower resolution than the image (``image_size`` = (W, H)); its pixel
    (i, j) is full-resolution pixel ((j + .5) W / w - .5, (i + .5) H / h - .5).
    -> {"share", "pixels" (with depth and a hit), "hit_rate", "median_abs_err"}."""
    W, H = int(image_size[0]), int(image_size[1])
    h, w = depth.shape
    ii, jj = np.mgrid[0:h:step, 0:w:step]
    d = depth[ii, jj].astype(np.float64).reshape(-1)
    u = ((jj + 0.5) * W / w - 0.5).reshape(-1)
    v = ((ii + 0.5) * H / h - 0.5).reshape(-1)
    keep = d > 0
    u, v, d = u[keep], v[keep], d[keep]
    Kf = np.asarray(K, np.float64)[:3, :3]
    rays = np.stack([(u - Kf[0, 2]) / Kf[0, 0], (v - Kf[1, 2]) / Kf[1, 1], np.ones_like(u)], 1)
    X, Y, Z = target.shape
    o = np.asarray(vox_origin, np.float64)
    zs = np.arange(voxel_size / 8, o[2] + Z * voxel_size, voxel_size / 4)
    occ = (target != 0) & (target != 255)
    if T_velo_2_cam is not None:
        Tinv = np.linalg.inv(np.asarray(T_velo_2_cam, np.float64))
    hit_z = np.full(len(d), np.nan)
    for s in range(0, len(d), 4096):  # chunks of rays: (rays, steps, 3) stays small
        r = rays[s:s + 4096]
        p = r[:, None, :] * zs[None, :, None]
        if T_velo_2_cam is not None:
            p = p @ Tinv[:3, :3].T + Tinv[:3, 3]
        idx = np.floor((p - o) / voxel_size).astype(np.int64)
        inside = ((idx >= 0) & (idx < np.array([X, Y, Z]))).all(-1)
        idc = np.where(inside[..., None], idx, 0)
        o_hit = occ[idc[..., 0], idc[..., 1], idc[..., 2]] & inside
        first = o_hit.argmax(axis=1)
        anyhit = o_hit.any(axis=1)
        hit_z[s:s + 4096] = np.where(anyhit, zs[first], np.nan)
    hit = np.isfinite(hit_z)
    err = np.abs(hit_z[hit] - d[hit])
    return {"share": float(np.mean(err <= tol)) if hit.any() else float("nan"),
            "pixels": int(hit.sum()), "hit_rate": float(hit.mean()) if len(d) else float("nan"),
            "median_abs_err": float(np.median(err)) if hit.any() else float("nan")}
