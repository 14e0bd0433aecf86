"""Reviewers' label corrections: the override layer above votes, fill and denoise.

Every reader of lifted labels goes through :func:`occufly.lifting.load_labels`, which applies
this layer with :func:`apply_overrides`: a corrected point takes the reviewer's class (0 =
"unlabelled"), confidence 1 and origin :data:`ORIGIN_CORRECTED`. The layer is stored as the
*net* effect of all active edits in ``Workspace.overrides_path`` (point ids sorted, one label
each), so applying it costs O(corrected points), never O(scene).

The edit history (who, when, from -> to, undo/redo, revert) is kept by the app; whoever
changes it rewrites the net layer with :func:`write_overrides` (atomic).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occufly.errors import WorkspaceError
from occufly.fsutil import atomic_write_bytes
from occufly.lifting.result import ORIGIN_CORRECTED, LiftResult
from occufly.workspace import Workspace


@dataclass(frozen=True)
class Overrides:
    """point_ids: (K,) int64 sorted unique point indices; labels: (K,) uint8 raw class ids
    (0 = the reviewer set the point to unlabelled)."""

    point_ids: np.ndarray
    labels: np.ndarray

    def __len__(self) -> int:
        return int(len(self.point_ids))


def read_overrides(ws: str | Path | Workspace, n_points: int | None = None) -> Overrides | None:
    """The net override layer of workspace ``ws``, or None when no correction exists.

    Raises WorkspaceError when the file is unreadable or names points outside ``n_points``.
    """
    p = Workspace.of(ws).overrides_path
    if not p.is_file():
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            ids = np.asarray(z["point_ids"], dtype=np.int64)
            labels = np.asarray(z["labels"], dtype=np.uint8)
    except (OSError, KeyError, ValueError) as e:
        raise WorkspaceError(f"{p}: unreadable label corrections ({e})") from None
    if ids.shape != labels.shape or ids.ndim != 1:
        raise WorkspaceError(f"{p}: point_ids {ids.shape} and labels {labels.shape} differ")
    if len(ids) and (ids[0] < 0 or (n_points is not None and ids[-1] >= n_points)):
        raise WorkspaceError(f"{p}: corrections name points outside 0..{(n_points or 0) - 1}; "
                             "the scene's points changed since they were made")
    return Overrides(ids, labels)


def write_overrides(ws: str | Path | Workspace, point_ids: np.ndarray,
                    labels: np.ndarray) -> None:
    """Store the net override layer atomically (``point_ids`` need not be sorted: the last
    label given for a point wins). An empty layer removes the file."""
    w = Workspace.of(ws)
    ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
    lab = np.asarray(labels, dtype=np.uint8).reshape(-1)
    if ids.shape != lab.shape:
        raise ValueError(f"write_overrides: {len(ids)} point ids but {len(lab)} labels")
    if len(ids) == 0:
        w.overrides_path.unlink(missing_ok=True)
        return
    # last occurrence wins: unique over the reversed arrays
    rev_ids = ids[::-1]
    uniq, first = np.unique(rev_ids, return_index=True)
    buf = io.BytesIO()
    np.savez(buf, point_ids=uniq, labels=lab[::-1][first])
    w.corrections_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(w.overrides_path, buf.getvalue())


def apply_overrides(result: LiftResult, ws: str | Path | Workspace) -> LiftResult:
    """``result`` with the workspace's corrections applied (a new result; the arrays of
    ``result`` are copied only when there is something to apply)."""
    ov = read_overrides(ws, len(result.labels))
    if ov is None or len(ov) == 0:
        return result
    labels = np.array(result.labels, dtype=np.uint8)
    conf = np.array(result.confidence, dtype=np.float32)
    origin = np.array(result.origin, dtype=np.uint8)
    labels[ov.point_ids] = ov.labels
    conf[ov.point_ids] = np.where(ov.labels > 0, 1.0, 0.0)
    origin[ov.point_ids] = ORIGIN_CORRECTED
    stats = dict(result.stats)
    stats["corrected_points"] = len(ov)
    return LiftResult(labels=labels, confidence=conf, origin=origin, stats=stats)


def apply_to_labels(labels: np.ndarray, ws: str | Path | Workspace) -> np.ndarray:
    """(N,) uint8 ``labels`` (e.g. direct votes, or leave-one-out labels) with the
    corrections applied; returned as is when there are none."""
    ov = read_overrides(ws, len(labels))
    if ov is None or len(ov) == 0:
        return labels
    out = np.array(labels, dtype=np.uint8)
    out[ov.point_ids] = ov.labels
    return out
