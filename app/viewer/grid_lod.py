"""The scene grid drawn without freezing the tab: a level of detail for instanced boxes.

One box per surface voxel of a survey's grid is hundreds of thousands of lit instances
(12 triangles each); under software WebGL that took 30 s and more to draw. Instead the grid is
coarsened by 2 x 2 x 2 blocks (each block takes its most common occupied class) until its
surface voxels fit ``max_boxes``, and drawn as boxes of the coarser edge -- every occupied
voxel stays inside a drawn box (no holes, unlike a stride subsample).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from app.viewer import scene_builder as sb

DEFAULT_MAX_BOXES = 40_000


def coarsen(labels: np.ndarray) -> np.ndarray:
    """(X, Y, Z) uint8 -> (ceil X/2, ceil Y/2, ceil Z/2): each block's most common class
    other than 0 (empty) and 255 (invalid), 0 where the block holds none. Vectorised."""
    lab = np.asarray(labels, np.uint8)
    pad = [(0, s % 2) for s in lab.shape]
    if any(p[1] for p in pad):
        lab = np.pad(lab, pad, constant_values=0)
    X, Y, Z = (s // 2 for s in lab.shape)
    blocks = lab.reshape(X, 2, Y, 2, Z, 2).transpose(0, 2, 4, 1, 3, 5).reshape(-1, 8)
    blocks = np.where(blocks == 255, 0, blocks)
    occ = blocks.any(axis=1)
    out = np.zeros(len(blocks), np.uint8)
    sub = np.sort(blocks[occ], axis=1)
    # most common non-zero value per row: run lengths on the sorted rows
    best = np.zeros(len(sub), np.uint8)
    best_n = np.zeros(len(sub), np.int64)
    for v_col in range(8):
        v = sub[:, v_col]
        n = (sub == v[:, None]).sum(axis=1)
        better = (v != 0) & (n > best_n)
        best[better], best_n[better] = v[better], n[better]
    out[occ] = best
    return out.reshape(X, Y, Z)


def lod_level(labels: np.ndarray, max_boxes: int = DEFAULT_MAX_BOXES,
              max_level: int = 6) -> tuple[np.ndarray, int]:
    """(labels at the level whose surface voxels fit ``max_boxes``, level): level k has
    voxels 2**k times the grid's edge."""
    lab = np.asarray(labels)
    level = 0
    while level < max_level:
        occ = (lab != 0) & (lab != 255)
        if int(sb.surface_mask(occ).sum()) <= max_boxes:
            break
        lab = coarsen(lab)
        level += 1
    return lab, level


def scene_grid_nodes_lod(grid: Any, scene_origin: np.ndarray, taxonomy: Any, *,
                         prefix: str = "/grid/scene",
                         max_boxes: int = DEFAULT_MAX_BOXES) -> list[sb.VoxelNode]:
    """Like :func:`app.viewer.scene_builder.scene_grid_nodes` (surface voxels, one node per
    class, centres in scene-local metres) at the level of detail that fits ``max_boxes``."""
    lab, level = lod_level(np.asarray(grid.labels), max_boxes)
    vs = float(grid.voxel_size) * (2 ** level)
    shift = np.asarray(grid.origin, np.float64) - np.asarray(scene_origin, np.float64)
    occ = (lab != 0) & (lab != 255)
    keep = sb.surface_mask(occ)

    def centers_of(ijk: np.ndarray) -> np.ndarray:
        return shift + (ijk + 0.5) * vs

    return sb._voxel_nodes(lab, keep, centers_of, taxonomy, prefix, vs, max_boxes,
                           np.array([1.0, 0.0, 0.0, 0.0]))
