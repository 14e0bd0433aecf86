"""The exact scene voxel grid of the synthetic world.

- instance classes: **solid** -- voxels whose centre lies inside an analytic primitive (later
  primitives win, so a roof overrides its building), plus the voxels their mesh surface passes
  through (so thin objects such as bicycles and persons are never lost);
- other classes: **surface** -- voxels the mesh surface passes through (dense area-weighted
  samples, <= 0.1 m apart), majority class per voxel;
- ground classes: the terrain surface sampled on a regular 0.1 m lattice, majority per voxel;
- precedence instance > other > ground; 0 is empty;
- the grid holds the world *above the terrain*: the ground is a surface one voxel thick, so
  object voxels that lie wholly below the terrain surface (the 0.5 m a building box is sunk
  into the slope, the buried foot of a trunk, a post or a tower leg) are empty like the soil
  around them; no camera and no LiDAR can observe them;
- columns outside the survey are 255 (invalid, ignored by every metric), as SSC benchmarks mark
  what their sensors never observed: a column is surveyed when its terrain point lies inside
  the image of at least ``min_views`` frames of the flight (the number of views the dense
  reconstruction needs for a point at all) *and* the fused cloud holds a point within
  ``observed_radius`` (2 m) of the column centre in plan view. The second condition drops the
  rim where grazing oblique views see the terrain but too coarsely to reconstruct it (on the
  ``bench`` preset a band ~4-8 m wide); holes smaller than 4 m inside the area stay scored.
  Occlusion is not considered: a column under a roof or a canopy is surveyed (the roof's
  points are in it), its hidden parts count.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from occufly.camera import project_world
from occufly.grid import SceneGrid
from occufly.synthetic.fuse import unique_inverse, unique_sorted
from occufly.synthetic.world import World
from occufly.taxonomy import EMPTY, INVALID, Taxonomy

SURFACE_SPACING = 0.1  # metres between surface samples (terrain lattice)
SURFACE_DENSITY = 200.0  # random surface samples per square metre on object meshes


def _surface_samples(world: World, tri_mask: np.ndarray, rng: np.random.Generator,
                     chunk: int = 2_000_000):
    """Yield (xyz (K, 3) float64, cls (K,) uint8) area-weighted samples of the selected triangles."""
    tris = np.flatnonzero(tri_mask)
    if not len(tris):
        return
    V = world.vertices.astype(np.float64)
    T = world.triangles[tris].astype(np.int64)
    a, b, c = V[T[:, 0]], V[T[:, 1]], V[T[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    n_per = np.maximum(1, np.ceil(area * SURFACE_DENSITY)).astype(np.int64)
    cum = np.cumsum(n_per)
    start = 0
    while start < len(tris):
        base = cum[start - 1] if start else 0
        stop = int(np.searchsorted(cum, base + chunk, side="right"))
        stop = max(stop, start + 1)
        sel = np.arange(start, stop)
        idx = np.repeat(sel, n_per[sel])
        r1 = np.sqrt(rng.random(len(idx)))
        r2 = rng.random(len(idx))
        p = (1 - r1)[:, None] * a[idx] + (r1 * (1 - r2))[:, None] * b[idx] + (r1 * r2)[:, None] * c[idx]
        yield p, world.tri_class[tris[idx]]
        start = stop


def _vote(world_grid: tuple[np.ndarray, np.ndarray, float], chunks, priority: np.ndarray) -> np.ndarray:
    """Majority class per voxel of sample chunks -> (X, Y, Z) uint8."""
    origin, dims, vs = world_grid
    cells, classes = [], []
    for xyz, cls in chunks:
        ijk = np.floor((xyz - origin) / vs).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < dims), axis=1)
        ijk, cls = ijk[ok], cls[ok]
        lin = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
        # reduce each chunk to unique (voxel, class) pairs with counts, repeated by count later
        pair, cnt = unique_sorted(lin * 256 + cls)
        cells.append(pair)
        classes.append(cnt)
    out = np.zeros(int(np.prod(dims)), np.uint8)
    if not cells:
        return out.reshape(dims)
    pair = np.concatenate(cells)
    cnt = np.concatenate(classes)
    u, inv, _ = unique_inverse(pair)
    tot = np.bincount(inv, weights=cnt).astype(np.int64)
    vox, cl = u // 256, (u % 256).astype(np.uint8)
    # majority per voxel with tie order: sort by (voxel, -count, priority)
    order = np.lexsort((priority[cl], -tot, vox))
    vox, cl = vox[order], cl[order]
    first = np.ones(len(vox), bool)
    first[1:] = vox[1:] != vox[:-1]
    out[vox[first]] = cl[first]
    return out.reshape(dims)


def column_terrain_range(world: World, origin: np.ndarray, dims: np.ndarray, voxel: float,
                         sub: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) float64 lowest and highest terrain height over each voxel column's footprint.

    The terrain is piecewise linear on a lattice the voxel edges divide, so the extremes lie
    on the footprint's corners and edges: ``sub`` x ``sub`` samples including the corners.
    """
    cx = origin[0] + np.arange(dims[0]) * voxel
    cy = origin[1] + np.arange(dims[1]) * voxel
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    lo = np.full(X.shape, np.inf)
    hi = np.full(X.shape, -np.inf)
    for dx in np.linspace(0.0, voxel, sub):
        for dy in np.linspace(0.0, voxel, sub):
            z = world.ground_z((X + dx).ravel(), (Y + dy).ravel()).reshape(X.shape)
            lo = np.minimum(lo, z)
            hi = np.maximum(hi, z)
    return lo, hi


def _column_centres(origin: np.ndarray, dims: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) float64 plan-view x and y of every voxel column's centre, local metres."""
    cx = origin[0] + (np.arange(dims[0]) + 0.5) * voxel
    cy = origin[1] + (np.arange(dims[1]) + 0.5) * voxel
    return np.meshgrid(cx, cy, indexing="ij")


