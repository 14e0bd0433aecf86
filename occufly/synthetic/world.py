"""The procedural world: terrain painted with ground classes plus objects built from primitives.

Everything is deterministic for a given ``numpy.random.Generator`` seed and lives in
scene-local metres (z up). The georeference offset is added only when files are written.

The ground surface is one heightfield mesh whose triangles carry the class id
:data:`TERRAIN` (0); the ground class of a terrain point is looked up in :class:`GroundMap`, a
raster of raw class ids at 0.1 m. Objects are :mod:`primitives` with their own class ids.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occufly.synthetic.presets import Preset
from occufly.synthetic.primitives import Box, Cylinder, Ellipsoid, Primitive, Prism

TERRAIN = 0  # tri_class of terrain triangles: the class comes from the GroundMap

# raw ids of the default OccuFly taxonomy (FORMATS.md section 1)
ROAD, WALKWAY, DIRT, GRAVEL, ROCK, GRASS, VEGETATION, TREE, OBSTACLE = 1, 2, 3, 4, 5, 6, 7, 8, 9
PERSON, BICYCLE, VEHICLE, WATER, BUILDING, ROOF = 11, 12, 13, 14, 16, 17
CABLE, CABLE_TOWER, PARKING, CONSTRUCTION, CRANE, TRUCK = 21, 22, 33, 34, 35, 36

WORLD_OFFSET = np.array([512_480.0, 5_403_120.0, 263.0])  # UTM-like E, N, h of local (0, 0, 0)

# base colours of the ground classes (texture and shading are added by the renderer)
GROUND_RGB = {
    ROAD: (72, 72, 76), WALKWAY: (178, 170, 156), DIRT: (126, 96, 66), GRAVEL: (160, 154, 142),
    GRASS: (86, 132, 56), VEGETATION: (52, 92, 36), WATER: (40, 70, 92), PARKING: (96, 96, 100),
}


@dataclass
class GroundMap:
    """Raster of ground class ids. Cell (i, j) covers x in x0 + [i, i+1) * res (same for y)."""

    x0: float
    y0: float
    res: float
    labels: np.ndarray  # (NX, NY) uint8

    @classmethod
    def filled(cls, x0: float, y0: float, size: float, res: float, value: int) -> GroundMap:
        n = int(round(size / res))
        return cls(x0, y0, res, np.full((n, n), value, dtype=np.uint8))

    def _span(self, a0: float, a1: float, origin: float, n: int) -> slice:
        i0 = int(np.clip(np.ceil((a0 - origin) / self.res - 0.5), 0, n))
        i1 = int(np.clip(np.ceil((a1 - origin) / self.res - 0.5), 0, n))
        return slice(i0, i1)

    def paint_rect(self, x0: float, x1: float, y0: float, y1: float, cls: int) -> None:
        """Cells whose centre lies in [x0, x1) x [y0, y1)."""
        sx = self._span(x0, x1, self.x0, self.labels.shape[0])
        sy = self._span(y0, y1, self.y0, self.labels.shape[1])
        self.labels[sx, sy] = cls

    def paint_ellipse(self, cx: float, cy: float, rx: float, ry: float, cls: int) -> None:
        sx = self._span(cx - rx, cx + rx, self.x0, self.labels.shape[0])
        sy = self._span(cy - ry, cy + ry, self.y0, self.labels.shape[1])
        xs = self.x0 + (np.arange(sx.start, sx.stop) + 0.5) * self.res
        ys = self.y0 + (np.arange(sy.start, sy.stop) + 0.5) * self.res
        inside = ((xs[:, None] - cx) / rx) ** 2 + ((ys[None, :] - cy) / ry) ** 2 <= 1.0
        self.labels[sx, sy][inside] = cls

    def lookup(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """x, y: (N,) local metres -> (N,) uint8 ground class (edge cells outside the raster)."""
        i = np.clip(np.floor((np.asarray(x) - self.x0) / self.res).astype(np.int64), 0, self.labels.shape[0] - 1)
        j = np.clip(np.floor((np.asarray(y) - self.y0) / self.res).astype(np.int64), 0, self.labels.shape[1] - 1)
        return self.labels[i, j]


@dataclass
class Road:
    """A straight road strip along ``axis`` ('x' or 'y') centred on the other coordinate ``c``."""

    axis: str
    c: float
    width: float
    a0: float
    a1: float


@dataclass
class World:
    """The whole synthetic world in scene-local metres.

    heights: (NX+1, NY+1) float64 terrain vertex heights on a ``terrain_cell`` lattice starting
    at (x0, y0); the terrain mesh splits cell (i, j) along its (i, j)-(i+1, j+1) diagonal.
    """

    preset: Preset
    x0: float
    y0: float
    size: float
    terrain_cell: float
    heights: np.ndarray
    ground: GroundMap
    prims: list[Primitive]
    roads: list[Road]
    markings: list[tuple[float, float, float, float]]  # white paint rects on parking lots
    sun: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: WORLD_OFFSET.copy())
    # the triangle soup, built by build_mesh()
    vertices: np.ndarray | None = None  # (V, 3) float32 local metres
    triangles: np.ndarray | None = None  # (T, 3) uint32
    tri_class: np.ndarray | None = None  # (T,) uint8, TERRAIN for ground
    tri_inst: np.ndarray | None = None  # (T,) int32, 0 for terrain
    tri_rgb: np.ndarray | None = None  # (T, 3) uint8 base colour (objects)
    tri_prim: np.ndarray | None = None  # (T,) int32 index into prims, -1 for terrain
    n_terrain_tris: int = 0

    # ---- terrain ---------------------------------------------------------------------
    def ground_z(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the terrain *mesh* at (x, y) (piecewise linear, as rendered)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        n = self.heights.shape[0] - 1
        fx = (x - self.x0) / self.terrain_cell
        fy = (y - self.y0) / self.terrain_cell
        i = np.clip(np.floor(fx).astype(np.int64), 0, n - 1)
        j = np.clip(np.floor(fy).astype(np.int64), 0, n - 1)
        fx = np.clip(fx - i, 0.0, 1.0)
        fy = np.clip(fy - j, 0.0, 1.0)
        h = self.heights
        z00, z10, z11, z01 = h[i, j], h[i + 1, j], h[i + 1, j + 1], h[i, j + 1]
        lower = z00 + fx * (z10 - z00) + fy * (z11 - z10)
        upper = z00 + fy * (z01 - z00) + fx * (z11 - z01)
        return np.where(fx >= fy, lower, upper)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """((3,), (3,)) float64 local min / max corner of everything in the world."""
        lo = np.array([self.x0, self.y0, self.heights.min()])
        hi = np.array([self.x0 + self.size, self.y0 + self.size, self.heights.max()])
        for p in self.prims:
            a, b = p.aabb()
            lo = np.minimum(lo, a)
            hi = np.maximum(hi, b)
        return lo, hi

    def build_mesh(self) -> None:
        """Concatenate terrain and primitives into one triangle soup with per-triangle ids."""
        n = self.heights.shape[0] - 1
        c = self.terrain_cell
        gx = self.x0 + np.arange(n + 1) * c
        X, Y = np.meshgrid(gx, self.y0 + np.arange(n + 1) * c, indexing="ij")
        verts = [np.column_stack([X.ravel(), Y.ravel(), self.heights.ravel()])]
        idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
        v00, v10 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
        v11, v01 = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        tris = [np.vstack([np.column_stack([v00, v10, v11]), np.column_stack([v00, v11, v01])])]
        n_terrain = len(tris[0])
        classes = [np.full(n_terrain, TERRAIN, np.uint8)]
        insts = [np.zeros(n_terrain, np.int32)]
        rgbs = [np.zeros((n_terrain, 3), np.uint8)]
        prim_ids = [np.full(n_terrain, -1, np.int32)]
        base = len(verts[0])
        for k, p in enumerate(self.prims):
            v, t = p.mesh()
            verts.append(v)
            tris.append(t + base)
            base += len(v)
            classes.append(np.full(len(t), p.cls, np.uint8))
            insts.append(np.full(len(t), p.inst, np.int32))
            rgbs.append(np.tile(np.array(p.rgb, np.uint8), (len(t), 1)))
            prim_ids.append(np.full(len(t), k, np.int32))
        self.vertices = np.vstack(verts).astype(np.float32)
        self.triangles = np.vstack(tris).astype(np.uint32)
        self.tri_class = np.concatenate(classes)
        self.tri_inst = np.concatenate(insts)
        self.tri_rgb = np.vstack(rgbs)
        self.tri_prim = np.concatenate(prim_ids)
        self.n_terrain_tris = n_terrain

    def classes_present(self) -> list[int]:
        ids = set(int(v) for v in np.flatnonzero(np.bincount(self.ground.labels.ravel(), minlength=256)))
        ids |= {int(p.cls) for p in self.prims}
        return sorted(ids)


# ================================================================================================
# layout
# ================================================================================================
class _Builder:
    """Places objects; keeps footprints to avoid overlaps and counts instance ids."""

    def __init__(self, world: World, rng: np.random.Generator) -> None:
        self.w = world
        self.rng = rng
        self.next_inst = 1
        self.taken: list[tuple[float, float, float, float]] = []
        self.taken_dyn: list[tuple[float, float, float, float]] = []  # traffic on the roads
        self.n_buildings = 0

    # -- bookkeeping --
    def inst(self) -> int:
        i = self.next_inst
        self.next_inst += 1
        return i

    def free(self, x0: float, x1: float, y0: float, y1: float) -> bool:
        for a0, a1, b0, b1 in self.taken:
            if x0 < a1 and a0 < x1 and y0 < b1 and b0 < y1:
                return False
        return True

    def take(self, x0: float, x1: float, y0: float, y1: float) -> None:
        self.taken.append((x0, x1, y0, y1))

    def zmin(self, x0: float, x1: float, y0: float, y1: float) -> float:
        xs = np.linspace(x0, x1, 5)
        ys = np.linspace(y0, y1, 5)
        X, Y = np.meshgrid(xs, ys)
        return float(self.w.ground_z(X.ravel(), Y.ravel()).min())

    def gz(self, x: float, y: float) -> float:
        return float(self.w.ground_z(np.array([x]), np.array([y]))[0])

    def add(self, *prims: Primitive) -> None:
        self.w.prims.extend(prims)

    def colour(self, palette: list[tuple[int, int, int]], jitter: int = 12) -> tuple[int, int, int]:
        c = np.array(palette[int(self.rng.integers(len(palette)))]) + self.rng.integers(-jitter, jitter + 1, 3)
        return tuple(int(v) for v in np.clip(c, 0, 255))

    def try_place(self, x0: float, x1: float, y0: float, y1: float, fx: float, fy: float,
                  tries: int = 30) -> tuple[float, float] | None:
        """A centre for a footprint of fx x fy inside [x0,x1]x[y0,y1] that overlaps nothing."""
        if x1 - x0 < fx or y1 - y0 < fy:
            return None
        for _ in range(tries):
            cx = self.rng.uniform(x0 + fx / 2, x1 - fx / 2)
            cy = self.rng.uniform(y0 + fy / 2, y1 - fy / 2)
            r = (cx - fx / 2, cx + fx / 2, cy - fy / 2, cy + fy / 2)
            if self.free(*r):
                self.take(*r)
                return cx, cy
        return None

    # -- objects (yaw 0 = along x) --
    def vehicle(self, cx: float, cy: float, yaw: float) -> None:
        z = self.gz(cx, cy)
        i = self.inst()
        col = self.colour([(180, 30, 30), (30, 60, 150), (220, 220, 220), (40, 40, 40), (120, 120, 125), (30, 110, 60)])
        d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        self.add(
            Box(VEHICLE, i, center=[cx, cy, z + 0.75], size=[4.4, 1.8, 0.9], yaw=yaw, rgb=col),
            Box(VEHICLE, i, center=np.array([cx, cy, z + 1.5]) - 0.3 * d, size=[2.3, 1.6, 0.6], yaw=yaw,
                rgb=tuple(int(v * 0.6) for v in col)),
        )

    def truck(self, cx: float, cy: float, yaw: float) -> None:
        z = self.gz(cx, cy)
        i = self.inst()
        d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        c = np.array([cx, cy, z])
        cab = self.colour([(200, 160, 30), (190, 190, 190), (30, 80, 160), (170, 40, 30)])
        self.add(
            Box(TRUCK, i, center=c + 3.4 * d + [0, 0, 1.8], size=[2.2, 2.4, 2.6], yaw=yaw, rgb=cab),
            Box(TRUCK, i, center=c - 1.0 * d + [0, 0, 2.1], size=[6.2, 2.5, 3.0], yaw=yaw,
                rgb=self.colour([(210, 210, 205), (150, 150, 140), (90, 110, 90)])),
        )

    def person(self, cx: float, cy: float) -> None:
        z = self.gz(cx, cy)
        i = self.inst()
        shirt = self.colour([(200, 40, 40), (40, 60, 180), (230, 200, 40), (240, 240, 240), (40, 140, 60)])
        self.add(
            Cylinder(PERSON, i, p0=[cx, cy, z], p1=[cx, cy, z + 1.45], radius=0.22, sides=10, rgb=shirt),
            Ellipsoid(PERSON, i, center=[cx, cy, z + 1.6], radii=[0.13, 0.13, 0.15], rings=6, segments=8,
                      rgb=(200, 160, 130)),
        )

    def bicycle(self, cx: float, cy: float, yaw: float) -> None:
        z = self.gz(cx, cy)
        i = self.inst()
        d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        s = np.array([-np.sin(yaw), np.cos(yaw), 0.0]) * 0.03
        c = np.array([cx, cy, z])
        col = self.colour([(20, 20, 20), (180, 30, 30), (40, 90, 170), (230, 230, 230)])
        prims: list[Primitive] = []
        for k in (-0.55, 0.55):
            hub = c + k * d + [0, 0, 0.35]
            prims.append(Cylinder(BICYCLE, i, p0=hub - s, p1=hub + s, radius=0.35, sides=12, rgb=(25, 25, 25)))
        prims.append(Box(BICYCLE, i, center=c + [0, 0, 0.65], size=[1.0, 0.06, 0.08], yaw=yaw, rgb=col))
        prims.append(Box(BICYCLE, i, center=c + 0.45 * d + [0, 0, 0.95], size=[0.08, 0.6, 0.05], yaw=yaw, rgb=col))
        self.add(*prims)

    def tree(self, cx: float, cy: float, scale: float = 1.0) -> None:
        z = self.gz(cx, cy)
        i = self.inst()
        h = self.rng.uniform(4.0, 7.0) * scale
        r = self.rng.uniform(2.0, 3.4) * scale
        self.add(
            Cylinder(TREE, i, p0=[cx, cy, z - 0.2], p1=[cx, cy, z + h], radius=0.18 * scale + 0.1, sides=8,
                     rgb=(92, 70, 48)),
            Ellipsoid(TREE, i, center=[cx, cy, z + h + 0.3 * r], radii=[r, r * self.rng.uniform(0.85, 1.15), r * 0.95],
                      rgb=self.colour([(48, 96, 40), (62, 104, 44), (40, 82, 46)], 10)),
        )

    def rock(self, cx: float, cy: float) -> None:
        z = self.gz(cx, cy)
        r = self.rng.uniform(0.5, 1.2, 3) * [1.0, 1.0, 0.6]
        self.add(Ellipsoid(ROCK, self.inst(), center=[cx, cy, z + 0.3 * r[2]], radii=r, rings=7, segments=10,
                           rgb=self.colour([(128, 124, 118), (110, 104, 98)], 8)))

    def bench(self, cx: float, cy: float, yaw: float) -> None:
        z = self.gz(cx, cy)
        i = self.inst()
        d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        n = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        c = np.array([cx, cy, z])
        wood = (140, 100, 60)
        self.add(
            Box(OBSTACLE, i, center=c + [0, 0, 0.45], size=[1.8, 0.5, 0.08], yaw=yaw, rgb=wood),
            Box(OBSTACLE, i, center=c + 0.25 * n + [0, 0, 0.75], size=[1.8, 0.06, 0.45], yaw=yaw, rgb=wood),
            Box(OBSTACLE, i, center=c - 0.8 * d + [0, 0, 0.22], size=[0.08, 0.5, 0.44], yaw=yaw, rgb=(60, 60, 60)),
            Box(OBSTACLE, i, center=c + 0.8 * d + [0, 0, 0.22], size=[0.08, 0.5, 0.44], yaw=yaw, rgb=(60, 60, 60)),
        )

    def bollard(self, cx: float, cy: float) -> None:
        z = self.gz(cx, cy)
        self.add(Cylinder(OBSTACLE, self.inst(), p0=[cx, cy, z - 0.1], p1=[cx, cy, z + 0.9], radius=0.12, sides=8,
                          rgb=(200, 200, 60)))

    def fence(self, xa: float, ya: float, xb: float, yb: float) -> None:
        i = self.inst()
        a, b = np.array([xa, ya]), np.array([xb, yb])
        length = float(np.linalg.norm(b - a))
        n_posts = max(2, int(np.ceil(length / 2.5)) + 1)
        t = np.linspace(0, 1, n_posts)
        pts = a + t[:, None] * (b - a)
        zs = self.w.ground_z(pts[:, 0], pts[:, 1])
        col = (150, 150, 155)
        for (x, y), z in zip(pts, zs, strict=False):
            self.add(Cylinder(OBSTACLE, i, p0=[x, y, z - 0.1], p1=[x, y, z + 1.5], radius=0.06, sides=6, rgb=col))
        yaw = float(np.arctan2(b[1] - a[1], b[0] - a[0]))
        mid = (a + b) / 2
        zm = float(zs.mean())
        for hgt in (0.6, 1.3):
            self.add(Box(OBSTACLE, i, center=[mid[0], mid[1], zm + hgt], size=[length, 0.05, 0.12], yaw=yaw, rgb=col))

    def building(self, cx: float, cy: float, wx: float, wy: float) -> None:
        rng = self.rng
        zb = self.zmin(cx - wx / 2, cx + wx / 2, cy - wy / 2, cy + wy / 2) - 0.5
        h = rng.uniform(5.0, 13.0)
        i = self.inst()
        wall = self.colour([(205, 195, 175), (180, 180, 178), (200, 170, 140), (150, 140, 130)], 10)
        top = zb + 0.5 + h
        self.add(Box(BUILDING, i, center=[cx, cy, (zb + top) / 2], size=[wx, wy, top - zb], rgb=wall))
        self.n_buildings += 1
        # the first building gets a flat roof, the second a gable roof, then random
        flat = self.n_buildings == 1 or (self.n_buildings > 2 and rng.random() < 0.5)
        if flat:
            roof_rgb = self.colour([(90, 90, 95), (120, 120, 118), (70, 75, 80)], 8)
            self.add(Box(ROOF, i, center=[cx, cy, top + 0.3], size=[wx + 0.2, wy + 0.2, 0.6], rgb=roof_rgb))
        else:
            roof_rgb = self.colour([(150, 60, 45), (110, 50, 40), (80, 80, 85)], 10)
            along_x = wx >= wy
            lx, ly = (wx, wy) if along_x else (wy, wx)
            self.add(Prism(ROOF, i, base=[cx, cy, top], size=[lx + 0.6, ly + 0.6, rng.uniform(2.0, 3.5)],
                           yaw=0.0 if along_x else np.pi / 2, rgb=roof_rgb))

    def crane(self, cx: float, cy: float) -> None:
        rng = self.rng
        z = self.gz(cx, cy)
        i = self.inst()
        h = rng.uniform(19.0, 23.0)
        yaw = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        c = np.array([cx, cy, z])
        yellow = (235, 190, 30)
        self.add(Box(CONSTRUCTION, self.inst(), center=c + [0, 0, 0.2], size=[4.0, 4.0, 0.8], rgb=(150, 150, 150)))
        jib_len, counter = 22.0, 7.0
        self.add(
            Box(CRANE, i, center=c + [0, 0, 0.6 + h / 2], size=[1.6, 1.6, h], rgb=yellow),
            Box(CRANE, i, center=c + [0, 0, 0.6 + h + 0.6] + d * (jib_len / 2), size=[jib_len, 1.2, 1.2], yaw=yaw, rgb=yellow),
            Box(CRANE, i, center=c + [0, 0, 0.6 + h + 0.6] - d * (counter / 2), size=[counter, 1.2, 1.0], yaw=yaw, rgb=yellow),
            Box(CRANE, i, center=c + [0, 0, 0.6 + h - 0.6] - d * (counter - 1.5), size=[2.0, 2.0, 2.0], yaw=yaw,
                rgb=(120, 120, 120)),
            Box(CRANE, i, center=c + [0, 0, 0.6 + h + 2.6], size=[1.0, 1.0, 2.8], yaw=yaw, rgb=yellow),
            Box(CRANE, i, center=c + [0, 0, 0.6 + h - 1.4] + d * 1.6, size=[1.6, 1.4, 1.4], yaw=yaw, rgb=(210, 210, 210)),
        )
        trolley = c + d * rng.uniform(10, jib_len - 2)
        hook_z = z + rng.uniform(6.0, 10.0)
        self.add(
            Cylinder(CRANE, i, p0=[trolley[0], trolley[1], hook_z], p1=[trolley[0], trolley[1], z + 0.6 + h],
                     radius=0.12, sides=6, rgb=(40, 40, 40)),
            Box(CRANE, i, center=[trolley[0], trolley[1], hook_z - 0.4], size=[0.8, 0.8, 0.8], rgb=(200, 40, 30)),
        )

    def cable_line(self, towers: np.ndarray) -> None:
        """towers: (K, 2) local xy of the towers; cables hang between consecutive ones."""
        H = 14.0
        arm = 3.2
        tops = []
        for x, y in towers:
            z = self.gz(x, y)
            i = self.inst()
            col = (120, 124, 130)
            for sx in (-1, 1):
                for sy in (-1, 1):
                    self.add(Cylinder(CABLE_TOWER, i, p0=[x + 1.6 * sx, y + 1.6 * sy, z - 0.2],
                                      p1=[x + 0.4 * sx, y + 0.4 * sy, z + H], radius=0.14, sides=6, rgb=col))
            self.add(
                Box(CABLE_TOWER, i, center=[x, y, z + H - 0.8], size=[0.5, 2 * arm + 0.6, 0.5], rgb=col),
                Box(CABLE_TOWER, i, center=[x, y, z + H + 0.6], size=[0.6, 0.6, 1.6], rgb=col),
            )
            tops.append(np.array([x, y, z + H - 1.0]))
        for a, b in zip(tops[:-1], tops[1:], strict=False):
            for side in (-arm, arm):
                i = self.inst()
                pa, pb = a + [0, side, 0], b + [0, side, 0]
                t = np.linspace(0, 1, 17)
                sag = 1.5
                pts = pa + t[:, None] * (pb - pa)
                pts[:, 2] -= 4 * sag * t * (1 - t)
                for p0, p1 in zip(pts[:-1], pts[1:], strict=False):
                    self.add(Cylinder(CABLE, i, p0=p0, p1=p1, radius=0.13, sides=6, rgb=(35, 35, 38)))


def _terrain_heights(x: np.ndarray, y: np.ndarray, rng_phase: np.ndarray) -> np.ndarray:
    p = rng_phase
    return (
        1.3 * np.sin(2 * np.pi * x / 97.0 + p[0]) * np.cos(2 * np.pi * y / 83.0 + p[1])
        + 0.6 * np.sin(2 * np.pi * (x + 0.6 * y) / 41.0 + p[2])
        + 0.25 * np.cos(2 * np.pi * (0.7 * x - y) / 23.0 + p[3])
    )


def build_world(preset: Preset, seed: int) -> World:
    """The deterministic world of ``preset`` for ``seed`` (mesh built)."""
    rng = np.random.default_rng([seed, 0x0CC0F1])
    C, M = preset.core, preset.margin
    x0 = y0 = -M
    size = C + 2 * M
    cell = preset.terrain_cell
    n = int(round(size / cell))
    size = n * cell
    ground = GroundMap.filled(x0, y0, size, 0.1, GRASS)
    roads, plan = _block_plan(C, x0, y0, size, rng)
    H, ponds = _terrain(x0, y0, n, cell, plan, rng)
    sun_az = rng.uniform(0, 2 * np.pi)
    sun_el = np.deg2rad(rng.uniform(45.0, 60.0))
    sun = np.array([np.cos(sun_el) * np.cos(sun_az), np.cos(sun_el) * np.sin(sun_az), np.sin(sun_el)])
    world = World(preset=preset, x0=x0, y0=y0, size=size, terrain_cell=cell, heights=H, ground=ground,
                  prims=[], roads=roads, markings=[], sun=sun)
    B = _Builder(world, rng)
    _paint_ground(B, ground, roads, ponds, C, x0, size, rng)
    _cable_line(B, roads, C, M)
    # --- blocks ------------------------------------------------------------------------------
    for rect, kind in plan:
        {"buildings": _fill_buildings, "parking": _fill_parking, "park": _fill_park,
         "construction": _fill_construction}[kind](B, *rect)
    _traffic(B, roads, C, rng)
    _margin_trees(B, C, x0, size, rng)
    world.build_mesh()
    return world


WALK_W = 2.0  # walkway width beside every road (m)


def _block_plan(C: float, x0: float, y0: float, size: float, rng: np.random.Generator
                ) -> tuple[list[Road], list[tuple[tuple[float, float, float, float], str]]]:
    """Internal roads split the core into nb x nb blocks, each with a kind:
    ``(roads, [((x0, x1, y0, y1), kind)])``."""
    nb = max(2, int(round(C / 40.0)))
    road_w, walk_w = 7.0, WALK_W
    cuts = [C * k / nb for k in range(1, nb)]
    roads = [Road("x", c, road_w, x0, x0 + size) for c in cuts] + [Road("y", c, road_w, y0, y0 + size) for c in cuts]
    edges = [0.0] + cuts + [C]
    half = road_w / 2 + walk_w + 0.5
    blocks = []
    for a in range(nb):
        for b in range(nb):
            bx0 = edges[a] + (half if a > 0 else 0.0)
            bx1 = edges[a + 1] - (half if a < nb - 1 else 0.0)
            by0 = edges[b] + (half if b > 0 else 0.0)
            by1 = edges[b + 1] - (half if b < nb - 1 else 0.0)
            blocks.append((bx0, bx1, by0, by1))
    kinds = ["buildings", "parking", "park", "construction"]
    rng.shuffle(kinds)
    extra = rng.choice(["buildings", "buildings", "park", "parking", "construction"], size=max(0, len(blocks) - 4))
    kinds = list(kinds) + [str(k) for k in extra]
    order = rng.permutation(len(blocks))
    plan = [(blocks[i], kinds[k]) for k, i in enumerate(order)]
    return roads, plan


def _terrain(x0: float, y0: float, n: int, cell: float, plan, rng: np.random.Generator  # noqa: ANN001
             ) -> tuple[np.ndarray, list[tuple[float, float, float, float]]]:
    """(n+1, n+1) terrain heights, flattened under the (first park's) pond; and the ponds."""
    # --- terrain, flattened under ponds ----------------------------------------------------
    phase = rng.uniform(0, 2 * np.pi, 4)
    gx = x0 + np.arange(n + 1) * cell
    X, Y = np.meshgrid(gx, y0 + np.arange(n + 1) * cell, indexing="ij")
    H = _terrain_heights(X, Y, phase)
    ponds = []
    for (bx0, bx1, by0, by1), kind in plan:
        if kind == "park" and not ponds:
            rx = min(7.0, (bx1 - bx0) * 0.25)
            ry = min(5.0, (by1 - by0) * 0.2)
            cx = rng.uniform(bx0 + rx + 1, bx1 - rx - 1)
            cy = rng.uniform(by0 + ry + 1, by1 - ry - 1)
            ponds.append((cx, cy, rx, ry))
    for cx, cy, rx, ry in ponds:
        level = float(_terrain_heights(np.array(cx), np.array(cy), phase)) - 0.3
        r = np.sqrt(((X - cx) / rx) ** 2 + ((Y - cy) / ry) ** 2)
        w = np.clip((1.6 - r) / 0.6, 0.0, 1.0)
        w = w * w * (3 - 2 * w)
        H = H * (1 - w) + level * w
    return H, ponds


def _paint_ground(B: _Builder, ground: GroundMap, roads: list[Road], ponds, C: float, x0: float,  # noqa: ANN001
                  size: float, rng: np.random.Generator) -> None:
    """Margin patches, ponds, then roads with walkways (painted last, on top of patches)."""
    walk_w = WALK_W
    # --- margin: irregular patches of dirt, gravel and low vegetation ---------------------
    n_patch = int(size * size / 900)
    for _ in range(n_patch):
        px, py = rng.uniform(x0, x0 + size, 2)
        if 0 <= px <= C and 0 <= py <= C:
            continue
        cls = int(rng.choice([VEGETATION, VEGETATION, DIRT, GRAVEL]))
        ground.paint_ellipse(px, py, rng.uniform(2.0, 7.0), rng.uniform(2.0, 6.0), cls)

    for cx, cy, rx, ry in ponds:
        ground.paint_ellipse(cx, cy, rx, ry, WATER)
        B.take(cx - rx - 0.5, cx + rx + 0.5, cy - ry - 0.5, cy + ry + 0.5)

    # --- roads with walkways (painted last, so they stay on top of patches) --------------
    for r in roads:
        wa = r.width / 2
        if r.axis == "x":
            ground.paint_rect(r.a0, r.a1, r.c - wa - walk_w, r.c + wa + walk_w, WALKWAY)
        else:
            ground.paint_rect(r.c - wa - walk_w, r.c + wa + walk_w, r.a0, r.a1, WALKWAY)
    for r in roads:
        wa = r.width / 2
        if r.axis == "x":
            ground.paint_rect(r.a0, r.a1, r.c - wa, r.c + wa, ROAD)
            B.take(r.a0, r.a1, r.c - wa - walk_w, r.c + wa + walk_w)
        else:
            ground.paint_rect(r.c - wa, r.c + wa, r.a0, r.a1, ROAD)
            B.take(r.c - wa - walk_w, r.c + wa + walk_w, r.a0, r.a1)


def _cable_line(B: _Builder, roads: list[Road], C: float, M: float) -> None:
    """The cable line, towers kept off the roads and trees out of the wires."""
    walk_w = WALK_W
    # --- the cable line, in the margin along the south edge of the core --------------------
    ty = -min(8.0, 0.5 * M)
    n_t = max(2, int(np.ceil((C + M) / 36.0)) + 1)
    txs = np.linspace(-0.5 * M, C + 0.5 * M, n_t)
    for k, tx in enumerate(txs):  # keep towers off the roads
        for r in roads:
            if r.axis == "y" and abs(tx - r.c) < r.width / 2 + walk_w + 2.5:
                txs[k] = r.c + np.sign(tx - r.c + 1e-9) * (r.width / 2 + walk_w + 2.5)
    towers = np.column_stack([txs, np.full(n_t, ty)])
    B.cable_line(towers)
    for tx, tyy in towers:
        B.take(tx - 2.2, tx + 2.2, tyy - 2.2, tyy + 2.2)
    B.take(txs.min() - 2, txs.max() + 2, ty - 4.5, ty + 4.5)  # keep trees out of the wires


def _traffic(B: _Builder, roads: list[Road], C: float, rng: np.random.Generator) -> None:
    """Vehicles on the roads, people and bicycles on the walkways (inside the core)."""
    walk_w = WALK_W
    # --- traffic on the roads and people on the walkways (inside the core) ----------------
    for r in roads:
        n_v = max(1, int(C / 30))
        for _ in range(n_v):
            lane = rng.choice([-1.75, 1.75])
            a = rng.uniform(2.0, C - 2.0)
            yaw = 0.0 if lane > 0 else np.pi
            if r.axis == "y":
                yaw += np.pi / 2
            big = rng.random() < 0.25
            fx, fy = (8.0, 2.6) if big else (4.6, 2.0)
            if r.axis == "x":
                cx, cy, rx, ry = a, r.c + lane, fx, fy
            else:
                cx, cy, rx, ry = r.c + lane, a, fy, fx
            if not _overlaps_any(B, cx, cy, rx, ry):
                (B.truck if big else B.vehicle)(cx, cy, yaw)
                B.taken_dyn.append((cx - rx / 2, cx + rx / 2, cy - ry / 2, cy + ry / 2))
        for side in (-1, 1):
            off = side * (r.width / 2 + walk_w / 2)
            for _ in range(max(1, int(C / 40))):
                a = rng.uniform(1.0, C - 1.0)
                cx, cy = (a, r.c + off) if r.axis == "x" else (r.c + off, a)
                if not _overlaps_any(B, cx, cy, 1.0, 1.0):
                    B.person(cx, cy)
                    B.taken_dyn.append((cx - 0.5, cx + 0.5, cy - 0.5, cy + 0.5))
            a = rng.uniform(1.0, C - 1.0)
            cx, cy = (a, r.c + off) if r.axis == "x" else (r.c + off, a)
            if not _overlaps_any(B, cx, cy, 2.0, 1.0):
                B.bicycle(cx, cy, 0.0 if r.axis == "x" else np.pi / 2)
                B.taken_dyn.append((cx - 1.0, cx + 1.0, cy - 1.0, cy + 1.0))


def _margin_trees(B: _Builder, C: float, x0: float, size: float, rng: np.random.Generator) -> None:
    # --- a few trees in the margin ------------------------------------------------------------
    for _ in range(int(size * size / 1500)):
        px, py = rng.uniform(x0 + 3, x0 + size - 3, 2)
        if -3 <= px <= C + 3 and -3 <= py <= C + 3:
            continue
        if B.free(px - 3, px + 3, py - 3, py + 3):
            B.take(px - 3, px + 3, py - 3, py + 3)
            B.tree(px, py)


def _overlaps_any(B: _Builder, cx: float, cy: float, fx: float, fy: float) -> bool:
    r = (cx - fx / 2, cx + fx / 2, cy - fy / 2, cy + fy / 2)
    for a0, a1, b0, b1 in B.taken_dyn:
        if r[0] < a1 and a0 < r[1] and r[2] < b1 and b0 < r[3]:
            return True
    return False


def _fill_buildings(B: _Builder, x0: float, x1: float, y0: float, y1: float) -> None:
    rng, g = B.rng, B.w.ground
    nx = max(1, int((x1 - x0) // 16))
    ny = max(1, int((y1 - y0) // 16))
    lx, ly = (x1 - x0) / nx, (y1 - y0) / ny
    for a in range(nx):
        for b in range(ny):
            lx0, ly0 = x0 + a * lx, y0 + b * ly
            wx = rng.uniform(0.55, 0.75) * lx
            wy = rng.uniform(0.55, 0.75) * ly
            cx = lx0 + lx / 2 + rng.uniform(-0.08, 0.08) * lx
            cy = ly0 + ly / 2 + rng.uniform(-0.08, 0.08) * ly
            g.paint_rect(cx - wx / 2 - 1.5, cx + wx / 2 + 1.5, cy - wy / 2 - 1.5, cy + wy / 2 + 1.5, WALKWAY)
            B.take(cx - wx / 2 - 0.3, cx + wx / 2 + 0.3, cy - wy / 2 - 0.3, cy + wy / 2 + 0.3)
            B.building(cx, cy, wx, wy)
            # a bicycle on the path around it, sometimes a person
            bx, by = cx + wx / 2 + 0.8, cy + rng.uniform(-wy / 3, wy / 3)
            if B.free(bx - 0.3, bx + 0.3, by - 1.0, by + 1.0):
                B.take(bx - 0.3, bx + 0.3, by - 1.0, by + 1.0)
                B.bicycle(bx, by, np.pi / 2)
            if rng.random() < 0.6:
                p = B.try_place(cx - wx / 2 - 1.5, cx + wx / 2 + 1.5, cy - wy / 2 - 1.5, cy - wy / 2, 0.6, 0.6)
                if p:
                    B.person(*p)
    for _ in range(int((x1 - x0) * (y1 - y0) / 250)):
        p = B.try_place(x0, x1, y0, y1, 5.0, 5.0, tries=10)
        if p:
            B.tree(*p, scale=0.8)


def _fill_parking(B: _Builder, x0: float, x1: float, y0: float, y1: float) -> None:
    rng, g = B.rng, B.w.ground
    g.paint_rect(x0 + 0.5, x1 - 0.5, y0 + 0.5, y1 - 0.5, PARKING)
    bay_w, bay_d, aisle = 2.6, 5.0, 6.0
    y = y0 + 1.0
    trucks = 0
    facing = 1
    while y + bay_d <= y1 - 0.5:
        n_bays = int((x1 - x0 - 2.0) // bay_w)
        for k in range(n_bays + 1):
            lx = x0 + 1.0 + k * bay_w
            B.w.markings.append((lx - 0.06, lx + 0.06, y, y + bay_d))
        for k in range(n_bays):
            cx = x0 + 1.0 + (k + 0.5) * bay_w
            cy = y + bay_d / 2
            if rng.random() < 0.6 and B.free(cx - 1.1, cx + 1.1, cy - 2.3, cy + 2.3):
                B.take(cx - 1.1, cx + 1.1, cy - 2.3, cy + 2.3)
                B.vehicle(cx, cy, np.pi / 2 if facing > 0 else -np.pi / 2)
        ay = y + bay_d + aisle / 2
        if ay + 1.3 <= y1:
            if trucks == 0:
                p = B.try_place(x0 + 2, x1 - 2, ay - 1.3, ay + 1.3, 8.5, 2.6)
                if p:
                    B.truck(p[0], p[1], 0.0)
                    trucks += 1
            p = B.try_place(x0 + 2, x1 - 2, ay - 2.5, min(y1, ay + 2.5), 0.6, 0.6)
            if p:
                B.person(*p)
        y += bay_d + (aisle if facing > 0 else 0.3)
        facing = -facing
    for bx in np.arange(x0 + 1.0, x1 - 0.5, 3.0):  # bollards along the south edge
        if B.free(bx - 0.2, bx + 0.2, y0 + 0.1, y0 + 0.5):
            B.bollard(bx, y0 + 0.3)
    if trucks == 0:
        p = B.try_place(x0, x1, y0, y1, 8.5, 2.6)
        if p:
            B.truck(p[0], p[1], 0.0)


def _fill_park(B: _Builder, x0: float, x1: float, y0: float, y1: float) -> None:
    rng, g = B.rng, B.w.ground
    py = rng.uniform(y0 + 0.3 * (y1 - y0), y0 + 0.7 * (y1 - y0))
    path_free = B.free(x0, x1, py - 1.25, py + 1.25)
    if path_free:
        g.paint_rect(x0, x1, py - 1.25, py + 1.25, WALKWAY)
        B.take(x0, x1, py - 1.25, py + 1.25)
    for _ in range(3):
        cx, cy = rng.uniform(x0, x1), rng.uniform(y0, y1)
        if B.free(cx - 3, cx + 3, cy - 2, cy + 2):
            g.paint_ellipse(cx, cy, rng.uniform(1.5, 3.5), rng.uniform(1.5, 3.0), VEGETATION)
    cx, cy = rng.uniform(x0 + 3, x1 - 3), rng.uniform(y0 + 3, y1 - 3)
    if B.free(cx - 2.5, cx + 2.5, cy - 2.0, cy + 2.0):
        g.paint_ellipse(cx, cy, 2.5, 2.0, DIRT)
    if path_free:
        for bx in rng.uniform(x0 + 2, x1 - 2, 2):
            if B.free(bx - 1.0, bx + 1.0, py + 1.3, py + 2.1):
                B.take(bx - 1.0, bx + 1.0, py + 1.3, py + 2.1)
                B.bench(bx, py + 1.7, 0.0)
        for px in rng.uniform(x0 + 1, x1 - 1, 2):
            B.person(px, py + rng.uniform(-0.6, 0.6))
        bx = rng.uniform(x0 + 2, x1 - 2)
        B.bicycle(bx, py + rng.uniform(-0.4, 0.4), 0.0)
    for _ in range(max(2, int((x1 - x0) * (y1 - y0) / 150))):
        p = B.try_place(x0, x1, y0, y1, 5.5, 5.5, tries=10)
        if p:
            B.tree(*p)
    for _ in range(3):
        p = B.try_place(x0, x1, y0, y1, 2.4, 2.4)
        if p:
            B.rock(*p)
    B.fence(x0 + 0.3, y1 - 0.4, x0 + 0.6 * (x1 - x0), y1 - 0.4)


def _fill_construction(B: _Builder, x0: float, x1: float, y0: float, y1: float) -> None:
    rng, g = B.rng, B.w.ground
    g.paint_rect(x0 + 0.5, x1 - 0.5, y0 + 0.5, y1 - 0.5, DIRT)
    gx0, gx1 = x0 + 1.0, x0 + 0.45 * (x1 - x0)
    gy0, gy1 = y0 + 1.0, y0 + 0.4 * (y1 - y0)
    g.paint_rect(gx0, gx1, gy0, gy1, GRAVEL)
    # the crane near the block centre
    cx, cy = (x0 + x1) / 2 + rng.uniform(-2, 2), (y0 + y1) / 2 + rng.uniform(-2, 2)
    B.take(cx - 2.2, cx + 2.2, cy - 2.2, cy + 2.2)
    B.crane(cx, cy)
    # material piles and containers
    for _ in range(2):
        p = B.try_place(x0 + 1, x1 - 1, y0 + 1, y1 - 1, 6.0, 5.0)
        if p:
            z = B.gz(*p)
            r = np.array([rng.uniform(2.0, 3.0), rng.uniform(1.6, 2.4), rng.uniform(1.2, 1.8)])
            B.add(Ellipsoid(CONSTRUCTION, B.inst(), center=[p[0], p[1], z - 0.3 * r[2]], radii=r,
                            rgb=B.colour([(150, 120, 90), (170, 165, 150), (120, 110, 100)], 8)))
    p = B.try_place(x0 + 1, x1 - 1, y0 + 1, y1 - 1, 6.4, 2.8)
    if p:
        z = B.zmin(p[0] - 3, p[0] + 3, p[1] - 1.2, p[1] + 1.2)
        B.add(Box(CONSTRUCTION, B.inst(), center=[p[0], p[1], z + 1.2], size=[6.0, 2.4, 2.6],
                  rgb=B.colour([(40, 90, 150), (170, 60, 40), (60, 120, 70)], 10)))
    # scaffold around a rectangle: poles + boards
    p = B.try_place(x0 + 1, x1 - 1, y0 + 1, y1 - 1, 7.0, 5.0)
    if p:
        i = B.inst()
        sx, sy = 6.0, 4.0
        z = B.zmin(p[0] - sx / 2, p[0] + sx / 2, p[1] - sy / 2, p[1] + sy / 2)
        B.add(Box(CONSTRUCTION, i, center=[p[0], p[1], z + 0.2], size=[sx - 1, sy - 1, 0.8], rgb=(165, 165, 160)))
        for ax in np.linspace(-sx / 2, sx / 2, 4):
            for ay in (-sy / 2, sy / 2):
                B.add(Cylinder(CONSTRUCTION, i, p0=[p[0] + ax, p[1] + ay, z - 0.1], p1=[p[0] + ax, p[1] + ay, z + 6.0],
                               radius=0.06, sides=6, rgb=(170, 170, 175)))
        for lvl in (2.0, 4.0, 6.0):
            for ay in (-sy / 2, sy / 2):
                B.add(Box(CONSTRUCTION, i, center=[p[0], p[1] + ay, z + lvl], size=[sx, 0.7, 0.06],
                          rgb=(175, 140, 90)))
    p = B.try_place(x0 + 1, x1 - 1, y0 + 1, y1 - 1, 8.5, 2.6)
    if p:
        B.truck(p[0], p[1], 0.0)
    for _ in range(2):
        p = B.try_place(x0 + 1, x1 - 1, y0 + 1, y1 - 1, 0.6, 0.6)
        if p:
            B.person(*p)
    B.fence(x0 + 0.3, y0 + 0.3, x1 - 0.3, y0 + 0.3)
