"""How dense a point cloud is: point spacing, surface density and k-NN radii, in one place.

All three measure the cloud on a seeded random subsample with a k-d tree, so the cost stays
bounded on tens of millions of points, and all three are exact-in-expectation rescalings of
the subsample's statistic to the full cloud:

- :func:`point_spacing` -- median nearest-neighbour distance (metres). Aerial clouds are
  surfaces, so the spacing of an m-point subsample is scaled by sqrt(m / N). Used for the
  splat size of rendered views and the z-buffer resolution of the visibility test.
- :func:`surface_density` -- median points per m² around sampled points (neighbours within
  ``radius`` / (π r²), counts rescaled by N / m). Used to scale DBSCAN's minPts to the cloud.
- :func:`knn_radius` -- a quantile of the k-th-neighbour distance; the k-th neighbour of the
  full cloud is about the (k m / N)-th of an m-point subsample. Used for the denoise lattice.

(These were three copies in render, densify and lifting; their results are unchanged.)
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree


def _subsample(xyz: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
    """(m, 3) float64: ``m`` distinct rows of ``xyz`` in file order (all of them if m >= N)."""
    n = len(xyz)
    if m >= n:
        return np.asarray(xyz, dtype=np.float64)
    return np.asarray(xyz[np.sort(rng.choice(n, size=m, replace=False))], dtype=np.float64)


def point_spacing(xyz: np.ndarray, *, sample: int = 200_000, queries: int = 5000,
                  seed: int = 0) -> float:
    """Median nearest-neighbour distance of the cloud (metres), from a subsample.

    xyz: (N, 3) float scene-local metres. 1.0 for fewer than 2 points or no positive distance.
    """
    n = len(xyz)
    if n < 2:
        return 1.0
    rng = np.random.default_rng(seed)
    m = min(n, sample)
    sub = _subsample(xyz, m, rng)
    tree = cKDTree(sub)
    q = sub[rng.choice(m, size=min(queries, m), replace=False)]
    d, _ = tree.query(q, k=2)
    d = d[:, 1]
    d = d[np.isfinite(d) & (d > 0)]
    if not len(d):
        return 1.0
    return float(np.median(d) * np.sqrt(m / n))


def surface_density(xyz: np.ndarray, *, radius: float = 0.5, samples: int = 2000,
                    sample: int = 400_000, seed: int = 0) -> float:
    """Median points per m² around sampled points (neighbours within ``radius`` / (π r²)).

    xyz: (N, 3) float scene-local metres. 0.0 for fewer than 10 points.
    """
    n = len(xyz)
    if n < 10:
        return 0.0
    rng = np.random.default_rng(seed)
    m = min(n, sample)
    sub = np.asarray(xyz[np.sort(rng.choice(n, m, replace=False))], dtype=np.float64)
    tree = cKDTree(sub)
    q = sub[rng.choice(m, min(samples, m), replace=False)]
    cnt = tree.query_ball_point(q, r=radius, return_length=True) * (n / m)
    return float(np.median(cnt) / (np.pi * radius * radius))


def knn_radius(xyz: np.ndarray, k: int, *, quantile: float = 0.75, sample: int = 2000,
               seed: int = 0) -> float:
    """``quantile`` of the distance from a point to its ``k``-th nearest neighbour (metres).

    The k-th neighbour in the full cloud is about the (k f)-th in a subsample of fraction f.
    A cloud of at most ``k`` points returns its largest extent (at least 1 mm).
    """
    n = len(xyz)
    if n <= k:
        ext = np.ptp(xyz, axis=0) if n else np.ones(3)
        return float(max(np.max(ext), 1e-3))
    rng = np.random.default_rng(seed)
    kk = 8
    m = min(n, max(int(math.ceil(n * kk / k)), kk + 1))
    sub = xyz[rng.choice(n, size=m, replace=False)] if m < n else xyz
    kk = max(1, min(kk, int(round(k * m / n))))
    tree = cKDTree(sub)
    qi = rng.choice(n, size=min(sample, n), replace=False)
    d, _ = tree.query(xyz[qi], k=kk + 1)
    r = d[:, -1]
    r = r[np.isfinite(r)]
    return float(np.quantile(r, quantile)) if len(r) else 1.0
