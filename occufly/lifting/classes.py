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
        # integer counts: key = count << bits | (C - 1 - rank), so one argmax over the columns
        # in table order finds the top count and, among equal counts, the preferred column
        rank = np.empty(self.C, np.int64)
        rank[self.perm] = np.arange(self.C)
        self._bits = max(1, int(self.C - 1).bit_length())
        self._tie_key = (self.C - 1 - rank)

    def winner(self, counts: np.ndarray) -> np.ndarray:
        """counts: (n, C) -> winner column (n,) int64 (tie order), -1 where all counts are 0.

        Unsigned integer counts take one pass over a packed key (:meth:`packed_winner`);
        anything else goes through :meth:`majority`.
        """
        c = np.asarray(counts)
        if not len(c):
            return np.zeros(0, np.int64)
        packed = self.packed_winner(c)
        return self.majority(c)[0] if packed is None else packed[0]

    def key_dtype(self, max_count: int) -> type | None:
        """The narrowest unsigned dtype whose packed key holds counts up to ``max_count``."""
        for dt in (np.uint16, np.uint32, np.uint64):
            if int(max_count) < (1 << (8 * np.dtype(dt).itemsize - self._bits)):
                return dt
        return None

    def packed_winner(self, counts: np.ndarray, dt: type | None = None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
        """(winner column (n,) int64, -1 = none; winner key (n,)) of unsigned integer counts,
        or None for other input. key = count << bits | (C - 1 - rank): one argmax over the
        columns in table order finds the top count and, among equal counts, the column the
        taxonomy's tie order prefers -- the same winner as :meth:`majority`, without
        reordering the columns. ``dt``: the key dtype (default: from the counts' maximum)."""
        c = np.asarray(counts)
        if c.ndim != 2 or not np.issubdtype(c.dtype, np.unsignedinteger):
            return None
        if dt is None:
            dt = self.key_dtype(int(c.max()) if c.size else 0)
            if dt is None:
                return None
        key = c.astype(dt)
        key <<= dt(self._bits)
        key |= self._tie_key.astype(dt)
        col = np.argmax(key, axis=1).astype(np.int64)
        kmax = np.take_along_axis(key, col[:, None], axis=1)[:, 0]
        col[kmax >> dt(self._bits) == 0] = -1
        return col, kmax

    def pack(self, count: np.ndarray, col: np.ndarray, dt: type) -> np.ndarray:
        """Packed keys of ``count`` votes for columns ``col`` (see :meth:`packed_winner`)."""
        return (np.asarray(count).astype(dt) << dt(self._bits)) | self._tie_key[col].astype(dt)

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
