"""Lifting a chosen set of mask versions again, in a scratch workspace (issue 23).

The live labels of a scene count every voting version (submitted, accepted, imported). An
export under a narrower policy (accepted versions only, the default) needs the labels those
versions alone give: :func:`relift` counts them in a fresh :class:`VoteStore` under a scratch
folder -- :meth:`VoteStore.apply_frame` for each mask, :meth:`VoteStore.snapshot`, then
:func:`fill_snapshot`, exactly the calls the app's lifting worker makes -- and writes
``labels.npy`` / ``confidence.npy`` / ``origin.npy`` there. Vote counts are sums, so the order
in which masks are applied does not matter, and the fill is deterministic: lifting the same
versions again gives the same arrays byte for byte (``tests/app/test_export_gating.py``).

:func:`labels_digest` is the sha256 of each array's bytes, what an export manifest records.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from occufly.lifting.confusion import load_frame_votes
from occufly.lifting.knn import LiftParams
from occufly.lifting.result import LiftResult, save_result
from occufly.lifting.votes import VoteStore, fill_snapshot
from occufly.progress import ProgressFn, noop
from occufly.scene import Scene
from occufly.workspace import Workspace


def vote_weighting_of(ws: str | Path) -> str:
    """The vote weighting of workspace ``ws``'s lifting state (``plain`` without one)."""
    p = Workspace(ws).lifting_state
    if not p.is_file():
        return "plain"
    try:
        return str(json.loads(p.read_text()).get("vote_weighting", "plain"))
    except (OSError, ValueError):
        return "plain"


def relift(scene: Scene, masks: Iterable[tuple[int, str, np.ndarray]], scratch: str | Path, *,
           vote_weighting: str = "plain", params: LiftParams | None = None,
           features_ws: str | Path | None = None, progress: ProgressFn | None = None,
           annotators: dict | None = None) -> LiftResult:
    """Lift ``masks`` ((frame index, version tag, (h, w) uint8 raw ids) each) from scratch into
    the empty folder ``scratch`` and return the fill result (also written there).

    features_ws: a workspace whose robust-decision feature cache may be read (never written;
    the features are a function of the cloud alone, so the result is the same without it).
    annotators: frame -> who painted it, for the decisions that tell painters apart
    (``RobustParams.confusion`` / ``regions``; they read these masks' votes from ``scratch``).
    """
    report = progress or noop
    scratch = Path(scratch)
    if Workspace(scratch).lifting_state.exists():
        raise FileExistsError(f"{scratch}: already holds a lifting state (relift needs an empty "
                              "folder)")
    scratch.mkdir(parents=True, exist_ok=True)
    state = VoteStore.open(scratch, scene, vote_weighting=vote_weighting)
    try:
        items = list(masks)
        for k, (fi, tag, mask) in enumerate(items):
            state.apply_frame(int(fi), mask, version=str(tag), name=f"mask version {tag}")
            report(0.5 * (k + 1) / max(1, len(items)), f"votes of {k + 1}/{len(items)} masks")
        snap = state.snapshot()
        rp = getattr(params, "robust_params", None)
        if getattr(rp, "confusion", None) is not None or getattr(rp, "regions", None) is not None:
            # every frame's votes from this scratch state (not features_ws's own masks)
            snap.frame_votes = load_frame_votes(scratch, sorted(snap.versions))
        snap.annotators = dict(annotators) if annotators is not None else None
        result = fill_snapshot(scene, snap, params=params, ws=features_ws, read_only=True,
                               progress=lambda f, m: report(0.5 + 0.45 * f, m))
        save_result(scratch, result)
    finally:
        state.close()
    report(1.0, "relifted")
    return result


def labels_digest(result: LiftResult) -> dict[str, str]:
    """sha256 of the bytes of the labels (uint8), confidence (float32) and origin (uint8)."""
    return {name: hashlib.sha256(np.ascontiguousarray(np.asarray(arr, dtype)).tobytes()).hexdigest()
            for name, arr, dtype in (("labels", result.labels, np.uint8),
                                     ("confidence", result.confidence, np.float32),
                                     ("origin", result.origin, np.uint8))}
