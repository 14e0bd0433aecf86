"""How far better masks or a better annotator model could take the lifting (issue 37).

Prints one JSON object. On a synthetic scene imported into ``--ws`` (``occufly synth`` then
``occufly import``), the greedy rho 0.99 frames are lifted with the default robust decision
from their exact masks, from degrade.py's masks, and from degrade.py's masks with one kind of
error taken back using the synthetic truth -- which no method has, so each figure is a
ceiling, not a result:

``degraded_swaps_repaired``
    the whole regions degrade.py painted as their look-alike (away from the exact masks'
    class boundaries) painted back to their true class;
``degraded_boundaries_repaired``
    every painted pixel within ``--band`` px of an exact class boundary that differs from the
    exact mask painted back: the boundary drift, and the small objects skipped or shifted;
``degraded_both_repaired``
    both;
``degraded_true_annotator_model``
    the degraded masks as they are, but the robust decision's pooled confusion matrix
    replaced by the one counted from the truth (every vote against its point's true class):
    what a perfect annotator model would give (decided without the refit rounds, which
    would count the matrix again from the labels).

Every other run decides with the library's defaults (since 6dce21b: with the refit rounds;
``docs/bench/lifting_issue37_round5_2026-12-07.json`` was measured at d226f0e, before them).

The baseline is the first run (``degraded``), in the same process. Each run also reports the
share of painted pixels still wrong (``pixels_wrong``) and the error breakdown of
``bench_lifting.error_breakdown``.

``causes`` (issue 37, sixth round): the points the default lifting of degrade.py's masks gets
wrong, each put in one group by the effect of degrade.py (:func:`degrade_stages`) that made most
of its wrong votes -- ``geometry`` (the exact mask is wrong there too: projection, occlusion
edges), ``boundaries`` (drift), ``skipped`` (small objects painted as their surroundings),
``confused`` (whole regions painted as their look-alike) -- or ``no_wrong_vote``; shares of
all points with a truth class, and each group's top (true, lifted) pairs.

    .venv/bin/python bench/bench_lifting_bounds.py --synthetic SYN --ws WS --seed 0
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _scene import greedy_truth, scratch_workspace  # noqa: E402
from bench_lifting import error_breakdown  # noqa: E402

from occufly.lifting import LiftParams, RobustParams, VoteStore  # noqa: E402
from occufly.lifting import robust as robust_mod  # noqa: E402
from occufly.lifting.votes import frame_mask_pixels  # noqa: E402
from occufly.metrics import evaluate_points  # noqa: E402
from occufly.scene import Scene  # noqa: E402
from occufly.synthetic.degrade import _confusion_lut, degrade_masks, degrade_stages  # noqa: E402


def boundary_band(mask: np.ndarray, band: int) -> np.ndarray:
    """Pixels within ``band`` px of a class boundary of ``mask``."""
    edge = ndimage.morphological_gradient(mask, size=3) > 0
    return ndimage.binary_dilation(edge, iterations=band) if band > 0 else edge


CAUSES = ("geometry", "boundaries", "skipped", "confused")


def wrong_vote_causes(scene: Scene, exact: dict, seed: int, labels: np.ndarray,
                      truth: np.ndarray) -> dict:
    """Where the wrong points of a lifting of ``degrade_masks(exact, seed)`` come from: each
    point by the degrade.py effect behind most of its wrong votes (module docstring)."""
    tax = scene.taxonomy
    names = {c.id: c.name for c in tax.classes}
    wrong_votes = np.zeros((len(truth), len(CAUSES)), np.int32)
    for fi, m in exact.items():
        stages = [m] + [s for _n, s in degrade_stages(m, tax, np.random.default_rng([seed, int(fi)]))]
        painted = stages[-1]
        cause = np.zeros(m.shape, np.int64)  # geometry unless an effect changed the pixel
        for k in range(1, len(CAUSES)):
            cause[stages[k] != stages[k - 1]] = k
        pids, row, col = frame_mask_pixels(scene, fi, m.shape)
        raw = painted[row, col]
        bad = (raw != 0) & (raw != truth[pids])
        np.add.at(wrong_votes, (pids[bad], cause[row[bad], col[bad]]), 1)
    valid = (truth > 0) & (truth < 255)
    n = max(1, int(valid.sum()))
    wrong = valid & (labels != truth)
    dom = np.where(wrong_votes.sum(axis=1) > 0, np.argmax(wrong_votes, axis=1), len(CAUSES))
    out: dict = {}
    for k, name in enumerate((*CAUSES, "no_wrong_vote")):
        m = wrong & (dom == k)
        key = truth[m].astype(np.int64) * 256 + labels[m]
        u, c = np.unique(key, return_counts=True)
        top = np.argsort(-c, kind="stable")[:5]
        out[name] = {"share": round(float(m.sum() / n), 5),
                     "pairs": [[names.get(int(u[i] // 256)), names.get(int(u[i] % 256), "unlabelled"),
                                round(float(c[i] / n), 5)] for i in top]}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synthetic", type=Path, required=True, help="the occufly synth folder (truth)")
    ap.add_argument("--ws", type=Path, required=True, help="its imported workspace")
    ap.add_argument("--seed", type=int, default=0, help="degrade.py's seed")
    ap.add_argument("--band", type=int, default=4, help="px either side of an exact boundary")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-bench"))
    ap.add_argument("--causes-only", action="store_true",
                    help="only the default lifting of degrade.py's masks and its causes")
    args = ap.parse_args()

    scene, truth, sel, exact = greedy_truth(args.synthetic, args.ws)
    tax = scene.taxonomy
    degraded = degrade_masks(exact, tax, seed=args.seed)
    lut = _confusion_lut(tax)
    bands = {fi: boundary_band(m, args.band) for fi, m in exact.items()}
    swapped = {fi: (degraded[fi] != m) & (lut[m] == degraded[fi]) & (lut[m] != m) & ~bands[fi]
               for fi, m in exact.items()}
    drifted = {fi: (degraded[fi] != m) & (degraded[fi] != 0) & bands[fi] for fi, m in exact.items()}

    def repaired(which: dict) -> dict:
        return {fi: np.where(which[fi], exact[fi], degraded[fi]).astype(np.uint8) for fi in exact}

    true_pi: dict = {}
    labels_of: dict = {}

    def lift(masks: dict, *, with_true_pi: bool = False) -> dict:
        tmp = scratch_workspace(args.cache / "bounds-ws", args.ws)
        st = VoteStore.open(tmp, scene)
        for fi in sel.frames:
            st.apply_frame(fi, masks[fi], version="bounds")
        estimate = robust_mod.estimate_confusion
        if with_true_pi:
            # the pooled matrix counted from the truth, with the EM's own Dirichlet prior
            cls = st._cls
            counts = np.zeros((cls.C, cls.C))
            for fi in sel.frames:
                pids, cols, _ = st.frame_votes(fi, masks[fi])
                tcol = cls.col_of[truth[pids]]
                ok = tcol >= 0
                np.add.at(counts, (tcol[ok], cols[ok].astype(np.int64)), 1)

            def true_matrix(c1, n1, c2, n2, C, p):  # noqa: ANN001, ANN202
                _pi, prior = estimate(c1, n1, c2, n2, C, p)
                a = counts + p.off_prior + p.diag_prior * np.eye(C)
                true_pi["matrix"] = a / a.sum(axis=1, keepdims=True)
                return true_pi["matrix"], prior

            robust_mod.estimate_confusion = true_matrix
        try:
            t = time.perf_counter()
            # the true matrix decides as it is: no refit rounds re-count it from the labels
            params = (LiftParams(robust_params=RobustParams(refit_rounds=0)) if with_true_pi
                      else LiftParams())
            res = st.fill_and_denoise(write=False, params=params)
            sec = time.perf_counter() - t
        finally:
            robust_mod.estimate_confusion = estimate
        ev = evaluate_points(res.labels, truth, tax, res.origin)
        labels_of.setdefault(id(masks), np.asarray(res.labels))  # the default's, not the ceilings'
        out = {"accuracy": round(ev["accuracy"], 4), "miou": round(ev["miou"], 4),
               "pixels_wrong": round(float(np.mean([((masks[f] != exact[f]) & (masks[f] != 0)).mean()
                                                    for f in exact])), 4),
               "errors": error_breakdown(np.asarray(st.votes), st._cls, st.direct_labels(),
                                         np.asarray(res.labels), truth, tax),
               "fill_seconds": round(sec, 2)}
        st.close()
        shutil.rmtree(tmp, ignore_errors=True)
        return out

    out: dict = {"bench": "lifting-bounds", "synthetic": str(args.synthetic), "seed": args.seed,
                 "points": scene.n_points, "frames": len(scene.frames), "selected": len(sel.frames),
                 "band_px": args.band,
                 "pixels_swapped": round(float(np.mean([s.mean() for s in swapped.values()])), 4),
                 "pixels_in_band_wrong": round(float(np.mean([d.mean() for d in drifted.values()])), 4)}
    runs = {"degraded": lambda: lift(degraded), "exact": lambda: lift(exact),
            "degraded_swaps_repaired": lambda: lift(repaired(swapped)),
            "degraded_boundaries_repaired": lambda: lift(repaired(drifted)),
            "degraded_both_repaired": lambda: lift(repaired({f: swapped[f] | drifted[f] for f in exact})),
            "degraded_true_annotator_model": lambda: lift(degraded, with_true_pi=True)}
    if args.causes_only:
        runs = {"degraded": runs["degraded"]}
    for name, run in runs.items():
        out[name] = run()
        print(json.dumps({name: {k: out[name][k] for k in ("accuracy", "miou", "pixels_wrong")}}),
              file=sys.stderr, flush=True)
    out["causes"] = wrong_vote_causes(scene, exact, args.seed, labels_of[id(degraded)], truth)
    base = out["degraded"]
    for name in runs:
        if name != "degraded":
            out[name]["gain_points"] = [round(100 * (out[name]["accuracy"] - base["accuracy"]), 2),
                                        round(100 * (out[name]["miou"] - base["miou"]), 2)]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
