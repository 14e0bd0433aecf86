"""The scene pipeline's job kinds: import a reconstruction, select frames to annotate,
propose the next frames to paint (issue 37), voxelize the labelled cloud. Each calls one pipeline entry point (looked up at run time in
``app.pipeline``: a missing one fails the job with a message naming it, never a fake
result) and records its result; all run on the job executor (``remote``).
"""

from __future__ import annotations

from pathlib import Path

from app import pipeline
from app.corrections.service import guard_reimport
from app.jobs.registry import JobContext, jsonable, kind
from app.scenes import service as scenes
from app.scenes.models import Scene
from occufly.densify.pipeline import DensifyOptions, voxelize_workspace
from occufly.errors import WorkspaceError
from occufly.lifting.nextbest import propose_for_workspace
from occufly.workspace import Workspace


def scene_of(jc: JobContext):  # noqa: ANN201 - (workspace path, occufly Scene)
    """The job's scene: its workspace folder and the loaded scene (cached per process)."""
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        return scene.workspace, jc.ctx.load_scene(scene.workspace)


def _import_failed(jc: JobContext, message: str) -> None:
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        if scene is not None and scene.status != "ready":
            scene.status = "failed"
            s.commit()


@kind("import", remote=True, on_failure=_import_failed)
def run_import(jc: JobContext) -> dict:
    p = jc.params
    with jc.ctx.sessions() as s:
        scene = s.get(Scene, jc.scene_id)
        # the import replaces this folder: it must be the scene's own (never '.', '..', a
        # symlink or anything outside the workspaces folder)
        ws = scenes.own_workspace(jc.ctx.settings, scene)
        # a re-import replaces the points: never silently under reviewers' corrections (409
        # naming their count unless the admin asked to drop them; issue 25)
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


@kind("selection", remote=True)
def run_selection(jc: JobContext) -> dict:
    _ws, ws_scene = scene_of(jc)
    jc.progress(0.1, "selecting frames")
    params = {k: jc.params[k] for k in ("cell", "mode", "target_coverage", "altitude")
              if k in jc.params}
    result = pipeline.select_frames(ws_scene, **params)
    if "cameras" not in result:
        result["cameras"] = ws_scene.centers()[:, :2].round(3).tolist()
    result["params"] = params

    result = jsonable(result)
    with jc.ctx.sessions() as s:
        scenes.apply_selection(session=s, scene=s.get(Scene, jc.scene_id), result=result,
                               ws_scene=ws_scene)
    jc.progress(1.0, f"{len(result['frames'])} frames selected")
    return result


@kind("next_frames", remote=True)
def run_next_frames(jc: JobContext) -> dict:
    """Issue 37: propose ``k`` frames without a mask whose masks would most settle the
    contested and uncertain labels, each with why (occufly.lifting.nextbest). An empty
    proposal (nothing contested) is a result with its message, not a failure."""
    ws, ws_scene = scene_of(jc)
    res = propose_for_workspace(Path(ws), int(jc.params.get("k", 5)), scene=ws_scene,
                                progress=jc.progress)
    return jsonable(res.to_dict())


@kind("voxelize", remote=True, done_event="grid_updated")
def run_voxelize(jc: JobContext) -> dict:
    ws, _scene_obj = scene_of(jc)

    if not Workspace(ws).has_labels():
        raise WorkspaceError(f"scene {jc.scene_id} has no lifted labels yet (lifting/labels.npy); "
                             "save masks and let fill/denoise finish first")
    return voxelize_workspace(Path(ws), options=DensifyOptions(voxel_size=float(jc.params.get("voxel_size", 0.5))),
              progress=jc.progress)