def survey_views(world: World, origin: np.ndarray, dims: np.ndarray, voxel: float, camera,
                 poses: list[np.ndarray]) -> np.ndarray:
    """(X, Y) int32: frames whose image holds the terrain point at each column's centre.

    poses: (4, 4) float64 local world-to-camera matrices; camera: :class:`occufly.camera.Camera`.
    """
    X, Y = _column_centres(origin, dims, voxel)
    pts = np.column_stack([X.ravel(), Y.ravel(), world.ground_z(X.ravel(), Y.ravel())])
    count = np.zeros(len(pts), np.int32)
    for T in poses:
        count += project_world(camera, T, pts)[2]
    return count.reshape(X.shape)


def observed_columns(xy: np.ndarray, origin: np.ndarray, dims: np.ndarray, voxel: float,
                     radius: float) -> np.ndarray:
    """(X, Y) bool: columns whose centre has a point of ``xy`` ((N, 2) local metres) within
    ``radius`` metres (plan view): one k-d tree query per column centre."""
    X, Y = int(dims[0]), int(dims[1])
    if len(xy) == 0:
        return np.zeros((X, Y), bool)
    pts = np.unique(np.round(np.asarray(xy, np.float64), 3), axis=0)  # mm duplicates add nothing
    GX, GY = _column_centres(origin, dims, voxel)
    d, _ = cKDTree(pts).query(np.column_stack([GX.ravel(), GY.ravel()]), k=1, distance_upper_bound=radius)
    return np.isfinite(d).reshape(X, Y)


def truth_grid(world: World, taxonomy: Taxonomy, voxel: float, seed: int, *, camera=None,
               poses: list[np.ndarray] | None = None, min_views: int = 1,
               observed_xy: np.ndarray | None = None, observed_radius: float = 2.0) -> SceneGrid:
    """The exact scene grid, origin in WORLD (georeferenced) coordinates.

    With ``camera`` and ``poses`` (the flight), columns seen by fewer than ``min_views``
    frames are 255 (outside the survey); with ``observed_xy`` ((N, 2) local metres, the fused
    cloud) also the columns with no point within ``observed_radius``. Without them every
    column counts.
    """
    rng = np.random.default_rng([seed, 0x6121D])
    lo, hi = world.bounds
    lo = lo - np.array([0.0, 0.0, voxel])
    hi = hi + np.array([0.0, 0.0, voxel])
    origin = np.floor(lo / voxel) * voxel
    dims = np.ceil((hi - origin) / voxel - 1e-9).astype(np.int64)
    grid = (origin, dims, voxel)
    priority = taxonomy.priority_lut()
    inst_ids = set(int(i) for i in taxonomy.group_ids("instance"))
    other_ids = set(int(i) for i in taxonomy.group_ids("other"))

    # ground: regular lattice on the terrain mesh
    def terrain_chunks():
        s = SURFACE_SPACING
        xs = world.x0 + (np.arange(int(round(world.size / s))) + 0.5) * s
        ys = world.y0 + (np.arange(int(round(world.size / s))) + 0.5) * s
        step = max(1, 2_000_000 // len(ys))
        for i in range(0, len(xs), step):
            X, Y = np.meshgrid(xs[i : i + step], ys, indexing="ij")
            x, y = X.ravel(), Y.ravel()
            z = world.ground_z(x, y)
            yield np.column_stack([x, y, z]), world.ground.lookup(x, y)

    ground = _vote(grid, terrain_chunks(), priority)

    tri_cls = world.tri_class
    is_other = np.isin(tri_cls, list(other_ids)) & (world.tri_prim >= 0)
    other = _vote(grid, _surface_samples(world, is_other, rng), priority)

    # instance: solid primitives, then their surfaces where nothing solid was found
    inst = np.zeros(tuple(dims), np.uint8)
    for prim in world.prims:
        if prim.cls not in inst_ids:
            continue
        a, b = prim.aabb()
        i0 = np.clip(np.floor((a - origin) / voxel - 0.5).astype(np.int64), 0, dims)
        i1 = np.clip(np.ceil((b - origin) / voxel + 0.5).astype(np.int64), 0, dims)
        if np.any(i1 <= i0):
            continue
        axes = [origin[k] + (np.arange(i0[k], i1[k]) + 0.5) * voxel for k in range(3)]
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        inside = prim.inside(np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])).reshape(X.shape)
        block = inst[i0[0] : i1[0], i0[1] : i1[1], i0[2] : i1[2]]
        block[inside] = prim.cls
    is_inst = np.isin(tri_cls, list(inst_ids)) & (world.tri_prim >= 0)
    inst_surface = _vote(grid, _surface_samples(world, is_inst, rng), priority)
    fill = (inst == 0) & (inst_surface > 0)
    inst[fill] = inst_surface[fill]

    labels = ground
    labels[other > 0] = other[other > 0]
    labels[inst > 0] = inst[inst > 0]
    # nothing below the terrain: voxels wholly under the lowest terrain point of their column
    z_lo, _ = column_terrain_range(world, origin, dims, voxel)
    k_lo = np.floor((z_lo - origin[2]) / voxel).astype(np.int64)
    labels[np.arange(dims[2])[None, None, :] < k_lo[:, :, None]] = EMPTY
    if camera is not None and poses is not None:
        views = survey_views(world, origin, dims, voxel, camera, poses)
        labels[views < min_views] = INVALID
    if observed_xy is not None:
        labels[~observed_columns(observed_xy, origin, dims, voxel, observed_radius)] = INVALID
    return SceneGrid(labels=labels, origin=origin + world.offset, voxel_size=voxel)
