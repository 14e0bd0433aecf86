"""Region consistency: a painted region the other views contradict as a whole (issue 37, sixth round).

Annotators give a class to a region at a time -- a polygon, a flood fill, a brush stroke over a
parking lot -- so their costliest errors are whole regions painted as a look-alike: a parking
lot painted road, a roof painted building, a grass field painted vegetation. Where only that
view sees part of the region no vote outnumbers it, and where one other view sees it the vote
is a 1:1 tie. But the region as a whole is seen by other views, and they say what it is.

:func:`region_votes` finds those regions in the votes every frame cast (the per-frame vote
files), after a first robust decision:

* A frame's *regions* are the connected sets of its votes for one class on a raster of its
  image (``RegionParams.cells`` cells along the longer side; 8-connected), the way the mask
  painted them (where no point projects, the raster has a hole, which splits nothing that
  touches across it diagonally).
* The other frames' votes on a region's points are counted. The region is contradicted when at
  least ``min_support`` of them fall on it, below ``agree_max`` of them for its class ``a``
  and at least ``top_share`` for one other class ``b``;
* and at least ``min_views`` independent annotators say ``b``: each of another annotator than
  the frame's (``annotators``: frame -> who painted it; without them every frame is an
  annotator of its own), with at least ``view_votes`` votes for ``b`` on the region and ``b``
  at least half of its votes there. A sloppy painter's several frames count once, and a view
  that only touches the region's rim does not count;
* and the first decision's annotator matrix says that true ``b`` is voted ``a`` at least
  ``guard`` of the time (``pi[b, a]``): only a confusion the votes themselves show is undone.
  A skipped person, voted as the ground around it, is never painted away, since true ground
  is almost never voted person; with exact masks no pair passes.

The contradicted regions' votes are counted for ``b``, and every voted point is decided again
with the first decision's matrix (:func:`occufly.lifting.robust.redecide` with
``confusion_matrix``; no EM and no refit rounds: refitted on the corrected votes, the matrix
learns that look-alikes are rarely confused and then trusts the confusions left -- measured in
docs/lifting.md, sixth round).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import ndimage

from occufly.lifting.confusion import annotator_index, point_order

_EIGHT = np.ones((3, 3), bool)


@dataclass
class RegionParams:
    """Thresholds of :func:`region_votes` (written down in docs/lifting.md, sixth round)."""

    cells: int = 160          # raster cells along the image's longer side (regions)
    agree_max: float = 0.25   # the region's class below this share of the other views' votes
    top_share: float = 0.6    # ... and one other class at least this share
    min_support: int = 20     # other views' votes on the region
    min_views: int = 2        # independent annotators that contradict it
    view_votes: int = 5       # a contradicting annotator's least votes for that class there
    guard: float = 0.15       # least pi[b, a] (true b voted a) of the first decision's matrix
    # the second decision's annotator matrix: "first" (the first decision's, no EM and no
    # refit) or "refit" (fitted again on the corrected votes, as a first decision is)
    matrix: str = "first"


def frame_regions(scene, frame_index: int, pids: np.ndarray, cols: np.ndarray,  # noqa: ANN001
                  cells: int) -> tuple[np.ndarray, int]:
    """(n,) int32 region of each vote of a frame (1-based) and the number of regions: the
    8-connected sets of its votes for one class on a raster of ``cells`` cells along the
    image's longer side (fewer where the frame has under about two votes per cell)."""
    n = len(pids)
    region = np.zeros(n, np.int32)
    if n == 0:
        return region, 0
    uv = _vote_pixels(scene, frame_index, pids)
    cam = scene.frames[frame_index].camera
    # no finer than about two votes per cell on average: a sparser raster has holes between
    # neighbouring points and splits every region into single points
    aspect = max(cam.width, cam.height) / min(cam.width, cam.height)
    cells = max(4, min(int(cells), int(np.sqrt(n * aspect / 2.0))))
    cell = max(cam.width, cam.height) / float(cells)
    gw, gh = int(np.ceil(cam.width / cell)), int(np.ceil(cam.height / cell))
    fin = np.isfinite(uv).all(axis=1)
    c = np.clip(np.floor(np.where(fin, uv[:, 0], 0) / cell).astype(np.int64), 0, gw - 1)
    r = np.clip(np.floor(np.where(fin, uv[:, 1], 0) / cell).astype(np.int64), 0, gh - 1)
    total = 0
    for col in np.unique(cols):
        sel = np.flatnonzero(cols == col)
        occ = np.zeros((gh, gw), bool)
        occ[r[sel], c[sel]] = True
        lab, k = ndimage.label(occ, structure=_EIGHT)
        region[sel] = lab[r[sel], c[sel]] + total
        total += k
    region[~fin] = 0
    return region, total


