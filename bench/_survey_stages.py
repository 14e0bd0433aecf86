"""The review-side stages of ``bench_survey.py`` (issue 38), each run as its own process so
that its wall time, CPU and peak memory are its own:

``review WS SRC``
    What a reviewer's day costs on the scene, library calls as the app makes them:

    * ``quality_report``: :func:`occufly.lifting.quality.quality_report` (the admin page's
      quality section: LOO agreement of every lifted frame, coverage, calibration, per class);
    * ``suspects``: :func:`occufly.lifting.suspects.find_suspects` over the votes and labels
      (the reviewer's suspects list);
    * ``loo_one_frame``: :func:`occufly.lifting.loo.frame_loo` of one lifted frame with its
      truth mask (the agreement request of the review page, uncached), a 20 MP frame where the
      scene has one;
    * ``correction_1m`` / ``correction_undo``: a relabel of about 1 M points (a box around the
      cloud's centre grown until it holds them) written to the corrections layer and applied
      to the labels, then undone -- the library calls of ``app.corrections.service``'s
      create / undo (read the net layer, activate / deactivate, write it, labels with the
      corrections applied).

``gated WS SRC STRIDE``
    An export gated to accepted frames (``app.review.provenance.export_labels`` without the
    app): four in five of the selected frames "accepted", their masks lifted again from
    scratch (``relift``), the relifted labels voxelized and every STRIDE-th frame exported
    with that grid (two workers). Timed per part.

Each prints one JSON object on its last line (figures in seconds: ``*_s`` wall, ``*_cpu_s``
CPU of this process; the export's workers are counted by the caller's process tree).
"""

from __future__ import annotations

import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

OUT: dict = {}


def timed(key: str, fn):  # noqa: ANN001, ANN201
    t0, c0 = time.perf_counter(), time.process_time()
    r = fn()
    OUT[key + "_s"] = round(time.perf_counter() - t0, 3)
    OUT[key + "_cpu_s"] = round(time.process_time() - c0, 3)
    return r


def _truth_mask(src: Path, scene, fi: int) -> np.ndarray:  # noqa: ANN001
    from occufly.io.masks import read_mask

    fr = scene.frames[fi]
    p = src / "truth" / "masks" / (Path(fr.name).stem + ".png")
    return read_mask(p.read_bytes(), fr, scene.taxonomy, name=str(p))


def review_frame(ws: Path, src: Path, scene) -> int:  # noqa: ANN001
    """One lifted frame to review: the first full-size (20 MP) one of the source's truth where
    the scene has one, else the first lifted frame."""
    from occufly.lifting.votes import VoteStore

    state = VoteStore.open(ws, scene, read_only=True)
    lifted = sorted(state.included_versions())
    state.close()
    meta = json.loads((src / "truth" / "meta.json").read_text())
    full = {scene.frame_index(n) for n in meta.get("full_size_frames", [])}
    return next((f for f in lifted if f in full), lifted[0])


def _box_of(xyz: np.ndarray, n: int) -> np.ndarray:
    """Ids of the points in the smallest square column (x, y) around the cloud's centre that
    holds at least ``n`` points (a lasso's worth of a reviewer's relabel)."""
    c = np.median(xyz[:, :2], axis=0)
    d = np.max(np.abs(xyz[:, :2] - c), axis=1)  # Chebyshev distance in plan
    if n >= len(d):
        return np.arange(len(d), dtype=np.int64)
    r = np.partition(d, n - 1)[n - 1]
    return np.flatnonzero(d <= r).astype(np.int64)


