"""Robust vote decision: imperfect annotators, the points' own evidence.

With two or three annotated views per point, the plain majority cannot tell a confused view
from a correct one: a region one annotator painted as its look-alike (road / parking lot,
grass / low vegetation, building / roof) is a 1:1 tie or, where only that view sees it, a
unanimous wrong vote; a small object skipped in one view ties with the ground around it.
This stage re-decides every voted point from two kinds of evidence, before the kNN fill and
denoise (:func:`redecide`, on by default through ``LiftParams.robust``):

Annotator model (Dawid-Skene, pooled over the frames)
    ``pi[t, c]``: the probability that a view of a point of true class ``t`` votes ``c``,
    estimated by EM from the votes alone (over the histogram of vote patterns of all voted
    points, a Dirichlet prior that favours the diagonal). It learns which classes people confuse and that confusions are
    asymmetric (a skipped person is voted ground; ground is almost never voted person).
    Per point the votes give ``log L(t) = sum_c n_c log pi[t, c]`` over its two leading
    vote classes (:class:`~occufly.lifting.votes.VoteSnapshot` keeps them).
Point classifier (per scene, trained on the votes)
    A quadratic discriminant (one Gaussian per class, full covariance) over per-point
    features that do not depend on any label (:func:`point_features`): the point's colour
    and its voxel's mean colour, height above a morphological ground estimate, and the
    voxel's normal verticality, surface variation and linearity. It is trained on the points
    whose votes are unanimous from at least two views (at most ``train_per_class`` per class,
    seeded); a class with fewer than ``min_train`` such points gets a neutral likelihood (one
    Gaussian over all training points), so the votes alone decide it.
Decision
    ``argmax_t  log L(t) + log p(x | t) + prior_weight * log prior_i(t)`` over the candidate
    classes of each point (the ``candidates`` classes the votes and the prior make likeliest,
    those within ``candidate_nats`` of the best; the classifier is evaluated on those only). The output replaces the vote majority
    (direct labels, a margin = posterior top - second that feeds the confirmation rule and the
    confidence, the winner's votes) and the fill and denoise run on it unchanged.

Refit (issue 37, fifth round; ``RobustParams.refit_rounds``, 2 by default)
    The EM's soft posteriors hand a rare look-alike class the mixed points of the regions one
    view painted as it: on degraded masks ``pi[vegetation, grass]`` came out 0.56-0.58 where
    the votes against the truth count 0.13-0.17, and correct grass majorities were then
    decided vegetation (1.4-1.6 % of all points on three of four scenes). After the decision
    the matrix is counted again from the decided labels (:func:`refit_confusion`: each point's
    two leading vote classes against its decided class, only where a view voted that class,
    the same Dirichlet prior) and the points are decided again, twice. The decided labels
    carry the classifier's and the neighbourhood's evidence, which the EM's posteriors did not.
    Measured in docs/lifting.md (fifth round): degraded masks +0.16 to +0.59 accuracy points
    on four scenes, exact masks within 0.02 accuracy and 0.04 mIoU points. The stats carry
    the matrix decided with (``robust_matrix``); the review's leave-one-out labels decide with
    the one the last fill stored (:mod:`occufly.lifting.loo`) instead of refitting: two more
    passes per open took a 20 MP first open over 1 s.

Region consistency (issue 37, sixth round; ``RobustParams.regions``, off by default)
    :mod:`occufly.lifting.regions`: a frame's painted region (the connected votes of one class
    on a raster of its image) that the other views contradict as a whole -- at least two
    independent annotators, and a confusion this decision's matrix shows -- is counted as they
    say, and every voted point is decided again with this decision's matrix. Measured in
    docs/lifting.md: exact masks unchanged on four scenes, degraded masks +0.12 to +0.76
    accuracy points; with a sloppy painter among good ones it needs who painted which frame
    (``annotators``), or his frames outvote the others.

Per-annotator confusion (issue 37, fourth round; ``RobustParams.confusion``, off by default)
    :mod:`occufly.lifting.confusion` fits one matrix per annotator (each frame, or its author
    when the caller names it) from every frame's votes; the decision then runs again with each
    point's vote log-likelihood from those matrices. Measured in docs/lifting.md: large gains
    with a systematically sloppy annotator, but exact masks lose 0.3-0.6 mIoU points (rare
    classes under per-frame matrices), so not the default.

Tiny objects (persons, bicycles, ground obstacles: blobs of about 10 mask pixels that an
annotator paints a few pixels off, onto the ground beside them, or skips)
    Three additions keep them; each was measured on its own (README):

    * *Neighbourhood prior* (:func:`local_votes`). For the classes a point's own views did not
      vote for, ``prior_i`` is the vote share of its 3x3x3 neighbourhood of ``local_voxel``
      voxels (mixed with ``local_mix`` of the scene-wide share): a person point whose views
      all voted the walkway beside it still has person votes around it, and its height above
      the ground decides. The classes it was voted keep the scene-wide share (a region
      painted as its look-alike has an equally confused neighbourhood).
    * *Majority training of rare classes.* A class with fewer than ``min_strong`` unanimous
      points (under degraded masks: 3 to 14 for the tiny classes of ``small``) is also
      trained on its majority points, trimmed of those a well-trained class's Gaussian
      explains better (the ground a shifted blob covered); a fit that would take more than
      ``max_steal`` of a well-trained class's own training points is a look-alike, not a
      tiny object, and keeps to its unanimous points.
    * *Confirmation by the posterior.* The fill's denoise (k = 200, keep share 0.25) erases
      any object of fewer than about 50 points unless the confirmation rule protects it,
      and with one vote per point from two or three views it rarely did. A robust decision
      with posterior margin >= ``LiftParams.confirm_margin`` is confirmed from one view
      (``confirm_views``) when a view of the point, or ``confirm_local_share`` of its
      neighbourhood's votes, voted that class (a class chosen by the features alone, far
      from any vote for it, is left to the denoise: on ``bench`` with exact masks about 5,000
      false bicycle and 3,700 false ground obstacle points).

No synthetic truth enters anywhere. The features depend only on the cloud and are cached in
``ws/lifting/features.npy`` (float16, with ``features.json`` naming the point count and a
checksum); everything that scales with points is chunked (``chunk`` points at a time), so
memory is bounded by the feature cache plus a few arrays of one byte to four per point.

Measured (bench/bench_lifting.py --robustness --robust-modes plain,robust: greedy rho 0.99
frames, union visibility, degrade.py defaults; accuracy / mIoU, plain vote -> robust):
small (19 frames) exact 0.9889 / 0.8851 -> 0.9912 / 0.9118, degraded 0.9595 / 0.7429 ->
0.9701 / 0.7952; bench (30 frames) exact 0.9891 / 0.9364 -> 0.9894 / 0.9359, degraded
0.9392 / 0.7658 -> 0.9644 / 0.8437. With the tiny-object additions: small exact 0.9921 /
0.9467, degraded 0.9724 / 0.8492; bench exact 0.9891 / 0.9390, degraded 0.9638 / 0.8642.
The README's "Lifting with imperfect annotators" has the held-out agreement, the cost and
what was tried.
"""

from __future__ import annotations

import hashlib
import json
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from scipy import ndimage

from occufly.lifting.classes import ClassColumns
from occufly.lifting.knn import VoxelGrid, dilate_keys
from occufly.progress import ProgressFn, noop

FEATURES_VERSION = 1
FEATURE_NAMES = ("r", "g", "b", "voxel_r", "voxel_g", "voxel_b", "log_height_above_ground",
                 "normal_verticality", "surface_variation", "linearity")


@dataclass
class RobustParams:
    """Parameters of :func:`redecide` (distances in scene metres)."""

    voxel: float = 0.6           # edge of the voxels whose covariance / mean colour are features
    ground_cell: float = 1.0     # cell of the ground grid (per-cell lowest point)
    ground_radius: float = 10.0  # morphological opening radius: objects narrower than ~2x this
    em_iterations: int = 10
    em_sample: int = 300_000     # sampled points, only when vote counts are beyond the histogram
    diag_prior: float = 20.0     # Dirichlet pseudo-votes on pi's diagonal (per class)
    off_prior: float = 0.05      # ... on every entry
    train_per_class: int = 20_000
    min_train: int = 20          # fewer training points: the class gets a neutral likelihood
    cov_reg: float = 1e-3
    prior: str = "vote"          # class prior: "vote" (majority shares), "train" or "em"
    prior_weight: float = 1.0    # weight of the log class prior (1 = Bayes; < 1 favours rare classes)
    candidates: int = 3          # classes per point the classifier weighs (the likeliest by votes)
    candidate_nats: float = 12.0
    # local prior of the classes a point's views did not vote for: the vote shares of its
    # neighbourhood (3x3x3 voxels of this edge; 0 = the scene-wide shares for every class),
    # mixed with the scene-wide shares by local_mix
    local_voxel: float = 0.5
    local_mix: float = 0.1       # weight of the scene-wide shares in the local prior
    # classes with fewer unanimous (>= 2 views) points than this are trained on their
    # majority points too, trimmed of those a well-trained class explains better
    min_strong: int = 200
    trim_iterations: int = 2
    # ... unless that Gaussian beats a well-trained class's own on more than this share of
    # that class's training points (a confused look-alike, not a tiny object): then the
    # class keeps to its unanimous points
    max_steal: float = 0.02
    # the fill's confirmation rule (LiftParams.confirm_views) on the robust decision: the
    # posterior margin is the evidence, so one view suffices (None: LiftParams' own rule)
    confirm_views: int | None = 1
    confirm_needs_vote: bool = True  # ... and only where a view of the point voted that class
    confirm_local_share: float = 0.1  # ... or its neighbourhood's votes hold this share of it
    chunk: int = 1_000_000
    seed: int = 0
    # issue 37, fourth round: the votes' likelihood from a per-annotator confusion model
    # (occufly.lifting.confusion, Dawid-Skene EM over every frame's votes, initialised from
    # this decision's own labels) instead of the pooled matrix over the two leading classes;
    # fill_snapshot runs the pooled decision first, fits the model, then decides again.
    # None = off (the default); a ConfusionParams = on.
    confusion: object | None = None
    # issue 37, fifth round: after the decision, the pooled matrix is counted again from the
    # decided labels (refit_confusion) and the points decided again, this many times (0 = the
    # EM's matrix only, the default before; module docstring, "Refit"). Not with a confusion
    # model (that one is fitted per annotator instead).
    refit_rounds: int = 2
    # issue 37, sixth round: a frame's painted regions that the other views contradict as a
    # whole are counted as they say, and the points decided again with this decision's matrix
    # (occufly.lifting.regions; fill_snapshot). None = off; a RegionParams = on. Plain votes
    # only, and not with a confusion model (that one decides per annotator instead).
    regions: object | None = None