def _vote_pixels(scene, frame_index: int, pids: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """(n, 2) float32 pixels of the points ``pids`` a frame voted on."""
    vis = scene.visibility
    xyz = vis.projected_on_demand() if hasattr(vis, "projected_on_demand") else None
    if xyz is not None:  # uv not stored: project only the voted points, as frame() would
        ids = vis.frame_ids(frame_index)
        if len(pids) and (pids[-1] > ids[-1] if len(ids) else True):
            raise ValueError(f"frame {frame_index}: votes on points the frame does not see")
        return vis.project(frame_index, pids)[0]
    vis_ids, uv, _ = vis.frame(frame_index)
    vis_ids = np.asarray(vis_ids)
    pos = np.minimum(np.searchsorted(vis_ids, pids), len(vis_ids) - 1)
    if not np.array_equal(vis_ids[pos], pids):  # a frame's point ids are stored ascending
        order = np.argsort(vis_ids, kind="stable")
        pos = order[np.minimum(np.searchsorted(vis_ids, pids, sorter=order), len(order) - 1)]
        if not np.array_equal(vis_ids[pos], pids):
            raise ValueError(f"frame {frame_index}: votes on points the frame does not see")
    return np.asarray(uv)[pos]


@numba.njit(cache=True, nogil=True)
def _other_votes(pids, region, indptr, t_frame, t_col, f, n_regions, C):  # noqa: ANN001, ANN202
    """(n_regions + 1, C) the other frames' votes on each region's points."""
    tot = np.zeros((n_regions + 1, C), np.int64)
    for i in range(len(pids)):
        k = region[i]
        if k == 0:
            continue
        p = pids[i]
        for e in range(indptr[p], indptr[p + 1]):
            if t_frame[e] != f:
                tot[k, t_col[e]] += 1
    return tot


@numba.njit(cache=True, nogil=True)
def _annotator_votes(pids, region, indptr, t_frame, t_ann, t_col, f, a_f, top, n_regions,  # noqa: ANN001, ANN202
                     A):
    """(n_regions + 1, A) votes of each other annotator on each region, and those for the
    region's ``top`` class."""
    all_ = np.zeros((n_regions + 1, A), np.int32)
    for_top = np.zeros((n_regions + 1, A), np.int32)
    for i in range(len(pids)):
        k = region[i]
        if k == 0:
            continue
        p = pids[i]
        for e in range(indptr[p], indptr[p + 1]):
            a = t_ann[e]
            if t_frame[e] == f or a == a_f:
                continue
            all_[k, a] += 1
            if t_col[e] == top[k]:
                for_top[k, a] += 1
    return all_, for_top


def _table(frames: dict[int, tuple], n_points: int, annotators: dict | None):  # noqa: ANN202
    """Every vote sorted by point: the frames in slot order, each slot's annotator index, the
    number of annotators, indptr (N + 1,), and per vote its frame slot, annotator and column."""
    keys = sorted(frames)
    ann_of, names = annotator_index(keys, annotators)
    sizes = [len(frames[f][0]) for f in keys]
    order, indptr = point_order(np.concatenate([np.asarray(frames[f][0], np.int32) for f in keys]),
                                n_points)
    col = np.concatenate([np.asarray(frames[f][1], np.int16) for f in keys])[order]
    slot = np.repeat(np.arange(len(keys), dtype=np.int16 if len(keys) < 1 << 15 else np.int32),
                     sizes)[order]
    ann = np.asarray(ann_of, np.int32)
    return keys, ann, len(names), indptr, slot, ann[slot], col


def region_votes(scene, frames: dict[int, tuple], pi: np.ndarray, *,  # noqa: ANN001
                 annotators: dict | None = None, params: RegionParams | None = None
                 ) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """The votes with every contradicted region counted for the class the others say.

    ``frames``: frame -> (point ids, class columns[, weights]) as stored per frame; ``pi``:
    (C, C) the first decision's annotator matrix (rows: true class, columns: voted).
    Returns None when no region is contradicted, else (point ids whose votes changed (n,)
    int64 ascending, their new (n, C) int32 vote counts, stats: ``regions`` -- frame, from,
    to (class columns), votes, agreement, annotators -- and ``votes_changed``)."""
    p = params or RegionParams()
    pi = np.asarray(pi, np.float64)
    C = pi.shape[0]
    frames = {int(f): v for f, v in frames.items() if len(v[0])}
    if len(frames) < 2:
        return None
    keys, ann_of, A, indptr, t_frame, t_ann, t_col = _table(frames, scene.n_points, annotators)
    moved: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # point, old column, new column
    found: list[dict] = []
    for s, f in enumerate(keys):
        pids = np.asarray(frames[f][0], np.int64)
        cols = np.asarray(frames[f][1], np.int64)
        region, nr = frame_regions(scene, f, pids, cols, p.cells)
        if nr == 0:
            continue
        tot = _other_votes(pids, region, indptr, t_frame, t_col, s, nr, C)
        own = np.zeros(nr + 1, np.int64)
        own[region] = cols
        n_other = tot.sum(axis=1)
        rows = np.arange(nr + 1)
        top = np.argmax(tot, axis=1)
        agree = tot[rows, own] / np.maximum(n_other, 1)
        share = tot[rows, top] / np.maximum(n_other, 1)
        cand = ((n_other >= p.min_support) & (agree < p.agree_max) & (share >= p.top_share)
                & (top != own) & (pi[top, own] >= p.guard))
        cand[0] = False
        if not cand.any():
            continue
        all_, for_top = _annotator_votes(pids, region, indptr, t_frame, t_ann, t_col, s,
                                         int(ann_of[s]), top.astype(np.int64), nr, A)
        views = ((for_top >= p.view_votes) & (2 * for_top >= all_)).sum(axis=1)
        flip = cand & (views >= p.min_views)
        if not flip.any():
            continue
        hit = flip[region]
        moved.append((pids[hit], cols[hit], top[region[hit]]))
        nvotes = np.bincount(region[hit], minlength=nr + 1)
        for k in np.flatnonzero(flip):
            found.append({"frame": int(f), "from": int(own[k]), "to": int(top[k]),
                          "votes": int(nvotes[k]), "agreement": round(float(agree[k]), 3),
                          "annotators": int(views[k])})
    if not found:
        return None
    pt, old_col, new_col = (np.concatenate(a) for a in zip(*moved, strict=True))
    # the points whose counts change: all of their votes, then the moved ones moved
    pts = np.unique(pt)
    lo, hi = indptr[pts], indptr[pts + 1]
    lens = hi - lo
    ent = np.repeat(lo - (np.cumsum(lens) - lens), lens) + np.arange(int(lens.sum()))
    row = np.repeat(np.arange(len(pts)), lens)
    counts = np.zeros((len(pts), C), np.int32)
    np.add.at(counts, (row, t_col[ent].astype(np.int64)), 1)
    at = np.searchsorted(pts, pt)
    np.add.at(counts, (at, old_col), -1)
    np.add.at(counts, (at, new_col), 1)
    return pts, counts, {"regions": found, "votes_changed": int(len(pt))}
