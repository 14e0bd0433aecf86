"""The one place the app calls the pipeline library (``occufly.*``).

Thin adapters only: every step (mask decoding, import, selection, lifting, rendering) is the
library's own function; the app never re-implements one.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from occufly import lifting, render, selection
from occufly.io import importer, masks
from occufly.progress import ProgressFn
from occufly.scene import Frame as SceneFrame
from occufly.scene import Scene
from occufly.taxonomy import Taxonomy


class PipelineMissing(RuntimeError):
    """A pipeline step the app needs cannot run in this installation (e.g. a Dask address is
    configured but the cluster cannot be reached)."""


# ---- masks ----------------------------------------------------------------------------------
def decode_mask(data: bytes, frame: SceneFrame, taxonomy: Taxonomy, *, name: str) -> np.ndarray:
    """(h, w) uint8 raw ids from an uploaded PNG (:func:`occufly.io.masks.read_mask`: frame
    size or an exact integer downscale, ids in the taxonomy, 0 and 255 allowed); raises
    MaskError naming ``name``."""
    return masks.read_mask(data, frame, taxonomy, name=name)


def stored_mask_ids(data: bytes, taxonomy: Taxonomy) -> np.ndarray:
    """(h, w) uint8 raw ids of a stored (already validated) mask PNG, raw-id or colour."""
    return masks.decode_mask_png(data, taxonomy, name="stored mask")


def encode_png(arr: np.ndarray) -> bytes:
    """(h, w) uint8 or (h, w, 3|4) uint8 to PNG bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(arr)).save(buf, format="PNG", compress_level=3)
    return buf.getvalue()


# ---- import / selection --------------------------------------------------------------------
def import_scene(source: Path, workspace: Path, *, cloud: Path | None = None,
                 depth_maps: Path | None = None, progress: ProgressFn | None = None,
                 fmt: str | None = None, images: Path | None = None,
                 crs: str | None = None) -> Scene:
    """Import a reconstruction into ``workspace``.

    ``source`` may be an existing OccuFly workspace (copied); otherwise it is handed to
    ``occufly.io.importer.import_scene``.
    """
    source = Path(source)
    from occufly.workspace import Workspace

    if Workspace(source).exists():
        scene = Scene.load(source, mmap=False)
        for f in scene.frames:  # images stay where they are: make their paths absolute
            if f.image_path and not Path(f.image_path).is_absolute():
                f.image_path = str((source / f.image_path).resolve())
        scene.save(workspace, overwrite=True)
        return Scene.load(workspace)
    # the workspace belongs to this scene: a resumed import replaces a partial earlier one
    return importer.import_scene(source, workspace, cloud=cloud, depth_maps=depth_maps, taxonomy=None,
              overwrite=True, progress=progress, fmt=fmt, images=images, crs=crs)


def select_frames(scene: Scene, **params) -> dict:
    result = selection.select_frames(scene, **params)
    d = result.to_dict()
    d["frames"] = [int(i) for i in result.frames]
    return d


# ---- lifting / render ----------------------------------------------------------------------
def open_lift_state(workspace: Path, scene: Scene) -> lifting.LiftState:
    """The workspace's vote state (created empty on first use)."""
    return lifting.LiftState.open(Path(workspace), scene)


def load_labels(workspace: Path) -> lifting.LiftResult | None:
    """The latest fill/denoise output of the workspace, or None before the first fill."""
    return lifting.load_labels(Path(workspace))


render_labels = render.render_labels
render_for_mask = render.render_for_mask
render_prefill = render.render_prefill
agreement = render.agreement
disagreement_image = render.disagreement_image


# ---- executor -------------------------------------------------------------------------------
def get_executor(dask_address: str | None = None):
    """The library's executor (:func:`occufly.parallel.get_executor`): a local process pool,
    or the Dask cluster at ``dask_address``."""
    from occufly.parallel import get_executor as _get_executor

    return _get_executor(dask_address)
