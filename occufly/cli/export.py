"""Export and evaluation commands: ``export``, ``eval-ssc``, ``eval-depth``, ``preview``."""

from __future__ import annotations

import argparse
from pathlib import Path

from occufly.cli import command
from occufly.errors import OccuflyError
from occufly.export import export_dataset
from occufly.export.splits import parse_ratios
from occufly.grid import SceneGrid
from occufly.metrics import depth_table, evaluate_depth_dirs, evaluate_ssc_dirs, ssc_report
from occufly.parallel import get_executor
from occufly.preview import write_preview
from occufly.progress import tqdm_progress
from occufly.sampling import FrameGridSpec


def _shape(text: str) -> tuple[int, int, int]:
    try:
        v = tuple(int(x) for x in text.lower().replace("x", ",").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid shape must look like 192x128x128, got {text!r}") from None
    if len(v) != 3 or min(v) <= 0:
        raise argparse.ArgumentTypeError(f"grid shape must be three positive ints, got {text!r}")
    return v  # type: ignore[return-value]


def _alt_map(text: str) -> dict[int, int]:
    """"40:50,30:50" -> {40: 50, 30: 50}."""
    out = {}
    for part in filter(None, text.split(",")):
        try:
            a, b = part.split(":")
            out[int(a)] = int(b)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"--grid-for-altitude expects ALT:GRIDALT pairs like 40:50,30:50, got {part!r}") from None
    return out


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "export", _export, help="export per-frame SSC ground truth (OccuFly / SSCBench layout)")
    p.add_argument("workspace", type=Path, help="scene workspace")
    p.add_argument("out", type=Path, help="export root (created; an earlier export of this scene resumes)")
    p.add_argument("--scene-id", default="scene_01", help="scene folder / sequence name (default scene_01)")
    p.add_argument("--layout", choices=("occufly", "sscbench"), default="occufly")
    p.add_argument("--grid", type=Path, help="scene grid .npz (default WS/grid/scene_grid[_ALT].npz)")
    p.add_argument("--frames", type=str, help="frame indices, e.g. 0,3,7-12 (default all)")
    p.add_argument("--grid-shape", type=_shape, default=(192, 128, 128), help="frame grid X,Y,Z")
    p.add_argument("--voxel-size", type=float, default=0.5, help="frame grid voxel edge (m)")
    p.add_argument("--near", type=float, default=1.0, help="near clip distance (m)")
    p.add_argument("--far", type=float, help="far clip distance (m); default grid depth")
    p.add_argument("--grid-for-altitude", type=_alt_map,
                   help="which altitude's grid each altitude samples, e.g. 40:50,30:50 "
                        "(default: the highest altitude's grid)")
    p.add_argument("--split", choices=("train", "val", "test"),
                   help="the scene's split in the splits files (default: scenes 1-5 train, 6-7 val, "
                        "8-9 test by the scene number, else train)")
    p.add_argument("--split-by", choices=("altitude", "region", "ratio"),
                   help="split this scene's frames into train/val/test: altitude = lowest "
                        "altitude test, next val, the rest train; region = per altitude, "
                        "contiguous strips along the flight; ratio = per altitude, interleaved "
                        "(see --split-ratios)")
    p.add_argument("--split-ratios", help="train,val,test shares for --split-by region|ratio "
                                          "(default 0.8,0.1,0.1)")
    p.add_argument("--downsample-rule", choices=("occufly", "lmscnet"), default="occufly",
                   help="coarser grids: occufly = most common non-empty class; lmscnet = empty "
                        "when > 95%% of the block is empty or invalid (LMSCNet / MonoScene)")
    p.add_argument("--velodyne", action="store_true",
                   help="SSCBench layout: also write velodyne_points/data/<frame>.bin (float32 N x 4, "
                        "camera frame) from the MVS points each frame sees")
    p.add_argument("--workers", type=int, help="local worker processes (default 2; 1 = in-process)")
    p.add_argument("--dask", help="Dask scheduler address, e.g. tcp://host:8786 (or OCCUFLY_DASK)")

    p = command(sub, "eval-ssc", _eval_ssc, help="SSC metrics of predictions against a ground-truth export")
    p.add_argument("pred", type=Path,
                   help="predictions: an OccuFly-layout or SSCBench-layout folder (.label raw ids, or "
                        "_1_1.npy training ids), or <seq>/<frame>_1_1.npy | .label directly under it")
    p.add_argument("gt", type=Path, help="ground-truth export root (OccuFly or SSCBench layout)")
    p.add_argument("--format", choices=("text", "markdown", "latex", "json"), default="text",
                   help="table format: the per-altitude and per-class tables (default text)")

    p = command(sub, "eval-depth", _eval_depth, help="depth metrics of predicted depth maps against ground truth")
    p.add_argument("pred", type=Path, help="predicted 1/4-resolution depth maps: an OccuFly- or SSCBench-layout "
                                           "folder, or <seq>/<frame>.npy directly under it")
    p.add_argument("gt", type=Path, help="ground-truth export root (OccuFly or SSCBench layout)")
    p.add_argument("--max-depth", type=float, default=1000.0, help="ignore GT depth at or beyond (m)")

    p = command(sub, "preview", _preview, help="PNG preview of one exported frame")
    p.add_argument("export", type=Path, help="export root (OccuFly layout)")
    p.add_argument("--frame", required=True, help="frame id, e.g. 3 or 000003")
    p.add_argument("--out", type=Path,
                   help="PNG to write (default: EXPORT/previews/<scene>_<altitude>_<frame>.png)")
    p.add_argument("--panels", default="image,depth,grid,masks",
                   help="comma list of image, depth, grid, masks")
    p.add_argument("--height", type=int, default=256, help="panel height in pixels")


