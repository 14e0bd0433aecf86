"""The one confusion matrix behind every label metric (SSC, scene grid, points, 2-D agreement).

Rows are the reference (ground truth, or the annotator's mask), columns the prediction
(or the rendering). Raw class ids are mapped through a lookup table to *compact columns*:

====================  ==================================================================
column 0              empty (raw id 0)
columns 1 .. C        the C taxonomy classes, in table order
column C + 1          "other": any raw id that is not 0 and not a taxonomy class
                      (255 too, unless the caller filters or remaps it first)
====================  ==================================================================

Each metric decides which items it evaluates (``keep``) and what a 255 prediction means
before calling :meth:`Confusion.add`; the counting and every derived figure live here.

**Rule for absent classes (all metrics).** A class with TP + FP + FN = 0 -- absent from both
the reference and the prediction over everything evaluated -- has no IoU: it is reported as
n/a (``None``, or left out of listings that only show present classes) and is left out of
the mean IoU. Every class present in the reference *or* the prediction enters the mean,
with IoU 0 when it never matches. The "other" column is never a class of its own: an
unknown predicted id is simply wrong (an FP of nobody, an FN of the reference class).

Counting is ``np.bincount(row * n + col)`` in chunks (bounded memory on large grids).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

_CHUNK = 1 << 24  # items per bincount pass: ~16 M (int64 temporaries ~ 400 MB at most)


class Confusion:
    """A (C + 2) x (C + 2) int64 confusion matrix over compact columns (see module doc)."""

    def __init__(self, class_ids) -> None:
        self.class_ids = np.asarray(class_ids, dtype=np.uint8).reshape(-1)
        if len(np.unique(self.class_ids)) != len(self.class_ids):
            raise ValueError("class ids must be distinct")
        if np.any(self.class_ids == 0):
            raise ValueError("raw id 0 is 'empty', not a class")
        self.n = len(self.class_ids) + 2
        self.lut = np.full(256, self.n - 1, dtype=np.int64)
        self.lut[0] = 0
        self.lut[self.class_ids] = np.arange(1, len(self.class_ids) + 1)
        self.matrix = np.zeros((self.n, self.n), dtype=np.int64)

    @property
    def C(self) -> int:
        return len(self.class_ids)

    # ---- counting ----------------------------------------------------------------------------
    def add(self, truth: np.ndarray, pred: np.ndarray, keep: np.ndarray | None = None) -> Confusion:
        """Count items of ``truth`` / ``pred`` (same shape, raw uint8 ids) where ``keep``."""
        t = np.asarray(truth).reshape(-1)
        p = np.asarray(pred).reshape(-1)
        if t.shape != p.shape:
            raise ValueError(f"truth has {t.size} items, prediction {p.size}")
        k = None if keep is None else np.asarray(keep, dtype=bool).reshape(-1)
        if k is not None and k.shape != t.shape:
            raise ValueError(f"keep has {k.size} items, truth {t.size}")
        n = self.n
        for s in range(0, t.size, _CHUNK):
            ts, ps = t[s : s + _CHUNK], p[s : s + _CHUNK]
            if k is not None:
                ks = k[s : s + _CHUNK]
                ts, ps = ts[ks], ps[ks]
            idx = self.lut[ts] * n + self.lut[ps]
            self.matrix += np.bincount(idx, minlength=n * n).reshape(n, n)
        return self

    def add_all_pairs(self, truth: np.ndarray, pred: np.ndarray) -> np.ndarray:
        """Count every item of ``truth`` / ``pred`` (same shape, uint8 raw ids) in one compiled
        pass (a 20 MP mask pair in ~0.05 s instead of the ~0.8 s of lookup + bincount), and
        return that (n, n) count of all pairs without adding it: the caller keeps the part
        it evaluates (the 2-D agreement keeps class x class, see ``occufly.render.agreement``)
        and :meth:`merge_counts` it."""
        t = np.ascontiguousarray(truth, dtype=np.uint8).reshape(-1)
        p = np.ascontiguousarray(pred, dtype=np.uint8).reshape(-1)
        if t.shape != p.shape:
            raise ValueError(f"truth has {t.size} items, prediction {p.size}")
        out = np.zeros((self.n, self.n), np.int64)
        _count_pairs(t, p, self.lut, out)
        return out

    def merge_counts(self, counts: np.ndarray) -> Confusion:
        """Add an (n, n) count over compact columns (as :meth:`add_all_pairs` returns it)."""
        self.matrix += np.asarray(counts, dtype=np.int64).reshape(self.n, self.n)
        return self

    def merge(self, other: Confusion) -> Confusion:
        if not np.array_equal(self.class_ids, other.class_ids):
            raise ValueError("cannot merge confusion matrices over different classes")
        self.matrix += other.matrix
        return self

    @classmethod
    def from_class_matrix(cls, class_ids, matrix) -> Confusion:
        """Rebuild from a C x C class-only matrix (as :meth:`class_matrix` returns it)."""
        c = cls(class_ids)
        m = np.asarray(matrix, dtype=np.int64)
        if m.shape != (c.C, c.C):
            raise ValueError(f"matrix {m.shape} does not match {c.C} classes")
        c.matrix[1 : c.C + 1, 1 : c.C + 1] = m
        return c

    # ---- derived figures ---------------------------------------------------------------------
    def class_matrix(self) -> np.ndarray:
        """(C, C) counts among the taxonomy classes only."""
        return self.matrix[1 : self.C + 1, 1 : self.C + 1]

    def truth_counts(self) -> np.ndarray:
        """(C,) items per class in the reference (row sums over every prediction column)."""
        return self.matrix[1 : self.C + 1, :].sum(axis=1)

    def pred_counts(self) -> np.ndarray:
        """(C,) items per class in the prediction (column sums over every reference row)."""
        return self.matrix[:, 1 : self.C + 1].sum(axis=0)

    def tp(self) -> np.ndarray:
        return np.diag(self.matrix)[1 : self.C + 1].copy()

    def class_iou(self) -> np.ndarray:
        """(C,) float64 IoU = TP / (TP + FP + FN); NaN where a class is absent (denominator 0)."""
        tp = self.tp().astype(np.float64)
        union = self.truth_counts() + self.pred_counts() - tp
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(union > 0, tp / np.maximum(union, 1), np.nan)

    def present(self) -> np.ndarray:
        """(C,) bool: the class occurs in the reference or the prediction."""
        return (self.truth_counts() + self.pred_counts()) > 0

    def per_class_iou(self, names: list[str] | None = None) -> dict[str, float | None]:
        """{name: IoU or None (absent)} for every class, in table order."""
        names = names if names is not None else [str(int(i)) for i in self.class_ids]
        return {nm: (None if np.isnan(v) else float(v))
                for nm, v in zip(names, self.class_iou(), strict=True)}

    def miou(self) -> float | None:
        """Mean IoU over the present classes (the absent-class rule); None if none is present."""
        v = self.class_iou()
        v = v[~np.isnan(v)]
        return float(v.mean()) if v.size else None

    def classes_evaluated(self) -> int:
        return int(self.present().sum())

    def total(self) -> int:
        return int(self.matrix.sum())

    def correct(self) -> int:
        """Items where prediction equals reference on a class (empty/other agreement excluded)."""
        return int(self.tp().sum())

    def completion(self) -> dict[str, float | None]:
        """Occupied (any column but 0) vs empty: IoU, precision, recall; None where 0/0."""
        m = self.matrix
        tp = float(m[1:, 1:].sum())
        fp = float(m[0, 1:].sum())
        fn = float(m[1:, 0].sum())
        return {"iou": _div(tp, tp + fp + fn), "precision": _div(tp, tp + fp),
                "recall": _div(tp, tp + fn)}


def _div(a: float, b: float) -> float | None:
    return float(a / b) if b > 0 else None


@numba.njit(nogil=True, cache=True)
def _count_pairs(t: np.ndarray, p: np.ndarray, lut: np.ndarray, out: np.ndarray) -> None:
    for i in range(t.shape[0]):
        out[lut[t[i]], lut[p[i]]] += 1


@numba.njit(nogil=True, cache=True)
def _count_pairs_many(t: np.ndarray, preds: tuple, lut: np.ndarray, out: np.ndarray) -> None:
    for i in range(t.shape[0]):
        a = lut[t[i]]
        for j in range(len(preds)):
            out[j, a, lut[preds[j][i]]] += 1


def count_pairs_many(class_ids, truth: np.ndarray, preds: list[np.ndarray], *,
                     workers: int = 1) -> list[np.ndarray]:
    """:meth:`Confusion.add_all_pairs` of one ``truth`` against each of ``preds`` (uint8 raw
    ids, all the same shape), in one compiled pass that reads ``truth`` once; with ``workers``
    > 1 the pixels are split into that many contiguous runs counted by as many threads (the
    compiled loop holds no interpreter lock) and the counts summed: the same integers."""
    c = Confusion(class_ids)
    t = np.ascontiguousarray(truth, dtype=np.uint8).reshape(-1)
    ps = tuple(np.ascontiguousarray(p, dtype=np.uint8).reshape(-1) for p in preds)
    for p in ps:
        if p.shape != t.shape:
            raise ValueError(f"truth has {t.size} items, prediction {p.size}")
    n = max(1, min(int(workers), t.size // _MIN_PAIRS_PER_WORKER))
    out = np.zeros((n, len(ps), c.n, c.n), np.int64)
    if ps:
        cuts = np.linspace(0, t.size, n + 1).astype(np.int64)

        def run(k: int) -> None:
            a, b = cuts[k], cuts[k + 1]
            _count_pairs_many(t[a:b], tuple(p[a:b] for p in ps), c.lut, out[k])

        if n == 1:
            run(0)
        else:
            with ThreadPoolExecutor(max_workers=n, thread_name_prefix="occufly-pairs") as pool:
                list(pool.map(run, range(n)))
    return list(out.sum(axis=0))


# pixels below which a second counting thread costs more than it saves
_MIN_PAIRS_PER_WORKER = 1 << 20
