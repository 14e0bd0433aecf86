"""Smart annotation tools that run server-side, without model downloads.

``POST /api/frames/{fid}/grabcut`` -- OpenCV GrabCut in a box the annotator drew (optionally
with foreground / background scribble points or strokes): answers a single-channel PNG of the box
(255 = the object, 0 = not) with ``X-Box: x0,y0,x1,y1`` (image pixels, exclusive ends). The
page fills those pixels with the active class as one undoable command, and re-runs the cut
with the scribbles the annotator paints afterwards (the new cut replaces the old one in that
same command). Large boxes are cut at <= ``WORK_SIDE`` px and the result scaled back
(nearest), so a 20 MP frame answers in about a second.

``POST /api/frames/{fid}/scissors`` -- intelligent scissors (OpenCV
``segmentation.IntelligentScissorsMB``, live-wire on Canny edges and the gradient): the path
between two anchor points that follows the image's edges, as JSON ``{"path": [[x, y], ...]}``
in image pixels from ``start`` to ``end``. It is computed on a crop around the two anchors
(their box plus a margin, so the path can detour around a corner), downscaled to at most
``SCISSORS_SIDE`` px, so it costs about 0.1 s whatever the frame size. The page joins the
segments into a polygon and fills it with the active class as one undoable command.

Both decode the frame's photo once and keep the last few decoded photos (``_photo``), so the
live preview of the scissors (a request per cursor pause) does not decode a 20 MP JPEG each
time.
"""

from __future__ import annotations

import io
import threading
import time
from collections import OrderedDict
from typing import Literal

import numpy as np
from fastapi import APIRouter, Response
from PIL import Image
from pydantic import BaseModel, Field

from app.annotations import service
from app.annotations.schemas import PNG
from app.deps import AnnotatorUser, CtxDep, FrameDep, SessionDep
from app.errors import Invalid
from app.scenes import service as scenes
from app.scenes.models import Frame, Scene

router = APIRouter(prefix="/api", tags=["annotations"])

WORK_SIDE = 640  # longest side of the box GrabCut works on
SCISSORS_SIDE = 512  # longest side of the crop the scissors work on (~0.1 s)
PHOTO_CACHE = 2  # decoded photos kept (a 20 MP photo is 60 MB)
Coord = Field(ge=0, le=200_000)


MAX_STROKE_POINTS = 20_000  # all scribble strokes of one request together


class Scribble(BaseModel):
    kind: Literal["fg", "bg"] = Field(description="fg: the object, bg: not the object")
    points: list[list[int]] = Field(min_length=1, max_length=MAX_STROKE_POINTS,
                                    description="x, y image px along the stroke")


class GrabCutIn(BaseModel):
    rect: list[int] = Field(min_length=4, max_length=4, description="x0, y0, x1, y1 (image px)")
    fg: list[list[int]] = Field(default_factory=list, max_length=20_000)
    bg: list[list[int]] = Field(default_factory=list, max_length=20_000)
    strokes: list[Scribble] = Field(
        default_factory=list, max_length=500,
        description="scribbles in the order they were painted (a later one wins where they "
                    "overlap), drawn as lines after the fg / bg points")
    iterations: int = Field(default=4, ge=1, le=10)


class ScissorsIn(BaseModel):
    start: list[int] = Field(min_length=2, max_length=2, description="x, y of the anchor (image px)")
    end: list[int] = Field(min_length=2, max_length=2, description="x, y of the next point (image px)")


class ScissorsOut(BaseModel):
    path: list[list[int]] = Field(description="x, y image pixels from start to end (both included)")
    crop: list[int] = Field(description="x0, y0, x1, y1: the part of the photo searched")
    scale: float = Field(description="working scale of the crop (1 = full resolution)")
    ms: float = Field(description="server time for the path, milliseconds")


_photos: OrderedDict[tuple, np.ndarray] = OrderedDict()
_photos_lock = threading.Lock()


def _photo(session, ctx, frame: Frame) -> np.ndarray:  # noqa: ANN001
    """The frame's photo as (height, width, 3) uint8 RGB at the frame's size (cached)."""
    scene = session.get(Scene, frame.scene_id)
    src = scenes.image_file(ctx.load_scene(scene.workspace), scene.workspace, frame.index,
                            roots=scenes.image_roots(ctx.settings))
    st = src.stat()
    key = (str(src), st.st_mtime_ns, st.st_size, frame.width, frame.height)
    with _photos_lock:
        if key in _photos:
            _photos.move_to_end(key)
            return _photos[key]
    with Image.open(src) as im:
        rgb = np.asarray(im.convert("RGB"))
    if rgb.shape[:2] != (frame.height, frame.width):  # image stored at another size
        rgb = np.asarray(Image.fromarray(rgb).resize((frame.width, frame.height)))
    rgb.setflags(write=False)
    with _photos_lock:
        _photos[key] = rgb
        while len(_photos) > PHOTO_CACHE:
            _photos.popitem(last=False)
    return rgb


