"""Corrections benchmark (issue 25): how much faster a correction in 3D is than the round trip
through an annotator, and what a large relabel costs on the server. Prints one JSON object.

Part 1 -- quality, on the synthetic scene (``--preset bench``, ~5 M points; generated and
imported once into ``--cache`` through the CLI):

* the greedy frame selection (rho >= 0.99) is painted with *degraded* masks
  (:func:`occufly.synthetic.degrade.degrade_masks`), lifted (votes, kNN fill + denoise): the
  baseline labels and their point accuracy against the synthetic truth (points whose truth is
  a class, i.e. not 0 / 255);
* a scripted reviewer works through the most *contested* regions, most contested first:
  ``--cell`` metre columns ranked by the number of points whose votes disagree (two or more
  votes, the winner short of all of them) or whose final label differs from their direct vote
  majority (a measure from the votes alone, no truth). In each region it relabels, for every
  true class that region's wrong points belong to, the region's points of that class to it --
  one 3D edit each (what a lasso with the "only class" filter or a click-to-grow selects on a
  well separated object; an idealised reviewer who reads the truth correctly). Edits go
  through the real net layer (:mod:`occufly.lifting.corrections`, incremental). Reported:
  accuracy after 0, 1, 2, 5, 10, ... edits;
* the 2D round trip: frames ordered by their share of degraded pixels are repainted to their
  true masks (pixels painted = pixels that change), re-lifted after each step (1, 2, 4, ...
  frames), until the accuracy reaches what the 3D edits reached. Reported: pixels painted and
  frames repainted for the same gain (interpolated between the two steps around it).

Part 2 -- scale: a 1 M-point relabel through the app's corrections service
(``app.corrections.service.create_edit``: SQLite row, point file, net layer) on a fabricated
32 M-point workspace (sparse memory-mapped cloud, random labels, a net layer already holding
three edits of 0.7 M points), then its undo, against a baseline measured in the same run:
the naive O(scene) way (read the 32 M labels, write them back with the edit applied).

    .venv/bin/python bench/bench_corrections.py [--preset bench] [--edits 200] [--skip-quality]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _scene import ensure_seeded_scene  # noqa: E402


def accuracy(labels: np.ndarray, truth: np.ndarray) -> float:
    ok = (truth > 0) & (truth < 255)
    return float((np.asarray(labels)[ok] == truth[ok]).mean())


def contested_regions(ws: Path, scene, labels: np.ndarray, cell: float):  # noqa: ANN001
    """[(region key, point ids)] most contested first (votes only, no truth)."""
    from occufly.lifting import VoteStore

    st = VoteStore.open(ws, scene)
    votes = np.asarray(st.votes)
    direct = np.asarray(st.direct_labels())
    total = votes.sum(axis=1, dtype=np.int64)
    top = votes.max(axis=1)
    contested = ((total >= 2) & (top < total)) | ((direct > 0) & (direct != labels))
    xy = np.floor(np.asarray(scene.xyz, np.float64)[:, :2] / cell).astype(np.int64)
    xy -= xy.min(axis=0)
    key = xy[:, 0] * (xy[:, 1].max() + 1) + xy[:, 1]
    score = np.bincount(key[contested], minlength=int(key.max()) + 1)
    order = np.argsort(key, kind="stable")
    skey = key[order]
    starts = np.searchsorted(skey, np.arange(len(score)))
    ends = np.searchsorted(skey, np.arange(len(score)), side="right")
    ranked = [int(k) for k in np.argsort(-score, kind="stable") if score[k] > 0]
    return [(k, order[starts[k]:ends[k]]) for k in ranked], int(contested.sum())


def quality(args: argparse.Namespace) -> dict:
    from occufly.io.masks import read_mask
    from occufly.lifting import VoteStore
    from occufly.lifting import corrections as lib
    from occufly.scene import Scene
    from occufly.selection import select_frames
    from occufly.synthetic.degrade import degrade_masks

    syn, ws = ensure_seeded_scene(args.cache, args.preset, args.seed)
    scene = Scene.load(ws)
    tax = scene.taxonomy
    truth = np.load(syn / "truth" / "point_labels.npy")
    sel = select_frames(scene, mode="greedy", target_coverage=0.99)
    frames = [int(f) for f in sel.frames]
    exact = {fi: read_mask(syn / "truth" / "masks" / f"{scene.frames[fi].stem}.png",
                           scene.frames[fi], tax) for fi in frames}
    degraded = degrade_masks(exact, tax, seed=args.seed)
    shutil.rmtree(ws / "lifting", ignore_errors=True)
    st = VoteStore.open(ws, scene)
    for fi in frames:
        st.set_mask(fi, degraded[fi], version="degraded")
    t = time.perf_counter()
    res = st.fill_and_denoise()
    t_fill = time.perf_counter() - t
    labels0 = np.asarray(res.labels).copy()
    acc0 = accuracy(labels0, truth)
    out = {"preset": args.preset, "points": scene.n_points, "frames": len(scene.frames),
           "selected": len(frames), "fill_s": round(t_fill, 1), "accuracy_degraded": acc0,
           "degraded_pixels_share": float(np.mean([(degraded[f] != exact[f]).mean()
                                                   for f in frames]))}

    # ---- 3D: the scripted reviewer -----------------------------------------------------------
    regions, n_contested = contested_regions(ws, scene, labels0, args.cell)
    out["contested_points"] = n_contested
    out["contested_regions"] = len(regions)
    net = lib.NetLayer.empty()
    cur = labels0.copy()
    curve = [{"edits": 0, "points": 0, "accuracy": acc0}]
    marks = {1, 2, 5, 10, 20, 50, 100, 150, 200, 300, 500, 1000}
    n_edits = n_pts = 0
    t_edit = 0.0
    regions_done = 0
    for _key, ids in regions:
        if n_edits >= args.edits:
            break
        regions_done += 1
        tr = truth[ids]
        wrong = (cur[ids] != tr) & (tr > 0) & (tr < 255)
        for c in np.unique(tr[wrong]):
            if n_edits >= args.edits:
                break
            pick = np.sort(ids[tr == c])  # the region's points of that true class
            t = time.perf_counter()
            n_edits += 1
            net = lib.activate_edit(net, n_edits, pick, int(c))
            t_edit += time.perf_counter() - t
            cur[pick] = c
            n_pts += len(pick)
            if n_edits in marks:
                curve.append({"edits": n_edits, "points": n_pts, "regions": regions_done,
                              "accuracy": accuracy(cur, truth)})
    lib.write_net(ws, net)
    applied = lib.apply_to_labels(labels0, ws)  # the consumers' view equals the script's
    acc3d = accuracy(applied, truth)
    assert np.array_equal(applied, cur)
    if curve[-1]["edits"] != n_edits:
        curve.append({"edits": n_edits, "points": n_pts, "regions": regions_done,
                      "accuracy": acc3d})
    lib.write_net(ws, lib.NetLayer.empty())
    out["3d"] = {"edits": n_edits, "points_relabelled": n_pts, "regions": regions_done,
                 "accuracy": acc3d, "gain": acc3d - acc0, "curve": curve,
                 "net_layer_update_s_total": round(t_edit, 3)}

    # ---- 2D: repaint masks, re-lift ----------------------------------------------------------
    order = sorted(frames, key=lambda f: -float((degraded[f] != exact[f]).mean()))
    steps = []
    painted = 0
    k_done = 0
    current = dict(degraded)
    k = 1
    prev = {"frames": 0, "pixels": 0, "accuracy": acc0}
    reached = None
    while k_done < len(order):
        for fi in order[k_done:k]:
            painted += int((current[fi] != exact[fi]).sum())
            current[fi] = exact[fi]
            st.set_mask(fi, exact[fi], version="repainted")
        k_done = min(k, len(order))
        acc = accuracy(st.fill_and_denoise().labels, truth)
        row = {"frames": k_done, "pixels": painted, "accuracy": acc}
        steps.append(row)
        if reached is None and acc >= acc3d:
            span = max(acc - prev["accuracy"], 1e-12)
            w = (acc3d - prev["accuracy"]) / span
            reached = {"frames": prev["frames"] + w * (row["frames"] - prev["frames"]),
                       "pixels": prev["pixels"] + w * (row["pixels"] - prev["pixels"])}
            if not args.full_2d:
                break
        prev = row
        k = min(2 * k, len(order))
    out["2d"] = {"steps": steps, "all_frames_accuracy": steps[-1]["accuracy"]
                 if k_done == len(order) else None,
                 "same_gain_as_3d": reached,
                 "same_gain_reached": reached is not None}
    if reached is not None:
        out["ratio_pixels_per_3d_edit"] = reached["pixels"] / max(n_edits, 1)
        out["ratio_frames_per_3d_edit"] = reached["frames"] / max(n_edits, 1)
    return out


def scale(args: argparse.Namespace) -> dict:
    """1 M-point relabel on a fabricated 32 M-point workspace through the app's service."""
    from app.config import Settings
    from app.corrections import service
    from app.db import upgrade
    from app.main import build_context
    from app.scenes.models import Scene as SceneRow
    from app.users import service as users
    from occufly.camera import Camera, look_at
    from occufly.lifting import corrections as lib
    from occufly.scene import Frame, Scene, Visibility
    from occufly.workspace import Workspace

    N = int(args.scale_points)
    M = int(args.scale_edit)
    root = Path(tempfile.mkdtemp(prefix="occufly-corr-scale-"))
    try:
        ws = root / "ws"
        cam = Camera("PINHOLE", 64, 48, np.array([50.0, 50.0, 32, 24]))
        fr = Frame(name="f0.png", camera=cam, T_cam_world=look_at(
            np.array([0.0, 0, 30]), np.zeros(3), up=(0.0, 1.0, 0.0)))
        tiny = Scene(frames=[fr], xyz=np.zeros((1, 3), np.float32),
                     rgb=np.zeros((1, 3), np.uint8), visibility=Visibility.empty(1))
        tiny.save(ws)
        w = Workspace(ws)
        # the cloud: sparse memory-mapped files of N points (no disk written for the zeros)
        for p, shape, dt in ((w.points_xyz, (N, 3), np.float32), (w.points_rgb, (N, 3), np.uint8)):
            arr = np.lib.format.open_memmap(p, mode="w+", dtype=dt, shape=shape)
            del arr
        hdr = json.loads(w.scene_json.read_text())
        hdr["n_points"] = N
        w.scene_json.write_text(json.dumps(hdr))
        rng = np.random.default_rng(1)
        labels = rng.integers(1, 20, N).astype(np.uint8)
        w.write_labels(labels, np.full(N, 0.5, np.float32), np.full(N, 2, np.uint8), {})
        db = root / "bench.db"
        upgrade(f"sqlite:///{db}")
        ctx = build_context(Settings(data_dir=root / "data", database_url=f"sqlite:///{db}",
                                     env="development"), lifting="off", jobs=False)
        with ctx.sessions() as s:
            user = users.create_user(session=s, username="rev", password="long-enough-1",
                                     role="reviewer")
            row = SceneRow(name="scale", status="ready", workspace=str(ws), source="-",
                           n_points=N, n_frames=1)
            s.add(row)
            s.commit()
            # three earlier edits of 0.7 M points each
            for _ in range(3):
                service.create_edit(session=s, ctx=ctx, scene=row, user=user,
                                    point_ids=np.unique(rng.integers(0, N, 700_000)), to_class=8)
            ids = np.unique(rng.integers(0, N, int(M * 1.06)))[:M]
            rng.shuffle(ids)  # as a client sends them: any order
            runs = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                e = service.create_edit(session=s, ctx=ctx, scene=row, user=user,
                                        point_ids=ids, to_class=13)
                t_edit = time.perf_counter() - t
                t = time.perf_counter()
                service.undo(session=s, ctx=ctx, scene=row, user=user)
                t_undo = time.perf_counter() - t
                runs.append({"edit_s": t_edit, "undo_s": t_undo, "edit_id": e.id})
            t = time.perf_counter()
            service.redo(session=s, ctx=ctx, scene=row, user=user)
            t_redo = time.perf_counter() - t
            from occufly.lifting import load_labels

            t = time.perf_counter()
            res = load_labels(ws)
            t_load = time.perf_counter() - t
            assert (np.asarray(res.labels)[np.sort(ids)] == 13).all()
            net_k = len(lib.read_net(ws, N))
            point_file = w.correction_edit(runs[-1]["edit_id"]).stat().st_size
        # baseline in the same run: the O(scene) way
        t = time.perf_counter()
        lab = np.array(np.load(w.labels_path))
        lab[ids] = 13
        from occufly.fsutil import atomic_save_npy

        atomic_save_npy(root / "labels_rewritten.npy", lab)
        t_base = time.perf_counter() - t
        ctx.engine.dispose()
        best = min(runs, key=lambda r: r["edit_s"])
        return {"points": N, "edit_points": M, "net_layer_points": net_k,
                "edit_s": [round(r["edit_s"], 3) for r in runs],
                "undo_s": [round(r["undo_s"], 3) for r in runs], "redo_s": round(t_redo, 3),
                "load_labels_with_layer_s": round(t_load, 3),
                "point_file_bytes": point_file,
                "baseline_full_rewrite_s": round(t_base, 3),
                "ratio_edit_vs_full_rewrite": round(best["edit_s"] / t_base, 3),
                "met_under_1s": best["edit_s"] < 1.0}
    finally:
        shutil.rmtree(root, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="bench")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-bench"))
    ap.add_argument("--edits", type=int, default=200, help="3D edits the reviewer makes")
    ap.add_argument("--cell", type=float, default=4.0, help="region edge (m)")
    ap.add_argument("--full-2d", action="store_true", help="repaint every frame")
    ap.add_argument("--skip-quality", action="store_true")
    ap.add_argument("--skip-scale", action="store_true")
    ap.add_argument("--scale-points", type=float, default=32e6)
    ap.add_argument("--scale-edit", type=float, default=1e6)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    out: dict = {"bench": "corrections"}
    with open("/proc/loadavg") as f:
        out["loadavg_start"] = f.read().split()[:3]
    if not args.skip_scale:
        out["scale"] = scale(args)
    if not args.skip_quality:
        out["quality"] = quality(args)
    with open("/proc/loadavg") as f:
        out["loadavg_end"] = f.read().split()[:3]
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
