"""Analytic solids used to build the synthetic world.

Every primitive gives a closed triangle mesh (for ray casting) and an exact point-inside test
(for the solid truth grid). All coordinates are scene-local metres, z up.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _yaw_matrix(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Primitive:
    """Base class: a solid with a semantic class id, an instance id and a base colour."""

    cls: int
    inst: int
    rgb: tuple[int, int, int] = field(default=(128, 128, 128), kw_only=True)

    kind: str = field(default="", init=False)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - abstract
        """-> vertices (V, 3) float64 local metres, triangles (T, 3) int64."""
        raise NotImplementedError

    def inside(self, xyz: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """xyz: (N, 3) float64 local metres -> (N,) bool, True inside the solid."""
        raise NotImplementedError

    def aabb(self) -> tuple[np.ndarray, np.ndarray]:
        v, _ = self.mesh()
        return v.min(axis=0), v.max(axis=0)

    def to_dict(self) -> dict:
        d = {"kind": self.kind, "cls": int(self.cls), "inst": int(self.inst)}
        d.update(self._params())
        return d

    def _params(self) -> dict:  # pragma: no cover - abstract
        raise NotImplementedError


_BOX_CORNERS = np.array(
    [[-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1]],
    dtype=np.float64,
) * 0.5
_BOX_TRIS = np.array(
    [[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
     [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]],
    dtype=np.int64,
)


@dataclass
class Box(Primitive):
    """A box rotated by ``yaw`` (radians) about the vertical axis through ``center``."""

    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size: np.ndarray = field(default_factory=lambda: np.ones(3))
    yaw: float = 0.0

    def __post_init__(self) -> None:
        self.kind = "box"
        self.center = np.asarray(self.center, dtype=np.float64)
        self.size = np.asarray(self.size, dtype=np.float64)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        v = (_BOX_CORNERS * self.size) @ _yaw_matrix(self.yaw).T + self.center
        return v, _BOX_TRIS.copy()

    def inside(self, xyz: np.ndarray) -> np.ndarray:
        local = (np.asarray(xyz, dtype=np.float64) - self.center) @ _yaw_matrix(self.yaw)
        return np.all(np.abs(local) <= self.size / 2, axis=1)

    def _params(self) -> dict:
        return {"center": self.center.tolist(), "size": self.size.tolist(), "yaw": float(self.yaw)}


@dataclass
class Prism(Primitive):
    """A gable roof: rectangle ``size[0] x size[1]`` at z = ``base[2]``, ridge along local x
    at height ``size[2]`` above the base, rotated by ``yaw`` about the vertical."""

    base: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size: np.ndarray = field(default_factory=lambda: np.ones(3))
    yaw: float = 0.0

    def __post_init__(self) -> None:
        self.kind = "prism"
        self.base = np.asarray(self.base, dtype=np.float64)
        self.size = np.asarray(self.size, dtype=np.float64)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        lx, ly, h = self.size / np.array([2, 2, 1])
        v = np.array(
            [[-lx, -ly, 0], [lx, -ly, 0], [lx, ly, 0], [-lx, ly, 0], [-lx, 0, h], [lx, 0, h]],
            dtype=np.float64,
        )
        t = np.array([[0, 2, 1], [0, 3, 2], [0, 1, 5], [0, 5, 4], [3, 4, 5], [3, 5, 2],
                      [0, 4, 3], [1, 2, 5]], dtype=np.int64)
        return v @ _yaw_matrix(self.yaw).T + self.base, t

    def inside(self, xyz: np.ndarray) -> np.ndarray:
        local = (np.asarray(xyz, dtype=np.float64) - self.base) @ _yaw_matrix(self.yaw)
        lx, ly, h = self.size
        w = local[:, 2]
        return (np.abs(local[:, 0]) <= lx / 2) & (w >= 0) & (w <= h) & (
            np.abs(local[:, 1]) <= (ly / 2) * (1 - w / h)
        )

    def _params(self) -> dict:
        return {"base": self.base.tolist(), "size": self.size.tolist(), "yaw": float(self.yaw)}


def _orthonormal(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(a, helper)
    u /= np.linalg.norm(u)
    return u, np.cross(a, u)


@dataclass
class Cylinder(Primitive):
    """A closed cylinder of ``radius`` from ``p0`` to ``p1`` (any direction)."""

    p0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    p1: np.ndarray = field(default_factory=lambda: np.array([0, 0, 1.0]))
    radius: float = 0.5
    sides: int = 12

    def __post_init__(self) -> None:
        self.kind = "cylinder"
        self.p0 = np.asarray(self.p0, dtype=np.float64)
        self.p1 = np.asarray(self.p1, dtype=np.float64)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        n = self.sides
        u, w = _orthonormal(self.p1 - self.p0)
        ang = np.arange(n) * (2 * np.pi / n)
        ring = self.radius * (np.cos(ang)[:, None] * u + np.sin(ang)[:, None] * w)
        v = np.vstack([self.p0 + ring, self.p1 + ring, self.p0, self.p1])
        i = np.arange(n)
        j = (i + 1) % n
        side = np.vstack([np.column_stack([i, j, n + j]), np.column_stack([i, n + j, n + i])])
        cap0 = np.column_stack([np.full(n, 2 * n), j, i])
        cap1 = np.column_stack([np.full(n, 2 * n + 1), n + i, n + j])
        return v, np.vstack([side, cap0, cap1]).astype(np.int64)

    def inside(self, xyz: np.ndarray) -> np.ndarray:
        p = np.asarray(xyz, dtype=np.float64) - self.p0
        a = self.p1 - self.p0
        t = p @ a / (a @ a)
        radial = p - t[:, None] * a
        return (t >= 0) & (t <= 1) & (np.einsum("ij,ij->i", radial, radial) <= self.radius**2)

    def _params(self) -> dict:
        return {"p0": self.p0.tolist(), "p1": self.p1.tolist(), "radius": float(self.radius)}


@dataclass
class Ellipsoid(Primitive):
    """An axis-aligned ellipsoid."""

    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radii: np.ndarray = field(default_factory=lambda: np.ones(3))
    rings: int = 10
    segments: int = 16

    def __post_init__(self) -> None:
        self.kind = "ellipsoid"
        self.center = np.asarray(self.center, dtype=np.float64)
        self.radii = np.asarray(self.radii, dtype=np.float64)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        nr, ns = self.rings, self.segments
        theta = np.arange(1, nr) * (np.pi / nr)  # polar angles of the inner rings
        phi = np.arange(ns) * (2 * np.pi / ns)
        st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
        ring = np.stack([st * np.cos(phi), st * np.sin(phi), np.broadcast_to(ct, (nr - 1, ns))], -1)
        v = np.vstack([[0, 0, 1.0], ring.reshape(-1, 3), [0, 0, -1.0]])
        top, bottom = 0, len(v) - 1
        tris = []
        k = np.arange(ns)
        kn = (k + 1) % ns
        tris.append(np.column_stack([np.full(ns, top), 1 + k, 1 + kn]))
        for r in range(nr - 2):
            a, b = 1 + r * ns, 1 + (r + 1) * ns
            tris.append(np.column_stack([a + k, b + k, b + kn]))
            tris.append(np.column_stack([a + k, b + kn, a + kn]))
        last = 1 + (nr - 2) * ns
        tris.append(np.column_stack([np.full(ns, bottom), last + kn, last + k]))
        return v * self.radii + self.center, np.vstack(tris).astype(np.int64)

    def inside(self, xyz: np.ndarray) -> np.ndarray:
        q = (np.asarray(xyz, dtype=np.float64) - self.center) / self.radii
        return np.einsum("ij,ij->i", q, q) <= 1.0

    def _params(self) -> dict:
        return {"center": self.center.tolist(), "radii": self.radii.tolist()}
