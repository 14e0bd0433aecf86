"""Core commands: ``import`` a reconstruction into a workspace, ``info`` on a workspace."""

from __future__ import annotations

import argparse
from pathlib import Path

from occufly.cli import command
from occufly.io.importer import import_scene
from occufly.progress import tqdm_progress
from occufly.scene import Scene
from occufly.workspace import Workspace


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "import", _import, help="import a reconstruction into a scene workspace")
    p.add_argument("source", type=Path,
                   help="the reconstruction: a COLMAP folder (model, images/, dense/), an "
                        "OpenDroneMap project folder, a Metashape camera XML or a Pix4D project "
                        "folder (kind detected; --format forces one)")
    p.add_argument("--format", dest="fmt", choices=("colmap", "odm", "metashape", "pix4d"),
                   help="the project kind, when detection should not decide")
    p.add_argument("--crs", type=str,
                   help="CRS of the cloud when its file declares none (EPSG:32633, WKT or "
                        "PROJ); LAS/LAZ CRS records and a .prj beside a PLY are read")
    p.add_argument("--workspace", "-w", type=Path, required=True, help="workspace folder to create")
    p.add_argument("--cloud", type=Path,
                   help="dense cloud (.ply/.las/.laz); default COLMAP dense/fused.ply, ODM "
                        "odm_georeferencing/odm_georeferenced_model.laz, Pix4D "
                        "2_densification/point_cloud/*_densified_point_cloud.las|laz")
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
    p.add_argument("--workers", type=int, default=1,
                   help="processes computing the visibility, frame blocks in parallel (same "
                        "output for any number; default 1)")
    p.add_argument("--scale", type=float, default=None,
                   help="metres per model unit for a COLMAP model that is neither "
                        "georeferenced nor geotagged (1 if it is metric already); without it "
                        "such a model is aligned to its images' EXIF GPS")
    p.add_argument("--force", action="store_true", help="replace an existing workspace")

    p = command(sub, "info", _info, help="summarise a scene workspace")
    p.add_argument("workspace", type=Path)


def _import(args: argparse.Namespace) -> dict:
    nominal = [float(v) for v in args.altitudes.split(",")] if args.altitudes else None
    with tqdm_progress("import") as bar:
        scene = import_scene(
            args.source, args.workspace, cloud=args.cloud, depth_maps=args.depth_maps,
            images=args.images, taxonomy=args.taxonomy, nominal_altitudes=nominal,
            rel_tol=args.rel_tol, visibility=args.visibility, fmt=args.fmt, crs=args.crs,
            scale=args.scale, overwrite=args.force, progress=bar, workers=args.workers,
        )
    meta = scene.meta
    return {"workspace": str(args.workspace), "format": meta.get("format"),
            "visibility_source": meta.get("visibility_source"),
            # what the importer computed itself (ODM/Metashape/Pix4D export no visibility)
            "visibility_computed": meta.get("visibility_depth_test"),
            "visibility_from_reconstruction": meta.get("visibility_mode") != "depth",
            "notes": meta.get("import_notes", []),
            "warnings": meta.get("import_warnings", []),
            "georeferencing": {k: v for k, v in (meta.get("georeferencing") or {}).items()
                               if k != "geotags"} or None,
            **scene.summary()}


def _info(args: argparse.Namespace) -> dict:
    ws = Workspace(args.workspace)

    scene = Scene.load(ws.root)
    out = {"workspace": str(args.workspace), **scene.summary()}
    out["steps"] = ws.steps()
    return out
