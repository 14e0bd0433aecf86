"""Export gating and provenance (issue 23): which mask versions an export takes, the labels
they give, and what the export records about them.

Policy (``docs/provenance.md``)
    An export takes, per frame, the frame's voting version (``Frame.voting_version_id``) when
    its state is in the export's ``include`` list: ``["accepted"]`` by default; ``submitted``
    and ``imported`` versions are unreviewed (an imported mask needs review like any other)
    and count only when the request names them. Drafts, rejected and conflict versions never
    count. A frame whose voting version is not taken is *left out* -- its votes are not in
    the exported labels -- and the export result says why (``draft``: only drafts, never
    submitted; ``submitted`` / ``imported``: not reviewed; ``rejected``).

Labels
    When the taken versions are exactly the versions the live labels count
    (``labels.json`` ``versions``), the export samples the workspace grid as before.
    Otherwise it lifts the taken versions again in a scratch folder
    (:func:`occufly.lifting.relift.relift`: the live worker's calls), applies the reviewers'
    corrections (the workspace's override layer, copied), voxelizes that
    (:func:`occufly.densify.pipeline.voxelize_workspace`, the voxelize job's function) and
    exports the scratch grid. The scratch folder is removed afterwards.

Provenance
    The manifest's ``provenance`` gets ``policy``, ``labels`` (the fill output's sha256 per
    array, the versions, whether it was lifted again) and ``masks``: for every frame whose
    mask voted, the version id, state, author, reviewer (``decided_by``), ``decided_at``,
    ``source`` and the sha256 of the mask PNG bytes (as stored). Lifting exactly those
    versions again reproduces the labels byte for byte (tests/app/test_export_gating.py).
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from app import pipeline
from app.annotations.models import MaskVersion
from app.context import AppContext
from app.lifting.service import decision_for, version_painters
from app.scenes.models import Frame
from app.users.models import User
from occufly.densify.pipeline import DensifyOptions, voxelize_workspace
from occufly.errors import OccuflyError, WorkspaceError
from occufly.grid import SceneGrid
from occufly.lifting import load_labels
from occufly.lifting import quality as lifting_quality
from occufly.lifting import relift as lifting_relift
from occufly.lifting.relift import labels_digest
from occufly.workspace import Workspace

#: the version states an export may take; ``accepted`` alone is the default
INCLUDE_STATES = ("accepted", "submitted", "imported")
DEFAULT_INCLUDE = ("accepted",)


class NothingToExport(OccuflyError):
    """No frame has a version the export's policy takes."""


def normalise_include(include) -> list[str]:  # noqa: ANN001
    vals = list(DEFAULT_INCLUDE if not include else include)
    bad = [v for v in vals if v not in INCLUDE_STATES]
    if bad:
        raise ValueError(f"include: {bad[0]!r} is not a version state an export takes; expected "
                         f"some of {', '.join(INCLUDE_STATES)}")
    return [s for s in INCLUDE_STATES if s in vals]


def _iso(t) -> str | None:  # noqa: ANN001
    return None if t is None else t.isoformat(timespec="seconds")


def export_plan(session: Session, scene_id: int, include=None) -> dict:  # noqa: ANN001
    """Which version of each frame an export with ``include`` takes, and which frames it
    leaves out and why (see the module docstring)."""
    inc = normalise_include(include)
    frames = session.execute(
        select(Frame.id, Frame.index, Frame.name, Frame.state, Frame.current_version_id,
               Frame.voting_version_id)
        .where(Frame.scene_id == scene_id,
               (Frame.current_version_id.is_not(None)) | (Frame.voting_version_id.is_not(None)))
        .order_by(Frame.index)).all()
    ids = {v for f in frames for v in (f.current_version_id, f.voting_version_id) if v is not None}
    versions = {v.id: v for v in session.scalars(select(MaskVersion).where(MaskVersion.id.in_(ids)))} \
        if ids else {}
    uids = {u for v in versions.values() for u in (v.author_id, v.decided_by_id) if u is not None}
    names = dict(session.execute(select(User.id, User.username).where(User.id.in_(uids))).all()) \
        if uids else {}
    taken, pending_drafts = [], []
    left: dict[str, list[int]] = {"draft": [], "submitted": [], "imported": [], "rejected": []}
    for f in frames:
        vv = versions.get(f.voting_version_id) if f.voting_version_id is not None else None
        cur = versions.get(f.current_version_id) if f.current_version_id is not None else None
        if vv is not None and vv.kind in inc:
            taken.append({
                "frame": int(f.index), "frame_id": int(f.id), "name": f.name, "version": int(vv.id),
                "state": vv.kind, "source": vv.source, "author": names.get(vv.author_id),
                "author_id": vv.author_id, "reviewer": names.get(vv.decided_by_id),
                "decided_by_id": vv.decided_by_id, "decided_at": _iso(vv.decided_at),
                "created_at": _iso(vv.created_at), "sha256": vv.sha256})
            if cur is not None and cur.id != vv.id and cur.kind == "draft":
                pending_drafts.append(int(f.index))  # a newer draft in progress: not taken
        elif vv is not None:
            left.setdefault(vv.kind, []).append(int(f.index))
        elif cur is not None and cur.kind == "draft":
            left["draft"].append(int(f.index))
        else:  # no voting version: rejected (or only conflicts)
            left["rejected"].append(int(f.index))
    counts = {s: sum(1 for t in taken if t["state"] == s) for s in INCLUDE_STATES}
    return {"include": inc, "taken": taken, "counts": counts,
            "left_out": {k: v for k, v in left.items()},
            "left_out_counts": {k: len(v) for k, v in left.items()},
            "drafts_after_taken": pending_drafts,
            "unreviewed_frames": [t["frame"] for t in taken if t["state"] != "accepted"]}


