"""The 3D prefill as 2D masks for other tools: the lifted labels (reviewers' corrections
applied, :func:`occufly.lifting.load_labels`) rendered into frames with the holes between
splats closed -- what the annotator's "Prefill from 3D" shows (:func:`occufly.render.render_prefill`)
-- so a team painting in CVAT or Label Studio starts from it (``occufly masks export --prefill``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from occufly.errors import WorkspaceError
from occufly.lifting import load_labels
from occufly.render import render_prefill
from occufly.scene import Scene


def prefill_masks(workspace: str | Path, frames: Sequence[int], *, scene: Scene | None = None,
                  downscale: int = 1) -> dict[int, np.ndarray]:
    """frame index -> (H/s, W/s) uint8 raw ids of the prefill (0 where no labelled point is
    near). Raises WorkspaceError when the workspace has no lifted labels yet."""
    res = load_labels(workspace)
    if res is None:
        raise WorkspaceError(f"{workspace}: no lifted labels yet, so no prefill; lift masks "
                             f"first (occufly lift WS --masks DIR)")
    scene = scene if scene is not None else Scene.load(workspace)
    labels = np.asarray(res.labels)
    out = {}
    for fi in frames:
        cls, _depth, _filled = render_prefill(scene, labels, int(fi), scale=1.0 / downscale)
        out[int(fi)] = np.asarray(cls, np.uint8)
    return out
