"""Class columns of the vote arrays: table order, tie-order majority, id lookups."""

from __future__ import annotations

import numpy as np

from occufly.taxonomy import Taxonomy


class ClassColumns:
    """Column bookkeeping: class columns in table order, priority permutation, id lookups."""

    def __init__(self, taxonomy: Taxonomy) -> None:
        self.taxonomy = taxonomy
        self.ids = taxonomy.ids  # (C,) uint8, column order
        self.C = len(self.ids)
        self.col_of = np.full(256, -1, dtype=np.int16)  # raw id -> column
        self.col_of[self.ids] = np.arange(self.C, dtype=np.int16)
        prio = taxonomy.priority_lut()[self.ids]  # rank of each column
        self.perm = np.argsort(prio, kind="stable")  # columns, most preferred first
        self.perm_ids = self.ids[self.perm]

    def winner(self, counts: np.ndarray) -> np.ndarray:
        """counts: (n, C) -> winner column (n,) int64 (tie order), -1 where all counts are 0."""
        c = np.asarray(counts)[:, self.perm]
        arg = np.argmax(c, axis=1)
        col = self.perm[arg].astype(np.int64)
        col[np.take_along_axis(c, arg[:, None], axis=1)[:, 0] <= 0] = -1
        return col

    def majority(self, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """counts: (n, C) -> (winner column (n,) int64, top (n,), second (n,)) in count units.

        Ties are broken by the taxonomy's order; winner is -1 where every count is 0.
        """
        c = np.asarray(counts)[:, self.perm]
        arg = np.argmax(c, axis=1)
        top = np.take_along_axis(c, arg[:, None], axis=1)[:, 0]
        col = self.perm[arg].astype(np.int64)
        col[top <= 0] = -1
        if self.C > 1:
            part = np.partition(c, self.C - 2, axis=1)
            second = part[:, self.C - 2]
        else:
            second = np.zeros(len(c), dtype=c.dtype)
        return col, top, second

    def labels_of(self, col: np.ndarray) -> np.ndarray:
        """(n,) column (-1 = none) -> (n,) uint8 raw ids (0 = none)."""
        out = np.zeros(len(col), dtype=np.uint8)
        ok = col >= 0
        out[ok] = self.ids[col[ok]]
        return out
