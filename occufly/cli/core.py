"""Core commands: ``import`` a reconstruction into a workspace, ``info`` on a workspace."""

from __future__ import annotations

import argparse
from pathlib import Path

from occufly.cli import command
from occufly.progress import tqdm_progress


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "import", _import, help="import a reconstruction into a scene workspace")
    p.add_argument("source", type=Path, help="reconstruction folder (COLMAP model, images/, dense/)")
    p.add_argument("--workspace", "-w", type=Path, required=True, help="workspace folder to create")
    p.add_argument("--cloud", type=Path, help="dense cloud (.ply/.las/.laz); default dense/fused.ply")
    p.add_argument("--depth-maps", type=Path, help="folder of COLMAP *.geometric.bin depth maps")
    p.add_argument("--images", type=Path, help="image folder; default SOURCE/images")
    p.add_argument("--taxonomy", type=Path, help="class table (.json/.yaml); default OccuFly")
    p.add_argument("--altitudes", type=str, help="nominal flight altitudes, e.g. 50,40,30")
    p.add_argument("--rel-tol", type=float, default=0.02, help="depth-test relative tolerance")
    p.add_argument("--visibility", choices=("union", "vis", "depth"), default="union",
                   help="which frames see a point: union (default) = the reconstruction's "
                        "lists (fused.ply.vis / tracks) united with a depth test against the "
                        "MVS depth maps or depth rendered from the cloud; vis = the lists "
                        "only; depth = the depth test only")
    p.add_argument("--force", action="store_true", help="replace an existing workspace")

    p = command(sub, "info", _info, help="summarise a scene workspace")
    p.add_argument("workspace", type=Path)


def _import(args: argparse.Namespace) -> dict:
    from occufly.io.importer import import_scene

    nominal = [float(v) for v in args.altitudes.split(",")] if args.altitudes else None
    with tqdm_progress("import") as bar:
        scene = import_scene(
            args.source, args.workspace, cloud=args.cloud, depth_maps=args.depth_maps,
            images=args.images, taxonomy=args.taxonomy, nominal_altitudes=nominal,
            rel_tol=args.rel_tol, visibility=args.visibility, overwrite=args.force, progress=bar,
        )
    return {"workspace": str(args.workspace), **scene.summary()}


def _info(args: argparse.Namespace) -> dict:
    from occufly.workspace import Workspace

    ws = Workspace(args.workspace)
    scene = ws.scene()
    out = {"workspace": str(args.workspace), **scene.summary()}
    out["steps"] = ws.steps()
    return out
