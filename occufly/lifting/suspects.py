"""Suspects: a ranked list of contested regions of a scene's lifted labels (issue 23).

A point is *flagged* when

- its votes disagree: at least ``min_votes`` votes and the second class holds at least
  ``second_share`` of them (from the vote counts ``ws/lifting/votes.npy``), or
- the fill / denoise overrode its votes: it has votes and its final label is not their
  majority (``origin`` filled or denoised over a direct majority).

Flagged points are binned into a voxel grid (edge ``voxel``) and the occupied voxels labelled
in 26-connectivity (``scipy.ndimage.label``); every cluster of at least ``min_points`` points
is a suspect with its size, classes (final labels and vote majorities), the frames that see it
(from the visibility) and the one that sees most of it, its bounding box and centroid. Ranked
by size. Everything is vectorised over the points and the correspondences.

Small islands of one class inside another are not flagged yet.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from occufly.lifting.classes import ClassColumns
from occufly.scene import Scene


@dataclass
class SuspectParams:
    second_share: float = 0.25
    min_votes: int = 2
    voxel: float = 1.0
    min_points: int = 10
    max_suspects: int = 200


def flag_points(votes: np.ndarray, labels: np.ndarray, cls: ClassColumns,
                p: SuspectParams) -> tuple[np.ndarray, np.ndarray]:
    """votes: (N, C) uint16 counts; labels: (N,) uint8 final labels ->
    ((N,) bool contested votes, (N,) bool label overrides its votes)."""
    n = len(labels)
    contested = np.zeros(n, bool)
    overridden = np.zeros(n, bool)
    for a in range(0, n, 1_000_000):
        b = min(n, a + 1_000_000)
        c = np.asarray(votes[a:b])
        col, top, second = cls.majority(c)
        total = c.sum(axis=1, dtype=np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            share = np.where(total > 0, second / np.maximum(total, 1), 0.0)
        contested[a:b] = (total >= p.min_votes) & (share >= p.second_share)
        direct = cls.labels_of(col)
        overridden[a:b] = (col >= 0) & (np.asarray(labels[a:b]) != direct)
    return contested, overridden


def find_suspects(scene: Scene, votes: np.ndarray, labels: np.ndarray,
                  params: SuspectParams | None = None) -> list[dict]:
    """Ranked suspects (largest first) of a scene; see the module docstring."""
    p = params or SuspectParams()
    cls = ClassColumns(scene.taxonomy)
    contested, overridden = flag_points(votes, labels, cls, p)
    flagged = np.flatnonzero(contested | overridden)
    if not len(flagged):
        return []
    xyz = np.asarray(scene.xyz[flagged], np.float64)
    lo = xyz.min(0)
    vox = np.floor((xyz - lo) / p.voxel).astype(np.int64)
    shape = tuple(int(s) for s in vox.max(0) + 1)
    occ = np.zeros(shape, bool)
    occ[vox[:, 0], vox[:, 1], vox[:, 2]] = True
    lab, n = ndimage.label(occ, structure=np.ones((3, 3, 3), bool))
    cid = lab[vox[:, 0], vox[:, 1], vox[:, 2]] - 1  # (F,) cluster of each flagged point
    size = np.bincount(cid, minlength=n)
    keep = np.flatnonzero(size >= p.min_points)
    keep = keep[np.argsort(-size[keep], kind="stable")][: p.max_suspects]
    if not len(keep):
        return []
    # frames that see each cluster: correspondences of flagged points
    vis = scene.visibility
    ent_pts = np.asarray(vis.point_ids, np.int64)
    ent_fr = vis.frames_of_entries()
    pos = np.minimum(np.searchsorted(flagged, ent_pts), len(flagged) - 1)
    hit = flagged[pos] == ent_pts
    pair = cid[pos[hit]].astype(np.int64) * vis.n_frames + ent_fr[hit]
    pairs, pc = np.unique(pair, return_counts=True)
    p_cl, p_fr = pairs // vis.n_frames, pairs % vis.n_frames
    lab_all = np.asarray(labels)[flagged]
    out = []
    for rank, c in enumerate(keep.tolist()):  # one entry per kept cluster (<= max_suspects)
        m = cid == c
        pts = xyz[m]
        sel = p_cl == c
        fr, cnt = p_fr[sel], pc[sel]
        order = np.argsort(-cnt, kind="stable")
        cl_ids, cl_n = np.unique(lab_all[m], return_counts=True)
        out.append({
            "id": rank + 1, "points": int(m.sum()),
            "contested": int(contested[flagged[m]].sum()),
            "overridden": int(overridden[flagged[m]].sum()),
            "classes": {str(int(k)): int(v) for k, v in zip(cl_ids, cl_n, strict=True)},
            "frames": [int(f) for f in fr[order]],
            "best_frame": int(fr[order[0]]) if len(fr) else None,
            "centroid": [float(v) for v in pts.mean(0)],
            "bbox": [[float(v) for v in pts.min(0)], [float(v) for v in pts.max(0)]],
            "point_ids": flagged[m].astype(np.int64),
        })
    return out


def contested_share(votes: np.ndarray, labels: np.ndarray, scene: Scene,
                    params: SuspectParams | None = None) -> float:
    """Share of the labelled points that are flagged (contested votes or overridden)."""
    p = params or SuspectParams()
    c, o = flag_points(votes, labels, ClassColumns(scene.taxonomy), p)
    n = int((np.asarray(labels) > 0).sum())
    return float((c | o).sum() / n) if n else 0.0
