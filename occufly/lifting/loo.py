"""Leave-one-out (independent) labels and agreement of one frame.

For frame ``f`` the labels decided *without f's votes*: the other frames' vote counts at the
points f needs (its visible points and the voted points whose fill can reach them) are the
counts minus f's own per-frame votes (``ws/lifting/frames/<f>.npz``), their majority follows
the pipeline's tie rule (:meth:`ClassColumns.packed_winner`); a point left without a vote
takes the pipeline fill's inverse-distance-weighted k-NN vote of the other frames' voted
points within ``LiftParams.fill_radius`` (``occufly.lifting.knn.knn_vote``, the same
function the fill calls; nothing is extrapolated beyond the radius). Reviewers' corrections
are applied on top. The labels are rendered into f exactly as the self-agreement is
(:func:`occufly.render.render_for_mask`) and compared with f's mask.

Cost: proportional to the points in f's frustum (the render cull), never a pass over the scene.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numba
import numpy as np
from scipy.spatial import cKDTree

from occufly.confusion import Confusion, count_pairs_many
from occufly.lifting.blockknn import points_in_box
from occufly.lifting.classes import ClassColumns
from occufly.lifting.corrections import read_overrides
from occufly.lifting.knn import LiftParams, VoxelGrid, _scores_to_cols, knn_vote
from occufly.lifting.votes import vote_unit
from occufly.render import (
    COARSE_MIN_PIXELS,
    MAX_COARSE,
    MAX_SPLAT,
    agreement_from_counts,
    disagreement_image,
    frame_geometry,
    frustum_candidates,
    render_many_for_mask,
)
from occufly.scene import Scene, project_points
from occufly.workspace import Workspace


@dataclass
class LooLabels:
    """Leave-one-out labels around one frame.

    point_ids: (K,) int64 sorted scene point ids (f's visible points and its frustum cull);
    labels: (K,) uint8 raw ids decided without f (0 = no independent evidence);
    voted: (K,) bool, the label comes from other frames' votes (else filled or none);
    share: (K,) float32 the label's share of the other frames' votes (of the weighted k-NN
    vote where filled; 1 where a reviewer's correction decided; 0 without a label) -- how
    unanimous the independent evidence is.
    """

    frame_index: int
    point_ids: np.ndarray
    labels: np.ndarray
    voted: np.ndarray
    share: np.ndarray | None = None


def _frame_votes(ws: Path, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame ``f``'s votes: (point ids, columns, weights) as int64."""
    got = Workspace(ws).read_frame_votes(f)  # stored members read straight: no CRC pass
    if got is None:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    pids, cols, w = got
    return (pids.astype(np.int64, copy=False), cols.astype(np.int64, copy=False),
            w.astype(np.int64, copy=False) if w is not None else np.ones(len(pids), np.int64))


@numba.njit(nogil=True, cache=True)
def _winner_minus_own(votes: np.ndarray, ids: np.ndarray, pos: np.ndarray, own_c: np.ndarray,
                      own_w: np.ndarray, tie_key: np.ndarray, out: np.ndarray,
                      share: np.ndarray, top: np.ndarray, out2: np.ndarray,
                      second: np.ndarray) -> None:
    """out[k] = the tie-order winner column of votes[ids[k]] minus the frame's own votes
    (entries ``pos`` sorted, -1 = not in ids), -1 where no vote is left; share[k] = the
    winner's share of the votes left (0 where none); top[k] its votes; out2[k] / second[k] the
    runner-up column (the tie-order winner of the rest, -1 = none) and its votes -- the two
    leading classes the robust decision reads (:class:`~occufly.lifting.votes.VoteSnapshot`)."""
    n_cls = votes.shape[1]
    sub = np.zeros(n_cls, np.int64)
    j = 0
    n_own = pos.shape[0]
    while j < n_own and pos[j] < 0:
        j += 1
    for k in range(ids.shape[0]):
        touched = False
        while j < n_own and pos[j] == k:
            sub[own_c[j]] += own_w[j]
            touched = True
            j += 1
        row = ids[k]
        best = -1
        best_key = -1
        nxt = -1
        nxt_key = -1
        total = 0
        for c in range(n_cls):
            v = np.int64(votes[row, c]) - sub[c]
            if v > 0:
                total += v
                key = v * n_cls + tie_key[c]
                if key > best_key:
                    nxt, nxt_key = best, best_key
                    best_key = key
                    best = c
                elif key > nxt_key:
                    nxt_key = key
                    nxt = c
        out[k] = best
        top[k] = best_key // n_cls if best >= 0 else 0
        share[k] = (best_key // n_cls) / total if total > 0 else 0.0
        out2[k] = nxt
        second[k] = nxt_key // n_cls if nxt >= 0 else 0
        if touched:
            for c in range(n_cls):
                sub[c] = 0


def loo_winner(votes: np.ndarray, ids: np.ndarray, own_p: np.ndarray, own_c: np.ndarray,
               own_w: np.ndarray, cls: ClassColumns, share: np.ndarray | None = None, *,
               rows: np.ndarray | None = None, own_rows: np.ndarray | None = None,
               second: bool = False
               ) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(K,) int64 winner column (:meth:`ClassColumns.winner`'s tie order; -1 = no vote) of the
    vote counts ``votes[ids]`` ((N, C) uint16, a memmap is read in place) minus a frame's
    own votes (``own_p`` point ids, ``own_c`` columns, ``own_w`` weights; a count never goes
    below 0). One compiled pass over the rows: no (K, C) copy, no packed key array.
    ``share``: an optional (K,) float32 output, the winner's share of the votes left;
    ``rows``: an optional (N,) map of scene point id -> row in ``ids`` (-1 = none), used
    instead of a binary search of ``own_p``; ``own_rows``: the rows of ``own_p`` in ``ids``
    already found (-1 = none). ``second``: return (winner, its votes, the
    runner-up column (-1 = none), its votes), the vote pattern of :func:`robust.redecide`."""
    ids = np.ascontiguousarray(ids, dtype=np.int64)
    n = len(ids)
    out = np.empty(n, np.int64)
    share = np.empty(n, np.float32) if share is None else share
    top, out2, n2 = np.zeros(n, np.int64), np.full(n, -1, np.int64), np.zeros(n, np.int64)
    if not n:
        return (out, top, out2, n2) if second else out
    if own_rows is not None:
        pos = np.asarray(own_rows, np.int64)
    elif rows is not None:
        pos = rows[own_p].astype(np.int64)
    else:
        pos = np.searchsorted(ids, own_p).astype(np.int64)
        pos = np.minimum(pos, n - 1)
        pos[ids[pos] != own_p] = -1
    order = np.argsort(pos, kind="stable") if len(pos) > 1 and (np.diff(pos) < 0).any() else None
    if order is not None:
        pos, own_c, own_w = pos[order], own_c[order], own_w[order]
    tie = np.asarray(cls._tie_key, np.int64)  # C - 1 - rank: larger = preferred on a tie
    _winner_minus_own(votes, ids, pos, np.ascontiguousarray(own_c, np.int64),
                      np.ascontiguousarray(own_w, np.int64), tie, out, share, top, out2, n2)
    return (out, top, out2, n2) if second else out


@numba.njit(nogil=True, cache=True)
def _rows_in(ids: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    n = ids.shape[0]
    m = q.shape[0]
    srt = True
    for i in range(1, m):
        if q[i] < q[i - 1]:
            srt = False
            break
    if srt:  # one merge walk
        j = 0
        for i in range(m):
            v = q[i]
            while j < n and ids[j] < v:
                j += 1
            out[i] = j if j < n and ids[j] == v else -1
        return
    for i in range(m):  # a binary search each
        v = q[i]
        lo, hi = 0, n
        while lo < hi:
            mid = (lo + hi) // 2
            if ids[mid] < v:
                lo = mid + 1
            else:
                hi = mid
        out[i] = lo if lo < n and ids[lo] == v else -1


def rows_in(ids: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(len(q),) int64 position of each of ``q`` in ``ids`` (sorted ascending, distinct),
    -1 where absent: one merge walk when ``q`` is sorted (a frame's visible points, its votes
    and the overrides are), else a binary search each -- what an (N,) map from point id to row
    gave without writing 4 bytes per scene point (128 MB on a 32 M-point scene) per call."""
    out = np.empty(len(q), np.int64)
    if len(q):
        _rows_in(np.ascontiguousarray(ids, np.int64), np.ascontiguousarray(q, np.int64), out)
    return out


def _vote_unit(ws: Path) -> int:
    """Counts per view of the workspace's votes (:data:`~occufly.lifting.votes.VOTE_UNITS`, as
    :meth:`VoteStore.snapshot` hands them to the robust decision)."""
    try:
        st = json.loads(Workspace(ws).lifting_state.read_text())
    except (OSError, ValueError):
        return 1
    return vote_unit(str(st.get("vote_weighting", "plain")))


def _painter_model(ws: Path, scene: Scene, frame_index: int, pts: np.ndarray, rec: tuple,
                   pooled: np.ndarray | None, unit: int):  # noqa: ANN202
    """The fill's per-painter confusion model (its ``confusion_model`` record, ``rec``) over
    the other frames' votes at the points ``pts`` (sorted ids; the table's rows are their
    positions), for :func:`_robust_decision`: each frame under its painter's matrix, as the
    fill decided. A frame the fill did not count (saved since) gets the pooled matrix."""
    from occufly.lifting.confusion import ConfusionModel, ConfusionParams, vote_table

    logpi, prior, painter_of = rec
    reach = frames_reaching(scene, frame_index, pts)
    w = Workspace(ws)
    if reach is None:  # every frame may vote there
        reach = [int(q.stem) for q in w.lifting_frames_dir.glob("*.npz") if q.stem.isdigit()]
    frames: dict[int, tuple] = {}
    for g in reach:
        if int(g) == frame_index:
            continue
        got = w.read_frame_votes(int(g))
        if got is None:
            continue
        pids, cols, wt = got
        r = rows_in(pts, np.asarray(pids, np.int64))
        keep = r >= 0
        if keep.any():
            frames[int(g)] = (r[keep].astype(np.int32), np.asarray(cols)[keep],
                              None if wt is None else np.asarray(wt)[keep])
    # annotator of each frame: its painter's index in the record, -1 - frame if it has none
    ann = {g: painter_of.get(g, -1 - g) for g in frames}
    table = vote_table(frames, len(pts), ann, unit)
    fallback = (np.log(np.maximum(pooled, 1e-12)).astype(np.float32) if pooled is not None
                else np.log(np.exp(logpi.astype(np.float64)).mean(axis=0)).astype(np.float32))
    local = np.stack([logpi[a] if a >= 0 else fallback for _k, a in table.names]) \
        if table.names else logpi[:0]
    if not len(local):
        local = fallback[None]
    return ConfusionModel(table, local, prior, ConfusionParams(), {})


def _robust_decision(ws: Path, scene: Scene, cls: ClassColumns, ids: np.ndarray,
                     col: np.ndarray, n1: np.ndarray, col2: np.ndarray, n2: np.ndarray,
                     share: np.ndarray, p: LiftParams, frame_index: int | None = None) -> None:
    """Re-decide the voted points of ``ids`` (votes already without the frame's own) with the
    pipeline's robust decision, :func:`occufly.lifting.robust.redecide` -- called, not copied:
    its annotator model and point classifier are fitted on the other frames' votes in the
    frame's cull, so a neighbour's wrong votes are overruled as the pipeline overrules them
    instead of deciding the labels where few frames overlap. ``col`` (winner columns) and
    ``share`` are updated in place: a re-decided point's share is its posterior
    ``(1 + margin) / 2`` (the top of two candidates; 1 where one class was possible).

    Where the last fill decided per painter (issue 37: its stats hold ``confusion_model``), the
    other frames' votes are weighed by their painters' matrices as the fill weighed them
    (:func:`_painter_model`; ``frame_index``, the frame left out), so the reviewer's figure
    and the shipped labels come from the same decision."""
    from occufly.lifting.confusion import model_from_record
    from occufly.lifting.robust import RobustParams, RowSubset, cached_features, redecide

    sel = np.flatnonzero(col >= 0)
    if len(sel) == 0:
        return
    rp = getattr(p, "robust_params", None) or RobustParams()
    # the annotator matrix the last fill decided with (refitted, RobustParams.refit_rounds):
    # the shipped labels' model at no cost per open. Without one (a fill before it was
    # stored, another taxonomy) the EM on the frame's cull, without the refit rounds: each is
    # another decision pass, and a 20 MP survey frame's first open went from 0.85 to 1.22 s
    # (frame 157) with them (docs/lifting.md, issue 37's fifth round)
    matrix = stored_matrix(ws, cls)
    rp = replace(rp, refit_rounds=0)
    # the features the pipeline's fill computed and cached (fill_snapshot: default parameters)
    feats = cached_features(ws, scene.xyz, scene.rgb, read_only=True)
    pts = ids[sel]
    unit = _vote_unit(ws)
    c1 = col[sel].astype(np.int16)
    top = n1[sel]
    sec = n2[sel]
    if unit != 1:  # weighted votes: the model counts views (VoteStore.snapshot, fill_snapshot)
        top = (top + unit - 1) // unit
        sec = sec.astype(np.float32) / unit
    else:
        sec = sec.astype(np.uint16)
    rec = (model_from_record(Workspace(ws).lift_stats().get("confusion_model"), cls.ids)
           if frame_index is not None else None)
    model = (_painter_model(ws, scene, frame_index, pts, rec, matrix, unit)
             if rec is not None else None)
    labels, margin, _top, _stats = redecide(
        cls, RowSubset(feats, pts), c1, top.astype(np.uint16), col2[sel].astype(np.int8), sec,
        rp, xyz=RowSubset(scene.xyz, pts), with_top=False, workers=LOO_THREADS,
        confusion_matrix=matrix, confusion=model)
    col[sel] = cls.col_of[labels]
    share[sel] = (1.0 + margin) / 2.0


def stored_matrix(ws: Path, cls: ClassColumns) -> np.ndarray | None:
    """The (C, C) pooled annotator matrix the workspace's last fill decided with (its
    ``labels.json``: ``robust_matrix``), or None: no fill stored one, or it names other
    classes than ``cls`` (the taxonomy changed), or it is not a matrix of probabilities."""
    from occufly.lifting.robust import is_annotator_matrix  # as redecide: loaded when used

    m = Workspace(ws).lift_stats().get("robust_matrix")
    if not isinstance(m, dict) or [int(i) for i in m.get("class_ids") or []] != [int(i) for i in cls.ids]:
        return None
    try:
        pi = np.asarray(m.get("pi"), np.float64)
    except (TypeError, ValueError):
        return None
    return pi if is_annotator_matrix(pi, cls.C) else None


# threads of a frame's robust decision (the reviewer waits for it; the same labels as one)
LOO_THREADS = max(1, min(4, os.cpu_count() or 1))


def _near(q: np.ndarray, pts: np.ndarray, radius: float) -> np.ndarray:
    """(len(pts),) bool: the points of ``pts`` in a voxel of edge ``radius`` next to (or
    holding) a point of ``q`` -- every point within ``radius`` of a query is one, so a k-NN
    within ``radius`` of ``q`` against them finds what it would against all of ``pts``. A
    frame's few points to fill need not build a k-d tree of every voted point in its view
    (survey: 5.8 k points to fill, 2.1 M voted points in their bounding box)."""
    grid = VoxelGrid(np.concatenate([np.asarray(q, np.float64), np.asarray(pts, np.float64)]),
                     radius, pad=1)
    near = np.zeros(grid.n_voxels, bool)
    near[grid.dilate(np.unique(grid.inverse[:len(q)]), 1)] = True
    return near[grid.inverse[len(q):]]


# the fill's k-NN vote by the compiled grid search (_fill_vote); False: the k-d tree it replaced
# (tests compare the two)
COMPILED_FILL = True
# the dense grid of the compiled fill (voxels of the fill radius over the box of the points to
# fill): above this many voxels the k-d tree path is taken instead
_FILL_GRID_MAX_CELLS = 1 << 24


@numba.njit(nogil=True, cache=True, inline="always")
def _grid_cell(xyz: np.ndarray, r: int, mn: np.ndarray, edge: float, n1: int, n2: int) -> int:
    """The dense grid cell of point ``xyz[r]`` (cells of ``edge`` from ``mn``, one cell of
    pad), row-major over (n0, n1, n2)."""
    c0 = np.int64(np.floor((np.float64(xyz[r, 0]) - mn[0]) / edge)) + 1
    c1 = np.int64(np.floor((np.float64(xyz[r, 1]) - mn[1]) / edge)) + 1
    c2 = np.int64(np.floor((np.float64(xyz[r, 2]) - mn[2]) / edge)) + 1
    return (c0 * n1 + c1) * n2 + c2


@numba.njit(nogil=True, cache=True)
def _fill_grid(xyz: np.ndarray, ids: np.ndarray, q_rows: np.ndarray, src_rows: np.ndarray,
               box_lo: np.ndarray, box_hi: np.ndarray, edge: float, max_cells: int) -> tuple:
    """The voted points the fill's k-d tree was built over, on a dense voxel grid: the source
    rows ``src_rows`` (into ``ids``) whose point lies in the box ``box_lo..box_hi`` (bounds
    inclusive, :func:`points_in_box`) and in a voxel that :func:`_near` keeps -- the voxels
    of edge ``edge`` (pad 1) of :class:`VoxelGrid` over the points to fill and those points,
    the points to fill's voxels and their 26 neighbours (:meth:`VoxelGrid.dilate` by one
    step), computed with the same float64 operations.
    Returns (grid origin (3,), dims (3,), cell starts (cells + 1,), the kept source rows
    grouped by cell in their given order, cell edge) of the search grid: cells of ``edge / 4``
    (coarser where that would exceed ``max_cells``) with the same origin and pad; dims[0] = -1
    when the voxels of ``edge`` exceed ``max_cells``, dims[0] = 0 when no source point is in
    the box."""
    nq = q_rows.shape[0]
    m = src_rows.shape[0]
    mn = np.empty(3, np.float64)
    mx = np.empty(3, np.float64)
    for d in range(3):
        mn[d] = np.inf
        mx[d] = -np.inf
    for i in range(nq):
        r = ids[q_rows[i]]
        for d in range(3):
            v = np.float64(xyz[r, d])
            mn[d] = min(mn[d], v)
            mx[d] = max(mx[d], v)
    inbox = np.zeros(m, np.bool_)
    n_in = 0
    for j in range(m):
        r = ids[src_rows[j]]
        x, y, z = np.float64(xyz[r, 0]), np.float64(xyz[r, 1]), np.float64(xyz[r, 2])
        if (box_lo[0] <= x <= box_hi[0]) and (box_lo[1] <= y <= box_hi[1]) \
                and (box_lo[2] <= z <= box_hi[2]):
            inbox[j] = True
            n_in += 1
            mn[0], mn[1], mn[2] = min(mn[0], x), min(mn[1], y), min(mn[2], z)
            mx[0], mx[1], mx[2] = max(mx[0], x), max(mx[1], y), max(mx[2], z)
    dims = np.zeros(3, np.int64)
    if n_in == 0:
        return mn, dims, np.zeros(1, np.int64), np.zeros(0, np.int64), edge
    total = 1.0
    for d in range(3):  # VoxelGrid(pad=1): q = floor((x - mn) / edge) + 1, dims = q.max + 2
        dims[d] = np.int64(np.floor((mx[d] - mn[d]) / edge)) + 3
        total *= dims[d]
    if total > max_cells:
        dims[0] = -1
        return mn, dims, np.zeros(1, np.int64), np.zeros(0, np.int64), edge
    n1, n2 = dims[1], dims[2]
    n_cells = dims[0] * n1 * n2
    mark = np.zeros(n_cells, np.bool_)
    for i in range(nq):
        mark[_grid_cell(xyz, ids[q_rows[i]], mn, edge, n1, n2)] = True
    cell = np.full(m, -1, np.int64)
    for j in range(m):
        if inbox[j]:
            cell[j] = _grid_cell(xyz, ids[src_rows[j]], mn, edge, n1, n2)
    # the separable dilation of VoxelGrid.dilate(voxels, 1): per axis, from the cells marked
    # before it, one step each way, empty cells included (the pad keeps steps inside)
    for stride in (n1 * n2, n2, 1):
        prev = mark.copy()
        for k in range(n_cells):
            if prev[k]:
                mark[k - stride] = True
                mark[k + stride] = True
    # the kept points binned on a finer grid (edge / sub from the same origin) for the search
    sub = 4
    while sub > 1 and (np.floor((mx[0] - mn[0]) / (edge / sub)) + 3) \
            * (np.floor((mx[1] - mn[1]) / (edge / sub)) + 3) \
            * (np.floor((mx[2] - mn[2]) / (edge / sub)) + 3) > max_cells:
        sub -= 1
    fine = edge / sub
    for d in range(3):
        dims[d] = np.int64(np.floor((mx[d] - mn[d]) / fine)) + 3
    n1, n2 = dims[1], dims[2]
    n_fine = dims[0] * n1 * n2
    starts = np.zeros(n_fine + 1, np.int64)
    for j in range(m):
        k = cell[j]
        if k >= 0:
            if mark[k]:
                k = _grid_cell(xyz, ids[src_rows[j]], mn, fine, n1, n2)
                cell[j] = k
                starts[k + 1] += 1
            else:
                cell[j] = -1
    for k in range(n_fine):
        starts[k + 1] += starts[k]
    pos = starts[:n_fine].copy()
    order = np.empty(starts[n_fine], np.int64)
    for j in range(m):
        k = cell[j]
        if k >= 0:
            order[pos[k]] = src_rows[j]
            pos[k] += 1
    return mn, dims, starts, order, fine


@numba.njit(nogil=True, cache=True)
def _gather_rows(xyz: np.ndarray, ids: np.ndarray, col: np.ndarray, order: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(float64 coordinates (m, 3), columns (m,)) of the rows ``order`` of ``ids``: the search
    reads them in cell order, contiguously."""
    m = order.shape[0]
    pts = np.empty((m, 3), np.float64)
    pc = np.empty(m, np.int64)
    for j in range(m):
        r = order[j]
        p = ids[r]
        pts[j, 0] = np.float64(xyz[p, 0])
        pts[j, 1] = np.float64(xyz[p, 1])
        pts[j, 2] = np.float64(xyz[p, 2])
        pc[j] = col[r]
    return pts, pc


@numba.njit(nogil=True, cache=True)
def _fill_knn_scores(xyz: np.ndarray, ids: np.ndarray, q_rows: np.ndarray, pts: np.ndarray,
                     pc: np.ndarray, mn: np.ndarray, dims: np.ndarray, starts: np.ndarray,
                     edge: float, k: int, radius: float, scores: np.ndarray,
                     ambiguous: np.ndarray) -> None:
    """Per query ``q_rows[i]``: its ``k`` nearest points ``pts`` (:func:`_fill_grid`'s, in its
    cell order, cells of ``edge``; columns ``pc``) closer than ``radius`` -- squared distances
    as scipy's k-d tree computes them (``(dx^2 + dy^2) + dz^2`` in float64, kept where below
    ``radius^2``) --, and their inverse-distance weights ``1 / max(sqrt(d2), 1e-6)`` added to
    ``scores[i, pc[j]]`` nearest first, the order :func:`knn_vote`'s bincount adds them. ``ambiguous[i]``: the
    k-th nearest ties with a point left out (which one a k-d tree keeps depends on its
    traversal). The columns of cells are visited nearest first; a column or a cell that
    cannot hold a point as near as the k-th found so far is skipped (with a 1 um margin, so
    no point at or below that distance is missed)."""
    n0, n1, n2 = dims[0], dims[1], dims[2]
    r2 = radius * radius
    eps = 1e-6
    R = np.int64(np.ceil(radius / edge)) + 1
    # column offsets, nearest first
    w = 2 * R + 1
    offs = np.empty((w * w, 2), np.int64)
    key = np.empty(w * w, np.int64)
    t = 0
    for da in range(-R, R + 1):
        for db in range(-R, R + 1):
            offs[t, 0] = da
            offs[t, 1] = db
            key[t] = da * da + db * db
            t += 1
    offs = offs[np.argsort(key, kind="mergesort")]
    hd = np.empty(k, np.float64)  # max-heap of the k nearest: squared distance, row
    hr = np.empty(k, np.int64)
    for i in range(q_rows.shape[0]):
        r = ids[q_rows[i]]
        qx = np.float64(xyz[r, 0])
        qy = np.float64(xyz[r, 1])
        qz = np.float64(xyz[r, 2])
        ca = np.int64(np.floor((qx - mn[0]) / edge)) + 1
        cb = np.int64(np.floor((qy - mn[1]) / edge)) + 1
        n = 0
        out_min = np.inf  # the smallest squared distance (< r2) left out
        for t in range(offs.shape[0]):
            a = ca + offs[t, 0]
            b = cb + offs[t, 1]
            if a < 0 or a >= n0 or b < 0 or b >= n1:
                continue
            lim = hd[0] if n == k else r2
            # the column's distance from the query in x and y, less the margin
            x0 = mn[0] + (a - 1) * edge
            gx = max(x0 - qx, qx - (x0 + edge), 0.0)
            gx = max(gx - eps, 0.0)
            y0 = mn[1] + (b - 1) * edge
            gy = max(y0 - qy, qy - (y0 + edge), 0.0)
            gy = max(gy - eps, 0.0)
            g2 = gx * gx + gy * gy
            if g2 > lim:
                continue
            hz = np.sqrt(lim - g2) + eps
            z0 = max(np.int64(np.floor(((qz - hz) - mn[2]) / edge)) + 1, 0)
            z1 = min(np.int64(np.floor(((qz + hz) - mn[2]) / edge)) + 1, n2 - 1)
            if z1 < z0:
                continue
            base = (a * n1 + b) * n2
            for row in range(starts[base + z0], starts[base + z1 + 1]):
                dx = pts[row, 0] - qx
                dy = pts[row, 1] - qy
                dz = pts[row, 2] - qz
                d2 = dx * dx + dy * dy
                d2 = d2 + dz * dz
                if not d2 < r2:
                    continue
                if n < k:  # sift up
                    j = n
                    n += 1
                    while j > 0:
                        par = (j - 1) // 2
                        if hd[par] >= d2:
                            break
                        hd[j] = hd[par]
                        hr[j] = hr[par]
                        j = par
                    hd[j] = d2
                    hr[j] = row
                    continue
                if d2 >= hd[0]:
                    out_min = min(out_min, d2)
                    continue
                out_min = min(out_min, hd[0])
                j = 0  # replace the farthest, sift down
                while True:
                    lc = 2 * j + 1
                    if lc >= k:
                        break
                    big = lc
                    if lc + 1 < k and hd[lc + 1] > hd[lc]:
                        big = lc + 1
                    if hd[big] <= d2:
                        break
                    hd[j] = hd[big]
                    hr[j] = hr[big]
                    j = big
                hd[j] = d2
                hr[j] = row
        ambiguous[i] = n == k and out_min == hd[0]
        if n == 0:
            continue
        # nearest first (points at equal distances weigh the same: their order changes no sum)
        srt = np.argsort(hd[:n])
        for t in range(n):
            e = srt[t]
            scores[i, pc[hr[e]]] += 1.0 / max(np.sqrt(hd[e]), 1e-6)


def _fill_tree(xyz: np.ndarray, ids: np.ndarray, todo: np.ndarray, src: np.ndarray,
               col: np.ndarray, p: LiftParams, cls: ClassColumns,
               only: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The fill's k-NN vote through a k-d tree (:func:`knn_vote`) of the voted points near the
    points to fill (rows ``todo`` of ``ids``): (column, -1 = none; share) of each point to fill,
    or with ``only`` (indices into ``todo``) of those alone (the tree is the same)."""
    q = np.asarray(xyz[ids[todo]], dtype=np.float64)
    qq = q if only is None else q[only]
    c = np.full(len(qq), -1, np.int64)
    fshare = np.zeros(len(qq), np.float32)
    if not len(q) or not len(src):
        return c, fshare
    lo, hi = q.min(0) - p.fill_radius, q.max(0) + p.fill_radius
    src = src[points_in_box(xyz, ids[src], lo, hi)]
    sx = np.asarray(xyz[ids[src]])
    if len(src):  # only voted points within the radius's voxels of a point to fill
        keep = _near(q, sx, p.fill_radius)
        src, sx = src[keep], sx[keep]
    if len(src):
        # built for a few thousand queries: the median splits of a balanced tree cost more
        # than they save (survey frame 52, 1.1 M points: 0.68 -> 0.28 s, the same neighbours)
        tree = cKDTree(np.asarray(sx, dtype=np.float64), balanced_tree=False, compact_nodes=False)
        c, fshare = knn_vote(tree, col[src], qq, p.fill_k, p.fill_radius, cls, weighted=True,
                             workers=p.workers)
    return c, fshare


# the compiled fill scores this many points to fill at a time (as knn_vote's chunks)
_FILL_CHUNK = 50_000


def _fill_vote(xyz: np.ndarray, ids: np.ndarray, todo: np.ndarray, src: np.ndarray,
               col: np.ndarray, p: LiftParams, cls: ClassColumns
               ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_fill_tree`'s inverse-distance-weighted k-NN vote (``p.fill_k`` nearest voted
    points within ``p.fill_radius``) of the points ``ids[todo]`` from the voted points
    ``ids[src]`` (columns ``col``), exactly: (column (len(todo),) int64, -1 = none; share
    (len(todo),) float32). The same points as the tree's (:func:`_fill_grid`), searched by
    brute force over the 3 x 3 x 3 voxels around each point to fill instead of a k-d tree
    built per frame (survey frame 52: a tree of 1.1 M points for 5.8 k queries); the same
    weights added in the same order. A point whose k-th neighbour ties with one left out
    takes the tree's answer."""
    k, radius = int(p.fill_k), float(p.fill_radius)
    if not len(todo) or not len(src):
        return np.full(len(todo), -1, np.int64), np.zeros(len(todo), np.float32)
    if k < 1 or not np.isfinite(radius) or radius <= 0 or int(col[src].min()) < 0:
        return _fill_tree(xyz, ids, todo, src, col, p, cls)
    xyz_a = np.asarray(xyz)
    ids = np.ascontiguousarray(ids, np.int64)
    todo = np.ascontiguousarray(todo, np.int64)
    q = np.asarray(xyz_a[ids[todo]], dtype=np.float64)
    lo, hi = q.min(0) - p.fill_radius, q.max(0) + p.fill_radius  # as _fill_tree's box
    mn, dims, starts, order, fine = _fill_grid(
        xyz_a, ids, todo, np.ascontiguousarray(src, np.int64), np.asarray(lo, np.float64),
        np.asarray(hi, np.float64), radius, _FILL_GRID_MAX_CELLS)
    if dims[0] < 0:
        return _fill_tree(xyz, ids, todo, src, col, p, cls)
    c = np.full(len(todo), -1, np.int64)
    fshare = np.zeros(len(todo), np.float32)
    if dims[0] == 0 or not len(order):
        return c, fshare
    pts, pc = _gather_rows(xyz_a, ids, np.ascontiguousarray(col, np.int64), order)
    amb = np.zeros(len(todo), bool)
    # each query alone: chunks of them, shared out to LOO_THREADS threads (the kernel holds
    # no interpreter lock), give the same result as one pass
    step = max(1, min(_FILL_CHUNK, -(-len(todo) // LOO_THREADS)))

    def run(a: int) -> None:
        b = min(len(todo), a + step)
        scores = np.zeros((b - a, cls.C), np.float64)
        _fill_knn_scores(xyz_a, ids, todo[a:b], pts, pc, mn, dims, starts, fine, k, radius,
                         scores, amb[a:b])
        c[a:b], fshare[a:b] = _scores_to_cols(cls, scores)

    starts_q = range(0, len(todo), step)
    if LOO_THREADS > 1 and len(starts_q) > 1:
        with ThreadPoolExecutor(max_workers=LOO_THREADS) as pool:
            list(pool.map(run, starts_q))
    else:
        for a in starts_q:
            run(a)
    if amb.any():  # ties at the k-th neighbour: the k-d tree decides, as before
        rows = np.flatnonzero(amb)
        c[rows], fshare[rows] = _fill_tree(xyz, ids, todo, src, col, p, cls, only=rows)
    return c, fshare


@numba.njit(nogil=True, cache=True)
def _reaching(xyz: np.ndarray, ids: np.ndarray, T: np.ndarray, fx: float, fy: float,
              cx: float, cy: float, w: float, h: float, splat: float, reach: float,
              tx: float, ty: float) -> np.ndarray:
    """(len(ids),) bool: the points whose splat (``splat`` pixels) can reach the image, or
    that lie within ``reach`` metres of a point projecting into it (a fill source): for a
    point at depth z the second is a margin of ``f * reach * (1 + t) / z`` pixels, ``t`` the
    tangent of the image's widest half angle (a displacement d at depth z moves the
    projection by at most ``f |d| (1 + t) / z``). A point within ``reach`` of the camera
    plane is kept; a non-finite one is not."""
    out = np.zeros(len(ids), np.bool_)
    for i in range(len(ids)):
        j = ids[i]
        px, py, pz = float(xyz[j, 0]), float(xyz[j, 1]), float(xyz[j, 2])
        x = T[0, 0] * px + T[0, 1] * py + T[0, 2] * pz + T[0, 3]
        y = T[1, 0] * px + T[1, 1] * py + T[1, 2] * pz + T[1, 3]
        z = T[2, 0] * px + T[2, 1] * py + T[2, 2] * pz + T[2, 3]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        if z <= reach:
            out[i] = z > -reach
            continue
        mu = splat + fx * reach * (1.0 + tx) / z
        mv = splat + fy * reach * (1.0 + ty) / z
        u = fx * x / z + cx
        v = fy * y / z + cy
        out[i] = (u >= -mu) and (u <= w + mu) and (v >= -mv) and (v <= h + mv)
    return out


def loo_point_ids(scene: Scene, frame_index: int, *, params: LiftParams | None = None
                  ) -> np.ndarray:
    """Sorted (K,) int64 ids of the points frame ``frame_index``'s leave-one-out labels are
    decided at: the points it sees, those whose splat can reach its image (the render's
    widest margin, ``MAX_SPLAT * MAX_COARSE`` pixels on a large image) and those within the
    fill radius of a point projecting into it -- nothing else can change what its review
    shows. Their decision depends only on the votes at these points, so on the vote files
    of :func:`frames_reaching` alone (the review cache's key). Every point for a
    cloud the render does not cull (small clouds, a lens model without a valid radius). A
    distorted camera: :func:`_distorted_point_ids`."""
    p = params or LiftParams()
    fr = scene.frames[frame_index]
    cam = fr.camera
    w, h = float(cam.width), float(cam.height)
    splat = float(MAX_SPLAT * (MAX_COARSE if w * h > COARSE_MIN_PIXELS else 1))
    # the cull's margin: the render's widest for a distorted camera (its cull is tight: the
    # view bounds); the bins' default for the others, as the labels were decided before (the
    # bins, ~20 m on a survey, reach far beyond it; the render's own cull takes splat)
    cand = frustum_candidates(scene, cam, fr.T_cam_world,
                              margin=splat if cam.has_distortion else MAX_SPLAT)
    if cand is None:
        return np.arange(scene.n_points, dtype=np.int64)
    if cam.has_distortion:
        return _distorted_point_ids(scene, frame_index, np.asarray(cand, np.int64), splat,
                                    float(p.fill_radius))
    vis = np.asarray(scene.visibility.frame_ids(frame_index), dtype=np.int64)
    ids = np.asarray(cand, np.int64)  # sorted: the cull's bins, 25-30 % beyond the image
    fx, fy = cam.focal
    cx, cy = cam.principal_point
    T = np.ascontiguousarray(np.asarray(fr.T_cam_world, np.float64)[:3, :4])
    keep = _reaching(np.asarray(scene.xyz), ids, T, float(fx), float(fy), float(cx),
                     float(cy), w, h, splat, float(p.fill_radius),
                     max(cx, w - cx) / fx, max(cy, h - cy) / fy)
    ids = ids[keep]
    missing = vis[rows_in(ids, vis) < 0]  # f's visible points are (almost) all in it
    if len(missing):  # a sort of the few left out, not a hash of them all (np.union1d)
        ids = np.sort(np.concatenate([ids, missing]))
    return ids


_PROJECT_CHUNK = 1 << 21  # points projected at once through a lens model (float64 temporaries)


def _distorted_point_ids(scene: Scene, frame_index: int, cand: np.ndarray, splat: float,
                         reach: float) -> np.ndarray:
    """:func:`loo_point_ids` for a distorted camera: of its cull ``cand`` (the cone of its
    lens model's valid radius), the points the render draws -- those in front whose projection
    through the lens model falls within ``splat`` pixels of the image (``render._render``'s
    rule at its coarsest) --, the points the frame sees, and the points within ``reach``
    metres of one it sees (the fill's sources: only seen points are filled; ``_near``'s
    voxels, a superset; looked for in the whole cloud by one compiled pass)."""
    fr = scene.frames[frame_index]
    cam = fr.camera
    xyz = scene.xyz
    n = scene.n_points
    w, h = float(cam.width), float(cam.height)
    keep = np.zeros(n, bool)
    for a in range(0, len(cand), _PROJECT_CHUNK):
        sub = cand[a:a + _PROJECT_CHUNK]
        uv, z = project_points(fr, xyz, sub)
        with np.errstate(invalid="ignore"):
            keep[sub] = ((z > 1e-6) & (uv[:, 0] >= -splat) & (uv[:, 0] < w + splat)
                         & (uv[:, 1] >= -splat) & (uv[:, 1] < h + splat))
    vis = np.asarray(scene.visibility.frame_ids(frame_index), dtype=np.int64)
    keep[vis] = True
    if len(vis) and reach > 0:
        q = np.asarray(xyz[vis], np.float64)
        q = q[np.isfinite(q).all(axis=1)]
        if len(q):
            lo, hi = q.min(axis=0) - reach, q.max(axis=0) + reach
            inbox = np.concatenate([
                a + np.flatnonzero(points_in_box(xyz, np.arange(a, min(n, a + _PROJECT_CHUNK)),
                                                 lo, hi))
                for a in range(0, n, _PROJECT_CHUNK)]).astype(np.int64)
            inbox = inbox[~keep[inbox]]
            if len(inbox):
                keep[inbox[_near(q, np.asarray(xyz[inbox], np.float64), reach)]] = True
    return np.flatnonzero(keep)


# a frame's votes at a point whose projection is outside its image by more than this share of
# the image's size are impossible (a visible point projects into the image; stored uv of an
# import are clipped to it): :func:`frames_reaching` widens every frustum by it
_VOTE_SLACK = 0.05


@numba.njit(nogil=True, cache=True)
def _tile_boxes(xyz: np.ndarray, ids: np.ndarray, tiles: int) -> np.ndarray:
    """(T, 6) float64 bounding boxes (min xyz, max xyz) of the finite points ``ids`` grouped
    by a ``tiles`` x ``tiles`` grid over their x-y extent, the empty tiles left out (an
    oblique footprint's points fill a few tiles of its bounding box)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(len(ids)):
        j = ids[i]
        x, y, z = float(xyz[j, 0]), float(xyz[j, 1]), float(xyz[j, 2])
        if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
            lo[0], lo[1], lo[2] = min(lo[0], x), min(lo[1], y), min(lo[2], z)
            hi[0], hi[1], hi[2] = max(hi[0], x), max(hi[1], y), max(hi[2], z)
    if not lo[0] <= hi[0]:
        return np.zeros((0, 6))
    box = np.empty((tiles * tiles, 6))
    box[:, :3] = np.inf
    box[:, 3:] = -np.inf
    sx = max(hi[0] - lo[0], 1e-9) / tiles
    sy = max(hi[1] - lo[1], 1e-9) / tiles
    for i in range(len(ids)):
        j = ids[i]
        x, y, z = float(xyz[j, 0]), float(xyz[j, 1]), float(xyz[j, 2])
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        t = min(int((x - lo[0]) / sx), tiles - 1) * tiles + min(int((y - lo[1]) / sy), tiles - 1)
        box[t, 0], box[t, 1], box[t, 2] = min(box[t, 0], x), min(box[t, 1], y), min(box[t, 2], z)
        box[t, 3], box[t, 4], box[t, 5] = max(box[t, 3], x), max(box[t, 4], y), max(box[t, 5], z)
    n = 0
    for t in range(tiles * tiles):
        if box[t, 0] <= box[t, 3]:
            box[n] = box[t]
            n += 1
    return box[:n].copy()


# the x-y grid of :func:`frames_reaching`'s boxes
_REACH_TILES = 4


def frames_reaching(scene: Scene, frame_index: int, ids: np.ndarray) -> np.ndarray | None:
    """Sorted int64 indices of the frames other than ``frame_index`` that can vote at any of
    the points ``ids`` (:func:`loo_point_ids`): those whose view frustum, widened by
    ``_VOTE_SLACK``, meets the bounding box of the points of one tile of a 4 x 4 x-y grid
    over them (a frame votes only at the points it sees, which lie in its frustum). A
    superset, never missing one; None where it cannot be bounded (a distorted camera, no
    finite point): every frame may."""
    ids = np.asarray(ids, np.int64)
    if not len(ids):
        return np.zeros(0, np.int64)
    # each frame's frustum as bounds of x / z and y / z: the image widened by the slack
    bounds = np.empty((len(scene.frames), 4))
    for g, fr in enumerate(scene.frames):
        cm = fr.camera
        if cm.has_distortion:
            # a distorted camera's votes lie within the cone of its valid radius only where
            # its votes were cast since Camera.valid_radius (a workspace lifted before may
            # hold votes at points its lens model folded into the image): not bounded
            return None
        fx, fy = cm.focal
        cx, cy = cm.principal_point
        mu, mv = _VOTE_SLACK * cm.width, _VOTE_SLACK * cm.height
        bounds[g] = (-(cx + mu) / fx, (cm.width + mu - cx) / fx,
                     -(cy + mv) / fy, (cm.height + mv - cy) / fy)
    boxes = _tile_boxes(np.asarray(scene.xyz), ids, _REACH_TILES)
    if not len(boxes):
        return None
    # (B, 8, 3) corners of every box
    sel = np.array([[a, b, c] for a in (0, 3) for b in (1, 4) for c in (2, 5)])
    corners = boxes[:, sel]
    T = np.stack([np.asarray(f.T_cam_world, np.float64)[:3, :4] for f in scene.frames])
    c = np.einsum("fij,bkj->fbki", T[:, :, :3], corners) + T[:, None, None, :, 3]  # (F, B, 8, 3)
    x, y, z = c[..., 0], c[..., 1], c[..., 2]
    meets = (z > 0).any(axis=2)  # (F, B); else the box is behind the camera
    # x / z >= xmin  <=>  x - xmin z >= 0 for z > 0, and so on: a box misses the frustum when
    # all eight corners fail one side
    e = (slice(None), None, None)
    x0, x1, y0, y1 = (bounds[:, i][e] for i in range(4))
    for side in (x - x0 * z, x1 * z - x, y - y0 * z, y1 * z - y):
        meets &= (side >= 0).any(axis=2)
    hit = meets.any(axis=1)
    hit[frame_index] = False
    return np.flatnonzero(hit).astype(np.int64)


def loo_labels(ws: str | Path, scene: Scene, frame_index: int, *,
               params: LiftParams | None = None, corrections: bool = True) -> LooLabels:
    """The labels of the points around frame ``frame_index`` (:func:`loo_point_ids`) decided
    without its votes."""
    ws = Path(ws)
    p = params or LiftParams()
    cls = ClassColumns(scene.taxonomy)
    votes = np.load(Workspace(ws).votes, mmap_mode="r")  # (N, C) uint16
    vis = np.asarray(scene.visibility.frame_ids(frame_index), dtype=np.int64)
    ids = loo_point_ids(scene, frame_index, params=p)
    # row in ids of the visible points, own votes and overrides (-1: not gathered): a merge
    # walk of the sorted ids and each sorted list (:func:`rows_in`), no (N,) map of the scene
    if len(ids) == scene.n_points:

        def rows(q: np.ndarray) -> np.ndarray:  # every point gathered: its id is its row
            q = np.asarray(q, np.int64)
            return np.where((q >= 0) & (q < len(ids)), q, -1)
    else:

        def rows(q: np.ndarray) -> np.ndarray:
            return rows_in(ids, q)
    own_p, own_c, own_w = _frame_votes(ws, frame_index)
    share = np.empty(len(ids), np.float32)
    col, n1, col2, n2 = loo_winner(votes, ids, own_p, own_c, own_w, cls, share,
                                   own_rows=rows(own_p), second=True)
    voted = col >= 0
    if getattr(p, "robust", False):
        _robust_decision(ws, scene, cls, ids, col, n1, col2, n2, share, p, frame_index)
    # fill: the points f sees without an independent vote, from the other frames' voted points
    is_vis = np.zeros(len(ids), bool)
    is_vis[rows(vis)] = True  # every visible point is in ids
    todo = np.flatnonzero(is_vis & ~voted)
    src = np.flatnonzero(voted)
    if len(todo) and len(src):
        fill = _fill_vote if COMPILED_FILL else _fill_tree
        c, fshare = fill(scene.xyz, ids, todo, src, col, p, cls)
        col[todo] = c
        share[todo] = np.where(c >= 0, fshare, 0.0)
    labels = cls.labels_of(col)
    if corrections:
        ov = read_overrides(ws, scene.n_points)
        if ov is not None and len(ov):
            op = np.asarray(ov.point_ids, np.int64)
            pos = rows(op)
            hit = pos >= 0
            labels[pos[hit]] = np.asarray(ov.labels)[hit]
            share[pos[hit]] = 1.0
    return LooLabels(frame_index, ids, labels, voted, share)


# a neighbour is named when it voted differently from the frame on at least this many of the
# points both voted, and on at least this share of them
NEIGHBOUR_MIN_POINTS = 50
NEIGHBOUR_MIN_SHARE = 0.1
_NEIGHBOUR_SAMPLE = 4096  # the frame's voted points projected to find the frames that see them


@numba.njit(nogil=True, cache=True)
def _gallop(a: np.ndarray, j: int, v: int) -> int:
    """The first index >= ``j`` of sorted ``a`` whose value is >= ``v``: doubling steps, then a
    binary search -- O(log gap), so a short list walked against a long one costs little."""
    n = a.shape[0]
    if j >= n or a[j] >= v:
        return j
    lo = j  # a[lo] < v
    step = 1
    hi = j + 1
    while hi < n and a[hi] < v:
        lo = hi
        step *= 2
        hi = j + step
    if hi > n:
        hi = n
    while hi - lo > 1:  # a[lo] < v <= a[hi] (or hi == n)
        mid = (lo + hi) // 2
        if a[mid] < v:
            lo = mid
        else:
            hi = mid
    return hi


@numba.njit(nogil=True, cache=True)
def _neighbour_counts(own_p: np.ndarray, own_c: np.ndarray, gp: np.ndarray, gc: np.ndarray,
                      pids: np.ndarray, loo_cols: np.ndarray) -> tuple:
    """(shared, disagreeing, overruled, disagreeing with an independent label) of a
    neighbour's votes ``gp``/``gc`` against the frame's ``own_p``/``own_c`` (sorted; a point's
    first vote counts), the independent labels' columns ``loo_cols`` of ``pids`` (sorted):
    one merge walk. (-1, 0, 0, 0) when ``gp`` is not sorted."""
    m = gp.shape[0]
    for i in range(1, m):
        if gp[i] < gp[i - 1]:
            return -1, 0, 0, 0
    n_own = own_p.shape[0]
    n_p = pids.shape[0]
    j = 0
    k = 0
    shared = 0
    dis = 0
    over = 0
    has = 0
    for i in range(m):
        v = np.int64(gp[i])
        j = _gallop(own_p, j, v)
        if j == n_own or own_p[j] != v:
            continue
        mc = np.int64(np.int16(own_c[j]))  # as the int16 map held it
        if mc < 0:
            continue
        shared += 1
        c = np.int64(gc[i])
        if c == mc:
            continue
        dis += 1
        k = _gallop(pids, k, v)
        if k < n_p and pids[k] == v:
            lc = loo_cols[k]
            if lc >= 0:
                has += 1
                if lc != c:
                    over += 1
    return shared, dis, over, has


def _neighbour_counts_map(mine_of: np.ndarray, gp: np.ndarray, gc: np.ndarray, loo: LooLabels,
                          loo_cols: np.ndarray) -> tuple[int, int, int, int]:
    """:func:`_neighbour_counts` for votes in any order, through the frame's (N,) vote map."""
    mine = mine_of[gp]
    hit = mine >= 0
    n_shared = int(hit.sum())
    if not n_shared:
        return 0, 0, 0, 0
    gp, gc, mine = gp[hit], gc[hit], mine[hit]
    dis = gc != mine
    r = np.minimum(np.searchsorted(loo.point_ids, gp[dis]), len(loo.point_ids) - 1)
    lc = np.where(loo.point_ids[r] == gp[dis], loo_cols[r], -1)
    has = lc >= 0
    return n_shared, int(dis.sum()), int((has & (lc != gc[dis])).sum()), int(has.sum())


@dataclass
class NeighbourVotes:
    """What :func:`disagreeing_neighbours` reads before it needs the leave-one-out labels:
    frame ``frame_index``'s votes (``own_p`` point ids sorted, ``own_c`` columns) and, for
    each annotated frame into which a sample of its voted points projects, that frame's index
    (``frames``, in frame order; its votes are read one frame at a time by
    :func:`disagreeing_neighbours`)."""

    frame_index: int
    own_p: np.ndarray
    own_c: np.ndarray
    frames: list


def neighbour_votes(ws: str | Path, scene: Scene, frame_index: int) -> NeighbourVotes:
    """The votes :func:`disagreeing_neighbours` compares (:class:`NeighbourVotes`): one
    projection of a sample of the frame's voted points per annotated frame, which frames see
    it. Needs no labels, so a review finds them while the leave-one-out labels are decided;
    their vote files are read when compared, one at a time (memory maps, one open file)."""
    w = Workspace(ws)
    own_p, own_c, _ = _frame_votes(Path(ws), frame_index)
    d = w.lifting_frames_dir
    others = sorted(int(q.stem) for q in d.glob("*.npz")) if d.is_dir() else []
    others = [g for g in others if g != frame_index and 0 <= g < len(scene.frames)]
    if not len(own_p) or not others:
        return NeighbourVotes(frame_index, own_p, own_c, [])
    if len(own_p) > 1 and (np.diff(own_p) < 0).any():  # stored sorted; else a stable sort
        order = np.argsort(own_p, kind="stable")
        own_p, own_c = own_p[order], own_c[order]
    samp = own_p[np.unique(np.linspace(0, len(own_p) - 1, min(len(own_p), _NEIGHBOUR_SAMPLE))
                          .astype(np.int64))]
    frames = []
    for g in others:
        fr = scene.frames[g]
        uv, z = project_points(fr, scene.xyz, samp)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < fr.camera.width) \
            & (uv[:, 1] >= 0) & (uv[:, 1] < fr.camera.height)
        if inside.any():
            frames.append(g)
    return NeighbourVotes(frame_index, own_p, own_c, frames)


def disagreeing_neighbours(ws: str | Path, scene: Scene, frame_index: int, loo: LooLabels, *,
                           limit: int = 3, votes: NeighbourVotes | None = None) -> list[dict]:
    """The annotated frames whose votes contradict frame ``frame_index``'s, most first.

    Candidates are the frames with votes (``ws/lifting/frames``) into which a sample of the
    frame's voted points projects (in front of the camera, inside the image); for each, on
    the points both voted: ``shared_points``, ``disagree_points`` (a different class),
    ``disagree_share`` and ``overruled_share`` -- the share of those disagreeing points where
    the independent labels (``loo``, decided without the frame, with the pipeline's robust
    decision) are not the neighbour's class either: near 1, the other frames overrule the
    neighbour (it is the likely wrong one); near 0, they side with it. Listed when at least
    ``NEIGHBOUR_MIN_POINTS`` and ``NEIGHBOUR_MIN_SHARE`` of the shared points disagree.
    Cost: one projection of the sample per annotated frame, the votes of the frames that see
    it (``votes``: those already read by :func:`neighbour_votes`)."""
    nv = votes if votes is not None else neighbour_votes(ws, scene, frame_index)
    if nv.frame_index != frame_index:
        raise ValueError(f"neighbour votes of frame {nv.frame_index}, not {frame_index}")
    own_p, own_c = nv.own_p, nv.own_c
    if not nv.frames:
        return []
    loo_cols = ClassColumns(scene.taxonomy).col_of[loo.labels]  # -1: no independent label
    pids = np.ascontiguousarray(loo.point_ids, np.int64)
    mine_of = None  # built only for a neighbour whose votes are not sorted
    out = []
    w = Workspace(ws)
    for g in nv.frames:
        # the stored votes mapped, not copied; dropped (and the file closed) each turn
        got = w.read_frame_votes(g, mmap=True)
        if got is None:  # its mask was deleted since: no votes to compare
            continue
        gp, gc = got[:2]
        del got
        # both vote lists sorted by point id: one merge walk counts the shared, disagreeing
        # and overruled points (no (N,) map of the frame's votes, no per-vote temporaries)
        counts = _neighbour_counts(own_p, own_c, gp, gc, pids, loo_cols) if len(gp) else (0, 0, 0, 0)
        if counts[0] < 0:
            if mine_of is None:
                # the frame's vote column per scene point (-1: none; a point's first vote where
                # it has two): one gather per neighbour's vote
                mine_of = np.full(scene.n_points, -1, np.int16)
                mine_of[own_p[::-1]] = own_c[::-1]
            counts = _neighbour_counts_map(mine_of, gp, gc, loo, loo_cols)
        n_shared, n_dis, over, n_has = counts
        if not n_shared:
            continue
        if n_dis < NEIGHBOUR_MIN_POINTS or n_dis < NEIGHBOUR_MIN_SHARE * n_shared:
            continue
        out.append({"frame_index": int(g), "shared_points": n_shared, "disagree_points": n_dis,
                    "disagree_share": round(n_dis / n_shared, 4),
                    "overruled_share": round(over / n_has, 4) if n_has else None})
    out.sort(key=lambda r: (-r["disagree_points"], r["frame_index"]))
    return out[:limit]


# the ranking score compares a mask with the *confident* independent labels only: a label
# holding at least this share of the other frames' votes (of the k-NN vote where filled).
# Where the other frames disagree among themselves (a wrong neighbour's votes against a right
# one's) the LOO label says little about this frame, and a right mask next to a wrong one
# would otherwise rank among the wrong ones (bench_review)
CONFIDENT_SHARE = 0.6


def render_review(scene: Scene, loo: LooLabels, mask_shape: tuple[int, int],
                  self_labels: np.ndarray | None = None, *, geometry=None) -> dict:  # noqa: ANN001
    """The renderings a review compares a mask with, in one pass over the frame's geometry
    (:func:`occufly.render.render_many_for_mask`; each image equals its own
    :func:`~occufly.render.render_for_mask`): ``"loo"`` the leave-one-out labels,
    ``"confident"`` those of them holding >= ``CONFIDENT_SHARE`` of their votes (others 0),
    and with ``self_labels`` ((N,) uint8, the lifted labels) ``"self"``. ``geometry``: the
    frame's :func:`occufly.render.frame_geometry` for ``mask_shape``, computed beforehand
    (then only the label pass runs)."""
    # sparse label sets: the render gathers its culled points' labels by one merge walk of
    # the sorted point ids, no (N,) array per set
    sets: list = [(loo.point_ids, loo.labels)]
    if loo.share is not None:
        sets.append((loo.point_ids, np.where(loo.share >= CONFIDENT_SHARE, loo.labels,
                                             np.uint8(0)).astype(np.uint8)))
    if self_labels is not None:
        sets.append(np.asarray(self_labels, np.uint8))
    imgs = render_many_for_mask(scene, sets, loo.frame_index, mask_shape, geometry=geometry)
    out = {"loo": imgs[0], "confident": imgs[1] if loo.share is not None else imgs[0]}
    if self_labels is not None:
        out["self"] = imgs[-1]
    return out


# the shift test: a mask that agrees better with the independent labels shifted by 1.5-6 % of
# the frame width (in x, y or both) than in place is misregistered (drawn on a shifted image,
# or pasted from a neighbouring frame); right masks agree best in place (bench_review: gain
# exactly 0 for every right frame of small and bench)
SHIFT_STEPS = (0.01, 0.02, 0.03, 0.04, 0.05, 0.06)
SHIFT_SIDE = 240  # the test runs on the images subsampled to about this width


def shift_gain(mask: np.ndarray, rendered: np.ndarray, valid: np.ndarray) -> float:
    """max over shifts s of agreement(mask, rendered moved by s) - agreement in place, >= 0.

    Both images are subsampled to ~``SHIFT_SIDE`` px wide (a stride, no filtering); shifts
    are the 9 x 9 grid of 0, +-``SHIFT_STEPS`` x width in x and y, compared over their overlap,
    pixels where both have a class. Cost: ~80 comparisons of ~40 k pixels."""
    h, w = mask.shape
    st = max(1, w // SHIFT_SIDE)
    m, r = np.asarray(mask)[::st, ::st], np.asarray(rendered)[::st, ::st]
    hm, wm = m.shape
    mv, rv = valid[m], valid[r]
    steps = sorted({0, *(int(round(f * wm)) for f in SHIFT_STEPS)} - {0})
    offs = [0, *steps, *(-x for x in steps)]

    def agree(dy: int, dx: int) -> float | None:
        ys, yd = (slice(dy, hm), slice(0, hm - dy)) if dy >= 0 else (slice(0, hm + dy), slice(-dy, hm))
        xs, xd = (slice(dx, wm), slice(0, wm - dx)) if dx >= 0 else (slice(0, wm + dx), slice(-dx, wm))
        both = mv[ys, xs] & rv[yd, xd]  # mask pixel (y, x) against rendered (y - dy, x - dx)
        n = int(both.sum())
        return float((both & (m[ys, xs] == r[yd, xd])).sum()) / n if n else None

    base = agree(0, 0)
    if base is None:
        return 0.0
    best = base
    for dy in offs:
        for dx in offs:
            if dy or dx:
                v = agree(dy, dx)
                if v is not None and v > best:
                    best = v
    return best - base


def score_figures(mask: np.ndarray, confident: np.ndarray, valid: np.ndarray,
                  counts: np.ndarray | None = None) -> dict:
    """The ranking score's figures of a mask against the *confident* LOO rendering:
    ``area_pixels`` (its class pixels where the mask has a class or nothing; "ignore" 255 and
    unknown ids left out), ``area_agree`` (of them, the mask's class equals it),
    ``area_agreement`` = agree / area (None without any), ``shift_gain`` (:func:`shift_gain`)
    and ``review_score`` (:func:`review_score`). ``counts``: the pair count of (mask,
    confident) over compact columns when the caller has it (:func:`count_pairs_many`)."""
    mask = np.asarray(mask)
    n_cls = int(valid.sum())
    if counts is None:
        counts = Confusion(np.flatnonzero(valid).astype(np.uint8)).add_all_pairs(mask, confident)
    full = counts  # rows mask, columns LOO
    cls_ = slice(1, n_cls + 1)  # compact columns of the classes; 0 = empty (unpainted)
    area = int(full[0, cls_].sum() + full[cls_, cls_].sum())
    agree = int(np.trace(full[cls_, cls_]))
    out = {"area_pixels": area, "area_agree": agree,
           "area_agreement": agree / area if area else None,
           "shift_gain": shift_gain(mask, confident, valid) if area else 0.0}
    out["review_score"] = review_score(out)
    return out


def review_score(fig: dict) -> float | None:
    """The review list's ranking score of a frame (higher = look first), from
    :func:`score_figures`: the share of the frame's *confidently, independently labelled*
    area (pixels the other frames' confident labels render into, painted or not) that the mask
    does not reproduce -- a wrong class, or nothing painted where the other frames see
    something -- plus the shift test's gain. None without any such pixel. Unlike the LOO
    agreement, which counts painted pixels only, it sees a half-painted frame (its unpainted
    half is disagreement) and a shifted one."""
    if not fig.get("area_pixels"):
        return None
    return float(1.0 - fig["area_agreement"] + (fig.get("shift_gain") or 0.0))


def self_figures(mask: np.ndarray, self_rendered: np.ndarray, scene: Scene) -> dict:
    """``self_agreement`` and ``self_pixels`` of :func:`loo_agreement`, alone: ``mask``
    against the scene's own labels rendered (the old, circular figure)."""
    mask = np.asarray(mask)
    if np.shape(self_rendered) != mask.shape:
        raise ValueError(f"mask {mask.shape} and rendering {np.shape(self_rendered)} must be the same (h, w)")
    s = agreement_from_counts(count_pairs_many(scene.taxonomy.ids, mask, [self_rendered])[0],
                              scene.taxonomy)
    sv = s.get("agreement")
    return {"self_agreement": None if sv is None or not np.isfinite(sv) else float(sv),
            "self_pixels": int(s.get("pixels", 0))}


def loo_agreement(mask: np.ndarray, rendered: np.ndarray, scene: Scene, *,
                  self_rendered: np.ndarray | None = None,
                  confident_rendered: np.ndarray | None = None) -> dict:
    """Agreement of ``mask`` (h, w uint8 raw ids) with the leave-one-out ``rendered`` labels.

    Returns ``agreement`` (share of the painted pixels with an independent label that agree;
    None without any), ``independent_pixels``, ``independent_coverage`` (share of the painted
    pixels with an independent label), ``painted_pixels``, ``painted_share`` (painted / all
    pixels), ``per_class`` and ``confusion`` (of the LOO rendering), the ranking score's
    figures (:func:`score_figures` against ``confident_rendered``, default ``rendered``:
    ``review_score``, ``area_agreement``, ``shift_gain``...), and, with ``self_rendered``,
    ``self_agreement`` (the old circular figure, kept apart).
    """
    mask = np.asarray(mask)
    tax = scene.taxonomy
    conf_ren = rendered if confident_rendered is None else confident_rendered
    imgs = [rendered, conf_ren] + ([self_rendered] if self_rendered is not None else [])
    for im in imgs:
        if np.shape(im) != mask.shape:
            raise ValueError(f"mask {mask.shape} and rendering {np.shape(im)} must be the same (h, w)")
    # every rendering's pixel pairs with the mask counted in one compiled pass
    counts = count_pairs_many(tax.ids, mask, imgs, workers=LOO_THREADS)
    res = agreement_from_counts(counts[0], tax)
    valid = tax.valid_lut()
    painted = int(res.get("mask_pixels", 0))  # pixels of a taxonomy class (not 0 / 255)
    ind = int(res.get("pixels", 0))
    val = res.get("agreement")
    val = None if val is None or not np.isfinite(val) or ind == 0 else float(val)
    out = {"agreement": val, "independent_pixels": ind, "painted_pixels": painted,
           "independent_coverage": (ind / painted) if painted else 0.0,
           "painted_share": painted / mask.size if mask.size else 0.0,
           "per_class": res.get("per_class") or {}, "confusion": res.get("confusion"),
           "agree": int(res.get("agree", 0))}
    fig = score_figures(mask, conf_ren, valid, counts[1])
    out.update(fig)
    out["area_share"] = fig["area_pixels"] / mask.size if mask.size else 0.0
    if self_rendered is not None:
        s = agreement_from_counts(counts[2], tax)
        sv = s.get("agreement")
        out["self_agreement"] = None if sv is None or not np.isfinite(sv) else float(sv)
        out["self_pixels"] = int(s.get("pixels", 0))
    return out


def review_renders(ws: str | Path, scene: Scene, frame_index: int,
                   mask: np.ndarray | Callable[[], np.ndarray], *,
                   params: LiftParams | None = None, self_labels: np.ndarray | None = None,
                   neighbours: bool = False) -> tuple:
    """(mask, :class:`LooLabels`, :func:`render_review`'s images, :func:`disagreeing_neighbours`
    or None) of frame ``frame_index``: what a review compares ``mask`` with. The parts that
    need no labels run in a second thread beside the leave-one-out labels -- the mask's decode
    where ``mask`` is a callable returning it, the render's depth pass
    (:func:`occufly.render.frame_geometry`), the neighbours' vote files -- and the
    neighbours' counts beside the render's label pass: a reviewer's first open of a 20 MP
    frame waits for the longest path only."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="occufly-loo") as pool:
        mask_fut = pool.submit(mask) if callable(mask) else None

        def geometry():  # noqa: ANN202
            shape = (mask_fut.result() if mask_fut is not None else mask).shape
            return frame_geometry(scene, frame_index, shape)

        geo_fut = pool.submit(geometry)
        nv_fut = pool.submit(neighbour_votes, ws, scene, frame_index) if neighbours else None
        loo = loo_labels(ws, scene, frame_index, params=params)
        nb_fut = None if nv_fut is None else pool.submit(
            lambda: disagreeing_neighbours(ws, scene, frame_index, loo, votes=nv_fut.result()))
        if mask_fut is not None:
            mask = mask_fut.result()
        imgs = render_review(scene, loo, mask.shape, self_labels, geometry=geo_fut.result())
        return mask, loo, imgs, None if nb_fut is None else nb_fut.result()


def frame_loo(ws: str | Path, scene: Scene, frame_index: int, mask: np.ndarray, *,
              params: LiftParams | None = None, self_labels: np.ndarray | None = None,
              image: bool = False, neighbours: bool = False) -> dict:
    """Leave-one-out agreement of frame ``frame_index``'s ``mask`` (see :func:`loo_agreement`);
    with ``self_labels`` ((N,) uint8, the lifted labels) also the self-agreement; with
    ``image`` the disagreement RGBA under ``"image"``; with ``neighbours`` the frames whose
    votes contradict this one's under ``"neighbours"`` (:func:`disagreeing_neighbours`)."""
    mask, _loo, imgs, nb = review_renders(ws, scene, frame_index, mask, params=params,
                                          self_labels=self_labels, neighbours=neighbours)
    ren = imgs["loo"]
    out = loo_agreement(mask, ren, scene, self_rendered=imgs.get("self"),
                        confident_rendered=imgs["confident"])
    if image:
        out["image"] = disagreement_image(mask, ren, scene.taxonomy)
    out["rendered"] = ren
    if nb is not None:
        out["neighbours"] = nb
    return out
