"""How a scene's votes are decided (issue 37): the annotator model of its live lifting.

``GET /api/scenes/{id}/lifting`` (members): the model, the models to choose from with what
each does, the lifting status and what the last fill used (its decision, how many painters it
told apart, how long it took). ``PUT`` (admins): ``{"model": "pooled" | "per_author"}``;
recorded in the audit log; a scene that has been lifted is filled again with it
at once (the worker owning it is told by the ``lifting_model_changed`` event).
"""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from app.audit import service as audit
from app.deps import AdminUser, ClientIp, CtxDep, SceneDep, SessionDep
from app.lifting.models import LIFT_MODELS
from occufly.workspace import Workspace

router = APIRouter(prefix="/api", tags=["lifting"])

ACCESS = {
    "GET /api/scenes/{sid}/lifting": "member",
    "PUT /api/scenes/{sid}/lifting": "admin",
}

# what the last fill's statistics say about how it decided (labels.json; the rest is large)
LAST_FILL_KEYS = ("decision", "painters", "annotated_frames", "total_seconds", "confusion_annotators",
                  "confusion_skipped")


class LiftingIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    model: Literal["pooled", "per_author"] = Field(
        description="pooled: one confusion matrix for every painter (the default); per_author: "
                    "one per mask author")


def _out(session, ctx, scene) -> dict:  # noqa: ANN001
    stats = Workspace(scene.workspace).lift_stats() if scene.status == "ready" else {}
    return {"scene_id": scene.id,
            "model": ctx.lifting.model(session, scene.id),
            "models": [{"id": k, "description": v} for k, v in LIFT_MODELS.items()],
            "status": ctx.lifting.status(scene.id),
            "last_fill": {k: stats[k] for k in LAST_FILL_KEYS if k in stats}}


@router.get("/scenes/{sid}/lifting")
def get_lifting(scene: SceneDep, session: SessionDep, ctx: CtxDep) -> dict:
    return _out(session, ctx, scene)


@router.put("/scenes/{sid}/lifting")
def set_lifting(body: LiftingIn, scene: SceneDep, session: SessionDep, ctx: CtxDep,
                admin: AdminUser, ip: ClientIp) -> dict:
    old = ctx.lifting.model(session, scene.id)
    changed = ctx.lifting.set_model(session, scene.id, body.model)
    if changed:
        audit.record(session, "lifting_model", actor=admin, scene_id=scene.id,
                     target=scene.name, client_ip=ip, detail={"from": old, "to": body.model})
    session.commit()
    if changed and ctx.events is not None:
        ctx.events.publish("lifting_model_changed", scene.id, model=body.model)
    return _out(session, ctx, scene)