def painters(session: Session, report: dict) -> list[dict]:
    """A quality report's per-frame leave-one-out figures summed per painter (issue 37): who
    painted each counted version (its author; an imported mask is its tool's, a version
    without an author ``unknown``), their frames, votes with an independent label, those that
    agree, the agreement, and their most frequent disagreements (``painted`` class where the
    independent label says ``independent``; summed over each frame's three most frequent).
    Lowest agreement first: a painter far below the others who swaps the same pair on every
    frame is what the per-painter annotator model corrects."""
    rows = (report.get("loo") or {}).get("per_frame") or []
    versions = report.get("versions") or {}
    info = version_painters(session, (v for v in versions.values()
                                      if v is not None and str(v).isdigit()))
    uids = {uid for uid, _src in info.values() if uid is not None}
    names = dict(session.execute(select(User.id, User.username).where(User.id.in_(uids))).all()) \
        if uids else {}
    acc: dict[tuple, dict] = {}
    for r in rows:
        tag = versions.get(str(r["frame"]))
        uid, src = info.get(int(tag), (None, None)) if tag is not None and str(tag).isdigit() \
            else (None, None)
        if (src or "").startswith("import:"):
            key, name = ("import", src), f"imported from {src[len('import:'):]}"
        elif uid is None:
            key, name = ("unknown",), "unknown"
        else:
            key, name = ("user", uid), names.get(uid, f"user {uid}")
        a = acc.setdefault(key, {"painter": name, "user_id": uid if key[0] == "user" else None,
                                 "frames": 0, "votes": 0, "independent": 0, "agree": 0,
                                 "pairs": {}})
        a["frames"] += 1
        for k in ("votes", "independent", "agree"):
            a[k] += int(r.get(k) or 0)
        for d in r.get("disagreements") or []:
            pair = (d["painted"], d["independent"])
            a["pairs"][pair] = a["pairs"].get(pair, 0) + int(d["votes"])
    out = []
    for a in acc.values():
        pairs = sorted(a.pop("pairs").items(), key=lambda kv: (-kv[1], kv[0]))[:3]
        a["agreement"] = round(a["agree"] / a["independent"], 4) if a["independent"] else None
        a["disagreements"] = [{"painted": p, "independent": i, "votes": n} for (p, i), n in pairs]
        out.append(a)
    return sorted(out, key=lambda a: (a["agreement"] is None, a["agreement"] or 0.0, a["painter"]))


def plan_text(plan: dict) -> str:
    """"12 accepted frames; left out: 2 drafts, 3 submitted" (what the job card shows)."""
    c = plan["counts"]
    took = ", ".join(f"{c[s]} {s}" for s in INCLUDE_STATES if c.get(s)) or "no"
    n = sum(c.values())
    left = plan["left_out_counts"]
    words = {"draft": ("draft", "drafts"), "submitted": ("submitted", "submitted"),
             "imported": ("imported", "imported"), "rejected": ("rejected", "rejected")}
    out = [f"{k} {words.get(s, (s, s))[k != 1]}" for s, k in left.items() if k]
    return f"{took} frame{'s' if n != 1 else ''}" + (f"; left out: {', '.join(out)}" if out else "")


def _mask_items(ctx: AppContext, taxonomy, taken: list[dict]) -> list:  # noqa: ANN001

    items = []
    for t in taken:
        data = ctx.store.get(t["sha256"])
        if hashlib.sha256(data).hexdigest() != t["sha256"]:
            raise OccuflyError(f"mask version {t['version']} of frame {t['name']}: the stored "
                               f"bytes do not match its sha256 {t['sha256'][:12]}...")
        items.append((t["frame"], str(t["version"]), pipeline.stored_mask_ids(data, taxonomy)))
    return items