def grabcut(rgb: np.ndarray, rect: tuple[int, int, int, int], fg=(), bg=(),  # noqa: ANN001
            iterations: int = 4, strokes=()) -> np.ndarray:  # noqa: ANN001
    """(y1-y0, x1-x0) bool mask of the object in ``rect`` of ``rgb`` (H, W, 3 uint8).

    ``fg`` / ``bg``: points certainly (not) on the object; ``strokes``: (kind, points) lines in
    painting order, "fg" or "bg", each ~6 px wide (at least 3 working px)."""
    import cv2  # OpenCV: a heavy import (~0.5 s) only the smart tools need

    x0, y0, x1, y1 = rect
    H, W = rgb.shape[:2]
    # work on the box plus a margin (GrabCut learns the background from around the box)
    m = max(8, (x1 - x0 + y1 - y0) // 8)
    cx0, cy0, cx1, cy1 = max(0, x0 - m), max(0, y0 - m), min(W, x1 + m), min(H, y1 + m)
    crop = rgb[cy0:cy1, cx0:cx1]
    s = min(1.0, WORK_SIDE / max(crop.shape[:2]))
    small = crop if s == 1.0 else cv2.resize(crop, (max(1, round(crop.shape[1] * s)),
                                                   max(1, round(crop.shape[0] * s))),
                                            interpolation=cv2.INTER_AREA)
    h, w = small.shape[:2]
    mask = np.zeros((h, w), np.uint8)  # GC_BGD
    r = [int((x0 - cx0) * s), int((y0 - cy0) * s), max(1, int((x1 - x0) * s)), max(1, int((y1 - y0) * s))]
    mask[r[1]:r[1] + r[3], r[0]:r[0] + r[2]] = cv2.GC_PR_FGD
    rad = max(1, int(round(3 * s)))
    for pts, val in ((fg, cv2.GC_FGD), (bg, cv2.GC_BGD)):
        for x, y in pts:
            cv2.circle(mask, (int((x - cx0) * s), int((y - cy0) * s)), rad, int(val), -1)
    for kind, pts in strokes:
        val = int(cv2.GC_FGD if kind == "fg" else cv2.GC_BGD)
        line = np.array([[int((x - cx0) * s), int((y - cy0) * s)] for x, y in pts], np.int32)
        if len(line) == 1:
            cv2.circle(mask, tuple(int(v) for v in line[0]), rad, val, -1)
        else:
            cv2.polylines(mask, [line.reshape(-1, 1, 2)], False, val, thickness=2 * rad + 1)
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    mode = cv2.GC_INIT_WITH_MASK
    cv2.setRNGSeed(0)  # GrabCut's k-means start: the same box gives the same cut every time
    cv2.grabCut(np.ascontiguousarray(small[:, :, ::-1]), mask, None, bgd, fgd, iterations, mode)
    obj = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)).astype(np.uint8)
    if s != 1.0:
        obj = cv2.resize(obj, (crop.shape[1], crop.shape[0]), interpolation=cv2.INTER_NEAREST)
    return obj[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0].astype(bool)