# ---- features ------------------------------------------------------------------------------
def _checksum(xyz: np.ndarray) -> str:
    n = len(xyz)
    idx = np.unique(np.linspace(0, max(n - 1, 0), num=min(n, 4096)).astype(np.int64))
    h = hashlib.sha256(np.ascontiguousarray(np.asarray(xyz[idx], np.float32)).tobytes())
    h.update(str(n).encode())
    return h.hexdigest()[:16]


def point_features(xyz: np.ndarray, rgb: np.ndarray, params: RobustParams | None = None
                   ) -> np.ndarray:
    """(N, F) float16 per-point features (:data:`FEATURE_NAMES`), from the cloud alone.

    Voxel statistics (mean colour, covariance eigenvalues / normal) are accumulated with
    bincounts in chunks; the ground is a grey opening (min filter, then max filter) of the
    per-cell lowest point, so buildings and trees narrower than twice ``ground_radius`` stand
    on the terrain around them.
    """
    p = params or RobustParams()
    xyz = np.asarray(xyz)
    n = len(xyz)
    F = len(FEATURE_NAMES)
    out = np.zeros((n, F), np.float16)
    if n == 0:
        return out
    ch = max(1, int(p.chunk))
    mn = np.asarray(xyz.min(axis=0), np.float64)
    e = float(p.voxel)

    # voxel keys (int64, one pass) and per-voxel sums
    def vkey(a: int, b: int) -> np.ndarray:
        q = np.floor((np.asarray(xyz[a:b], np.float64) - mn) / e).astype(np.int64)
        return q

    dims = np.floor((np.asarray(xyz.max(axis=0), np.float64) - mn) / e).astype(np.int64) + 1
    keys = np.empty(n, np.int64)
    for a in range(0, n, ch):
        b = min(n, a + ch)
        q = vkey(a, b)
        keys[a:b] = (q[:, 0] * dims[1] + q[:, 1]) * dims[2] + q[:, 2]
    uk, inv = np.unique(keys, return_inverse=True)
    del keys
    inv = inv.reshape(-1).astype(np.int32 if len(uk) < 2**31 else np.int64)
    V = len(uk)
    del uk
    # per-voxel sums in float32 (coordinates relative to the voxel centre, |x| < voxel)
    acc = np.zeros((13, V), np.float32)  # count, x, y, z, xx, xy, xz, yy, yz, zz, r, g, b
    for a in range(0, n, ch):
        b = min(n, a + ch)
        iv = inv[a:b]
        pts = np.asarray(xyz[a:b], np.float64)
        loc = pts - mn - (np.floor((pts - mn) / e) + 0.5) * e
        acc[0] += np.bincount(iv, minlength=V)
        for i in range(3):
            acc[1 + i] += np.bincount(iv, loc[:, i], V)
        k = 4
        for i in range(3):
            for j in range(i, 3):
                acc[k] += np.bincount(iv, loc[:, i] * loc[:, j], V)
                k += 1
        col = np.asarray(rgb[a:b], np.float64)
        for i in range(3):
            acc[10 + i] += np.bincount(iv, col[:, i], V)
    vcol = np.empty((3, V), np.float32)
    vert = np.empty(V, np.float32)
    curv = np.empty(V, np.float32)
    lin = np.empty(V, np.float32)
    for a in range(0, V, ch):  # covariance, eigen decomposition: chunks of voxels
        b = min(V, a + ch)
        cnt = acc[0, a:b].astype(np.float64)
        mean = acc[1:4, a:b] / cnt
        cov = np.empty((b - a, 3, 3), np.float64)
        k = 4
        for i in range(3):
            for j in range(i, 3):
                cov[:, i, j] = cov[:, j, i] = acc[k, a:b] / cnt - mean[i] * mean[j]
                k += 1
        w, vec = np.linalg.eigh(cov + 1e-9 * np.eye(3))
        vert[a:b] = 1.0 - np.abs(vec[:, 2, 0])  # 0: horizontal surface, 1: vertical
        curv[a:b] = 3.0 * w[:, 0] / np.maximum(w.sum(axis=1), 1e-12)
        lin[a:b] = (w[:, 2] - w[:, 1]) / np.maximum(w[:, 2], 1e-12)
        vcol[:, a:b] = acc[10:13, a:b] / cnt / 255.0
        single = cnt < 3  # a voxel of one or two points has no shape
        vert[a:b][single], curv[a:b][single], lin[a:b][single] = 0.5, 0.0, 0.0
    del acc

    # ground: grey opening of the per-cell lowest point
    c = float(p.ground_cell)
    gd = np.floor((np.asarray(xyz.max(axis=0), np.float64)[:2] - mn[:2]) / c).astype(np.int64) + 1
    zmin = np.full(int(gd[0] * gd[1]), np.inf)
    for a in range(0, n, ch):
        b = min(n, a + ch)
        pts = np.asarray(xyz[a:b], np.float64)
        g = np.floor((pts[:, :2] - mn[:2]) / c).astype(np.int64)
        np.minimum.at(zmin, g[:, 0] * gd[1] + g[:, 1], pts[:, 2])
    zmin = zmin.reshape(gd)
    r = max(1, int(round(p.ground_radius / c)))
    ero = ndimage.minimum_filter(zmin, size=2 * r + 1, mode="nearest")
    ero[~np.isfinite(ero)] = -np.inf
    ground = ndimage.maximum_filter(ero, size=2 * r + 1, mode="nearest").ravel()
    del zmin, ero

    for a in range(0, n, ch):
        b = min(n, a + ch)
        pts = np.asarray(xyz[a:b], np.float64)
        g = np.floor((pts[:, :2] - mn[:2]) / c).astype(np.int64)
        gz = ground[g[:, 0] * gd[1] + g[:, 1]]
        hag = np.where(np.isfinite(gz), pts[:, 2] - gz, 0.0)
        iv = inv[a:b]
        col = np.asarray(rgb[a:b], np.float32) / 255.0
        blk = np.empty((b - a, F), np.float32)
        blk[:, 0:3] = col
        blk[:, 3:6] = vcol[:, iv].T
        blk[:, 6] = np.log1p(np.clip(hag, 0.0, 100.0))
        blk[:, 7] = vert[iv]
        blk[:, 8] = curv[iv]
        blk[:, 9] = lin[iv]
        out[a:b] = blk
    return out


def cached_features(ws: str | Path | None, xyz: np.ndarray, rgb: np.ndarray,
                    params: RobustParams | None = None, *, read_only: bool = False
                    ) -> np.ndarray:
    """:func:`point_features`, cached in ``ws/lifting/features.npy`` (recomputed when the
    point count, the checksum of the cloud or the feature parameters differ). ``ws=None``
    or ``read_only``: computed, not stored (an existing valid cache is still used)."""
    p = params or RobustParams()
    key = {"version": FEATURES_VERSION, "n_points": int(len(xyz)), "checksum": _checksum(xyz),
           "voxel": p.voxel, "ground_cell": p.ground_cell, "ground_radius": p.ground_radius,
           "names": list(FEATURE_NAMES)}
    if ws is not None:
        from occufly.workspace import Workspace

        d = Workspace(ws).lifting_dir
        fp, jp = d / "features.npy", d / "features.json"
        try:
            if jp.is_file() and fp.is_file() and json.loads(jp.read_text()) == key:
                f = np.load(fp, mmap_mode="r")
                if f.shape == (len(xyz), len(FEATURE_NAMES)) and f.dtype == np.float16:
                    return f
        except (OSError, ValueError):
            pass
    f = point_features(xyz, rgb, p)
    if ws is not None and not read_only and d.is_dir():
        from occufly.fsutil import atomic_save_npy, atomic_write_text

        atomic_save_npy(fp, f)
        atomic_write_text(jp, json.dumps(key, indent=1))
    return f


