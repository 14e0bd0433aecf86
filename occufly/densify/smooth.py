"""Surface denoising of point clouds: projection onto local least-squares planes.

MVS depth noise grows with distance (the synthetic scenes use 0.4 % of the depth, ~0.2 m at
50 m); binned as it is, a surface becomes a band two or three voxels thick, and on a solid
object every noisy point outside the surface adds a voxel that does not exist. Each point is
moved along the normal of the (weighted) least-squares plane of its neighbours onto that
plane: on a smooth surface the noise averages out over the neighbourhood, the surface keeps
its shape, and the point keeps its position *along* the surface. Edges and corners are rounded
by about the radius, thin structures (a cable, a post) collapse onto their middle plane.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def plane_offsets(data: np.ndarray, queries: np.ndarray, radius: float, *, weight: np.ndarray | None = None,
                  k: int = 24, min_neighbours: int = 4, chunk: int = 200_000, tree: cKDTree | None = None,
                  workers: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance of each query point to the least-squares plane of its data neighbours.

    data: (N, 3) metres, weight: (N,) (default 1); queries: (Q, 3). Neighbours: the ``k``
    nearest data points within ``radius``. Returns (offset (Q,) float64 along the plane normal,
    normal (Q, 3) float64 unit, ok (Q,) bool: at least ``min_neighbours`` neighbours; offset 0
    where not ok). Vectorised in chunks of ``chunk`` queries ((chunk, k, 3) temporaries).
    """
    d64 = np.asarray(data, dtype=np.float64)
    q64 = np.asarray(queries, dtype=np.float64)
    n, m = len(d64), len(q64)
    off = np.zeros(m)
    nrm_out = np.zeros((m, 3))
    nrm_out[:, 2] = 1.0
    good = np.zeros(m, bool)
    if n < min_neighbours or radius <= 0 or m == 0:
        return off, nrm_out, good
    w_all = np.ones(n) if weight is None else np.asarray(weight, dtype=np.float64)
    tree = tree if tree is not None else cKDTree(d64)
    kk = min(k, n)
    for a in range(0, m, chunk):
        q = q64[a : a + chunk]
        d, nn = tree.query(q, k=kk, distance_upper_bound=radius, workers=workers)
        if kk == 1:
            d, nn = d[:, None], nn[:, None]
        ok = np.isfinite(d)
        nn = np.where(ok, nn, 0)
        w = np.where(ok, w_all[nn], 0.0)
        ws = np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
        nb = d64[nn]  # (b, k, 3)
        mu = np.einsum("bk,bki->bi", w, nb) / ws
        c = nb - mu[:, None, :]
        cov = np.einsum("bk,bki,bkj->bij", w, c, c) / ws[..., None]
        _, vecs = np.linalg.eigh(cov)
        nrm = vecs[:, :, 0]  # eigenvector of the smallest eigenvalue: the plane normal
        enough = ok.sum(axis=1) >= min_neighbours
        o = np.einsum("bi,bi->b", q - mu, nrm)
        off[a : a + chunk] = np.where(enough, o, 0.0)
        nrm_out[a : a + chunk] = np.where(enough[:, None], nrm, nrm_out[a : a + chunk])
        good[a : a + chunk] = enough
    return off, nrm_out, good


def project_to_planes(xyz: np.ndarray, radius: float, *, weight: np.ndarray | None = None, k: int = 24,
                      min_neighbours: int = 4, chunk: int = 200_000, workers: int = 1) -> np.ndarray:
    """Points moved onto the least-squares plane of their ``k`` nearest neighbours.

    xyz: (N, 3) float32/float64 metres; weight: (N,) per-point weights (e.g. the number of raw
    points a centroid stands for; default 1); neighbours: the k nearest within ``radius``
    (the point itself included). Points with fewer than ``min_neighbours`` neighbours stay.
    Returns (N, 3) in xyz's dtype.
    """
    pts = np.asarray(xyz)
    if len(pts) < min_neighbours or radius <= 0:
        return pts.copy()
    off, nrm, _ = plane_offsets(pts, pts, radius, weight=weight, k=k, min_neighbours=min_neighbours,
                                chunk=chunk, workers=workers)
    return (pts.astype(np.float64) - off[:, None] * nrm).astype(pts.dtype)
