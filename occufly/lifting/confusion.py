"""Per-annotator confusion model of the votes (Dawid-Skene EM; issue 37, fourth round).

The robust decision (:mod:`occufly.lifting.robust`) pools every view into one confusion matrix
and reads only each point's two leading vote classes. Here every *annotator* has a matrix of
its own, ``pi[a, t, c]`` = P(annotator ``a`` votes ``c`` | true class ``t``), estimated by EM
from every vote of every frame (``ws/lifting/frames/*.npz``):

Annotators
    Who painted a frame's mask, when the caller knows it (``annotators``: frame -> id; the
    app's mask versions have an author), else every frame is an annotator of its own (the
    votes store keeps the mask's version tag, not its author). A sloppy painter's one-way
    confusion (every grass region painted vegetation) shows in his own frames' matrices and
    not in the others', so where a careful view votes grass and his votes vegetation, grass
    wins (``pi_careful[veg, grass]`` is small, ``pi_sloppy[grass, veg]`` is not); where only
    his frames see a point, his vote carries no evidence between the two classes and the
    robust decision's point classifier decides.
Prior
    Dirichlet pseudo-votes per row: ``diag_prior`` on the diagonal, ``pooled_prior`` spread
    along the pooled matrix's row (all annotators' expected counts together, itself with the
    diagonal prior) and ``off_prior`` on every entry, so a class an annotator voted a handful
    of times, or an annotator with few votes, keeps a matrix near the diagonal and the pool.
EM
    Initialised from given labels (the default robust decision's: one-hot posteriors) or the
    vote shares; M-step: expected (annotator, true, voted) counts; E-step: ``post(t) ~
    prior(t) prod_v pi[a_v, t, c_v]``. Fitted on a seeded sample of ``sample`` voted points
    (all their votes); :meth:`ConfusionModel.loglik` then gives every point's vote
    log-likelihood ``sum_v w_v log pi[a_v, t, c_v]`` (no prior: the robust decision adds its
    own). Vectorised: the votes sorted by point once, per-point sums by ``np.add.reduceat``,
    the M-step as one sparse product per chunk; nothing loops over points in Python.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import sparse


@dataclass
class ConfusionParams:
    """Parameters of :func:`fit_confusion` (written down before any measurement: docs/lifting.md)."""

    iterations: int = 3
    diag_prior: float = 10.0    # pseudo-votes on each annotator's diagonal, per true class
    pooled_prior: float = 10.0  # pseudo-votes along the pooled matrix's row (shrinkage to the pool)
    off_prior: float = 0.05     # pseudo-votes on every entry
    sample: int = 500_000       # voted points the EM is fitted on (seeded); 0 = all
    train_min_posterior: float = 0.5  # classifier training: unanimous points whose class the
    #                                   model gives at least this posterior (0 = no filter)
    chunk: int = 200_000        # points per block of the E-step
    seed: int = 0


@dataclass
class VoteTable:
    """Every vote of every frame, sorted by point.

    pid: (V,) int32 point ids ascending; col: (V,) int16 voted class column; ann: (V,) int32
    annotator index; w: (V,) float32 weight in views (1 with plain votes); indptr: (N + 1,)
    int64 the votes of point ``i`` are ``indptr[i]:indptr[i + 1]``; names: annotator ids."""

    pid: np.ndarray
    col: np.ndarray
    ann: np.ndarray
    w: np.ndarray
    indptr: np.ndarray
    names: list

    @property
    def n_annotators(self) -> int:
        return len(self.names)


def annotator_index(frames: list[int], annotators: dict | None) -> tuple[list[int], list]:
    """Each frame's annotator index and the annotators' ids (``("author", id)`` for a frame
    ``annotators`` names, else ``("frame", index)``: its own), in the order first seen."""
    names: list = []
    index: dict = {}
    of = []
    for f in frames:
        key = ("author", annotators[f]) if annotators and f in annotators else ("frame", int(f))
        of.append(index.setdefault(key, len(names)))
        if of[-1] == len(names):
            names.append(key)
    return of, names


def point_order(pid: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """The (V,) order that sorts votes by point (stable: frames keep their order per point)
    and the (N + 1,) int64 indptr of the sorted votes: point ``i``'s are
    ``indptr[i]:indptr[i + 1]``."""
    order = np.argsort(pid, kind="stable")
    indptr = np.zeros(n_points + 1, np.int64)
    np.cumsum(np.bincount(pid, minlength=n_points), out=indptr[1:])
    return order, indptr


def vote_table(frames: dict[int, tuple], n_points: int, annotators: dict | None = None,
               unit: int = 1) -> VoteTable:
    """frames: frame -> (point ids, class columns[, weights]) as stored per frame;
    annotators: frame -> annotator id (None or a frame missing from it: the frame is its own
    annotator); unit: counts per view of the weights."""
    voted = [f for f in sorted(frames) if len(frames[f][0])]
    ann_of, names = annotator_index(voted, annotators)
    parts = []
    for f, a in zip(voted, ann_of, strict=True):
        v = frames[f]
        pids = np.asarray(v[0], np.int32)
        w = (np.asarray(v[2], np.float32) / unit if len(v) > 2 and v[2] is not None
             else np.ones(len(pids), np.float32))
        parts.append((pids, np.asarray(v[1], np.int16), np.full(len(pids), a, np.int32), w))
    if not parts:
        z = np.zeros(0, np.int32)
        return VoteTable(z, z.astype(np.int16), z, z.astype(np.float32),
                         np.zeros(n_points + 1, np.int64), names)
    pid, col, ann, w = (np.concatenate([p[i] for p in parts]) for i in range(4))
    keep = w > 0
    if not keep.all():
        pid, col, ann, w = pid[keep], col[keep], ann[keep], w[keep]
    order, indptr = point_order(pid, n_points)
    return VoteTable(pid[order], col[order], ann[order], w[order], indptr, names)


def model_record(model: ConfusionModel, frames: dict, annotators: dict | None,
                 class_ids) -> dict:  # noqa: ANN001
    """What the review's leave-one-out decision needs of a fitted model, for ``labels.json``
    (``confusion_model``): the class ids, the annotators' ids, each voting frame's annotator
    index, the (A, C, C) log matrices and the class prior (5 significant digits)."""
    voted = [f for f in sorted(frames) if len(frames[f][0])]
    of, names = annotator_index(voted, annotators)
    return {"class_ids": [int(i) for i in class_ids],
            "names": [[str(k), v if isinstance(v, (int, str)) else str(v)] for k, v in names],
            "frames": {str(int(f)): int(a) for f, a in zip(voted, of, strict=True)},
            "logpi": np.round(np.asarray(model.logpi, np.float64), 5).tolist(),
            "prior": [float(f"{x:.6g}") for x in np.asarray(model.prior, np.float64)],
            # expected votes behind each row (in the EM's sample; how sure each row is)
            "support": (np.rint(np.asarray(model.support, np.float64)).astype(int).tolist()
                        if model.support is not None else None)}


def model_from_record(rec: dict, class_ids) -> tuple[np.ndarray, np.ndarray, dict] | None:  # noqa: ANN001
    """(logpi (A, C, C) float32, prior (C,), frame -> annotator index) of a
    :func:`model_record`, or None when it does not fit ``class_ids`` or is malformed."""
    if not isinstance(rec, dict) or [int(i) for i in rec.get("class_ids") or []] != \
            [int(i) for i in class_ids]:
        return None
    try:
        logpi = np.asarray(rec["logpi"], np.float32)
        prior = np.asarray(rec["prior"], np.float64)
        frames = {int(k): int(v) for k, v in rec["frames"].items()}
    except (KeyError, TypeError, ValueError, AttributeError):
        return None
    C = len(class_ids)
    if logpi.ndim != 3 or logpi.shape[1:] != (C, C) or prior.shape != (C,) or \
            not np.isfinite(logpi).all() or any(not 0 <= a < len(logpi) for a in frames.values()):
        return None
    return logpi, prior, frames


def load_frame_votes(ws: str | Path, frames: list[int]) -> dict[int, tuple]:
    """frame -> (point ids, columns, weights) of the given frames' vote files in ``ws``
    (frames without a file are left out)."""
    from occufly.workspace import Workspace

    w_s = Workspace(ws)
    return {int(f): got for f in frames if (got := w_s.read_frame_votes(f)) is not None}


def _gather(t: VoteTable, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vote indices of the points ``ids`` in order, per-point vote counts)."""
    start = t.indptr[ids]
    lens = t.indptr[ids + 1] - start
    total = int(lens.sum())
    if total == 0:
        return np.zeros(0, np.int64), lens
    before = np.cumsum(lens) - lens
    idx = np.repeat(start - before, lens) + np.arange(total, dtype=np.int64)
    return idx, lens


