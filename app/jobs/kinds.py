"""The job kinds: each calls one pipeline entry point and records its result.

Pipeline functions are looked up at run time (``app.pipeline``); a missing one fails the job
with a message naming it, never a fake result.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from app import pipeline
from app.jobs.runner import JobContext, _jsonable, kind
from app.review import provenance
from app.review import service as review
from app.scenes import service as scenes
from app.scenes.models import Scene
from occufly.densify.evaluate import evaluate_grids
from occufly.densify.pipeline import DensifyOptions as options_cls
from occufly.densify.pipeline import voxelize_workspace as fn
from occufly.errors import OccuflyError
from occufly.workspace import Workspace


@kind("import")
def run_import(jc: JobContext) -> dict:
    p = jc.params
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        # the import replaces this folder: it must be the scene's own (never '.', '..', a
        # symlink or anything outside the workspaces folder)
        ws = scenes.own_workspace(jc.ctx.settings, scene)
        # a re-import replaces the points: never silently under reviewers' corrections (409
        # naming their count unless the admin asked to drop them; issue 25)
        from app.corrections.service import guard_reimport

        guard_reimport(session=s, scene=scene, drop=bool(p.get("drop_corrections")), user=None)
        scene.status = "importing"
        s.commit()
    jc.progress(0.0, f"importing {p['source']}")
    ws_scene = pipeline.import_scene(
        Path(p["source"]), ws, cloud=Path(p["cloud"]) if p.get("cloud") else None,
        depth_maps=Path(p["depth_maps"]) if p.get("depth_maps") else None,
        fmt=p.get("format"), images=Path(p["images"]) if p.get("images") else None,
        crs=p.get("crs"), scale=p.get("scale"), progress=lambda f, m="": jc.progress(0.95 * f, m),
        # every path read from a project file stays inside the import roots (issue 24,
        # finding 1); not the data dir, which holds the database, the masks and the exports
        roots=scenes.import_roots(jc.ctx.settings))
    jc.ctx.scene_cache.pop(str(ws), None)
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        scenes.sync_frames(session=s, scene=scene, ws_scene=ws_scene)
    jc.progress(1.0, "frames registered")
    geo = ws_scene.meta.get("georeferencing") or {}
    return {"frames": len(ws_scene.frames), "points": ws_scene.n_points,
            # issue 26: the georeferencing checks, and how the scene was made metric
            "warnings": list(ws_scene.meta.get("import_warnings", [])),
            "georeferencing": {k: v for k, v in geo.items() if k != "geotags"} or None}


def _import_failed(jc: JobContext, message: str) -> None:
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        if scene is not None and scene.status != "ready":
            scene.status = "failed"
            s.commit()


run_import.on_failure = _import_failed
run_import.remote = True


def _scene(jc: JobContext):
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        return scene.workspace, jc.ctx.load_scene(scene.workspace)


@kind("selection")
def run_selection(jc: JobContext) -> dict:
    _ws, ws_scene = _scene(jc)
    jc.progress(0.1, "selecting frames")
    params = {k: jc.params[k] for k in ("cell", "mode", "target_coverage", "altitude")
              if k in jc.params}
    result = pipeline.select_frames(ws_scene, **params)
    if "cameras" not in result:
        result["cameras"] = ws_scene.centers()[:, :2].round(3).tolist()
    result["params"] = params

    result = _jsonable(result)
    with jc.ctx.sessions() as s:
        scenes.apply_selection(session=s, scene=s.get(Scene, jc.scene_id), result=result,
                               ws_scene=ws_scene)
    jc.progress(1.0, f"{len(result['frames'])} frames selected")
    return result


run_selection.remote = True


@kind("voxelize")
def run_voxelize(jc: JobContext) -> dict:
    ws, _scene_obj = _scene(jc)

    if not Workspace(ws).has_labels():
        from occufly.errors import WorkspaceError

        raise WorkspaceError(f"scene {jc.scene_id} has no lifted labels yet (lifting/labels.npy); "
                             "save masks and let fill/denoise finish first")
    return fn(Path(ws), options=options_cls(voxel_size=float(jc.params.get("voxel_size", 0.5))),
              progress=jc.progress)


run_voxelize.remote = True


@kind("export")
def run_export(jc: JobContext) -> dict:
    from occufly.export import export_dataset as fn

    ws, ws_scene = _scene(jc)
    out = jc.ctx.settings.exports_dir / f"job_{jc.job_id}"

    # issue 23: which version of each frame the export takes (accepted only unless the request
    # includes submitted / imported ones), decided before the labels are read; a narrower set
    # than the live labels count is lifted again in a scratch folder (app.review.provenance)
    with jc.ctx.sessions() as s:
        plan = provenance.export_plan(s, jc.scene_id, jc.params.get("include"))
    scratch = jc.ctx.settings.data_dir / "scratch" / f"export_{jc.job_id}_{jc.attempt}"
    shutil.rmtree(scratch, ignore_errors=True)
    try:
        lab = provenance.export_labels(jc.ctx, Path(ws), ws_scene, plan, scratch,
                                       progress=lambda f, m="": jc.progress(0.3 * f, m))
        # written under an attempt-private name, moved to ``out`` when this attempt is
        # recorded done (a stale attempt of the same job can never touch it; app.jobs.runner)
        staging = jc.output_dir(out)
        summary = fn(Path(ws), staging, scene_id=f"scene_{jc.scene_id:02d}",
                     layout=jc.params.get("layout", "occufly"), frames=jc.params.get("frames"),
                     executor=jc.executor(), grid=lab["grid"], provenance=lab["provenance"],
                     quality=lab["quality"], progress=lambda f, m="": jc.progress(0.3 + 0.7 * f, m))
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


run_export.remote = True


@kind("eval")
def run_eval(jc: JobContext) -> dict:
    """2D agreement of the lifted labels rendered into every frame that has a current mask."""
    result = review.evaluate_scene(ctx=jc.ctx, scene_id=jc.scene_id, frames=jc.params.get("frames"),
                                   progress=lambda f, m="": jc.progress(0.9 * f, m))
    ws, scene = _scene(jc)

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
