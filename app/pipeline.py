"""Where the app adds something to a pipeline library call: a workspace as an import source
(copied, its frames' names and image paths checked and confined), a selection as JSON, stored
mask PNGs decoded without a frame, label images encoded for the API.

The app calls every other library function (mask decoding, lifting, rendering, the executor)
directly from ``occufly``; it never re-implements one.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from occufly import selection
from occufly.errors import UnsafePathError, check_name
from occufly.export import common as export_common
from occufly.fsutil import PathNotConfined, confined, image_content_type
from occufly.io import importer, masks
from occufly.progress import ProgressFn
from occufly.scene import Scene
from occufly.taxonomy import Taxonomy
from occufly.workspace import Workspace


class PipelineMissing(RuntimeError):
    """A pipeline step the app needs cannot run in this installation (e.g. a Dask address is
    configured but the cluster cannot be reached)."""


# ---- masks ----------------------------------------------------------------------------------
def stored_mask_ids(data: bytes, taxonomy: Taxonomy) -> np.ndarray:
    """(h, w) uint8 raw ids of a stored (already validated) mask PNG, raw-id or colour."""
    return masks.decode_mask_png(data, taxonomy, name="stored mask")


def encode_png(arr: np.ndarray) -> bytes:
    """(h, w) uint8 or (h, w, 3|4) uint8 to PNG bytes: the export's encoder
    (:func:`occufly.export.common.encode_png`: rows Up-filtered, one ISA-L deflate), a 20 MP
    label rendering in ~0.005 s of one core where PIL's per-row adaptive filter took ~0.1 s,
    for fewer bytes."""
    return export_common.encode_png(np.asarray(arr, np.uint8))


def encode_png_palette(indices: np.ndarray, palette: np.ndarray) -> bytes:
    """(h, w) uint8 palette indices and their (256, 4) uint8 RGBA colours to an indexed PNG
    (PLTE + tRNS): decoded, the same pixels as ``palette[indices]`` as RGBA, a quarter of the
    bytes of the RGBA image to filter and deflate (the export's encoder, as :func:`encode_png`:
    a 20 MP review overlay in ~0.01 s, where PIL took ~0.09 s)."""
    return export_common.encode_png(np.ascontiguousarray(indices, dtype=np.uint8),
                                    palette=np.asarray(palette, np.uint8))


# ---- import / selection --------------------------------------------------------------------
def import_scene(source: Path, workspace: Path, *, cloud: Path | None = None,
                 depth_maps: Path | None = None, progress: ProgressFn | None = None,
                 fmt: str | None = None, images: Path | None = None,
                 crs: str | None = None, roots: list[Path] | None = None,
                 scale: float | None = None) -> Scene:
    """Import a reconstruction into ``workspace``.

    ``source`` may be an existing OccuFly workspace (copied); otherwise it is handed to
    ``occufly.io.importer.import_scene``. With ``roots`` (the import roots)
    every path read from a file must resolve inside them (:func:`check_workspace_source`,
    :func:`occufly.io.importer.confine_inputs`).
    """
    source = Path(source)
    if Workspace(source).exists():
        if roots is not None:  # scene.json, taxonomy.json, the arrays: no link out
            importer.confine_tree(source, roots)
        scene = Scene.load(source, mmap=False)
        workspace_image_paths(scene, source, roots)
        scene.save(workspace, overwrite=True)
        return Scene.load(workspace)
    # the workspace belongs to this scene: a resumed import replaces a partial earlier one
    return importer.import_scene(source, workspace, cloud=cloud, depth_maps=depth_maps, taxonomy=None,
              overwrite=True, progress=progress, fmt=fmt, images=images, crs=crs, roots=roots,
              scale=scale)


def workspace_image_paths(scene: Scene, source: Path, roots: list[Path] | None) -> None:
    """The frames of a workspace being imported: names checked (no markup, no control
    characters), image paths made absolute (images stay where they are) and, with ``roots``,
    resolved (symlinks followed) and confined to them. Raises UnsafePathError naming
    ``source``'s scene.json and the frame's path -- ``/etc/passwd``, ``../../occufly.db`` or
    the app's own database file never become a frame image."""
    header = Workspace(source).scene_json
    for f in scene.frames:
        check_name(f.name, f"{header}: frame")
        if not f.image_path:
            continue
        p = Path(f.image_path)
        if not p.is_absolute():
            p = Path(source) / p
        if roots is not None:
            try:
                real = confined(p, roots)
            except PathNotConfined:
                where = ("contains a NUL byte" if "\x00" in str(p) else
                         f"resolves to {os.path.realpath(p)}, outside the import roots")
                raise UnsafePathError(
                    f"{header}: frame {f.name!r} image_path {f.image_path!r} {where}") from None
            # inside the roots is not enough (a database or key file may sit there too): what
            # is there must be an image by its content
            importer.refuse_hard_link(real, f"{header}: frame {f.name!r} image_path ")
            if real.is_file() and image_content_type(real) is None:
                raise UnsafePathError(
                    f"{header}: frame {f.name!r} image_path {f.image_path!r} is not a PNG, "
                    "JPEG, TIFF or WebP image")
            f.image_path = str(real)
        else:
            f.image_path = str(p.resolve())


def check_workspace_source(source: Path, roots: list[Path]) -> None:
    """Before an import job is created: a workspace source's scene.json is read (it is small)
    and its frames checked as :func:`workspace_image_paths` does (a 4xx from the route, not a
    failed job). A source that is not a workspace is checked by the import itself."""
    if Workspace(source).exists():
        importer.confine_tree(source, roots)
        workspace_image_paths(Scene.load(source, mmap=True), source, roots)


def select_frames(scene: Scene, **params) -> dict:
    result = selection.select_frames(scene, **params)
    d = result.to_dict()
    d["frames"] = [int(i) for i in result.frames]
    return d
