"""Review ranking benchmark (issue 23): does the leave-one-out agreement find wrong masks?

On a synthetic scene (``small``, ``bench``) the exact masks of the stratified selection are
lifted with ``k`` of them replaced by wrong masks, one per kind: classes permuted, shifted
20 px, half unpainted, one class painted everywhere. For every lifted frame the review figures
are computed (:mod:`occufly.lifting.loo`: LOO agreement, self-agreement, independent coverage,
painted share), and the ranking of wrong against right frames is scored by the AUC (wrong =
positive; frames without enough independent views sort after the scored ones, as in the
list) for the LOO agreement, the old self-agreement, LOO agreement x painted share, and the
review list's ranking score (:func:`occufly.lifting.loo.review_score`: the share of the
confidently, independently labelled area the mask does not reproduce, plus the shift test's
gain; every frame with any such pixel is ranked by it, the coverage threshold only decides what
the page says); and by how many frames a reviewer opens in list order before every wrong one is
found. ``--seed`` picks other wrong frames, ``--k 8`` puts two of each kind in.

The votes are counted in a private folder (``--cache``), the synthetic scenes are shared
with bench_calibration's cache layout. Prints one JSON object.

    .venv/bin/python bench/bench_review.py --presets small
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

from _scene import ensure_seeded_scene  # noqa: E402

from occufly.io.masks import read_mask  # noqa: E402
from occufly.lifting.knn import LiftParams  # noqa: E402
from occufly.lifting.loo import frame_loo  # noqa: E402
from occufly.lifting.votes import VoteStore, _npz_bytes, fill_snapshot  # noqa: E402
from occufly.scene import Scene  # noqa: E402
from occufly.selection import select_frames  # noqa: E402
from occufly.workspace import Workspace  # noqa: E402

KINDS = ("permuted", "shifted", "half", "one_class")


def wrong_mask(m: np.ndarray, kind: str, ids: np.ndarray, rng) -> np.ndarray:
    out = m.copy()
    valid = (m > 0) & (m < 255)
    if kind == "permuted":
        present = np.unique(m[valid])
        perm = np.roll(present, 1) if len(present) > 1 else present
        lut = np.arange(256, dtype=np.uint8)
        lut[present] = perm
        out = lut[m]
    elif kind == "shifted":
        out = np.roll(m, 20, axis=1)
        out[:, :20] = 0
    elif kind == "half":
        out[:, m.shape[1] // 2:] = 0
    elif kind == "one_class":
        vals, cnt = np.unique(m[valid], return_counts=True)
        out[valid] = vals[np.argmax(cnt)]
    return out


def auc(score: np.ndarray, wrong: np.ndarray) -> float:
    """P(score of a wrong frame > score of a right one), ties count half."""
    s_w, s_r = score[wrong], score[~wrong]
    if not len(s_w) or not len(s_r):
        return float("nan")
    gt = (s_w[:, None] > s_r[None, :]).mean()
    eq = (s_w[:, None] == s_r[None, :]).mean()
    return float(gt + 0.5 * eq)


def list_score(agree: list, cov: list, floor: float) -> np.ndarray:
    """Higher = earlier in the review list: 1 - agreement; not enough views after all scored."""
    out = []
    for a, c in zip(agree, cov, strict=True):
        out.append(-1.0 - (1.0 - c) if a is None or c < floor else 1.0 - a)
    return np.asarray(out)


def run(cache: Path, preset: str, k: int, floor: float, seed: int = 0,
        decisions: tuple[str, ...] = ("robust",)) -> dict:
    syn, ws = ensure_seeded_scene(cache, preset, 0)
    scene = Scene.load(ws)
    tax = scene.taxonomy
    sel = [int(f) for f in select_frames(scene, mode="stratified").frames]
    rng = np.random.default_rng(seed)
    wrong_idx = [int(x) for x in rng.choice(sel, size=min(k, len(sel)), replace=False)]
    kinds = {fi: KINDS[i % len(KINDS)] for i, fi in enumerate(wrong_idx)}
    masks = {}
    for fi in sel:
        fr = scene.frames[fi]
        m = read_mask(syn / "truth" / "masks" / f"{fr.stem}.png", fr, tax)
        masks[fi] = wrong_mask(m, kinds[fi], tax.ids, rng) if fi in kinds else m
    votes_ws = cache / f"review-{preset}-votes-k{k}-s{seed}"
    w = Workspace(votes_ws)
    w.lifting_frames_dir.mkdir(parents=True, exist_ok=True)
    C = len(tax.ids)
    st = VoteStore(votes_ws, scene, np.zeros((scene.n_points, C), np.uint16), {})
    flat = st.votes.reshape(-1)
    t0 = time.perf_counter()
    for fi, m in masks.items():
        pids, cols, wt = st.frame_votes(fi, m)
        np.add.at(flat, pids.astype(np.int64) * C + cols, wt)
        w.lifting_frame(fi).write_bytes(_npz_bytes(point_ids=pids, cols=cols, weights=wt))
        st._versions[int(fi)] = "bench"
    np.save(w.votes, st.votes)
    # read_only=False: the robust decision's point features are cached in the private folder
    # (the app's fill writes them too), so every LOO decision reads them
    res = fill_snapshot(scene, st.snapshot(), params=LiftParams(), ws=votes_ws, read_only=False)
    t_lift = time.perf_counter() - t0
    out = {"preset": preset, "points": scene.n_points, "frames_lifted": len(masks),
           "wrong": {str(fi): kd for fi, kd in kinds.items()}, "lift_s": round(t_lift, 2)}
    for dec in decisions:
        out[dec] = score(votes_ws, scene, masks, kinds, res, dec, floor)
    return out


def score(votes_ws: Path, scene: Scene, masks: dict, kinds: dict, res, decision: str,
          floor: float) -> dict:
    """The review figures of every lifted frame with the LOO labels decided by ``decision``:
    ``robust`` (the pipeline's robust decision without the frame, the default) or ``plain``
    (the raw majority of the other frames' votes: the LOO labels before issue 40)."""
    params = LiftParams(robust=decision == "robust")
    rows, t1 = [], time.perf_counter()
    for fi, m in masks.items():
        o = frame_loo(votes_ws, scene, fi, m, self_labels=np.asarray(res.labels), params=params,
                      neighbours=True)
        rows.append({"frame": fi, "wrong": kinds.get(fi), "agreement": o["agreement"],
                     "self_agreement": o["self_agreement"],
                     "independent_coverage": round(o["independent_coverage"], 4),
                     "painted_share": round(o["painted_share"], 4),
                     "review_score": o["review_score"],
                     "area_agreement": o["area_agreement"],
                     "area_share": round(o["area_share"], 4),
                     "shift_gain": round(o["shift_gain"], 4),
                     "neighbours": o["neighbours"][:2]})
    t_loo = (time.perf_counter() - t1) / max(len(rows), 1)
    wrong = np.array([r["wrong"] is not None for r in rows])
    cov = [r["independent_coverage"] for r in rows]
    s_loo = list_score([r["agreement"] for r in rows], cov, floor)
    s_self = np.array([1.0 - (r["self_agreement"] or 0.0) for r in rows])
    s_both = list_score([None if r["agreement"] is None else r["agreement"] * r["painted_share"]
                         for r in rows], cov, floor)
    s_rank = np.array([-1.0 if r["review_score"] is None else r["review_score"] for r in rows])

    def opened(score: np.ndarray) -> int:
        order = np.argsort(-score, kind="stable")
        pos = np.flatnonzero(wrong[order])
        return int(pos.max() + 1) if len(pos) else 0

    right = [r["agreement"] for r in rows if not r["wrong"] and r["agreement"] is not None]
    right_cov = [r["agreement"] for r in rows if not r["wrong"] and r["agreement"] is not None
                 and r["independent_coverage"] >= floor]
    return {"auc_loo": round(auc(s_loo, wrong), 4), "auc_self": round(auc(s_self, wrong), 4),
            "auc_loo_x_painted_share": round(auc(s_both, wrong), 4),
            "auc_review_score": round(auc(s_rank, wrong), 4),
            "opened_before_all_wrong_found": {"loo": opened(s_loo), "self": opened(s_self),
                                              "loo_x_painted_share": opened(s_both),
                                              "review_score": opened(s_rank)},
            "loo_per_frame_s": round(t_loo, 3),
            "wrong_frames": [r for r in rows if r["wrong"]],
            "wrong_frames_loo_max": max((r["agreement"] for r in rows if r["wrong"]
                                         and r["agreement"] is not None), default=None),
            "right_frames_review_score_max": max((r["review_score"] for r in rows
                                                  if not r["wrong"] and r["review_score"] is not None),
                                                 default=None),
            "right_frames_loo": {"min": min(right, default=None),
                                 "median": float(np.median(right)) if right else None,
                                 "below_0.75": sum(1 for a in right if a < 0.75),
                                 "min_with_coverage": min(right_cov, default=None),
                                 "not_enough_views": sum(1 for r in rows if not r["wrong"]
                                                         and (r["agreement"] is None
                                                              or r["independent_coverage"] < floor))},
            "right_frames_lowest": sorted((r for r in rows if not r["wrong"]
                                           and r["agreement"] is not None),
                                          key=lambda r: r["agreement"])[:3]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", default="small,bench")
    ap.add_argument("--k", type=int, default=4, help="wrong masks (one kind each, cycled)")
    ap.add_argument("--min-coverage", type=float, default=0.5)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-review"))
    ap.add_argument("--seed", type=int, default=0, help="which frames get the wrong masks")
    ap.add_argument("--decisions", default="robust,plain",
                    help="LOO decisions scored on the same lift: robust (the pipeline's robust "
                         "decision without the frame, the review's) and/or plain (the raw "
                         "majority of the other frames' votes, the review before issue 40)")
    ap.add_argument("--json", type=Path, help="also write the JSON here")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    out = {"bench": "review", "k": args.k, "seed": args.seed,
           "min_independent_coverage": args.min_coverage,
           "scenes": [run(args.cache, p, args.k, args.min_coverage, args.seed,
                          tuple(args.decisions.split(",")))
                      for p in args.presets.split(",")]}
    out["seconds"] = round(time.perf_counter() - t0, 1)
    text = json.dumps(out, indent=1, default=float)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