# ---- annotator model -------------------------------------------------------------------------
def estimate_confusion(c1: np.ndarray, n1: np.ndarray, c2: np.ndarray, n2: np.ndarray, C: int,
                       p: RobustParams) -> tuple[np.ndarray, np.ndarray]:
    """Pooled Dawid-Skene EM over every voted point: (pi (C, C) float64 with rows = true
    class, columns = voted class; class prior (C,) float64).

    The likelihood of a point depends only on its vote pattern (leading class and votes,
    second class and votes), so the EM runs on the histogram of patterns (one bincount over
    the points, chunked) weighted by how many points share each -- exact, deterministic and
    independent of the point count after that pass. A pattern space beyond ``2**26`` keys
    (vote counts in the thousands) falls back to a seeded sample of ``em_sample`` points."""
    n = len(c1)
    voted = n1 > 0
    if not voted.any():
        return np.eye(C) * 0.9 + 0.1 / C, np.full(C, 1.0 / C)
    integral = all(np.issubdtype(np.asarray(v).dtype, np.integer) for v in (n1, n2))
    m1 = int(np.max(n1)) + 1
    m2 = int(np.max(n2)) + 1
    space = C * (C + 1) * m1 * m2
    if integral and space <= 1 << 26:
        hist = np.zeros(space, np.int64)
        for a in range(0, n, p.chunk):
            b = min(n, a + p.chunk)
            v = voted[a:b]
            k = ((np.asarray(c1[a:b])[v].astype(np.int64) * (C + 1)
                  + (np.asarray(c2[a:b])[v].astype(np.int64) + 1)) * m1
                 + np.asarray(n1[a:b])[v]) * m2 + np.asarray(n2[a:b])[v]
            hist += np.bincount(k, minlength=space)
        keys = np.flatnonzero(hist)
        weight = hist[keys].astype(np.float64)
        b2 = (keys % m2).astype(np.float64)
        keys //= m2
        b1 = (keys % m1).astype(np.float64)
        keys //= m1
        a2 = (keys % (C + 1)) - 1
        a1 = keys // (C + 1)
    else:
        rng = np.random.default_rng(p.seed)
        idx = np.flatnonzero(voted)
        if len(idx) > p.em_sample:
            idx = np.sort(rng.choice(idx, p.em_sample, replace=False))
        a1, a2 = np.asarray(c1)[idx].astype(np.int64), np.asarray(c2)[idx].astype(np.int64)
        b1, b2 = np.asarray(n1)[idx].astype(np.float64), np.asarray(n2)[idx].astype(np.float64)
        weight = np.ones(len(idx))
    m = len(a1)
    rows = np.arange(m)
    M = np.zeros((m, C), np.float64)  # vote counts of each pattern over its two classes
    M[rows, a1] += b1
    has2 = a2 >= 0
    M[rows[has2], a2[has2]] += b2[has2]
    post = M / M.sum(axis=1, keepdims=True)  # start: the vote shares
    W = M * weight[:, None]
    wsum = weight.sum()
    pi = np.eye(C)
    prior = np.full(C, 1.0 / C)
    for _ in range(max(1, p.em_iterations)):
        # M-step: expected (true, voted) counts; einsum, not BLAS (threads on a busy machine)
        pi = _rows_with_prior(np.einsum("nt,nc->tc", post, W), p)
        prior = np.einsum("nt,n->t", post, weight) / wsum + 1e-6
        prior /= prior.sum()
        # E-step
        L = np.einsum("nc,tc->nt", M, np.log(pi)) + np.log(prior)
        L -= L.max(axis=1, keepdims=True)
        post = np.exp(L)
        post /= post.sum(axis=1, keepdims=True)
    return pi, prior


def _rows_with_prior(counts: np.ndarray, p: RobustParams) -> np.ndarray:
    """(C, C) expected or counted (true, voted) votes plus the Dirichlet pseudo-votes
    (``off_prior`` everywhere, ``diag_prior`` on the diagonal), each row normalised; a row
    with nothing in it (no votes and no pseudo-votes) uniform."""
    C = len(counts)
    A = counts + p.off_prior + p.diag_prior * np.eye(C)
    total = A.sum(axis=1, keepdims=True)
    return np.where(total > 0, A / np.where(total > 0, total, 1.0), 1.0 / C)


def is_annotator_matrix(pi: np.ndarray, C: int) -> bool:
    """Whether ``pi`` can be decided with: a (C, C) matrix of finite, positive
    probabilities (its logs are taken)."""
    return pi.shape == (C, C) and bool(np.isfinite(pi).all()) and not bool((pi <= 0).any())


def _refit(cls: ClassColumns, vidx: np.ndarray, col1: np.ndarray, n1: np.ndarray,
           col2: np.ndarray, n2: np.ndarray, p: RobustParams, labels: np.ndarray, stats: dict,
           decide) -> tuple[np.ndarray, list]:  # noqa: ANN001
    """:func:`redecide`'s refit rounds (:attr:`RobustParams.refit_rounds`): the matrix
    counted from the labels decided so far (:func:`refit_confusion`), then ``decide(log pi)``
    (every voted point again, into ``labels``); returns the last matrix and decision."""
    t0 = time.perf_counter()
    first = labels[vidx].copy()
    votes = (col1[vidx], n1[vidx], col2[vidx], n2[vidx])  # the same every round
    pi, done = None, []
    for _ in range(p.refit_rounds):
        pi = refit_confusion(cls.col_of[labels[vidx]], *votes, cls.C, p)
        done = decide(np.log(pi).astype(np.float32))
    stats["robust_refit_changed"] = int(np.count_nonzero(labels[vidx] != first))
    stats["robust_refit_seconds"] = round(time.perf_counter() - t0, 3)
    return pi, done


