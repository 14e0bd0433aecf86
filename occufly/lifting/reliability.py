"""Per-annotator, per-class reliability of the votes (issue 37).

The robust decision (:mod:`occufly.lifting.robust`) pools every view into one annotator model
and sees only each point's two leading vote classes, so a frame whose painter swaps one class
for another *systematically* (every grass region of his frames painted vegetation) weighs as
much as the careful frames that see the same points. Here every frame is an annotator of its
own. After a first lifting, each frame's votes for each class are compared with the lifted
labels of the points it voted on: ``agree[f, c]`` = the share of frame ``f``'s votes for class
``c`` whose point was lifted as ``c``. A frame's votes for a class it paints with an agreement
below ``threshold`` (over at least ``min_votes`` of its votes for that class, and at most half
the other frames' agreement on that class -- a class all frames paint poorly, such as a thin
object, is not one frame's mistake) are *vetoed*: removed from the counts, and the lifting is
decided again from what the other frames say. No truth is used.

Judged against what? Against a first lifting (:func:`frame_class_agreement`), a systematic
painter who sees a third of the points wins the lifting of many of them, and then agrees with
it; against the other frames' votes on the same points (:func:`frame_class_agreement_loo`,
the default: votes only, before any lifting) he is outvoted by the careful frames.

Cost: one pass over the per-frame vote files (``ws/lifting/frames/*.npz``, about one int32 and
one uint8 per correspondence) and a copy of the (N, C) uint16 counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occufly.lifting.classes import ClassColumns


@dataclass
class ReliabilityParams:
    threshold: float = 0.4   # a frame's class agreement below this ...
    min_votes: int = 200     # ... over at least this many of its votes for the class ...
    relative: float = 0.5    # ... and below this share of the other frames' agreement on it
    min_frames: int = 3      # frames needed to tell one frame from the others


def frame_class_agreement(frames: dict[int, tuple[np.ndarray, np.ndarray]], labels: np.ndarray,
                          cls: ClassColumns) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """frames: frame -> (point ids, vote columns); labels: (N,) uint8 lifted labels ->
    (frame -> (C,) votes per class, frame -> (C,) votes per class that agree with the labels)."""
    C = cls.C
    lab_col = cls.col_of[np.asarray(labels)]
    votes, agree = {}, {}
    for f, (pids, cols) in frames.items():
        cols = np.asarray(cols, np.int64)
        votes[f] = np.bincount(cols, minlength=C)
        agree[f] = np.bincount(cols[lab_col[np.asarray(pids)] == cols], minlength=C)
    return votes, agree


def frame_class_agreement_loo(frames: dict[int, tuple[np.ndarray, np.ndarray]],
                              counts: np.ndarray, cls: ClassColumns, chunk: int = 1_000_000
                              ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """As :func:`frame_class_agreement`, judged against the other frames' votes instead of a
    lifting: a vote of frame ``f`` for class ``c`` agrees by the share of the other frames'
    votes on that point that are ``c``; points no other frame voted on do not count (counts:
    (N, C) the votes of every frame, ``f``'s included -- plain weighting, one per view)."""
    C = cls.C
    votes, agree = {}, {}
    for f, (pids, cols) in frames.items():
        v = np.zeros(C, np.int64)
        a = np.zeros(C, np.float64)
        for s in range(0, len(pids), chunk):
            ids = np.asarray(pids[s:s + chunk], np.int64)
            col = np.asarray(cols[s:s + chunk], np.int64)
            other = np.asarray(counts[ids], np.int32)
            other[np.arange(len(ids)), col] -= 1
            tot = other.sum(axis=1)
            has = tot > 0
            share = other[np.arange(len(ids)), col] / np.maximum(tot, 1)
            v += np.bincount(col[has], minlength=C)
            a += np.bincount(col[has], share[has], minlength=C)
        votes[f], agree[f] = v, a
    return votes, agree


def vetoes(votes: dict[int, np.ndarray], agree: dict[int, np.ndarray],
           params: ReliabilityParams | None = None) -> dict[int, np.ndarray]:
    """frame -> (C,) bool: the classes whose votes of that frame are vetoed (module docstring)."""
    p = params or ReliabilityParams()
    if len(votes) < p.min_frames:
        return {}
    tot = np.sum(list(votes.values()), axis=0).astype(np.float64)
    ok = np.sum(list(agree.values()), axis=0).astype(np.float64)
    out = {}
    for f, v in votes.items():
        rate = np.where(v > 0, agree[f] / np.maximum(v, 1), 1.0)
        # the other frames' agreement on the class (1 where none of them paints it)
        t_o, a_o = tot - v, ok - agree[f]
        others = np.where(t_o > 0, a_o / np.maximum(t_o, 1), 1.0)
        bad = (v >= p.min_votes) & (rate < p.threshold) & (rate < p.relative * others)
        if bad.any():
            out[f] = bad
    return out


def vetoed_counts(counts: np.ndarray, frames: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]],
                  veto: dict[int, np.ndarray]) -> np.ndarray:
    """(N, C) uint16 copy of ``counts`` without the vetoed votes (frames: frame -> (point ids,
    columns, weights) as stored)."""
    out = np.array(counts, copy=True)
    C = out.shape[1]
    flat = out.reshape(-1)
    for f, bad in veto.items():
        pids, cols, w = frames[f]
        sel = bad[np.asarray(cols, np.int64)]
        if not sel.any():
            continue
        key = np.asarray(pids, np.int64)[sel] * C + np.asarray(cols, np.int64)[sel]
        # a frame votes once per point: the keys are unique, plain fancy indexing is exact
        flat[key] -= np.asarray(w, np.uint16)[sel]
    return out
