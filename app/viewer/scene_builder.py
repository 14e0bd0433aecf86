"""Turn pipeline outputs into viser scene calls (pure numpy; the only viser code is `send_*`).

Everything here works in float32 *scene-local* metres (``xyz_world = scene.origin + xyz``):
viser's default float16 point precision would round a point 3 km from the origin to ~2 m, so
point clouds are sent with ``precision="float32"``.

Node names (what a client receives; tests assert them)::

    /points/<class name>            one point cloud per class present ("unlabelled" for 0)
    /grid/scene/<class name>        instanced boxes of the scene grid (surface voxels)
    /grid/frame/<class name>        a frame's camera grid, valid occupied voxels
    /grid/frame/_occluded           ... occupied voxels hidden behind the first surface
    /grid/frame/_invalid            ... a sparse sample of invalid voxels (outside frustum)
    /cameras/<frame stem>           a frustum per frame, coloured by review state

Colour modes (:data:`COLOUR_MODES`): ``rgb`` (reconstruction colour), ``semantic`` (taxonomy
colour of the final label), ``confidence`` (the calibrated probability that the label is
right, occufly.lifting.calibration: dark red 0 -> yellow 1; 0 for unlabelled points; a
filled label's falls with its distance to the votes), ``origin`` (grey none,
blue direct, orange kNN-filled, purple denoised) and ``disagreement`` (red where the final
label differs from the direct vote of the masks, light grey where they agree, dark grey where
no mask voted).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from occufly.errors import WorkspaceError
from occufly.lifting import VoteStore
from occufly.lifting.corrections import apply_overrides
from occufly.lifting.result import ORIGIN_CORRECTED, LiftResult
from occufly.scene import Scene
from occufly.subsample import selection_sample
from occufly.taxonomy import Taxonomy
from occufly.workspace import Workspace

log = logging.getLogger(__name__)

DEFAULT_MAX_POINTS = 2_000_000
COLOUR_MODES = ("rgb", "semantic", "confidence", "origin", "disagreement")
UNLABELLED = "unlabelled"

# origin codes written by occufly.lifting: 0 none, 1 direct, 2 filled, 3 denoised, 4 corrected
ORIGIN_NAMES = ("none", "direct", "filled", "denoised", "corrected")
ORIGIN_COLOURS = np.array([[128, 128, 128], [30, 110, 255], [255, 150, 0], [170, 60, 220],
                           [255, 20, 147]], np.uint8)
DISAGREE_COLOUR = np.array([230, 20, 20], np.uint8)
AGREE_COLOUR = np.array([200, 200, 200], np.uint8)
NO_VOTE_COLOUR = np.array([90, 90, 90], np.uint8)

FRAME_STATES = ("not_selected", "selected", "annotated", "accepted", "rejected")
STATE_COLOURS: dict[str, tuple[int, int, int]] = {
    "not_selected": (150, 150, 150),
    "selected": (40, 120, 255),
    "annotated": (255, 190, 0),
    "accepted": (0, 180, 60),
    "rejected": (230, 20, 20),
}
HIGHLIGHT_COLOUR = (255, 0, 200)  # the frame opened with "Open in 3D viewer"


# ---- inputs ------------------------------------------------------------------------------
@dataclass
class ViewerData:
    """What the viewer draws for one scene.

    labels: (N,) uint8 final raw class ids (0 = unlabelled) or None (RGB-only fallback).
    confidence: (N,) float32 in [0, 1] or None. origin: (N,) uint8 codes 0..3 or None.
    direct: (N,) uint8 direct-vote labels (0 = no vote) or None.
    grid: an ``occufly.grid.SceneGrid`` or None.
    base: the fill output the corrections were applied to (memory-mapped; None when the
    data was not loaded from a workspace's lifting files): what :meth:`with_corrections`
    applies the current correction layer to again.
    """

    scene: Scene
    labels: np.ndarray | None = None
    confidence: np.ndarray | None = None
    origin: np.ndarray | None = None
    direct: np.ndarray | None = None
    grid: Any = None
    workspace: Path | None = None
    base: LiftResult | None = field(default=None, repr=False)
    _counts: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        n = self.scene.n_points
        for name in ("labels", "confidence", "origin", "direct"):
            arr = getattr(self, name)
            if arr is None:
                continue
            if isinstance(arr, LazyLabels):  # direct votes: shape checked when computed
                continue
            arr = np.asarray(arr)
            if arr.shape != (n,):
                where = f"{self.workspace}/lifting/{name}.npy" if self.workspace else name
                raise WorkspaceError(f"{where}: expected shape ({n},) for {n} points, got {arr.shape}")
            setattr(self, name, arr)

    @property
    def taxonomy(self) -> Taxonomy:
        return self.scene.taxonomy

    def start_background(self) -> None:
        """Start what is computed in the background (the direct-vote labels), if not yet."""
        if isinstance(self.direct, LazyLabels):
            self.direct.start()

    def direct_array(self) -> np.ndarray | None:
        """The direct-vote labels as an array (waiting for the background computation), or
        None: no votes, or votes that could not be read."""
        d = self.direct
        return d.get_or_none() if isinstance(d, LazyLabels) else d

    def label_counts(self) -> np.ndarray:
        """(256,) int64 points per raw class id (all unlabelled without labels); computed
        once per data (a relabel's data gets them from :meth:`with_corrections`)."""
        if self._counts is None:
            if self.labels is None:
                c = np.zeros(256, np.int64)
                c[0] = self.scene.n_points
            else:
                c = count_labels(self.labels)
            self._counts = c
        return self._counts

    def with_corrections(self) -> tuple[ViewerData, LabelDelta | None]:
        """This data with the workspace's *current* correction layer applied to the same fill
        output (:attr:`base`, unchanged on disk: the caller checks), and what changed.

        What a relabel, undo or redo (anyone's) changes is the correction layer only, so the
        scene, votes and grid are kept and the fill output is not read again; the changed
        points are found among the corrected points of the old and new layers (their origin
        is ``ORIGIN_CORRECTED``), never by comparing every point. The delta is None when
        this data cannot be refreshed so (no lifting files): reload it instead."""
        if self.base is None or self.workspace is None or self.labels is None:
            return self, None
        res = apply_overrides(self.base, self.workspace)
        new = ViewerData(self.scene, res.labels, res.confidence, res.origin, self.direct,
                         self.grid, self.workspace, self.base)
        delta = label_delta(self, new)
        c = self.label_counts().copy()
        np.subtract.at(c, delta.old.astype(np.int64), 1)
        np.add.at(c, delta.new.astype(np.int64), 1)
        new._counts = c
        return new, delta

    @classmethod
    def load(cls, ws: str | Path, *, scene: Scene | None = None) -> ViewerData:
        """Load a workspace: scene, ``lifting/{labels,confidence,origin}.npy`` if present,
        direct votes (``occufly.lifting.VoteStore``) if available, ``grid/scene_grid.npz``."""
        ws = Path(ws)
        w = Workspace(ws)
        scene = scene if scene is not None else Scene.load(ws)

        def opt(p: Path) -> np.ndarray | None:
            if not p.is_file():
                return None
            try:
                return np.load(p, mmap_mode="r", allow_pickle=False)
            except (OSError, ValueError) as e:
                raise WorkspaceError(f"{p}: not a readable .npy array ({e})") from None

        labels = opt(w.labels_path)
        conf = opt(w.confidence_path)
        origin = opt(w.label_origin_path)
        base = None
        if labels is not None and conf is not None and origin is not None:
            # what every reader sees: the fill output with reviewers' corrections on top
            base = LiftResult(labels, conf, origin)
            res = apply_overrides(base, w)
            labels, conf, origin = res.labels, res.confidence, res.origin
        direct = _load_direct(ws, scene)
        grid = w.grid()
        return cls(scene, labels, conf, origin, direct, grid, ws, base)


@dataclass
class LabelDelta:
    """The points whose label, confidence or origin differ between two datas of one scene:
    ids (K,) int64 sorted; old / new (K,) uint8 their labels before and after."""

    ids: np.ndarray
    old: np.ndarray
    new: np.ndarray


def label_delta(old: ViewerData, new: ViewerData) -> LabelDelta:
    """What changed from ``old`` to ``new``, two datas of the same fill output that differ
    only by their correction layers: every point either layer names has origin
    ``ORIGIN_CORRECTED`` in the data it is applied to, so only those points are compared."""
    cand = np.flatnonzero((np.asarray(old.origin) == ORIGIN_CORRECTED)
                          | (np.asarray(new.origin) == ORIGIN_CORRECTED))
    ol, nl = np.asarray(old.labels[cand]), np.asarray(new.labels[cand])
    changed = ((ol != nl) | (np.asarray(old.confidence[cand]) != np.asarray(new.confidence[cand]))
               | (np.asarray(old.origin[cand]) != np.asarray(new.origin[cand])))
    return LabelDelta(cand[changed], ol[changed], nl[changed])


class LazyLabels:
    """(N,) uint8 labels computed once, in a background thread; the first reader that needs
    them before they are done waits. ``np.asarray``, indexing and ``shape`` work as on the
    array. The viewer's direct-vote labels: a pass over the (N, C) vote counts (the survey's
    31.9 M x 21: 1.1-1.3 s of CPU) that only the *disagreement* colours read, so a scene's
    first points are not sent after it.

    The thread starts at :meth:`start` or with the first reader: the viewer starts it once a
    tab's level of detail is on screen. Started at once, the pass took the second of two
    cores from the first picture (the plan, the chunks, the browser's own drawing): the
    survey's first points 2.70 s with it running, 2.20 s without."""

    def __init__(self, n: int, compute: Any) -> None:
        self.shape = (int(n),)
        self._compute = compute
        self._value: np.ndarray | None = None
        self._error: BaseException | None = None
        self._done = threading.Event()
        self._started = False
        self._start_lock = threading.Lock()

    def start(self) -> None:
        """Start the computation (once; later calls do nothing)."""
        with self._start_lock:
            if self._started:
                return
            self._started = True
        threading.Thread(target=self._run, daemon=True, name="occufly-viewer-direct").start()

    @property
    def started(self) -> bool:
        return self._started

    def _run(self) -> None:
        try:
            v = np.asarray(self._compute(), dtype=np.uint8)
            if v.shape != self.shape:
                raise WorkspaceError(f"direct labels of shape {v.shape}, expected {self.shape}")
            self._value = v
        except Exception as e:  # noqa: BLE001 - a half-written lifting state must not kill the viewer
            log.warning("viewer: cannot read direct votes: %s", e)
            self._error = e
        finally:
            self._compute = None
            self._done.set()

    def get(self) -> np.ndarray:
        """The labels (waits for them, starting them if nobody has); raises what their
        computation raised."""
        self.start()
        self._done.wait()
        if self._error is not None:
            raise self._error
        return self._value

    def get_or_none(self) -> np.ndarray | None:
        """The labels, or None where they could not be computed (logged)."""
        self.start()
        self._done.wait()
        return self._value

    def __array__(self, dtype=None, copy=None) -> np.ndarray:  # noqa: ANN001
        a = self.get()
        return a if dtype is None else a.astype(dtype)

    def __getitem__(self, idx):  # noqa: ANN001, ANN204
        return self.get()[idx]

    def __len__(self) -> int:
        return self.shape[0]


def _load_direct(ws: Path, scene: Scene) -> LazyLabels | None:
    """Direct (mask-vote majority) labels from ``lifting/votes.npy``, read-only, or None
    (no votes, or counts of another shape); computed in the background (:class:`LazyLabels`)
    once the viewer starts them (:meth:`ViewerData.start_background`) or a reader needs them.

    Built without ``VoteStore.open`` on purpose: that may create or repair the state (writes),
    and the backend's lifting worker owns the workspace. A torn read during a concurrent
    update only affects the display until the next refresh.
    """
    votes_path = Workspace(ws).votes
    if not votes_path.is_file():
        return None
    try:
        votes = np.load(votes_path, mmap_mode="r", allow_pickle=False)
        if votes.shape != (scene.n_points, len(scene.taxonomy)):
            log.warning("viewer: %s has shape %s, expected (%d, %d)", votes_path, votes.shape,
                        scene.n_points, len(scene.taxonomy))
            return None
    except Exception as e:  # noqa: BLE001 - a half-written lifting state must not kill the viewer
        log.warning("viewer: cannot read direct votes in %s: %s", ws, e)
        return None
    return LazyLabels(scene.n_points, lambda: VoteStore(ws, scene, votes, {}).direct_labels())


# ---- level of detail ---------------------------------------------------------------------
def count_labels(labels: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """(256,) int64 points per raw class id of ``labels`` ((N,) uint8), counted in chunks:
    one ``np.bincount`` of a survey's 32 M labels first casts them to a 256 MB index array
    (0.37-0.79 s when that memory is fresh), chunks of 1 M stay in cache (0.05 s)."""
    lab = np.asarray(labels)
    out = np.zeros(256, np.int64)
    for i in range(0, len(lab), chunk):
        out += np.bincount(lab[i:i + chunk], minlength=256)[:256]
    return out


def class_quotas(counts: np.ndarray, max_points: int, *, floor_share: float = 0.25) -> np.ndarray:
    """Stratified LOD budget per class: a guaranteed floor, the rest proportional.

    counts: (C,) int points per class. Every class present first gets
    ``min(count, floor_share * max_points / classes_present)`` points (so a rare class is kept
    whole and never squeezed out by a dominant one); the remaining budget is shared in
    proportion to the points each class has left, which keeps the relative density of the
    large classes. Returns (C,) int64 quotas with ``quota <= count`` and
    ``sum == min(sum(counts), max_points)``.
    """
    counts = np.asarray(counts, dtype=np.int64)
    if max_points < 0:
        raise ValueError(f"max_points must be >= 0, got {max_points}")
    total = int(counts.sum())
    if total <= max_points:
        return counts.copy()
    n_present = int((counts > 0).sum())
    floor = np.minimum(counts, int(floor_share * max_points / n_present))
    budget = int(max_points - floor.sum())
    rest = counts - floor
    share = rest * (budget / float(rest.sum()))
    quotas = floor + np.floor(share).astype(np.int64)
    quotas = np.minimum(quotas, counts)
    short = int(max_points - quotas.sum())
    if short > 0:  # hand out the rounding remainder by largest fractional part
        frac = np.where(quotas < counts, share - np.floor(share), -1.0)
        for ci in np.argsort(-frac, kind="stable")[:short]:
            quotas[ci] += 1
    return quotas


def stratified_subsample(labels: np.ndarray | None, n_points: int, max_points: int,
                         *, seed: int = 0, counts: np.ndarray | None = None) -> np.ndarray:
    """Indices (sorted, int64) of at most ``max_points`` points, stratified per class.

    labels: (N,) uint8 raw ids or None (one stratum); counts: (256,) int64 points per class
    of ``labels`` when known (:meth:`ViewerData.label_counts`: a bincount of a survey's
    32 M labels costs 0.2-0.7 s). Deterministic for a given seed.
    """
    if n_points <= max_points:
        return np.arange(n_points, dtype=np.int64)
    labels = np.zeros(n_points, np.uint8) if labels is None else np.asarray(labels)
    if labels.dtype != np.uint8:  # raw class ids (< 256) in a wider type
        labels = labels.astype(np.uint8)
    if counts is None:
        counts = count_labels(labels)
    quotas = class_quotas(counts, max_points)
    # one compiled pass over the labels (selection sampling per class): the numpy version
    # (sorted rng.choice ranks per class, then a comparison and flatnonzero per class and 1 M
    # chunk) took 0.44-1.5 s of a 32 M survey's first picture
    return selection_sample(labels, quotas, counts, seed=seed)


# ---- colours -----------------------------------------------------------------------------
def confidence_colours(conf: np.ndarray) -> np.ndarray:
    """(n,) float in [0, 1] -> (n, 3) uint8 ramp dark red (0) -> orange -> yellow (1)."""
    c = np.clip(np.nan_to_num(np.asarray(conf, np.float32), nan=0.0), 0.0, 1.0)
    out = np.empty((len(c), 3), np.uint8)
    out[:, 0] = (120 + 135 * np.minimum(c * 2, 1.0)).astype(np.uint8)
    out[:, 1] = (230 * c).astype(np.uint8)
    out[:, 2] = (40 * (1 - c)).astype(np.uint8)
    return out


def point_colours(data: ViewerData, mode: str, idx: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 colours of points ``idx`` (int64 indices) in colour ``mode``.

    Modes that need lifting outputs fall back to RGB when those are missing.
    """
    if mode not in COLOUR_MODES:
        raise ValueError(f"colour mode must be one of {COLOUR_MODES}, got {mode!r}")
    if mode == "semantic" and data.labels is not None:
        return data.taxonomy.colour_lut()[np.asarray(data.labels[idx])]
    if mode == "confidence" and data.confidence is not None:
        return confidence_colours(np.asarray(data.confidence[idx]))
    if mode == "origin" and data.origin is not None:
        return ORIGIN_COLOURS[np.minimum(np.asarray(data.origin[idx]), len(ORIGIN_COLOURS) - 1)]
    if mode == "disagreement" and data.labels is not None:
        lab = np.asarray(data.labels[idx])
        out = np.empty((len(idx), 3), np.uint8)
        direct = data.direct_array()
        if direct is not None:
            d = np.asarray(direct[idx])
            voted = d != 0
            disagree = voted & (d != lab)
        else:  # no vote state: a point relabelled by the denoise pass disagrees with its votes
            o = np.asarray(data.origin[idx]) if data.origin is not None else np.zeros(len(idx))
            voted = o != 0
            disagree = o == 3
        out[:] = NO_VOTE_COLOUR
        out[voted] = AGREE_COLOUR
        out[disagree] = DISAGREE_COLOUR
        return out
    return np.ascontiguousarray(np.asarray(data.scene.rgb[idx], dtype=np.uint8))


# ---- point nodes -------------------------------------------------------------------------
@dataclass
class PointNode:
    """One class's points. point_ids: (n,) int64 into the full cloud; xyz: (n, 3) float32
    scene-local metres; colors: (n, 3) uint8."""

    name: str
    class_id: int
    point_ids: np.ndarray
    xyz: np.ndarray
    colors: np.ndarray


def class_name(taxonomy: Taxonomy, class_id: int) -> str:
    if class_id == 0:
        return UNLABELLED
    if class_id in taxonomy:
        return taxonomy[class_id].name
    return f"id_{class_id}"


def build_point_nodes(data: ViewerData, *, mode: str = "semantic",
                      max_points: int = DEFAULT_MAX_POINTS, seed: int = 0,
                      classes: set[int] | None = None,
                      subsample: np.ndarray | None = None) -> list[PointNode]:
    """One :class:`PointNode` per class present, after a stratified LOD subsample.

    ``classes`` restricts the output to those raw ids (for live refresh). ``subsample``
    reuses precomputed indices (from :func:`stratified_subsample`).
    """
    n = data.scene.n_points
    idx = subsample if subsample is not None else stratified_subsample(data.labels, n, max_points, seed=seed)
    lab = np.asarray(data.labels[idx]) if data.labels is not None else np.zeros(len(idx), np.uint8)
    if classes is not None:  # colour and copy only what is re-sent
        keep = np.isin(lab, np.fromiter(classes, dtype=np.int64))
        idx, lab = idx[keep], lab[keep]
    order = np.argsort(lab, kind="stable")
    idx, lab = idx[order], lab[order]
    ids, starts = np.unique(lab, return_index=True)
    ends = np.append(starts[1:], len(lab))
    cols = point_colours(data, mode, idx)
    xyz = np.asarray(data.scene.xyz[idx], dtype=np.float32)
    nodes = []
    for cid, a, b in zip(ids.tolist(), starts.tolist(), ends.tolist(), strict=True):
        if classes is not None and cid not in classes:
            continue
        nodes.append(PointNode(
            name=f"/points/{class_name(data.taxonomy, cid)}",
            class_id=int(cid),
            point_ids=idx[a:b],
            xyz=np.ascontiguousarray(xyz[a:b]),
            colors=np.ascontiguousarray(cols[a:b]),
        ))
    return nodes


def send_point_nodes(scene_api: Any, nodes: list[PointNode], *, point_size: float = 0.05,
                     visible: dict[int, bool] | None = None) -> dict[int, Any]:
    """Add every node to a viser ``SceneApi`` (server.scene or client.scene) in float32."""
    handles = {}
    for nd in nodes:
        handles[nd.class_id] = scene_api.add_point_cloud(
            nd.name, points=nd.xyz, colors=nd.colors, point_size=point_size,
            precision="float32", point_shape="square", point_shading="flat",
            visible=True if visible is None else visible.get(nd.class_id, True),
        )
    return handles


# ---- rectangle selection -----------------------------------------------------------------
def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """(4,) quaternion (w, x, y, z) -> (3, 3) float64 rotation."""
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) float64 quaternion (w, x, y, z), w >= 0."""
    return matrices_to_quats(np.asarray(R, np.float64)[None])[0]


def matrices_to_quats(R: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations -> (n, 4) float64 quaternions (w, x, y, z), w >= 0: each row what
    :func:`matrix_to_quat` gives for that matrix."""
    q = Rotation.from_matrix(np.asarray(R, np.float64)).as_quat()[:, [3, 0, 1, 2]]
    return np.where(q[:, :1] >= 0, q, -q)


def points_in_screen_rect(xyz: np.ndarray, cam_position: np.ndarray, cam_wxyz: np.ndarray,
                          fov_y: float, aspect: float, screen_min: tuple[float, float],
                          screen_max: tuple[float, float]) -> np.ndarray:
    """(N,) bool: points in front of a viser camera whose projection falls in the rectangle.

    xyz: (N, 3) float32 scene-local metres. The camera follows viser: ``wxyz``/``position``
    map camera to world (OpenCV axes: x right, y down, z forward), ``fov_y`` vertical field
    of view in radians, ``aspect`` = width / height; screen coordinates are 0..1 from the
    top-left corner.
    """
    R = quat_to_matrix(cam_wxyz)
    p = (np.asarray(xyz, np.float64) - np.asarray(cam_position, np.float64)) @ R  # = R^T (x - t)
    z = p[:, 2]
    t = np.tan(fov_y / 2.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 0.5 + p[:, 0] / (z * t * aspect) / 2.0
        v = 0.5 + p[:, 1] / (z * t) / 2.0
    (u0, v0), (u1, v1) = screen_min, screen_max
    u0, u1 = min(u0, u1), max(u0, u1)
    v0, v1 = min(v0, v1), max(v0, v1)
    return (z > 0) & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1)


# ---- voxel grids -------------------------------------------------------------------------
CUBE_VERTICES = np.array(
    [[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)], np.float32
)
CUBE_FACES = np.array([
    [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5],  # -x, +x
    [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],  # -y, +y
    [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],  # -z, +z
], np.uint32)


@dataclass
class VoxelNode:
    """Instanced boxes of one class. centers: (n, 3) float32 scene-local metres."""

    name: str
    class_id: int
    centers: np.ndarray
    size: float
    color: tuple[int, int, int]
    wxyz: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    opacity: float | None = None


def surface_mask(occupied: np.ndarray) -> np.ndarray:
    """(X, Y, Z) bool: occupied voxels with at least one empty (or out-of-grid) 6-neighbour."""
    occ = np.asarray(occupied, bool)
    p = np.pad(occ, 1, constant_values=False)
    inner = (p[:-2, 1:-1, 1:-1] & p[2:, 1:-1, 1:-1] & p[1:-1, :-2, 1:-1] & p[1:-1, 2:, 1:-1]
             & p[1:-1, 1:-1, :-2] & p[1:-1, 1:-1, 2:])
    return occ & ~inner


def _cap(ijk: np.ndarray, max_voxels: int) -> np.ndarray:
    if len(ijk) <= max_voxels:
        return ijk
    step = int(np.ceil(len(ijk) / max_voxels))
    return ijk[::step]


def _voxel_nodes(labels: np.ndarray, keep: np.ndarray, centers_of, taxonomy: Taxonomy,
                 prefix: str, size: float, max_voxels: int, wxyz: np.ndarray) -> list[VoxelNode]:
    ijk = np.argwhere(keep)
    if len(ijk) == 0:
        return []
    lab = labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
    order = np.argsort(lab, kind="stable")
    ijk, lab = ijk[order], lab[order]
    ids, starts = np.unique(lab, return_index=True)
    ends = np.append(starts[1:], len(lab))
    lut = taxonomy.colour_lut()
    total = len(lab)
    nodes = []
    for cid, a, b in zip(ids.tolist(), starts.tolist(), ends.tolist(), strict=True):
        share = max(1, int(max_voxels * (b - a) / total)) if total > max_voxels else b - a
        sel = _cap(ijk[a:b], share)
        nodes.append(VoxelNode(
            name=f"{prefix}/{class_name(taxonomy, cid)}", class_id=int(cid),
            centers=centers_of(sel).astype(np.float32), size=size,
            color=tuple(int(v) for v in lut[cid]), wxyz=wxyz,
        ))
    return nodes


def scene_grid_nodes(grid: Any, scene_origin: np.ndarray, taxonomy: Taxonomy, *,
                     prefix: str = "/grid/scene", surface_only: bool = True,
                     max_voxels: int = 300_000) -> list[VoxelNode]:
    """Scene grid -> one node per class with voxel centres in scene-local metres.

    Only surface voxels are drawn by default (interior boxes are never visible); at most
    ``max_voxels`` in total, shared by class in proportion (regular stride).
    """
    labels = np.asarray(grid.labels)
    occ = (labels != 0) & (labels != 255)
    keep = surface_mask(occ) if surface_only else occ
    shift = np.asarray(grid.origin, np.float64) - np.asarray(scene_origin, np.float64)
    vs = float(grid.voxel_size)

    def centers_of(ijk: np.ndarray) -> np.ndarray:
        return shift + (ijk + 0.5) * vs

    return _voxel_nodes(labels, keep, centers_of, taxonomy, prefix, vs, max_voxels,
                        np.array([1.0, 0.0, 0.0, 0.0]))


def camera_grid_nodes(labels: np.ndarray, invalid: np.ndarray, occluded: np.ndarray,
                      surface: np.ndarray, T_cam_world: np.ndarray, voxel_size: float,
                      taxonomy: Taxonomy, *, prefix: str = "/grid/frame",
                      surface_only: bool = False, max_voxels: int = 300_000,
                      max_invalid: int = 20_000) -> list[VoxelNode]:
    """A frame's camera-centric grid (FORMATS.md section 2) -> nodes in scene-local metres.

    labels: (X, Y, Z) uint8 raw ids (255 = invalid); invalid / occluded / surface: (X, Y, Z)
    bool masks; T_cam_world: (4, 4) float64 scene-local world-to-camera. Voxel (i, j, k) has
    camera centre ((i - X/2 + .5) r, (j - Y/2 + .5) r, (k + .5) r). Valid occupied voxels
    (optionally surface only) are drawn per class; ``_occluded`` (grey, translucent) holds the
    occupied voxels behind the first surface; ``_invalid`` a sparse sample of invalid voxels.
    """
    labels = np.asarray(labels)
    X, Y, _ = labels.shape
    invalid = np.asarray(invalid, bool)
    occluded = np.asarray(occluded, bool)
    surface = np.asarray(surface, bool)
    T_world_cam = np.linalg.inv(np.asarray(T_cam_world, np.float64))
    R, t = T_world_cam[:3, :3], T_world_cam[:3, 3]
    r = float(voxel_size)
    off = np.array([X / 2.0, Y / 2.0, 0.0])

    def centers_of(ijk: np.ndarray) -> np.ndarray:
        cam = (ijk - off + 0.5) * r
        return cam @ R.T + t

    wxyz = matrix_to_quat(R)
    occ = (labels != 0) & (labels != 255) & ~invalid
    visible = occ & ~occluded
    if surface_only:
        visible &= surface
    nodes = _voxel_nodes(labels, visible, centers_of, taxonomy, prefix, r, max_voxels, wxyz)
    occ_ijk = _cap(np.argwhere(occ & occluded), max_voxels)
    if len(occ_ijk):
        nodes.append(VoxelNode(f"{prefix}/_occluded", -1, centers_of(occ_ijk).astype(np.float32),
                               r, (110, 110, 110), wxyz, opacity=0.35))
    inv_ijk = _cap(np.argwhere(invalid), max_invalid)
    if len(inv_ijk):
        nodes.append(VoxelNode(f"{prefix}/_invalid", -2, centers_of(inv_ijk).astype(np.float32),
                               r * 0.3, (60, 60, 60), wxyz, opacity=0.15))
    return nodes


#: the voxel grids' mesh material: ``toon3`` (three shading bands, no physically based
#: lighting) drew the survey's scene grid in 3.5 s frames under software WebGL where the
#: standard material took 7.3 s, with 44 % less of the browser's CPU (issue 38)
GRID_MATERIAL = "toon3"


def send_voxel_nodes(scene_api: Any, nodes: list[VoxelNode],
                     visible: dict[int, bool] | None = None) -> dict[str, Any]:
    """Add every voxel node as instanced boxes (``add_batched_meshes_simple``, the
    :data:`GRID_MATERIAL`)."""
    handles = {}
    for nd in nodes:
        n = len(nd.centers)
        handles[nd.name] = scene_api.add_batched_meshes_simple(
            nd.name, vertices=CUBE_VERTICES * np.float32(nd.size), faces=CUBE_FACES,
            batched_wxyzs=np.broadcast_to(np.asarray(nd.wxyz, np.float32), (n, 4)),
            batched_positions=nd.centers, batched_colors=np.asarray(nd.color, np.uint8),
            opacity=nd.opacity, flat_shading=True, lod="off", material=GRID_MATERIAL,
            cast_shadow=False,
            receive_shadow=False,
            visible=True if visible is None else visible.get(nd.class_id, True),
        )
    return handles


# ---- cameras -----------------------------------------------------------------------------
@dataclass
class FrustumNode:
    """A frame's frustum: camera-to-world pose (viser/OpenCV axes) in scene-local metres."""

    name: str
    frame_index: int
    fov: float
    aspect: float
    wxyz: np.ndarray
    position: np.ndarray
    state: str
    color: tuple[int, int, int]


def viewer_state(selected: bool, state: str | None) -> str:
    """Map the backend's frame fields to a frustum state of :data:`FRAME_STATES`."""
    if state == "accepted":
        return "accepted"
    if state == "rejected":
        return "rejected"
    if state == "submitted":
        return "annotated"
    return "selected" if selected else "not_selected"


def frustum_nodes(scene: Scene, states: dict[int, str] | None = None) -> list[FrustumNode]:
    """One frustum per frame; ``states`` maps frame index -> one of :data:`FRAME_STATES`."""
    nodes = []
    states = states or {}
    if not scene.frames:
        return nodes
    # every frame's pose inverted and turned into a quaternion in one batched call each (a
    # survey's 2,100 cameras: 0.3 s of per-frame scipy calls before the first points)
    T_world_cam = np.linalg.inv(np.stack([np.asarray(fr.T_cam_world, np.float64)
                                          for fr in scene.frames]))
    wxyz = matrices_to_quats(T_world_cam[:, :3, :3])
    for i, fr in enumerate(scene.frames):
        fy = fr.camera.focal[1]
        fov = 2.0 * float(np.arctan2(fr.camera.height / 2.0, fy))
        st = states.get(i, "not_selected")
        if st not in STATE_COLOURS:
            raise ValueError(f"frame state must be one of {FRAME_STATES}, got {st!r}")
        nodes.append(FrustumNode(
            name=f"/cameras/{fr.stem}", frame_index=i, fov=fov,
            aspect=fr.camera.width / fr.camera.height, wxyz=wxyz[i],
            position=T_world_cam[i, :3, 3].copy(), state=st, color=STATE_COLOURS[st],
        ))
    return nodes


#: the viewer's "Show cameras" choices
CAMERA_FILTERS = ("all", "selected and annotated", "none")
#: above this many frames the viewer starts with only the selected and annotated cameras
MANY_FRAMES = 400


def default_camera_filter(n_frames: int) -> str:
    return CAMERA_FILTERS[0] if n_frames <= MANY_FRAMES else CAMERA_FILTERS[1]


def filter_frustum_nodes(nodes: list[FrustumNode], mode: str,
                         keep: set[int] | None = None) -> list[FrustumNode]:
    """The frusta shown for a "Show cameras" choice; frames in ``keep`` (the focused frame of
    "Open in 3D") are always shown."""
    if mode not in CAMERA_FILTERS:
        raise ValueError(f"camera filter must be one of {CAMERA_FILTERS}, got {mode!r}")
    keep = keep or set()
    if mode == "all":
        return list(nodes)
    if mode == "none":
        return [nd for nd in nodes if nd.frame_index in keep]
    return [nd for nd in nodes if nd.state != "not_selected" or nd.frame_index in keep]


def send_frustum_nodes(scene_api: Any, nodes: list[FrustumNode], *, scale: float = 2.0) -> dict[int, Any]:
    handles = {}
    for nd in nodes:
        handles[nd.frame_index] = scene_api.add_camera_frustum(
            nd.name, fov=nd.fov, aspect=nd.aspect, scale=scale, color=nd.color,
            wxyz=nd.wxyz, position=nd.position, thickness=0.05,
        )
    return handles


def scene_extent(data: ViewerData) -> float:
    """A length scale (metres) of the scene for frustum size and point size defaults."""
    xyz = np.asarray(data.scene.xyz[:: max(1, data.scene.n_points // 100_000)])
    if len(xyz) == 0:
        return 10.0
    return float(max(np.ptp(xyz, axis=0).max(), 1.0))


def default_point_size(data: ViewerData, n_shown: int) -> float:
    """Point size (metres) close to the spacing of the shown points on the scene footprint."""
    xyz = np.asarray(data.scene.xyz[:: max(1, data.scene.n_points // 100_000)])
    if len(xyz) == 0 or n_shown <= 0:
        return 0.05
    span = np.ptp(xyz[:, :2], axis=0)
    area = float(max(span[0], 1.0) * max(span[1], 1.0))
    return float(np.clip(0.8 * np.sqrt(area / n_shown), 0.01, 2.0))

