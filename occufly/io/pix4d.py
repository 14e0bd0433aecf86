"""Pix4D projects (``1_initial/params``) -> :class:`SparseModel`.

Files (``<p>`` = the project name; ``SOURCE`` = the project folder, its ``1_initial/params``
folder, or the calibrated-camera-parameters file itself):

- ``<p>_calibrated_camera_parameters.txt``: header lines, then per image ``name width
  height``, K (3 lines), radial distortion R1 R2 R3 (1 line), tangential T1 T2 (1 line), camera
  position t (1 line, relative to the offset), R (3 lines, world-to-camera, x right / y down /
  z forward); ``P = K [R | -R t]``. Pix4D's perspective model is Brown's with OpenCV's
  tangential order: ``x' = x (1 + R1 r^2 + R2 r^4 + R3 r^6) + 2 T1 x y + T2 (r^2 + 2 x^2)`` ->
  the ``BROWN`` camera model; pixel (0, 0) is the top-left corner (the principal point offset
  of the ``.cam`` file is relative to W/2).
- ``<p>_offset.xyz``: the offset of the positions in the output CRS.
- ``<p>_wkt.prj``: that CRS (when present; else the densified cloud's).
- the densified cloud: ``2_densification/point_cloud/<p>_group1_densified_point_cloud.(las|laz)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from occufly.camera import Camera
from occufly.errors import InputFormatError
from occufly.io import crs as crsmod
from occufly.io.colmap import SparseImage, SparseModel

SUFFIX = "_calibrated_camera_parameters.txt"
MAX_BYTES = 256 * 1024**2


def find_pix4d_params(source: Path) -> Path | None:
    """The calibrated camera parameters file of a Pix4D project, or None."""
    if source.is_file():
        return source if source.name.endswith(SUFFIX) else None
    for d in (source, source / "params", source / "1_initial" / "params"):
        if d.is_dir():
            found = sorted(p for p in d.glob(f"*{SUFFIX}") if p.is_file())
            if len(found) > 1:
                raise InputFormatError(f"{d}: several Pix4D projects "
                                       f"({', '.join(p.name for p in found)}); pass one file")
            if found:
                return found[0]
    return None


def read_pix4d(source: str | Path) -> SparseModel:
    source = Path(source)
    params = find_pix4d_params(source)
    if params is None:
        raise InputFormatError(f"{source}: no Pix4D *{SUFFIX} (looked in {source}, params/ and "
                               f"1_initial/params/)")
    if params.stat().st_size > MAX_BYTES:
        raise InputFormatError(f"{params}: larger than {MAX_BYTES} bytes")
    project = params.name[: -len(SUFFIX)]
    pdir = params.parent
    off_p = pdir / f"{project}_offset.xyz"
    if not off_p.is_file():
        raise InputFormatError(f"{off_p}: missing (the offset of the camera positions)")
    try:
        offset = np.array([float(v) for v in off_p.read_text().split()[:3]])
    except ValueError:
        raise InputFormatError(f"{off_p}: expected three numbers") from None
    if offset.shape != (3,) or not np.isfinite(offset).all():
        raise InputFormatError(f"{off_p}: expected three finite numbers")
    prj_p = pdir / f"{project}_wkt.prj"
    crs = crsmod.read_prj(prj_p) if prj_p.is_file() else None
    images = _parse(params, offset)
    root = pdir.parent.parent if pdir.parent.name == "1_initial" else pdir.parent
    cloud = None
    pc = root / "2_densification" / "point_cloud"
    for ext in (".laz", ".las"):
        cand = pc / f"{project}_group1_densified_point_cloud{ext}"
        if cand.is_file():
            cloud = cand
            break
    notes = [] if crs is not None else [
        f"{prj_p.name} not found: the cameras are taken to be in the cloud's CRS"]
    return SparseModel(images, np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                       params, kind="pix4d", crs=crs, output_crs=crs, has_tracks=False,
                       default_cloud=cloud, notes=notes,
                       meta={"project": project, "offset": offset.tolist()})


def _parse(path: Path, offset: np.ndarray) -> list[SparseImage]:
    lines = path.read_text(errors="replace").splitlines()
    i = 0
    # header: lines until the first line of the form "<name> <int> <int>"
    while i < len(lines):
        parts = lines[i].split()
        if len(parts) == 3 and parts[1].isdigit() and parts[2].isdigit():
            break
        i += 1
    images = []
    while i < len(lines):
        if not lines[i].strip():
            i += 1
            continue
        head = lines[i].split()
        where = f"{path}:{i + 1}"
        if len(head) != 3 or not head[1].isdigit() or not head[2].isdigit():
            raise InputFormatError(f"{where}: expected 'image width height', got {lines[i]!r:.80}")
        block = lines[i + 1 : i + 10]
        if len(block) < 9:
            raise InputFormatError(f"{where}: image {head[0]} is truncated (expected 9 lines)")
        try:
            nums = [np.array([float(v) for v in ln.split()]) for ln in block]
        except ValueError:
            raise InputFormatError(f"{where}: image {head[0]}: non-numeric parameters") from None
        if [len(a) for a in nums] != [3, 3, 3, 3, 2, 3, 3, 3, 3]:
            raise InputFormatError(f"{where}: image {head[0]}: expected K (3x3), 3 radial, "
                                   f"2 tangential, t (3) and R (3x3)")
        K = np.stack(nums[0:3])
        radial, tang, t = nums[3], nums[4], nums[5]
        R = np.stack(nums[6:9])
        if not (np.isfinite(K).all() and np.isfinite(R).all() and np.isfinite(t).all()):
            raise InputFormatError(f"{where}: image {head[0]}: non-finite parameters")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise InputFormatError(f"{where}: image {head[0]}: R is not a rotation")
        w, h = int(head[1]), int(head[2])
        cam = Camera("BROWN", w, h, [K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1],
                                     radial[0], radial[1], radial[2], 0.0, tang[0], tang[1]])
        C = t + offset
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = -R @ C
        images.append(SparseImage(len(images) + 1, head[0], cam, T, np.zeros(0, np.int64),
                                  np.zeros((0, 2))))
        i += 10
    if not images:
        raise InputFormatError(f"{path}: no camera blocks found")
    return images