def review(ws: Path, src: Path) -> None:
    from occufly.lifting import corrections as corr
    from occufly.lifting.loo import frame_loo
    from occufly.lifting.quality import quality_report
    from occufly.lifting.suspects import find_suspects
    from occufly.scene import Scene
    from occufly.workspace import Workspace

    scene = timed("scene_load", lambda: Scene.load(ws))
    OUT["points"] = int(scene.n_points)
    q = timed("quality_report", lambda: quality_report(ws, scene))
    OUT["quality_loo_frames"] = (q.get("loo") or {}).get("frames")
    OUT["quality_loo_agreement"] = (q.get("loo") or {}).get("agreement")
    OUT["quality_seconds"] = q.get("seconds")  # its own split: total, the LOO of every frame
    votes = np.load(Workspace(ws).votes, mmap_mode="r")
    labels = np.asarray(corr.load_labels(ws).labels)
    sus = timed("suspects", lambda: find_suspects(scene, votes, labels))
    OUT["suspects"] = len(sus)
    fi = review_frame(ws, src, scene)
    mask = _truth_mask(src, scene, fi)
    OUT["loo_frame"] = {"index": int(fi), "size": [int(mask.shape[1]), int(mask.shape[0])]}
    fig = timed("loo_one_frame", lambda: frame_loo(ws, scene, fi, mask, self_labels=labels))
    OUT["loo_one_frame_agreement"] = fig.get("agreement")
    # a 1 M point relabel and its undo (the layer's edit ids far above the app's own)
    ids = _box_of(np.asarray(scene.xyz), 1_000_000)
    OUT["correction_points"] = int(len(ids))
    to_class = int(scene.taxonomy.ids[-1])
    edit = 2**30
    w = Workspace(ws)
    layer = w.overrides_path
    saved = layer.read_bytes() if layer.exists() else None

    def apply() -> None:
        net = corr.read_net(ws, scene.n_points)
        corr.write_edit_points(ws, edit, ids, to_class)
        corr.write_net(ws, corr.activate_edit(net, edit, corr.read_edit_points(ws, edit),
                                              to_class))
        lab = corr.apply_to_labels(np.array(labels), ws)
        OUT["correction_applied"] = int(np.count_nonzero(lab[ids] == to_class))

    def undo() -> None:
        net = corr.read_net(ws, scene.n_points)
        corr.write_net(ws, corr.deactivate_edit(net, edit, corr.read_edit_points(ws, edit), ()))
        lab = corr.apply_to_labels(np.array(labels), ws)
        OUT["correction_undone"] = bool(np.array_equal(lab[ids], labels[ids]))

    try:
        timed("correction_1m", apply)
        timed("correction_undo", undo)
    finally:  # the workspace's own layer back as it was
        if saved is None:
            layer.unlink(missing_ok=True)
        else:
            layer.write_bytes(saved)
        w.correction_edit(edit).unlink(missing_ok=True)


def gated(ws: Path, src: Path, stride: int) -> None:
    from occufly.densify.pipeline import DensifyOptions, voxelize_workspace
    from occufly.export.dataset import export_dataset
    from occufly.grid import SceneGrid
    from occufly.lifting.corrections import load_labels
    from occufly.lifting.relift import relift, vote_weighting_of
    from occufly.lifting.votes import VoteStore
    from occufly.scene import Scene
    from occufly.workspace import Workspace

    scene = timed("scene_load", lambda: Scene.load(ws))
    state = VoteStore.open(ws, scene, read_only=True)
    lifted = sorted(state.included_versions())
    state.close()
    accepted = [f for k, f in enumerate(lifted) if k % 5 != 4]  # four in five accepted
    OUT["lifted_frames"], OUT["accepted_frames"] = len(lifted), len(accepted)
    scratch = Path(tempfile.mkdtemp(prefix="gated_", dir=str(ws.parent)))
    try:
        items = timed("masks_read", lambda: [(f, f"v{f}", _truth_mask(src, scene, f))
                                             for f in accepted])
        timed("relift", lambda: relift(scene, items, scratch / "lift",
                                       vote_weighting=vote_weighting_of(ws), features_ws=ws))
        lp = scratch / "labels_corrected.npy"
        np.save(lp, np.asarray(load_labels(scratch / "lift").labels, np.uint8))
        g = Workspace(ws).grid()
        vs = float(g.voxel_size) if g is not None else 0.5
        gp = scratch / "grid" / "scene_grid.npz"
        gp.parent.mkdir(parents=True)
        timed("voxelize", lambda: voxelize_workspace(ws, labels_path=lp, out_path=gp,
                                                     options=DensifyOptions(voxel_size=vs)))
        grid = SceneGrid.load(gp)
        frames = list(range(0, len(scene.frames), max(1, stride)))
        OUT["exported_frames"] = len(frames)
        timed("export", lambda: export_dataset(ws, scratch / "out", frames=frames, grid=grid,
                                               workers=2))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    OUT["total_s"] = round(sum(v for k, v in OUT.items() if k.endswith("_s")
                               and not k.endswith("cpu_s") and k != "total_s"), 3)


if __name__ == "__main__":
    what, ws_arg, src_arg = sys.argv[1:4]
    if what == "review":
        review(Path(ws_arg), Path(src_arg))
    elif what == "gated":
        gated(Path(ws_arg), Path(src_arg), int(sys.argv[4]))
    else:
        sys.exit(f"unknown stage {what!r}: review or gated")
    print(json.dumps(OUT))
