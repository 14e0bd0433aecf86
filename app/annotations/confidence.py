"""How much to trust a prefill: the lifted labels' confidence rendered into a frame.

``GET /api/frames/{fid}/prefill/confidence`` -- a single-channel PNG at the frame's size (or
1/``downscale``): 0 where no lifted label reaches the pixel (also where the point seen there
is unlabelled: the fill does not extrapolate beyond its radius, so the prefill leaves it
unpainted), else ``1 + round(254 * confidence)`` of the point seen there (confidence in
[0, 1]: the calibrated probability that the label is right, occufly.lifting.calibration;
docs/confidence.md); pixels of a closed hole between rendered points (labelled from the
nearest rendered pixel) get 1, the lowest. 404 before the first fill
(direct votes carry none). Its own router, included by app/main.py.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Response

from app import pipeline
from app.annotations import service
from app.annotations.schemas import PNG
from app.deps import CtxDep, CurrentUser, FrameDep, SessionDep
from app.errors import NotFound
from app.scenes.models import Scene
from occufly.lifting import load_labels

router = APIRouter(prefix="/api", tags=["annotations"])


def confidence_image(ctx, scene: Scene, frame, *, downscale: int = 1) -> np.ndarray:  # noqa: ANN001
    res = load_labels(scene.workspace)
    if res is None:
        raise NotFound(f"scene {scene.id} has no filled labels yet, so no confidence")
    conf = np.nan_to_num(np.asarray(res.confidence, np.float32), nan=0.0)
    q = np.where(np.asarray(res.labels) > 0,
                 1 + np.rint(254.0 * np.clip(conf, 0.0, 1.0)), 0).astype(np.uint8)
    # rendered as the prefill is (holes closed); a hole's pixels are guessed from the
    # nearest rendered pixel, so they get the lowest confidence (1)
    img, filled = service.prefill_image(ctx, scene, frame, downscale=downscale, labels=q)
    img[filled & (img > 0)] = 1
    return img


@router.get("/frames/{fid}/prefill/confidence", response_class=Response,
             responses={200: PNG})
def prefill_confidence(frame: FrameDep, session: SessionDep, ctx: CtxDep, user: CurrentUser,
                       downscale: Annotated[int, Query(ge=1, le=64)] = 1):
    service.check_read(session, frame, user)
    scene = session.get(Scene, frame.scene_id)
    img = confidence_image(ctx, scene, frame, downscale=downscale)
    return Response(pipeline.encode_png(img), media_type="image/png",
                    headers={"Cache-Control": "private, no-cache"})


# app/access.py: who may call what
ACCESS = {"GET /api/frames/{fid}/prefill/confidence": "member"}
