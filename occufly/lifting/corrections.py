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
import zlib
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
                    labels: np.ndarray, *, edit_ids: np.ndarray | None = None,
                    applied: np.ndarray | list[int] | None = None) -> None:
    """Store the net override layer atomically (``point_ids`` need not be sorted: the last
    label given for a point wins). An empty layer removes the file -- unless ``applied`` is
    given, then an empty layer is kept so that it records which edits it reflects.

    ``edit_ids`` (optional, (K,) int64 aligned with ``point_ids``): the edit that set each
    point; ``applied`` (optional): the ids of the active edits the layer reflects (what the
    app compares with its edit table to repair a layer a crash left behind).
    """
    w = Workspace.of(ws)
    ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
    lab = np.asarray(labels, dtype=np.uint8).reshape(-1)
    if ids.shape != lab.shape:
        raise ValueError(f"write_overrides: {len(ids)} point ids but {len(lab)} labels")
    if edit_ids is not None:
        edit_ids = np.asarray(edit_ids, dtype=np.int64).reshape(-1)
        if edit_ids.shape != ids.shape:
            raise ValueError(f"write_overrides: {len(ids)} point ids but {len(edit_ids)} edit ids")
    if len(ids) == 0 and applied is None:
        w.overrides_path.unlink(missing_ok=True)
        return
    if len(ids) and np.all(ids[1:] > ids[:-1]):  # already sorted unique (the app's layers)
        uniq, lab_u = ids, lab
        eid_u = edit_ids
    else:  # last occurrence wins: unique over the reversed arrays
        uniq, first = np.unique(ids[::-1], return_index=True)
        lab_u = lab[::-1][first]
        eid_u = edit_ids[::-1][first] if edit_ids is not None else None
    # compact on disk: ids below 2**32 as uint32 (read back as int64 by read_overrides)
    small = len(uniq) == 0 or int(uniq[-1]) <= np.iinfo(np.uint32).max
    arrays = {"point_ids": uniq.astype(np.uint32) if small else uniq, "labels": lab_u}
    if eid_u is not None:
        arrays["edit_ids"] = eid_u.astype(np.int32)
    if applied is not None:
        arrays["applied"] = np.unique(np.asarray(applied, dtype=np.int64).reshape(-1))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
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


# ---- the edit history's building blocks (used by the app's corrections service) ----------
# An edit is (edit id, point ids, class). The net layer is the edits applied in id order
# (the highest id wins on a point); it also records, per point, which edit set it and the
# set of edits it reflects, so activating or deactivating one edit rewrites only that edit's
# points: O(edited points), never O(scene).


@dataclass(frozen=True)
class NetLayer:
    """The net override layer with its bookkeeping.

    point_ids: (K,) int64 sorted unique; labels: (K,) uint8; edit_ids: (K,) int64 the edit that
    set each point (-1 where a layer was written without them); applied: (E,) int64 sorted ids
    of the edits the layer reflects (None when the file does not record them).
    """

    point_ids: np.ndarray
    labels: np.ndarray
    edit_ids: np.ndarray
    applied: np.ndarray | None

    @classmethod
    def empty(cls) -> NetLayer:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int64),
                   np.zeros(0, np.int64))

    def __len__(self) -> int:
        return int(len(self.point_ids))


def read_net(ws: str | Path | Workspace, n_points: int | None = None) -> NetLayer:
    """The workspace's net layer with its bookkeeping (empty when there is none)."""
    ov = read_overrides(ws, n_points)
    if ov is None:
        return NetLayer(np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int64), None)
    p = Workspace.of(ws).overrides_path
    with np.load(p, allow_pickle=False) as z:
        eids = (np.asarray(z["edit_ids"], np.int64) if "edit_ids" in z.files
                else np.full(len(ov), -1, np.int64))
        applied = np.asarray(z["applied"], np.int64) if "applied" in z.files else None
    if eids.shape != ov.point_ids.shape:
        raise WorkspaceError(f"{p}: edit_ids {eids.shape} and point_ids {ov.point_ids.shape} differ")
    return NetLayer(ov.point_ids, ov.labels, eids, applied)


