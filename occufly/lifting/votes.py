"""The incremental per-point vote state of one scene workspace.

Votes
    Every annotated frame votes once for each point it sees, with the mask pixel the point
    projects to (``floor(uv / s)`` for a mask downscaled by the integer ``s``). 0 (unpainted)
    and 255 (ignore) cast no vote. Counts live in ``ws/lifting/votes.npy``, a memory-mapped
    (N, C) uint16 array over the taxonomy's classes in table order, and every frame's own votes
    in ``ws/lifting/frames/<frame_index>.npz`` (point ids, class column) so that replacing or
    removing a mask subtracts exactly what it added. The cost of :meth:`VoteStore.apply_frame` is
    proportional to the points that frame sees, never to the scene.

    Crash safety: ``state.json`` is marked dirty before the votes are touched and clean after;
    the per-frame file is written (atomically) *before* the counts change, so a dirty state is
    repaired on open by recounting from the per-frame files.

Majority
    Unweighted by default (``vote_weighting="plain"``; ``"boundary"`` and ``"interior"``
    weight each view's vote by its pixel's distance to a boundary of its own mask, ``"snap"``
    first moves the mask's boundaries onto its photo's edges (:mod:`occufly.lifting.snap`);
    measured in issue 37 and not the default: docs/lifting.md); ties go to the class that comes first in ``taxonomy.tie_order`` (vectorised:
    one argmax over packed keys ``count << bits | (C - 1 - rank)``,
    :meth:`ClassColumns.packed_winner`).

Update cost
    :meth:`VoteStore.apply_frame` reads and writes only the points whose vote from that frame
    changes (a per-point code of the frame's old and new vote), updates their counts in memory
    and recounts a winner only where the winning class lost a vote. On a fabricated
    5472 x 3648 frame seeing 1.7 M points (``bench/bench_lifting.py --vote-update``, best of
    5 CPU at load 4.6) an edit went from 0.54 s to 0.24 s and a first save from 0.54 s to
    0.47 s (at load 11-14: 1.40 -> 0.24 s and 0.59 -> 0.45 s); identical counts and
    changed-point figures.

Robust decision
    :meth:`VoteStore.snapshot` also keeps each point's second vote class, which the robust
    decision of :func:`fill_snapshot` (:mod:`occufly.lifting.robust`, ``LiftParams.robust``)
    needs besides the majority.
"""

from __future__ import annotations

import io
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
from scipy import ndimage

from occufly.errors import MaskError, OccuflyError, WorkspaceError
from occufly.fsutil import atomic_write_bytes, atomic_write_text, require_memory
from occufly.io.masks import mask_scale, validate_ids
from occufly.lifting import knn
from occufly.lifting.classes import ClassColumns
from occufly.lifting.corrections import load_labels
from occufly.lifting.knn import LiftParams
from occufly.lifting.reliability import (
    frame_class_agreement,
    frame_class_agreement_loo,
    vetoed_counts,
    vetoes,
)
from occufly.lifting.result import LiftResult, save_result
from occufly.lifting.snap import snap_frame_mask
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
#: an edge. ``interior`` (issue 37): the same idea scaled to each painted region's own size
#: (:func:`interior_weights`), so that a small or thin region's core keeps a full vote.
#: ``snap`` (issue 37): one vote per view, of the mask with its class boundaries first moved
#: onto the edges of the frame's photo (:func:`occufly.lifting.snap.snap_mask`; a frame with
#: no readable photo votes its mask as painted).
VOTE_WEIGHTINGS = ("plain", "boundary", "interior", "snap")
#: counts per view (the weight of a vote well inside a region) of each weighting
VOTE_UNITS = {"plain": 1, "boundary": 3, "interior": 4, "snap": 1}
#: the weighting of a new lifting state (an existing one keeps the one it was built with)
DEFAULT_VOTE_WEIGHTING = "plain"
BOUNDARY_PX = 3
#: ``interior``: full weight from this share of the mask's longer side away from a boundary
#: (3.75 px of a 480 px mask, about 43 px of a 5472 px photo)
INTERIOR_SHARE = 1.0 / 128.0
#: ``interior`` weights of a mask larger than this many pixels are computed on a subsample
#: (every f-th row and column) with at least this many pixels, and looked up there
INTERIOR_MAX_PIXELS = 1 << 20
#: ``interior``: the least weight of a vote (on a boundary), in counts of ``VOTE_UNITS``
INTERIOR_FLOOR = 1


def vote_unit(weighting: str) -> int:
    """Counts per view of a vote weighting (1 for ``plain``)."""
    return VOTE_UNITS.get(weighting, 1)


def boundary_weights(mask: np.ndarray, px: int = BOUNDARY_PX) -> np.ndarray:
    """(h, w) uint8 vote weight of each mask pixel: 1 / 2 / 3 by chessboard distance to the
    nearest pixel whose 4-neighbourhood holds another id (< px, < 2 px, beyond)."""
    m = np.asarray(mask)
    edge = _edges(m)
    if not edge.any():
        return np.full(m.shape, 3, np.uint8)
    d = ndimage.distance_transform_cdt(~edge, metric="chessboard")
    return (1 + (d >= px).astype(np.uint8) + (d >= 2 * px).astype(np.uint8)).astype(np.uint8)


