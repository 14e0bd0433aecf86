"""The scene workspace on disk: the one owner of every artefact path.

A workspace is a folder written by ``occufly import`` and grown by later steps. This module
is the only place that spells its layout; every other module asks a :class:`Workspace` for a
path, a reader or an atomic writer::

    WS/scene.json                  header: format, version, origin (float64), frames, meta
    WS/taxonomy.json               the scene's class table
    WS/points/xyz.npy              (N, 3) float32 scene-local metres
    WS/points/rgb.npy              (N, 3) uint8
    WS/visibility/offsets.npy      (F + 1,) int64 CSR by frame
    WS/visibility/point_ids.npy    (M,) int32
    WS/visibility/uv.npy           (M, 2) float32 pixel coordinates [optional since v2]
    WS/visibility/depth.npy        (M,) float32 camera depth, metres [optional since v2]
    WS/lifting/state.json          vote state: included mask versions, dirty flag
    WS/lifting/votes.npy           (N, C) uint16 vote counts (memory-mapped, updated in place)
    WS/lifting/frames/<F>.npz      the votes one frame cast (point ids, class columns)
    WS/lifting/labels.npy          (N,) uint8 fill + denoise output (written last)
    WS/lifting/confidence.npy      (N,) float32 in [0, 1]
    WS/lifting/origin.npy          (N,) uint8 label origin: 0 none, 1 direct, 2 filled, 3 denoised
    WS/lifting/labels.json         statistics of the last fill
    WS/lifting/corrections/overrides.npz
                                   net effect of reviewers' label corrections (point ids, labels):
                                   the override layer above votes, fill and denoise
                                   (occufly.lifting.corrections; applied by load_labels)
    WS/lifting/corrections/edit_<id>.npz
                                   the point ids of one correction edit (uint32, zlib)
    WS/grid/scene_grid.npz         the densified scene grid (``scene_grid_<alt>.npz`` per altitude)
    WS/grid/scene_grid_report.json the densification report
    WS/truth/scene_grid.npz        a truth grid kept with the workspace (synthetic scenes)

Writers are atomic (temporary name, fsync, rename). :meth:`Workspace.stamp` changes whenever
an artefact that readers cache (header, labels, grid) changes, so a viewer or a review page
can tell cheaply whether to reload.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib import format as npy_format

from occufly.errors import WorkspaceError
from occufly.fsutil import atomic_save_npy, atomic_write_text, load_npz
from occufly.grid import SceneGrid

SCENE_JSON = "scene.json"
TAXONOMY_JSON = "taxonomy.json"
POINTS_DIR = "points"
VISIBILITY_DIR = "visibility"
LIFTING_DIR = "lifting"
GRID_DIR = "grid"
TRUTH_DIR = "truth"
#: the visibility arrays, in the order :class:`occufly.scene.Visibility` takes them
VISIBILITY_ARRAYS = ("offsets", "point_ids", "uv", "depth")


class Workspace:
    """Paths, readers and atomic writers of one scene workspace rooted at ``root``."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"Workspace({str(self.root)!r})"

    def __fspath__(self) -> str:
        return str(self.root)

    @classmethod
    def of(cls, ws: str | Path | Workspace) -> Workspace:
        """``ws`` itself if it is a :class:`Workspace`, else a new one rooted there."""
        return ws if isinstance(ws, Workspace) else cls(ws)

    # ---- header -------------------------------------------------------------------------
    @property
    def scene_json(self) -> Path:
        return self.root / SCENE_JSON

    @property
    def taxonomy_json(self) -> Path:
        return self.root / TAXONOMY_JSON

    def exists(self) -> bool:
        """True when ``root`` holds a workspace header."""
        return self.scene_json.is_file()

    def require(self) -> Workspace:
        """``self``, or :class:`WorkspaceError` naming the folder when it is no workspace."""
        if not self.exists():
            raise WorkspaceError(f"{self.root}: not a scene workspace (no {SCENE_JSON})")
        return self

    def header(self) -> dict:
        """The parsed ``scene.json``."""
        self.require()
        try:
            return json.loads(self.scene_json.read_text())
        except json.JSONDecodeError as e:
            raise WorkspaceError(f"{self.scene_json}: not valid JSON ({e})") from None

    def write_header(self, header: dict) -> None:
        atomic_write_text(self.scene_json, json.dumps(header, indent=1))

    # ---- points and visibility ----------------------------------------------------------
    @property
    def points_dir(self) -> Path:
        return self.root / POINTS_DIR

    @property
    def points_xyz(self) -> Path:
        return self.points_dir / "xyz.npy"

    @property
    def points_rgb(self) -> Path:
        return self.points_dir / "rgb.npy"

    @property
    def visibility_dir(self) -> Path:
        return self.root / VISIBILITY_DIR

    def visibility_array(self, name: str) -> Path:
        """Path of one visibility array (``offsets``, ``point_ids``, ``uv``, ``depth``, ...)."""
        if not name.isidentifier():
            raise ValueError(f"visibility array name must be an identifier, got {name!r}")
        return self.visibility_dir / f"{name}.npy"

    def array(self, path: Path, *, mmap: bool = True) -> np.ndarray:
        """Load a workspace array, or :class:`WorkspaceError` naming the missing file."""
        if not path.is_file():
            raise WorkspaceError(f"{path}: missing workspace array")
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)

    # ---- lifting ------------------------------------------------------------------------
    @property
    def lifting_dir(self) -> Path:
        return self.root / LIFTING_DIR

    @property
    def lifting_state(self) -> Path:
        return self.lifting_dir / "state.json"

    @property
    def votes(self) -> Path:
        return self.lifting_dir / "votes.npy"

    @property
    def lifting_frames_dir(self) -> Path:
        return self.lifting_dir / "frames"

    def lifting_frame(self, frame_index: int) -> Path:
        """The votes frame ``frame_index`` cast (``lifting/frames/<index>.npz``)."""
        return self.lifting_frames_dir / f"{int(frame_index)}.npz"

    def read_frame_votes(self, frame_index: int, *, mmap: bool = False
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
        """The votes frame ``frame_index`` cast, as stored: (point ids, vote columns, weights --
        None where the state counts plain votes and the file keeps none), or None without a
        file. The one reader of ``lifting/frames/<index>.npz`` (the votes store, the review's
        leave-one-out labels, the quality report, the confusion model): stored members are
        read straight into their arrays (:func:`occufly.fsutil.load_npz`: no zip stream, no
        CRC pass, no descriptor left open; ``mmap``: read-only memory maps instead, each
        holding the file open until dropped); a file that is not the archive the votes store
        writes is a :class:`WorkspaceError` naming it, one removed meanwhile (its mask deleted)
        None."""
        p = self.lifting_frame(frame_index)
        if not p.is_file():
            return None
        try:
            z = load_npz(p, mmap=mmap)
            pids, cols = z["point_ids"], z["cols"]
        except FileNotFoundError:
            return None
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
            raise WorkspaceError(f"{p}: unreadable votes of frame {int(frame_index)} ({e}); "
                                 "re-apply the frame's mask to rewrite them") from None
        w = z.get("weights")
        if pids.ndim != 1 or cols.shape != pids.shape or (w is not None and w.shape != pids.shape):
            raise WorkspaceError(f"{p}: point_ids {pids.shape}, cols {cols.shape} and weights "
                                 f"{None if w is None else w.shape} differ")
        return pids, cols, w

    @property
    def labels_path(self) -> Path:
        return self.lifting_dir / "labels.npy"

    @property
    def confidence_path(self) -> Path:
        return self.lifting_dir / "confidence.npy"

    @property
    def label_origin_path(self) -> Path:
        return self.lifting_dir / "origin.npy"

    @property
    def labels_stats_path(self) -> Path:
        return self.lifting_dir / "labels.json"

    @property
    def corrections_dir(self) -> Path:
        """Reviewers' label corrections (``lifting/corrections/``): per-edit point-id files and
        the net override layer (:mod:`occufly.lifting.corrections`)."""
        return self.lifting_dir / "corrections"

    @property
    def overrides_path(self) -> Path:
        """``lifting/corrections/overrides.npz``: the net override layer (``point_ids`` (K,)
        int64 sorted unique, ``labels`` (K,) uint8 raw ids, 0 = set to unlabelled)."""
        return self.corrections_dir / "overrides.npz"

    def correction_edit(self, edit_id: int) -> Path:
        """``lifting/corrections/edit_<id>.npz``: the point ids of one correction edit
        (``point_ids`` (K,) uint32 sorted unique, zlib-compressed; written before the edit's
        database row, see :func:`occufly.lifting.corrections.write_edit_points`)."""
        return self.corrections_dir / f"edit_{int(edit_id):08d}.npz"

    def has_labels(self) -> bool:
        return self.labels_path.is_file()

    def labels(self, *, mmap: bool = True) -> np.ndarray | None:
        """(N,) uint8 lifted point labels (fill + denoise output), or None before any fill."""
        return self._optional(self.labels_path, mmap)

    def confidence(self, *, mmap: bool = True) -> np.ndarray | None:
        """(N,) float32 label confidence in [0, 1], or None before any fill."""
        return self._optional(self.confidence_path, mmap)

    def label_origin(self, *, mmap: bool = True) -> np.ndarray | None:
        """(N,) uint8 origin of each label (0 none, 1 direct, 2 filled, 3 denoised), or None."""
        return self._optional(self.label_origin_path, mmap)

    def lift_stats(self) -> dict:
        """Statistics of the last fill (``labels.json``), ``{}`` when absent or unreadable."""
        p = self.labels_stats_path
        if not p.is_file():
            return {}
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError:
            return {}

    def write_labels(self, labels: np.ndarray, confidence: np.ndarray, origin: np.ndarray,
                     stats: dict | None = None) -> None:
        """Store a fill result atomically; ``labels.npy`` is written last, so a reader that
        finds it finds its companion arrays too.

        labels: (N,) uint8 raw ids; confidence: (N,) float32; origin: (N,) uint8.
        """
        n = len(labels)
        if len(confidence) != n or len(origin) != n:
            raise ValueError(f"write_labels: labels ({n}), confidence ({len(confidence)}) and "
                             f"origin ({len(origin)}) must have one value per point")
        atomic_save_npy(self.confidence_path, np.asarray(confidence, dtype=np.float32))
        atomic_save_npy(self.label_origin_path, np.asarray(origin, dtype=np.uint8))
        if stats is not None:
            atomic_write_text(self.labels_stats_path,
                              json.dumps(stats, indent=1, default=_jsonable))
        atomic_save_npy(self.labels_path, np.asarray(labels, dtype=np.uint8))

    # ---- grids --------------------------------------------------------------------------
    @property
    def grid_dir(self) -> Path:
        return self.root / GRID_DIR

    def grid_path(self, altitude: int | None = None) -> Path:
        """``grid/scene_grid.npz`` or, for an altitude-specific grid, ``scene_grid_<alt>.npz``."""
        if altitude is None:
            return self.grid_dir / "scene_grid.npz"
        return self.grid_dir / f"scene_grid_{int(altitude)}.npz"

    def altitude_grids(self) -> dict[int, Path]:
        """altitude -> path of every altitude-specific grid present."""
        out: dict[int, Path] = {}
        for p in sorted(self.grid_dir.glob("scene_grid_*.npz")):
            tail = p.stem[len("scene_grid_"):]
            if tail.isdigit():
                out[int(tail)] = p
        return out

    @staticmethod
    def report_path_of(grid_path: Path) -> Path:
        """The densification report written beside a grid file."""
        return grid_path.with_name(grid_path.stem + "_report.json")

    def has_grid(self, altitude: int | None = None) -> bool:
        return self.grid_path(altitude).is_file()

    def grid(self, altitude: int | None = None) -> SceneGrid | None:
        """The densified scene grid, or None before ``occufly voxelize``."""
        p = self.grid_path(altitude)
        return SceneGrid.load(p) if p.is_file() else None

    def write_grid(self, grid: SceneGrid, altitude: int | None = None,
                   report: dict | None = None) -> Path:
        """Store a scene grid (and its report) atomically; returns the grid's path."""
        p = self.grid_path(altitude)
        grid.save(p)
        if report is not None:
            atomic_write_text(self.report_path_of(p), json.dumps(report, indent=1, default=_jsonable))
        return p

    @property
    def truth_dir(self) -> Path:
        return self.root / TRUTH_DIR

    @property
    def truth_grid_path(self) -> Path:
        return self.truth_dir / "scene_grid.npz"

    def truth_grid(self) -> SceneGrid | None:
        p = self.truth_grid_path
        return SceneGrid.load(p) if p.is_file() else None

    # ---- change stamp -------------------------------------------------------------------
    def stamp_paths(self) -> list[Path]:
        """The artefacts whose change readers care about (header, labels, grids)."""
        paths = [self.scene_json, self.labels_path, self.confidence_path, self.label_origin_path,
                 self.lifting_state, self.overrides_path, self.grid_path()]
        paths += list(self.altitude_grids().values())
        return paths

    def stamp(self) -> str:
        """A short string that changes whenever any of :meth:`stamp_paths` changes
        (modification time in ns and size; absent files count as absent)."""
        h = hashlib.sha1()
        for p in self.stamp_paths():
            try:
                st = p.stat()
                h.update(f"{p.name}:{st.st_mtime_ns}:{st.st_size};".encode())
            except FileNotFoundError:
                h.update(f"{p.name}:-;".encode())
        return h.hexdigest()[:16]

    def steps(self) -> dict[str, bool]:
        """Which pipeline steps have produced their artefact (for ``occufly info``)."""
        return {"lifting": self.has_labels(), "grid": self.has_grid(),
                "truth_grid": self.truth_grid_path.is_file()}

    # ---- helpers ------------------------------------------------------------------------
    def _optional(self, path: Path, mmap: bool) -> np.ndarray | None:
        if not path.is_file():
            return None
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)