def _annotator_model(col1: np.ndarray, n1: np.ndarray, col2: np.ndarray, n2: np.ndarray,
                     C: int, p: RobustParams, given: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(pi, prior) of :func:`redecide`: the EM's (:func:`estimate_confusion`), or ``given``
    checked (a (C, C) matrix of positive probabilities) with a uniform prior -- which the
    "vote" and "train" priors replace; the "em" prior is still fitted."""
    if given is None:
        return estimate_confusion(col1, n1, col2, n2, C, p)
    pi = np.asarray(given, np.float64)
    if not is_annotator_matrix(pi, C):
        raise ValueError(f"confusion_matrix: expected a ({C}, {C}) matrix of positive "
                         f"probabilities, got shape {pi.shape}")
    prior = (estimate_confusion(col1, n1, col2, n2, C, p)[1] if p.prior == "em"
             else np.full(C, 1.0 / C))
    return pi, prior


def refit_confusion(decided: np.ndarray, c1: np.ndarray, n1: np.ndarray, c2: np.ndarray,
                    n2: np.ndarray, C: int, p: RobustParams, chunk: int = 1 << 22) -> np.ndarray:
    """(C, C) pooled matrix counted from decided labels (:attr:`RobustParams.refit_rounds`):
    row ``t`` = the votes of the points decided ``t`` (their two leading classes, the votes
    :func:`estimate_confusion` sees) plus the EM's Dirichlet pseudo-votes, normalised.

    decided: (n,) column of each point's decided class (-1: none, not counted); c1/n1, c2/n2:
    its leading and second vote column and votes (c2 = -1: none)."""
    A = np.zeros(C * C, np.float64)
    for a in range(0, len(decided), chunk):
        t = np.asarray(decided[a:a + chunk], np.int64)
        k1, v1 = np.asarray(c1[a:a + chunk], np.int64), np.asarray(n1[a:a + chunk], np.float64)
        k2, v2 = np.asarray(c2[a:a + chunk], np.int64), np.asarray(n2[a:a + chunk], np.float64)
        # only points decided for a class a view voted: one decided against every vote
        # (a tiny object the neighbourhood and the classifier kept where every view voted
        # the ground) would teach the matrix that its class is voted as the ground, and the
        # next round would take more ground for it
        seen = (t >= 0) & ((t == k1) | (t == k2))
        ok = seen & (k1 >= 0) & (v1 > 0)
        A += np.bincount(t[ok] * C + k1[ok], v1[ok], minlength=C * C)
        ok2 = seen & (k2 >= 0) & (v2 > 0)
        A += np.bincount(t[ok2] * C + k2[ok2], v2[ok2], minlength=C * C)
    return _rows_with_prior(A.reshape(C, C), p)


# ---- classifier ------------------------------------------------------------------------------
@dataclass
class _QDA:
    mean: np.ndarray      # (C, F) float32
    whiten: np.ndarray    # (C, F, F) float32: Cholesky factor of the precision (L^T)
    logdet: np.ndarray    # (C,) float32 (of the covariance)
    ok: np.ndarray        # (C,) bool: fitted
    pooled: tuple         # (mean, whiten, logdet) of all training points: the neutral density


def _fit_qda(features: np.ndarray, train: np.ndarray, cols: np.ndarray, C: int,
             p: RobustParams, majority: np.ndarray | None = None) -> _QDA:
    """One Gaussian per class over a seeded sample of its training points, and one over all
    of them (the neutral density of classes with too few).

    ``majority`` (indices of the voted points whose leading class beats the second): a class
    with fewer than ``min_strong`` unanimous training points -- a tiny object that degraded
    masks shift off itself or skip in half the views has only a handful -- is fitted on its
    unanimous points plus its majority points, trimmed ``trim_iterations`` times of those that
    a well-trained class's Gaussian explains better than its own (the ground around a shifted
    blob is voted for the blob's class, but looks like ground)."""
    rng = np.random.default_rng(p.seed + 1)
    F = features.shape[1]
    mean = np.zeros((C, F), np.float32)
    whiten = np.zeros((C, F, F), np.float32)
    logdet = np.zeros(C, np.float32)
    ok = np.zeros(C, bool)
    need = max(p.min_train, F + 2)

    def split(idx_all: np.ndarray) -> list[np.ndarray]:
        # a stable counting sort by class (what a stable argsort did, in two passes)
        grouped, bounds = _group_by_class(np.asarray(idx_all), np.asarray(cols[idx_all]), C)
        return [grouped[bounds[c]:bounds[c + 1]] for c in range(C)]

    def cap(idx: np.ndarray) -> np.ndarray:
        if len(idx) > p.train_per_class:
            idx = np.sort(rng.choice(idx, p.train_per_class, replace=False))
        return idx

    per = split(train)
    weak = []
    for c in range(C):
        idx = per[c]
        if majority is not None and len(idx) < p.min_strong:
            weak.append(c)
            continue
        if len(idx) < need:
            continue
        g = _gaussian(np.asarray(features[cap(idx)], np.float64), p.cov_reg)
        if g is None:
            continue
        mean[c], whiten[c], logdet[c] = g
        ok[c] = True
    if weak:
        strong = np.flatnonzero(ok)
        maj = split(majority)
        # 2,000 of each strong class's points drawn without replacement in O(2,000) (a
        # permutation of all of them cost ~0.03 s per 20 MP review)
        steal_sample = {s: np.asarray(features[per[s][rng.choice(
            len(per[s]), min(2000, len(per[s])), replace=False)]], np.float32) for s in strong}
        for c in weak:
            base = per[c]
            extra = cap(np.setdiff1d(maj[c], base, assume_unique=False))
            xb = np.asarray(features[base], np.float64)
            xe = np.asarray(features[extra], np.float64)
            if len(xb) + len(xe) < need:
                continue
            g = _gaussian(np.concatenate([xb, xe]), p.cov_reg)
            if g is None:
                continue
            if len(xe) and len(strong):
                xe32 = xe.astype(np.float32)
                other = np.full(len(xe), -np.inf, np.float32)
                for s in strong:
                    if s != c:
                        other = np.maximum(other, _gauss_loglik(xe32, mean[s], whiten[s],
                                                                logdet[s]))
                for _ in range(max(0, p.trim_iterations)):
                    keep = _gauss_loglik(xe32, *g) >= other
                    if len(xb) + int(keep.sum()) < need:
                        break
                    g2 = _gaussian(np.concatenate([xb, xe[keep]]), p.cov_reg)
                    if g2 is None:
                        break
                    g = g2
            if len(strong) and p.max_steal < 1.0:
                # an indistinguishable look-alike (a confused region, not a tiny object):
                # its Gaussian would take the well-trained class's own points
                stolen = 0.0
                for s in strong:
                    if s == c:
                        continue
                    xs = steal_sample[s]
                    own_s = _gauss_loglik(xs, mean[s], whiten[s], logdet[s])
                    stolen = max(stolen, float(np.mean(_gauss_loglik(xs, *g) > own_s)))
                if stolen > p.max_steal:  # keep to the unanimous points, as a strong class
                    g = _gaussian(xb, p.cov_reg) if len(xb) >= need else None
                    if g is None:
                        continue
            mean[c], whiten[c], logdet[c] = g
            ok[c] = True
    sample = train if len(train) <= 100_000 else np.sort(rng.choice(train, 100_000, replace=False))
    pooled = _gaussian(np.asarray(features[sample], np.float64), p.cov_reg) if len(sample) > F else None
    if pooled is None:
        pooled = (np.zeros(F, np.float32), np.eye(F, dtype=np.float32), np.float32(0.0))
    return _QDA(mean, whiten, logdet, ok, pooled)


@numba.njit(nogil=True, cache=True)
def _group_by_class(idx: np.ndarray, tc: np.ndarray, C: int) -> tuple[np.ndarray, np.ndarray]:
    """(``idx`` grouped by class ``tc`` in [0, C), each group in ``idx``'s order -- entries of
    another class left out --, group bounds (C + 1,)): a stable counting sort."""
    bounds = np.zeros(C + 1, np.int64)
    for i in range(len(tc)):
        c = tc[i]
        if 0 <= c < C:
            bounds[c + 1] += 1
    for c in range(C):
        bounds[c + 1] += bounds[c]
    pos = bounds[:C].copy()
    out = np.empty(bounds[C], idx.dtype)
    for i in range(len(tc)):
        c = tc[i]
        if 0 <= c < C:
            out[pos[c]] = idx[i]
            pos[c] += 1
    return out, bounds


def _gaussian(x: np.ndarray, reg: float) -> tuple | None:
    """(mean, whitening L^T with ||(x - mean) @ L||^2 the Mahalanobis distance, log det cov)."""
    F = x.shape[1]
    cov = np.cov(x.T) + reg * np.eye(F)
    try:
        Lc = np.linalg.cholesky(np.linalg.inv(cov))
    except np.linalg.LinAlgError:
        return None
    return (x.mean(axis=0).astype(np.float32), Lc.T.astype(np.float32),
            np.float32(np.linalg.slogdet(cov)[1]))


def _gauss_loglik(x: np.ndarray, mean: np.ndarray, whiten: np.ndarray, logdet) -> np.ndarray:
    z = np.einsum("nf,gf->ng", x - mean, whiten)
    return -0.5 * (np.einsum("ng,ng->n", z, z) + logdet)


# ---- the decision ------------------------------------------------------------------------------
def local_votes(xyz: np.ndarray, voted: np.ndarray, col1: np.ndarray, n1: np.ndarray,
                col2: np.ndarray, n2: np.ndarray, C: int, edge: float, chunk: int = 1_000_000,
                origin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The votes of each voted point's neighbourhood: (voxel index (m,) int32 of the voted
    points ``voted`` (sorted ids), block counts (V, C) float32 = the two leading vote classes
    of every voted point summed over the 3x3x3 voxels of edge ``edge`` around a voxel).

    ``origin``: the lattice's corner (default the voted points' minimum); a subset of the
    voted points given the whole set's corner gets the same voxels, and the same block counts
    wherever its points hold every voted point of the block (:class:`HeldDecision`).

    Cost ~ the voted points (one voxel hash, 26 sorted-key lookups per occupied voxel)."""
    # a RowSubset (the review's cloud rows) is gathered here, in the caller's pool thread
    whole = len(voted) == len(xyz) and not isinstance(xyz, RowSubset)
    pts = np.asarray(xyz, np.float32) if whole else np.asarray(xyz[voted], np.float32)
    grid = VoxelGrid(pts, edge, pad=1, origin=origin)
    del pts
    vox = grid.inverse.astype(np.int32)
    V = grid.n_voxels
    counts = np.zeros(V * C, np.float32)
    if _integral_votes(n1, n2, voted, col2):
        # whole vote counts whose total stays below 2^24: every partial sum is exact in
        # float32, so summing straight into the float32 counts gives the chunked float64
        # bincounts' result without their (V * C) float64 arrays (3 passes of 100+ MB on a
        # 20 MP frame's 2 M voted points)
        _vote_counts_into(counts, vox, np.ascontiguousarray(voted, np.int64), col1, n1, col2,
                          n2, C)
        return vox, grid.block_sum(counts.reshape(V, C))
    for a in range(0, len(voted), chunk):
        ids = voted[a:a + chunk]
        v = vox[a:a + chunk].astype(np.int64) * C
        counts += np.bincount(v + np.asarray(col1[ids], np.int64), np.asarray(n1[ids], np.float64),
                              V * C).astype(np.float32)
        c2 = np.asarray(col2[ids], np.int64)
        h2 = c2 >= 0
        counts += np.bincount((v + c2)[h2], np.asarray(n2[ids], np.float64)[h2],
                              V * C).astype(np.float32)
    return vox, grid.block_sum(counts.reshape(V, C))


def _integral_votes(n1: np.ndarray, n2: np.ndarray, voted: np.ndarray, col2: np.ndarray) -> bool:
    """Whether the vote counts that :func:`local_votes` adds up (``n1``, and ``n2`` where
    ``col2 >= 0``, of the points ``voted``) are non-negative integers whose total stays below
    2^24: float32 sums of them are then exact in any order."""
    n1, n2 = np.asarray(n1), np.asarray(n2)
    if not (np.issubdtype(n1.dtype, np.integer) and np.issubdtype(n2.dtype, np.integer)):
        return False
    return 0 <= _vote_total(np.ascontiguousarray(voted, np.int64), n1, col2, n2) < 1 << 24


@numba.njit(nogil=True, cache=True)
def _vote_total(voted: np.ndarray, n1: np.ndarray, col2: np.ndarray, n2: np.ndarray) -> int:
    """The sum of ``n1`` and of ``n2`` where ``col2 >= 0`` over ``voted``; -1 if any is < 0."""
    total = 0
    for k in range(voted.shape[0]):
        p = voted[k]
        a = np.int64(n1[p])
        if a < 0:
            return -1
        total += a
        if col2[p] >= 0:
            b = np.int64(n2[p])
            if b < 0:
                return -1
            total += b
    return total


@numba.njit(nogil=True, cache=True)
def _vote_counts_into(counts: np.ndarray, vox: np.ndarray, voted: np.ndarray, col1: np.ndarray,
                      n1: np.ndarray, col2: np.ndarray, n2: np.ndarray, C: int) -> None:
    """``counts[vox[k] * C + col1[p]] += n1[p]`` and the same for ``col2`` (where >= 0) over
    the voted points ``p = voted[k]`` (whole counts: exact in float32)."""
    for k in range(voted.shape[0]):
        p = voted[k]
        base = np.int64(vox[k]) * C
        counts[base + np.int64(col1[p])] += np.float32(n1[p])
        c2 = np.int64(col2[p])
        if c2 >= 0:
            counts[base + c2] += np.float32(n2[p])


def _class_prior(p: RobustParams, prior: np.ndarray, train: np.ndarray, vidx: np.ndarray,
                 col1: np.ndarray, C: int) -> np.ndarray:
    """The class prior of :func:`redecide` (``RobustParams.prior``): "vote", the shares of the
    vote majority over all voted points ``vidx``; "train", over the unanimous ones ``train``
    (biased against classes few views see, such as facades). Both are steadier than the EM's
    prior (``prior``, kept for "em"), which can trade a confusable class's mass for its
    look-alike's."""
    if p.prior not in ("train", "vote"):
        return prior
    share = np.bincount(col1[train if p.prior == "train" else vidx], minlength=C)
    share = share.astype(np.float64) + 1.0
    return share / share.sum()