def _parse_frames(text: str | None) -> list[int] | None:
    if not text:
        return None
    out: list[int] = []
    for part in text.split(","):
        try:
            if "-" in part:
                a, b = part.split("-")
                out.extend(range(int(a), int(b) + 1))
            else:
                out.append(int(part))
        except ValueError:
            raise OccuflyError(f"--frames: expected indices like 0,3,7-12, got {part!r}") from None
    return out


def _split_ratios(text: str | None):
    return None if text is None else parse_ratios(text)


def _export(args: argparse.Namespace) -> dict:
    spec = FrameGridSpec(shape=args.grid_shape, voxel_size=args.voxel_size, near=args.near, far=args.far)
    grid = SceneGrid.load(args.grid) if args.grid else None
    with get_executor(args.dask, args.workers if args.workers is not None else 2) as ex, \
            tqdm_progress("export") as bar:
        res = export_dataset(args.workspace, args.out, scene_id=args.scene_id, layout=args.layout,
                             grid=grid, frames=_parse_frames(args.frames), executor=ex,
                             progress=bar, spec=spec, grid_for_altitude=args.grid_for_altitude,
                             split=args.split, split_by=args.split_by,
                             split_ratios=_split_ratios(args.split_ratios),
                             downsample_rule=args.downsample_rule,
                             velodyne=args.velodyne)
    if not args.json:
        res = {k: v for k, v in res.items() if k != "results"}
    return res


def _eval_ssc(args: argparse.Namespace):
    res = evaluate_ssc_dirs(args.pred, args.gt)
    return res if args.json else ssc_report(res, args.format)


def _eval_depth(args: argparse.Namespace):
    res = evaluate_depth_dirs(args.pred, args.gt, max_depth=args.max_depth)
    return res if args.json else depth_table(res)


def _preview(args: argparse.Namespace) -> dict:
    panels = tuple(p.strip() for p in args.panels.split(",") if p.strip())
    out = args.out
    if out is None:  # like grid-preview: a default next to the data, outside the dataset tree
        from occufly.preview import find_frame

        alt_dir, fid = find_frame(Path(args.export), str(args.frame))
        out = Path(args.export) / "previews" / f"{alt_dir.parent.name}_{alt_dir.name}_{fid}.png"
    return write_preview(args.export, args.frame, out, panels=panels, height=args.height)