class NpyStreamWriter:
    """Write a 1-D ``.npy`` file part by part, without the array ever in memory.

    The header is written first with a length of 0 and rewritten with the final length on
    :meth:`close` (numpy pads a 1-D header for 21 digits, so its size does not change): the
    file is byte-identical to ``np.save`` of the concatenated parts. Memory is one part.
    Used inside an atomic directory (the import's visibility ids), so a failed write leaves
    nothing behind.

        with NpyStreamWriter(path, np.int32) as w:
            w.append(part)
    """

    def __init__(self, path: str | Path, dtype: np.dtype | type) -> None:
        self.path = Path(path)
        self.dtype = np.dtype(dtype)
        self.count = 0
        self._fmt = npy_format
        self._fh = open(self.path, "wb")
        self._header_len = self._write_header()

    def _write_header(self) -> int:
        d = self._fmt.header_data_from_array_1_0(np.zeros(0, self.dtype))
        d["shape"] = (self.count,)
        self._fh.seek(0)
        self._fmt.write_array_header_1_0(self._fh, d)
        return self._fh.tell()

    def append(self, part: np.ndarray) -> None:
        """Append ``part`` (1-D, cast to the writer's dtype)."""
        a = np.ascontiguousarray(part, dtype=self.dtype).reshape(-1)
        if len(a):
            self._fh.write(memoryview(a).cast("B"))
            self.count += len(a)

    def close(self) -> None:
        """Rewrite the header with the final length and close the file."""
        if self._fh.closed:
            return
        try:
            end = self._fh.tell()
            if self._write_header() != self._header_len:  # cannot happen with numpy's padding
                raise RuntimeError(f"{self.path}: .npy header changed size")
            self._fh.seek(end)
            self._fh.flush()
        finally:
            self._fh.close()

    def __enter__(self) -> NpyStreamWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
