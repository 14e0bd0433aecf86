"""Lifting commands: ``select``, ``lift``, ``agreement``, ``eval-points``, ``export-points``."""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from occufly.cli import command, emit
from occufly.errors import InputFormatError, MaskError, WorkspaceError
from occufly.fsutil import atomic_write_text
from occufly.io.masks import read_mask
from occufly.io.pointcloud_export import export_scene_points
from occufly.lifting import LiftParams, RobustParams, VoteStore, load_labels
from occufly.lifting.confusion import ConfusionParams
from occufly.lifting.nextbest import propose_for_workspace
from occufly.lifting.quality import quality_report, summary_text, workspace_truth
from occufly.lifting.regions import RegionParams
from occufly.metrics import evaluate_points
from occufly.progress import tqdm_progress
from occufly.render import agreement, disagreement_image, merge_agreements, render_for_mask
from occufly.scene import Scene
from occufly.selection import select_frames
from occufly.workspace import Workspace


def _cell(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected metres or 'auto', got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive edge in metres, got {text!r}")
    return v


def register(sub: argparse._SubParsersAction) -> None:
    p = command(sub, "select", _select, help="choose the frames to annotate (stratified / greedy)")
    p.add_argument("workspace", type=Path)
    p.add_argument("--cell", type=_cell, default=25.0,
                   help="ground cell edge in metres (23-28), or 'auto' (greedy modes: the edge of "
                   "23-28 m giving the fewest frames at the target coverage)")
    p.add_argument("--mode", choices=("stratified", "greedy", "cover"), default="stratified",
                   help="greedy: stratified + coverage-greedy; cover: coverage-greedy only")
    p.add_argument("--no-prune", action="store_true",
                   help="keep frames the target coverage does not need (greedy modes)")
    p.add_argument("--target-coverage", type=float, default=0.99, help="greedy target rho")
    p.add_argument("--altitude", type=int, help="only frames at this nominal altitude (m)")
    p.add_argument("--next", type=int, metavar="K",
                   help="on a workspace with votes and lifted labels: propose the K frames "
                        "without a mask whose masks would most settle the contested and "
                        "uncertain labels, each with why (writes next_frames.json; exits 2 "
                        "when nothing is contested)")

    p = command(sub, "lift", _lift, help="lift masks (DIR/<image stem>.png) into point labels")
    p.add_argument("workspace", type=Path)
    p.add_argument("--masks", type=Path, required=True, help="folder of <image stem>.png masks")
    p.add_argument("--sync", action="store_true",
                   help="also remove the votes of frames that have no mask in DIR")
    p.add_argument("--method", choices=("voxel", "exact"), default="voxel",
                   help="kNN fill/denoise method (exact = plain cKDTree baseline)")
    p.add_argument("--no-fill", action="store_true", help="update the votes only")
    p.add_argument("--far-fill", action="store_true",
                   help="let points with no labelled point within 3 m take the vote of their 100 "
                   "nearest labelled points at any distance, at the lowest confidence (default "
                   "since issue 23: they stay unlabelled, the fill does not extrapolate)")
    p.add_argument("--no-far-fill", action="store_true",
                   help="the default (kept for older scripts): points with no labelled point "
                   "within 3 m stay unlabelled")
    p.add_argument("--confirm-views", type=int, default=2,
                   help="a direct label with this many agreeing views (and margin >= 0.5) survives "
                   "the denoise (0 = off)")
    p.add_argument("--keep-share", type=float, default=0.25,
                   help="denoise: a point keeps its class if it holds this share of its k=200 "
                        "neighbours (0 = the paper's rule: always the dominant class)")
    p.add_argument("--regions", action="store_true",
                   help="count a mask's painted regions that the other views contradict as a "
                        "whole (a parking lot painted road where the others see parking lot) "
                        "as those views say, then decide again (issue 37; docs/lifting.md)")
    p.add_argument("--per-author", action="store_true",
                   help="decide the votes with one confusion matrix per painter (a painter who "
                        "swaps two look-alike classes is outvoted where the others see the same "
                        "points; issue 37) instead of one for all masks; not with --regions")
    p.add_argument("--authors", type=Path, metavar="JSON",
                   help="with --regions or --per-author: a JSON object of mask file stem -> who "
                        "painted it (default: every mask its own painter); one painter's masks "
                        "count as one view against a region and share one confusion matrix")

    p = command(sub, "agreement", _agreement,
                help="pixel agreement of the rendered labels with masks")
    p.add_argument("workspace", type=Path)
    p.add_argument("--masks", type=Path, required=True, help="folder of <image stem>.png masks")
    p.add_argument("--frames", nargs="*", help="frame names/stems/indices (default: all masks)")
    p.add_argument("--held-out", action="store_true",
                   help="only frames whose masks were not lifted")
    p.add_argument("--out", type=Path, help="write <stem>.disagreement.png overlays here")

    p = command(sub, "eval-points", _eval_points,
                help="per-point accuracy / IoU against truth labels")
    p.add_argument("workspace", type=Path)
    p.add_argument("--truth", type=Path, required=True,
                   help="(N,) uint8 .npy labels in the source cloud's point order")

    p = command(sub, "report", _report,
                help="quality report of the lifted labels: leave-one-out agreement, independent "
                     "coverage, multi-view and contested shares, calibration, per class "
                     "(--json: the quality.json object)")
    p.add_argument("workspace", type=Path)
    p.add_argument("--truth", type=Path,
                   help="(N,) uint8 .npy point truth in the source cloud's order (e.g. a synthetic "
                        "scene's truth/point_labels.npy): measures the calibration (ECE); default "
                        "WS/truth/point_labels.npy when the workspace keeps one (the demo's)")
    p.add_argument("--no-loo", action="store_true",
                   help="skip the per-frame leave-one-out agreement (one local k-NN per frame)")
    p.add_argument("--out", type=Path, help="also write the report as JSON to this file")

    p = command(sub, "export-points", _export_points,
                help="export the semantic cloud (.ply/.las/.laz/.copc.laz, georeferenced; LAS/COPC with "
                     "ASPRS codes, the class id and the class table)")
    p.add_argument("workspace", type=Path)
    p.add_argument("out", type=Path)


# ---- select ------------------------------------------------------------------------------
def _select(args: argparse.Namespace) -> dict | int:
    if args.next is not None:
        return _select_next(args)
    scene = Scene.load(args.workspace)
    res = select_frames(scene, cell=args.cell, mode=args.mode,
                        target_coverage=args.target_coverage, altitude=args.altitude,
                        prune_redundant=not args.no_prune)
    out = res.to_dict()
    atomic_write_text(args.workspace / "selection.json", json.dumps(out, indent=1))
    out["written"] = str(args.workspace / "selection.json")
    return out


def _select_next(args: argparse.Namespace) -> dict | int:
    if args.next < 1:
        raise InputFormatError(f"--next: expected a number of frames >= 1, got {args.next}")
    res = propose_for_workspace(args.workspace, args.next)
    out = res.to_dict()
    if not res.frames:
        emit(out, getattr(args, "json", False))
        print(f"occufly select --next: {res.message}", file=sys.stderr)
        return 2
    atomic_write_text(args.workspace / "next_frames.json", json.dumps(out, indent=1))
    out["written"] = str(args.workspace / "next_frames.json")
    return out


# ---- lift --------------------------------------------------------------------------------
def _mask_files(scene, masks: Path) -> dict[int, Path]:
    """frame index -> mask path; every PNG in ``masks`` must name a frame (MaskError)."""
    if not masks.is_dir():
        raise InputFormatError(f"{masks}: mask folder does not exist")
    by_stem = {f.stem: i for i, f in enumerate(scene.frames)}
    out: dict[int, Path] = {}
    unknown = []
    for p in sorted(masks.iterdir()):
        if p.suffix.lower() != ".png" or p.name.startswith("."):
            continue
        if p.stem not in by_stem:
            unknown.append(p)
            continue
        out[by_stem[p.stem]] = p
    if unknown:
        raise MaskError(
            f"{unknown[0]}: mask for an unknown frame {unknown[0].stem!r}"
            + (f" (and {len(unknown) - 1} more)" if len(unknown) > 1 else "")
            + "; masks must be named <image stem>.png after a frame of the scene"
        )
    return out


def _authors(path: Path, scene) -> dict[int, str]:  # noqa: ANN001
    """frame index -> annotator from a JSON object of mask file stem -> annotator name."""
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputFormatError(f"{path}: expected a JSON object of mask stem -> annotator ({e})") from None
    if not isinstance(raw, dict) or not all(isinstance(v, (str, int)) for v in raw.values()):
        raise InputFormatError(f"{path}: expected a JSON object of mask stem -> annotator name")
    by_stem = {f.stem: i for i, f in enumerate(scene.frames)}
    unknown = [k for k in raw if k not in by_stem]
    if unknown:
        raise InputFormatError(f"{path}: {unknown[0]!r} is not a frame of the scene "
                               f"({len(unknown)} unknown); expected <image stem> keys")
    return {by_stem[k]: str(v) for k, v in raw.items()}


def _robust_params(args: argparse.Namespace) -> RobustParams | None:
    """--regions / --per-author as the robust decision's parameters (None: the default)."""
    if args.regions:
        return RobustParams(regions=RegionParams())
    if args.per_author:
        return RobustParams(confusion=ConfusionParams())
    return None


def _lift(args: argparse.Namespace) -> dict:
    if args.confirm_views < 0:
        raise InputFormatError(f"--confirm-views: expected a number of views >= 0 (0 = off), got {args.confirm_views}")
    if not 0 <= args.keep_share <= 1:
        raise InputFormatError(f"--keep-share: expected a share in [0, 1], got {args.keep_share}")
    if args.regions and args.per_author:
        raise InputFormatError("--regions and --per-author: choose one (the per-painter model "
                               "decides by painter itself)")
    if args.authors and not (args.regions or args.per_author):
        raise InputFormatError(f"--authors {args.authors}: only used with --regions or "
                               "--per-author (the default decision does not tell painters apart)")
    scene = Scene.load(args.workspace)
    files = _mask_files(scene, args.masks)
    annotators = _authors(args.authors, scene) if args.authors else None
    state = VoteStore.open(args.workspace, scene)
    included = state.included_versions()
    if not files and not (args.sync and included):
        raise InputFormatError(
            f"{args.masks}: no mask to lift: expected PNGs named after frames of the scene, "
            f"<image stem>.png (e.g. {scene.frames[0].stem}.png)")
    todo = []
    painted = 0
    for fi, path in files.items():  # validate everything before touching the votes
        data = path.read_bytes()
        version = hashlib.sha256(data).hexdigest()[:16]
        if included.get(fi) == version:
            continue
        painted += int(read_mask(data, scene.frames[fi], scene.taxonomy, name=str(path)).any())
        todo.append((fi, path, version))
    if todo and not painted and len(todo) == len(files) and not included:
        raise InputFormatError(
            f"{args.masks}: all {len(files)} masks are empty (no painted pixel; 0 = unpainted): "
            f"nothing to lift; expected masks with class ids painted")
    changed = 0
    with tqdm_progress("votes") as bar:
        for k, (fi, path, version) in enumerate(todo):
            mask = read_mask(path, scene.frames[fi], scene.taxonomy)
            changed += state.set_mask(fi, mask, version=version, name=str(path))["points_changed"]
            bar((k + 1) / max(1, len(todo)), path.name)
    removed = []
    if args.sync:
        for fi in list(state.included_versions()):
            if fi not in files:
                state.remove_mask(fi)
                removed.append(scene.frames[fi].name)
    out = {
        "masks": len(files),
        "updated": len(todo),
        "unchanged": len(files) - len(todo),
        "removed": removed,
        "direct_label_changes": changed,
        "annotated_frames": len(state.included_versions()),
    }
    direct = state.direct_labels()
    out["directly_labelled"] = float((direct > 0).mean()) if len(direct) else 0.0
    if not args.no_fill:
        with tqdm_progress("fill/denoise") as bar:
            res = state.fill_and_denoise(progress=bar, annotators=annotators, params=LiftParams(
                method=args.method, denoise_keep_share=args.keep_share or None,
                fill_far=args.far_fill and not args.no_far_fill, confirm_views=args.confirm_views or None,
                robust_params=_robust_params(args)))
        out["labels"] = res.summary(scene.taxonomy)
        out["labels"].pop("versions", None)
        out["labels"].pop("robust_matrix", None)  # C x C numbers, kept in labels.json
        out["labels"].pop("confusion_model", None)  # A x C x C, kept there too
    return out


# ---- agreement ---------------------------------------------------------------------------
def _frame_ids(scene, names: list[str]) -> list[int]:
    out = []
    for n in names:
        if n.isdigit() and int(n) < len(scene.frames):
            out.append(int(n))
            continue
        try:
            out.append(scene.frame_index(n))
        except KeyError:
            raise InputFormatError(f"--frames: {n!r} is not a frame of the scene") from None
    return out


def _scene_and_labels(workspace: Path):  # noqa: ANN202
    """(Scene, LiftResult) of a workspace; WorkspaceError before the first ``occufly lift``."""
    scene = Scene.load(workspace)
    res = load_labels(workspace)
    if res is None:
        raise WorkspaceError(f"{workspace}: no lifted labels yet; run `occufly lift` first")
    return scene, res


def _agreement(args: argparse.Namespace) -> dict:
    from occufly.lifting import VoteStore

    scene, res = _scene_and_labels(args.workspace)
    files = _mask_files(scene, args.masks)
    frames = sorted(files) if not args.frames else _frame_ids(scene, args.frames)
    missing = [scene.frames[f].name for f in frames if f not in files]
    if missing:
        raise InputFormatError(f"{args.masks}: no mask for frame(s) {', '.join(missing)}")
    annotated = set(VoteStore.open(args.workspace, scene).included_versions())
    if args.held_out:
        frames = [f for f in frames if f not in annotated]
    if not frames:
        raise InputFormatError(
            f"{args.masks}: nothing to compare: "
            + ("every mask there is of an annotated frame (--held-out keeps the others)"
               if args.held_out and files else "no mask PNG named after a frame of the scene"))
    labels = np.asarray(res.labels)
    per_frame, held, ann = [], [], []
    for fi in frames:
        mask = read_mask(files[fi], scene.frames[fi], scene.taxonomy)
        rendered, _ = render_for_mask(scene, labels, fi, mask.shape)
        a = agreement(mask, rendered, scene.taxonomy)
        (ann if fi in annotated else held).append(a)
        per_frame.append({"frame": scene.frames[fi].name, "annotated": fi in annotated,
                          "agreement": a["agreement"], "pixels": a["pixels"],
                          "coverage": a["coverage"]})
        if args.out:
            import io

            from PIL import Image

            from occufly.fsutil import atomic_write_bytes

            buf = io.BytesIO()
            Image.fromarray(disagreement_image(mask, rendered, scene.taxonomy)).save(buf, "PNG")
            atomic_write_bytes(args.out / f"{scene.frames[fi].stem}.disagreement.png",
                               buf.getvalue())
    total = merge_agreements(held + ann)
    if not total.get("pixels"):
        raise InputFormatError(
            f"{args.masks}: nothing to compare: no pixel of the {len(frames)} mask(s) has both a "
            f"painted class and a lifted label rendered into it")
    names = {int(c.id): c.name for c in scene.taxonomy.classes}
    total["per_class_iou"] = {names[i]: v for i, v in total.get("per_class_iou", {}).items()}
    total.pop("confusion", None)
    return {
        "frames": len(frames),
        **total,
        "held_out": {k: v for k, v in merge_agreements(held).items() if k in
                     ("agreement", "pixels", "coverage")} | {"frames": len(held)},
        "annotated": {k: v for k, v in merge_agreements(ann).items() if k in
                      ("agreement", "pixels", "coverage")} | {"frames": len(ann)},
        "per_frame": per_frame,
    }


# ---- eval-points -------------------------------------------------------------------------
def load_truth_labels(ws: Path, truth_path: Path, n_points: int) -> np.ndarray:
    """Truth labels given in the source cloud's order, reordered to the workspace's points.

    If the workspace has ``points/source_index.npy`` ((N,) int, source index of each point)
    it is applied; otherwise the workspace keeps the source order and lengths must match.
    """
    try:
        truth = np.load(truth_path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputFormatError(f"{truth_path}: cannot read truth labels ({e})") from None
    truth = np.asarray(truth).reshape(-1)
    src = ws / "points" / "source_index.npy"
    if src.is_file():
        idx = np.load(src, mmap_mode="r")
        if len(idx) != n_points or (len(idx) and int(np.max(idx)) >= len(truth)):
            raise InputFormatError(f"{truth_path}: does not match {src} ({len(truth)} labels)")
        truth = truth[np.asarray(idx)]
    if len(truth) != n_points:
        raise InputFormatError(
            f"{truth_path}: has {len(truth)} labels but the workspace has {n_points} points"
        )
    if truth.size and (truth.min() < 0 or truth.max() > 255):
        raise InputFormatError(f"{truth_path}: labels must be raw class ids 0..255")
    return truth.astype(np.uint8)


def _eval_points(args: argparse.Namespace) -> dict:
    from occufly.lifting import VoteStore

    scene, res = _scene_and_labels(args.workspace)
    truth = load_truth_labels(args.workspace, args.truth, scene.n_points)
    out = evaluate_points(np.asarray(res.labels), truth, scene.taxonomy, np.asarray(res.origin))
    direct = VoteStore.open(args.workspace, scene).direct_labels()
    has = (direct > 0) & (truth > 0) & (truth < 255)
    out["direct_votes"] = {"points": int(has.sum()),
                           "accuracy": float((direct[has] == truth[has]).mean()) if has.any() else None}
    return out


# ---- report ------------------------------------------------------------------------------
def _report(args: argparse.Namespace) -> dict | int:
    Workspace(args.workspace).require()
    scene = Scene.load(args.workspace)

    truth = (load_truth_labels(args.workspace, args.truth, scene.n_points)
             if args.truth else workspace_truth(args.workspace, scene.n_points))
    q = quality_report(args.workspace, scene, truth=truth, loo=not args.no_loo)
    if args.out:
        atomic_write_text(args.out, json.dumps(q, indent=1))
    if args.json:
        return q
    print(summary_text(q))
    return 0


# ---- export-points -----------------------------------------------------------------------
def _export_points(args: argparse.Namespace) -> dict:
    scene, res = _scene_and_labels(args.workspace)
    return export_scene_points(scene, np.asarray(res.labels), args.out,
                               confidence=np.asarray(res.confidence), origin=np.asarray(res.origin))
