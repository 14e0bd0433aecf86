"""The live lifting's annotator models in the app (issue 37, seventh round): what one save costs.

Prints one JSON object. The app fills a scene after every save, incrementally (the k-NN passes
rerun only around the points whose decided label changed; ``IncrementalFill``); an admin picks
the scene's annotator model (``LiftStatus.model``). On a synthetic scene imported into
``--ws``, the greedy rho 0.99 frames are painted by the crew (``occufly.synthetic.noise``: a
sloppy painter among careful ones, who painted each frame known, as the app knows its mask
authors), lifted and filled once (the first fill is a full one), then ``--saves`` frames are
saved again as the reviewer fixed them (the crew mask replaced by the exact one, the sloppy
painter's frames first), each followed by the fill the app runs, with the same inputs the
worker passes (``app.lifting.service.decision_for``: the model's parameters, frame -> author,
every frame's votes). The baseline is ``pooled`` (the default), in the same process; ratios
are of CPU seconds (the machine may be shared).

    .venv/bin/python bench/bench_lifting_models.py --synthetic SYN --ws WS --seed 0
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _scene import greedy_truth, scratch_workspace  # noqa: E402

from occufly.lifting import LiftParams, RobustParams, VoteStore  # noqa: E402
from occufly.lifting.confusion import ConfusionParams, load_frame_votes  # noqa: E402
from occufly.lifting.incremental import IncrementalFill  # noqa: E402
from occufly.lifting.regions import RegionParams  # noqa: E402
from occufly.metrics import evaluate_points  # noqa: E402
from occufly.synthetic.noise import Crew, crew_masks  # noqa: E402

# the app's models (app/lifting/models.py LIFT_MODELS) as decision_for builds them
MODELS = {"pooled": None,
          "per_author": LiftParams(robust_params=RobustParams(confusion=ConfusionParams())),
          "regions": LiftParams(robust_params=RobustParams(regions=RegionParams()))}


def _fill(st: VoteStore, inc: IncrementalFill, params, who: dict) -> tuple:  # noqa: ANN001
    """One fill as the app's worker runs it: (result, wall s, CPU s)."""
    t, c = time.perf_counter(), time.process_time()
    snap = st.snapshot()
    annotators = None
    if params is not None:
        snap.frame_votes = load_frame_votes(st.ws, sorted(snap.versions))
        annotators = who
    res = st.fill_and_denoise(snapshot=snap, incremental=inc, params=params,
                              annotators=annotators)
    return res, time.perf_counter() - t, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synthetic", type=Path, required=True, help="the occufly synth folder (truth)")
    ap.add_argument("--ws", type=Path, required=True, help="its imported workspace")
    ap.add_argument("--seed", type=int, default=0, help="the crew's seed")
    ap.add_argument("--saves", type=int, default=3, help="frames saved again after the first fill")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-bench-models"))
    args = ap.parse_args()

    scene, truth, _sel, exact = greedy_truth(args.synthetic, args.ws)
    tax = scene.taxonomy
    crew = Crew()
    masks, who = crew_masks(exact, tax, seed=args.seed, crew=crew)
    fixed = sorted(masks, key=lambda f: (who[f] >= crew.sloppy, f))[:args.saves]
    out: dict = {"bench": "lifting_models", "points": scene.n_points, "frames": len(masks),
                 "painters": len(set(who.values())),
                 "sloppy_frames": sum(1 for a in who.values() if a < crew.sloppy),
                 "saves": [scene.frames[f].name for f in fixed]}
    for name, params in MODELS.items():
        tmp = scratch_workspace(args.cache / name, args.ws)
        st = VoteStore.open(tmp, scene)
        for fi, m in masks.items():
            st.apply_frame(fi, m, version=f"crew{fi}")
        inc = IncrementalFill(scene.xyz, tax)
        res, wall, cpu = _fill(st, inc, params, who)
        ev = evaluate_points(res.labels, truth, tax, res.origin)
        row = {"first_fill": {"seconds": round(wall, 2), "cpu_seconds": round(cpu, 2),
                              "accuracy": round(ev["accuracy"], 4), "miou": round(ev["miou"], 4),
                              "decision": res.stats.get("decision")},
               "saves": []}
        for fi in fixed:
            st.apply_frame(fi, exact[fi], version=f"fixed{fi}")
            res, wall, cpu = _fill(st, inc, params, who)
            ev = evaluate_points(res.labels, truth, tax, res.origin)
            inc_stats = res.stats.get("incremental") or {}
            row["saves"].append({"seconds": round(wall, 2), "cpu_seconds": round(cpu, 2),
                                 "updated_points": inc_stats.get("updated_points"),
                                 "accuracy": round(ev["accuracy"], 4), "miou": round(ev["miou"], 4)})
        row["save_cpu_seconds_mean"] = round(float(np.mean([s["cpu_seconds"] for s in row["saves"]])), 2) \
            if row["saves"] else None
        out[name] = row
        st.close()
        shutil.rmtree(tmp, ignore_errors=True)
        print(json.dumps({name: row}), file=sys.stderr, flush=True)
    base = out["pooled"]
    for name in MODELS:
        if name == "pooled":
            continue
        out[name]["ratio_first_fill_cpu"] = round(out[name]["first_fill"]["cpu_seconds"]
                                                  / max(1e-9, base["first_fill"]["cpu_seconds"]), 2)
        if base["save_cpu_seconds_mean"]:
            out[name]["ratio_save_cpu"] = round(out[name]["save_cpu_seconds_mean"]
                                                / base["save_cpu_seconds_mean"], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