class ConfusionModel:
    """A fitted per-annotator confusion model over a :class:`VoteTable`."""

    def __init__(self, table: VoteTable, logpi: np.ndarray, prior: np.ndarray,
                 params: ConfusionParams, stats: dict, support: np.ndarray | None = None):
        self.table = table
        self.logpi = logpi  # (A, C, C) float32 log pi[a, true, voted]
        self.prior = prior  # (C,) float64 the EM's class prior
        self.params = params
        self.stats = stats
        # (A, C) the expected votes of each annotator on each true class in the fitted sample
        # (the data behind each row of its matrix; None where not fitted)
        self.support = support
        A, C, _ = logpi.shape
        # row (a * C + voted) -> log pi[a, :, voted]: one gather per vote
        self._rows = np.ascontiguousarray(logpi.transpose(0, 2, 1).reshape(A * C, C))

    @property
    def C(self) -> int:
        return self.logpi.shape[1]

    def loglik(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids), C) float32: ``sum_v w_v log pi[a_v, t, c_v]`` over each point's votes
        (0 for a point without votes)."""
        ids = np.asarray(ids, np.int64)
        out = np.zeros((len(ids), self.C), np.float32)
        ch = max(1, self.params.chunk)
        for a in range(0, len(ids), ch):
            out[a:a + ch] = _loglik_block(self.table, self._rows, ids[a:a + ch], self.C)
        return out

    def posterior(self, ids: np.ndarray) -> np.ndarray:
        """(len(ids), C) float32 posterior with the EM's class prior."""
        L = self.loglik(ids) + np.log(self.prior).astype(np.float32)
        L -= L.max(axis=1, keepdims=True)
        np.exp(L, out=L)
        L /= L.sum(axis=1, keepdims=True)
        return L

    def class_posterior(self, ids: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(len(ids),) float32: the posterior of class column ``cols[i]`` at point ``ids[i]``
        (chunked: no (len(ids), C) array)."""
        ids = np.asarray(ids, np.int64)
        cols = np.asarray(cols, np.int64)
        out = np.zeros(len(ids), np.float32)
        ch = max(1, self.params.chunk)
        for a in range(0, len(ids), ch):
            post = self.posterior(ids[a:a + ch])
            out[a:a + ch] = post[np.arange(len(post)), cols[a:a + ch]]
        return out

    def matrix(self, annotator: int) -> np.ndarray:
        """(C, C) float64 pi of one annotator (rows: true class)."""
        return np.exp(self.logpi[annotator].astype(np.float64))


def _loglik_block(t: VoteTable, rows: np.ndarray, ids: np.ndarray, C: int) -> np.ndarray:
    idx, lens = _gather(t, ids)
    out = np.zeros((len(ids), C), np.float32)
    if len(idx) == 0:
        return out
    g = rows[t.ann[idx].astype(np.int64) * C + t.col[idx]]
    if not np.all(t.w[idx] == 1.0):
        g *= t.w[idx][:, None]
    has = lens > 0
    starts = (np.cumsum(lens) - lens)[has]
    out[has] = np.add.reduceat(g, starts, axis=0)
    return out


def fit_confusion(table: VoteTable, C: int, init_labels: np.ndarray | None = None,
                  params: ConfusionParams | None = None) -> ConfusionModel:
    """EM of the per-annotator confusion matrices (module docstring). ``init_labels``: (N,)
    class columns (-1 = none) of a first decision to start from; None: the vote shares."""
    p = params or ConfusionParams()
    A = max(1, table.n_annotators)
    voted = np.flatnonzero(np.diff(table.indptr) > 0)
    stats: dict = {"confusion_annotators": table.n_annotators, "confusion_votes": len(table.pid),
                   "confusion_points": int(len(voted))}
    eye = np.eye(C)
    if len(voted) == 0:
        pi = np.broadcast_to(eye * 0.9 + 0.1 / C, (A, C, C))
        return ConfusionModel(table, np.log(pi).astype(np.float32), np.full(C, 1.0 / C), p, stats)
    ids = voted
    if p.sample and len(ids) > p.sample:
        rng = np.random.default_rng(p.seed)
        ids = np.sort(rng.choice(ids, p.sample, replace=False))
    idx, lens = _gather(table, ids)
    key = table.ann[idx].astype(np.int64) * C + table.col[idx]
    local = np.repeat(np.arange(len(ids)), lens)
    # (A * C, m): vote weight of (annotator, voted class) on each sampled point
    S = sparse.csr_matrix((table.w[idx].astype(np.float64), (key, local)), shape=(A * C, len(ids)))
    if init_labels is not None:
        lab = np.asarray(init_labels)[ids].astype(np.int64)
        post = np.zeros((len(ids), C), np.float64)
        ok = lab >= 0
        post[np.flatnonzero(ok), lab[ok]] = 1.0
        if not ok.all():  # no label: the point's vote shares
            post[~ok] = _vote_shares(S, ~ok, A, C)
    else:
        post = _vote_shares(S, np.ones(len(ids), bool), A, C)
    for _ in range(max(1, p.iterations)):
        # M-step: expected counts E[a, t, c] = sum over a's votes c of post[point, t]
        E = np.asarray(S @ post).reshape(A, C, C).transpose(0, 2, 1)  # (A, true, voted)
        pooled = E.sum(axis=0) + p.off_prior + p.diag_prior * eye
        pooled /= pooled.sum(axis=1, keepdims=True)
        Acnt = E + p.off_prior + p.diag_prior * eye + p.pooled_prior * pooled
        pi = Acnt / Acnt.sum(axis=2, keepdims=True)
        prior = post.sum(axis=0) + 1.0
        prior /= prior.sum()
        # E-step on the sample, in blocks (float32 gathers, as ConfusionModel.loglik)
        rows = np.ascontiguousarray(np.log(pi).transpose(0, 2, 1).reshape(A * C, C), np.float32)
        L = np.empty((len(ids), C), np.float64)
        ch = max(1, p.chunk)
        for a in range(0, len(ids), ch):
            L[a:a + ch] = _loglik_block(table, rows, ids[a:a + ch], C)
        L += np.log(prior)
        L -= L.max(axis=1, keepdims=True)
        post = np.exp(L)
        post /= post.sum(axis=1, keepdims=True)
    stats["confusion_sample_points"] = int(len(ids))
    stats["confusion_sample_votes"] = int(len(idx))
    return ConfusionModel(table, np.log(pi).astype(np.float32), prior, p, stats,
                          support=E.sum(axis=2))


def _vote_shares(S: sparse.csr_matrix, sel: np.ndarray, A: int, C: int) -> np.ndarray:
    """(sel.sum(), C) each selected point's vote shares over the classes (annotators summed)."""
    fold = sparse.csr_matrix((np.ones(A * C), (np.arange(A * C), np.tile(np.arange(C), A))),
                             shape=(A * C, C))
    M = np.asarray((S[:, np.flatnonzero(sel)].T @ fold).todense(), np.float64)
    tot = M.sum(axis=1, keepdims=True)
    return np.where(tot > 0, M / np.maximum(tot, 1e-12), 1.0 / C)
