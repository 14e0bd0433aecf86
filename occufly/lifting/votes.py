"""The incremental per-point vote state of one scene workspace.

Votes
    Every annotated frame votes once for each point it sees, with the mask pixel the point
    projects to (``floor(uv / s)`` for a mask downscaled by the integer ``s``). 0 (unpainted)
    and 255 (ignore) cast no vote. Counts live in ``ws/lifting/votes.npy``, a memory-mapped
    (N, C) uint16 array over the taxonomy's classes in table order, and every frame's own votes
    in ``ws/lifting/frames/<frame_index>.npz`` (point ids, class column) so that replacing or
    removing a mask subtracts exactly what it added. The cost of :meth:`LiftState.apply_frame` is
    proportional to the points that frame sees, never to the scene.

    Crash safety: ``state.json`` is marked dirty before the votes are touched and clean after;
    the per-frame file is written (atomically) *before* the counts change, so a dirty state is
    repaired on open by recounting from the per-frame files.

Majority
    Unweighted; ties go to the class that comes first in ``taxonomy.tie_order`` (vectorised:
    argmax over the class columns reordered by priority returns the first maximum).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occufly.errors import MaskError, WorkspaceError
from occufly.fsutil import atomic_write_bytes, atomic_write_text
from occufly.lifting.classes import ClassColumns
from occufly.lifting.knn import LiftParams
from occufly.lifting.result import LiftResult, save_result
from occufly.progress import ProgressFn, noop
from occufly.scene import Scene
from occufly.taxonomy import EMPTY, INVALID
from occufly.workspace import Workspace

STATE_VERSION = 1
_CHUNK_ROWS = 1_000_000

#: ``plain``: every view casts one vote. ``boundary``: a view's vote counts 1 within
#: ``BOUNDARY_PX`` mask pixels of a boundary in its mask (a class change or the edge of an
#: unpainted area), 2 within twice that, else 3 -- people paint boundaries a few pixels off,
#: so the views in which a point lies well inside a region outvote those in which it sits on
#: an edge.
VOTE_WEIGHTINGS = ("plain", "boundary")
BOUNDARY_PX = 3


def boundary_weights(mask: np.ndarray, px: int = BOUNDARY_PX) -> np.ndarray:
    """(h, w) uint8 vote weight of each mask pixel: 1 / 2 / 3 by chessboard distance to the
    nearest pixel whose 4-neighbourhood holds another id (< px, < 2 px, beyond)."""
    from scipy import ndimage

    m = np.asarray(mask)
    edge = np.zeros(m.shape, bool)
    dv = m[1:, :] != m[:-1, :]
    dh = m[:, 1:] != m[:, :-1]
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    if not edge.any():
        return np.full(m.shape, 3, np.uint8)
    d = ndimage.distance_transform_cdt(~edge, metric="chessboard")
    return (1 + (d >= px).astype(np.uint8) + (d >= 2 * px).astype(np.uint8)).astype(np.uint8)


class LiftState:
    """Per-point vote counts for one scene workspace, updated incrementally.

    Not safe for concurrent writers: one process (the web app's lifting worker or the CLI)
    owns a workspace's lifting state at a time.
    """

    def __init__(self, ws: Path, scene: Scene, votes: np.ndarray, versions: dict[int, str | None]):
        self.ws = Path(ws)
        self.scene = scene
        self.votes = votes  # (N, C) uint16 memmap
        self._versions = versions
        self._cls = ClassColumns(scene.taxonomy)
        self.read_only = False
        self.vote_weighting = "plain"

    # -- paths
    @property
    def dir(self) -> Path:
        return Workspace(self.ws).lifting_dir

    def _frame_path(self, frame_index: int) -> Path:
        return Workspace(self.ws).lifting_frame(frame_index)

    # -- open / save
    @classmethod
    def open(cls, ws: str | Path, scene: Scene | None = None, *,
             read_only: bool = False, vote_weighting: str | None = None) -> LiftState:
        """Load the lifting state of workspace ``ws`` (resuming from what is on disk: the
        counts, the per-frame votes and the included versions), or create an empty one.

        A state left dirty by an interrupted update is repaired by recounting from the
        per-frame files. ``read_only=True`` (readers such as the viewer, while a worker owns
        the workspace) never writes: it maps the counts read-only, neither creates nor repairs
        a state, and raises :class:`WorkspaceError` when there is none or it is dirty.

        vote_weighting: ``"plain"`` (one vote per view) or ``"boundary"`` (votes fall off near
        mask boundaries, see :data:`VOTE_WEIGHTINGS`); fixed when the state is created
        (None: the stored one, ``"plain"`` for a new state).
        """
        if vote_weighting is not None and vote_weighting not in VOTE_WEIGHTINGS:
            raise ValueError(f"vote_weighting {vote_weighting!r}: expected one of "
                             f"{', '.join(VOTE_WEIGHTINGS)}")
        ws = Path(ws)
        if scene is None:
            scene = Scene.load(ws)
        w = Workspace(ws)
        d = w.lifting_dir
        state_path = w.lifting_state
        n, ids = scene.n_points, [int(i) for i in scene.taxonomy.ids]
        votes_path = w.votes
        if read_only and not state_path.is_file():
            raise WorkspaceError(f"{state_path}: no lifting state yet (no mask has been lifted)")
        if state_path.is_file():
            try:
                state = json.loads(state_path.read_text())
            except json.JSONDecodeError as e:
                raise WorkspaceError(f"{state_path}: not valid JSON ({e})") from None
            if state.get("n_points") != n or state.get("class_ids") != ids:
                raise WorkspaceError(
                    f"{state_path}: lifting state was built for {state.get('n_points')} points / "
                    f"classes {state.get('class_ids')}, the scene has {n} points / classes {ids}; "
                    f"remove {d} to start the lifting over"
                )
            if not votes_path.is_file():
                raise WorkspaceError(f"{votes_path}: missing vote counts (remove {d} to start over)")
            votes = np.lib.format.open_memmap(votes_path, mode="r" if read_only else "r+")
            if votes.shape != (n, len(ids)) or votes.dtype != np.uint16:
                raise WorkspaceError(f"{votes_path}: expected ({n}, {len(ids)}) uint16 vote counts")
            versions = {int(k): v for k, v in state.get("versions", {}).items()}
            stored = state.get("vote_weighting", "plain")
            if vote_weighting is not None and vote_weighting != stored:
                raise WorkspaceError(
                    f"{state_path}: the lifting state counts {stored!r} votes, not "
                    f"{vote_weighting!r}; remove {d} to start the lifting over")
            self = cls(ws, scene, votes, versions)
            self.vote_weighting = stored
            self.read_only = read_only
            if state.get("dirty"):
                if read_only:
                    raise WorkspaceError(f"{state_path}: an update is in progress or was "
                                         "interrupted (open it writable to repair it)")
                self.rebuild()
            return self
        w.lifting_frames_dir.mkdir(parents=True, exist_ok=True)
        tmp = d / f".votes.npy.{os.getpid()}.tmp"
        votes = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint16, shape=(n, len(ids)))
        votes.flush()
        del votes
        os.replace(tmp, votes_path)
        votes = np.lib.format.open_memmap(votes_path, mode="r+")
        self = cls(ws, scene, votes, {})
        self.vote_weighting = vote_weighting or "plain"
        stale = sorted(w.lifting_frames_dir.glob("*.npz"))
        if stale:  # frame votes without a state file: recount from them
            self._versions = {int(p.stem): None for p in stale if p.stem.isdigit()}
            self.rebuild()
        else:
            self._write_state(dirty=False)
        return self

    def _write_state(self, *, dirty: bool) -> None:
        state = {
            "version": STATE_VERSION,
            "n_points": self.scene.n_points,
            "class_ids": [int(i) for i in self._cls.ids],
            "versions": {str(k): v for k, v in sorted(self._versions.items())},
            "vote_weighting": self.vote_weighting,
            "dirty": dirty,
        }
        atomic_write_text(Workspace(self.ws).lifting_state, json.dumps(state, indent=1))

    def save(self) -> None:
        """Flush the vote counts and write ``state.json`` atomically.

        Every update already ends with a save; a worker can stop at any point between
        updates and :meth:`open` resumes from exactly these files."""
        self._writable()
        self.votes.flush()
        self._write_state(dirty=False)

    def close(self) -> None:
        """Flush (when writable) and drop the memory map; the object is unusable after."""
        if not self.read_only:
            self.votes.flush()
        self.votes = None

    def _writable(self) -> None:
        if self.read_only:
            raise WorkspaceError(f"{self.dir}: lifting state opened read-only")

    def rebuild(self) -> None:
        """Recount every vote from the per-frame files (repairs an interrupted update)."""
        self._write_state(dirty=True)
        self.votes[:] = 0
        flat = self.votes.reshape(-1)
        C = self._cls.C
        for p in sorted(Workspace(self.ws).lifting_frames_dir.glob("*.npz")):
            if not p.stem.isdigit():
                continue
            pids, cols, w = self._load_frame_file(p)
            np.add.at(flat, pids.astype(np.int64) * C + cols, w)
            self._versions.setdefault(int(p.stem), None)
        for fi in list(self._versions):
            if not self._frame_path(fi).is_file():
                del self._versions[fi]
        self.save()

    # -- queries
    def included_versions(self) -> dict[int, str | None]:
        """frame_index -> version tag of the mask whose votes are counted."""
        return dict(sorted(self._versions.items()))

    def version_of(self, frame_index: int) -> str | None:
        """Version tag of the mask counted for ``frame_index`` (None when none is)."""
        return self._versions.get(int(frame_index))

    def direct_labels(self) -> np.ndarray:
        """(N,) uint8 raw ids of the vote majority, 0 where a point has no votes."""
        return self._direct()[0]

    def snapshot(self) -> VoteSnapshot:
        """The vote majority and the versions it counts, copied out of the shared counts.

        Cheap next to a fill (one pass over the (N, C) counts): take it under the lock that
        serialises updates, then run :meth:`fill_and_denoise` ``(snapshot=...)`` or
        :func:`fill_snapshot` without holding it."""
        direct, margin, top = self._direct()
        if self.vote_weighting == "boundary":
            # the confirmation rule counts views: a weight-3 vote is one view
            top = ((top.astype(np.uint32) + 2) // 3).astype(np.uint16)
        return VoteSnapshot(direct=direct, margin=margin, top=top,
                            versions=self.included_versions())

    def labels(self) -> LiftResult | None:
        """The latest fill/denoise output on disk (labels, confidence, origin), or None."""
        from occufly.lifting.result import load_labels

        return load_labels(self.ws)

    def _direct(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(labels (N,) uint8, vote margin (N,) float32 = (top - second) / votes,
        top (N,) uint16 = votes of the winning class)."""
        n = self.scene.n_points
        labels = np.zeros(n, dtype=np.uint8)
        margin = np.zeros(n, dtype=np.float32)
        top_votes = np.zeros(n, dtype=np.uint16)
        for a in range(0, n, _CHUNK_ROWS):
            b = min(n, a + _CHUNK_ROWS)
            c = np.asarray(self.votes[a:b])
            col, top, second = self._cls.majority(c)
            labels[a:b] = self._cls.labels_of(col)
            top_votes[a:b] = top
            total = c.sum(axis=1, dtype=np.int64)
            with np.errstate(divide="ignore", invalid="ignore"):
                margin[a:b] = np.where(total > 0, (top.astype(np.float64) - second) / total, 0.0)
        return labels, margin, top_votes

    def labels_of_points(self, point_ids: np.ndarray) -> np.ndarray:
        """(m,) uint8 direct labels of the given points (cost ~ m)."""
        return self._cls.labels_of(self._cls.winner(self.votes[np.asarray(point_ids, np.int64)]))

    # -- updates
    def _check_frame(self, frame_index: int, name: str) -> int:
        if not isinstance(frame_index, (int, np.integer)) or not (
            0 <= int(frame_index) < len(self.scene.frames)
        ):
            raise MaskError(
                f"{name}: frame {frame_index!r} is not in the scene (it has "
                f"{len(self.scene.frames)} frames, indices 0..{len(self.scene.frames) - 1})"
            )
        return int(frame_index)

    def frame_votes(self, frame_index: int, mask: np.ndarray, *, name: str = "<mask>"
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validate ``mask`` for a frame and return its votes: (point ids int32, column uint8,
        weight uint8 -- all 1 with plain weighting)."""
        from occufly.io.masks import mask_scale, validate_ids

        fi = self._check_frame(frame_index, name)
        frame = self.scene.frames[fi]
        mask = np.asarray(mask)
        if mask.ndim != 2:
            raise MaskError(f"{name}: expected a (h, w) array of raw class ids, got shape {mask.shape}")
        if mask.dtype != np.uint8:
            if not np.issubdtype(mask.dtype, np.integer) or (
                mask.size and (mask.min() < 0 or mask.max() > 255)
            ):
                raise MaskError(f"{name}: expected uint8 raw class ids 0..255, got {mask.dtype}")
            mask = mask.astype(np.uint8)
        s = mask_scale(mask.shape, frame, name=name)
        validate_ids(mask, self.scene.taxonomy, name=name)
        pids, uv, _ = self.scene.visibility.frame(fi)
        h, w = mask.shape
        uv = np.asarray(uv)
        col = np.clip(np.floor(uv[:, 0] / s).astype(np.int64), 0, w - 1)
        row = np.clip(np.floor(uv[:, 1] / s).astype(np.int64), 0, h - 1)
        raw = mask[row, col]
        keep = (raw != EMPTY) & (raw != INVALID)
        if self.vote_weighting == "boundary":
            weight = boundary_weights(mask)[row[keep], col[keep]]
        else:
            weight = np.ones(int(keep.sum()), np.uint8)
        return (np.asarray(pids)[keep].astype(np.int32),
                self._cls.col_of[raw[keep]].astype(np.uint8), weight)

    @staticmethod
    def _load_frame_file(p: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        with np.load(p, allow_pickle=False) as z:
            pids, cols = z["point_ids"], z["cols"]
            w = z["weights"] if "weights" in z.files else np.ones(len(pids), np.uint8)
            return pids, cols, w

    def _old_votes(self, fi: int) -> tuple[np.ndarray, np.ndarray]:
        p = self._frame_path(fi)
        if p.is_file():
            return self._load_frame_file(p)
        return np.zeros(0, np.int32), np.zeros(0, np.uint8), np.zeros(0, np.uint8)

    def _apply(self, old: tuple[np.ndarray, ...], new: tuple[np.ndarray, ...]) -> dict:
        C = self._cls.C
        mark = np.zeros(self.scene.n_points, dtype=bool)  # O(N) bytes, no sort
        mark[old[0]] = True
        mark[new[0]] = True
        touched = np.flatnonzero(mark)
        before = self.labels_of_points(touched)
        flat = self.votes.reshape(-1)
        if len(old[0]):
            np.subtract.at(flat, old[0].astype(np.int64) * C + old[1], old[2].astype(np.uint16))
        if len(new[0]):
            np.add.at(flat, new[0].astype(np.int64) * C + new[1], new[2].astype(np.uint16))
        after = self.labels_of_points(touched)
        return {
            "points_touched": int(len(touched)),
            "points_changed": int(np.count_nonzero(before != after)),
            "votes_removed": int(old[2].sum(dtype=np.int64)),
            "votes_added": int(new[2].sum(dtype=np.int64)),
        }

    def apply_frame(self, frame_index: int, mask: np.ndarray, *, version: str | None = None,
                    name: str | None = None) -> dict:
        """Replace frame ``frame_index``'s votes with those of ``mask`` ((h, w) uint8 raw ids).

        Validates the mask first (MaskError naming ``name``; the state is then unchanged).
        Returns {points_touched, points_changed (direct label changed), votes_removed,
        votes_added, seconds}.
        """
        self._writable()
        t0 = time.perf_counter()
        name = name or f"mask of frame {frame_index}"
        pids, cols, weights = self.frame_votes(frame_index, mask, name=name)
        fi = int(frame_index)
        old = self._old_votes(fi)
        self._write_state(dirty=True)
        arrays = {"point_ids": pids, "cols": cols}
        if self.vote_weighting != "plain":
            arrays["weights"] = weights
        atomic_write_bytes(self._frame_path(fi), _npz_bytes(**arrays))
        stats = self._apply(old, (pids, cols, weights))
        self._versions[fi] = version
        self.save()
        stats["frame_index"] = fi
        stats["seconds"] = time.perf_counter() - t0
        return stats

    set_mask = apply_frame  # the original name, kept for callers and tests

    def remove_frame(self, frame_index: int) -> dict:
        """Subtract frame ``frame_index``'s votes (no-op if it has none)."""
        self._writable()
        t0 = time.perf_counter()
        fi = self._check_frame(frame_index, f"mask of frame {frame_index}")
        p = self._frame_path(fi)
        if not p.is_file():
            return {"frame_index": fi, "removed": False, "points_touched": 0, "points_changed": 0,
                    "votes_removed": 0, "votes_added": 0, "seconds": time.perf_counter() - t0}
        old = self._old_votes(fi)
        self._write_state(dirty=True)
        stats = self._apply(old, (np.zeros(0, np.int32), np.zeros(0, np.uint8), np.zeros(0, np.uint8)))
        self.votes.flush()
        p.unlink()
        self._versions.pop(fi, None)
        self.save()
        stats.update(frame_index=fi, removed=True, seconds=time.perf_counter() - t0)
        return stats

    remove_mask = remove_frame

    # -- fill and denoise
    def fill_and_denoise(self, progress: ProgressFn | None = None,
                         params: LiftParams | None = None, *,
                         snapshot: VoteSnapshot | None = None, write: bool = True) -> LiftResult:
        """kNN fill + denoise of the votes; writes labels/confidence/origin (``write=False``:
        only returns them).

        Without ``snapshot`` the current counts are read first (hold the update lock for the
        whole call then); with one taken by :meth:`snapshot`, nothing here reads the shared
        counts, so updates may go on meanwhile.
        """
        report = progress or noop
        if write:
            self._writable()
        if snapshot is None:
            report(0.0, "majority vote")
            snapshot = self.snapshot()
        result = fill_snapshot(self.scene, snapshot, params=params,
                               progress=lambda f, m: report(0.05 + 0.9 * f, m))
        if write:
            report(0.96, "writing labels")
            save_result(self.ws, result)
        report(1.0, "done")
        return result


@dataclass
class VoteSnapshot:
    """The vote majority of a :class:`LiftState` at one moment.

    direct: (N,) uint8 raw ids (0 = no votes); margin: (N,) float32 ``(top - second) /
    votes``; top: (N,) uint16 votes of the winning class; versions: frame index -> version
    tag of the masks counted.
    """

    direct: np.ndarray
    margin: np.ndarray
    top: np.ndarray
    versions: dict[int, str | None]

    @property
    def annotated_frames(self) -> int:
        return len(self.versions)


def fill_snapshot(scene: Scene, snapshot: VoteSnapshot, *, params: LiftParams | None = None,
                  progress: ProgressFn | None = None) -> LiftResult:
    """kNN fill + denoise of a :class:`VoteSnapshot` (does not write anything)."""
    # looked up on the package at call time, so that a test (or a profiler) patching
    # ``occufly.lifting.fill_and_denoise`` sees every fill, whichever entry point ran it
    import occufly.lifting as pkg

    result = pkg.fill_and_denoise(
        np.asarray(scene.xyz), snapshot.direct, scene.taxonomy, params=params,
        vote_margin=snapshot.margin, vote_top=snapshot.top, progress=progress)
    result.stats["annotated_frames"] = snapshot.annotated_frames
    result.stats["versions"] = {str(k): v for k, v in sorted(snapshot.versions.items())}
    return result


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()
