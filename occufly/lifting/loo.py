"""Leave-one-out (independent) labels and agreement of one frame.

For frame ``f`` the labels decided *without f's votes*: the other frames' vote counts at the
points f needs (its visible points and the voted points whose fill can reach them) are the
counts minus f's own per-frame votes (``ws/lifting/frames/<f>.npz``), their majority follows
the pipeline's tie rule (:meth:`ClassColumns.packed_winner`); a point left without a vote
takes the pipeline fill's inverse-distance-weighted k-NN vote of the other frames' voted
points within ``LiftParams.fill_radius`` (``occufly.lifting.knn._knn_vote``, the same
function the fill calls; nothing is extrapolated beyond the radius). Reviewers' corrections
are applied on top. The labels are rendered into f exactly as the self-agreement is
(:func:`occufly.render.render_for_mask`) and compared with f's mask.

Cost: proportional to the points in f's frustum (the render cull), never a pass over the scene.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from occufly.lifting.classes import ClassColumns
from occufly.lifting.corrections import read_overrides
from occufly.lifting.knn import LiftParams, _knn_vote
from occufly.render import agreement as _agreement
from occufly.render import disagreement_image, frustum_candidates, render_for_mask
from occufly.scene import Scene
from occufly.taxonomy import INVALID
from occufly.workspace import Workspace


@dataclass
class LooLabels:
    """Leave-one-out labels around one frame.

    point_ids: (K,) int64 sorted scene point ids (f's visible points and its frustum cull);
    labels: (K,) uint8 raw ids decided without f (0 = no independent evidence);
    voted: (K,) bool, the label comes from other frames' votes (else filled or none).
    """

    frame_index: int
    point_ids: np.ndarray
    labels: np.ndarray
    voted: np.ndarray


def _frame_votes(ws: Path, f: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = Workspace(ws).lifting_frame(f)
    if not p.is_file():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    with np.load(p, allow_pickle=False) as z:
        pids = z["point_ids"].astype(np.int64)
        cols = z["cols"].astype(np.int64)
        w = z["weights"].astype(np.int64) if "weights" in z.files else np.ones(len(pids), np.int64)
    return pids, cols, w


def loo_labels(ws: str | Path, scene: Scene, frame_index: int, *,
               params: LiftParams | None = None, corrections: bool = True) -> LooLabels:
    """The labels of the points around frame ``frame_index`` decided without its votes."""
    ws = Path(ws)
    p = params or LiftParams()
    cls = ClassColumns(scene.taxonomy)
    votes = np.load(Workspace(ws).votes, mmap_mode="r")  # (N, C) uint16
    fr = scene.frames[frame_index]
    vis = np.asarray(scene.visibility.frame_ids(frame_index), dtype=np.int64)
    cand = frustum_candidates(scene, fr.camera, fr.T_cam_world)
    if cand is None:
        ids = np.arange(scene.n_points, dtype=np.int64)
    else:
        ids = np.asarray(cand, np.int64)  # sorted; f's visible points are (almost) all in it
        pos = np.minimum(np.searchsorted(ids, vis), len(ids) - 1) if len(ids) else vis * 0
        missing = vis[ids[pos] != vis] if len(ids) else vis
        if len(missing):  # a sort of the few left out, not a hash of them all (np.union1d)
            ids = np.sort(np.concatenate([ids, missing]))
    counts = np.array(votes[ids])  # (K, C) uint16 copy
    own_p, own_c, own_w = _frame_votes(ws, frame_index)
    if len(own_p):
        pos = np.searchsorted(ids, own_p)
        pos = np.minimum(pos, len(ids) - 1)
        ok = ids[pos] == own_p
        r, c = pos[ok], own_c[ok]
        counts[r, c] = np.maximum(counts[r, c].astype(np.int64) - own_w[ok], 0).astype(np.uint16)
    col = cls.winner(counts)
    voted = col >= 0
    # fill: the points f sees without an independent vote, from the other frames' voted points
    is_vis = np.zeros(len(ids), bool)
    is_vis[np.searchsorted(ids, vis)] = True
    todo = np.flatnonzero(is_vis & ~voted)
    src = np.flatnonzero(voted)
    if len(todo) and len(src):
        xyz = scene.xyz
        q = np.asarray(xyz[ids[todo]], dtype=np.float64)
        lo, hi = q.min(0) - p.fill_radius, q.max(0) + p.fill_radius
        sx = np.asarray(xyz[ids[src]])
        src = src[np.all((sx >= lo) & (sx <= hi), axis=1)]  # only voted points in reach
    if len(todo) and len(src):
        tree = cKDTree(np.asarray(xyz[ids[src]], dtype=np.float64))
        c, _share = _knn_vote(tree, col[src], q,
                              p.fill_k, p.fill_radius, cls, weighted=True, workers=p.workers)
        col[todo] = c
    labels = cls.labels_of(col)
    if corrections:
        ov = read_overrides(ws, scene.n_points)
        if ov is not None and len(ov):
            op = np.asarray(ov.point_ids, np.int64)
            pos = np.minimum(np.searchsorted(ids, op), len(ids) - 1)
            hit = ids[pos] == op
            labels[pos[hit]] = np.asarray(ov.labels)[hit]
    return LooLabels(frame_index, ids, labels, voted)


def render_loo(scene: Scene, loo: LooLabels, mask_shape: tuple[int, int]) -> np.ndarray:
    """(h, w) uint8 rendering of the leave-one-out labels into their frame at the mask's size."""
    full = np.zeros(scene.n_points, np.uint8)  # calloc'd: only the cull's pages are touched
    full[loo.point_ids] = loo.labels
    ren, _depth = render_for_mask(scene, full, loo.frame_index, mask_shape)
    return np.asarray(ren, np.uint8)


def loo_agreement(mask: np.ndarray, rendered: np.ndarray, scene: Scene, *,
                  self_rendered: np.ndarray | None = None) -> dict:
    """Agreement of ``mask`` (h, w uint8 raw ids) with the leave-one-out ``rendered`` labels.

    Returns ``agreement`` (share of the painted pixels with an independent label that agree;
    None without any), ``independent_pixels``, ``independent_coverage`` (share of the painted
    pixels with an independent label), ``painted_pixels``, ``painted_share`` (painted / all
    pixels), ``per_class`` and ``confusion`` (of the LOO rendering), and, with
    ``self_rendered``, ``self_agreement`` (the old circular figure, kept apart).
    """
    mask = np.asarray(mask)
    res = _agreement(mask, rendered, scene.taxonomy)
    valid = scene.taxonomy.valid_lut()
    painted = int((valid[mask] & (mask != INVALID)).sum())
    ind = int(res.get("pixels", 0))
    val = res.get("agreement")
    val = None if val is None or not np.isfinite(val) or ind == 0 else float(val)
    out = {"agreement": val, "independent_pixels": ind, "painted_pixels": painted,
           "independent_coverage": (ind / painted) if painted else 0.0,
           "painted_share": painted / mask.size if mask.size else 0.0,
           "per_class": res.get("per_class") or {}, "confusion": res.get("confusion"),
           "agree": int(res.get("agree", 0))}
    if self_rendered is not None:
        s = _agreement(mask, self_rendered, scene.taxonomy)
        sv = s.get("agreement")
        out["self_agreement"] = None if sv is None or not np.isfinite(sv) else float(sv)
        out["self_pixels"] = int(s.get("pixels", 0))
    return out


def frame_loo(ws: str | Path, scene: Scene, frame_index: int, mask: np.ndarray, *,
              params: LiftParams | None = None, self_labels: np.ndarray | None = None,
              image: bool = False) -> dict:
    """Leave-one-out agreement of frame ``frame_index``'s ``mask`` (see :func:`loo_agreement`);
    with ``self_labels`` ((N,) uint8, the lifted labels) also the self-agreement; with
    ``image`` the disagreement RGBA under ``"image"``."""
    loo = loo_labels(ws, scene, frame_index, params=params)
    ren = render_loo(scene, loo, mask.shape)
    self_ren = None
    if self_labels is not None:
        self_ren = np.asarray(render_for_mask(scene, self_labels, frame_index, mask.shape)[0],
                              np.uint8)
    out = loo_agreement(mask, ren, scene, self_rendered=self_ren)
    if image:
        out["image"] = disagreement_image(mask, ren, scene.taxonomy)
    out["rendered"] = ren
    return out