def read_applied(ws: str | Path | Workspace) -> np.ndarray | None:
    """Only the ids of the edits the net layer reflects (None: no layer, or a layer that does
    not record them) -- the cheap consistency check, without reading the point arrays."""
    p = Workspace.of(ws).overrides_path
    if not p.is_file():
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            return np.asarray(z["applied"], np.int64) if "applied" in z.files else None
    except (OSError, KeyError, ValueError) as e:
        raise WorkspaceError(f"{p}: unreadable label corrections ({e})") from None


def write_net(ws: str | Path | Workspace, net: NetLayer) -> None:
    """Store ``net`` atomically (kept even when empty, so it records ``applied``)."""
    write_overrides(ws, net.point_ids, net.labels, edit_ids=net.edit_ids,
                    applied=net.applied if net.applied is not None else np.zeros(0, np.int64))


def normalise_point_ids(point_ids: np.ndarray | list[int], n_points: int) -> np.ndarray:
    """(K,) int64 sorted unique ids; ValueError naming the range for ids outside 0..n-1."""
    ids = np.sort(np.asarray(point_ids, dtype=np.int64).reshape(-1))  # (np.unique hashes:
    if len(ids) > 1:                                                  #  ~8x slower on 1 M)
        ids = ids[np.r_[True, ids[1:] != ids[:-1]]]
    if len(ids) and (ids[0] < 0 or ids[-1] >= n_points):
        raise ValueError(f"point ids must be in 0..{n_points - 1}, got {int(ids[0])}..{int(ids[-1])}")
    return ids


def write_edit_points(ws: str | Path | Workspace, edit_id: int, point_ids: np.ndarray,
                      to_class: int) -> Path:
    """Store one edit's point ids (sorted unique, as uint32 deltas, zlib) atomically;
    returns the path (:meth:`Workspace.correction_edit`)."""
    w = Workspace.of(ws)
    ids = np.asarray(point_ids, dtype=np.int64).reshape(-1)
    if len(ids) and (ids[0] < 0 or ids[-1] > np.iinfo(np.uint32).max or np.any(np.diff(ids) <= 0)):
        raise ValueError("write_edit_points: point ids must be sorted unique uint32 values")
    deltas = np.diff(ids, prepend=0).astype(np.uint32)
    buf = io.BytesIO()
    np.savez(buf, deltas_zlib=np.frombuffer(zlib.compress(deltas.tobytes(), 1), np.uint8),
             n=np.int64(len(ids)), to_class=np.int64(to_class))
    w.corrections_dir.mkdir(parents=True, exist_ok=True)
    p = w.correction_edit(edit_id)
    atomic_write_bytes(p, buf.getvalue())
    return p


def read_edit_points(ws: str | Path | Workspace, edit_id: int) -> np.ndarray:
    """(K,) int64 sorted point ids of edit ``edit_id``; WorkspaceError when missing/corrupt."""
    p = Workspace.of(ws).correction_edit(edit_id)
    try:
        with np.load(p, allow_pickle=False) as z:
            raw = zlib.decompress(np.asarray(z["deltas_zlib"], np.uint8).tobytes())
            n = int(z["n"])
    except (OSError, KeyError, ValueError, zlib.error) as e:
        raise WorkspaceError(f"{p}: unreadable correction edit ({e})") from None
    deltas = np.frombuffer(raw, np.uint32)
    if len(deltas) != n:
        raise WorkspaceError(f"{p}: {len(deltas)} point ids stored, header says {n}")
    return np.cumsum(deltas, dtype=np.int64)


