"""Grid placement, point binning and per-voxel majority votes.

All functions here work on *linear voxel keys* (``int64``, C order over the grid shape) so the
densification steps can exchange sparse voxel sets without building dense arrays until the
final aggregation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SceneGridSpec:
    """Where a scene grid lies.

    origin: (3,) float64 WORLD metres of the min corner of voxel (0, 0, 0);
    local_origin: (3,) float64 the same corner in scene-local metres (origin - scene.origin);
    shape: (X, Y, Z) voxel counts; voxel_size: edge length in metres.
    """

    origin: np.ndarray
    local_origin: np.ndarray
    shape: tuple[int, int, int]
    voxel_size: float

    @property
    def n_voxels(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def ijk_of_local(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxel of each point.

        xyz: (N, 3) float32/float64, scene-local metres.
        Returns (ijk (N, 3) int64 clipped into the grid, inside (N,) bool).
        """
        f = np.floor((np.asarray(xyz, dtype=np.float64) - self.local_origin) / self.voxel_size)
        shape = np.asarray(self.shape)
        inside = np.all((f >= 0) & (f < shape), axis=1)
        return np.clip(f, 0, shape - 1).astype(np.int64), inside

    def keys_of_local(self, xyz: np.ndarray, chunk: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
        """Linear voxel key of each point (chunked, O(chunk) temporaries).

        xyz: (N, 3) float32, scene-local metres. Returns (keys (N,) int64, inside (N,) bool);
        keys of outside points are meaningless (mask them with ``inside``).
        """
        n = len(xyz)
        keys = np.empty(n, dtype=np.int64)
        inside = np.empty(n, dtype=bool)
        for a in range(0, n, chunk):
            ijk, ins = self.ijk_of_local(xyz[a : a + chunk])
            keys[a : a + chunk] = self.linear(ijk)
            inside[a : a + chunk] = ins
        return keys, inside

    def linear(self, ijk: np.ndarray) -> np.ndarray:
        """ijk: (N, 3) int64 in-grid indices -> (N,) int64 C-order linear keys."""
        return np.ravel_multi_index((ijk[:, 0], ijk[:, 1], ijk[:, 2]), self.shape)

    def unravel(self, keys: np.ndarray) -> np.ndarray:
        """(N,) int64 linear keys -> (N, 3) int64 ijk."""
        return np.stack(np.unravel_index(keys, self.shape), axis=1).astype(np.int64)

    def centers_local(self, ijk: np.ndarray) -> np.ndarray:
        """ijk: (N, 3) int -> (N, 3) float64 voxel centres, scene-local metres."""
        return self.local_origin + (np.asarray(ijk, dtype=np.float64) + 0.5) * self.voxel_size


def grid_spec_for(
    lo_local: np.ndarray,
    hi_local: np.ndarray,
    scene_origin: np.ndarray,
    voxel_size: float,
    *,
    pad: int = 2,
) -> SceneGridSpec:
    """A grid covering the local box [lo, hi] plus ``pad`` voxels on every side.

    lo_local, hi_local: (3,) scene-local metres. The world origin is snapped to a multiple of
    ``voxel_size`` so grids of the same scene (and the synthetic truth) share one lattice.
    """
    if not voxel_size > 0:
        raise ValueError(f"voxel_size must be > 0, got {voxel_size}")
    scene_origin = np.asarray(scene_origin, dtype=np.float64).reshape(3)
    lo_w = scene_origin + np.asarray(lo_local, dtype=np.float64)
    hi_w = scene_origin + np.asarray(hi_local, dtype=np.float64)
    origin = (np.floor(lo_w / voxel_size) - pad) * voxel_size
    shape = np.floor((hi_w - origin) / voxel_size).astype(np.int64) + 1 + pad
    shape = np.maximum(shape, 1)
    return SceneGridSpec(
        origin=origin,
        local_origin=origin - scene_origin,
        shape=(int(shape[0]), int(shape[1]), int(shape[2])),
        voxel_size=float(voxel_size),
    )


def majority_vote(
    keys: np.ndarray, labels: np.ndarray, priority_lut: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Most frequent label per key; ties go to the class ranked first in ``priority_lut``.

    keys: (N,) int64 voxel keys; labels: (N,) uint8 raw ids; priority_lut: (256,) int rank
    (0 = most preferred, as :meth:`Taxonomy.priority_lut`).
    Returns (unique keys (V,) int64 sorted, winning label (V,) uint8, votes per key (V,) int64).
    """
    keys = np.asarray(keys, dtype=np.int64)
    labels = np.asarray(labels, dtype=np.uint8)
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.uint8), np.zeros(0, np.int64)
    combo = keys * 256 + labels
    uc, cnt = np.unique(combo, return_counts=True)
    k = uc // 256
    lab = (uc % 256).astype(np.uint8)
    rank = np.asarray(priority_lut)[lab].astype(np.int64)
    rank = np.where(rank < 0, 1 << 20, rank)
    # order within each key: most votes first, then best priority
    order = np.lexsort((rank, -cnt, k))
    k, lab, cnt = k[order], lab[order], cnt[order]
    first = np.ones(len(k), dtype=bool)
    first[1:] = k[1:] != k[:-1]
    total = np.add.reduceat(cnt, np.flatnonzero(first))
    return k[first], lab[first], total


def bin_points(
    spec: SceneGridSpec, xyz: np.ndarray, labels: np.ndarray, priority_lut: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Direct binning with a majority vote per voxel.

    xyz: (N, 3) float32 scene-local metres; labels: (N,) uint8 raw ids.
    Returns (keys (V,) int64, labels (V,) uint8) of the occupied voxels; points outside the
    grid are ignored.
    """
    keys, inside = spec.keys_of_local(xyz)
    k, lab, _ = majority_vote(keys[inside], np.asarray(labels)[inside], priority_lut)
    return k, lab
