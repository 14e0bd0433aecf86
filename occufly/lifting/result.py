"""Lifting output: per-point labels, confidence and origin, and their files in
``ws/lifting/`` (labels.npy written last, so a reader that finds it finds the rest)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occufly.taxonomy import Taxonomy
from occufly.workspace import LIFTING_DIR as LIFT_DIR  # noqa: F401 - the old public name
from occufly.workspace import Workspace

ORIGIN_NONE = 0
ORIGIN_DIRECT = 1
ORIGIN_FILLED = 2
ORIGIN_DENOISED = 3
ORIGIN_CORRECTED = 4  # a reviewer's correction (occufly.lifting.corrections)
ORIGIN_NAMES = {ORIGIN_NONE: "none", ORIGIN_DIRECT: "direct", ORIGIN_FILLED: "filled",
                ORIGIN_DENOISED: "denoised", ORIGIN_CORRECTED: "corrected"}


@dataclass
class LiftResult:
    """Output of the fill/denoise passes.

    labels: (N,) uint8 raw class ids (0 = no label); confidence: (N,) float32 in [0, 1];
    origin: (N,) uint8 (0 none, 1 direct, 2 filled, 3 denoised, 4 corrected by a reviewer);
    stats: timings and counts.
    """

    labels: np.ndarray
    confidence: np.ndarray
    origin: np.ndarray
    stats: dict = field(default_factory=dict)

    def summary(self, taxonomy: Taxonomy | None = None) -> dict:
        counts = np.bincount(np.asarray(self.origin), minlength=len(ORIGIN_NAMES))
        out = {
            "points": int(len(self.labels)),
            "origin": {ORIGIN_NAMES[i]: int(counts[i]) for i in range(len(ORIGIN_NAMES))},
            "mean_confidence": float(np.mean(self.confidence)) if len(self.confidence) else 0.0,
        }
        if taxonomy is not None:
            per = np.bincount(np.asarray(self.labels), minlength=256)
            out["classes"] = {c.name: int(per[c.id]) for c in taxonomy.classes if per[c.id]}
        out.update(self.stats)
        return out


def save_result(ws: str | Path, result: LiftResult) -> None:
    """Store a fill result in workspace ``ws`` (labels last: :meth:`Workspace.write_labels`)."""
    Workspace(ws).write_labels(result.labels, result.confidence, result.origin, result.stats)