def matrix_record(pi: np.ndarray) -> list[list[float]]:
    """The annotator matrix as stats carry it (``robust_matrix``): nested lists with 6
    significant digits -- rounding to decimals would make the rarest confusions (1e-9 with
    millions of votes) zero, which no decision may take the log of."""
    return [[float(f"{x:.6g}") for x in row] for row in np.asarray(pi)]


@dataclass
class HeldDecision:
    """A pooled robust decision kept between the fills of one scene (issue 37, eighth round).

    The annotator matrix, the class prior and the point classifier of :func:`redecide` are
    fitted from all the votes, so a decision fitted again after a 40 x 40 px brush stroke
    moves near-tie points all over the scene, and the fill after it is a full one (the k-NN
    passes are incremental only where the decided labels changed). With a held decision the
    next :func:`redecide` keeps the fitted model and decides again only the points whose
    decision can have changed with it fixed: those whose votes changed, and those whose
    neighbourhood prior (3x3x3 voxels of ``local_voxel``) holds a changed vote. The result is
    what a full decision with the held model would give, bit for bit (tests).

    The model is fitted again (a *cold* decision) when there is none, the parameters, classes
    or cloud changed, the points whose votes changed exceed ``max_share_save`` of the voted
    points in this decision or ``max_share`` since the fit, a class is voted that had no vote
    at the fit, or the caller :meth:`clear`-s it (the app's worker does when the scene has been
    quiet for a while, so the labels do not depend on the order of the saves for long). A
    brush stroke keeps the model; a frame's worth of new or repainted votes fits it again:
    with a sloppy painter's frame repainted (103,754 px, `small` seed 0, the crew) the held
    model decided 0.8642 where the refitted one reached 0.9231 -- the other frames' points
    are decided better by a model that no longer learns his confusions. Memory: copies of the
    votes and of the result, about 15 bytes per point."""

    max_share: float = 0.05       # points with changed votes since the fit, of the voted
    max_share_save: float = 0.01  # ... in this one decision (a brush stroke, not a frame)
    key: tuple | None = None
    logpi: np.ndarray | None = None
    pi: np.ndarray | None = None
    prior: np.ndarray | None = None
    logprior_scene: np.ndarray | None = None
    logprior: np.ndarray | None = None
    q: _QDA | None = None
    votes: tuple | None = None      # (col1, n1, col2, n2) as of the last decision
    out: tuple | None = None        # (labels, margin, top) of the last decision
    fit_classes: np.ndarray | None = None  # (C,) bool: voted at the fit
    fit_stats: dict | None = None
    fit_voted: int = 0
    changed: int = 0                # points whose votes changed since the fit
    warm: int = 0                   # warm decisions since the fit

    def clear(self) -> None:
        """Drop the model: the next decision fits one."""
        self.key = None
        self.votes = self.out = self.q = None

    def why_cold(self, p: RobustParams, C: int, n: int, with_top: bool) -> str | None:
        """Why the next decision must fit its model (None: it may keep it)."""
        if self.key is None:
            return "no held model"
        if self.key != (repr(p), C, n, with_top):
            return "other parameters, classes or points"
        return None

    def store(self, why: str | None, p: RobustParams, C: int, n: int, with_top: bool,
              pi: np.ndarray, prior: np.ndarray, logprior_scene: np.ndarray,
              logprior: np.ndarray, q: _QDA, votes: tuple, out: tuple, stats: dict) -> None:
        """Hold what a decision that fitted its model (because of ``why``) decided with, and
        its result; ``why`` None: a decision that is not held (:meth:`clear`)."""
        if why is None:
            self.clear()
            return
        stats["robust_cold_why"] = why
        fit_stats = {k: stats[k] for k in ("robust_classifier_classes", "robust_train_points")}
        self.key = (repr(p), C, n, with_top)
        self.pi = np.asarray(pi, np.float64)
        self.logpi = np.log(self.pi).astype(np.float32)  # what the last decision used
        self.prior = np.asarray(prior)
        self.logprior_scene, self.logprior = logprior_scene, logprior
        self.q = q
        self.votes = tuple(np.array(v, copy=True) for v in votes)
        self.out = tuple(np.array(v, copy=True) for v in out)
        col1, n1, col2, n2 = votes
        on = np.asarray(n1) > 0
        self.fit_classes = np.zeros(C, bool)
        self.fit_classes[np.unique(np.asarray(col1)[on])] = True
        two = np.asarray(n2) > 0
        self.fit_classes[np.unique(np.asarray(col2)[two & (np.asarray(col2) >= 0)])] = True
        self.fit_voted = int(on.sum())
        self.fit_stats = dict(fit_stats)
        self.changed = 0
        self.warm = 0


def _warm_decision(h: HeldDecision, cls: ClassColumns, features: np.ndarray, col1: np.ndarray,
                   n1: np.ndarray, col2: np.ndarray, n2: np.ndarray, xyz, p: RobustParams,  # noqa: ANN001
                   with_top: bool, workers: int, report: ProgressFn):  # noqa: ANN202
    """:func:`redecide` with the held model ``h``: the points whose votes changed since its
    last decision, and the voted points in the 3x3x3 voxel blocks around them (their
    neighbourhood prior counts the changed votes), decided again; every other point keeps
    its label, margin and support. Returns redecide's tuple, or why the model must be fitted
    again (str)."""
    t0, c0 = time.perf_counter(), time.process_time()
    C = cls.C
    o1, on1, o2, on2 = h.votes
    diff = _changed_votes(col1, n1, col2, n2, o1, on1, o2, on2)
    voted = n1 > 0
    n_voted = int(np.count_nonzero(voted))
    of = max(n_voted, h.fit_voted, 1)
    if len(diff) > h.max_share_save * of:
        return (f"{len(diff):,} points with changed votes, over {h.max_share_save:.0%} of "
                f"{of:,}")
    if h.changed + len(diff) > h.max_share * of:
        return (f"{h.changed + len(diff):,} points with changed votes since the fit, over "
                f"{h.max_share:.0%} of {of:,}")
    now_classes = np.concatenate([col1[diff][n1[diff] > 0],
                                  col2[diff][(n2[diff] > 0) & (col2[diff] >= 0)]])
    if len(now_classes) and not h.fit_classes[np.asarray(now_classes, np.int64)].all():
        return "a class voted that had no vote at the fit"
    labels, margin, top = (np.array(v, copy=True) for v in h.out)
    gone = diff[~voted[diff]]
    labels[gone], margin[gone], top[gone] = 0, 0.0, 0
    vidx_all = np.flatnonzero(voted)
    local = None
    if xyz is not None and p.local_voxel > 0 and len(diff):
        affected, sources, origin = _around(xyz, vidx_all, diff, p.local_voxel)
        if len(affected):
            vox, block = local_votes(xyz, sources, col1, n1, col2, n2, C, p.local_voxel,
                                     p.chunk, origin=origin)
            local = (vox[np.searchsorted(sources, affected)],
                     *_local_prior_tables(block, h.prior, p))
            del block
    else:
        affected = diff[voted[diff]]
    done = []
    if len(affected):
        done = _decide_all(cls, affected, col1, n1, col2, n2, h.logpi, h.logprior_scene,
                           h.logprior, local, min(p.candidates, C), p, features, h.q, None,
                           labels, margin, top, with_top, None, workers, report)
    for held_v, v in zip(h.votes, (col1, n1, col2, n2), strict=True):
        held_v[diff] = v[diff]
    for held_v, v in zip(h.out, (labels, margin, top), strict=True):
        held_v[affected] = v[affected]
        held_v[gone] = v[gone]
    h.changed += len(diff)
    h.warm += 1
    stats = dict(h.fit_stats or {})
    stats.update({
        "robust_warm": True,
        "robust_warm_changed_votes": int(len(diff)),
        "robust_warm_decided": int(len(affected)),
        "robust_warm_since_fit": {"decisions": h.warm, "changed_points": h.changed},
        "robust_matrix": matrix_record(h.pi),
        "robust_points_evaluated": int(sum(d[0] for d in done)),
        "robust_points_changed": int(sum(d[1] for d in done)),
        "robust_seconds": round(time.perf_counter() - t0, 3),
        "robust_cpu_seconds": round(time.process_time() - c0, 3),
    })
    return labels, margin, top, stats


