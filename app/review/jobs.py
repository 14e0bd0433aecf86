"""The review domain's job kinds: export the dataset (the accepted masks' labels, with the
quality report) and evaluate the lifted labels against every annotated frame."""

from __future__ import annotations

import shutil
from pathlib import Path

from app.jobs.registry import JobContext, kind
from app.review import provenance
from app.review import service as review
from app.scenes import disk
from app.scenes.jobs import scene_of
from occufly.densify.evaluate import evaluate_grids
from occufly.errors import OccuflyError
from occufly.export import export_dataset
from occufly.export.common import ExportDiskFull, ExportError, is_disk_full
from occufly.workspace import Workspace


def _apply_retention(jc: JobContext) -> None:
    """Retention counts the export that just finished."""
    disk.apply_export_retention(jc.ctx, jc.scene_id)


@kind("export", remote=True, on_done=_apply_retention)
def run_export(jc: JobContext) -> dict:
    ws, ws_scene = scene_of(jc)
    out = jc.ctx.settings.exports_dir / f"job_{jc.job_id}"

    # issue 23: which version of each frame the export takes (accepted only unless the request
    # includes submitted / imported ones), decided before the labels are read; a narrower set
    # than the live labels count is lifted again in a scratch folder (app.review.provenance)
    with jc.ctx.sessions() as s:
        plan = provenance.export_plan(s, jc.scene_id, jc.params.get("include"))
    scratch = jc.ctx.settings.data_dir / "scratch" / f"export_{jc.job_id}_{jc.attempt}"
    shutil.rmtree(scratch, ignore_errors=True)
    try:
        summary, lab, staging = _write_export(jc, ws, ws_scene, plan, scratch, out)
    except (OSError, ExportError) as e:
        # the disk (or a quota) filled while the labels were lifted again or the files were
        # written: the runner removes the attempt's staging folder (nothing of this export is
        # left) and the job says so in words, naming where it was writing
        if not is_disk_full(e):
            raise
        raise ExportDiskFull(
            f"disk full while exporting scene {jc.scene_id} to {out}: nothing of this export "
            "was kept (the partial output was removed) -- free space in the data folder, then "
            "run the export again") from None
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    q = lab["quality"]
    # the files a user downloads (the exporter's .occufly_export bookkeeping not counted)
    n_files = sum(1 for p in staging.rglob("*") if p.is_file() and ".occufly_export" not in p.parts)
    return {"output": str(out), "summary": summary if isinstance(summary, dict) else {},
            "files": n_files,
            "review": provenance.export_result(plan),
            "labels": {k: lab["provenance"]["labels"][k] for k in ("relifted", "sha256")},
            "quality": None if q is None else {
                "loo_agreement": (q.get("loo") or {}).get("agreement"),
                "multi_view_share": q["votes"]["multi_view_share"],
                "contested_share": q["contested"]["share"]}}


def _write_export(jc: JobContext, ws, ws_scene, plan: dict, scratch: Path,  # noqa: ANN001
                  out: Path) -> tuple[dict, dict, Path]:
    """Lift the planned versions (in ``scratch`` when needed) and write the export into the
    attempt's staging folder: ``(summary, labels, staging)``."""
    lab = provenance.export_labels(jc.ctx, Path(ws), ws_scene, plan, scratch,
                                   progress=lambda f, m="": jc.progress(0.3 * f, m),
                                   scene_id=jc.scene_id)
    # written under an attempt-private name, moved to ``out`` when this attempt is
    # recorded done (a stale attempt of the same job can never touch it; app.jobs.runner)
    staging = jc.output_dir(out)
    summary = export_dataset(
        Path(ws), staging, scene_id=f"scene_{jc.scene_id:02d}",
        layout=jc.params.get("layout", "occufly"), frames=jc.params.get("frames"),
        executor=jc.executor(), grid=lab["grid"], provenance=lab["provenance"],
        quality=lab["quality"], progress=lambda f, m="": jc.progress(0.3 + 0.7 * f, m))
    return summary, lab, staging


@kind("eval")
def run_eval(jc: JobContext) -> dict:
    """2D agreement of the lifted labels rendered into every frame that has a current mask."""
    result = review.evaluate_scene(ctx=jc.ctx, scene_id=jc.scene_id, frames=jc.params.get("frames"),
                                   progress=lambda f, m="": jc.progress(0.9 * f, m))
    ws, scene = scene_of(jc)

    try:
        grid_eval = _scene_grid_eval(Path(ws), scene.taxonomy)
    except OccuflyError as e:  # a bad truth grid must not cost the 2D agreement just computed
        grid_eval = {"table": "scene_grid_vs_truth", "error": str(e)}
    if grid_eval is not None:
        result["scene_grid"] = grid_eval
    jc.progress(1.0, "done")
    return result


def _scene_grid_eval(ws: Path, taxonomy) -> dict | None:  # noqa: ANN001
    """Completion / per-class IoU of WS/grid/scene_grid.npz against WS/truth/scene_grid.npz, when
    both exist (e.g. the demo's synthetic scene after a voxelize job); None otherwise."""
    w = Workspace(ws)
    if not (w.has_grid() and w.truth_grid_path.is_file()):
        return None
    ev = evaluate_grids(w.grid(), w.truth_grid(), taxonomy)
    keep = ("completion_iou", "precision", "recall", "miou", "classes_evaluated")
    return {"table": "scene_grid_vs_truth", **{k: ev[k] for k in keep if k in ev},
            "per_class_iou": ev.get("per_class_iou", {})}
