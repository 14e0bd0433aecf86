"""Lifting output: per-point labels, confidence and origin, and their files in
``ws/lifting/`` (labels.npy written last, so a reader that finds it finds the rest)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from occufly.fsutil import atomic_save_npy, atomic_write_text
from occufly.taxonomy import Taxonomy

LIFT_DIR = "lifting"

ORIGIN_NONE = 0
ORIGIN_DIRECT = 1
ORIGIN_FILLED = 2
ORIGIN_DENOISED = 3
ORIGIN_NAMES = {ORIGIN_NONE: "none", ORIGIN_DIRECT: "direct", ORIGIN_FILLED: "filled",
                ORIGIN_DENOISED: "denoised"}


@dataclass
class LiftResult:
    """Output of the fill/denoise passes.

    labels: (N,) uint8 raw class ids (0 = no label); confidence: (N,) float32 in [0, 1];
    origin: (N,) uint8 (0 none, 1 direct, 2 filled, 3 denoised); stats: timings and counts.
    """

    labels: np.ndarray
    confidence: np.ndarray
    origin: np.ndarray
    stats: dict = field(default_factory=dict)

    def summary(self, taxonomy: Taxonomy | None = None) -> dict:
        counts = np.bincount(np.asarray(self.origin), minlength=4)
        out = {
            "points": int(len(self.labels)),
            "origin": {ORIGIN_NAMES[i]: int(counts[i]) for i in range(4)},
            "mean_confidence": float(np.mean(self.confidence)) if len(self.confidence) else 0.0,
        }
        if taxonomy is not None:
            per = np.bincount(np.asarray(self.labels), minlength=256)
            out["classes"] = {c.name: int(per[c.id]) for c in taxonomy.classes if per[c.id]}
        out.update(self.stats)
        return out


def save_result(ws: str | Path, result: LiftResult) -> None:
    d = Path(ws) / LIFT_DIR
    # labels.npy is what readers test for: write it last so a reader that finds it finds
    # the companion arrays too (the first fill used to expose labels without confidence)
    atomic_save_npy(d / "confidence.npy", result.confidence.astype(np.float32))
    atomic_save_npy(d / "origin.npy", result.origin.astype(np.uint8))
    atomic_write_text(d / "labels.json", json.dumps(result.stats, indent=1, default=_jsonable))
    atomic_save_npy(d / "labels.npy", result.labels.astype(np.uint8))


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def load_labels(ws: str | Path) -> LiftResult | None:
    """The latest fill/denoise output of workspace ``ws`` (memory-mapped), or None."""
    d = Path(ws) / LIFT_DIR
    if not (d / "labels.npy").is_file():
        return None
    stats = {}
    if (d / "labels.json").is_file():
        try:
            stats = json.loads((d / "labels.json").read_text())
        except json.JSONDecodeError:
            stats = {}
    return LiftResult(
        labels=np.load(d / "labels.npy", mmap_mode="r"),
        confidence=np.load(d / "confidence.npy", mmap_mode="r"),
        origin=np.load(d / "origin.npy", mmap_mode="r"),
        stats=stats,
    )
