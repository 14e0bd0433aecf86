"""``occufly masks import`` / ``occufly masks export``: masks in and out of CVAT, COCO,
Label Studio and plain PNGs (occufly.io.mask_interchange), the 3D prefill as pre-annotations."""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

from occufly.cli import command
from occufly.errors import InputFormatError, MaskError
from occufly.io.mask_interchange import FORMATS, load_class_map, read_masks, write_masks
from occufly.io.masks import encode_mask_png, read_mask
from occufly.scene import Scene

_FORMAT_HELP = ("cvat (CVAT for images 1.1 or Segmentation mask 1.1, told by the files), "
                "cvat_images, cvat_mask, coco (instances: polygons or RLE), coco_panoptic, "
                "labelstudio (JSON export: brush RLE and polygons), png (indexed or colour "
                "PNGs named after the frames, class map labelmap.txt / dataset_meta.json / "
                "classes.json beside them; without one the values are raw class ids)")


def register(sub: argparse._SubParsersAction) -> None:
    grp = sub.add_parser("masks", help="masks in and out of CVAT, COCO, Label Studio, PNG")
    msub = grp.add_subparsers(dest="masks_command", required=True)
    p = command(msub, "import", _import,
                help="read masks painted in another tool into <frame stem>.png masks")
    p.add_argument("workspace", type=Path)
    p.add_argument("archive", type=Path, help="the tool's export: a zip, a folder or a file")
    p.add_argument("--format", dest="fmt", required=True, choices=FORMATS, help=_FORMAT_HELP)
    p.add_argument("--map", dest="class_map", type=Path,
                   help="class mapping (JSON/YAML) {external class name: taxonomy class name, "
                        "id, \"ignore\" or \"unpainted\"} where the names differ")
    p.add_argument("--out", type=Path,
                   help="folder for the masks (default WS/masks); lift them with "
                        "`occufly lift WS --masks DIR`")

    p = command(msub, "export", _export,
                help="write masks or the 3D prefill per frame for another tool")
    p.add_argument("workspace", type=Path)
    p.add_argument("out", type=Path, help="a .zip file, or a new folder")
    p.add_argument("--format", dest="fmt", required=True, choices=FORMATS, help=_FORMAT_HELP)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--masks", type=Path, help="folder of <frame stem>.png masks to export")
    src.add_argument("--prefill", action="store_true",
                     help="export the lifted labels rendered into the frames (the annotator's "
                          "prefill), as pre-annotations")
    p.add_argument("--frames", nargs="*",
                   help="frame names / stems (default: every mask, or every frame with --prefill)")
    p.add_argument("--downscale", type=int, default=1,
                   help="render the prefill at 1/s of the image size (written at full size)")


def _import(args: argparse.Namespace) -> dict:
    scene = Scene.load(args.workspace)
    cmap = load_class_map(args.class_map) if args.class_map else None
    res = read_masks(args.archive, args.fmt, scene.frames, scene.taxonomy, class_map=cmap)
    if not res.masks:
        raise MaskError(f"{args.archive}: no painted mask in the {res.tool} export "
                        f"({len(res.skipped_empty)} image(s) without annotations): nothing to "
                        f"import")
    out = args.out or args.workspace / "masks"
    out.mkdir(parents=True, exist_ok=True)
    # every mask is written beside the folder first, then moved in: all of them or none
    with tempfile.TemporaryDirectory(dir=out, prefix=".import-") as tmp:
        staged = []
        for fi, mask in sorted(res.masks.items()):
            p = Path(tmp) / f"{scene.frames[fi].stem}.png"
            p.write_bytes(encode_mask_png(mask))
            staged.append(p)
        for p in staged:
            shutil.move(str(p), out / p.name)
    return {"format": res.fmt, "source": f"imported from {res.tool}", "out": str(out),
            "frames_imported": len(res.masks),
            "frames": [scene.frames[fi].name for fi in sorted(res.masks)],
            "skipped_without_annotations": len(res.skipped_empty), "classes": res.classes,
            "next": f"occufly lift {args.workspace} --masks {out}"}


def _frames(scene, names: list[str]) -> list[int]:  # noqa: ANN001
    out, unknown = [], []
    for n in names:
        try:
            out.append(scene.frame_index(n))
        except KeyError:
            unknown.append(n)
    if unknown:
        raise InputFormatError(f"--frames: {', '.join(unknown)} name no frame of the scene")
    return out


def _export(args: argparse.Namespace) -> dict:
    scene = Scene.load(args.workspace)
    if args.prefill:
        from occufly.export.prefill_masks import prefill_masks

        if args.downscale < 1:
            raise InputFormatError(f"--downscale must be >= 1, got {args.downscale}")
        frames = _frames(scene, args.frames) if args.frames else range(len(scene.frames))
        masks = prefill_masks(args.workspace, frames, scene=scene, downscale=args.downscale)
    else:
        if not args.masks.is_dir():
            raise InputFormatError(f"{args.masks}: mask folder does not exist")
        by_stem = {f.stem: i for i, f in enumerate(scene.frames)}
        files = {by_stem[p.stem]: p for p in sorted(args.masks.glob("*.png")) if p.stem in by_stem}
        unknown = [p.name for p in sorted(args.masks.glob("*.png")) if p.stem not in by_stem]
        if unknown:
            raise MaskError(f"{args.masks}: mask(s) {', '.join(unknown)} name no frame of the "
                            f"scene; masks must be named <image stem>.png")
        if args.frames:
            want = set(_frames(scene, args.frames))
            files = {fi: p for fi, p in files.items() if fi in want}
        masks = {fi: read_mask(p, scene.frames[fi], scene.taxonomy) for fi, p in files.items()}
    if not masks:
        raise MaskError("nothing to export: no mask PNG named after a frame of the scene"
                        + (" among --frames" if args.frames else ""))
    res = write_masks(args.out, args.fmt, masks, scene.frames, scene.taxonomy,
                      prediction=args.prefill)
    res["kind"] = "prefill" if args.prefill else "masks"
    return res