def scissors(rgb: np.ndarray, start: tuple[int, int], end: tuple[int, int],
             side: int = SCISSORS_SIDE) -> tuple[np.ndarray, tuple[int, int, int, int], float]:
    """Edge-following path from ``start`` to ``end`` (x, y image px) in ``rgb`` (H, W, 3).

    Returns (path (n, 2) int x, y with path[0] == start and path[-1] == end, crop box
    x0, y0, x1, y1, working scale). The live-wire runs on the anchors' box plus a margin of
    half their distance (at least 24 px), downscaled so its longest side is <= ``side``.
    """
    import cv2  # OpenCV: a heavy import (~0.5 s) only the smart tools need

    H, W = rgb.shape[:2]
    (sx, sy), (ex, ey) = start, end
    if (sx, sy) == (ex, ey):
        return np.array([[sx, sy]], np.int32), (sx, sy, sx + 1, sy + 1), 1.0
    m = max(24, int(0.5 * np.hypot(ex - sx, ey - sy)))
    cx0, cy0 = max(0, min(sx, ex) - m), max(0, min(sy, ey) - m)
    cx1, cy1 = min(W, max(sx, ex) + m + 1), min(H, max(sy, ey) + m + 1)
    crop = rgb[cy0:cy1, cx0:cx1]
    s = min(1.0, side / max(crop.shape[:2]))
    if s < 1.0:
        crop = cv2.resize(crop, (max(2, round(crop.shape[1] * s)), max(2, round(crop.shape[0] * s))),
                          interpolation=cv2.INTER_AREA)
    h, w = crop.shape[:2]

    def to_work(x: int, y: int) -> tuple[int, int]:
        return (min(w - 1, max(0, int((x - cx0 + 0.5) * s))),
                min(h - 1, max(0, int((y - cy0 + 0.5) * s))))

    tool = cv2.segmentation.IntelligentScissorsMB()
    tool.setEdgeFeatureCannyParameters(32, 100)
    tool.setGradientMagnitudeMaxLimit(200)
    tool.applyImage(np.ascontiguousarray(crop[:, :, ::-1]))
    tool.buildMap(to_work(sx, sy))
    c = tool.getContour(to_work(ex, ey)).reshape(-1, 2)
    # getContour answers the path from the target back to the source: start it at the anchor
    if len(c) > 1 and tuple(c[0]) == to_work(ex, ey) and tuple(c[-1]) == to_work(sx, sy):
        c = c[::-1]
    if s < 1.0:
        c = np.round((c + 0.5) / s - 0.5).astype(np.int64) + (cx0, cy0)
        c = np.clip(c, 0, (W - 1, H - 1))
    else:
        c = c.astype(np.int64) + (cx0, cy0)
    path = np.concatenate([[(sx, sy)], c, [(ex, ey)]]).astype(np.int32)
    keep = np.ones(len(path), bool)
    keep[1:] = np.any(path[1:] != path[:-1], axis=1)  # drop repeated points
    path = path[keep]
    if len(path) > 3:  # straight runs -> their end points (within half a working pixel)
        path = cv2.approxPolyDP(path.reshape(-1, 1, 2), 0.5 / s, False).reshape(-1, 2)
    return path, (cx0, cy0, cx1, cy1), s


def _inside(name: str, p: list[int], frame: Frame) -> tuple[int, int]:
    if len(p) != 2 or not (0 <= p[0] < frame.width and 0 <= p[1] < frame.height):
        raise Invalid(f"{name}: point {p} is not an (x, y) inside the {frame.width}x{frame.height} "
                      f"image of frame {frame.id}")
    return int(p[0]), int(p[1])


@router.post("/frames/{fid}/grabcut", response_class=Response,
              responses={200: PNG, 422: {"description": "box outside the image"}})
def grabcut_route(body: GrabCutIn, frame: FrameDep, session: SessionDep, ctx: CtxDep,
                  user: AnnotatorUser):
    service.check_read(session, frame, user)
    x0, y0, x1, y1 = (int(v) for v in body.rect)
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    if x0 < 0 or y0 < 0 or x1 > frame.width or y1 > frame.height or x1 - x0 < 2 or y1 - y0 < 2:
        raise Invalid(f"rect {body.rect} must be a box of at least 2x2 px inside the "
                      f"{frame.width}x{frame.height} image of frame {frame.id}")
    for name, pts in (("fg", body.fg), ("bg", body.bg)):
        for p in pts:
            _inside(name, p, frame)
    total = sum(len(st.points) for st in body.strokes)
    if total > MAX_STROKE_POINTS:
        raise Invalid(f"strokes: {total} points in all; at most {MAX_STROKE_POINTS}")
    for i, st in enumerate(body.strokes):
        for p in st.points:
            _inside(f"strokes[{i}]", p, frame)
    rgb = _photo(session, ctx, frame)
    obj = grabcut(rgb, (x0, y0, x1, y1), body.fg, body.bg, body.iterations,
                  [(st.kind, st.points) for st in body.strokes])
    buf = io.BytesIO()
    Image.fromarray(obj.astype(np.uint8) * 255, mode="L").save(buf, format="PNG")
    return Response(buf.getvalue(), media_type="image/png",
                    headers={"X-Box": f"{x0},{y0},{x1},{y1}", "Cache-Control": "no-store",
                             "Access-Control-Expose-Headers": "X-Box"})


@router.post("/frames/{fid}/scissors", response_model=ScissorsOut,
             responses={422: {"description": "a point outside the image"}})
def scissors_route(body: ScissorsIn, frame: FrameDep, session: SessionDep, ctx: CtxDep,
                   user: AnnotatorUser) -> ScissorsOut:
    service.check_read(session, frame, user)
    start = _inside("start", body.start, frame)
    end = _inside("end", body.end, frame)
    rgb = _photo(session, ctx, frame)
    t0 = time.perf_counter()
    path, crop, s = scissors(rgb, start, end)
    return ScissorsOut(path=path.tolist(), crop=list(crop), scale=round(s, 4),
                       ms=round(1000 * (time.perf_counter() - t0), 1))


# app/access.py: who may call what
ACCESS = {"POST /api/frames/{fid}/grabcut": "annotator",
          "POST /api/frames/{fid}/scissors": "annotator"}
