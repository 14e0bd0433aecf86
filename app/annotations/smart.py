"""Smart annotation tools that run server-side, without model downloads.

``POST /api/frames/{fid}/grabcut`` -- OpenCV GrabCut in a box the annotator drew (optionally
with foreground / background scribble points): answers a single-channel PNG of the box
(255 = the object, 0 = not) with ``X-Box: x0,y0,x1,y1`` (image pixels, exclusive ends). The
page fills those pixels with the active class as one undoable command. Large boxes are cut at
<= ``WORK_SIDE`` px and the result scaled back (nearest), so a 20 MP frame answers in about a
second.
"""

from __future__ import annotations

import io

import numpy as np
from fastapi import APIRouter, Response
from pydantic import BaseModel, Field

from app.annotations import service
from app.annotations.schemas import PNG
from app.deps import AnnotatorUser, CtxDep, FrameDep, SessionDep
from app.errors import Invalid
from app.scenes import service as scenes
from app.scenes.models import Scene

router = APIRouter(prefix="/api", tags=["annotations"])

WORK_SIDE = 640  # longest side of the box GrabCut works on
Coord = Field(ge=0, le=200_000)


class GrabCutIn(BaseModel):
    rect: list[int] = Field(min_length=4, max_length=4, description="x0, y0, x1, y1 (image px)")
    fg: list[list[int]] = Field(default_factory=list, max_length=20_000)
    bg: list[list[int]] = Field(default_factory=list, max_length=20_000)
    iterations: int = Field(default=4, ge=1, le=10)


def grabcut(rgb: np.ndarray, rect: tuple[int, int, int, int], fg=(), bg=(),  # noqa: ANN001
            iterations: int = 4) -> np.ndarray:
    """(y1-y0, x1-x0) bool mask of the object in ``rect`` of ``rgb`` (H, W, 3 uint8)."""
    import cv2

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
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    mode = cv2.GC_INIT_WITH_MASK
    cv2.setRNGSeed(0)  # GrabCut's k-means start: the same box gives the same cut every time
    cv2.grabCut(np.ascontiguousarray(small[:, :, ::-1]), mask, None, bgd, fgd, iterations, mode)
    obj = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)).astype(np.uint8)
    if s != 1.0:
        obj = cv2.resize(obj, (crop.shape[1], crop.shape[0]), interpolation=cv2.INTER_NEAREST)
    return obj[y0 - cy0:y1 - cy0, x0 - cx0:x1 - cx0].astype(bool)


@router.post("/frames/{fid}/grabcut", response_class=Response,
              responses={200: PNG, 422: {"description": "box outside the image"}})
def grabcut_route(body: GrabCutIn, frame: FrameDep, session: SessionDep, ctx: CtxDep,
                  user: AnnotatorUser):
    from PIL import Image

    service.check_read(session, frame, user)
    x0, y0, x1, y1 = (int(v) for v in body.rect)
    x0, x1 = sorted((x0, x1))
    y0, y1 = sorted((y0, y1))
    if x0 < 0 or y0 < 0 or x1 > frame.width or y1 > frame.height or x1 - x0 < 2 or y1 - y0 < 2:
        raise Invalid(f"rect {body.rect} must be a box of at least 2x2 px inside the "
                      f"{frame.width}x{frame.height} image of frame {frame.id}")
    for name, pts in (("fg", body.fg), ("bg", body.bg)):
        for p in pts:
            if len(p) != 2 or not (0 <= p[0] < frame.width and 0 <= p[1] < frame.height):
                raise Invalid(f"{name}: point {p} is not an (x, y) inside the image")
    scene = session.get(Scene, frame.scene_id)
    src = scenes.image_file(ctx.load_scene(scene.workspace), scene.workspace, frame.index)
    with Image.open(src) as im:
        rgb = np.asarray(im.convert("RGB"))
    if rgb.shape[:2] != (frame.height, frame.width):  # image stored at another size
        rgb = np.asarray(Image.fromarray(rgb).resize((frame.width, frame.height)))
    obj = grabcut(rgb, (x0, y0, x1, y1), body.fg, body.bg, body.iterations)
    buf = io.BytesIO()
    Image.fromarray(obj.astype(np.uint8) * 255, mode="L").save(buf, format="PNG")
    return Response(buf.getvalue(), media_type="image/png",
                    headers={"X-Box": f"{x0},{y0},{x1},{y1}", "Cache-Control": "no-store",
                             "Access-Control-Expose-Headers": "X-Box"})


# app/access.py: who may call what
ACCESS = {"POST /api/frames/{fid}/grabcut": "annotator"}
