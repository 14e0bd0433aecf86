"""Level of detail for survey-sized point clouds: a coarse level first, then region tiles.

One point cloud node per class of 2 M points reached the browser in 2.4 s, but software WebGL
(SwiftShader) needed ~18 s before it drew anything: the browser decoded and uploaded every
class's whole buffer before the first frame, and each later frame drew all of it. The viewer
now sends the points it shows (the stratified LOD subsample of ``max_points``) as

- a **coarse level**: ``coarse_points`` of them (per-class stratified again, so a rare class is
  on screen from the start), one node per class ``/points/<class>/coarse`` -- the first picture;
- **refinement tiles**: the rest, split by a ``tiles`` x ``tiles`` grid over the scene's
  footprint, one node per (class, tile) ``/points/<class>/detail/t<k>``, sent from the
  middle of the view outwards in a few batches (:func:`batches`), each once the browser has
  drawn the one before (every batch that arrives costs software WebGL a frame of everything
  shown, so tile-by-tile sending drew 16 growing frames and was slower than one bulk send).

``/points/<class>`` is a frame (no axes) holding its class's nodes: a class toggle is one
visibility flag. ``/points/<class>/detail`` holds the tiles: while the camera moves the
viewer hides these frames (the coarse level alone is drawn, fast enough to orbit under
software WebGL) and shows them again once the camera rests (``motion_rest_s``). The plan (which points, which tile) is fixed when a scene is opened: a
relabel moves points between the class nodes of the *same* tile, so a correction re-sends only
the (class, tile) chunks holding changed points (:func:`delta_chunks` from the points a
correction changed; :func:`affected_chunks` when the whole labels were compared).

Chunk keys are ``(group, class id)`` with group 0 = coarse and ``1 + tile index`` = a tile.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from app.viewer import scene_builder as sb
from occufly.subsample import tile_groups

DEFAULT_COARSE_POINTS = 200_000
DEFAULT_TILES = 4  # 4 x 4 region tiles over the footprint


@dataclass
class LodPlan:
    """ids: (M,) int64 sorted point ids shown; group: (M,) int16 0 = coarse level (the
    motion level where the plan has one), 1 + k = refinement tile k; order: the tile groups
    (1 + k) in sending order; first: the groups sent at once (the coarse level: group 0 and,
    with a motion level, the rest of the coarse level as one more detail group, hidden while
    the camera moves)."""

    ids: np.ndarray
    group: np.ndarray
    order: list[int]
    first: tuple[int, ...] = (0,)

    @property
    def n_coarse(self) -> int:
        return int((self.group == 0).sum())


def plan_lod(data: sb.ViewerData, max_points: int, *, coarse_points: int = DEFAULT_COARSE_POINTS,
             tiles: int = DEFAULT_TILES, focus: np.ndarray | None = None,
             subsample: np.ndarray | None = None, seed: int = 0,
             motion_points: int | None = None) -> LodPlan:
    """The points shown and their level: a stratified subsample of ``max_points`` (or
    ``subsample``), ``coarse_points`` of them in the coarse level, the rest in tiles ordered
    by distance of the tile's centre to ``focus`` (scene-local xy; default the middle).
    ``motion_points`` (fewer than the coarse level): a stratified part of the coarse level
    stays group 0 (drawn while the camera moves), the rest of it becomes one more detail
    group ``1 + tiles**2``, sent with group 0 (``first``) and hidden while moving."""
    n = data.scene.n_points
    ids = subsample if subsample is not None else sb.stratified_subsample(
        data.labels, n, max_points, seed=seed,
        counts=data.label_counts() if data.labels is not None else None)
    ids = np.asarray(ids, np.int64)
    group = np.zeros(len(ids), np.int16)
    if len(ids) <= coarse_points or tiles < 1:
        return LodPlan(ids, group, [])
    lab = np.asarray(data.labels[ids]) if data.labels is not None else None
    coarse = sb.stratified_subsample(lab, len(ids), coarse_points, seed=seed + 1)
    # the tile of each point, compiled: straight from the (memory-mapped) cloud's rows, no
    # (M, 3) gather and no reductions along axis 0 of an (M, 2) array (~0.6 s of a 32 M
    # survey's first picture in numpy)
    group[:], lo, hi = tile_groups(data.scene.xyz, ids, tiles)
    span = np.maximum(hi - lo, 1e-6)
    group[coarse] = 0
    centre = lo + span * (np.stack(np.meshgrid(np.arange(tiles), np.arange(tiles),
                                               indexing="ij"), -1).reshape(-1, 2) + 0.5) / tiles
    f = (lo + hi) / 2 if focus is None else np.asarray(focus, np.float64)[:2]
    present = set(np.unique(group[group > 0]).tolist())
    order = [1 + int(k) for k in np.argsort(np.linalg.norm(centre - f, axis=1), kind="stable")
             if 1 + int(k) in present]
    if motion_points is not None and 0 < motion_points < len(coarse):
        rest = 1 + tiles * tiles
        keep = sb.stratified_subsample(lab[coarse] if lab is not None else None, len(coarse),
                                       motion_points, seed=seed + 2)
        group[coarse] = rest
        group[coarse[keep]] = 0
        return LodPlan(ids, group, order, (0, rest))
    return LodPlan(ids, group, order)


def batches(plan: LodPlan, n: int) -> list[list[int]]:
    """The tile groups of ``plan.order`` cut into at most ``n`` batches of about equal point
    counts (in order: the middle of the view first)."""
    if not plan.order:
        return []
    sizes = np.bincount(plan.group, minlength=max(plan.order) + 1)[plan.order]
    edges = np.cumsum(sizes) / max(int(sizes.sum()), 1)
    cut = np.minimum((edges * max(1, n) - 1e-9).astype(np.int64), max(1, n) - 1)
    out: list[list[int]] = [[] for _ in range(max(1, n))]
    for g, b in zip(plan.order, cut.tolist(), strict=True):
        out[b].append(g)
    return [b for b in out if b]


def group_sizes(plan: LodPlan) -> dict[int, int]:
    """Points per tile group of ``plan.order``."""
    if not plan.order:
        return {}
    counts = np.bincount(plan.group, minlength=max(plan.order) + 1)
    return {g: int(counts[g]) for g in plan.order}


def next_batch(todo: list[int], sizes: dict[int, int], shown: int, draw_s: float,
               budget_s: float, must: set[int] | frozenset = frozenset()) -> list[int]:
    """The tile groups to send next so that a frame stays within ``budget_s``: the browser
    drew ``shown`` points in ``draw_s`` seconds (a render round trip), so it is taken to
    need ``draw_s / shown`` seconds a point (an over-estimate where a fixed cost is part of
    the round trip: the next measurement, with more points shown, corrects it). Tiles are
    taken in ``todo``'s order (the middle of the view first) while the predicted frame fits;
    the groups of ``must`` (on screen before: a colour change re-sends them) always go.
    An empty list: nothing more fits, the refinement stops."""
    per_point = max(draw_s, 0.0) / max(shown, 1)
    room = budget_s / per_point - shown if per_point > 0 else float("inf")
    out, used, full = [], 0, False
    for g in todo:
        n = sizes.get(g, 0)
        if g in must or (not full and used + n <= room):
            out.append(g)
            used += n
        else:
            full = True  # keep the order: no farther tile behind one that did not fit
    return out


def chunk_name(taxonomy: sb.Taxonomy, class_id: int, group: int) -> str:
    part = "coarse" if group == 0 else f"detail/t{group - 1:03d}"
    return f"/points/{sb.class_name(taxonomy, class_id)}/{part}"


def detail_frame_name(taxonomy: sb.Taxonomy, class_id: int) -> str:
    return f"/points/{sb.class_name(taxonomy, class_id)}/detail"


def class_frame_name(taxonomy: sb.Taxonomy, class_id: int) -> str:
    return f"/points/{sb.class_name(taxonomy, class_id)}"


def build_chunks(data: sb.ViewerData, plan: LodPlan, *, mode: str = "semantic",
                 groups: set[int] | None = None,
                 keys: set[tuple[int, int]] | None = None) -> dict[tuple[int, int], sb.PointNode]:
    """The chunk nodes of ``groups`` (all when None), or only the chunks ``keys``, keyed by
    ``(group, class id)``, points split by the *current* labels."""
    # the plan's rows of the wanted groups first, then their labels: the first picture's
    # 150 k coarse points no longer gather the labels of all 2 M planned ones (from a
    # memory-mapped survey: up to 0.25 s of it)
    wanted = None if groups is None else set(groups)
    if keys is not None:
        key_groups = {g for g, _c in keys}
        wanted = key_groups if wanted is None else wanted & key_groups
    if wanted is None:
        pos = np.arange(len(plan.ids))
    else:
        lut = np.zeros(max([int(plan.group.max(initial=0)), *wanted]) + 1, bool)
        lut[[g for g in wanted if g >= 0]] = True
        pos = np.flatnonzero(lut[plan.group])
    lab = (np.asarray(data.labels[plan.ids[pos]]) if data.labels is not None
           else np.zeros(len(pos), np.uint8)).astype(np.int64)
    key = plan.group[pos].astype(np.int64) * 256 + lab
    if keys is not None:
        hit = np.isin(key, np.fromiter((g * 256 + c for g, c in keys), np.int64))
        pos, key = pos[hit], key[hit]
    order = np.argsort(key, kind="stable")
    pos, k = pos[order], key[order]
    if len(k) == 0:  # nothing of these groups or keys (ends below would be [0])
        return {}
    uniq, starts = np.unique(k, return_index=True)
    ends = np.append(starts[1:], len(k))
    idx = plan.ids[pos]
    cols = sb.point_colours(data, mode, idx)
    xyz = np.asarray(data.scene.xyz[idx], dtype=np.float32)
    out = {}
    for u, a, b in zip(uniq.tolist(), starts.tolist(), ends.tolist(), strict=True):
        g, cid = divmod(int(u), 256)
        out[(g, cid)] = sb.PointNode(chunk_name(data.taxonomy, cid, g), cid, idx[a:b],
                                     np.ascontiguousarray(xyz[a:b]),
                                     np.ascontiguousarray(cols[a:b]))
    return out


def affected_chunks(plan: LodPlan, old: sb.ViewerData, new: sb.ViewerData,
                    mode: str) -> set[tuple[int, int]] | None:
    """The ``(group, class id)`` chunks whose points changed from ``old`` to ``new`` (label,
    or what colour ``mode`` shows); None when everything must be re-sent."""
    if (old.labels is None) != (new.labels is None) or old.scene.n_points != new.scene.n_points:
        return None
    if new.labels is None:
        return set()
    ol, nl = np.asarray(old.labels[plan.ids]), np.asarray(new.labels[plan.ids])
    changed = ol != nl
    extra = {"confidence": ("confidence",), "origin": ("origin",),
             "disagreement": ("direct", "origin")}.get(mode, ())
    for name in extra:
        a, b = getattr(old, name), getattr(new, name)
        if (a is None) != (b is None):
            return None
        if a is not None:
            changed |= np.asarray(a[plan.ids]) != np.asarray(b[plan.ids])
    pos = np.flatnonzero(changed)
    g = plan.group[pos].astype(np.int64)
    keys = np.union1d(g * 256 + ol[pos], g * 256 + nl[pos])
    return {divmod(int(k), 256) for k in keys}


def delta_chunks(plan: LodPlan, delta: sb.LabelDelta, mode: str) -> set[tuple[int, int]]:
    """The ``(group, class id)`` chunks holding the shown points of ``delta`` (a relabel's,
    an undo's: :meth:`sb.ViewerData.with_corrections`): both the chunk a point leaves and
    the one it joins. In the semantic and RGB modes a point whose label stayed (only its
    confidence or origin changed) keeps its node and colour and is left out."""
    ids, old, new = delta.ids, delta.old, delta.new
    if mode in ("semantic", "rgb"):
        moved = old != new
        ids, old, new = ids[moved], old[moved], new[moved]
    if len(ids) == 0 or len(plan.ids) == 0:
        return set()
    pos = np.minimum(np.searchsorted(plan.ids, ids), len(plan.ids) - 1)
    shown = plan.ids[pos] == ids
    g = plan.group[pos[shown]].astype(np.int64)
    keys = np.union1d(g * 256 + old[shown], g * 256 + new[shown])
    return {divmod(int(k), 256) for k in keys}


def merge_by_class(chunks: dict[tuple[int, int], sb.PointNode],
                   taxonomy: sb.Taxonomy) -> dict[int, sb.PointNode]:
    """One aggregate :class:`PointNode` per class of every chunk sent (what selection on the
    shown points and the tests read)."""
    by: dict[int, list[sb.PointNode]] = {}
    for (_g, cid), nd in sorted(chunks.items()):
        by.setdefault(cid, []).append(nd)
    out = {}
    for cid, parts in by.items():
        out[cid] = sb.PointNode(
            class_frame_name(taxonomy, cid), cid,
            np.concatenate([p.point_ids for p in parts]),
            np.concatenate([p.xyz for p in parts]),
            np.concatenate([p.colors for p in parts]))
    return out