def export_labels(ctx: AppContext, ws: Path, ws_scene, plan: dict, scratch: Path, *,  # noqa: ANN001
                  voxel_size: float | None = None, progress=None,  # noqa: ANN001
                  scene_id: int | None = None) -> dict:
    """Labels, grid and provenance of an export under ``plan``.

    Returns ``{"grid": SceneGrid | None (None: the workspace's grid), "provenance": {...},
    "quality": {...}}``; lifts again in ``scratch`` (left for the caller to remove) when the
    taken versions differ from what the live labels count, deciding the votes with the scene
    ``scene_id``'s annotator model as the live lifting does (:func:`decision_for`)."""
    report = progress or (lambda f, m="": None)
    ws = Path(ws)
    chosen = {str(t["frame"]): str(t["version"]) for t in plan["taken"]}
    live = load_labels(ws, corrections=False)
    live_versions = {str(k): (None if v is None else str(v))
                     for k, v in ((live.stats.get("versions") or {}) if live is not None else {}).items()}
    if not plan["taken"] and live_versions:
        raise NothingToExport(
            f"nothing to export: no frame has a mask version in state "
            f"{' / '.join(plan['include'])} ({plan_text(plan)}); accept frames, or include "
            "submitted (and imported) versions in the export")
    policy = {"include": plan["include"], "frames": len(plan["taken"]), "counts": plan["counts"],
              "left_out": plan["left_out"], "drafts_after_taken": plan["drafts_after_taken"]}
    truth = lifting_quality.workspace_truth(ws, ws_scene.n_points)  # a synthetic scene's
    masks = [{k: t[k] for k in ("frame", "name", "version", "state", "author", "reviewer",
                                "decided_at", "source", "sha256", "created_at")}
             for t in plan["taken"]]
    if not plan["taken"]:
        # labels that no mask version of this app made (written into the workspace by the
        # command line, say): exported as they are, and the manifest says so
        try:
            q = lifting_quality.quality_report(ws, ws_scene, policy=policy, truth=truth)
        except WorkspaceError:
            q = None
        return {"grid": None, "quality": q, "provenance": {
            "policy": policy, "masks": [],
            "labels": {"relifted": False, "versions": {},
                       "sha256": labels_digest(live) if live is not None else None,
                       "note": "the workspace's labels were not lifted from mask versions of "
                               "this app; exported as they are",
                       "corrections": Workspace(ws).overrides_path.is_file()}}}
    if live is not None and live_versions == chosen:
        decided = live.stats
        digest = labels_digest(live)
        q = lifting_quality.quality_report(ws, ws_scene, policy=policy, truth=truth)
        grid = None
        relifted = False
    else:
        report(0.0, f"lifting {len(chosen)} mask versions again ({', '.join(plan['include'])})")
        items = _mask_items(ctx, ws_scene.taxonomy, plan["taken"])
        lift_dir = scratch / "lift"
        params = annotators = None
        if scene_id is not None:
            with ctx.sessions() as s:
                _model, params, annotators = decision_for(
                    s, scene_id, {t["frame"]: t["version"] for t in plan["taken"]})
        res = lifting_relift.relift(
            ws_scene, items, lift_dir, vote_weighting=lifting_relift.vote_weighting_of(ws),
            features_ws=ws, progress=lambda f, m="": report(0.6 * f, m), params=params,
            annotators=annotators)
        decided = res.stats
        digest = labels_digest(res)
        ov = Workspace(ws).overrides_path
        if ov.is_file():  # the reviewers' corrections apply to these labels as well
            dst = Workspace(lift_dir).overrides_path
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(ov, dst)
        corrected = load_labels(lift_dir)
        lp = scratch / "labels_corrected.npy"
        np.save(lp, np.asarray(corrected.labels, np.uint8))
        if voxel_size is None:
            g = Workspace(ws).grid()
            voxel_size = float(g.voxel_size) if g is not None else 0.5
        report(0.65, "voxelizing the relifted labels")
        gp = scratch / "grid" / "scene_grid.npz"
        gp.parent.mkdir(parents=True, exist_ok=True)
        voxelize_workspace(ws, labels_path=lp, out_path=gp,
                           options=DensifyOptions(voxel_size=float(voxel_size)),
                           progress=lambda f, m="": report(0.65 + 0.3 * f, m))
        grid = SceneGrid.load(gp)
        q = lifting_quality.quality_report(lift_dir, ws_scene, policy=policy, truth=truth)
        relifted = True
    report(1.0, "labels ready")
    return {"grid": grid, "quality": q, "provenance": {
        "policy": policy,
        "labels": {"relifted": relifted, "versions": chosen, "sha256": digest,
                   "what": "sha256 of the fill output's bytes (labels uint8, confidence float32, "
                           "origin uint8), before reviewers' corrections",
                   "corrections": Workspace(ws).overrides_path.is_file(),
                   # how the votes were decided (issue 37: the scene's annotator model)
                   **{k: decided[k] for k in ("decision", "painters") if k in decided}},
        "masks": masks}}


def export_result(plan: dict) -> dict:
    """The ``review`` record of an export job: the taken versions, honestly -- frames left out
    (drafts among them) are listed under ``left_out``, never as unreviewed frames taken."""
    return {"frames": [{k: t[k] for k in ("frame", "frame_id", "version", "state", "reviewer")}
                       for t in plan["taken"]],
            "n_frames": len(plan["taken"]), "n_reviewed": plan["counts"]["accepted"],
            "unreviewed_frames": plan["unreviewed_frames"], "left_out": plan["left_out"],
            "drafts_after_taken": plan["drafts_after_taken"], "include": plan["include"],
            "took": plan_text(plan)}
