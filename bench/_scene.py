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


# the files of a workspace that hold its scene (a vote state beside them writes only lifting/)
SCENE_PARTS = ("scene.json", "taxonomy.json", "points", "visibility")


def scratch_workspace(path: Path, ws: Path) -> Path:
    """``path``, emptied, with the scene files of workspace ``ws`` linked in: a vote state
    opened there shares the scene's arrays and writes only its own ``lifting/``."""
    import shutil

    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    for name in SCENE_PARTS:
        (path / name).symlink_to(Path(ws).resolve() / name)
    return path


def greedy_truth(synthetic: Path, ws: Path):  # noqa: ANN201
    """A synthetic scene imported into ``ws``: (scene, point truth, the greedy rho 0.99
    selection, frame -> its exact truth mask); exits naming both folders when the truth does
    not belong to the workspace."""
    import numpy as np

    from occufly.io.masks import read_mask
    from occufly.scene import Scene
    from occufly.selection import select_frames

    scene = Scene.load(ws)
    truth = np.load(synthetic / "truth" / "point_labels.npy")
    if len(truth) != scene.n_points:
        raise SystemExit(f"{synthetic}: truth has {len(truth)} points, {ws} {scene.n_points}")
    sel = select_frames(scene, mode="greedy", target_coverage=0.99)
    exact = {fi: read_mask(synthetic / "truth" / "masks" / f"{scene.frames[fi].stem}.png",
                           scene.frames[fi], scene.taxonomy) for fi in sel.frames}
    return scene, truth, sel, exact
