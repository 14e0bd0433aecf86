"""kNN fill and denoise of per-point labels (the method's step after the vote).

Fill and denoise (:func:`fill_and_denoise`)
    Fill: each point without votes takes the inverse-distance-weighted vote of its k=100
    nearest *directly labelled* points within ``fill_radius`` (exact, cKDTree over the
    labelled points near unlabelled ones only). The fill does not extrapolate: points with
    none that close stay unlabelled (label 0, origin none, confidence 0; the prefill shows
    them unpainted) -- the default since issue 23. ``fill_far=True`` (opt-in; ``occufly lift
    --far-fill``) restores the earlier default, the method's plain k-NN fill: they take the
    vote of their k=100 nearest labelled points at any distance, at the lowest confidence
    (measured then on ``small`` seed 2 with the 24 stratified frames: 7,174 points stayed
    unlabelled with the 3 m bound alone, point accuracy 0.9739 -> 0.9843, scene-grid
    completion IoU 0.834 -> 0.879 -- with the far fill; bench/bench_calibration.py has the
    coverage / accuracy / prefill figures of both).
    Ties: a point whose top classes have equal votes (typically 1:1 from two views) is filled
    like an unvoted one -- its labelled neighbours decide -- rather than by the taxonomy's tie
    order (``tie_fill``, default on). Measured on ``small`` seed 0, greedy rho 0.99 frames (19),
    union visibility: truth masks accuracy 0.9881 -> 0.9889, mIoU 0.8812 -> 0.8851; degraded
    masks (:mod:`occufly.synthetic.degrade` defaults) 0.9584 -> 0.9595, mIoU 0.7238 -> 0.7429.
    Demoting every point with margin < 1/3 instead lowered the degraded accuracy to 0.9433.
    On ``bench`` (30 greedy frames, union visibility) it is mixed: truth masks 0.9883 ->
    0.9891, mIoU 0.9299 -> 0.9364; degraded masks accuracy 0.9476 -> 0.9392 but mIoU
    0.7559 -> 0.7658 and held-out 2-D agreement 0.9253 -> 0.9287.
    Denoise: every labelled point takes the dominant class of its k=200 nearest labelled points
    (itself included) within ``denoise_radius``, unless its own class holds at least ``denoise_keep_share`` (default
    0.25) of that neighbourhood. The keep rule is our addition: the paper's plain rule
    (``denoise_keep_share=None``) relabels every point, which on the synthetic ``small`` scene
    lowers point accuracy from 0.991 to 0.986 and mIoU from 0.918 to 0.827 (persons, bicycles,
    cables are smaller than 200 points' neighbourhoods); isolated mislabels (own share ~1/k)
    are still relabelled. Second addition, the confirmation rule: a directly labelled point
    whose winning class holds >= ``confirm_views`` (default 2) votes and a vote margin
    >= ``confirm_margin`` (0.5) keeps that class whatever its neighbourhood says -- several
    annotated views agreeing are stronger evidence than the 200 nearest points, which around a
    person are mostly ground. Measured on ``small`` with truth masks (same votes, same run):
    stratified selection, accuracy 0.9809 -> 0.9828, mIoU 0.820 -> 0.900; greedy selection
    0.9884 -> 0.9906, mIoU 0.826 -> 0.922 (persons, bicycles, benches survive the denoise).
    ``confirm_views=None`` turns it off. The fast method certifies whole voxels at once: with
    voxel edge ``v`` near the typical k-NN radius, a point's k nearest neighbours lie in the 3x3x3 voxel block
    around its voxel; if that block holds at least ``k`` points and fewer than k/2 of them
    disagree with the block's dominant class, that class must win the k-NN vote (with the keep
    rule, a point of another class is certified only if the block holds fewer than
    ``keep_share * k`` points of its class). Points of uncertified voxels (class boundaries,
    sparse areas) get their exact k nearest neighbours by brute force over their voxel's
    3x3x3 block (a compiled kernel, :mod:`occufly.lifting.blockknn`); where the k-th neighbour is farther than the block
    reaches, a cKDTree over the surrounding labelled points answers instead. :func:`fill_and_denoise_exact` is the plain
    cKDTree baseline used by tests and the benchmark.

Confidence (float32 in [0, 1])
    A calibrated probability that the label is right (``LiftParams.confidence="calibrated"``,
    :mod:`occufly.lifting.calibration`): a raw evidence score per origin -- direct: the vote
    margin ``(top - second) / votes`` averaged with the denoise share; filled: the IDW share
    of the winning class among the voted neighbours times the denoise share times
    ``1 - d / (2 fill_radius)`` (``d`` the nearest voted neighbour); denoised: the denoise share -- mapped through the per-origin
    isotonic table fitted on synthetic truth (``confidence_calibration.json``). ``"raw"``
    gives the score itself, ``"legacy"`` the earlier confidence (the denoise share, averaged
    with the vote margin for direct labels: ~0.9 for filled labels however far from a vote).
Origin (uint8)
    0 none (no label), 1 direct, 2 filled, 3 denoised (denoising changed the direct/fill label).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass

import numpy as np
from scipy.spatial import cKDTree

from occufly.density import knn_radius as typical_knn_radius
from occufly.fsutil import require_memory
from occufly.lifting import calibration
from occufly.lifting.blockknn import block_sum_sorted, block_votes, voxel_keys
from occufly.lifting.classes import ClassColumns
from occufly.lifting.result import ORIGIN_DENOISED, ORIGIN_DIRECT, ORIGIN_FILLED, LiftResult
from occufly.parallel import single_threaded_blas
from occufly.progress import ProgressFn, noop
from occufly.taxonomy import Taxonomy


@dataclass
class LiftParams:
    """kNN parameters of the fill and denoise passes (all distances in scene metres)."""

    fill_k: int = 100
    fill_radius: float = 3.0
    # points with no directly labelled point within fill_radius: False (the default since
    # issue 23: the fill does not extrapolate) = they stay unlabelled (label 0, origin none,
    # confidence 0); True = the method's plain k-NN fill at any distance (one more pass, the
    # earlier default; opt in with ``occufly lift --far-fill``), at the lowest confidence
    fill_far: bool = False
    denoise_k: int = 200
    denoise_radius: float = 3.0
    method: str = "voxel"  # "voxel" (fast, certified voxels + exact boundaries) or "exact"
    voxel: float | None = None  # voxel edge of the fast method; None = from the point density
    voxel_factor: float = 1.0  # auto voxel = factor * typical denoise k-NN radius
    certify_min_points: float = 1.5  # a block needs >= this * k points to be certified
    # A point keeps its own class if that holds >= this share of its denoise neighbourhood;
    # otherwise it takes the dominant class. None = the paper's rule (always the dominant
    # class), which on the synthetic scenes erases small objects (see the module docstring).
    denoise_keep_share: float | None = 0.25
    # A directly labelled point whose winning class has >= confirm_views votes and a vote
    # margin >= confirm_margin keeps it through the denoise (None = off): agreement of several
    # annotated views is stronger evidence than the spatial neighbourhood (see module docstring).
    confirm_views: int | None = 2
    confirm_margin: float = 0.5
    # A point whose top classes tie (equal votes, e.g. 1:1 from two views) is left to the
    # fill instead of the taxonomy's tie order: its labelled neighbours decide (needs the
    # vote margin/top; see the module docstring for the measurement). False = tie order.
    tie_fill: bool = True
    # Re-decide the voted points before the fill (occufly.lifting.robust): a Dawid-Skene
    # annotator model estimated from the votes plus a per-scene point classifier trained on
    # the unanimous points. False = the plain vote majority (see the robust module docstring
    # and the README for the measurements). robust_params: its RobustParams (None = defaults).
    robust: bool = True
    robust_params: object | None = None
    # issue 37: leave out the votes of frames that paint a class far worse than the other
    # frames seeing the same points (occufly.lifting.reliability; VoteStore.fill_and_denoise)
    reliability: bool = False
    # threads of the k-NN queries and of the boundary brute force (-1 = every core, as in
    # cKDTree); the result does not depend on it
    workers: int = -1
    # what the confidence is: "calibrated" (the default: the probability that the label is
    # right, occufly.lifting.calibration's fitted per-origin map of the raw evidence score),
    # "raw" (that score itself, what the calibration is fitted on) or "legacy" (before issue
    # 23: the denoise share, averaged with the vote margin for direct labels)
    confidence: str = "calibrated"


# ---- memory: up-front estimate ------------------------------------------------------------
# Peak memory of :func:`fill_and_denoise` beyond its inputs, measured with
# ``bench/bench_scale.py`` (crops of the synthetic survey cloud, 90 % voted: 1.03 GB peak RSS
# with the inputs at 4 M points, 3.50 GB at 15 M, i.e. ~225 bytes per point with the inputs;
# tiled ``small``, 30 % voted: 0.83 GB at 4 M, 0.49 GB at 1.1 M): per point (the voxel hash, the per-point class / share / origin arrays, the k-NN
# trees over the labelled points) plus the fixed k-NN query chunks (50,000 queries x k
# neighbours x distances, indices and vote keys), with some margin.
FILL_BYTES_PER_POINT = 200
FILL_FIXED_BYTES = 400 * 2**20


def fill_memory_estimate(n_points: int) -> int:
    """Estimated peak bytes :func:`fill_and_denoise` allocates for ``n_points`` points."""
    return int(FILL_FIXED_BYTES + FILL_BYTES_PER_POINT * int(n_points))


def check_fill_memory(n_points: int) -> dict:
    """Raise :class:`~occufly.errors.OccuflyError` (CLI exit 2, HTTP 4xx) before any work when
    the fill + denoise of ``n_points`` points cannot fit in the memory available now (Linux
    ``MemAvailable``; not checked where that is unknown). Returns the figures."""
    return require_memory(
        fill_memory_estimate(n_points), f"kNN fill + denoise of {n_points:,} points",
        detail=f" ({FILL_BYTES_PER_POINT} bytes per point + {FILL_FIXED_BYTES / 2**30:.1f} GB)",
        hint="nothing was written (free memory, or lift a cropped scene)")


# ---- kNN fill and denoise -----------------------------------------------------------------
def _threads(workers: int) -> int:
    """Thread count for ``workers`` (cKDTree convention: -1 = every core of this machine)."""
    if workers is None or workers < 0:
        try:
            return max(1, len(os.sched_getaffinity(0)))
        except (AttributeError, OSError):
            return max(1, os.cpu_count() or 1)
    return max(1, int(workers))


def check_inputs(xyz: np.ndarray, direct: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be (N, 3), got {xyz.shape}")
    direct = np.asarray(direct)
    if direct.shape != (len(xyz),):
        raise ValueError(f"labels must be ({len(xyz)},), got {direct.shape}")
    return np.ascontiguousarray(xyz, dtype=np.float32), direct.astype(np.uint8, copy=False)


def untie(direct: np.ndarray, vote_margin: np.ndarray | None, vote_top: np.ndarray | None,
           p: LiftParams) -> np.ndarray:
    """``direct`` with tied points (margin 0, some votes) set to 0 when ``p.tie_fill``."""
    if not p.tie_fill or vote_margin is None or vote_top is None:
        return direct
    tied = (np.asarray(vote_margin) <= 0) & (np.asarray(vote_top) > 0) & (direct > 0)
    if not tied.any():
        return direct
    return np.where(tied, np.uint8(0), direct)


def _scores_to_cols(cls: ClassColumns, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, C) scores -> (winner column (n,) int64, -1 = none; winner share (n,) float32)."""
    col, top, _ = cls.majority(scores)
    total = scores.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        share = np.where(total > 0, top / total, 0.0).astype(np.float32)
    return col, share


