"""How a scene's votes are decided (issue 37): the annotator model of its live lifting.

``GET /api/scenes/{id}/lifting`` (members): the model, the models to choose from with what
each does, the lifting status and what the last fill used (its decision, how many painters it
told apart, how long it took). ``PUT`` (admins): ``{"model": "pooled" | "per_author"}``;
recorded in the audit log; a scene that has been lifted is filled again with it
at once (the worker owning it is told by the ``lifting_model_changed`` event).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
from sqlalchemy import select

from app.audit import service as audit
from app.deps import AdminUser, ClientIp, CtxDep, SceneDep, SessionDep
from app.lifting.models import LIFT_MODELS
from app.users.models import User
from occufly.workspace import Workspace

router = APIRouter(prefix="/api", tags=["lifting"])

ACCESS = {
    "GET /api/scenes/{sid}/lifting": "member",
    "PUT /api/scenes/{sid}/lifting": "admin",
}

# what the last fill's statistics say about how it decided (labels.json; the rest is large)
LAST_FILL_KEYS = ("decision", "painters", "annotated_frames", "total_seconds", "confusion_annotators",
                  "confusion_skipped", "robust_warm", "robust_warm_decided", "robust_cold_why")


class LiftingIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    model: Literal["pooled", "per_author"] = Field(
        description="pooled: one confusion matrix for every painter (the default); per_author: "
                    "one per mask author")


# a painter's learned confusion is shown from this share of a true class painted as another,
# and where the EM saw at least this many of the painter's votes on that true class (5x the
# 20 pseudo-votes of its prior per row, ConfusionParams: below, the prior decides the row)
LEARNED_MIN_SHARE = 0.15
LEARNED_MIN_VOTES = 100


def learned_confusions(session, rec: dict, class_names: dict[int, str], frame_names: list[str]
                       ) -> list[dict]:  # noqa: ANN001
    """What a per-painter fill's model learned (its ``confusion_model`` record): per painter,
    the true classes it paints as another at least :data:`LEARNED_MIN_SHARE` of the time,
    where the EM saw at least :data:`LEARNED_MIN_VOTES` of its votes on that class, most first
    -- ``[{"painter", "confusions": [{"true", "painted", "share", "votes"}]}]`` (``votes``: the
    expected votes on the true class), painters with none left out. A painter is a user (by
    name) or, without an author, a frame."""
    try:
        logpi = np.asarray(rec["logpi"], np.float64)
        ids = [int(i) for i in rec["class_ids"]]
        names = [tuple(n) for n in rec["names"]]
        support = np.asarray(rec.get("support"), np.float64) if rec.get("support") is not None \
            else np.full(logpi.shape[:2], np.inf)
    except (KeyError, TypeError, ValueError):
        return []
    uids = [int(v) for k, v in names if k == "author" and str(v).lstrip("-").isdigit()]
    users = dict(session.execute(select(User.id, User.username).where(User.id.in_(uids))).all()) \
        if uids else {}
    out = []
    for a, (kind, who) in enumerate(names):
        if a >= len(logpi):
            break
        pi = np.exp(logpi[a])
        np.fill_diagonal(pi, 0.0)
        pi[support[a] < LEARNED_MIN_VOTES] = 0.0  # rows the prior decides, not the votes
        t, c = np.nonzero(pi >= LEARNED_MIN_SHARE)
        order = np.argsort(-pi[t, c], kind="stable")[:3]
        if not len(order):
            continue
        if kind == "author":
            label = users.get(int(who), f"user {who}") if str(who).lstrip("-").isdigit() else str(who)
        else:
            fi = int(who)
            label = f"{frame_names[fi] if 0 <= fi < len(frame_names) else fi} (no author)"
        out.append({"painter": label, "confusions": [
            {"true": class_names.get(ids[t[i]], str(ids[t[i]])),
             "painted": class_names.get(ids[c[i]], str(ids[c[i]])),
             "share": round(float(pi[t[i], c[i]]), 3),
             "votes": int(support[a, t[i]]) if np.isfinite(support[a, t[i]]) else None}
            for i in order]})
    return sorted(out, key=lambda r: -r["confusions"][0]["share"])


def _out(session, ctx, scene) -> dict:  # noqa: ANN001
    stats = Workspace(scene.workspace).lift_stats() if scene.status == "ready" else {}
    last = {k: stats[k] for k in LAST_FILL_KEYS if k in stats}
    rec = stats.get("confusion_model")
    if isinstance(rec, dict):
        ws_scene = ctx.load_scene(scene.workspace)
        last["learned"] = learned_confusions(
            session, rec, {c.id: c.name for c in ws_scene.taxonomy.classes},
            [f.name for f in ws_scene.frames])
    return {"scene_id": scene.id,
            "model": ctx.lifting.model(session, scene.id),
            "models": [{"id": k, "description": v} for k, v in LIFT_MODELS.items()],
            "status": ctx.lifting.status(scene.id),
            "last_fill": last}


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
