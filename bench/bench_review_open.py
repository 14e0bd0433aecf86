"""A reviewer's first open of a frame that nothing prefetched, step by step, on a real workspace.

What ``app.review.service.review_images`` computes for ``GET /frames/{fid}/agreement`` and
``/disagreement`` when neither the process nor the shared cache holds it: the leave-one-out
labels (:func:`occufly.lifting.loo.loo_labels`), the one render of the LOO, confident-LOO and
self labels, the figures, the disagreeing neighbours and the overlay PNG -- each step's CPU
time in one process, best of ``--repeat`` after a warm-up, for the working tree and for a
baseline git revision (its ``occufly/`` and ``app/`` extracted, run in its own process,
alternating rounds), plus whether both give the same LOO labels. Then the route's whole
computation as it runs (``compute_review``: its threads included, the mask already decoded):
``route_wall_s`` is what a reviewer waits for on an idle machine, ``route_cpu_s`` its CPU.
Each revision's process tunes its allocator as that revision's serving processes do
(``app.serving.tune_allocator`` where it exists; ``allocator_tuned`` in the output).
``after_fill_wall_s``: the same request after a fill where the leave-one-out part is cached
(``compute_self``: the labels' render, the self-agreement, the /render PNG). ``loo_compare``:
the two revisions' leave-one-out point sets, labels at their common points, rendered images.

The frame: ``--frame`` or the first annotated full-size frame of the source's truth
(``<source>/truth/meta.json``), its mask the source's truth mask. Prints one JSON object.

    .venv/bin/python bench/bench_review_open.py WS SOURCE --baseline d7b0818
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
from pathlib import Path
import numpy as np
ws, src, frame, rep, out = Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
sys.path.append(sys.argv[6])  # bench/: the survey stages' frame choice and truth mask
from _survey_stages import _truth_mask, review_frame
from occufly import render
from occufly.lifting import corrections as corr
from occufly.lifting import loo as L
from occufly.scene import Scene
try:  # what the revision's serving processes do to their allocator (app.serving)
    from app.serving import tune_allocator
except ImportError:
    tune_allocator = None
TUNED = bool(tune_allocator and tune_allocator())
scene = Scene.load(ws)
labels = np.asarray(corr.load_labels(ws).labels)
if frame < 0:
    frame = review_frame(ws, src, scene)
mask = _truth_mask(src, scene, frame)

def overlay(imgs):
    if hasattr(render, "disagreement_indices"):
        from app.pipeline import encode_png_palette
        return encode_png_palette(render.disagreement_indices(mask, imgs["loo"], scene.taxonomy),
                                  render.disagreement_palette(scene.taxonomy))
    from app.pipeline import encode_png
    return encode_png(render.disagreement_image(mask, imgs["loo"], scene.taxonomy))

def step():
    t, c = {}, time.process_time()
    loo = L.loo_labels(ws, scene, frame); t["loo_labels"] = time.process_time() - c
    c = time.process_time()
    imgs = L.render_review(scene, loo, mask.shape, labels); t["render_review"] = time.process_time() - c
    c = time.process_time()
    fig = L.loo_agreement(mask, imgs["loo"], scene, self_rendered=imgs["self"],
                          confident_rendered=imgs["confident"]); t["agreement"] = time.process_time() - c
    c = time.process_time()
    L.disagreeing_neighbours(ws, scene, frame, loo); t["neighbours"] = time.process_time() - c
    c = time.process_time()
    png = overlay(imgs); t["overlay_png"] = time.process_time() - c
    t["total"] = sum(t.values())
    return t, fig, loo, len(png)

def route():
    # the route's whole computation as it runs (app.review.service.compute_review, threads
    # included; before it existed, the steps one after another plus the /render PNG the
    # route encoded too): CPU and wall
    c, w = time.process_time(), time.perf_counter()
    try:
        from app.review.service import compute_review
    except ImportError:
        compute_review = None
    if compute_review is not None:
        r = compute_review(scene, ws, frame, mask, labels)
        nbytes = len(r["disagreement_png"])
    else:
        from app.pipeline import encode_png
        loo = L.loo_labels(ws, scene, frame)
        imgs = L.render_review(scene, loo, mask.shape, labels)
        encode_png(np.asarray(imgs["self"], np.uint8))
        L.loo_agreement(mask, imgs["loo"], scene, self_rendered=imgs["self"],
                        confident_rendered=imgs["confident"])
        L.disagreeing_neighbours(ws, scene, frame, loo)
        nbytes = len(overlay(imgs))
    return {"cpu": time.process_time() - c, "wall": time.perf_counter() - w, "bytes": nbytes}

def self_route():
    # what a frame's review computes after a fill when its leave-one-out part is cached
    # (app.review.service.compute_self: one label render, the self-agreement, the /render PNG)
    try:
        from app.review.service import compute_self
    except ImportError:
        return None
    c, w = time.process_time(), time.perf_counter()
    compute_self(scene, frame, mask, labels)
    return {"cpu": time.process_time() - c, "wall": time.perf_counter() - w}

step()
runs = [step() for _ in range(rep)]
t, fig, loo, nbytes = min(runs, key=lambda r: r[0]["total"])
route()
routes = [route() for _ in range(rep)]
self_route()
selfs = [r for r in (self_route() for _ in range(rep)) if r is not None]
np.savez(out, ids=loo.point_ids, labels=loo.labels,
         rendered=L.render_review(scene, loo, mask.shape)["loo"])
import occufly
print(json.dumps({"frame": int(frame), "size": [int(mask.shape[1]), int(mask.shape[0])],
                  "code": str(Path(occufly.__file__).resolve().parents[1]), "allocator_tuned": TUNED,
                  "points_gathered": int(len(loo.point_ids)),
                  "cpu_s": {k: round(v, 3) for k, v in t.items()},
                  "totals": [round(r[0]["total"], 3) for r in runs], "overlay_bytes": nbytes,
                  "agreement": fig["agreement"], "review_score": fig["review_score"],
                  "route_wall_s": [round(r["wall"], 3) for r in routes],
                  "route_cpu_s": [round(r["cpu"], 3) for r in routes],
                  "after_fill_wall_s": [round(r["wall"], 3) for r in selfs],
                  "after_fill_cpu_s": [round(r["cpu"], 3) for r in selfs]}))
"""


