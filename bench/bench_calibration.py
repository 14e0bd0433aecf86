"""Calibration benchmark: is the lifted labels' confidence the probability that they are right?

Prints one JSON object. For each evaluation case (synthetic scene, seed, exact or degraded
masks of the greedy rho >= 0.99 selection) it lifts the masks twice -- the OLD fill (far fill
on, the pre-issue-23 confidence: ``LiftParams(fill_far=True, confidence="legacy")``) and the
NEW one (defaults: no extrapolation, calibrated confidence) -- and reports per case the
expected calibration error (10 equal-width bins, :func:`occufly.lifting.calibration.reliability`)
over the labelled points with truth, the point accuracy over labelled points and the coverage
(share of points with truth that got a label), per origin as well. Then the prefill of the
next frames to annotate after 1, 3 and 10 submitted (exact) masks, old vs new: the share of
the frames' truth pixels the prefill gets right, and the share it leaves unpainted.

``--fit`` (re)fits the calibration table ``occufly/lifting/confidence_calibration.json`` on
the FIT cases (never the evaluation cases: other seeds of ``small``, and ``tiny``) from the
raw scores (``LiftParams(confidence="raw")``), and writes the scenes / seeds / mask kinds into
it. ``--plot PATH`` draws the reliability diagrams of the evaluation cases (PIL PNG).

    .venv/bin/python bench/bench_calibration.py --fit          # regenerate the table
    .venv/bin/python bench/bench_calibration.py --plot docs/reliability.png

Scenes are generated and imported once into ``--cache`` (default /tmp/occufly-conf) through
the CLI in subprocesses.
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
from occufly.lifting import LiftParams, VoteStore, fill_snapshot  # noqa: E402
from occufly.lifting import calibration as cal  # noqa: E402
from occufly.lifting.result import ORIGIN_NAMES  # noqa: E402
from occufly.scene import Scene  # noqa: E402
from occufly.selection import select_frames  # noqa: E402

#: fitted on (preset, seed, selection, masks); evaluated on EVAL_CASES: no scene+seed in both
FIT_CASES = [(pr, sd, sel, mk) for pr, sd in (("tiny", 0), ("tiny", 1), ("small", 1), ("small", 2))
             for sel in ("greedy", "stratified") for mk in ("exact", "degraded")]
EVAL_CASES = [("small", 0, "greedy", "exact"), ("small", 0, "greedy", "degraded"),
              ("bench", 0, "greedy", "exact"), ("bench", 0, "greedy", "degraded")]
OLD = {"fill_far": True, "confidence": "legacy"}
PREFILL_AFTER = (1, 3, 10)
LOW_CONFIDENCE = 0.6  # frontend/js/pages/annotator.js: prefill pixels below it are hatched


class Case:
    """One synthetic scene with its truth, masks and frame selections."""

    def __init__(self, cache: Path, preset: str, seed: int) -> None:
        self.preset, self.seed = preset, seed
        self.syn, self.ws = ensure_seeded_scene(cache, preset, seed)
        self.scene = Scene.load(self.ws)
        self.truth = np.load(self.syn / "truth" / "point_labels.npy")
        self._masks: dict[int, np.ndarray] = {}
        self._sel: dict[str, list[int]] = {}

    def mask(self, fi: int) -> np.ndarray:
        if fi not in self._masks:
            fr = self.scene.frames[fi]
            self._masks[fi] = read_mask(self.syn / "truth" / "masks" / f"{fr.stem}.png", fr,
                                        self.scene.taxonomy)
        return self._masks[fi]

    def selection(self, mode: str) -> list[int]:
        if mode not in self._sel:
            if mode == "greedy":
                s = select_frames(self.scene, mode="greedy", target_coverage=0.99)
            else:
                s = select_frames(self.scene, mode="stratified")
            self._sel[mode] = [int(f) for f in s.frames]
        return self._sel[mode]

    def masks(self, frames: list[int], kind: str) -> dict[int, np.ndarray]:
        exact = {fi: self.mask(fi) for fi in frames}
        if kind == "exact":
            return exact
        from occufly.synthetic.degrade import degrade_masks

        return degrade_masks(exact, self.scene.taxonomy, seed=self.seed)

    def lift(self, masks: dict[int, np.ndarray], **params):
        """Fill + denoise of the votes of ``masks`` (robust decision on, as the app lifts),
        with the votes counted in memory (the workspace's lifting state is not touched)."""
        tax = self.scene.taxonomy
        st = VoteStore(self.ws, self.scene, np.zeros((self.scene.n_points, len(tax.ids)), np.uint16), {})
        flat = st.votes.reshape(-1)
        C = len(tax.ids)
        for fi, m in masks.items():
            pids, cols, w = st.frame_votes(fi, m)
            np.add.at(flat, pids.astype(np.int64) * C + cols, w)
            st._versions[int(fi)] = "bench"
        snap = st.snapshot()
        return fill_snapshot(self.scene, snap, params=LiftParams(**params), ws=self.ws,
                             read_only=False)

    def evaluated(self) -> np.ndarray:
        """(N,) bool: points with a truth class."""
        t = self.truth
        return (t > 0) & (t < 255) & np.isin(t, np.asarray(self.scene.taxonomy.ids))


def point_report(case: Case, res, bins: int) -> dict:
    ev = case.evaluated()
    lab = np.asarray(res.labels)
    has = ev & (lab > 0)
    correct = lab[has] == case.truth[has]
    conf = np.asarray(res.confidence)[has]
    org = np.asarray(res.origin)[has]
    rel = cal.reliability(conf, correct, bins)
    out = {"ece": round(rel["ece"], 4), "accuracy_labelled": round(float(correct.mean()), 4),
           "coverage": round(float(has.sum() / max(1, ev.sum())), 4),
           "accuracy_all": round(float(correct.sum() / max(1, ev.sum())), 4),
           "mean_confidence": round(float(conf.mean()), 4), "by_origin": {},
           "reliability": rel}
    for code, name in ORIGIN_NAMES.items():
        s = org == code
        if s.any():
            r = cal.reliability(conf[s], correct[s], bins)
            out["by_origin"][name] = {"points": int(s.sum()), "accuracy": round(float(correct[s].mean()), 4),
                                      "mean_confidence": round(float(conf[s].mean()), 4),
                                      "ece": round(r["ece"], 4)}
    f = org == 2
    if f.any():  # defect 3: wrong filled labels must be less confident than right ones
        out["filled_conf_right_wrong"] = [
            round(float(conf[f][correct[f]].mean()), 4) if correct[f].any() else None,
            round(float(conf[f][~correct[f]].mean()), 4) if (~correct[f]).any() else None]
    return out


def prefill_report(case: Case, frames: list[int], after: tuple[int, ...], params: dict,
                   next_frames: int = 3) -> dict:
    """Prefill of the next ``next_frames`` frames of the selection after the first k (exact)
    masks of it are submitted: share of their truth pixels right / unpainted."""
    from occufly.render import prefill_for_mask

    out = {}
    cut = 1 + round(254 * LOW_CONFIDENCE)
    for k in after:
        if k + 1 > len(frames):
            continue
        res = case.lift(case.masks(frames[:k], "exact"), **params)
        pts = point_report(case, res, 10)  # calibration with few masks (far fill matters)
        lab = np.asarray(res.labels)
        # the confidence image as app/annotations/confidence.py renders it (holes get 1)
        q = np.where(lab > 0, 1 + np.rint(254.0 * np.clip(np.asarray(res.confidence), 0, 1)),
                     0).astype(np.uint8)
        right = painted = total = wrong = wrong_low = right_low = 0
        for fi in frames[k:k + next_frames]:
            m = case.mask(fi)
            img, _, _ = prefill_for_mask(case.scene, lab, fi, m.shape)
            cimg, _, holes = prefill_for_mask(case.scene, q, fi, m.shape)
            cimg[holes & (cimg > 0)] = 1
            low = (cimg > 0) & (cimg < cut)
            t = (m > 0) & (m < 255)
            total += int(t.sum())
            ok = (img == m) & t
            bad = (img > 0) & (img != m) & t
            right += int(ok.sum())
            painted += int(((img > 0) & t).sum())
            wrong += int(bad.sum())
            wrong_low += int((bad & low).sum())
            right_low += int((ok & low).sum())
        out[str(k)] = {"right": round(right / max(1, total), 4),
                       "unpainted": round(1 - painted / max(1, total), 4),
                       "right_of_painted": round(right / max(1, painted), 4),
                       # the annotator's hatching: low-confidence (< 0.6) share of the wrong
                       # and of the right prefill pixels
                       "wrong_marked_low": round(wrong_low / max(1, wrong), 4),
                       "right_marked_low": round(right_low / max(1, right), 4),
                       "points": {key: pts[key] for key in ("ece", "accuracy_labelled", "coverage",
                                                            "filled_conf_right_wrong")},
                       "frames": frames[k:k + next_frames]}
    return out


def fit(args: argparse.Namespace) -> dict:
    raws, origins, oks, used = [], [], [], []
    cases: dict[tuple[str, int], Case] = {}
    for preset, seed, sel, kind in FIT_CASES:
        case = cases.setdefault((preset, seed), Case(args.cache, preset, seed))
        res = case.lift(case.masks(case.selection(sel), kind), confidence="raw")
        ev = case.evaluated()
        lab = np.asarray(res.labels)
        has = ev & (lab > 0)
        raws.append(np.asarray(res.confidence)[has])
        origins.append(np.asarray(res.origin)[has])
        oks.append(lab[has] == case.truth[has])
        used.append({"preset": preset, "seed": seed, "selection": sel, "masks": kind,
                     "points": int(has.sum())})
        print(f"fit case {preset} {seed} {sel} {kind}: {int(has.sum())} points", file=sys.stderr)
    # every case weighs the same (the small scenes would otherwise drown the tiny ones)
    raw = np.concatenate(raws)
    origin = np.concatenate(origins)
    ok = np.concatenate(oks)
    table = cal.fit_table(raw, origin, ok, meta={
        "what": "isotonic map raw evidence score -> P(label right), per origin "
                "(occufly.lifting.calibration; regenerate: bench/bench_calibration.py --fit)",
        "fitted_on": used,
        "degradation": "occufly.synthetic.degrade.Degradation() defaults, seed = scene seed",
        "lift": "LiftParams() defaults (no far fill, robust decision on), votes of the "
                "selection's masks",
    })
    table.save(args.table)
    cal._load.cache_clear()
    return {"table": str(args.table), "maps": {k: len(v[0]) for k, v in table.maps.items()},
            "fitted_points": table.meta["fitted_points"]}


def evaluate(args: argparse.Namespace) -> dict:
    out: dict = {"bench": "calibration", "bins": args.bins, "loadavg": open("/proc/loadavg").read().split()[:3],
                 "fit_cases": [f"{p}-{s}-{sel}-{m}" for p, s, sel, m in FIT_CASES],
                 "cases": {}, "prefill": {}}
    table = cal.default_table()
    out["table_fitted_on"] = table.meta.get("fitted_on") if table else None
    cases: dict[tuple[str, int], Case] = {}
    plot = []
    for preset, seed, sel, kind in EVAL_CASES:
        if args.presets and preset not in args.presets:
            continue
        t0 = time.perf_counter()
        case = cases.setdefault((preset, seed), Case(args.cache, preset, seed))
        frames = case.selection(sel)
        masks = case.masks(frames, kind)
        name = f"{preset}-{seed}-{sel}-{kind}"
        row = {"frames": len(frames)}
        for label, params in (("old", OLD), ("new", {})):
            res = case.lift(masks, **params)
            row[label] = point_report(case, res, args.bins)
            plot.append((f"{name} {label}", row[label]["reliability"]))
        row["seconds"] = round(time.perf_counter() - t0, 1)
        for label in ("old", "new"):
            row[label].pop("reliability")
        out["cases"][name] = row
        print(f"{name}: ECE old {row['old']['ece']} new {row['new']['ece']}", file=sys.stderr)
    if not args.no_prefill:
        for preset, seed in cases:
            case = cases[(preset, seed)]
            frames = case.selection("greedy")
            out["prefill"][f"{preset}-{seed}"] = {
                label: prefill_report(case, frames, PREFILL_AFTER, params)
                for label, params in (("old", OLD), ("new", {}))}
    out["ece_target_met"] = all(r["new"]["ece"] <= 0.05 for r in out["cases"].values())
    if args.plot:
        draw_reliability(plot, args.plot)
        out["plot"] = str(args.plot)
    return out


def draw_reliability(panels: list[tuple[str, dict]], path: Path) -> None:
    """Reliability diagrams (accuracy per confidence bin, bar width ~ bin share) with PIL."""
    from PIL import Image, ImageDraw

    cols = 2
    rows = -(-len(panels) // cols)
    W, H, pad = 420, 380, 46
    img = Image.new("RGB", (cols * W, rows * H), "white")
    d = ImageDraw.Draw(img)
    for i, (title, rel) in enumerate(panels):
        ox, oy = (i % cols) * W, (i // cols) * H
        x0, y0, x1, y1 = ox + pad, oy + 30, ox + W - 16, oy + H - pad
        sx, sy = x1 - x0, y1 - y0
        d.rectangle([x0, y0, x1, y1], outline=(0, 0, 0))
        for t in range(0, 11, 2):
            v = t / 10
            d.line([x0 + v * sx, y1, x0 + v * sx, y1 + 4], fill=(0, 0, 0))
            d.text((x0 + v * sx - 8, y1 + 6), f"{v:.1f}", fill=(0, 0, 0))
            d.line([x0 - 4, y1 - v * sy, x0, y1 - v * sy], fill=(0, 0, 0))
            d.text((ox + 8, y1 - v * sy - 6), f"{v:.1f}", fill=(0, 0, 0))
        d.line([x0, y1, x1, y0], fill=(150, 150, 150))  # perfect calibration
        n = max(1, rel["n"])
        for b in rel["bins"]:
            if not b["count"]:
                continue
            bx0, bx1 = x0 + b["lo"] * sx + 2, x0 + b["hi"] * sx - 2
            acc = b["accuracy"]
            d.rectangle([bx0, y1 - acc * sy, bx1, y1], fill=(70, 120, 220), outline=(30, 60, 140))
            mc = b["mean_conf"]
            d.line([bx0, y1 - mc * sy, bx1, y1 - mc * sy], fill=(220, 40, 40), width=3)
            share = b["count"] / n  # bin share as a thin grey bar along the bottom
            d.rectangle([bx0, y1 - max(1.0, share * sy * 0.25), bx1, y1], fill=(90, 90, 90))
        d.text((ox + pad, oy + 8), f"{title}   ECE {rel['ece']:.3f}   n={rel['n']:,}", fill=(0, 0, 0))
        d.text((x0 + sx / 2 - 40, y1 + 22), "confidence", fill=(0, 0, 0))
    d.text((8, rows * H - 14), "blue: accuracy per bin; red: mean confidence; grey: share of "
           "points (x4); diagonal: calibrated", fill=(0, 0, 0))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img.save(path)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-conf"))
    ap.add_argument("--fit", action="store_true", help="refit the calibration table")
    ap.add_argument("--table", type=Path, default=cal.TABLE_PATH)
    ap.add_argument("--bins", type=int, default=10)
    ap.add_argument("--presets", nargs="*", default=None, help="evaluate only these presets")
    ap.add_argument("--no-prefill", action="store_true")
    ap.add_argument("--plot", type=Path, default=None)
    args = ap.parse_args(argv)
    out = fit(args) if args.fit else evaluate(args)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