def _edges(m: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels with a 4-neighbour of another id (both sides of a boundary)."""
    edge = np.zeros(m.shape, bool)
    dv = m[1:, :] != m[:-1, :]
    dh = m[:, 1:] != m[:, :-1]
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    return edge


def interior_weights(mask: np.ndarray, *, unit: int = VOTE_UNITS["interior"],
                     share: float = INTERIOR_SHARE, floor: int | None = None) -> np.ndarray:
    """(h, w) uint8 vote weight 1..``unit`` of each mask pixel (the ``interior`` weighting).

    ``d``: chessboard distance to the nearest pixel of another id (1 on a boundary);
    ``r``: the largest ``d`` of the pixel's connected same-id region (its inscribed
    radius); ``weight = max(floor, round(unit * min(1, d / min(d0, r))))`` with ``d0 = share
    * max(h, w)`` pixels (``floor``: :data:`INTERIOR_FLOOR` when None). A hurried mask is wrong along its boundaries and right inside, so a
    pixel on the boundary of a large region votes 1/``unit`` of a view and one ``d0`` inside
    a full view; a region narrower than ``2 * d0`` (a person, a cable) reaches full weight
    at its own centre line instead of never. Masks over :data:`INTERIOR_MAX_PIXELS` pixels are
    weighted on a subsample of every f-th row and column (``d0`` scaled alike) and the
    weights looked up there: a 20 MP mask costs about what a 0.6 MP one does.
    """
    m = np.asarray(mask)
    h, w = m.shape
    f = 1
    while (h // f) * (w // f) > INTERIOR_MAX_PIXELS:
        f += 1
    sub = m[::f, ::f] if f > 1 else m
    d0 = max(1.0, share * max(h, w) / f)
    edge = _edges(sub)
    if not edge.any():
        out = np.full(sub.shape, unit, np.uint8)
    else:
        # distance to another id: 1 on the boundary's own side, + the chessboard distance
        cap = int(np.ceil(d0))
        d = np.minimum(ndimage.distance_transform_cdt(~edge, metric="chessboard"), cap) + 1
        # inscribed radius of each connected same-id region (4-connected, one id at a time)
        lab = np.zeros(sub.shape, np.int32)
        n = 0
        for v in np.unique(sub):
            lv, k = ndimage.label(sub == v)
            if k:
                sel = lv > 0
                lab[sel] = lv[sel] + n
                n += k
        r = np.asarray(ndimage.maximum(d, lab, np.arange(n + 1)), np.float32)
        r[0] = 1.0
        scale = np.minimum(np.float32(d0), r[lab])
        t = np.minimum(1.0, d.astype(np.float32) / scale)
        lo = INTERIOR_FLOOR if floor is None else floor
        out = np.clip(np.rint(unit * t), max(1, lo), unit).astype(np.uint8)
    if f > 1:
        out = np.repeat(np.repeat(out, f, axis=0), f, axis=1)
        if out.shape != (h, w):
            out = np.pad(out, ((0, max(0, h - out.shape[0])), (0, max(0, w - out.shape[1]))),
                         mode="edge")[:h, :w]
    return out


def frame_mask_pixels(scene: Scene, frame_index: int, shape: tuple[int, int], *,
                      name: str = "<mask>") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points frame ``frame_index`` sees and the pixel of a mask of ``shape`` each falls
    in: (point ids, row, col), clipped to the mask. A mask at a downscale of the frame is
    scaled by :func:`mask_scale` (a MaskError naming ``name`` for any other size); points
    projected beyond the lens model's valid radius are left out."""
    s = mask_scale(shape, scene.frames[frame_index], name=name)
    pids, uv, _ = scene.visibility.frame(frame_index)
    h, w = shape
    uv = np.asarray(uv)
    pids = np.asarray(pids)
    fin = np.isfinite(uv).all(axis=1)
    if not fin.all():  # projected on demand: points beyond the lens model's valid radius
        pids, uv = pids[fin], uv[fin]
    col = np.clip(np.floor(uv[:, 0] / s).astype(np.int64), 0, w - 1)
    row = np.clip(np.floor(uv[:, 1] / s).astype(np.int64), 0, h - 1)
    return pids, row, col


