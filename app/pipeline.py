"""The one place the app calls the pipeline library (``occufly.*``).

Pipeline modules written by other engineers are imported lazily, at call time, so a module
that lands later is picked up without touching the app; where a module is still missing the
call either falls back (documented per function) or raises :class:`PipelineMissing`, which a
job reports as a clear failure instead of faking a result.
"""

from __future__ import annotations

import importlib
import io
from pathlib import Path
from typing import Any

import numpy as np

from occufly.errors import InputFormatError, MaskError
from occufly.progress import ProgressFn
from occufly.scene import Frame as SceneFrame
from occufly.scene import Scene
from occufly.taxonomy import Taxonomy


class PipelineMissing(RuntimeError):
    """A pipeline function the app needs is not available in this installation."""


def pipeline_function(module: str, name: str) -> Any:
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and module.startswith(e.name):
            raise PipelineMissing(
                f"{module}.{name} is not available in this installation (module {module} "
                f"is missing)") from None
        raise
    fn = getattr(mod, name, None)
    if fn is None:
        raise PipelineMissing(f"{module}.{name} is not available in this installation")
    return fn


def has(module: str, name: str) -> bool:
    try:
        pipeline_function(module, name)
        return True
    except PipelineMissing:
        return False


# ---- masks ----------------------------------------------------------------------------------
def decode_mask(data: bytes, frame: SceneFrame, taxonomy: Taxonomy, *, name: str) -> np.ndarray:
    """(h, w) uint8 raw ids from an uploaded PNG; raises MaskError naming ``name``.

    Uses ``occufly.io.masks.read_mask`` when present; otherwise an equivalent check of the
    single-channel raw-id format (frame size or an exact integer downscale, ids in taxonomy,
    0 and 255 allowed).
    """
    if has("occufly.io.masks", "decode_mask_png"):
        # read_mask's steps, with the id check done as a 256-entry lookup (no int64 copy of a
        # 20 MP mask per upload); on failure occufly's own validate_ids raises its message
        from occufly.io import masks

        ids = masks.decode_mask_png(data, taxonomy, name=name)
        masks.mask_scale(ids.shape, frame, name=name)
        ok = taxonomy.valid_lut().copy()
        ok[0] = ok[255] = True
        if not ok[ids].all():
            masks.validate_ids(ids, taxonomy, name=name)
            raise MaskError(f"{name}: class ids not in taxonomy {taxonomy.name!r}")
        return ids
    if has("occufly.io.masks", "read_mask"):
        return pipeline_function("occufly.io.masks", "read_mask")(data, frame, taxonomy, name=name)
    from PIL import Image, UnidentifiedImageError

    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise MaskError(f"{name}: not a PNG file")
    try:
        with Image.open(io.BytesIO(data)) as im:
            im.load()
            mode = im.mode
            arr = np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise MaskError(f"{name}: PNG does not decode ({e})") from None
    if mode not in ("L", "P", "I;16", "I"):
        raise MaskError(f"{name}: expected a single-channel raw-id PNG, got mode {mode}")
    if arr.ndim != 2:
        raise MaskError(f"{name}: expected a single-channel image, got shape {arr.shape}")
    h, w = arr.shape
    W, H = frame.camera.width, frame.camera.height
    if (w, h) != (W, H):
        s = W // w if w else 0
        if not (s >= 2 and w * s == W and h * s == H):
            raise MaskError(f"{name}: size {w}x{h} does not match the frame ({W}x{H}) or an "
                            "exact integer downscale of it")
    if arr.max(initial=0) > 255:
        raise MaskError(f"{name}: values above 255 are not class ids")
    arr = arr.astype(np.uint8)
    present = np.unique(arr)
    allowed = set(int(i) for i in taxonomy.ids) | {0, 255}
    bad = [int(v) for v in present if int(v) not in allowed]
    if bad:
        raise MaskError(f"{name}: class ids {bad[:10]} are not in taxonomy {taxonomy.name!r}")
    return arr


def stored_mask_ids(data: bytes, taxonomy: Taxonomy) -> np.ndarray:
    """(h, w) uint8 raw ids of a stored (already validated) mask PNG, raw-id or colour."""
    if has("occufly.io.masks", "decode_mask_png"):
        from occufly.io import masks

        return masks.decode_mask_png(data, taxonomy, name="stored mask")
    from PIL import Image

    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im).astype(np.uint8)


def encode_png(arr: np.ndarray) -> bytes:
    """(h, w) uint8 or (h, w, 3|4) uint8 to PNG bytes."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(arr)).save(buf, format="PNG", compress_level=3)
    return buf.getvalue()


# ---- import / selection --------------------------------------------------------------------
def import_scene(source: Path, workspace: Path, *, cloud: Path | None = None,
                 depth_maps: Path | None = None, progress: ProgressFn | None = None) -> Scene:
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
    fn = pipeline_function("occufly.io.importer", "import_scene")
    # the workspace belongs to this scene: a resumed import replaces a partial earlier one
    return fn(source, workspace, cloud=cloud, depth_maps=depth_maps, taxonomy=None,
              overwrite=True, progress=progress)


def select_frames(scene: Scene, **params) -> dict:
    result = pipeline_function("occufly.selection", "select_frames")(scene, **params)
    d = result.to_dict() if hasattr(result, "to_dict") else dict(result)
    d["frames"] = [int(i) for i in result.frames]
    return d


# ---- lifting / render ----------------------------------------------------------------------
def open_lift_state(workspace: Path, scene: Scene):
    """occufly.lifting.LiftState for the workspace, or None while lifting is not installed."""
    if not has("occufly.lifting", "LiftState"):
        return None
    return pipeline_function("occufly.lifting", "LiftState").open(Path(workspace), scene)


def load_labels(workspace: Path):
    if not has("occufly.lifting", "load_labels"):
        return None
    return pipeline_function("occufly.lifting", "load_labels")(Path(workspace))


def render_labels(scene: Scene, labels: np.ndarray, frame_index: int, *, scale: float = 1.0):
    return pipeline_function("occufly.render", "render_labels")(scene, labels, frame_index,
                                                                 scale=scale)


def render_for_mask(scene: Scene, labels: np.ndarray, frame_index: int,
                    mask_shape: tuple[int, int]):
    return pipeline_function("occufly.render", "render_for_mask")(scene, labels, frame_index,
                                                                   tuple(mask_shape))


def agreement(mask: np.ndarray, rendered: np.ndarray, taxonomy: Taxonomy) -> dict:
    return pipeline_function("occufly.render", "agreement")(mask, rendered, taxonomy)


def disagreement_image(mask: np.ndarray, rendered: np.ndarray, taxonomy: Taxonomy) -> np.ndarray:
    return pipeline_function("occufly.render", "disagreement_image")(mask, rendered, taxonomy)


def upsample_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour upsample of an integer-downscaled (h, w) mask to (height, width)."""
    h, w = mask.shape
    if (w, h) == (width, height):
        return mask
    s = width // w
    return np.repeat(np.repeat(mask, s, axis=0), s, axis=1)


# ---- executor -------------------------------------------------------------------------------
def get_executor(dask_address: str | None = None):
    """occufly.parallel.get_executor when present, else None (callers then run in-process)."""
    if has("occufly.parallel", "get_executor"):
        return pipeline_function("occufly.parallel", "get_executor")(dask_address)
    if dask_address:
        raise InputFormatError(
            "OCCUFLY_DASK_ADDRESS is set but occufly.parallel is not available to use it")
    return None
