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

*Islands* (:func:`find_islands`) are the third kind: a small group of voxels (at most
``island_max_voxels``) that is a whole 26-connected component of its class (no voxel of the
same class touches it from outside) and whose bordering occupied voxels -- at least
``island_min_border`` of them -- are at least ``island_share`` one other class. A 2 m patch of
road in the middle of a lawn is one. Classes of the ``instance`` group (vehicles, people, ...)
are small objects on another class by nature and are not islands; nor is anything that spans
more voxels than an island may. Voxels are labelled by the majority of their points, so a
single stray point inside a voxel does not make an island.
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
    island_max_voxels: int = 6
    island_min_border: int = 6
    island_share: float = 0.9
    island_min_points: int = 3


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


def _flag_clusters(scene: Scene, votes: np.ndarray, labels: np.ndarray,
                   p: SuspectParams, flags: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> list[dict]:
    """Clusters of contested / overridden points, largest first (module docstring).
    ``flags``: :func:`flag_points`' (contested, overridden) when the caller has them."""
    cls = ClassColumns(scene.taxonomy)
    contested, overridden = flags if flags is not None else flag_points(votes, labels, cls, p)
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
    # frames that see each kept cluster: one pass over the correspondences (a point -> group
    # map, not a search per correspondence)
    group = np.full(scene.n_points, -1, np.int32)
    kept = np.zeros(n, bool)
    kept[keep] = True
    fk = kept[cid]
    group[flagged[fk]] = cid[fk]
    frames_of = _frames_seeing_groups(scene, group)
    # the kept clusters' members: flagged positions sorted by cluster (stable: ascending
    # positions within one, as a boolean mask would give them)
    order = np.argsort(cid, kind="stable")
    starts = np.searchsorted(cid[order], np.arange(n + 1))
    lab_all = np.asarray(labels)[flagged]
    out = []
    for c in keep.tolist():  # one entry per kept cluster (<= max_suspects)
        m = order[starts[c]:starts[c + 1]]
        pts = xyz[m]
        fr, _cnt = frames_of.get(c, (np.zeros(0, np.int64), None))
        cl_ids, cl_n = np.unique(lab_all[m], return_counts=True)
        ids = flagged[m]
        out.append({
            "kind": "contested" if contested[ids].any() else "overridden",
            "points": int(len(m)),
            "contested": int(contested[ids].sum()),
            "overridden": int(overridden[ids].sum()),
            "classes": {str(int(k)): int(v) for k, v in zip(cl_ids, cl_n, strict=True)},
            "frames": [int(f) for f in fr],
            "best_frame": int(fr[0]) if len(fr) else None,
            "centroid": [float(v) for v in pts.mean(0)],
            "bbox": [[float(v) for v in pts.min(0)], [float(v) for v in pts.max(0)]],
            "point_ids": ids.astype(np.int64),
        })
    return out


def _frames_seeing_groups(scene: Scene, group: np.ndarray, step: int = 1 << 24,
                          dense_max: int = 1 << 22) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per group of points (``group``: (N,) int32 group of each point, -1 = none): the frames
    that see any of its points, most points first (ties: lower frame index first), and their
    counts. One pass over the correspondences for every group together, ``step`` at a time (a
    survey has 2 B of them: the whole gather held 11 GB), counted in a (group, frame) table
    of at most ``dense_max`` cells, else as sorted keys merged at the end."""
    vis = scene.visibility
    n_groups = int(group.max()) + 1 if len(group) else 0
    if n_groups <= 0:
        return {}
    F = vis.n_frames
    offsets = np.asarray(vis.offsets, np.int64)  # the frames' entries are contiguous, in order
    dense = n_groups * F <= dense_max
    table = np.zeros(n_groups * F, np.int64) if dense else None
    parts: list[tuple[np.ndarray, np.ndarray]] = []
    for a, ids in vis.point_id_chunks(step):
        g = group[ids]
        hit = np.flatnonzero(g >= 0)
        if not len(hit):
            continue
        fr = np.searchsorted(offsets, hit + a, side="right") - 1  # frame of each hit
        key = g[hit].astype(np.int64) * F + fr
        if dense:
            table += np.bincount(key, minlength=n_groups * F)
        else:
            parts.append(np.unique(key, return_counts=True))
    if dense:
        pairs = np.flatnonzero(table)
        cnt = table[pairs]
    elif parts:
        pairs, inv = np.unique(np.concatenate([k for k, _ in parts]), return_inverse=True)
        cnt = np.bincount(inv.reshape(-1), np.concatenate([c for _, c in parts]).astype(np.float64),
                          len(pairs)).astype(np.int64)
    else:
        pairs = cnt = np.zeros(0, np.int64)
    if not len(pairs):
        return {}
    gid, frm = pairs // F, pairs % F
    out = {}
    edges = np.flatnonzero(np.diff(gid)) + 1
    for a, b in zip(np.r_[0, edges], np.r_[edges, len(gid)], strict=True):
        order = np.argsort(-cnt[a:b], kind="stable")
        out[int(gid[a])] = (frm[a:b][order], cnt[a:b][order])
    return out


def find_suspects(scene: Scene, votes: np.ndarray, labels: np.ndarray,
                  params: SuspectParams | None = None) -> list[dict]:
    """Ranked suspects (largest first) of a scene: clusters of contested / overridden points
    and small islands (see the module docstring); an island most of whose points already lie
    in a contested cluster is not listed twice. Each has ``id`` (its rank, 1-based) and
    ``kind`` ("contested", "overridden" or "island")."""
    p = params or SuspectParams()
    cls = ClassColumns(scene.taxonomy)
    contested, overridden = flag_points(votes, labels, cls, p)
    rows = _flag_clusters(scene, votes, labels, p, flags=(contested, overridden))
    in_cluster = np.zeros(scene.n_points, bool)
    for r in rows:
        in_cluster[r["point_ids"]] = True
    islands = [isl for isl in find_islands(scene.xyz, labels, p,
                                           exempt=scene.taxonomy.group_ids("instance"))
               if in_cluster[isl["point_ids"]].mean() <= 0.5]
    group = np.full(scene.n_points, -1, np.int32)
    for k, isl in enumerate(islands):  # islands are disjoint (one class each, connected)
        group[isl["point_ids"]] = k
    frames_of = _frames_seeing_groups(scene, group) if islands else {}
    for k, isl in enumerate(islands):
        pts = isl["point_ids"]
        xyz = np.asarray(scene.xyz[pts], np.float64)
        fr, _cnt = frames_of.get(k, (np.zeros(0, np.int64), None))
        rows.append({
            "kind": "island", "points": int(len(pts)),
            "contested": int(contested[pts].sum()), "overridden": int(overridden[pts].sum()),
            "classes": {str(isl["class"]): int(len(pts))},
            "island_of": isl["class"], "inside": isl["inside"],
            "frames": [int(f) for f in fr], "best_frame": int(fr[0]) if len(fr) else None,
            "centroid": [float(v) for v in xyz.mean(0)],
            "bbox": [[float(v) for v in xyz.min(0)], [float(v) for v in xyz.max(0)]],
            "point_ids": pts,
        })
    rows.sort(key=lambda r: -r["points"])  # stable: clusters before islands of equal size
    rows = rows[: p.max_suspects]
    for rank, r in enumerate(rows):
        r["id"] = rank + 1
    return rows


_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                     if (a, b, c) != (0, 0, 0)], np.int64)


def find_islands(xyz: np.ndarray, labels: np.ndarray, p: SuspectParams,
                 chunk: int = 32_768, exempt: np.ndarray | None = None) -> list[dict]:
    """Small islands of one class inside another (module docstring) ->
    [{"class", "inside", "voxels", "border", "point_ids" (sorted int64)}], largest first.

    Works on the occupied voxels only (sorted keys, 26 neighbour lookups per voxel, chunked),
    so memory scales with the labelled points, not with the scene's extent. ``exempt``: class
    ids that are never islands (their voxels still border others)."""
    labels = np.asarray(labels)
    idx = np.flatnonzero(labels > 0)
    if len(idx) < p.island_min_points:
        return []
    pts = np.asarray(xyz[idx], np.float64)
    v = np.floor((pts - pts.min(0)) / p.voxel).astype(np.int64) + 1  # 1-voxel pad
    d1, d2 = int(v[:, 1].max()) + 2, int(v[:, 2].max()) + 2
    key = (v[:, 0] * d1 + v[:, 1]) * d2 + v[:, 2]
    lab = labels[idx].astype(np.int64)
    # each voxel's majority label (ties: the smaller id)
    u, cnt = np.unique(key * 256 + lab, return_counts=True)
    uk, ul = u >> 8, u & 255
    order = np.lexsort((ul, -cnt, uk))
    vk, first = np.unique(uk[order], return_index=True)
    vlab = ul[order][first]
    m = len(vk)
    offs = (_OFFSETS[:, 0] * d1 + _OFFSETS[:, 1]) * d2 + _OFFSETS[:, 2]
    half = offs > 0  # each undirected edge once

    def neighbours(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        nb = vk[sel, None] + offs[None, :]
        pos = np.minimum(np.searchsorted(vk, nb), m - 1)
        return pos, vk[pos] == nb

    # connected components of same-class voxels (26-connected), edges gathered chunk by chunk
    src, dst = [], []
    for a in range(0, m, chunk):
        sel = np.arange(a, min(m, a + chunk))
        pos, found = neighbours(sel)
        e = found & half[None, :] & (vlab[pos] == vlab[sel, None])
        r, c = np.nonzero(e)
        src.append(sel[r].astype(np.int32))
        dst.append(pos[r, c].astype(np.int32))
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    src_a, dst_a = np.concatenate(src), np.concatenate(dst)
    g = coo_matrix((np.ones(len(src_a), np.int8), (src_a, dst_a)), shape=(m, m))
    del src, dst, src_a, dst_a
    ncomp, comp = connected_components(g, directed=False)
    size = np.bincount(comp, minlength=ncomp)
    cand = np.flatnonzero(size[comp] <= p.island_max_voxels)  # voxels of small components
    if not len(cand):
        return []
    # each small component's border: its voxels' occupied neighbours of another class (a
    # neighbour two of its voxels share is counted once per voxel), and the class most of it is
    pos, found = neighbours(cand)
    other = found & (vlab[pos] != vlab[cand, None])
    r, c = np.nonzero(other)
    pair = comp[cand[r]].astype(np.int64) * 256 + vlab[pos[r, c]]
    pu, pn = np.unique(pair, return_counts=True)
    pcomp = pu >> 8
    border = np.bincount(pcomp, weights=pn, minlength=ncomp)
    o = np.lexsort((-pn, pcomp))
    pc_, firsts = np.unique(pcomp[o], return_index=True)
    sur = np.zeros(ncomp, np.int64)
    wmax = np.zeros(ncomp)
    sur[pc_] = (pu & 255)[o][firsts]
    wmax[pc_] = pn[o][firsts]
    share = wmax / np.maximum(border, 1)
    ok = (size <= p.island_max_voxels) & (border >= p.island_min_border) \
        & (share >= p.island_share)
    if exempt is not None and len(exempt):
        comp_lab = np.zeros(ncomp, np.int64)
        comp_lab[comp] = vlab
        ok &= ~np.isin(comp_lab, np.asarray(exempt, np.int64))
    good = np.flatnonzero(ok)
    if not len(good):
        return []
    pv = np.searchsorted(vk, key)  # voxel of every labelled point
    pcomp = comp[pv]
    keep = ok[pcomp] & (lab == vlab[pv])
    out = []
    kp, kc = idx[keep], pcomp[keep]
    srt = np.argsort(kc, kind="stable")
    kp, kc, kl = kp[srt], kc[srt], lab[keep][srt]
    bounds = np.searchsorted(kc, good)
    ends = np.searchsorted(kc, good, side="right")
    for g_, s0, s1 in zip(good.tolist(), bounds.tolist(), ends.tolist(), strict=True):
        if s1 - s0 < p.island_min_points:
            continue
        out.append({"class": int(kl[s0]), "inside": int(sur[g_]),
                    "voxels": int(size[g_]), "border": int(border[g_]),
                    "point_ids": np.sort(kp[s0:s1]).astype(np.int64)})
    out.sort(key=lambda r: -len(r["point_ids"]))
    return out


def contested_share(votes: np.ndarray, labels: np.ndarray, scene: Scene,
                    params: SuspectParams | None = None) -> float:
    """Share of the labelled points that are flagged (contested votes or overridden)."""
    p = params or SuspectParams()
    c, o = flag_points(votes, labels, ClassColumns(scene.taxonomy), p)
    n = int((np.asarray(labels) > 0).sum())
    return float((c | o).sum() / n) if n else 0.0
