"""Frame selection: stratified ground cells (the method) and a coverage-greedy extension.

Stratified (paper 3.3.2): the ground plane (scene-local x, y; z is up) is cut into square cells
of edge ``cell`` metres (default 25 m; the method uses 23-28 m) anchored at the minimum corner
of the point cloud. Only cells that contain points count. For each cell the frame whose camera
centre is closest (in x, y) to the cell centre is selected; for a *border* cell (one whose
4-neighbour lies outside the grid or holds no points) the target moves from the centre to the
middle of the cell's outer edge(s), i.e. onto the scene border, and the frame closest to that
point is selected. Frames may be restricted to one nominal flight altitude.

Coverage rho(J) is the share of all scene points seen by at least one selected frame (through
the scene's visibility). Greedy mode starts from the stratified set and adds, one at a time,
the frame that sees the most not-yet-covered points until rho reaches ``target_coverage`` (or
no frame adds anything). Gains only shrink as coverage grows, so a lazy max-heap re-evaluates
only the top candidate: each step costs about one frame's points, not the scene's.
Afterwards (``prune_redundant``, default on) frames are dropped, least unique contribution
first, while rho stays at the target: stratified frames that later additions made redundant
go. Mode "cover" runs the same greedy from an empty set (no stratified seed).

``cell="auto"`` (greedy modes only) runs the selection for every cell edge of the method's
range (23-28 m in 0.5 m steps) and keeps the result with the fewest frames that reaches the
target coverage (ties: the higher coverage, then the edge closest to 25 m); the stratified
seed depends on the cell lattice, so the best edge differs between scenes.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

import numpy as np

from occufly.errors import InputFormatError
from occufly.scene import Scene

METHOD_CELL_RANGE = (23.0, 28.0)


@dataclass
class SelectionResult:
    """Selected frames and their coverage.

    frames: selected frame indices (stratified ones first, then greedy additions in order);
    ratio: |J| / number of candidate frames; coverage: rho(J) over all scene points;
    curve: (number of frames, coverage) after the stratified set and after each addition.
    """

    frames: list[int]
    ratio: float
    coverage: float
    curve: list[tuple[int, float]]
    mode: str = "stratified"
    cell: float = 25.0
    altitude: int | None = None
    n_candidates: int = 0
    n_points: int = 0
    max_coverage: float = 0.0
    stratified_frames: list[int] = field(default_factory=list)
    cells: int = 0
    auto_cells: list = field(default_factory=list)  # cell="auto": (edge, frames, coverage) tried
    cell_origin: list | None = None  # (x, y) scene-local min corner of cell (0, 0)
    occupied_cells: list = field(default_factory=list)  # [[i, j], ...] cells holding points
    frame_names: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {
            "mode": self.mode,
            "cell": self.cell,
            "cell_in_method_range": METHOD_CELL_RANGE[0] <= self.cell <= METHOD_CELL_RANGE[1],
            "altitude": self.altitude,
            "frames": list(self.frames),
            "frame_names": list(self.frame_names),
            "selected": len(self.frames),
            "candidates": self.n_candidates,
            "ratio": self.ratio,
            "coverage": self.coverage,
            "max_coverage": self.max_coverage,
            "points": self.n_points,
            "cells": self.cells,
            "cell_origin": self.cell_origin,
            "occupied_cells": [list(c) for c in self.occupied_cells],
            "stratified_frames": list(self.stratified_frames),
            "curve": [[int(n), float(c)] for n, c in self.curve],
            **({"auto_cells": [[c, n, cov] for c, n, cov in self.auto_cells]} if self.auto_cells else {}),
        }


def candidate_frames(scene: Scene, altitude: int | None) -> np.ndarray:
    """(K,) int frame indices usable for selection (all, or those at one nominal altitude)."""
    if altitude is None:
        return np.arange(len(scene.frames))
    idx = [i for i, f in enumerate(scene.frames) if f.nominal_altitude == int(altitude)]
    if not idx:
        have = sorted({f.nominal_altitude for f in scene.frames if f.nominal_altitude is not None})
        raise InputFormatError(
            f"altitude: no frame flies at nominal altitude {altitude} m; the scene has "
            f"{have or 'no assigned altitudes'}"
        )
    return np.asarray(idx)


def coverage_mask(scene: Scene, frames: list[int] | np.ndarray) -> np.ndarray:
    """(N,) bool: points seen by at least one of ``frames``."""
    seen = np.zeros(scene.n_points, dtype=bool)
    vis = scene.visibility
    for f in frames:
        a, b = int(vis.offsets[f]), int(vis.offsets[f + 1])
        seen[vis.point_ids[a:b]] = True
    return seen


def coverage(scene: Scene, frames: list[int] | np.ndarray) -> float:
    """rho(J): share of all scene points seen by at least one frame of ``frames``."""
    if scene.n_points == 0:
        return 0.0
    return float(coverage_mask(scene, frames).sum()) / scene.n_points


def stratified(scene: Scene, candidates: np.ndarray, cell: float, *, max_points: int = 2_000_000,
               geometry: dict | None = None
               ) -> tuple[list[int], int]:
    """Stratified selection over ``candidates``; returns (frames, number of occupied cells).

    With ``geometry`` (a dict), the cell lattice is written into it: ``cell_origin`` (x, y)
    scene-local metres of cell (0, 0)'s min corner and ``occupied_cells`` [[i, j], ...].
    """
    if cell <= 0:
        raise InputFormatError(f"cell: the cell edge must be positive, got {cell}")
    if len(candidates) == 0 or scene.n_points == 0:
        return [], 0
    step = max(1, scene.n_points // max_points)
    xy = np.asarray(scene.xyz[::step, :2], dtype=np.float64)
    lo = xy.min(axis=0)
    hi = xy.max(axis=0)
    nx, ny = (np.maximum(np.ceil((hi - lo) / cell), 1)).astype(int)
    ij = np.minimum(((xy - lo) / cell).astype(int), [nx - 1, ny - 1])
    occ = np.bincount(ij[:, 0] * ny + ij[:, 1], minlength=nx * ny).reshape(nx, ny) > 0
    # a border cell has a 4-neighbour outside the grid or without points
    pad = np.zeros((nx + 2, ny + 2), bool)
    pad[1:-1, 1:-1] = occ
    out_w, out_e = ~pad[:-2, 1:-1], ~pad[2:, 1:-1]
    out_s, out_n = ~pad[1:-1, :-2], ~pad[1:-1, 2:]
    ci, cj = np.nonzero(occ)
    if geometry is not None:
        geometry["cell_origin"] = [float(lo[0]), float(lo[1])]
        geometry["occupied_cells"] = np.column_stack([ci, cj]).tolist()
    centre = lo + (np.column_stack([ci, cj]) + 0.5) * cell
    shift = np.zeros_like(centre)
    shift[:, 0] = (out_e[ci, cj].astype(float) - out_w[ci, cj]) * cell / 2
    shift[:, 1] = (out_n[ci, cj].astype(float) - out_s[ci, cj]) * cell / 2
    target = centre + shift
    # clamp onto the cloud's extent: the scene border for cells that stick out of it
    target = np.clip(target, lo, hi)
    cam_xy = scene.centers()[candidates, :2]
    d2 = ((target[:, None, :] - cam_xy[None, :, :]) ** 2).sum(axis=2)
    best = candidates[np.argmin(d2, axis=1)]
    seen: dict[int, None] = {}
    for f in best.tolist():
        seen.setdefault(int(f), None)
    return list(seen), int(len(ci))


def greedy(scene: Scene, candidates: np.ndarray, start: list[int], target: float
           ) -> tuple[list[int], list[tuple[int, float]]]:
    """Add frames by largest coverage gain until ``target`` coverage; returns (added, curve)."""
    n = scene.n_points
    vis = scene.visibility
    covered = coverage_mask(scene, start)
    n_cov = int(covered.sum())
    curve = [(len(start), n_cov / n if n else 0.0)]
    if n == 0:
        return [], curve
    chosen = set(start)
    cand = np.array([c for c in candidates if int(c) not in chosen], dtype=np.int64)
    if not len(cand) or n_cov / n >= target:
        return [], curve
    gains = _uncovered_per_frame(vis, covered, len(scene.frames))
    heap = [(-float(gains[c]), int(c)) for c in cand if gains[c] > 0]
    heapq.heapify(heap)
    added: list[int] = []
    while heap and n_cov / n < target:
        neg, f = heapq.heappop(heap)
        pids = vis.point_ids[int(vis.offsets[f]):int(vis.offsets[f + 1])]
        g = int(np.count_nonzero(~covered[pids]))
        if g == 0:
            continue
        if heap and g < -heap[0][0]:
            heapq.heappush(heap, (-float(g), f))  # stale: re-insert with its true gain
            continue
        covered[pids] = True
        n_cov += g
        added.append(f)
        curve.append((len(start) + len(added), n_cov / n))
    return added, curve


def _uncovered_per_frame(vis, covered: np.ndarray, n_frames: int,  # noqa: ANN001
                         block: int = 1 << 24) -> np.ndarray:
    """(F,) float64 number of points each frame sees that ``covered`` does not mark, in blocks
    of whole frames of about ``block`` correspondences (one bincount over all of them needed
    float64 weights + frame ids for every correspondence: ~5 GB on bench's 266 M)."""
    off = np.asarray(vis.offsets, dtype=np.int64)
    gains = np.zeros(n_frames, dtype=np.float64)
    f0 = 0
    while f0 < n_frames:
        f1 = int(np.searchsorted(off, off[f0] + block, side="right")) - 1
        f1 = min(n_frames, max(f1, f0 + 1))
        a, b = int(off[f0]), int(off[f1])
        unc = ~covered[np.asarray(vis.point_ids[a:b])]
        cs = np.zeros(b - a + 1, dtype=np.int64)
        np.cumsum(unc, out=cs[1:])
        gains[f0:f1] = cs[off[f0 + 1:f1 + 1] - a] - cs[off[f0:f1] - a]
        f0 = f1
    return gains


def prune(scene: Scene, frames: list[int], target: float) -> list[int]:
    """Drop frames whose points are all seen by the others while coverage stays >= target.

    Repeatedly removes the frame that sees the fewest points no other selected frame sees, as
    long as the coverage without it still reaches ``target``. Order of the rest is kept.
    """
    n = scene.n_points
    if n == 0 or len(frames) < 2:
        return list(frames)
    vis = scene.visibility
    ids = {f: np.asarray(vis.point_ids[int(vis.offsets[f]):int(vis.offsets[f + 1])]) for f in frames}
    count = np.zeros(n, dtype=np.int32)
    for f in frames:
        count[ids[f]] += 1
    covered = int((count > 0).sum())
    keep = list(frames)
    while len(keep) > 1:
        unique = np.array([int(np.count_nonzero(count[ids[f]] == 1)) for f in keep])
        i = int(np.argmin(unique))
        if (covered - unique[i]) / n < target:
            break
        f = keep.pop(i)
        count[ids[f]] -= 1
        covered -= int(unique[i])
    return keep


AUTO_CELLS = tuple(float(c) for c in np.arange(METHOD_CELL_RANGE[0], METHOD_CELL_RANGE[1] + 0.25, 0.5))


def select_frames(scene: Scene, *, cell: float | str = 25.0, mode: str = "stratified",
                  target_coverage: float = 0.99, altitude: int | None = None,
                  prune_redundant: bool = True) -> SelectionResult:
    """Select frames to annotate (see the module docstring). Returns a :class:`SelectionResult`.

    mode: "stratified" (the method), "greedy" (stratified + coverage-greedy additions), or
    "cover" (coverage-greedy from an empty set). In the greedy modes, ``prune_redundant`` then
    drops frames (stratified ones included) that the target coverage does not need.
    cell: edge in metres, or "auto" (greedy modes) to search the method's range.
    """
    if mode not in ("stratified", "greedy", "cover"):
        raise InputFormatError(
            f"mode: expected 'stratified', 'greedy' or 'cover', got {mode!r}")
    if not 0.0 < target_coverage <= 1.0:
        raise InputFormatError(f"target coverage must be in (0, 1], got {target_coverage}")
    if isinstance(cell, str):
        if cell != "auto":
            raise InputFormatError(f"cell: expected a number of metres or 'auto', got {cell!r}")
        if mode == "stratified":
            raise InputFormatError("cell 'auto' needs a target coverage: use mode 'greedy' or 'cover'")
        results = [select_frames(scene, cell=c, mode=mode, target_coverage=target_coverage,
                                 altitude=altitude, prune_redundant=prune_redundant) for c in AUTO_CELLS]
        best = min(results, key=lambda r: (r.coverage < target_coverage, len(r.frames), -r.coverage,
                                           abs(r.cell - 25.0)))
        best.auto_cells = [(r.cell, len(r.frames), round(r.coverage, 5)) for r in results]
        return best
    cand = candidate_frames(scene, altitude)
    geometry: dict = {}
    frames, cells = stratified(scene, cand, float(cell), geometry=geometry)
    strat = list(frames)
    if mode in ("greedy", "cover"):
        start = frames if mode == "greedy" else []
        added, curve = greedy(scene, cand, start, target_coverage)
        frames = start + added
        cov = curve[-1][1]
        if prune_redundant and cov >= target_coverage:
            pruned = prune(scene, frames, target_coverage)
            if len(pruned) < len(frames):
                frames = pruned
                cov = coverage(scene, frames)
                curve = curve + [(len(frames), cov)]
    else:
        cov = coverage(scene, frames)
        curve = [(len(frames), cov)]
    max_cov = coverage(scene, cand)
    return SelectionResult(
        frames=[int(f) for f in frames],
        ratio=len(frames) / len(cand) if len(cand) else 0.0,
        coverage=float(cov),
        curve=[(int(a), float(b)) for a, b in curve],
        mode=mode,
        cell=float(cell),
        altitude=None if altitude is None else int(altitude),
        n_candidates=int(len(cand)),
        n_points=scene.n_points,
        max_coverage=max_cov,
        stratified_frames=strat,
        cells=cells,
        cell_origin=geometry.get("cell_origin"),
        occupied_cells=geometry.get("occupied_cells", []),
        frame_names=[scene.frames[f].name for f in frames],
    )
