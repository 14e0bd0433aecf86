"""What one save costs the live fill with the robust decision's model held (issue 37, eighth round).

Prints one JSON object. The app fills a scene after every save, incrementally (the k-NN passes
rerun only around the points whose decided label changed; ``IncrementalFill``). The robust
decision fitted its annotator model and classifier again at every fill, which flipped near-tie
labels across the scene, so every save ran a full fill. ``IncrementalFill.held``
(``occufly.lifting.robust.HeldDecision``) keeps the model between fills and decides again only
around the changed votes.

On a synthetic scene imported into ``--ws``, the greedy rho 0.99 frames are painted by the crew
(``occufly.synthetic.noise``) or with degrade.py (``--noise degraded``), lifted and filled once,
then ``--saves`` corrections are saved one after the other: a reviewer repaints a
``--brush`` px square of a frame's mask with the exact mask, around a pixel where the painted
mask is wrong (``--whole``: whole frames replaced by their exact masks instead). After each
save two fills run on the same vote snapshot, in the same process:

* ``held``: the fill with the model kept (what the app runs now);
* ``refit``: the same fill with the held model dropped first (what it ran before: the model
  fitted again from all votes, the k-NN passes wherever a label flipped).

Reported per save: CPU seconds of each, the points the k-NN passes updated, how many final
labels differ between the two, and each one's accuracy / mIoU against the point truth. Ratios
are of CPU seconds (the machine may be shared).

    .venv/bin/python bench/bench_lifting_held.py --synthetic SYN --ws WS --seed 0
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _scene import greedy_truth, scratch_workspace  # noqa: E402

from occufly.lifting import VoteStore  # noqa: E402
from occufly.lifting.incremental import IncrementalFill  # noqa: E402
from occufly.metrics import evaluate_points  # noqa: E402
from occufly.synthetic.degrade import degrade_masks  # noqa: E402
from occufly.synthetic.noise import crew_masks  # noqa: E402


def _fill(st: VoteStore, snap, inc: IncrementalFill) -> tuple:  # noqa: ANN001
    t, c = time.perf_counter(), time.process_time()
    res = st.fill_and_denoise(snapshot=snap, incremental=inc)
    return res, time.perf_counter() - t, time.process_time() - c


def _row(res, wall: float, cpu: float, truth: np.ndarray, tax) -> dict:  # noqa: ANN001
    ev = evaluate_points(res.labels, truth, tax, res.origin)
    inc = res.stats.get("incremental") or {}
    return {"seconds": round(wall, 2), "cpu_seconds": round(cpu, 2),
            "robust_seconds": res.stats.get("robust_seconds"),
            "warm": bool(res.stats.get("robust_warm")),
            "robust_decided": res.stats.get("robust_warm_decided"),
            "cold_why": res.stats.get("robust_cold_why"),
            "knn_incremental": bool(inc.get("incremental")),
            "updated_points": inc.get("updated_points"),
            "accuracy": round(ev["accuracy"], 4), "miou": round(ev["miou"], 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synthetic", type=Path, required=True, help="the occufly synth folder (truth)")
    ap.add_argument("--ws", type=Path, required=True, help="its imported workspace")
    ap.add_argument("--seed", type=int, default=0, help="the painters' and the saves' seed")
    ap.add_argument("--noise", default="crew", choices=("crew", "degraded"))
    ap.add_argument("--saves", type=int, default=8, help="corrections saved after the first fill")
    ap.add_argument("--brush", type=int, default=40, help="side of the repainted square, px")
    ap.add_argument("--whole", action="store_true", help="whole frames repainted exactly")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-bench-held"))
    args = ap.parse_args()

    scene, truth, _sel, exact = greedy_truth(args.synthetic, args.ws)
    tax = scene.taxonomy
    if args.noise == "crew":
        masks, _who = crew_masks(exact, tax, seed=args.seed)
    else:
        masks = degrade_masks(exact, tax, seed=args.seed)
    rng = np.random.default_rng(args.seed + 100)
    tmp = scratch_workspace(args.cache / "ws", args.ws)
    st = VoteStore.open(tmp, scene)
    for fi, m in masks.items():
        st.apply_frame(fi, m, version=f"painted{fi}")
    held, refit = IncrementalFill(scene.xyz, tax), IncrementalFill(scene.xyz, tax)
    snap = st.snapshot()
    res_h, wall, cpu = _fill(st, snap, held)
    first = _row(res_h, wall, cpu, truth, tax)
    _fill(st, snap, refit)
    out: dict = {"bench": "lifting_held", "points": scene.n_points, "frames": len(masks),
                 "noise": args.noise, "brush_px": None if args.whole else args.brush,
                 "first_fill": first, "saves": []}
    current = {fi: m.copy() for fi, m in masks.items()}
    order = sorted(current)
    for k in range(args.saves):
        if args.whole:
            fi = order[k % len(order)]
            current[fi] = exact[fi].copy()
            what = {"frame": scene.frames[fi].name, "pixels": int((masks[fi] != exact[fi]).sum())}
        else:
            wrong = {fi: np.argwhere(current[fi] != exact[fi]) for fi in order}
            fi = int(rng.choice([f for f in order if len(wrong[f])]))
            y, x = wrong[fi][rng.integers(len(wrong[fi]))]
            h = args.brush // 2
            sl = (slice(max(0, y - h), y + h), slice(max(0, x - h), x + h))
            before = current[fi][sl].copy()
            current[fi][sl] = exact[fi][sl]
            what = {"frame": scene.frames[fi].name,
                    "pixels": int((before != current[fi][sl]).sum())}
        st.apply_frame(fi, current[fi], version=f"save{k}")
        snap = st.snapshot()
        res_h, wall_h, cpu_h = _fill(st, snap, held)
        refit.held.clear()  # the model fitted again from all votes, as every fill did before
        res_r, wall_r, cpu_r = _fill(st, snap, refit)
        row = {**what, "held": _row(res_h, wall_h, cpu_h, truth, tax),
               "refit": _row(res_r, wall_r, cpu_r, truth, tax),
               "labels_differing": int(np.count_nonzero(res_h.labels != res_r.labels))}
        out["saves"].append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    # once the scene is quiet: the model fitted again on the held chain gives the refit labels
    held.held.clear()
    snap = st.snapshot()
    res_c, wall, cpu = _fill(st, snap, held)
    out["settled"] = {**_row(res_c, wall, cpu, truth, tax),
                      "labels_differing_from_refit": int(np.count_nonzero(res_c.labels
                                                                          != res_r.labels))}
    cpu_h = [s["held"]["cpu_seconds"] for s in out["saves"]]
    cpu_r = [s["refit"]["cpu_seconds"] for s in out["saves"]]
    out["save_cpu_seconds_mean"] = {"held": round(float(np.mean(cpu_h)), 2),
                                    "refit": round(float(np.mean(cpu_r)), 2)}
    out["ratio_save_cpu"] = round(float(np.mean(cpu_h)) / max(1e-9, float(np.mean(cpu_r))), 3)
    st.close()
    print(json.dumps(out))


if __name__ == "__main__":
    main()