def _changed_votes(col1: np.ndarray, n1: np.ndarray, col2: np.ndarray, n2: np.ndarray,
                   o1: np.ndarray, on1: np.ndarray, o2: np.ndarray, on2: np.ndarray,
                   chunk: int = 1 << 22) -> np.ndarray:
    """Sorted ids of the points whose two leading vote classes or counts differ."""
    out = []
    for a in range(0, len(col1), chunk):
        b = a + chunk
        d = ((col1[a:b] != o1[a:b]) | (n1[a:b] != on1[a:b]) | (col2[a:b] != o2[a:b])
             | (n2[a:b] != on2[a:b]))
        out.append(np.flatnonzero(d) + a)
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def _around(xyz, vidx: np.ndarray, diff: np.ndarray, edge: float  # noqa: ANN001
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """On the lattice of :func:`local_votes` over the voted points ``vidx`` (edge ``edge``,
    corner their minimum): (the voted points within one voxel (Chebyshev) of a point of
    ``diff`` -- those whose neighbourhood block holds it --, the voted points within two --
    every point of those blocks --, the corner)."""
    from occufly.lifting.blockknn import voxel_keys

    pts = np.asarray(xyz[vidx], np.float32)
    origin, dims, keys = voxel_keys(pts, edge, 2)
    del pts
    dp = np.asarray(xyz[diff], np.float64)
    q = np.floor((dp - origin) / float(edge)).astype(np.int64) + 2
    ok = ((q >= 0) & (q < dims)).all(axis=1)  # farther off: no voted point within two voxels
    dk = (q[ok, 0] * dims[1] + q[ok, 1]) * dims[2] + q[ok, 2]

    def within(r: int) -> np.ndarray:
        near = dilate_keys(dk, r, (int(dims[1] * dims[2]), int(dims[2]), 1))
        if not len(near):
            return vidx[:0]
        pos = np.minimum(np.searchsorted(near, keys), len(near) - 1)
        return vidx[near[pos] == keys]

    return within(1), within(2), np.asarray(origin, np.float64)


def redecide(cls: ClassColumns, features: np.ndarray, col1: np.ndarray, n1: np.ndarray,
             col2: np.ndarray, n2: np.ndarray, params: RobustParams | None = None,
             progress: ProgressFn | None = None, xyz: np.ndarray | None = None,
             confusion=None,  # noqa: ANN001
             with_top: bool = True, workers: int = 1,
             confusion_matrix: np.ndarray | None = None,
             held: HeldDecision | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Re-decide every voted point from its votes, the annotator model and the classifier.

    ``confusion``: a fitted :class:`occufly.lifting.confusion.ConfusionModel` over the same
    points: every voted point's vote log-likelihood comes from it (all its votes, each under
    its annotator's matrix) instead of the pooled matrix over the two leading classes, and
    the classifier trains only on the unanimous points whose class the model gives at least
    ``train_min_posterior`` (a sloppy painter's unanimous wrong regions are left out).

    col1/n1: (N,) leading vote column (-1 = no votes) and its votes; col2/n2: the second
    (n2 = 0 where none); xyz: (N, 3) the cloud (or a :class:`RowSubset` of it, gathered
    where :func:`local_votes` runs), for the neighbourhood prior (None: the scene-wide prior
    only). Returns (labels (N,) uint8 raw ids, 0 = no votes; margin (N,)
    float32 posterior top - second; top (N,) uint16 the support of the decided class for the
    fill's confirmation rule: its votes, at least 1 where the neighbourhood supports it
    (``confirm_local_share``), 0 where nothing but the features chose it (with
    ``confirm_needs_vote=False``: its votes, at least 1); stats). ``with_top=False``: the
    support is not computed (``top`` all 0; the leave-one-out labels use labels and margin only).
    ``workers`` > 1: the neighbourhood votes are counted while the classifier is fitted, and
    the chunks are decided by that many threads (compiled kernels without the interpreter
    lock; each chunk writes its own rows): the same result as one thread, in less wall time.
    ``confusion_matrix``: a (C, C) pooled matrix to decide with instead of fitting one (the
    matrix a fill decided with, its stats' ``robust_matrix``: the review's leave-one-out
    labels reuse it); no EM and no refit rounds then. The stats carry the matrix the final
    decision used as ``robust_matrix`` (nested lists, 6 significant digits).
    ``held``: a :class:`HeldDecision` kept between calls (the live fill): it holds the fitted
    model, and a call after few vote changes decides again only around them with it.
    """
    p = params or RobustParams()
    report = progress or noop
    t0 = time.perf_counter()
    c0 = time.process_time()
    C = cls.C
    n = len(col1)
    col1, col2, n1, n2 = (np.asarray(v) for v in (col1, col2, n1, n2))
    labels = np.zeros(n, np.uint8)
    margin = np.zeros(n, np.float32)
    top = np.zeros(n, np.uint16)
    stats: dict = {}
    voted = n1 > 0
    if not voted.any():
        if held is not None:
            held.clear()
        return labels, margin, top, {"robust_seconds": 0.0}
    got = None if held is None or confusion is not None or confusion_matrix is not None else (
        held.why_cold(p, C, n, with_top) or _warm_decision(
            held, cls, features, col1, n1, col2, n2, xyz, p, with_top, workers, report))
    if isinstance(got, tuple):
        return got
    report(0.0, "annotator model")
    given = confusion_matrix is not None
    pi, prior = _annotator_model(col1, n1, col2, n2, C, p, confusion_matrix)
    logpi = np.log(pi).astype(np.float32)
    t_em = time.perf_counter()
    report(0.2, "point classifier")
    train = np.flatnonzero(voted & (n2 == 0) & (n1 >= 2))
    if confusion is not None and confusion.params.train_min_posterior > 0 and len(train):
        ok = confusion.class_posterior(train, col1[train]) >= confusion.params.train_min_posterior
        stats["confusion_train_dropped"] = int(len(train) - ok.sum())
        train = train[ok]
    vidx_all = np.flatnonzero(voted)
    majority = vidx_all[n1[vidx_all] > n2[vidx_all]] if p.min_strong > 0 else None
    want_local = xyz is not None and p.local_voxel > 0
    pool = ThreadPoolExecutor(max_workers=workers) if workers > 1 else None
    try:
        local_fut = (pool.submit(local_votes, xyz, vidx_all, col1, n1, col2, n2, C, p.local_voxel,
                                 p.chunk) if pool is not None and want_local else None)
        q = _fit_qda(features, train, col1, C, p, majority)
        del majority
        stats["robust_classifier_classes"] = int(q.ok.sum())
        stats["robust_train_points"] = int(len(train))
        t_fit = time.perf_counter()
        prior = _class_prior(p, prior, train, vidx_all, col1, C)
        logprior_scene = np.log(prior).astype(np.float32)
        logprior = (p.prior_weight * logprior_scene).astype(np.float32)
        vidx = vidx_all
        local = None
        if want_local:
            report(0.25, "neighbourhood votes")
            vox, block = (local_fut.result() if local_fut is not None else
                          local_votes(xyz, vidx, col1, n1, col2, n2, C, p.local_voxel, p.chunk))
            # per voxel, once: the neighbourhood's vote shares and the log of the mixed prior
            # (the same float32 operations per row as per point, so the same values)
            local = (vox, *_local_prior_tables(block, prior, p))
            del block
        t_local = time.perf_counter()
        K = min(p.candidates, C)
        done = _decide_all(cls, vidx, col1, n1, col2, n2, logpi, logprior_scene, logprior, local, K,
                           p, features, q, confusion, labels, margin, top, with_top, pool, workers,
                           report)
        if p.refit_rounds > 0 and confusion is None and not given:
            pi, done = _refit(cls, vidx, col1, n1, col2, n2, p, labels, stats, lambda lp: _decide_all(
                cls, vidx, col1, n1, col2, n2, lp, logprior_scene, logprior, local, K, p, features,
                q, None, labels, margin, top, with_top, pool, workers, report))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    if held is not None:  # got None: a per-painter or given-matrix decision, not held
        held.store(got, p, C, n, with_top, pi, prior, logprior_scene, logprior, q,
                   (col1, n1, col2, n2), (labels, margin, top), stats)
    stats["robust_matrix"] = matrix_record(pi)
    stats.update({
        "robust_points_evaluated": int(sum(d[0] for d in done)),
        "robust_points_changed": int(sum(d[1] for d in done)),
        "robust_em_seconds": round(t_em - t0, 3),
        "robust_fit_seconds": round(t_fit - t_em, 3),
        "robust_local_seconds": round(t_local - t_fit, 3),
        "robust_seconds": round(time.perf_counter() - t0, 3),
        "robust_cpu_seconds": round(time.process_time() - c0, 3),
    })
    report(1.0, "robust decision")
    return labels, margin, top, stats


def _decide_all(cls: ClassColumns, vidx: np.ndarray, col1: np.ndarray, n1: np.ndarray,
                col2: np.ndarray, n2: np.ndarray, logpi: np.ndarray, logprior_scene: np.ndarray,
                logprior: np.ndarray, local: tuple | None, K: int, p: RobustParams,
                features: np.ndarray, q: _QDA, confusion, labels: np.ndarray,  # noqa: ANN001
                margin: np.ndarray, top: np.ndarray, with_top: bool,
                pool: ThreadPoolExecutor | None, workers: int, report: ProgressFn
                ) -> list[tuple[int, int]]:
    """:func:`redecide`'s decision of the voted points ``vidx`` in chunks, written into
    ``labels`` / ``margin`` / ``top``; with ``pool`` the chunks shared out to its threads.
    Returns (points the classifier weighed, points changed) per chunk."""
    # pointwise: any split into chunks gives the same result; threads take one share each
    # with threads: a multiple of ``workers`` chunks of equal size (not full chunks and a
    # short last one, which left a thread idle while the other decided two)
    n_chunks = 1 if pool is None else workers * max(1, -(-len(vidx) // (workers * p.chunk)))
    step = p.chunk if pool is None else max(1, -(-len(vidx) // n_chunks))

    def decide(a: int) -> tuple[int, int]:
        ids = vidx[a:a + step]
        c1, c2 = col1[ids].astype(np.int64), col2[ids].astype(np.int64)
        vrow = local[0][a:a + step] if local is not None else None
        best, m, n_multi = _decide_chunk(
            logpi, c1, n1[ids], c2, n2[ids], logprior_scene, logprior,
            None if local is None else (local[2], vrow), K, p, features, ids, q,
            None if confusion is None else confusion.loglik(ids))
        labels[ids] = cls.ids[best]
        margin[ids] = m
        if with_top:
            votes_best = np.where(best == c1, n1[ids], np.where(best == c2, n2[ids], 0))
            # 0 where no view of the point voted for the decided class: the fill's
            # confirmation rule then never protects it (the denoise decides)
            if p.confirm_needs_vote:
                supported = votes_best
                if local is not None and p.confirm_local_share < 1.0:
                    near = local[1][vrow, best] >= p.confirm_local_share
                    supported = np.where(near, np.maximum(votes_best, 1), votes_best)
            else:
                supported = np.maximum(votes_best, 1)
            top[ids] = supported.astype(np.uint16)
        return n_multi, int(np.count_nonzero(best != c1))

    starts = range(0, len(vidx), step)
    if pool is not None and len(starts) > 1:
        return list(pool.map(decide, starts))
    done = []
    for a in starts:
        report(0.3 + 0.7 * a / len(vidx), "robust decision")
        done.append(decide(a))
    return done


def _local_prior_tables(block: np.ndarray, prior: np.ndarray, p: RobustParams
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel of the neighbourhood grid, from its block vote counts ``block`` (V, C):
    (the neighbourhood's vote shares (V, C) float32, the log of those shares mixed with the
    scene's ``prior`` (V, C) float32). Computed once per voxel, gathered per point."""
    share = block / np.maximum(block.sum(axis=1, keepdims=True), 1e-9)
    mixed = share * np.float32(1.0 - p.local_mix)
    mixed += np.float32(p.local_mix) * prior.astype(np.float32)
    return share, np.log(mixed)


@numba.njit(nogil=True, cache=True)
def _vote_candidates(logpi_t: np.ndarray, c1: np.ndarray, n1: np.ndarray, c2: np.ndarray,
                     n2: np.ndarray, lp_vox: np.ndarray, vrow: np.ndarray,
                     logprior_scene: np.ndarray, logprior: np.ndarray, pw: np.float32,
                     K: int, nats: np.float32, best: np.ndarray, cand: np.ndarray,
                     lk: np.ndarray, ll: np.ndarray) -> np.ndarray:
    """Per point (one compiled pass, float32 as the model is): the log-likelihood of every
    class, ``sum_c n_c log pi[t, c]`` over the two leading vote classes plus the weighted log
    prior (with ``lp_vox`` non-empty: the neighbourhood's row ``lp_vox[vrow]`` for the classes
    the point's views did not vote for, the scene's for those they did); ``best`` its argmax
    (the first of equals). Returns the rows with a second class within ``nats`` of the best,
    and for each of those its ``K`` likeliest classes within ``nats`` in ``cand`` (by
    likelihood, the lower column first among equals) with their log-likelihoods in ``lk``
    (slots beyond them: -inf). ``ll`` non-empty ((n, C)): the votes' log-likelihood of every
    class per point (the confusion model's) instead of the pooled ``logpi_t`` rows."""
    n = c1.shape[0]
    C = logpi_t.shape[0]
    local = lp_vox.shape[0] > 0
    own = ll.shape[0] > 0
    L = np.empty(C, np.float32)
    multi = np.zeros(n, np.bool_)
    for i in range(n):
        a = max(c1[i], 0)
        w1 = np.float32(n1[i])
        w2 = np.float32(n2[i])
        b = c2[i]
        if own:
            for t in range(C):
                L[t] = ll[i, t]
        else:
            ra = logpi_t[a]
            for t in range(C):
                L[t] = ra[t] * w1
            if w2 > 0:
                rb = logpi_t[b]
                for t in range(C):
                    L[t] += rb[t] * w2
        if local:
            lv = lp_vox[vrow[i]]
            # the classes the views voted for take the scene's prior, the others the
            # neighbourhood's (each value the same float32 sum as one formula per class)
            L[a] += logprior_scene[a] * pw
            if b >= 0:
                L[b] += logprior_scene[b] * pw
            for t in range(C):
                if t != a and t != b:
                    L[t] += lv[t] * pw
        else:
            for t in range(C):
                L[t] += logprior[t]
        arg = 0
        for t in range(1, C):
            if L[t] > L[arg]:
                arg = t
        best[i] = arg
        if K < 2:
            continue
        floor = L[arg] - nats
        # the K largest within nats, kept sorted (the lower column first among equals)
        got = 0
        for t in range(C):
            v = L[t]
            if v < floor:
                continue
            if got == K and not v > lk[i, K - 1]:
                continue
            j = got if got < K else K - 1
            while j > 0 and v > lk[i, j - 1]:
                if j < K:
                    lk[i, j] = lk[i, j - 1]
                    cand[i, j] = cand[i, j - 1]
                j -= 1
            lk[i, j] = v
            cand[i, j] = t
            if got < K:
                got += 1
        if got < 2:
            continue
        multi[i] = True
        for k in range(got, K):
            lk[i, k] = -np.inf
            cand[i, k] = arg
    return multi


@numba.njit(nogil=True, cache=True)
def _gauss_row(x: np.ndarray, mean: np.ndarray, whiten: np.ndarray, logdet: np.float32,
               d: np.ndarray) -> np.float32:
    """The Gaussian log-density of one feature row (float32, as :func:`_gauss_loglik`).
    ``whiten`` is upper triangular (the transposed Cholesky factor of :func:`_gaussian`): the
    zeros below its diagonal are skipped."""
    F = x.shape[0]
    for f in range(F):
        d[f] = x[f] - mean[f]
    ss = np.float32(0.0)
    for g in range(F):
        z = np.float32(0.0)
        for f in range(g, F):
            z += d[f] * whiten[g, f]
        ss += z * z
    return np.float32(-0.5) * (ss + logdet)


@numba.njit(nogil=True, cache=True)
def _gauss_at(x: np.ndarray, i: int, mean: np.ndarray, whiten: np.ndarray, logdet: np.ndarray,
              c: int, d: np.ndarray, z: np.ndarray) -> np.float32:
    """:func:`_gauss_row` of ``x[i]`` under class ``c`` of the stacked ``mean`` (C, F),
    ``whiten`` (C, F, F) and ``logdet`` (C,), the same float32 operations in the same order
    (each ``z[g]`` sums ``d[f] * whiten[g, f]`` over f = g..F-1 ascending, then ``ss`` sums
    ``z[g]^2`` over g ascending), with no array views per call and the F sums of the
    triangle advanced together (independent accumulators): ~40 % less time."""
    F = x.shape[1]
    for f in range(F):
        d[f] = x[i, f] - mean[c, f]
        z[f] = np.float32(0.0)
    for f in range(F):
        df = d[f]
        for g in range(f + 1):
            z[g] += df * whiten[c, g, f]
    ss = np.float32(0.0)
    for g in range(F):
        ss += z[g] * z[g]
    return np.float32(-0.5) * (ss + logdet[c])


@numba.njit(nogil=True, cache=True)
def _feature_kernel(x: np.ndarray, cand: np.ndarray, lk: np.ndarray, mean: np.ndarray,
                    whiten: np.ndarray, logdet: np.ndarray, ok: np.ndarray, p_mean: np.ndarray,
                    p_whiten: np.ndarray, p_logdet: np.float32, best: np.ndarray,
                    margin: np.ndarray) -> None:
    """Per row with several candidates: each live candidate's log-likelihood plus the point
    classifier's density of the features (the pooled density for a class without one), the
    argmax (the first of equals) and the posterior margin top - second."""
    m, K = cand.shape
    F = x.shape[1]
    d = np.empty(F, np.float32)
    z = np.empty(F, np.float32)
    post = np.empty(K, np.float32)
    pm = np.empty((1, F), np.float32)  # the pooled density, stacked as one class
    pw = np.empty((1, F, F), np.float32)
    pl = np.empty(1, np.float32)
    for f in range(F):
        pm[0, f] = p_mean[f]
        for g in range(F):
            pw[0, f, g] = p_whiten[f, g]
    pl[0] = p_logdet
    for i in range(m):
        neutral = np.float32(0.0)
        have_neutral = False
        arg = -1
        for k in range(K):
            if lk[i, k] == -np.inf:
                continue
            c = cand[i, k]
            if ok[c]:
                g = _gauss_at(x, i, mean, whiten, logdet, c, d, z)
            else:
                if not have_neutral:
                    neutral = _gauss_at(x, i, pm, pw, pl, 0, d, z)
                    have_neutral = True
                g = neutral
            lk[i, k] += g
            if arg < 0 or lk[i, k] > lk[i, arg]:
                arg = k
        best[i] = cand[i, arg]
        total = np.float32(0.0)
        for k in range(K):
            post[k] = np.exp(lk[i, k] - lk[i, arg])
            total += post[k]
        top = np.float32(0.0)
        second = np.float32(0.0)
        for k in range(K):
            v = post[k] / total
            if v > top:
                second = top
                top = v
            elif v > second:
                second = v
        margin[i] = top - second


@numba.njit(nogil=True, cache=True)
def _gather_half_rows(src: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    """``out[i]`` = the float32 bits of the IEEE halves ``src[rows[i]]`` (their uint16 bits):
    exact (every half is a float32), subnormals normalised, infinities and NaN payloads kept
    -- numpy's half to float conversion, bit for bit."""
    F = src.shape[1]
    for i in range(rows.shape[0]):
        r = rows[i]
        for j in range(F):
            h = np.uint32(src[r, j])
            sign = (h & np.uint32(0x8000)) << np.uint32(16)
            e = (h >> np.uint32(10)) & np.uint32(0x1F)
            m = h & np.uint32(0x3FF)
            if e == 0:
                if m == 0:
                    out[i, j] = sign
                    continue
                e32 = np.uint32(113)
                while (m & np.uint32(0x400)) == 0:
                    m <<= np.uint32(1)
                    e32 -= np.uint32(1)
                out[i, j] = sign | (e32 << np.uint32(23)) | ((m & np.uint32(0x3FF)) << np.uint32(13))
            elif e == 31:
                out[i, j] = sign | np.uint32(0x7F800000) | (m << np.uint32(13))
            else:
                out[i, j] = sign | ((e + np.uint32(112)) << np.uint32(23)) | (m << np.uint32(13))


@numba.njit(nogil=True, cache=True)
def _gather_u16_rows(src: np.ndarray, rows: np.ndarray, out: np.ndarray) -> None:
    F = src.shape[1]
    for i in range(rows.shape[0]):
        r = rows[i]
        for j in range(F):
            out[i, j] = src[r, j]


def half_rows(features: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``np.asarray(features[rows])`` of (N, F) features; C-contiguous float16 ones (the
    memory-mapped cache) gathered by a compiled loop over their bits (~2x less CPU than
    numpy's fancy index of 20-byte rows)."""
    f = features
    if (isinstance(f, np.ndarray) and f.dtype == np.float16 and f.ndim == 2
            and f.flags.c_contiguous):
        out = np.empty((len(rows), f.shape[1]), np.uint16)
        _gather_u16_rows(f.view(np.uint16), np.ascontiguousarray(rows, np.int64), out)
        return out.view(np.float16)
    return np.asarray(features[rows])


class RowSubset:
    """The rows ``rows`` of an (N, F) feature array, gathered only where indexed:
    ``sub[idx]`` is ``half_rows(src, rows[idx])``. :func:`redecide` reads features only at the
    classifier's training sample and at the points with several candidates, so a caller that
    decides a subset of the cloud (the review's leave-one-out labels: millions of points, most
    with one candidate) passes this instead of gathering every row first."""

    def __init__(self, src: np.ndarray, rows: np.ndarray) -> None:
        self.src = src
        self.rows = np.ascontiguousarray(rows, np.int64)

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.rows), int(self.src.shape[1]))

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, idx) -> np.ndarray:  # noqa: ANN001
        return half_rows(self.src, self.rows[idx])


def half_rows_as_float32(features: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``np.asarray(features[rows], np.float32)`` of (N, F) features: for C-contiguous float16
    ones in one compiled gather and conversion (numpy's float16 cast is ~3x slower than the
    gather itself), else through numpy. The same values (float16 -> float32 is exact).
    A :class:`RowSubset` is gathered from its source rows directly."""
    if isinstance(features, RowSubset):
        return half_rows_as_float32(features.src, features.rows[rows])
    f = features
    if (isinstance(f, np.ndarray) and f.dtype == np.float16 and f.ndim == 2
            and f.flags.c_contiguous):
        out = np.empty((len(rows), f.shape[1]), np.uint32)
        _gather_half_rows(f.view(np.uint16), np.ascontiguousarray(rows, np.int64), out)
        return out.view(np.float32)
    return np.asarray(features[rows], np.float32)


def _decide_chunk(logpi: np.ndarray, c1: np.ndarray, n1: np.ndarray, c2: np.ndarray,
                  n2: np.ndarray, logprior_scene: np.ndarray, logprior: np.ndarray,
                  local: tuple | None, K: int, p: RobustParams, features: np.ndarray,
                  ids: np.ndarray, q: _QDA, ll: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, int]:
    """The decision of one chunk of voted points ``ids``: (class column (n,), posterior margin
    (n,) float32, how many points the classifier weighed). Candidates: the ``K`` classes the
    votes and the prior make likeliest (``local``: (the per-voxel log of the mixed
    neighbourhood prior, each point's voxel row), else the scene's prior), those within
    ``candidate_nats`` of the best; a point with one candidate takes it (margin 1) without the
    classifier (most points of a survey have one). Compiled kernels, no (n, C) array."""
    n = len(ids)
    C = logpi.shape[0]
    best = np.empty(n, np.int64)
    m = np.ones(n, np.float32)
    Kc = max(1, K)
    cand = np.empty((n, Kc), np.int64)
    lk = np.empty((n, Kc), np.float32)
    lp_vox, vrow = local if local is not None else (np.zeros((0, C), np.float32),
                                                    np.zeros(0, np.int32))
    multi = _vote_candidates(
        np.ascontiguousarray(logpi.T, np.float32), c1, np.asarray(n1, np.float32), c2,
        np.asarray(n2, np.float32), lp_vox, np.asarray(vrow), logprior_scene, logprior,
        np.float32(p.prior_weight), K, np.float32(p.candidate_nats), best, cand, lk,
        np.zeros((0, C), np.float32) if ll is None else np.ascontiguousarray(ll, np.float32))
    rows = np.flatnonzero(multi)
    if len(rows) == 0:
        return best, m, 0
    cm, lm = cand[rows], lk[rows]
    b, mm = np.empty(len(rows), np.int64), np.empty(len(rows), np.float32)
    pm, pwh, pld = q.pooled
    _feature_kernel(half_rows_as_float32(features, ids[rows]), cm, lm, q.mean, q.whiten,
                    q.logdet, q.ok, np.asarray(pm, np.float32), np.asarray(pwh, np.float32),
                    np.float32(pld), b, mm)
    best[rows], m[rows] = b, mm
    return best, m, len(rows)


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the decision's kernels on a tiny input: the Docker
    image runs this at build time, so a container's first fill or review request does not
    pay the compilation."""
    C, F = 2, 2
    one = np.zeros(1, np.int64)
    best, cand, lk = np.empty(1, np.int64), np.empty((1, 2), np.int64), np.empty((1, 2), np.float32)
    z = np.zeros(C, np.float32)
    for lp_vox in (np.zeros((1, C), np.float32), np.zeros((0, C), np.float32)):
        for ll in (np.zeros((0, C), np.float32), np.zeros((1, C), np.float32)):
            _vote_candidates(np.zeros((C, C), np.float32), one, np.ones(1, np.float32), one - 1,
                             np.zeros(1, np.float32), lp_vox, np.zeros(1, np.int32), z, z,
                             np.float32(1.0), 2, np.float32(12.0), best, cand, lk, ll)
    for dt in (np.int16, np.int64):
        _group_by_class(np.arange(2, dtype=np.int64), np.array([1, 0], dt), C)
    eye = np.eye(F, dtype=np.float32)
    _feature_kernel(np.zeros((1, F), np.float32), np.array([[0, 1]]), np.zeros((1, 2), np.float32),
                    np.zeros((C, F), np.float32), np.stack([eye, eye]), z, np.array([True, False]),
                    np.zeros(F, np.float32), eye, np.float32(0.0), best, np.empty(1, np.float32))
