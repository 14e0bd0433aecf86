"""Where a reviewer's first open of a frame spends its CPU, sub-step by sub-step, in one process
(the steps of ``bench/bench_review_open.py``, each broken down further).

Every library function a step calls is wrapped by a timer (CPU ``time.process_time`` and wall
``time.perf_counter``, summed over its calls); what a step spends outside them is its own
inline numpy work (``<step> (inline)``). The figures are the best of ``--repeat`` runs after a
warm-up run. ``--cprofile N`` prints the N largest ``tottime`` entries of one more run.

    .venv/bin/python bench/_profile_review_open.py WS SOURCE [--frame 52]
    PROFILE_TREE=/tmp/old .venv/bin/python bench/_profile_review_open.py WS SOURCE

Not a benchmark of record: ``bench_review_open.py`` is (this one's wrappers add a few ms).
"""

from __future__ import annotations

import argparse
import cProfile
import functools
import io
import json
import os
import pstats
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

# PROFILE_TREE: another code tree (a directory holding occufly/ and app/, e.g. a git archive
# of an older revision) to profile instead of this checkout
sys.path.insert(0, os.environ.get("PROFILE_TREE") or str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

ACC: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0])
STACK: list[str] = []


def _wrap(mod, name: str, label: str) -> None:  # noqa: ANN001
    fn = getattr(mod, name, None)
    if fn is None or getattr(fn, "_profiled", False):
        return

    @functools.wraps(fn)
    def w(*a, **k):  # noqa: ANN002, ANN003, ANN202
        STACK.append(label)
        c, t = time.process_time(), time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            e = ACC[label]
            e[0] += time.process_time() - c
            e[1] += time.perf_counter() - t
            e[2] += 1
            STACK.pop()

    w._profiled = True
    setattr(mod, name, w)


def instrument() -> None:
    from occufly import render, splat
    from occufly.lifting import loo as L
    from occufly.lifting import robust as R

    for mod, names, pre in (
        (L, ["frustum_candidates", "_frame_votes", "loo_winner", "_robust_decision", "points_in_box",
             "_near", "cKDTree", "knn_vote", "read_overrides", "render_many_for_mask",
             "_vote_unit", "count_pairs_many", "agreement_from_counts", "score_figures",
             "project_points", "_fill_vote", "_fill_tree", "_fill_grid", "_fill_knn_scores", "_gather_rows", "rows_in"], "loo."),
        (R, ["cached_features", "redecide", "estimate_confusion", "_fit_qda", "local_votes",
             "_local_prior_tables", "_decide_chunk", "_vote_candidates", "_feature_kernel",
             "_integral_votes", "_vote_counts_into"], "robust."),
        (render, ["frustum_candidates", "_coarsening", "_render", "_finish", "_labels_at",
                  "project_splat_pass"], "render."),
        (splat, ["upsample_u8", "project_splat_pass", "sparse_at"], "splat."),
    ):
        for n in names:
            _wrap(mod, n, pre + n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("source", type=Path)
    ap.add_argument("--frame", type=int, default=-1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cprofile", type=int, default=0)
    args = ap.parse_args()

    from _survey_stages import _truth_mask, review_frame

    from occufly import render
    from occufly.lifting import corrections as corr
    from occufly.lifting import loo as L
    from occufly.scene import Scene

    ws, src = args.workspace, args.source
    scene = Scene.load(ws)
    labels = np.asarray(corr.load_labels(ws).labels)
    frame = args.frame if args.frame >= 0 else review_frame(ws, src, scene)
    mask = _truth_mask(src, scene, frame)
    instrument()

    def overlay(imgs: dict) -> bytes:
        from app.pipeline import encode_png_palette

        idx = timed("overlay.disagreement_indices",
                    lambda: render.disagreement_indices(mask, imgs["loo"], scene.taxonomy))
        return timed("overlay.encode_png_palette",
                     lambda: encode_png_palette(idx, render.disagreement_palette(scene.taxonomy)))

    def timed(label: str, fn):  # noqa: ANN001, ANN202
        c, t = time.process_time(), time.perf_counter()
        r = fn()
        e = ACC[label]
        e[0] += time.process_time() - c
        e[1] += time.perf_counter() - t
        e[2] += 1
        return r

    def step() -> dict:
        ACC.clear()
        loo = timed("STEP loo_labels", lambda: L.loo_labels(ws, scene, frame))
        imgs = timed("STEP render_review", lambda: L.render_review(scene, loo, mask.shape, labels))
        timed("STEP agreement", lambda: L.loo_agreement(mask, imgs["loo"], scene,
                                                         self_rendered=imgs["self"],
                                                         confident_rendered=imgs["confident"]))
        timed("STEP neighbours", lambda: L.disagreeing_neighbours(ws, scene, frame, loo))
        timed("STEP overlay_png", lambda: overlay(imgs))
        return {k: list(v) for k, v in ACC.items()}

    step()  # warm-up: kernels loaded, the cull's bins built, files in the page cache
    runs = [step() for _ in range(args.repeat)]
    best = min(runs, key=lambda r: sum(v[0] for k, v in r.items() if k.startswith("STEP")))
    total = sum(v[0] for k, v in best.items() if k.startswith("STEP"))
    total_wall = sum(v[1] for k, v in best.items() if k.startswith("STEP"))
    print(f"frame {frame}  size {mask.shape[1]}x{mask.shape[0]}  total CPU {total:.3f} s  "
          f"wall {total_wall:.3f} s  (totals CPU: "
          f"{[round(sum(v[0] for k, v in r.items() if k.startswith('STEP')), 3) for r in runs]})")
    print(f"{'what':52s} {'cpu_s':>7s} {'wall_s':>7s} {'calls':>5s}")
    for k, (c, t, n) in sorted(best.items(), key=lambda kv: (-kv[1][0])):
        print(f"{k:52s} {c:7.3f} {t:7.3f} {n:5d}")
    print(json.dumps({"frame": frame, "cpu_total": round(total, 3),
                      "best": {k: [round(v[0], 4), round(v[1], 4), v[2]] for k, v in best.items()}}))
    if args.cprofile:
        pr = cProfile.Profile()
        pr.enable()
        step()
        pr.disable()
        s = io.StringIO()
        pstats.Stats(pr, stream=s).sort_stats("tottime").print_stats(args.cprofile)
        print(s.getvalue())


if __name__ == "__main__":
    main()
