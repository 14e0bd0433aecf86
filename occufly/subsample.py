"""Compiled kernels for choosing and binning a few million points out of tens of millions.

The 3D viewer's level of detail picks a stratified subsample of a survey's points (2 M of 32 M,
a quota per class) and bins it into region tiles each time a scene is opened; with numpy that
took ~1 s of the first picture (a sorted ``rng.choice`` of ranks per class, a comparison and
``flatnonzero`` per class and chunk, then reductions over an (N, 2) array along axis 0).

- :func:`selection_sample` -- one pass over the labels, Knuth's selection sampling (Algorithm S)
  per class: every subset of ``quota[c]`` points of class ``c`` is equally likely, the count is
  exact, the result comes out sorted. Deterministic for a seed.
- :func:`tile_groups` -- the points' xy bounds and their ``tiles`` x ``tiles`` cell, in two
  passes over the chosen rows of a (memory-mapped) cloud; the same float64 arithmetic as
  ``((xy - lo) / span * tiles).astype(int64)``, so the cells are identical.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def _selection(labels: np.ndarray, quota: np.ndarray, count: np.ndarray, total: int,
               seed: int) -> np.ndarray:
    # uniforms from splitmix64 (a few ns each, not numpy's generator: one per point of a class
    # that is only partly taken, i.e. ~all 32 M of a survey)
    # the first state: the seed through splitmix64's finaliser (seed * constant alone made
    # seed s + 1's stream seed s's, one step on)
    z = np.uint64(seed) ^ np.uint64(0x632BE59BD9B4E019)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    state = z ^ (z >> np.uint64(31))
    scale = 1.0 / 9007199254740992.0  # 2**-53
    need = quota.copy()
    left = count.copy()
    out = np.empty(total, np.int64)
    k = 0
    for i in range(labels.shape[0]):
        c = labels[i]
        n = need[c]
        if n > 0:
            r = left[c]
            take = n >= r
            if not take:
                state += np.uint64(0x9E3779B97F4A7C15)
                z = state
                z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
                z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
                z = z ^ (z >> np.uint64(31))
                take = np.float64(z >> np.uint64(11)) * scale * r < n
            if take:
                out[k] = i
                k += 1
                need[c] = n - 1
        left[c] -= 1
    return out[:k]


def selection_sample(labels: np.ndarray, quotas: np.ndarray, counts: np.ndarray, *,
                     seed: int = 0) -> np.ndarray:
    """Sorted int64 indices: ``quotas[c]`` points of each class ``c`` of ``labels`` ((N,) uint8),
    chosen uniformly without replacement. ``counts``: (256,) points per class of ``labels``
    (exact: a wrong count biases the choice towards the end and is refused when it
    is too small to hold a quota)."""
    lab = np.asarray(labels)
    if lab.dtype != np.uint8:
        raise TypeError(f"labels: expected uint8 class ids, got {lab.dtype}")
    q = np.zeros(256, np.int64)
    q[:len(quotas)] = np.asarray(quotas, np.int64)[:256]
    c = np.zeros(256, np.int64)
    c[:len(counts)] = np.asarray(counts, np.int64)[:256]
    if (q < 0).any() or (q > c).any():
        raise ValueError("quotas: expected 0 <= quota <= count for every class")
    return _selection(lab, q, c, int(q.sum()), int(seed) & 0xFFFFFFFF)


@numba.njit(nogil=True, cache=True)
def _bounds_xy(xyz: np.ndarray, ids: np.ndarray) -> np.ndarray:
    out = np.empty(4, np.float64)  # x lo, y lo, x hi, y hi
    out[0] = out[1] = np.inf
    out[2] = out[3] = -np.inf
    for j in range(ids.shape[0]):
        i = ids[j]
        x = np.float64(xyz[i, 0])
        y = np.float64(xyz[i, 1])
        out[0] = min(out[0], x)
        out[1] = min(out[1], y)
        out[2] = max(out[2], x)
        out[3] = max(out[3], y)
    return out


@numba.njit(nogil=True, cache=True)
def _cells(xyz: np.ndarray, ids: np.ndarray, lo0: float, lo1: float, sp0: float, sp1: float,
           tiles: int) -> np.ndarray:
    out = np.empty(ids.shape[0], np.int16)
    for j in range(ids.shape[0]):
        i = ids[j]
        cx = np.int64((np.float64(xyz[i, 0]) - lo0) / sp0 * tiles)
        cy = np.int64((np.float64(xyz[i, 1]) - lo1) / sp1 * tiles)
        out[j] = 1 + min(cx, tiles - 1) * tiles + min(cy, tiles - 1)
    return out


def tile_groups(xyz: np.ndarray, ids: np.ndarray, tiles: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(group, lo, hi): ``group`` (len(ids),) int16 ``1 + cx * tiles + cy``, the cell of each
    point ``xyz[ids]`` in a ``tiles`` x ``tiles`` grid over their xy bounds ``lo``, ``hi``
    ((2,) float64; the span is at least 1e-6)."""
    ids = np.ascontiguousarray(ids, np.int64)
    if len(ids) == 0:
        raise ValueError("tile_groups: no points")
    b = _bounds_xy(xyz, ids)
    lo, hi = b[:2].copy(), b[2:].copy()
    span = np.maximum(hi - lo, 1e-6)
    return _cells(xyz, ids, lo[0], lo[1], span[0], span[1], int(tiles)), lo, hi


def warm() -> None:
    """Load the compiled kernels (from numba's cache) for the arrays a scene has, writable and
    read-only (memory-mapped): a process's first call otherwise pays numba's start-up and the
    load, ~1-1.5 s, in the first picture of a scene."""
    counts = np.zeros(256, np.int64)
    counts[0] = 4
    quotas = np.zeros(256, np.int64)
    quotas[0] = 2
    ids = np.arange(2, dtype=np.int64)
    for readonly in (False, True):
        lab = np.zeros(4, np.uint8)
        lab.flags.writeable = not readonly
        selection_sample(lab, quotas, counts)
        for dtype in (np.float32, np.float64):
            xyz = np.zeros((2, 3), dtype)
            xyz.flags.writeable = not readonly
            tile_groups(xyz, ids, 2)
