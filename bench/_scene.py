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


def ensure_seeded_scene(cache: Path, preset: str, seed: int, synthetic: Path | None = None
                        ) -> tuple[Path, Path]:
    """The synthetic scene ``preset`` / ``seed`` (``synthetic``, default ``cache/<preset>-<seed>``,
    with its point truth) and its workspace beside it, each made once in a subprocess."""
    syn = synthetic or cache / f"{preset}-{seed}"
    ws = cache / f"{syn.name}-{preset}-{seed}-ws"
    py = sys.executable
    root = Path(__file__).resolve().parents[1]
    if not (syn / "truth" / "point_labels.npy").is_file():
        subprocess.run([py, "-m", "occufly.cli", "synth", str(syn), "--preset", preset,
                        "--seed", str(seed), "--force", "--json"], check=True, cwd=root,
                       stdout=subprocess.DEVNULL)
    if not (ws / "scene.json").is_file():
        subprocess.run([py, "-m", "occufly.cli", "import", str(syn), "--workspace", str(ws),
                        "--force", "--json"], check=True, cwd=root, stdout=subprocess.DEVNULL)
    return syn, ws