def _locate(net: NetLayer, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(positions (M,) int64 of ``ids`` in the layer's sorted point ids, found (M,) bool)."""
    pos = np.searchsorted(net.point_ids, ids)
    found = np.zeros(len(ids), bool)
    inb = pos < len(net.point_ids)
    found[inb] = net.point_ids[pos[inb]] == ids[inb]
    return pos, found


def activate_edit(net: NetLayer, edit_id: int, point_ids: np.ndarray, to_class: int) -> NetLayer:
    """``net`` with edit ``edit_id`` applied: its points take ``to_class`` unless a later
    (higher id) active edit set them. ``point_ids``: (M,) int64 sorted unique. O(M log K + K)."""
    ids = np.asarray(point_ids, np.int64)
    pos, found = _locate(net, ids)
    labels = net.labels.copy()
    eids = net.edit_ids.copy()
    hit = pos[found]
    win = eids[hit] <= edit_id
    labels[hit[win]] = to_class
    eids[hit[win]] = edit_id
    new = ~found
    ins = pos[new]
    out_ids = np.insert(net.point_ids, ins, ids[new])
    out_lab = np.insert(labels, ins, np.uint8(to_class))
    out_eid = np.insert(eids, ins, np.int64(edit_id))
    applied = np.union1d(net.applied if net.applied is not None else np.zeros(0, np.int64),
                         [edit_id]).astype(np.int64)
    return NetLayer(out_ids, out_lab, out_eid, applied)


def deactivate_edit(net: NetLayer, edit_id: int, point_ids: np.ndarray,
                    earlier) -> NetLayer:  # noqa: ANN001 - iterable of (id, class, loader)
    """``net`` without edit ``edit_id``. Its points that it still decides fall back to the
    next-newest active edit covering them (``earlier``: (edit id, class, load_point_ids())
    of the other active edits with lower ids, newest first; loaded only while points remain
    unresolved) or leave the layer. ``point_ids``: (M,) int64 sorted unique."""
    ids = np.asarray(point_ids, np.int64)
    pos, found = _locate(net, ids)
    mine = pos[found][net.edit_ids[pos[found]] == edit_id]  # positions this edit decides
    labels = net.labels.copy()
    eids = net.edit_ids.copy()
    todo = mine  # positions still unresolved (sorted)
    for eid, cls, load in earlier:
        if len(todo) == 0:
            break
        if eid >= edit_id:
            continue
        other = np.asarray(load(), np.int64)
        q = np.searchsorted(other, net.point_ids[todo])
        ok = q < len(other)
        ok[ok] = other[q[ok]] == net.point_ids[todo[ok]]
        labels[todo[ok]] = cls
        eids[todo[ok]] = eid
        todo = todo[~ok]
    keep = np.ones(len(net.point_ids), bool)
    keep[todo] = False
    applied = net.applied if net.applied is not None else np.zeros(0, np.int64)
    applied = applied[applied != edit_id]
    return NetLayer(net.point_ids[keep], labels[keep], eids[keep], applied)


def rebuild_net(edits) -> NetLayer:  # noqa: ANN001 - iterable of (id, class, point ids)
    """The net layer of ``edits`` (any order; the highest edit id wins on a point).
    O(total edited points)."""
    edits = sorted(((int(e), int(c), np.asarray(p, np.int64)) for e, c, p in edits),
                   key=lambda t: t[0])
    if not edits:
        return NetLayer.empty()
    ids = np.concatenate([p for _e, _c, p in edits])
    lab = np.concatenate([np.full(len(p), c, np.uint8) for _e, c, p in edits])
    eid = np.concatenate([np.full(len(p), e, np.int64) for e, _c, p in edits])
    uniq, first = np.unique(ids[::-1], return_index=True)
    return NetLayer(uniq, lab[::-1][first], eid[::-1][first],
                    np.asarray([e for e, _c, _p in edits], np.int64))


def labels_at(ws: str | Path | Workspace, point_ids: np.ndarray,
              net: NetLayer | Overrides | None = None) -> np.ndarray | None:
    """(M,) uint8 current labels (fill output with corrections) of ``point_ids`` only --
    O(M log K), the other points are never read; None before the first fill."""
    w = Workspace.of(ws)
    base = w.labels()
    if base is None:
        return None
    ids = np.asarray(point_ids, np.int64)
    out = np.asarray(base[ids], np.uint8).copy()
    if net is None:
        net = read_overrides(w, len(base))
    if net is None or len(net) == 0:
        return out
    pos = np.searchsorted(net.point_ids, ids)
    ok = pos < len(net.point_ids)
    ok[ok] = net.point_ids[pos[ok]] == ids[ok]
    out[ok] = net.labels[pos[ok]]
    return out


def load_labels(ws: str | Path, *, corrections: bool = True) -> LiftResult | None:
    """The labels every consumer reads: the latest fill/denoise output of workspace ``ws``
    (memory-mapped) with reviewers' corrections applied on top
    (:func:`occufly.lifting.corrections.apply_overrides`; ``corrections=False`` gives the
    fill output alone), or None before the first fill."""
    w = Workspace(ws)
    labels = w.labels()
    if labels is None:
        return None
    res = LiftResult(labels=labels, confidence=w.confidence(), origin=w.label_origin(),
                     stats=w.lift_stats())
    return apply_overrides(res, w) if corrections else res
