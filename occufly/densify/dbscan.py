"""DBSCAN that scales to 10 M-point classes within a small memory budget.

Open3D's ``cluster_dbscan`` stores every point's full ε-neighbourhood (gigabytes for a
million roof points at ε = 1 m). Here the cloud is first reduced to occupied cells of edge
``cell`` (default ε/4) carrying their point count and centroid; DBSCAN then runs on the cells
with *weighted* neighbour counts (a cell's count is the number of points it holds):

1. core cells: the summed point count of all cells whose centroid lies within ε of the cell's
   centroid is ≥ minPts (the point itself included, as in Open3D and scikit-learn);
2. clusters: connected components of core cells, two core cells linked when their centroids
   are within ε;
3. border cells: a non-core cell within ε of a core cell joins the nearest core cell's
   cluster; everything else is noise (label -1);
4. every point takes its cell's label.

With ``cell=0`` the cells are the distinct points themselves and the result is exact DBSCAN
(border points go to their nearest core point, one of the assignments DBSCAN allows). With
``cell > 0`` the neighbourhood test is off by at most the cell diagonal, so clusters separated
by gaps wider than ε + 2·√3·cell and denser than minPts per ε-ball come out identical to
exact DBSCAN -- the tests check this against Open3D. Memory is O(cells × neighbours per cell):
neighbour pairs are produced in chunks and only core-core edges are kept.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

NOISE = -1


def _pairs_within(tree: cKDTree, pts: np.ndarray, r: float, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i in [start, stop), j any) with |pts[i] - pts[j]| <= r, i != j. int64 arrays."""
    sub = cKDTree(pts[start:stop])
    m = sub.sparse_distance_matrix(tree, r, output_type="ndarray")
    i = m["i"].astype(np.int64) + start
    j = m["j"].astype(np.int64)
    keep = i != j
    return i[keep], j[keep]


def _cells(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroids (V, 3) float64, counts (V,) int64, inverse (N,) int64) of occupied cells."""
    xyz = np.asarray(xyz)
    if cell > 0:
        lo = xyz.min(axis=0).astype(np.float64)
        q = np.floor((xyz.astype(np.float64) - lo) / cell).astype(np.int64)
        dims = q.max(axis=0) + 1
        key = np.ravel_multi_index((q[:, 0], q[:, 1], q[:, 2]), dims)
        _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
        inverse = inverse.reshape(-1)
        cent = np.empty((len(counts), 3), dtype=np.float64)
        for d in range(3):
            cent[:, d] = np.bincount(inverse, weights=xyz[:, d], minlength=len(counts)) / counts
        return cent, counts.astype(np.int64), inverse
    pts = np.ascontiguousarray(xyz, dtype=np.float64)
    uniq, inverse, counts = np.unique(pts, axis=0, return_inverse=True, return_counts=True)
    return uniq, counts.astype(np.int64), inverse.reshape(-1)


def dbscan(
    xyz: np.ndarray,
    eps: float,
    min_points: int,
    *,
    cell: float | None = None,
    chunk: int = 20_000,
) -> np.ndarray:
    """Cluster points; returns (N,) int32 cluster ids 0..K-1 (largest first), -1 for noise.

    xyz: (N, 3) float32, scene-local metres. eps: neighbourhood radius in metres;
    min_points: neighbours (self included) needed for a core point. cell: edge of the
    reduction cells in metres; None means ε/4, 0 means exact point-level DBSCAN.
    """
    if eps <= 0:
        raise ValueError(f"eps must be > 0, got {eps}")
    n = len(xyz)
    out = np.full(n, NOISE, dtype=np.int32)
    if n == 0 or n < min_points:
        return out
    cell = eps / 4.0 if cell is None else float(cell)
    cent, counts, inverse = _cells(xyz, cell)
    v = len(cent)
    tree = cKDTree(cent)

    # 1. weighted neighbour counts
    wcount = counts.astype(np.int64).copy()
    for a in range(0, v, chunk):
        i, j = _pairs_within(tree, cent, eps, a, min(v, a + chunk))
        wcount += np.bincount(i, weights=counts[j], minlength=v).astype(np.int64)
    core = wcount >= min_points
    core_idx = np.flatnonzero(core)
    if len(core_idx) == 0:
        return out

    # 2. connected components of core cells
    cc = cent[core_idx]
    ctree = cKDTree(cc)
    ei: list[np.ndarray] = []
    ej: list[np.ndarray] = []
    for a in range(0, len(cc), chunk):
        i, j = _pairs_within(ctree, cc, eps, a, min(len(cc), a + chunk))
        keep = i < j
        ei.append(i[keep].astype(np.int32))
        ej.append(j[keep].astype(np.int32))
    i = np.concatenate(ei)
    j = np.concatenate(ej)
    graph = coo_matrix((np.ones(len(i), dtype=np.int8), (i, j)), shape=(len(cc), len(cc)))
    _, comp = connected_components(graph, directed=False)

    cell_label = np.full(v, NOISE, dtype=np.int64)
    cell_label[core_idx] = comp
    # 3. border cells join the nearest core cell within eps
    border = np.flatnonzero(~core)
    if len(border):
        d, nn = ctree.query(cent[border], k=1, distance_upper_bound=eps)
        ok = np.isfinite(d)
        cell_label[border[ok]] = comp[nn[ok]]

    # relabel clusters by size (points), largest first
    lab = cell_label[inverse]
    valid = lab >= 0
    sizes = np.bincount(lab[valid], minlength=int(comp.max()) + 1)
    order = np.argsort(-sizes, kind="stable")
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    out[valid] = remap[lab[valid]].astype(np.int32)
    return out


def partition_agreement(a: np.ndarray, b: np.ndarray) -> float:
    """Share of points on which two clusterings agree under the best one-to-one cluster match.

    a, b: (N,) int cluster ids, -1 = noise (noise only matches noise). 1.0 means identical
    partitions up to renaming.
    """
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    if len(a) == 0:
        return 1.0
    pair, cnt = np.unique(np.stack([a, b], axis=1), axis=0, return_counts=True)
    # greedy one-to-one matching by overlap size (exact when partitions nearly agree)
    order = np.argsort(-cnt, kind="stable")
    used_a: set[int] = set()
    used_b: set[int] = set()
    agree = 0
    for (x, y), c in zip(pair[order], cnt[order], strict=True):
        if (x == NOISE) != (y == NOISE) or x in used_a or y in used_b:
            continue
        if x != NOISE:
            used_a.add(int(x))
            used_b.add(int(y))
        agree += int(c)
    return agree / len(a)