def code_tree(rev: str, dest: Path) -> Path:
    """``occufly/`` and ``app/`` of git revision ``rev`` extracted under ``dest``."""
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    arch = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "occufly", "app"],
                          capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(dest)], input=arch, check=True)
    return dest


def main() -> None:
    import numpy as np

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("source", type=Path, help="the synthetic project (its truth masks)")
    ap.add_argument("--frame", type=int, default=-1)
    ap.add_argument("--baseline", default="d7b0818", help="git revision to compare with")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"baseline": code_tree(args.baseline, Path(tmp) / "base"), "now": ROOT}
        runs: dict[str, list[dict]] = {k: [] for k in trees}
        for _ in range(args.rounds):
            for k, tree in trees.items():
                out = str(Path(tmp) / f"{k}.npz")
                # run outside the checkout: ``python -c`` puts its working directory first on
                # sys.path, ahead of PYTHONPATH, so from the repository root the baseline child
                # imported the working tree's occufly (both columns were today's code)
                p = subprocess.run([sys.executable, "-c", CHILD, str(args.workspace.resolve()),
                                    str(args.source.resolve()),
                                    str(args.frame), str(args.repeat), out, str(ROOT / "bench")],
                                   capture_output=True, cwd=tmp,
                                   text=True, env={**os.environ, "PYTHONPATH": str(tree)})
                if p.returncode:
                    sys.exit(f"{k} failed:\n{p.stderr[-3000:]}")
                runs[k].append(json.loads(p.stdout.strip().splitlines()[-1]))
        a, b = np.load(Path(tmp) / "baseline.npz"), np.load(Path(tmp) / "now.npz")
        same = bool(np.array_equal(a["ids"], b["ids"]) and np.array_equal(a["labels"], b["labels"]))
        # where the two decide a point both gather (the robust decision's models are fitted on
        # the points gathered, so a different set may change a few), and the rendered images
        common, ia, ib = np.intersect1d(a["ids"], b["ids"], return_indices=True)
        compare = {"points_baseline": int(len(a["ids"])), "points_now": int(len(b["ids"])),
                   "points_common": int(len(common)),
                   "labels_equal_share_at_common": round(float(
                       (a["labels"][ia] == b["labels"][ib]).mean()) if len(common) else 1.0, 6),
                   "rendered_pixels_equal_share": round(float(
                       (a["rendered"] == b["rendered"]).mean()), 6)}
    best = {k: min(rs, key=lambda r: r["cpu_s"]["total"]) for k, rs in runs.items()}
    res = {"benchmark": "review_open", "workspace": str(args.workspace), "baseline": args.baseline,
           "load_avg": os.getloadavg(), "cpus": os.cpu_count(), "repeat": args.repeat,
           "rounds": args.rounds, "best": best,
           "totals": {k: [r["cpu_s"]["total"] for r in rs] for k, rs in runs.items()},
           "ratio_now_to_baseline": round(best["now"]["cpu_s"]["total"]
                                          / best["baseline"]["cpu_s"]["total"], 3),
           "loo_labels_identical": same, "loo_compare": compare,
           "budget_first_open_le_1s_cpu": best["now"]["cpu_s"]["total"] <= 1.0,
           "route_wall_s": {k: min(w for r in rs for w in r["route_wall_s"]) for k, rs in runs.items()},
           "route_cpu_s": {k: min(w for r in rs for w in r["route_cpu_s"]) for k, rs in runs.items()},
           "after_fill_wall_s": {k: min((w for r in rs for w in r.get("after_fill_wall_s", [])),
                                        default=None) for k, rs in runs.items()}}
    res["budget_first_open_le_1s_wall"] = res["route_wall_s"]["now"] <= 1.0
    text = json.dumps(res, indent=1)
    if args.json:
        args.json.write_text(text)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