def knn_vote(tree, tree_cols: np.ndarray, queries: np.ndarray, k: int, radius: float,
              cls: ClassColumns, *, weighted: bool, workers: int = 1, chunk: int = 50_000,
              own: np.ndarray | None = None, keep_share: float | None = None,
              nearest: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Exact k-NN (within ``radius``) vote of ``queries`` against a cKDTree of labelled points.

    tree_cols: (n_tree,) column of each tree point. Returns (column (q,) int64, share (q,)).
    With ``own`` ((q,) columns of the queries) and ``keep_share``, a query keeps its own
    column when that holds at least ``keep_share`` of its neighbourhood. ``nearest``: an
    optional (q,) float32 output, the distance to each query's nearest tree point within
    ``radius`` (inf where none).
    """
    q = len(queries)
    cols = np.full(q, -1, dtype=np.int64)
    share = np.zeros(q, dtype=np.float32)
    n_tree = tree.n
    if nearest is not None:
        nearest[:] = np.inf
    if q == 0 or n_tree == 0:
        return cols, share
    k_eff = min(k, n_tree)
    C = cls.C
    for a in range(0, q, chunk):
        b = min(q, a + chunk)
        d, idx = tree.query(queries[a:b], k=k_eff, distance_upper_bound=radius, workers=workers)
        if k_eff == 1:
            d, idx = d[:, None], idx[:, None]
        if nearest is not None:
            nearest[a:b] = d[:, 0]  # sorted ascending; inf where nothing lies within radius
        ok = idx < n_tree
        rows = np.broadcast_to(np.arange(b - a)[:, None], idx.shape)[ok]
        c = tree_cols[idx[ok]]
        if weighted:
            w = 1.0 / np.maximum(d[ok], 1e-6)
        else:
            w = None
        scores = np.bincount(rows * C + c, weights=w, minlength=(b - a) * C).reshape(b - a, C)
        cols[a:b], share[a:b] = _keep_own(cls, scores, None if own is None else own[a:b],
                                          keep_share)
    return cols, share


def _fill_far(xyz: np.ndarray, dcols: np.ndarray, filled: np.ndarray, share: np.ndarray,
              p: LiftParams, cls: ClassColumns, tree=None, tree_idx: np.ndarray | None = None,
              nearest: np.ndarray | None = None) -> int:
    """Second fill pass (in place; opt-in, ``p.fill_far``): points still without a label after
    the ``fill_radius`` pass take the IDW vote of their ``fill_k`` nearest directly labelled
    points at any distance (``nearest`` (N,) gets their nearest voted distance, beyond the
    radius, so their raw confidence score is 0). Returns how many were filled (0 when
    ``p.fill_far`` is off)."""
    rest = np.flatnonzero(filled < 0)
    if not p.fill_far or not len(rest):
        return 0
    if tree is None:
        tree_idx = np.flatnonzero(dcols >= 0)
        if not len(tree_idx):
            return 0
        tree = cKDTree(xyz[tree_idx])
    near = np.empty(len(rest), np.float32)
    c, s = knn_vote(tree, dcols[tree_idx], xyz[rest], p.fill_k, np.inf, cls, weighted=True,
                     workers=p.workers, nearest=near)
    filled[rest], share[rest] = c, s
    if nearest is not None:
        nearest[rest] = near
    return int(len(rest))


def _keep_own(cls: ClassColumns, scores: np.ndarray, own: np.ndarray | None,
              keep_share: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Winner per row of ``scores``; rows whose own column has >= keep_share keep it."""
    col, share = _scores_to_cols(cls, scores)
    if own is None or keep_share is None:
        return col, share
    total = scores.sum(axis=1)
    ok = own >= 0
    own_sc = np.zeros(len(own), dtype=np.float64)
    own_sc[ok] = scores[np.flatnonzero(ok), own[ok]]
    with np.errstate(divide="ignore", invalid="ignore"):
        own_share = np.where(total > 0, own_sc / total, 0.0)
    keep = ok & (own_share >= keep_share)
    col[keep] = own[keep]
    share[keep] = own_share[keep]
    return col, share


def confirmed(direct: np.ndarray, vote_margin: np.ndarray | None, vote_top: np.ndarray | None,
               p: LiftParams) -> np.ndarray | None:
    """(N,) bool: direct labels confirmed by several views (kept through the denoise), or None."""
    if p.confirm_views is None or vote_margin is None or vote_top is None:
        return None
    return (direct > 0) & (np.asarray(vote_top) >= p.confirm_views) & (
        np.asarray(vote_margin) >= p.confirm_margin)


def lift_result(cls: ClassColumns, direct: np.ndarray, filled_cols: np.ndarray, final_cols: np.ndarray,
            agree: np.ndarray, vote_margin: np.ndarray | None, confirmed: np.ndarray | None = None,
            *, p: LiftParams | None = None, fill_share: np.ndarray | None = None,
            fill_distance: np.ndarray | None = None) -> LiftResult:
    if confirmed is not None and confirmed.any():
        # confirmed points the denoise relabelled get their direct class back; their
        # neighbourhood share is unknown for that class, so their confidence is the vote margin
        reverted = confirmed & (final_cols != cls.col_of[direct])
        final_cols = final_cols.copy()
        final_cols[reverted] = cls.col_of[direct[reverted]]
        agree = np.where(reverted, np.asarray(vote_margin, np.float32), agree)
    labels = cls.labels_of(final_cols)
    filled = cls.labels_of(filled_cols)
    origin = np.zeros(len(labels), dtype=np.uint8)
    has = labels > 0
    is_direct = has & (direct > 0) & (labels == direct)
    is_filled = has & (direct == 0) & (labels == filled)
    origin[has] = ORIGIN_DENOISED
    origin[is_filled] = ORIGIN_FILLED
    origin[is_direct] = ORIGIN_DIRECT
    p = p or LiftParams()
    if p.confidence == "legacy":  # before issue 23 (kept for the calibration benchmark)
        conf = np.where(has, agree, 0.0).astype(np.float32)
        if vote_margin is not None:
            conf[is_direct] = 0.5 * (conf[is_direct] + np.asarray(vote_margin, np.float32)[is_direct])
        return LiftResult(labels=labels, confidence=conf, origin=origin)
    if p.confidence not in ("calibrated", "raw"):
        raise ValueError(f"LiftParams.confidence {p.confidence!r}: expected 'calibrated', "
                         "'raw' or 'legacy'")
    n = len(labels)
    conf = calibration.raw_scores(
        origin, denoise_share=agree, vote_margin=vote_margin,
        fill_share=np.zeros(n, np.float32) if fill_share is None else fill_share,
        fill_distance=np.full(n, np.inf, np.float32) if fill_distance is None else fill_distance,
        fill_radius=p.fill_radius)
    if p.confidence == "calibrated":
        table = calibration.default_table()
        if table is not None:
            conf = table.probability(origin, conf)
    conf[~has] = 0.0
    return LiftResult(labels=labels, confidence=conf.astype(np.float32), origin=origin)


def fill_and_denoise_exact(xyz: np.ndarray, direct: np.ndarray, taxonomy: Taxonomy, *,
                           params: LiftParams | None = None, vote_margin: np.ndarray | None = None,
                           vote_top: np.ndarray | None = None,
                           query_index: np.ndarray | None = None,
                           progress: ProgressFn | None = None) -> LiftResult:
    """Baseline: plain cKDTree k=100 IDW fill then k=200 majority denoise over all points.

    xyz: (N, 3) float32 scene-local metres; direct: (N,) uint8 raw ids (0 = no votes).
    With ``query_index`` ((q,) int) the denoise queries only those points (for timing the
    baseline on a sample); labels of the others are then just the filled labels.
    """
    p = params or LiftParams()
    report = progress or noop
    xyz, direct = check_inputs(xyz, direct)
    check_fill_memory(len(xyz))
    direct = untie(direct, vote_margin, vote_top, p)
    cls = ClassColumns(taxonomy)
    t0 = time.perf_counter()
    dcols = cls.col_of[direct].astype(np.int64)  # -1 where no label
    lab_idx = np.flatnonzero(dcols >= 0)
    un_idx = np.flatnonzero(dcols < 0)
    filled = dcols.copy()
    fill_share = np.zeros(len(xyz), np.float32)
    fill_dist = np.full(len(xyz), np.inf, np.float32)
    if len(un_idx) and len(lab_idx):
        report(0.0, "fill: building tree")
        tree = cKDTree(xyz[lab_idx])
        report(0.1, "fill: querying")
        near = np.empty(len(un_idx), np.float32)
        c, s = knn_vote(tree, dcols[lab_idx], xyz[un_idx], p.fill_k, p.fill_radius, cls,
                         weighted=True, workers=p.workers, nearest=near)
        filled[un_idx], fill_share[un_idx], fill_dist[un_idx] = c, s, near
        _fill_far(xyz, dcols, filled, fill_share, p, cls, tree, lab_idx, nearest=fill_dist)
    t1 = time.perf_counter()
    report(0.3, "denoise: building tree")
    lab2 = np.flatnonzero(filled >= 0)
    final = filled.copy()
    agree = fill_share.copy()
    agree[dcols >= 0] = 1.0
    t_build = 0.0
    if len(lab2):
        tb = time.perf_counter()
        tree2 = cKDTree(xyz[lab2])
        t_build = time.perf_counter() - tb
        q = lab2 if query_index is None else np.intersect1d(np.asarray(query_index), lab2)
        report(0.4, "denoise: querying")
        c, s = knn_vote(tree2, filled[lab2], xyz[q], p.denoise_k, p.denoise_radius, cls,
                         weighted=False, workers=p.workers, own=filled[q],
                         keep_share=p.denoise_keep_share)
        final[q], agree[q] = c, s
    t2 = time.perf_counter()
    res = lift_result(cls, direct, filled, final, agree, vote_margin,
                  confirmed(direct, vote_margin, vote_top, p), p=p, fill_share=fill_share,
                  fill_distance=fill_dist)
    res.stats = {"method": "exact", "fill_seconds": t1 - t0, "denoise_seconds": t2 - t1,
                 "denoise_build_seconds": t_build, "denoise_points": int(len(lab2)),
                 "unlabelled_before_fill": int(len(un_idx))}
    report(1.0, "done")
    return res


# -- voxel hashing helpers
def unique_keys(key: np.ndarray, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(key, return_inverse=True)`` of non-negative keys below ``n_cells``: the same
    (sorted unique keys (V,) int64, inverse (n,) int64). Where the key range is at most a few
    times the number of keys (a frame's cull, a region), a mark per cell and a rank of the
    marked ones replace the sort: O(n + cells) instead of O(n log n), about 5 bytes per cell."""
    n = len(key)
    if n == 0 or n_cells > 4 * n + (1 << 22):
        keys, inverse = np.unique(key, return_inverse=True)
        return keys, inverse.reshape(-1)
    mark = np.zeros(n_cells, np.bool_)
    mark[key] = True
    keys = np.flatnonzero(mark)
    del mark
    rank = np.empty(n_cells, np.int32 if len(keys) < 2**31 else np.int64)
    rank[keys] = np.arange(len(keys), dtype=rank.dtype)
    return keys, rank[key].astype(np.int64)


class VoxelGrid:
    """Sparse voxel hash of a point set: sorted unique keys, per-point voxel index."""

    def __init__(self, xyz: np.ndarray, edge: float, pad: int,
                 origin: np.ndarray | None = None) -> None:
        self.edge = float(edge)
        self.pad = int(pad)
        # origin: the lattice's corner (default the cloud's minimum); a subset of a cloud
        # given the whole cloud's origin gets the same voxels (occufly.lifting.incremental)
        # the lattice and each point's key in compiled passes (voxel_keys: what
        # floor((xyz - mn) / edge) + pad and a row-major key computed with (n, 3) temporaries)
        self.mn, self.dims, key = voxel_keys(xyz, edge, pad, origin)
        if float(np.prod(self.dims.astype(np.float64))) > 2**62:
            raise ValueError("scene too large for the voxel hash at this voxel size")
        self.keys, self.inverse = unique_keys(key, int(np.prod(self.dims)))

    @property
    def n_voxels(self) -> int:
        return len(self.keys)

    def offset_key(self, dx: int, dy: int, dz: int) -> int:
        return int((dx * self.dims[1] + dy) * self.dims[2] + dz)

    def neighbour(self, voxels: np.ndarray, dx: int, dy: int, dz: int) -> np.ndarray:
        """(m,) voxel indices -> (m,) index of the neighbour voxel at the offset, -1 if empty."""
        nk = self.keys[voxels] + self.offset_key(dx, dy, dz)
        pos = np.searchsorted(self.keys, nk)
        pos = np.minimum(pos, len(self.keys) - 1)
        return np.where(self.keys[pos] == nk, pos, -1)

    def block_sum(self, counts: np.ndarray) -> np.ndarray:
        """(V, C) per-voxel counts -> (V, C) sums over each voxel's 3x3x3 block (occupied
        neighbours only), in ``counts``' dtype: the voxel's own counts, then each occupied
        neighbour's added in the order (dx, dy, dz) over -1, 0, 1 -- so float sums are the same
        bit for bit however they are computed. Compiled for float32 / float64 counts (one
        merge walk of the sorted keys per offset, no (V, C) temporaries); numpy otherwise."""
        if counts.ndim == 2 and counts.dtype in (np.float32, np.float64) and len(self.keys):
            offs = np.array([self.offset_key(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1)
                             for dz in (-1, 0, 1) if (dx, dy, dz) != (0, 0, 0)], np.int64)
            out = np.ascontiguousarray(counts).copy()
            block_sum_sorted(np.ascontiguousarray(self.keys, np.int64), offs,
                             np.ascontiguousarray(counts), out)
            return out
        block = counts.copy()
        allv = np.arange(self.n_voxels)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    if dx == dy == dz == 0:
                        continue
                    nb = self.neighbour(allv, dx, dy, dz)
                    ok = nb >= 0
                    block[ok] += counts[nb[ok]]
        return block

    def _cells(self, key: np.ndarray, r: int) -> np.ndarray:
        """Sorted unique lattice keys within Chebyshev distance ``r`` (in voxel steps) of the
        keys ``key``, empty cells included: a separable dilation over the lattice's keys, x
        then y then z. Each step stays inside the lattice where ``r`` <= the pad."""
        if r > self.pad:
            raise ValueError(f"dilation by {r} voxels exceeds the grid's pad of {self.pad}")
        return dilate_keys(key, r, (self.offset_key(1, 0, 0), self.offset_key(0, 1, 0), 1))

    def dilate(self, voxels: np.ndarray, r: int) -> np.ndarray:
        """(m,) voxel indices -> sorted indices of the occupied voxels within Chebyshev distance
        ``r`` (voxel steps) of any of them. The dilation runs over every cell of the lattice,
        empty ones too (stepping through occupied voxels only, as this once did, misses a voxel
        diagonal behind an empty one); about m (2r + 1)^3 keys at worst, so for radii of many
        voxels :meth:`near` is the cheap superset."""
        cells = self._cells(self.keys[np.asarray(voxels, np.int64)], int(r))
        if not len(cells) or not len(self.keys):
            return np.zeros(0, np.int64)
        pos = np.minimum(np.searchsorted(self.keys, cells), len(self.keys) - 1)
        return pos[self.keys[pos] == cells]  # sorted: both key lists are

    def near(self, voxels: np.ndarray, r: int, split: int = 3) -> np.ndarray:
        """(V,) bool: occupied voxels that may lie within Chebyshev distance ``r`` (voxel
        steps) of one of ``voxels`` -- every voxel that does is marked, and some up to about
        r (1 + 1 / split) steps away: blocks of b = ceil(r / split) voxels a side, the blocks
        within ceil(r / b) blocks of each block holding one of ``voxels`` (a voxel r steps
        away is never farther). A k-NN within ``r`` voxel edges of those voxels' points
        against the marked voxels' points finds what it would against every point, at the cost
        of one key per voxel (the exact :meth:`dilate` costs (2r + 1)^3 keys per voxel)."""
        r = max(int(r), 1)
        b = -(-r // max(int(split), 1))
        m = -(-r // b)
        d1, d2 = int(self.dims[1]), int(self.dims[2])
        c0, rest = np.divmod(self.keys, d1 * d2)
        c1, c2 = np.divmod(rest, d2)
        # block coordinates, m blocks of pad around them (so that +-m stays inside)
        b0, b1, b2 = ((c - self.pad) // b + m for c in (c0, c1, c2))
        n1, n2 = int(b1.max()) + m + 1, int(b2.max()) + m + 1
        bkey = (b0 * n1 + b1) * n2 + b2
        hit = dilate_keys(bkey[np.asarray(voxels, np.int64)], m, (n1 * n2, n2, 1))
        pos = np.minimum(np.searchsorted(hit, bkey), len(hit) - 1)
        return hit[pos] == bkey


def dilate_keys(key: np.ndarray, r: int, strides: tuple[int, int, int]) -> np.ndarray:
    """Sorted unique row-major lattice keys within Chebyshev distance ``r`` of ``key``: a
    separable dilation, each axis (``strides``) in turn by -r..r steps."""
    key = np.unique(key)
    if r:
        steps = np.arange(-r, r + 1, dtype=np.int64)
        for stride in strides:
            key = np.unique((key[:, None] + steps[None, :] * stride).ravel())
    return key


def _block_knn(xyz: np.ndarray, cols: np.ndarray, lab_idx: np.ndarray, grid: VoxelGrid,
               todo: np.ndarray, k: int, radius: float, cls: ClassColumns,
               progress: ProgressFn | None = None, keep_share: float | None = None,
               only: np.ndarray | None = None, workers: int = 1
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact k-NN majority for the labelled points of voxels ``todo`` by brute force over
    each voxel's 3x3x3 block of labelled points.

    cols: (N,) column per point (-1 = unlabelled); lab_idx: indices of labelled points.
    Returns (column (N,), share (N,), unsafe (N,) bool) -- filled for the points of ``todo``;
    ``unsafe`` marks points whose k-th neighbour is farther than the block reaches (they need
    a query against a larger neighbourhood). ``workers`` threads share the voxels (same result).
    """
    n = len(xyz)
    out_c = np.full(n, -1, dtype=np.int64)
    out_s = np.zeros(n, dtype=np.float32)
    unsafe = np.zeros(n, dtype=bool)
    vox = grid.inverse
    V = grid.n_voxels
    C = cls.C
    order = lab_idx[np.argsort(vox[lab_idx], kind="stable")]
    vs = vox[order]
    starts = np.searchsorted(vs, np.arange(V))
    ends = np.searchsorted(vs, np.arange(V), side="right")
    offs = [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)]
    nb = np.stack([grid.neighbour(todo, *o) for o in offs], axis=1)  # (T, 27)
    e = grid.edge
    r2 = radius * radius
    report = progress or noop
    xyz32 = np.ascontiguousarray(xyz, dtype=np.float32).view()
    xyz32.flags.writeable = False  # one compiled signature whether or not xyz is a file map
    cols64 = np.ascontiguousarray(cols, dtype=np.int64)
    only_arr = np.zeros(1, bool) if only is None else np.ascontiguousarray(only, dtype=bool)

    def run(a: int, b: int) -> int:
        # the compiled kernel (no GIL) counts the k nearest per class; numpy decides
        q, votes, kth, full = block_votes(xyz32, cols64, order, starts, ends, todo[a:b],
                                          np.ascontiguousarray(nb[a:b]), only_arr,
                                          only is not None, int(k), float(r2), int(C))
        if not len(q):
            return b - a
        c, s = _keep_own(cls, votes, cols[q], keep_share)
        out_c[q], out_s[q] = c, s
        # safe if the k-th neighbour (or the radius) is within the block around the point
        xq = xyz[q]
        lo = np.floor((xq - grid.mn) / e) * e + grid.mn  # own voxel's low corner
        frac = np.minimum(xq - lo, lo + e - xq).min(axis=1)
        border = e + np.maximum(frac, 0.0)
        reach = np.where(full, np.sqrt(np.maximum(kth, 0.0)), np.inf)
        unsafe[q] = ~((reach <= border * 0.999) | (radius <= border * 0.999))
        return b - a

    # voxels write disjoint points: threads (the kernel runs without the GIL) give the same
    # result as one loop; one BLAS thread each for the small numpy steps (a BLAS thread pool
    # costs more than they do, see occufly.parallel.single_threaded_blas)

    T = len(todo)
    step = max(1, min(2000, -(-T // 50)))
    n_threads = _threads(workers)
    report(0.0, "denoise: exact k-NN at boundaries")
    with single_threaded_blas():
        if n_threads <= 1 or T < 2 * step:
            for a in range(0, T, step):
                run(a, min(T, a + step))
                report(min(T, a + step) / max(T, 1), "denoise: exact k-NN at boundaries")
        else:
            from concurrent.futures import ThreadPoolExecutor, as_completed

            done = 0
            with ThreadPoolExecutor(n_threads) as ex:
                futs = [ex.submit(run, a, min(T, a + step)) for a in range(0, T, step)]
                for f in as_completed(futs):
                    done += f.result()
                    report(done / T, "denoise: exact k-NN at boundaries")
    report(1.0, "denoise: exact k-NN at boundaries")
    return out_c, out_s, unsafe


def fill_and_denoise(xyz: np.ndarray, direct: np.ndarray, taxonomy: Taxonomy, *,
                     params: LiftParams | None = None, vote_margin: np.ndarray | None = None,
                     vote_top: np.ndarray | None = None,
                     progress: ProgressFn | None = None, grid_origin: np.ndarray | None = None,
                     keep: dict | None = None) -> LiftResult:
    """kNN fill (k=100, IDW, bounded radius) then kNN denoise (k=200) of per-point labels.

    xyz: (N, 3) float32 scene-local metres; direct: (N,) uint8 raw ids of the vote majority
    (0 = no votes); vote_margin: (N,) float32 optional, enters the confidence of direct points.
    See the module docstring for the certified-voxel method; ``params.method == "exact"``
    runs :func:`fill_and_denoise_exact`.

    grid_origin: the voxel lattice's corner (default ``xyz.min(0)``; with ``params.voxel``
    set too, a subset of a cloud gets the voxels of the whole cloud). keep: a dict that
    receives the per-point intermediates before the confidence step (``direct`` untied,
    ``filled``, ``final`` columns, ``agree``, ``fill_share``, ``fill_distance``) and the
    lattice (``edge``, ``origin``) -- what :mod:`occufly.lifting.incremental` updates.
    """
    p = params or LiftParams()
    if p.method == "exact":
        return fill_and_denoise_exact(xyz, direct, taxonomy, params=p, vote_margin=vote_margin,
                                      vote_top=vote_top,
                                      progress=progress)
    if p.method != "voxel":
        raise ValueError(f"unknown lifting method {p.method!r}; expected 'voxel' or 'exact'")
    report = progress or noop
    xyz, direct = check_inputs(xyz, direct)
    stats_mem = check_fill_memory(len(xyz))
    direct = untie(direct, vote_margin, vote_top, p)
    cls = ClassColumns(taxonomy)
    n = len(xyz)
    t0 = time.perf_counter()
    stats: dict = {"method": "voxel", "memory_estimate_bytes": stats_mem["memory_bytes"]}
    dcols = cls.col_of[direct].astype(np.int64)
    if n == 0 or not (dcols >= 0).any():
        res = lift_result(cls, direct, dcols, dcols, np.zeros(n, np.float32), vote_margin, p=p)
        res.stats = {**stats, "note": "no labelled points"}
        if keep is not None:
            keep.update(direct=direct, filled=dcols, final=dcols.copy(),
                        agree=np.zeros(n, np.float32), fill_share=np.zeros(n, np.float32),
                        fill_distance=np.full(n, np.inf, np.float32), edge=None, origin=None)
        return res

    # voxel edge: about the typical k-NN radius of the denoise pass
    report(0.0, "voxel size")
    edge = p.voxel or p.voxel_factor * typical_knn_radius(xyz, p.denoise_k)
    edge = float(min(max(edge, 1e-3), max(p.denoise_radius, p.fill_radius)))
    stats["voxel"] = edge
    report(0.05, "voxel hash")
    fill_r = int(math.ceil(p.fill_radius / edge))
    grid = VoxelGrid(xyz, edge, pad=max(fill_r, 1) + 1, origin=grid_origin)
    stats["grid_origin"] = [float(v) for v in grid.mn]
    stats["voxels"] = int(grid.n_voxels)

    filled, agree, fill_dist = _fill(xyz, dcols, grid, p, cls, stats, report)
    fill_share = agree.copy()  # the fill's IDW share (the denoise overwrites agree)
    t_den = time.perf_counter()
    final, agree = _denoise(xyz, filled, agree, grid, p, cls, stats, report)
    stats["denoise_seconds"] = time.perf_counter() - t_den
    if keep is not None:
        keep.update(direct=direct, filled=filled, final=final, agree=agree.copy(),
                    fill_share=fill_share, fill_distance=fill_dist, edge=edge, origin=grid.mn)
    res = lift_result(cls, direct, filled, final, agree, vote_margin,
                  confirmed(direct, vote_margin, vote_top, p), p=p, fill_share=fill_share,
                  fill_distance=fill_dist)
    stats["seconds"] = time.perf_counter() - t0
    res.stats = stats
    report(1.0, "done")
    return res


def _fill(xyz: np.ndarray, dcols: np.ndarray, grid: VoxelGrid, p: LiftParams, cls: ClassColumns,
          stats: dict, report: ProgressFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fill: exact IDW k-NN for points without votes (``dcols`` < 0), a tree over the
    labelled points near them. Returns (N,) int64 ``filled`` columns (-1: none), (N,) float32
    ``agree`` (1 for voted points, the IDW share for filled ones) and (N,) float32 distance to
    the nearest voted point (inf: none)."""
    n, vox = len(xyz), grid.inverse
    fill_r = int(math.ceil(p.fill_radius / grid.edge))
    filled = dcols.copy()
    agree = np.zeros(n, np.float32)
    agree[dcols >= 0] = 1.0
    fill_dist = np.full(n, np.inf, np.float32)  # nearest voted point of each filled point
    un_idx = np.flatnonzero(dcols < 0)
    t_fill = time.perf_counter()
    if len(un_idx):
        report(0.1, "fill")
        in_near = grid.near(np.unique(vox[un_idx]), fill_r)
        src = np.flatnonzero((dcols >= 0) & in_near[vox])
        if len(src):
            tree = cKDTree(xyz[src])
            near = np.empty(len(un_idx), np.float32)
            c, s = knn_vote(tree, dcols[src], xyz[un_idx], p.fill_k, p.fill_radius, cls,
                             weighted=True, workers=p.workers, nearest=near)
            filled[un_idx], agree[un_idx], fill_dist[un_idx] = c, s, near
        stats["fill_tree_points"] = int(len(src))
        stats["filled_far"] = _fill_far(xyz, dcols, filled, agree, p, cls, nearest=fill_dist)
        stats["unlabelled_after_fill"] = int((filled < 0).sum())
    stats["unlabelled_before_fill"] = int(len(un_idx))
    stats["fill_seconds"] = time.perf_counter() - t_fill
    return filled, agree, fill_dist


def _denoise(xyz: np.ndarray, filled: np.ndarray, agree: np.ndarray, grid: VoxelGrid,
             p: LiftParams, cls: ClassColumns, stats: dict, report: ProgressFn
             ) -> tuple[np.ndarray, np.ndarray]:
    """The denoise: voxels whose 3x3x3 block certifies the majority of any point's k
    neighbours take it at once; exact k-NN elsewhere (:func:`_denoise_boundaries`). Returns
    the (N,) ``final`` columns and ``agree`` (updated in place)."""
    C, V, vox = cls.C, grid.n_voxels, grid.inverse
    report(0.3, "denoise: voxel histograms")
    lab = filled >= 0
    lab_idx = np.flatnonzero(lab)
    counts = np.bincount(vox[lab_idx] * C + filled[lab_idx], minlength=V * C)
    counts = counts.reshape(V, C).astype(np.int32)
    block = grid.block_sum(counts)
    bcol, btop, _ = cls.majority(block)
    btotal = block.sum(axis=1)
    k = p.denoise_k
    certified = (btotal >= p.certify_min_points * k) & ((btotal - btop) * 2 < k) & (bcol >= 0)
    final = filled.copy()
    cert_pts = lab & certified[vox]
    if p.denoise_keep_share is not None:
        # a point whose own class differs from the block's winner keeps it if it may hold
        # keep_share of its k neighbours: the block count of that class bounds it from above
        own = np.maximum(filled, 0)
        maybe_keep = cert_pts & (filled != bcol[vox]) & (
            block[vox, own] >= p.denoise_keep_share * k)
        cert_pts &= ~maybe_keep
    final[cert_pts] = bcol[vox[cert_pts]]
    with np.errstate(divide="ignore", invalid="ignore"):
        bshare = np.where(btotal > 0, btop / np.maximum(btotal, 1), 0.0).astype(np.float32)
    agree[cert_pts] = bshare[vox[cert_pts]]
    need = lab & ~cert_pts
    rest = np.flatnonzero(need)
    stats["certified_voxels"] = int(certified.sum())
    stats["block_denoise_points"] = int(len(rest))
    if len(rest):
        _denoise_boundaries(xyz, filled, lab, lab_idx, need, rest, final, agree, grid, p, cls,
                            stats, report)
    return final, agree


def _denoise_boundaries(xyz: np.ndarray, filled: np.ndarray, lab: np.ndarray,
                        lab_idx: np.ndarray, need: np.ndarray, rest: np.ndarray,
                        final: np.ndarray, agree: np.ndarray, grid: VoxelGrid, p: LiftParams,
                        cls: ClassColumns, stats: dict, report: ProgressFn) -> None:
    """Exact k-NN denoise of the points ``rest`` no certified voxel decides, written into
    ``final`` / ``agree``: brute force per 3x3x3 block, then coarser blocks, then a cKDTree."""
    k, edge, vox = p.denoise_k, grid.edge, grid.inverse
    report(0.5, "denoise: exact k-NN at boundaries")
    todo = np.unique(vox[rest])
    c, s, unsafe = _block_knn(xyz, filled, lab_idx, grid, todo, k, p.denoise_radius, cls,
                              progress=lambda f, m: report(0.5 + 0.4 * f, m),
                              keep_share=p.denoise_keep_share, only=need, workers=p.workers)
    final[rest], agree[rest] = c[rest], s[rest]
    # points whose k-th neighbour could lie outside their 3x3x3 block (sparse areas):
    # the same brute force on a coarser grid, then a cKDTree for what is still unsafe
    # (edge 2.5 v, then the denoise radius itself, where every point is safe)
    stats["coarse_denoise_points"] = int(unsafe.sum())
    for level, coarse_edge in enumerate((2.5 * edge, p.denoise_radius)):
        if not unsafe.any() or coarse_edge <= edge:
            continue
        if level == 0 and coarse_edge >= p.denoise_radius:
            continue
        coarse = VoxelGrid(xyz, coarse_edge, pad=2, origin=grid.mn)
        todo2 = np.unique(coarse.inverse[unsafe])
        c2, s2, unsafe2 = _block_knn(xyz, filled, lab_idx, coarse, todo2, k,
                                     p.denoise_radius, cls, keep_share=p.denoise_keep_share,
                                     only=unsafe, workers=p.workers)
        sel2 = np.flatnonzero(unsafe)
        final[sel2], agree[sel2] = c2[sel2], s2[sel2]
        unsafe = unsafe2
        stats[f"coarse{level + 2}_unsafe_points"] = int(unsafe.sum())
    tree_q = np.flatnonzero(unsafe)
    stats["tree_denoise_points"] = int(len(tree_q))
    if len(tree_q):
        r = int(math.ceil(p.denoise_radius / edge))
        in_near = grid.near(np.unique(vox[tree_q]), r)
        src = np.flatnonzero(lab & in_near[vox])
        tree = cKDTree(xyz[src])
        c2, s2 = knn_vote(tree, filled[src], xyz[tree_q], k, p.denoise_radius, cls,
                           weighted=False, workers=p.workers, own=filled[tree_q],
                           keep_share=p.denoise_keep_share)
        final[tree_q], agree[tree_q] = c2, s2


def params_dict(p: LiftParams) -> dict:
    return asdict(p)
