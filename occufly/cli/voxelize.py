"""CLI: ``voxelize``, ``eval-grid``, ``grid-preview`` (densification and the scene grid)."""

from __future__ import annotations

import argparse
from pathlib import Path

from occufly.cli import command
from occufly.densify.evaluate import evaluate_grids
from occufly.densify.pipeline import DensifyOptions, voxelize_workspace
from occufly.densify.preview import save_preview
from occufly.errors import OccuflyError
from occufly.grid import SceneGrid
from occufly.progress import tqdm_progress
from occufly.taxonomy import Taxonomy, default_taxonomy
from occufly.workspace import Workspace


def _voxelize(args: argparse.Namespace) -> dict:
    scale = None if args.min_points_scale == "auto" else _positive_float(args.min_points_scale)
    if args.smooth_radius < 0:
        from occufly.errors import OccuflyError

        raise OccuflyError(f"--smooth-radius: expected a number >= 0 (voxel edges), got {args.smooth_radius}")
    opts = DensifyOptions(
        voxel_size=args.voxel, carve=not args.no_carve, poisson=not args.no_poisson, min_points_scale=scale,
        free_space=not args.no_free_space, smooth_radius=args.smooth_radius,
    )
    with tqdm_progress("voxelize") as bar:
        report = voxelize_workspace(args.workspace, labels_path=args.labels, options=opts, out_path=args.out, progress=bar)
    if args.preview:
        _write_preview(Path(report["grid"]), Path(args.workspace), Path(args.preview))
        report["preview"] = args.preview
    return report


def _positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = -1.0
    if not v > 0:
        raise OccuflyError(f"--min-points-scale: expected 'auto' or a number > 0, got {text!r}")
    return v


def _load_taxonomy(ws: Path | None):
    if ws is not None and Workspace(ws).taxonomy_json.is_file():
        return Taxonomy.load(Workspace(ws).taxonomy_json)
    return default_taxonomy()


def _grid_path(arg: str) -> Path:
    """A grid file, or a workspace whose grid/scene_grid.npz is meant."""

    p = Path(arg)
    return Workspace(p).grid_path() if p.is_dir() else p


def _eval(args: argparse.Namespace) -> dict:
    ws = Path(args.workspace)
    pred_path = Path(args.grid) if args.grid else _grid_path(str(ws))
    pred = SceneGrid.load(pred_path)
    if args.truth:
        truth_path = _grid_path(args.truth)
    else:
        from occufly.errors import InputFormatError

        truth_path = Workspace(ws).truth_grid_path
        if not truth_path.is_file():
            raise InputFormatError(f"{truth_path}: no truth grid in the workspace; pass --truth GRID")
    truth = SceneGrid.load(truth_path)
    out = evaluate_grids(pred, truth, _load_taxonomy(ws if ws.is_dir() else None), region=args.region)
    out["pred"] = str(pred_path)
    out["truth"] = str(truth_path)
    return out


def _write_preview(grid_path: Path, ws: Path | None, out: Path) -> None:
    save_preview(SceneGrid.load(grid_path), _load_taxonomy(ws), out)


def _preview(args: argparse.Namespace) -> dict:
    src = Path(args.source)
    ws = src if src.is_dir() else None
    grid_path = _grid_path(args.source)
    out = Path(args.out) if args.out else grid_path.with_suffix(".png")
    _write_preview(grid_path, ws, out)
    return {"grid": str(grid_path), "preview": str(out)}


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "voxelize", _voxelize, help="densify the labelled cloud into WS/grid/scene_grid.npz")
    p.add_argument("workspace", help="scene workspace")
    p.add_argument("--voxel", type=float, default=0.5, help="voxel edge in metres (default 0.5)")
    p.add_argument("--labels", help="(N,) uint8 point labels .npy (default WS/lifting/labels.npy)")
    p.add_argument("--out", help="grid path (default WS/grid/scene_grid.npz)")
    p.add_argument("--no-carve", action="store_true", help="ablation: instance points binned, no DBSCAN/carving")
    p.add_argument("--no-poisson", action="store_true", help="ablation: ground points binned, no Poisson")
    p.add_argument("--no-free-space", action="store_true",
                   help="ablation: keep carved voxels the survey's cameras saw through")
    p.add_argument("--smooth-radius", type=float, default=3.0,
                   help="instance points: plane-projection radius in voxel edges, capped at the "
                   "class's DBSCAN eps (default 3; 0 = off)")
    p.add_argument("--preview", help="also write a PNG preview here")
    p.add_argument(
        "--min-points-scale", default="auto",
        help="multiply the taxonomy's DBSCAN minPts; 'auto' (default) scales by the cloud's "
        "surface density relative to 400 points/m^2 (1 for denser clouds); 1 = the table as-is",
    )

    p = command(sub, "eval-grid", _eval, help="completion IoU, per-class IoU and mIoU vs a truth grid")
    p.add_argument("workspace", help="scene workspace (its grid/scene_grid.npz and taxonomy)")
    p.add_argument("--truth", help="truth grid .npz (or a folder holding grid/scene_grid.npz); "
                   "default WS/truth/scene_grid.npz")
    p.add_argument("--grid", help="evaluate this grid instead of the workspace's")
    p.add_argument("--region", choices=("truth", "union"), default="truth",
                   help="evaluate inside the truth grid's extent (default) or the union of both")

    p = command(sub, "grid-preview", _preview, help="PNG preview (top-down + oblique) of a scene grid")
    p.add_argument("source", help="workspace or grid .npz")
    p.add_argument("--out", help="PNG path (default: next to the grid)")