class VoteStore:
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
        # while a snapshot is taken without the update lock (snapshot_begin .. _finish): the
        # point ids of every row an update wrote meanwhile, recomputed at the finish
        self._touch_log: list[np.ndarray] | None = None
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
             read_only: bool = False, vote_weighting: str | None = None) -> VoteStore:
        """Load the lifting state of workspace ``ws`` (resuming from what is on disk: the
        counts, the per-frame votes and the included versions), or create an empty one.

        A state left dirty by an interrupted update is repaired by recounting from the
        per-frame files. ``read_only=True`` (readers such as the viewer, while a worker owns
        the workspace) never writes: it maps the counts read-only, neither creates nor repairs
        a state, and raises :class:`WorkspaceError` when there is none or it is dirty.

        vote_weighting: ``"plain"`` (one vote per view), ``"boundary"`` or ``"interior"``
        (votes fall off near mask boundaries), ``"snap"`` (one vote per view of the mask
        snapped to its photo's edges), see :data:`VOTE_WEIGHTINGS`; fixed when the
        state is created
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
        self.vote_weighting = vote_weighting or DEFAULT_VOTE_WEIGHTING
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
        self._touched(None)
        self.votes[:] = 0
        flat = self.votes.reshape(-1)
        C = self._cls.C
        for p in sorted(Workspace(self.ws).lifting_frames_dir.glob("*.npz")):
            if not p.stem.isdigit():
                continue
            pids, cols, w = self._frame_file(int(p.stem))
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

    def snapshot(self, counts: np.ndarray | None = None) -> VoteSnapshot:
        """The vote majority and the versions it counts, copied out of the shared counts.

        One compiled pass over the (N, C) counts: take it under the lock that serialises
        updates, then run :meth:`fill_and_denoise` ``(snapshot=...)`` or
        :func:`fill_snapshot` without holding it -- or hold the lock only at both ends
        (:meth:`snapshot_begin`, :meth:`snapshot_finish`). It keeps the two leading vote
        classes of every point, all the robust decision (:mod:`occufly.lifting.robust`) reads."""
        return self._as_snapshot(self._direct(with_second=True, counts=counts))

    def _as_snapshot(self, rows: tuple) -> VoteSnapshot:
        direct, margin, top, second_col, second = rows
        unit = vote_unit(self.vote_weighting)
        if unit != 1:
            # the confirmation rule counts views: a full-weight vote is one view
            top = ((top.astype(np.uint32) + unit - 1) // unit).astype(np.uint16)
        return VoteSnapshot(direct=direct, margin=margin, top=top,
                            versions=self.included_versions(), second_col=second_col,
                            second=second, vote_unit=unit)

    def _touched(self, rows: np.ndarray | None) -> None:
        """An update wrote the counts of points ``rows`` (None: every point)."""
        if self._touch_log is not None:
            self._touch_log.append(np.arange(self.scene.n_points, dtype=np.int64) if rows is None
                                   else np.array(rows, np.int64))

    def snapshot_begin(self) -> None:
        """Start a :meth:`snapshot` whose pass over the counts runs without the update lock
        (a survey's 32 M x 21 counts: about a second, which every vote update would wait for):
        call holding the lock, then :meth:`snapshot_rows` without it, then
        :meth:`snapshot_finish` holding it again. The updates in between log the rows they
        write; the finish recomputes those rows from the counts as they are then, so the
        snapshot is the one the lock would have given at the finish."""
        self._touch_log = []

    def snapshot_rows(self) -> tuple:
        """The pass over the counts of a snapshot begun with :meth:`snapshot_begin` (no lock:
        rows an update writes meanwhile may be read half old, half new; they are logged)."""
        return self._direct(with_second=True)

    def snapshot_cancel(self) -> None:
        """Stop logging the updates' rows (a begun snapshot that will not be finished)."""
        self._touch_log = None

    def snapshot_finish(self, rows: tuple) -> VoteSnapshot:
        """The snapshot of :meth:`snapshot_rows`' ``rows`` with every row an update wrote
        since :meth:`snapshot_begin` recomputed; call holding the update lock."""
        log, self._touch_log = self._touch_log, None
        if log is None:
            raise RuntimeError("snapshot_finish without snapshot_begin")
        if log:
            t = np.unique(np.concatenate(log))
            again = self._direct(with_second=True, counts=np.asarray(self.votes[t]))
            for full, part in zip(rows, again, strict=True):
                full[t] = part
        return self._as_snapshot(rows)

    def labels(self) -> LiftResult | None:
        """The latest fill/denoise output on disk (labels, confidence, origin), or None."""
        return load_labels(self.ws)

    def _direct(self, with_second: bool = False, counts: np.ndarray | None = None
                ) -> tuple[np.ndarray, ...]:
        """(labels (N,) uint8, vote margin (N,) float32 = (top - second) / votes,
        top (N,) uint16 = votes of the winning class); ``with_second`` adds the second
        class's column (N,) int8 (-1 = none) and votes (N,) uint16. ``counts``: (n, C) counts (any rows)
        to read instead of the state's (the reliability veto's)."""
        src = self.votes if counts is None else counts
        n = len(src)
        labels = np.zeros(n, dtype=np.uint8)
        margin = np.zeros(n, dtype=np.float32)
        top_votes = np.zeros(n, dtype=np.uint16)
        if with_second:
            col2 = np.full(n, -1, dtype=np.int8)
            votes2 = np.zeros(n, dtype=np.uint16)
        if COMPILED_DIRECT and direct_compiles(src, self._cls):
            # one compiled pass over the rows, no temporaries: the live worker takes this
            # under the lock that vote updates wait for (a survey's 32 M x 21 counts: seconds
            # of numpy passes before)
            c2o = col2 if with_second else np.empty(n, np.int8)
            v2o = votes2 if with_second else np.empty(n, np.uint16)
            cls = self._cls
            _direct_rows(src, np.asarray(cls._tie_key, np.int64), int(cls._bits),
                         np.asarray(cls.ids, np.uint8), labels, margin, top_votes, c2o, v2o)
            if with_second:
                return labels, margin, top_votes, col2, votes2
            return labels, margin, top_votes
        for a in range(0, n, _CHUNK_ROWS):
            b = min(n, a + _CHUNK_ROWS)
            c = np.asarray(src[a:b])
            packed = self._cls.packed_winner(c)
            if packed is None:
                col, top, second = self._cls.majority(c)
            else:
                col = packed[0]
                top = c[np.arange(b - a), np.maximum(col, 0)]
                top = np.where(col >= 0, top, 0)
                rest = c.copy()
                rest[np.arange(b - a), np.maximum(col, 0)] = 0
                c2 = self._cls.winner(rest)
                second = np.where(c2 >= 0, rest[np.arange(b - a), np.maximum(c2, 0)], 0)
                if with_second:
                    col2[a:b] = c2
                    votes2[a:b] = second
            labels[a:b] = self._cls.labels_of(col)
            top_votes[a:b] = top
            total = c.sum(axis=1, dtype=np.int64)
            with np.errstate(divide="ignore", invalid="ignore"):
                margin[a:b] = np.where(total > 0, (top.astype(np.float64) - second) / total, 0.0)
        if with_second:
            return labels, margin, top_votes, col2, votes2
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
        pids, row, col = frame_mask_pixels(self.scene, fi, mask.shape, name=name)
        validate_ids(mask, self.scene.taxonomy, name=name)
        if self.vote_weighting == "snap":
            mask = snap_frame_mask(frame, mask)
        raw = mask[row, col]
        keep = (raw != EMPTY) & (raw != INVALID)
        if self.vote_weighting == "boundary":
            weight = boundary_weights(mask)[row[keep], col[keep]]
        elif self.vote_weighting == "interior":
            weight = interior_weights(mask)[row[keep], col[keep]]
        else:
            weight = np.ones(int(keep.sum()), np.uint8)
        return (np.asarray(pids)[keep].astype(np.int32),
                self._cls.col_of[raw[keep]].astype(np.uint8), weight)

    def _frame_file(self, fi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Frame ``fi``'s stored votes (point ids, columns, weights -- ones for plain votes),
        or None without a file (:meth:`Workspace.read_frame_votes`)."""
        got = Workspace(self.ws).read_frame_votes(fi)
        if got is None:
            return None
        pids, cols, w = got
        return pids, cols, (w if w is not None else np.ones(len(pids), np.uint8))

    def _old_votes(self, fi: int) -> tuple[np.ndarray, np.ndarray]:
        got = self._frame_file(fi)
        if got is not None:
            return got
        return np.zeros(0, np.int32), np.zeros(0, np.uint8), np.zeros(0, np.uint8)

    def _apply(self, old: tuple[np.ndarray, ...], new: tuple[np.ndarray, ...]) -> dict:
        """Subtract a frame's ``old`` votes and add its ``new`` ones (point ids, columns,
        weights; a frame votes at most once per point).

        Only points whose vote from this frame changes are read and written: a per-point code
        (column + 1, weight) of the frame's old and new vote is compared, the counts of the
        differing points are gathered once, updated in memory (at most one old and one new vote
        per point: plain fancy indexing, no ``ufunc.at``) and written back. Their winner before
        is one packed-key argmax (:meth:`ClassColumns.packed_winner`); after, it is recounted
        only where the winner lost a vote, elsewhere the gaining column either beats it or not.
        Counts and statistics are those of the full recount (tests/test_lifting.py)."""
        n = self.scene.n_points
        code_old = self._vote_codes(n, old)
        code_new = self._vote_codes(n, new)
        # only the frame's points can differ: look there, not at all n (a 20 MP frame sees
        # ~2.5 M of the survey's 32 M points)
        po, pn = np.asarray(old[0], np.int64), np.asarray(new[0], np.int64)
        o_at_n, n_at_n = code_old[pn] != 0, code_new[pn] != 0
        points_touched = int(np.count_nonzero(code_old[po]) + np.count_nonzero(n_at_n)
                             - np.count_nonzero(o_at_n & n_at_n))
        d_old = po[code_old[po] != code_new[po]]
        d_new = pn[code_old[pn] != code_new[pn]]
        if len(d_old) and len(d_new):
            seen = np.zeros(n, bool)  # lazily zeroed pages: only the frame's are touched
            seen[d_old] = True
            d_new = d_new[~seen[d_new]]
        # point ids ascending (two sorted runs: the stable sort merges them in linear time)
        diff = np.sort(np.concatenate([d_old, d_new]), kind="stable")
        changed = 0
        if len(diff):
            rows = np.asarray(self.votes[diff])  # (T, C) copy of the affected counts
            co, cn = code_old[diff], code_new[diff]
            grow = max(1, int(cn.max() & 0xFF)) if len(cn) else 1
            dt = self._cls.key_dtype(int(rows.max()) + grow)
            if dt is None:  # counts beyond any packed key: plain recount of the winner
                before = self._cls.winner(rows)
                self._add_codes(rows, co, cn)
                after = self._cls.winner(rows)
            else:
                before, bkey = self._cls.packed_winner(rows, dt)
                self._add_codes(rows, co, cn)
                # the winner changes only if its own count fell (recount those rows) or the
                # column that gained beats it; a column that lost a vote cannot overtake it
                after = before.copy()
                ocol = (co >> 8).astype(np.int64) - 1
                ncol = (cn >> 8).astype(np.int64) - 1
                fell = (co > 0) & (ocol == before)
                gain = np.flatnonzero((cn > 0) & ~fell)
                if len(gain):
                    g = ncol[gain]
                    k = self._cls.pack(rows[gain, g], g, dt)
                    win = k > bkey[gain]
                    after[gain[win]] = g[win]
                f = np.flatnonzero(fell)
                if len(f):
                    after[f] = self._cls.packed_winner(rows[f], dt)[0]
            self.votes[diff] = rows
            self._touched(diff)
            changed = int(np.count_nonzero(before != after))
        return {
            "points_touched": points_touched,
            "points_changed": changed,
            "votes_removed": int(old[2].sum(dtype=np.int64)),
            "votes_added": int(new[2].sum(dtype=np.int64)),
        }

    @staticmethod
    def _add_codes(rows: np.ndarray, code_old: np.ndarray, code_new: np.ndarray) -> None:
        """Subtract the old and add the new vote of each row (codes of :meth:`_vote_codes`)."""
        for code, sign in ((code_old, -1), (code_new, 1)):
            r = np.flatnonzero(code)
            c = code[r]
            col = (c >> 8).astype(np.int64) - 1
            w = (c & 0xFF).astype(rows.dtype)
            if sign < 0:
                rows[r, col] -= w
            else:
                rows[r, col] += w

    def _vote_codes(self, n: int, votes: tuple[np.ndarray, ...]) -> np.ndarray:
        """(n,) uint16 code of one frame's vote per point: 0 none, else (column + 1) << 8 |
        weight (a weight of 0 counts nothing: it is no vote)."""
        code = np.zeros(n, np.uint16)
        pids, cols, w = votes
        if len(pids):
            code[pids] = ((cols.astype(np.uint16) + 1) << 8) | w.astype(np.uint16)
            code[pids[w == 0]] = 0
        return code

    def apply_frame(self, frame_index: int, mask: np.ndarray | None, *,
                    version: str | None = None, name: str | None = None,
                    votes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> dict:
        """Replace frame ``frame_index``'s votes with those of ``mask`` ((h, w) uint8 raw ids).

        Validates the mask first (MaskError naming ``name``; the state is then unchanged).
        ``votes``: the mask's :meth:`frame_votes`, computed beforehand (a worker decodes and
        projects several masks in parallel threads -- :meth:`frame_votes` only reads the
        scene -- then applies them here one at a time, in order); ``mask`` is then unused.
        Returns {points_touched, points_changed (direct label changed), votes_removed,
        votes_added, seconds}.
        """
        self._writable()
        t0 = time.perf_counter()
        name = name or f"mask of frame {frame_index}"
        if votes is None:
            votes = self.frame_votes(frame_index, mask, name=name)
        else:
            self._check_frame(frame_index, name)
        pids, cols, weights = votes
        fi = int(frame_index)
        old = self._old_votes(fi)
        self._write_state(dirty=True)
        arrays = {"point_ids": pids, "cols": cols}
        if vote_unit(self.vote_weighting) != 1:
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

    def reliability_snapshot(self, labels: np.ndarray, params=None  # noqa: ANN001
                             ) -> tuple[VoteSnapshot | None, dict]:
        """The votes without those of frames that paint a class far worse than the others
        (:mod:`occufly.lifting.reliability`; judged against ``labels``, a first lifting, or
        with ``labels=None`` against the other frames' votes), as a snapshot; None when
        nothing is vetoed. Stats: the vetoed (frame, class) pairs."""
        frames = {fi: got for fi in self._versions if (got := self._frame_file(fi)) is not None}
        pairs = {f: v[:2] for f, v in frames.items()}
        if labels is not None:
            votes, agree = frame_class_agreement(pairs, labels, self._cls)
        elif vote_unit(self.vote_weighting) == 1:
            votes, agree = frame_class_agreement_loo(pairs, self.votes, self._cls)
        else:  # weighted counts are not one vote per view
            return None, {"reliability_vetoed": {}, "reliability_skipped": "weighted votes"}
        veto = vetoes(votes, agree, params)
        names = {c.id: c.name for c in self.scene.taxonomy.classes}
        stats = {"reliability_vetoed": {
            str(f): [names[int(self._cls.ids[c])] for c in np.flatnonzero(b)]
            for f, b in sorted(veto.items())}}
        if not veto:
            return None, stats
        counts = vetoed_counts(self.votes, frames, veto)
        stats["reliability_votes_removed"] = int(np.asarray(self.votes).sum(dtype=np.int64)
                                                 - counts.sum(dtype=np.int64))
        return self.snapshot(counts=counts), stats

    # -- fill and denoise
    def fill_and_denoise(self, progress: ProgressFn | None = None,
                         params: LiftParams | None = None, *,
                         snapshot: VoteSnapshot | None = None, write: bool = True,
                         incremental=None, annotators: dict | None = None
                         ) -> LiftResult:  # noqa: ANN001
        """kNN fill + denoise of the votes; writes labels/confidence/origin (``write=False``:
        only returns them).

        Without ``snapshot`` the current counts are read first (hold the update lock for the
        whole call then); with one taken by :meth:`snapshot`, nothing here reads the shared
        counts, so updates may go on meanwhile. ``incremental``: an
        :class:`occufly.lifting.incremental.IncrementalFill` of this scene (a live worker keeps
        one per scene): the k-NN passes rerun only around the points whose decided label
        changed since its last fill (same result). ``annotators``: frame -> who painted it,
        for the confusion model (``RobustParams.confusion``; default: each frame its own).
        """
        report = progress or noop
        if write:
            self._writable()
        rstats: dict = {}
        if snapshot is None:
            report(0.0, "majority vote")
            snapshot = self.snapshot()
            if getattr(params, "reliability", False):
                # issue 37: a frame's votes for a class it paints far worse than the other
                # frames that see the same points are left out
                vetoed, rstats = self.reliability_snapshot(None)
                snapshot = vetoed or snapshot
            rp = getattr(params, "robust_params", None)
            if (getattr(rp, "confusion", None) is not None
                    or getattr(rp, "regions", None) is not None):  # the votes as counted now
                snapshot.frame_votes = {fi: got for fi in self._versions
                                        if (got := self._frame_file(fi)) is not None}
        if annotators is not None:
            snapshot.annotators = dict(annotators)
        result = fill_snapshot(self.scene, snapshot, params=params, ws=self.ws,
                               read_only=self.read_only or not write,
                               progress=lambda f, m: report(0.05 + 0.9 * f, m),
                               incremental=incremental)
        result.stats.update(rstats)
        if write:
            report(0.96, "writing labels")
            save_result(self.ws, result)
        report(1.0, "done")
        return result


# the compiled majority pass of VoteStore._direct (False: the numpy passes it replaced; tests
# compare the two)
COMPILED_DIRECT = True


def direct_compiles(counts, cls: ClassColumns) -> bool:  # noqa: ANN001
    """Whether :func:`_direct_rows` takes ``counts``: an (n, C) unsigned integer array of at
    most 32 bits (a packed key of count and tie rank then fits in 64 bits)."""
    return (isinstance(counts, np.ndarray) and counts.ndim == 2 and counts.shape[1] == cls.C
            and np.issubdtype(counts.dtype, np.unsignedinteger) and counts.dtype.itemsize <= 4
            and cls.C >= 1 and int(cls._bits) <= 31)


@numba.njit(nogil=True, cache=True)
def _direct_rows(c: np.ndarray, tie: np.ndarray, bits: int, ids: np.ndarray,
                 labels: np.ndarray, margin: np.ndarray, top_out: np.ndarray,
                 col2: np.ndarray, votes2: np.ndarray) -> None:
    """Per row of the (n, C) counts ``c``, what :meth:`VoteStore._direct` computes with numpy
    (:meth:`ClassColumns.packed_winner`, the winner of the rest): the column with the
    largest key ``count << bits | tie[j]`` (the taxonomy's tie order among equal counts; -1
    where every count is 0) as a raw id in ``labels``, its count in ``top_out``, the next
    largest key's column (-1 where it has no vote) in ``col2`` and its count in ``votes2``,
    and ``(top - second) / total`` in float64 stored as float32 in ``margin`` (0 without
    votes)."""
    n, C = c.shape
    for i in range(n):
        k1 = np.int64(-1)
        k2 = np.int64(-1)
        b1 = -1
        b2 = -1
        total = np.int64(0)
        for j in range(C):
            v = np.int64(c[i, j])
            total += v
            key = (v << bits) | tie[j]
            if key > k1:
                k2, b2 = k1, b1
                k1, b1 = key, j
            elif key > k2:
                k2, b2 = key, j
        top = k1 >> bits
        if top > 0:
            labels[i] = ids[b1]
            top_out[i] = top
        else:
            labels[i] = 0
            top_out[i] = 0
            top = 0
        second = k2 >> bits if b2 >= 0 else np.int64(0)
        if top > 0 and second > 0:
            col2[i] = b2
            votes2[i] = second
        else:
            col2[i] = -1
            votes2[i] = 0
            second = 0
        if total > 0:
            margin[i] = np.float32((np.float64(top) - np.float64(second)) / np.float64(total))
        else:
            margin[i] = np.float32(0.0)


@dataclass
class VoteSnapshot:
    """The vote majority of a :class:`VoteStore` at one moment.

    direct: (N,) uint8 raw ids (0 = no votes); margin: (N,) float32 ``(top - second) /
    votes``; top: (N,) uint16 votes of the winning class; versions: frame index -> version
    tag of the masks counted; second_col: (N,) int8 column of the second class (-1 = none)
    and second: (N,) uint16 its votes (None in snapshots made without them: then the robust
    decision is skipped).
    """

    direct: np.ndarray
    margin: np.ndarray
    top: np.ndarray
    versions: dict[int, str | None]
    second_col: np.ndarray | None = None
    second: np.ndarray | None = None
    vote_unit: int = 1  # counts per view (VOTE_UNITS; top is already in views)
    # issue 37, the confusion model (RobustParams.confusion): every frame's votes (frame ->
    # point ids, columns, weights; None = read from the workspace's frame files) and who
    # painted each frame (frame -> annotator id; None or a frame missing: its own annotator)
    frame_votes: dict | None = None
    annotators: dict | None = None

    @property
    def annotated_frames(self) -> int:
        return len(self.versions)


def read_direct_labels(ws: str | Path) -> np.ndarray | None:
    """(N,) uint8 majority of the direct votes of workspace ``ws`` (0 = no vote), or None
    without a vote state. Opened read-only: a reader never writes, so a state left dirty by an
    interrupted update is a :class:`WorkspaceError` here (the lifting worker repairs it)."""
    if not Workspace(ws).lifting_state.is_file():
        return None
    return VoteStore.open(ws, read_only=True).direct_labels()


def fill_snapshot(scene: Scene, snapshot: VoteSnapshot, *, params: LiftParams | None = None,
                  progress: ProgressFn | None = None, ws: str | Path | None = None,
                  read_only: bool = True, incremental=None) -> LiftResult:  # noqa: ANN001
    """Robust decision (``params.robust``, :mod:`occufly.lifting.robust`) then kNN fill +
    denoise of a :class:`VoteSnapshot` (does not write anything but, with ``ws`` and not
    ``read_only``, the feature cache ``ws/lifting/features.npy``).

    After a robust decision the fill's confirmation rule counts ``RobustParams.confirm_views``
    (default 1) instead of ``LiftParams.confirm_views``: its margin is a posterior margin, and
    a tiny object seen by two or three views rarely has two votes for itself."""

    t_start = time.perf_counter()
    p = params or LiftParams()
    report = progress or noop
    direct, margin, top = snapshot.direct, snapshot.margin, snapshot.top
    robust_stats: dict = {}
    fill_progress = progress
    if getattr(p, "robust", False) and snapshot.second_col is not None:
        from dataclasses import replace

        from occufly.lifting.robust import RobustParams, cached_features, redecide

        t0 = time.perf_counter()
        report(0.0, "robust decision: point features")
        feats = cached_features(ws, scene.xyz, scene.rgb, read_only=read_only)
        t_feat = time.perf_counter() - t0
        cls = ClassColumns(scene.taxonomy)
        col1 = cls.col_of[snapshot.direct]  # int16, -1 = no votes
        top1 = np.where(col1 >= 0, snapshot.top, np.uint16(0))
        second = snapshot.second
        if snapshot.vote_unit != 1:  # weighted votes: the model counts views
            second = second.astype(np.float32) / snapshot.vote_unit
        rp = getattr(p, "robust_params", None) or RobustParams()
        # a live scene's fill keeps the pooled model between saves (robust.HeldDecision); the
        # per-painter and region decisions read every frame's votes and are fitted each time
        held = getattr(incremental, "held", None)
        if held is not None and (getattr(rp, "confusion", None) is not None
                                 or getattr(rp, "regions", None) is not None):
            held.clear()
            held = None
        direct, margin, top, robust_stats = redecide(
            cls, feats, col1, top1, snapshot.second_col, second,
            rp, progress=lambda f, m: report(0.3 * f, m), xyz=scene.xyz, held=held)
        if getattr(rp, "confusion", None) is not None:
            direct, margin, top, robust_stats = _confusion_decision(
                scene, snapshot, ws, cls, feats, col1, top1, second, rp,
                (direct, margin, top, robust_stats), lambda f, m: report(0.3 * f, m))
        elif getattr(rp, "regions", None) is not None:
            direct, margin, top, robust_stats = _region_decision(
                scene, snapshot, ws, cls, feats, (col1, top1, second), rp,
                (direct, margin, top, robust_stats), lambda f, m: report(0.3 * f, m))
        if "robust_matrix" in robust_stats:  # the matrix decided with, for the review's LOO
            robust_stats["robust_matrix"] = {"class_ids": [int(i) for i in cls.ids],
                                             "pi": robust_stats["robust_matrix"]}
        if rp.confirm_views is not None and p.confirm_views is not None:
            # the robust margin is a posterior margin, not a vote share: it confirms alone
            p = replace(p, confirm_views=rp.confirm_views)
        robust_stats["robust_features_seconds"] = round(t_feat, 3)
        fill_progress = lambda f, m: report(0.3 + 0.7 * f, m)  # noqa: E731
    if incremental is not None:  # same result, k-NN only where the decided labels changed
        result = incremental.fill(direct, params=p, vote_margin=margin, vote_top=top,
                                  progress=fill_progress)
    else:
        # looked up on the module at call time: a test (or a profiler) patching
        # ``occufly.lifting.knn.fill_and_denoise`` sees every fill, whichever entry point ran it
        result = knn.fill_and_denoise(
            np.asarray(scene.xyz), direct, scene.taxonomy, params=p,
            vote_margin=margin, vote_top=top, progress=fill_progress)
    result.stats.update(robust_stats)
    result.stats["robust"] = bool(robust_stats)
    # how the votes were decided, and by how many painters (the app's admin console)
    rp_used = getattr(p, "robust_params", None) if robust_stats else None
    result.stats["decision"] = ("majority" if not robust_stats
                                else "confusion" if getattr(rp_used, "confusion", None) is not None
                                else "regions" if getattr(rp_used, "regions", None) is not None
                                else "robust")
    if snapshot.annotators is not None:
        named = {f: a for f, a in snapshot.annotators.items() if f in snapshot.versions}
        result.stats["painters"] = {
            "authors": len(set(named.values())),
            "frames_with_author": len(named),
            "frames_own": int(snapshot.annotated_frames) - len(named)}
    result.stats["annotated_frames"] = snapshot.annotated_frames
    # the whole decision and fill (``seconds`` is the k-NN fill's own)
    result.stats["total_seconds"] = round(time.perf_counter() - t_start, 3)
    result.stats["versions"] = {str(k): v for k, v in sorted(snapshot.versions.items())}
    return result


# peak bytes per vote of the per-frame models' vote table (confusion.vote_table, regions._table:
# point id, column, annotator, weight, the sort by point) beyond the frames' votes themselves
VOTE_TABLE_BYTES = 24


def _model_frames(scene: Scene, snapshot: VoteSnapshot, ws, what: str  # noqa: ANN001
                  ) -> tuple[dict | None, str | None]:
    """Every frame's votes for a decision that reads them (the per-painter model, region
    consistency): the snapshot's, else the workspace's files; (frames, None), or (None, why
    not) -- no per-frame votes, or a vote table that does not fit in the memory available now
    (the decision then keeps the first one and the fill goes on: a survey's worker is not
    brought down by a model an admin chose)."""
    frames = snapshot.frame_votes
    if frames is None and ws is not None:
        from occufly.lifting.confusion import load_frame_votes

        frames = load_frame_votes(ws, sorted(snapshot.versions))
    if not frames:
        return None, "no per-frame votes"
    votes = sum(len(v[0]) for v in frames.values())
    try:
        require_memory(VOTE_TABLE_BYTES * votes + 8 * (int(scene.n_points) + 1), what,
                       detail=f" ({votes:,} votes)", count_own=False)
    except OccuflyError as e:
        return None, f"{e}; decided with one model for all painters"
    return frames, None


def _confusion_decision(scene: Scene, snapshot: VoteSnapshot, ws, cls: ClassColumns,  # noqa: ANN001
                        feats: np.ndarray, col1: np.ndarray, top1: np.ndarray, second: np.ndarray,
                        rp, first: tuple, report: ProgressFn  # noqa: ANN001
                        ) -> tuple:
    """The robust decision again, with the votes' likelihood from a per-annotator confusion
    model (:mod:`occufly.lifting.confusion`) fitted from every frame's votes and initialised
    from the first decision's labels (``first``: its (labels, margin, top, stats)). Without the frames' votes (a snapshot made
    without them and no workspace): the first decision, with a stat saying so."""
    from occufly.lifting.confusion import fit_confusion, model_record, vote_table
    from occufly.lifting.robust import redecide

    t0, c0 = time.perf_counter(), time.process_time()
    frames, why_not = _model_frames(scene, snapshot, ws, "the per-painter model")
    if frames is None:
        first[3]["confusion_skipped"] = why_not
        return first
    table = vote_table(frames, scene.n_points, snapshot.annotators, snapshot.vote_unit)
    init = np.where(first[0] > 0, cls.col_of[first[0]], -1)
    model = fit_confusion(table, cls.C, init, rp.confusion)
    t_fit, c_fit = time.perf_counter() - t0, time.process_time() - c0
    direct, margin, top, stats = redecide(cls, feats, col1, top1, snapshot.second_col, second,
                                          rp, progress=report, xyz=scene.xyz, confusion=model)
    stats.update(model.stats)
    # the per-painter matrices, for the review's leave-one-out decision (occufly.lifting.loo)
    stats["confusion_model"] = model_record(model, frames, snapshot.annotators, cls.ids)
    stats["confusion_fit_seconds"] = round(t_fit, 3)
    stats["confusion_fit_cpu_seconds"] = round(c_fit, 3)
    stats["confusion_first_robust_seconds"] = first[3].get("robust_seconds")
    stats["confusion_changed_points"] = int(np.count_nonzero(direct != first[0]))
    return direct, margin, top, stats


def _region_decision(scene: Scene, snapshot: VoteSnapshot, ws, cls: ClassColumns,  # noqa: ANN001
                     feats: np.ndarray, votes: tuple, rp, first: tuple,  # noqa: ANN001
                     report: ProgressFn) -> tuple:
    """Issue 37, sixth round (``RobustParams.regions``): the frames' painted regions that the
    other views contradict as a whole counted as they say (:func:`occufly.lifting.regions.
    region_votes`), and every voted point decided again with the first decision's matrix
    (``first``: its (labels, margin, top, stats)). The first decision where no region is
    contradicted, where the votes are weighted, or without the frames' votes."""
    from occufly.lifting.regions import region_votes
    from occufly.lifting.robust import redecide

    stats = first[3]
    if snapshot.vote_unit != 1 or "robust_matrix" not in stats:
        stats["regions_skipped"] = "weighted votes" if snapshot.vote_unit != 1 else "no matrix"
        return first
    t0, c0 = time.perf_counter(), time.process_time()
    frames, why_not = _model_frames(scene, snapshot, ws, "region consistency")
    if frames is None:
        stats["regions_skipped"] = why_not
        return first
    pi = np.asarray(stats["robust_matrix"], np.float64)
    got = region_votes(scene, frames, pi, annotators=snapshot.annotators, params=rp.regions)
    if got is None:
        stats.update(regions=0, regions_seconds=round(time.perf_counter() - t0, 3))
        return first
    pts, counts, rstats = got
    col1, top1, second = (np.array(a, copy=True) for a in votes)
    col2 = np.array(snapshot.second_col, copy=True)
    c = counts.astype(np.uint32)
    w = cls.winner(c)
    idx = np.arange(len(pts))
    col1[pts] = w
    top1[pts] = np.where(w >= 0, c[idx, np.maximum(w, 0)], 0)
    c[idx, np.maximum(w, 0)] = 0
    w2 = cls.winner(c)
    col2[pts] = w2
    second[pts] = np.where(w2 >= 0, c[idx, np.maximum(w2, 0)], 0)
    t_find, c_find = time.perf_counter() - t0, time.process_time() - c0
    fixed = pi if getattr(rp.regions, "matrix", "first") == "first" else None
    direct, margin, top, out = redecide(cls, feats, col1, top1, col2, second, rp,
                                        progress=report, xyz=scene.xyz, confusion_matrix=fixed)
    names = {c.id: c.name for c in scene.taxonomy.classes}
    for r in rstats["regions"]:  # raw class ids, as the labels are, and names for people
        r["from"], r["to"] = int(cls.ids[r["from"]]), int(cls.ids[r["to"]])
        r["frame_name"] = scene.frames[r["frame"]].name
        r["painted"], r["counted_as"] = names.get(r["from"]), names.get(r["to"])
    out.update(regions=len(rstats["regions"]), region_votes_changed=rstats["votes_changed"],
               region_list=rstats["regions"][:50], regions_seconds=round(t_find, 3),
               regions_cpu_seconds=round(c_find, 3),
               regions_first_robust_seconds=stats.get("robust_seconds"),
               regions_changed_points=int(np.count_nonzero(direct != first[0])))
    return direct, margin, top, out


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()
