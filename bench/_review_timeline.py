"""A reviewer's open of a frame as a timeline: ``app.review.service.compute_review`` run
``--repeat`` times in one fresh process (the first run is what a fresh API process's first
review pays: the point bins, numba's cached kernels, the features cache), each run's wall and
CPU, then the last run's steps by thread (start, duration, end).

    .venv/bin/python bench/_review_timeline.py WS SOURCE [--frame 52] [--repeat 3]

Not a benchmark of record (``bench_review_open.py`` is): one JSON line of the totals, then
the timeline."""

from __future__ import annotations

import argparse
import functools
import json
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from app import pipeline  # noqa: E402
from app.review import service  # noqa: E402
from occufly.io.masks import read_mask  # noqa: E402
from occufly.lifting import (
    load_labels,  # noqa: E402
    robust,  # noqa: E402
)
from occufly.lifting import loo as loo_mod  # noqa: E402
from occufly.scene import Scene  # noqa: E402

LOG: list[tuple[str, str, float, float]] = []
T0 = [0.0]


def _wrap(mod, name: str) -> None:  # noqa: ANN001
    fn = getattr(mod, name)

    @functools.wraps(fn)
    def w(*a, **k):  # noqa: ANN002, ANN003, ANN202
        t = time.perf_counter()
        try:
            return fn(*a, **k)
        finally:
            LOG.append((threading.current_thread().name[:16], name, t - T0[0],
                        time.perf_counter() - t))

    setattr(mod, name, w)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("source", type=Path, help="the synthetic source (truth/masks/*.png)")
    ap.add_argument("--frame", type=int, default=52)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--warm-frame", type=int, default=None,
                    help="first review this frame (untimed in the runs, reported as warm_up): "
                         "a server process after its start's warm-up (warm_process_start)")
    a = ap.parse_args()
    for n in ("loo_labels", "frame_geometry", "neighbour_votes", "disagreeing_neighbours",
              "render_review", "_robust_decision", "_fill_vote", "loo_winner", "loo_agreement"):
        _wrap(loo_mod, n)
    for n in ("redecide", "_fit_qda", "estimate_confusion", "local_votes"):
        _wrap(robust, n)
    for n in ("encode_png", "encode_png_palette"):
        _wrap(pipeline, n)
    scene = Scene.load(a.workspace)
    labels = np.asarray(load_labels(a.workspace).labels)
    fr = scene.frames[a.frame]
    path = a.source / "truth" / "masks" / (Path(fr.name).stem + ".png")
    data = path.read_bytes()

    def mask() -> np.ndarray:
        t = time.perf_counter()
        m = read_mask(data, fr, scene.taxonomy, name=str(path))
        LOG.append((threading.current_thread().name[:16], "mask decode", t - T0[0],
                    time.perf_counter() - t))
        return m

    warm = None
    if a.warm_frame is not None:
        wf = scene.frames[a.warm_frame]
        wpath = a.source / "truth" / "masks" / (Path(wf.name).stem + ".png")
        wmask = read_mask(wpath.read_bytes(), wf, scene.taxonomy, name=str(wpath))
        t, c = time.perf_counter(), time.process_time()
        service.compute_review(scene, a.workspace, a.warm_frame, wmask, labels)
        warm = {"frame": a.warm_frame, "wall_s": round(time.perf_counter() - t, 3),
                "cpu_s": round(time.process_time() - c, 3)}
    runs = []
    for _ in range(max(1, a.repeat)):
        LOG.clear()
        T0[0], c = time.perf_counter(), time.process_time()
        service.compute_review(scene, a.workspace, a.frame, mask, labels)
        runs.append({"wall_s": round(time.perf_counter() - T0[0], 3),
                     "cpu_s": round(time.process_time() - c, 3)})
    print(json.dumps({"frame": a.frame, "size": [fr.camera.width, fr.camera.height],
                      "warm_up": warm, "first_run": runs[0], "later_runs": runs[1:]}))
    for th, n, t, d in sorted(LOG, key=lambda e: e[2]):
        print(f"{th:17s} {n:24s} {t:6.3f} + {d:6.3f} -> {t + d:6.3f}")


if __name__ == "__main__":
    main()
