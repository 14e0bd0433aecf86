"""Shared by the benchmarks: generate and import a synthetic scene once, in subprocesses."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def ensure_scene(root: Path, preset: str) -> tuple[Path, Path]:
    """``root/synth_<preset>`` (synthetic output) and ``root/ws_<preset>`` (its workspace)."""
    out = root / f"synth_{preset}"
    ws = root / f"ws_{preset}"
    py = sys.executable
    if not (out / "truth" / "scene_grid.npz").is_file():
        subprocess.run([py, "-m", "occufly.cli", "synth", str(out), "--preset", preset, "--force"],
                       check=True, stdout=subprocess.DEVNULL)
    if not (ws / "scene.json").is_file():
        subprocess.run([py, "-m", "occufly.cli", "import", str(out), "--workspace", str(ws), "--force"],
                       check=True, stdout=subprocess.DEVNULL)
    return out, ws
