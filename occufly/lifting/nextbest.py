"""Next best frames: which frames to paint next to settle the uncertain labels (issue 37).

After a first round of masks, every labelled point carries three kinds of evidence about how
settled its label is, none of which uses truth:

- its votes (``ws/lifting/votes.npy``): *contested* when the second class holds at least
  ``second_share`` of two or more votes, *overridden* when the fill / denoise chose another
  class than its vote majority (:func:`occufly.lifting.suspects.flag_points`, the reviewer's
  suspects);
- its calibrated confidence (``ws/lifting/confidence.npy``, the probability that the label is
  right, :mod:`occufly.lifting.calibration`): *uncertain* below ``max_confidence``;
- how many views already voted on it: a new view adds one vote to ``n``, so it settles a
  point seen by no annotated frame (a filled label) more than one voted five times.

The *need* of a point is ``max(contested or overridden: 1 - vote margin, uncertain:
1 - confidence) * 2 / (2 + votes)`` (0 for a settled point). A frame's gain is the sum of
the needs of the points it sees (through the scene's visibility, in blocks of frames); the
proposal is greedy: the frame of largest gain that has no mask yet, after which the needs of
the points it sees are multiplied by ``resolved`` (the new view settles them partly), and so
on ``k`` times. Gains only shrink, so a lazy max-heap re-evaluates only the top candidate.
No frame is proposed twice and no annotated frame is proposed. Each proposal says why: the
contested / uncertain points it sees, their current classes, the reviewer's suspects
(:func:`occufly.lifting.suspects.find_suspects`) it sees; and each suspect lists the proposed
frames that see it (a suspect no annotated frame settles points to the frames that would).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from occufly.errors import WorkspaceError
from occufly.lifting.classes import ClassColumns
from occufly.lifting.corrections import load_labels
from occufly.lifting.suspects import SuspectParams, find_suspects, flag_points
from occufly.lifting.votes import VoteStore
from occufly.progress import ProgressFn, noop
from occufly.scene import Scene
from occufly.workspace import Workspace


@dataclass
class NextParams:
    max_confidence: float = 0.7   # calibrated confidence below this: uncertain
    min_need: float = 0.05        # points with less need count as settled
    resolved: float = 0.3         # need left on a point after one more proposed view
    second_share: float = 0.25    # contested votes (the suspects' rule)
    min_votes: int = 2
    block: int = 1 << 24          # correspondences per block of the per-frame sums


@dataclass
class NextFrames:
    """frames: proposed frame indices, best first; reasons: one dict per frame (gain, the
    contested / uncertain points it sees, their classes, the suspects it sees);
    contested / uncertain: points flagged in the scene; needy: points with any need."""

    frames: list[int]
    reasons: list[dict]
    contested: int
    uncertain: int
    needy: int
    annotated: int
    candidates: int
    message: str = ""
    frame_names: list[str] = field(default_factory=list)
    suspects: list[dict] = field(default_factory=list)  # id, kind, points, proposed_frames

    def to_dict(self) -> dict:
        return {"mode": "next", "frames": list(self.frames), "frame_names": list(self.frame_names),
                "proposed": len(self.frames), "reasons": self.reasons,
                "contested_points": self.contested, "uncertain_points": self.uncertain,
                "needy_points": self.needy, "annotated_frames": self.annotated,
                "candidates": self.candidates, "message": self.message,
                "suspects": self.suspects}


def point_need(votes: np.ndarray, labels: np.ndarray, confidence: np.ndarray | None,
               cls: ClassColumns, params: NextParams | None = None, chunk: int = 1_000_000
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(need (N,) float32 in [0, 1], contested-or-overridden (N,) bool, uncertain (N,) bool)
    of every point (module docstring); votes: (N, C) counts, labels: (N,) uint8 final labels,
    confidence: (N,) calibrated confidence (None: votes only)."""
    p = params or NextParams()
    sp = SuspectParams(second_share=p.second_share, min_votes=p.min_votes)
    n = len(labels)
    need = np.zeros(n, np.float32)
    flagged = np.zeros(n, bool)
    uncertain = np.zeros(n, bool)
    for a in range(0, n, chunk):
        b = min(n, a + chunk)
        c = np.asarray(votes[a:b])
        lab = np.asarray(labels[a:b])
        con, over = flag_points(c, lab, cls, sp)
        col, top, second = cls.majority(c)
        total = c.sum(axis=1, dtype=np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            margin = np.where(total > 0, (top - second) / np.maximum(total, 1), 1.0)
        f = (con | over) & (lab > 0)
        v = np.where(over, 1.0, np.where(con, 1.0 - margin, 0.0))
        u = np.zeros(b - a, bool)
        if confidence is not None:
            conf = np.asarray(confidence[a:b], np.float32)
            u = (lab > 0) & (conf < p.max_confidence)
            v = np.maximum(v, np.where(u, 1.0 - conf, 0.0))
        v = v * 2.0 / (2.0 + total)
        v[lab == 0] = 0.0
        v[v < p.min_need] = 0.0
        need[a:b] = v
        flagged[a:b] = f
        uncertain[a:b] = u
    return need, flagged, uncertain


def _sum_per_frame(vis, values: np.ndarray, frames: np.ndarray, block: int) -> np.ndarray:  # noqa: ANN001
    """(len(frames),) float64 sum of ``values`` over the points each frame sees (frames
    sorted; whole frames in blocks of about ``block`` correspondences)."""
    off = np.asarray(vis.offsets, np.int64)
    out = np.zeros(len(frames), np.float64)
    i = 0
    while i < len(frames):
        j = i + 1
        while j < len(frames) and off[frames[j] + 1] - off[frames[i]] <= block:
            j += 1
        a, b = int(off[frames[i]]), int(off[frames[j - 1] + 1])
        cs = np.zeros(b - a + 1, np.float64)
        np.cumsum(values[np.asarray(vis.point_ids[a:b])], out=cs[1:])
        fr = frames[i:j]
        out[i:j] = cs[off[fr + 1] - a] - cs[off[fr] - a]
        i = j
    return out


def propose_next(scene: Scene, votes: np.ndarray, labels: np.ndarray,
                 confidence: np.ndarray | None, k: int, *, annotated: list[int] | set[int],
                 params: NextParams | None = None, suspects: list[dict] | None = None
                 ) -> NextFrames:
    """Up to ``k`` frames (none of ``annotated``) whose masks would most settle the contested
    and uncertain labels (module docstring). An empty proposal (nothing needs a view, or no
    frame sees what does) has its reason in ``message``."""
    p = params or NextParams()
    if k < 1:
        raise ValueError(f"k: expected at least 1 frame, got {k}")
    cls = ClassColumns(scene.taxonomy)
    need, flagged, uncertain = point_need(votes, labels, confidence, cls, p)
    needy = int(np.count_nonzero(need))
    done = {int(f) for f in annotated}
    cand = np.array([f for f in range(len(scene.frames)) if f not in done], np.int64)
    base = dict(contested=int(flagged.sum()), uncertain=int(uncertain.sum()), needy=needy,
                annotated=len(done), candidates=int(len(cand)))
    if needy == 0:
        return NextFrames([], [], message="nothing is contested or uncertain: no frame to propose",
                          **base)
    if not len(cand):
        return NextFrames([], [], message="every frame already has a mask", **base)
    vis = scene.visibility
    gains = _sum_per_frame(vis, need, cand, p.block)
    heap = [(-float(g), int(f)) for g, f in zip(gains, cand, strict=True) if g > 0]
    heapq.heapify(heap)
    names = {c.id: c.name for c in scene.taxonomy.classes}
    sus = [(int(s.get("id", i + 1)), np.asarray(s["point_ids"], np.int64))
           for i, s in enumerate(suspects or [])]
    seen_by: dict[int, list[int]] = {}
    frames: list[int] = []
    reasons: list[dict] = []
    while heap and len(frames) < k:
        neg, f = heapq.heappop(heap)
        pids = np.asarray(vis.point_ids[int(vis.offsets[f]):int(vis.offsets[f + 1])], np.int64)
        g = float(need[pids].sum(dtype=np.float64))
        if g <= 0:
            continue
        if heap and g < -heap[0][0] * (1 - 1e-9):
            heapq.heappush(heap, (-g, f))  # stale: re-insert with its true gain
            continue
        mine = pids[need[pids] > 0]
        lab = np.asarray(labels)[mine]
        ids, cnt = np.unique(lab, return_counts=True)
        order = np.argsort(-cnt, kind="stable")[:5]
        seen_sus = [i for i, sp in sus if len(sp) and np.isin(sp, pids, assume_unique=True).any()]
        for i in seen_sus:
            seen_by.setdefault(i, []).append(f)
        reasons.append({
            "frame": f, "frame_name": scene.frames[f].name, "gain": round(g, 2),
            "contested_points": int(flagged[mine].sum()),
            "uncertain_points": int(uncertain[mine].sum()),
            "needy_points": int(len(mine)),
            "classes": {names.get(int(ids[o]), str(int(ids[o]))): int(cnt[o]) for o in order},
            "suspects": seen_sus,
        })
        frames.append(f)
        need[pids] *= np.float32(p.resolved)
    msg = "" if frames else "no frame without a mask sees the contested or uncertain points"
    # the reviewer's suspects, each with the proposed frames that would settle it
    sus_rows = [{"id": int(s.get("id", i + 1)), "kind": s.get("kind"),
                 "points": int(s.get("points", len(s["point_ids"]))),
                 "proposed_frames": seen_by.get(int(s.get("id", i + 1)), [])}
                for i, s in enumerate(suspects or [])]
    return NextFrames(frames, reasons, message=msg, suspects=sus_rows,
                      frame_names=[scene.frames[f].name for f in frames], **base)


def propose_for_workspace(ws, k: int, *, scene: Scene | None = None,  # noqa: ANN001
                          params: NextParams | None = None, progress: ProgressFn | None = None
                          ) -> NextFrames:
    """:func:`propose_next` on workspace ``ws``: its votes, its lifted labels and their
    calibrated confidence, the frames whose masks are counted as annotated. Raises
    :class:`WorkspaceError` (naming what is missing) without votes or lifted labels."""
    report = progress or noop
    if not Workspace(ws).lifting_state.is_file():
        raise WorkspaceError(f"{ws}: no votes yet: lift a first round of masks before asking "
                             "for the next frames")
    lifted = load_labels(ws)
    if lifted is None:
        raise WorkspaceError(f"{ws}: votes but no lifted labels: let the fill run (occufly lift "
                             "without --no-fill) first")
    report(0.1, "reading votes")
    scene = scene if scene is not None else Scene.load(ws)
    st = VoteStore.open(ws, scene, read_only=True)
    try:
        report(0.3, "weighing the frames")
        report(0.2, "finding the suspects")
        suspects = find_suspects(scene, st.votes, lifted.labels)
        res = propose_next(scene, st.votes, lifted.labels, lifted.confidence, k,
                           annotated=set(st.included_versions()), params=params,
                           suspects=suspects)
    finally:
        st.close()
    report(1.0, f"{len(res.frames)} frames proposed")
    return res
