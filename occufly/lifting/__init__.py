"""Multi-view label lifting: incremental votes, kNN fill, kNN denoise, confidence.

Its main modules (each module's docstring gives the details; beside them ``loo`` -- the
review's leave-one-out labels --, ``quality``, ``suspects``, ``incremental``, ``corrections``
and ``calibration``):

``occufly.lifting.votes``
    :class:`VoteStore`, the per-point vote counts of one workspace, updated one frame at a
    time (:meth:`~VoteStore.apply_frame`, :meth:`~VoteStore.remove_frame`), crash-safe on
    disk and resumed by :meth:`~VoteStore.open`; :meth:`~VoteStore.snapshot` copies out the
    vote majority so a fill can run while updates go on.
``occufly.lifting.knn``
    :func:`fill_and_denoise` (certified voxels plus exact k-NN at class boundaries) and
    :func:`fill_and_denoise_exact`, the plain cKDTree reference it must agree with.
``occufly.lifting.robust``
    :func:`~occufly.lifting.robust.redecide`: the votes of imperfect annotators re-decided
    before the fill with an annotator model estimated from the votes and a per-scene point
    classifier (``LiftParams.robust``, on by default; :class:`RobustParams`).
``occufly.lifting.result``
    :class:`LiftResult` (labels, confidence, origin) and its files (:func:`save_result`,
    :func:`load_labels`).

Point-level evaluation against truth lives in :func:`occufly.metrics.evaluate_points` (a
layer above this package: ``pyproject.toml``'s import-linter contracts).

A live worker (the app's lifting service) uses::

    state = VoteStore.open(ws, scene)           # resumes from disk
    state.version_of(fi)                        # what is counted for frame fi
    state.apply_frame(fi, mask, version="42")   # or state.remove_frame(fi)
    snap = state.snapshot()                     # under the worker's update lock
    state.fill_and_denoise(snapshot=snap)       # without it; writes labels/confidence/origin
"""

from __future__ import annotations

from occufly.lifting.classes import ClassColumns
from occufly.lifting.corrections import load_labels
from occufly.lifting.knn import (
    LiftParams,
    fill_and_denoise,
    fill_and_denoise_exact,
    params_dict,
    typical_knn_radius,
)
from occufly.lifting.result import (
    LIFT_DIR,
    ORIGIN_CORRECTED,
    ORIGIN_DENOISED,
    ORIGIN_DIRECT,
    ORIGIN_FILLED,
    ORIGIN_NAMES,
    ORIGIN_NONE,
    LiftResult,
    save_result,
)
from occufly.lifting.robust import RobustParams
from occufly.lifting.votes import (
    DEFAULT_VOTE_WEIGHTING,
    STATE_VERSION,
    VOTE_WEIGHTINGS,
    VoteSnapshot,
    VoteStore,
    boundary_weights,
    fill_snapshot,
    interior_weights,
    read_direct_labels,
)

__all__ = [
    "LIFT_DIR", "ORIGIN_CORRECTED", "ORIGIN_DENOISED", "ORIGIN_DIRECT", "ORIGIN_FILLED", "ORIGIN_NAMES",
    "ORIGIN_NONE", "RobustParams", "STATE_VERSION", "VOTE_WEIGHTINGS", "DEFAULT_VOTE_WEIGHTING", "boundary_weights", "interior_weights", "ClassColumns", "LiftParams", "LiftResult", "VoteStore",
    "VoteSnapshot", "fill_and_denoise", "fill_and_denoise_exact",
    "fill_snapshot", "load_labels", "read_direct_labels", "params_dict", "save_result", "typical_knn_radius",
]

