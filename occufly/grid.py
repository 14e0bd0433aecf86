"""The scene voxel grid: one raw class id per voxel in world (georeferenced) coordinates.

Layout on disk (``.npz``, written atomically) -- the same as the synthetic generator's
``truth/scene_grid.npz`` and the workspace's ``WS/grid/scene_grid.npz``:

- ``labels``: (X, Y, Z) uint8 raw class ids, 0 = empty (255 = unknown, if ever used)
- ``origin``: (3,) float64 WORLD coordinates of the min corner of voxel (0, 0, 0)
- ``voxel_size``: () float64 edge length in metres

Voxel (i, j, k) spans ``origin + [i, i+1) * voxel_size`` (same for j, k) and its centre is
``origin + (i + 0.5) * voxel_size``. A scene's local points map to world by
``xyz_world = scene.origin + xyz``; use :meth:`SceneGrid.index_of_local` for local points.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occufly.errors import InputFormatError
from occufly.fsutil import atomic_write_bytes


@dataclass
class SceneGrid:
    """A dense semantic voxel grid.

    labels: (X, Y, Z) uint8 raw class ids, 0 = empty.
    origin: (3,) float64 world coordinates of the min corner of voxel (0, 0, 0).
    voxel_size: edge length in metres.
    crs: WKT of the CRS ``origin`` is in (the scene's; stored as ``crs`` in the .npz), or None.
    """

    labels: np.ndarray
    origin: np.ndarray
    voxel_size: float
    crs: str | None = None

    def __post_init__(self) -> None:
        labels = np.asarray(self.labels)
        if labels.ndim != 3:
            raise ValueError(f"SceneGrid.labels must be (X, Y, Z), got shape {labels.shape}")
        if labels.dtype != np.uint8:
            raise ValueError(f"SceneGrid.labels must be uint8, got {labels.dtype}")
        self.labels = labels
        origin = np.asarray(self.origin, dtype=np.float64).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise ValueError(f"SceneGrid.origin must be 3 finite numbers, got {self.origin!r}")
        self.origin = origin
        vs = float(self.voxel_size)
        if not np.isfinite(vs) or vs <= 0:
            raise ValueError(f"SceneGrid.voxel_size must be > 0, got {self.voxel_size!r}")
        self.voxel_size = vs

    # ---- geometry ----------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.labels.shape)  # type: ignore[return-value]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """((3,) min corner, (3,) max corner) float64 world metres."""
        return self.origin.copy(), self.origin + np.asarray(self.shape, float) * self.voxel_size

    def centers(self, ijk: np.ndarray | None = None) -> np.ndarray:
        """World centres of voxels.

        ijk: (N, 3) int voxel indices, or None for the occupied voxels (labels != 0).
        Returns (N, 3) float64 world metres.
        """
        if ijk is None:
            ijk = self.occupied_indices()
        ijk = np.asarray(ijk).reshape(-1, 3)
        return self.origin + (ijk.astype(np.float64) + 0.5) * self.voxel_size

    def occupied_indices(self) -> np.ndarray:
        """(N, 3) int64 indices of voxels with a non-zero label."""
        return np.argwhere(self.labels != 0)

    def index_of(self, xyz_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Voxel containing each point.

        xyz_world: (N, 3) float64 world metres.
        Returns (ijk (N, 3) int64, inside (N,) bool); ijk of outside points is clipped into
        the grid so it can still be used as an index (mask it with ``inside``).
        """
        xyz = np.asarray(xyz_world, dtype=np.float64).reshape(-1, 3)
        with np.errstate(invalid="ignore"):
            f = np.floor((xyz - self.origin) / self.voxel_size)
        shape = np.asarray(self.shape)
        inside = np.all((f >= 0) & (f < shape), axis=1)
        f = np.nan_to_num(f, nan=-1.0)
        ijk = np.clip(f, 0, shape - 1).astype(np.int64)
        return ijk, inside

    def index_of_local(self, xyz_local: np.ndarray, scene_origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`index_of` for xyz_local: (N, 3) float32 scene-local metres.

        The subtraction ``scene_origin - grid.origin`` happens in float64 first so UTM-sized
        coordinates keep their precision.
        """
        shift = np.asarray(scene_origin, dtype=np.float64) - self.origin
        xyz = np.asarray(xyz_local, dtype=np.float64).reshape(-1, 3) + shift
        return SceneGrid(self.labels, np.zeros(3), self.voxel_size).index_of(xyz)

    def lookup(self, xyz_world: np.ndarray, outside: int = 0) -> np.ndarray:
        """(N,) uint8 label of the voxel containing each world point; ``outside`` beyond bounds."""
        ijk, inside = self.index_of(xyz_world)
        out = self.labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        return np.where(inside, out, np.uint8(outside)).astype(np.uint8)

    def class_counts(self) -> dict[int, int]:
        """Raw id -> voxel count, for non-empty ids present.

        Chunked: ``np.bincount`` widens its input to int64, 8x the grid's bytes at once otherwise.
        """
        flat = self.labels.reshape(-1)
        counts = np.zeros(256, np.int64)
        step = 1 << 24
        for a in range(0, len(flat), step):
            counts += np.bincount(flat[a : a + step], minlength=256)
        return {int(i): int(counts[i]) for i in np.flatnonzero(counts) if i != 0}

    # ---- I/O ---------------------------------------------------------------------------
    def to_bytes(self, *, compress: bool = True) -> bytes:
        buf = io.BytesIO()
        (np.savez_compressed if compress else np.savez)(
            buf,
            labels=np.ascontiguousarray(self.labels, dtype=np.uint8),
            origin=self.origin.astype(np.float64),
            voxel_size=np.float64(self.voxel_size),
            **({"crs": np.array(self.crs)} if self.crs else {}),
        )
        return buf.getvalue()

    def save(self, path: str | Path) -> Path:
        """Write the grid atomically as a compressed ``.npz``."""
        path = Path(path)
        atomic_write_bytes(path, self.to_bytes())
        return path

    @classmethod
    def load(cls, path: str | Path) -> SceneGrid:
        path = Path(path)
        if not path.is_file():
            raise InputFormatError(f"{path}: scene grid not found (expected an .npz with labels, origin, voxel_size)")
        try:
            with np.load(path, allow_pickle=False) as z:
                missing = [k for k in ("labels", "origin", "voxel_size") if k not in z.files]
                if missing:
                    raise InputFormatError(
                        f"{path}: scene grid is missing array(s) {', '.join(missing)} "
                        "(expected labels, origin, voxel_size)"
                    )
                labels, origin, vs = z["labels"], z["origin"], z["voxel_size"]
                crs = str(z["crs"]) if "crs" in z.files else None
        except InputFormatError:
            raise
        except Exception as e:  # noqa: BLE001 - zip / npy parser errors vary
            raise InputFormatError(f"{path}: not a readable .npz scene grid ({e})") from None
        if labels.ndim != 3 or labels.dtype != np.uint8:
            raise InputFormatError(
                f"{path}: labels must be a 3-D uint8 array, got {labels.dtype} {labels.shape}"
            )
        try:
            return cls(labels, origin, float(np.asarray(vs).reshape(-1)[0]), crs=crs)
        except (ValueError, IndexError) as e:
            raise InputFormatError(f"{path}: {e}") from None

