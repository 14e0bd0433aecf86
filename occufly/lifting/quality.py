"""The quality report of a scene's lifted labels (issue 23): how its labels were made.

:func:`quality_report` reads a workspace's lifting state (the per-frame votes
``ws/lifting/frames/<f>.npz`` and their counts ``ws/lifting/votes.npy``) and its labels
(:func:`occufly.lifting.load_labels`: the fill output with reviewers' corrections) and returns
one JSON-able dict (the format is documented in ``docs/quality-json.md``):

``loo``
    Leave-one-out agreement of every annotated frame, in point space: for frame ``f``, the
    labels decided *without f's votes* (:func:`occufly.lifting.loo.loo_labels` -- the other
    frames' vote majority, then their fill within ``LiftParams.fill_radius``, corrections on
    top: the rules the reviewer page uses) at the points ``f`` voted for, compared with ``f``'s
    vote. ``agreement`` = agreeing / independently labelled votes of ``f``; ``independent
    coverage`` = independently labelled / all votes of ``f``. Per frame, their distribution
    (quantiles, histogram) and the vote-weighted totals.
``votes``
    Points with votes from at least two different frames (``multi_view``; a frame votes at
    most once per point, so this counts frames, whatever the vote weighting), of the labelled
    points and of all points.
``contested``
    Points whose votes disagree: at least two votes and the second class holding at least
    ``SuspectParams.second_share`` of them (the suspects' rule,
    :func:`occufly.lifting.suspects.flag_points`), points with any dissenting vote, and points
    whose final label overrides their vote majority.
``confidence``
    The calibrated confidence (:mod:`occufly.lifting.calibration`): its mean over the labelled
    points (what it predicts the share of right labels to be), its histogram per origin, the
    shipped calibration table's provenance, and -- when point truth is available
    (``truth=``, e.g. a synthetic scene's ``truth/point_labels.npy``) -- the reliability bins and
    the expected calibration error (ECE) measured on this scene.
``classes``
    Per class: labelled points, mean confidence, multi-view and contested shares, the LOO
    agreement of the votes for that class, and with truth its accuracy.

Everything is vectorised over points and votes; the LOO part costs one frustum cull and one
local k-NN per annotated frame (proportional to the points each frame sees).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from occufly.errors import WorkspaceError
from occufly.lifting.calibration import TABLE_PATH, default_table, reliability
from occufly.lifting.classes import ClassColumns
from occufly.lifting.corrections import load_labels
from occufly.lifting.knn import LiftParams
from occufly.lifting.loo import loo_labels
from occufly.lifting.result import ORIGIN_NAMES
from occufly.lifting.suspects import SuspectParams
from occufly.scene import Scene
from occufly.taxonomy import INVALID
from occufly.workspace import Workspace

FORMAT = "occufly-quality"
FORMAT_VERSION = 1
QUANTILES = (0.0, 0.1, 0.25, 0.5, 0.75, 0.9, 1.0)
HIST_BINS = 10
_CHUNK = 1_000_000
TRUTH_POINTS = "point_labels.npy"  # WS/truth/<this>: point truth kept with a workspace


def _share(a: int | float, b: int | float) -> float | None:
    return round(float(a) / float(b), 6) if b else None


def distribution(values: list[float] | np.ndarray, bins: int = HIST_BINS) -> dict:
    """Quantiles and an equal-width histogram over [0, 1] of per-frame figures (None skipped)."""
    v = np.asarray([x for x in values if x is not None], np.float64)
    if not len(v):
        return {"n": 0, "mean": None, "quantiles": None,
                "histogram": {"edges": [i / bins for i in range(bins + 1)], "counts": [0] * bins}}
    b = np.minimum((np.clip(v, 0.0, 1.0) * bins).astype(np.int64), bins - 1)
    return {"n": int(len(v)), "mean": round(float(v.mean()), 6),
            "quantiles": {f"p{int(round(q * 100))}": round(float(np.quantile(v, q)), 6)
                          for q in QUANTILES},
            "histogram": {"edges": [round(i / bins, 6) for i in range(bins + 1)],
                          "counts": np.bincount(b, minlength=bins).astype(int).tolist()}}


def workspace_truth(ws: str | Path, n_points: int) -> np.ndarray | None:
    """(N,) uint8 point truth kept with a workspace (``WS/truth/point_labels.npy``, a synthetic
    scene's, in the source cloud's order; ``points/source_index.npy`` reorders it), or None
    when there is none or it does not fit the cloud."""
    w = Workspace(ws)
    p = w.truth_dir / TRUTH_POINTS
    if not p.is_file():
        return None
    try:
        t = np.asarray(np.load(p, mmap_mode="r", allow_pickle=False)).reshape(-1)
        src = w.root / "points" / "source_index.npy"
        if src.is_file():
            idx = np.load(src, mmap_mode="r")
            if len(idx) != n_points or (len(idx) and int(np.max(idx)) >= len(t)):
                return None
            t = t[np.asarray(idx, np.int64)]
    except (OSError, ValueError):
        return None
    if t.shape != (n_points,) or not np.issubdtype(t.dtype, np.integer) or (
            t.size and (t.min() < 0 or t.max() > 255)):
        return None
    return t.astype(np.uint8)


def _frame_votes(w: Workspace, f: int) -> tuple[np.ndarray, np.ndarray]:
    got = w.read_frame_votes(f)
    if got is None:
        raise WorkspaceError(f"{w.lifting_frame(f)}: the votes of frame {f} are missing; "
                             "re-apply the frame's mask")
    return got[0].astype(np.int64), got[1].astype(np.int64)


def _vote_stats(votes: np.ndarray, labels: np.ndarray, cls: ClassColumns,
                p: SuspectParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(contested (N,) bool, any dissent (N,) bool, overridden (N,) bool) from the counts."""
    n = len(labels)
    contested = np.zeros(n, bool)
    dissent = np.zeros(n, bool)
    overridden = np.zeros(n, bool)
    for a in range(0, n, _CHUNK):
        b = min(n, a + _CHUNK)
        c = np.asarray(votes[a:b])
        col, _top, second = cls.majority(c)
        total = c.sum(axis=1, dtype=np.int64)
        share = np.where(total > 0, second / np.maximum(total, 1), 0.0)
        contested[a:b] = (total >= p.min_votes) & (share >= p.second_share)
        dissent[a:b] = second > 0
        overridden[a:b] = (col >= 0) & (np.asarray(labels[a:b]) != cls.labels_of(col))
    return contested, dissent, overridden


def quality_report(ws: str | Path, scene: Scene | None = None, *, truth: np.ndarray | None = None,
                   policy: dict | None = None, params: LiftParams | None = None,
                   loo: bool = True, labels=None, bins: int = 10) -> dict:  # noqa: ANN001
    """The quality report of workspace ``ws`` (see the module docstring).

    truth: (N,) uint8 raw ids per point (0 / 255 = no truth) for the measured calibration
    (:func:`workspace_truth` reads the one kept with a workspace);
    policy: the version policy the labels were lifted under (recorded as given; default: the
    versions the workspace's lifting state counts); loo: False skips the per-frame
    leave-one-out part; labels: a :class:`LiftResult` to report on instead of
    ``load_labels(ws)`` (an export's scratch labels, lifted from the same votes).
    """
    t0 = time.perf_counter()
    ws = Path(ws)
    w = Workspace(ws)
    if scene is None:
        scene = Scene.load(ws)
    if not w.lifting_state.is_file() or not w.votes.is_file():
        raise WorkspaceError(f"{w.lifting_state}: no lifting state yet (no mask has been lifted); "
                             "nothing to report")
    res = labels if labels is not None else load_labels(ws)
    if res is None:
        raise WorkspaceError(f"{w.labels_path}: no lifted labels yet (the fill has not run); "
                             "nothing to report")
    tax = scene.taxonomy
    cls = ClassColumns(tax)
    n = scene.n_points
    lab = np.asarray(res.labels)
    conf = np.asarray(res.confidence, np.float32)
    origin = np.asarray(res.origin)
    if len(lab) != n:
        raise WorkspaceError(f"{w.labels_path}: {len(lab)} labels for a scene of {n} points")
    votes = np.load(w.votes, mmap_mode="r")
    frames = sorted(int(p.stem) for p in w.lifting_frames_dir.glob("*.npz") if p.stem.isdigit())
    valid = tax.valid_lut()
    labelled = valid[lab] & (lab != INVALID) & (lab > 0)
    n_lab = int(labelled.sum())

    # ---- frames voting per point (a frame votes at most once per point) -------------------
    views = np.zeros(n, np.uint16)
    per_frame_votes: dict[int, int] = {}
    for f in frames:
        pids, _cols = _frame_votes(w, f)
        views[pids] += 1
        per_frame_votes[f] = int(len(pids))
    multi = views >= 2
    sp = SuspectParams()
    contested, dissent, overridden = _vote_stats(votes, lab, cls, sp)
    voted = views >= 1

    # ---- leave-one-out agreement per annotated frame ---------------------------------------
    t_loo = time.perf_counter()
    frame_rows, cls_votes, cls_ind, cls_agree = (
        _loo_rows(w, ws, scene, frames, cls, params) if loo else
        ([], np.zeros(cls.C, np.int64), np.zeros(cls.C, np.int64), np.zeros(cls.C, np.int64)))
    t_loo = time.perf_counter() - t_loo
    tot_votes = sum(r["votes"] for r in frame_rows)
    tot_ind = sum(r["independent"] for r in frame_rows)
    tot_agree = sum(r["agree"] for r in frame_rows)

    # ---- confidence / calibration ------------------------------------------------------------
    calib, truth_correct, has_t = _calibration(lab, conf, origin, labelled, valid, truth, n, bins)

    # ---- per class --------------------------------------------------------------------------
    classes = _per_class(tax, cls, lab, conf, labelled, multi, contested, truth_correct, has_t,
                         cls_votes, cls_ind, cls_agree, n_lab)

    versions = {str(k): v for k, v in sorted(res.stats.get("versions", {}).items(),
                                             key=lambda kv: int(kv[0]))} \
        if isinstance(res.stats.get("versions"), dict) else {}
    return {
        "format": FORMAT, "version": FORMAT_VERSION,
        "policy": policy if policy is not None else {
            "include": None, "note": "the versions the workspace's lifting state counts"},
        "versions": versions,
        "points": n, "labelled_points": n_lab, "labelled_share": _share(n_lab, n),
        "annotated_frames": len(frames),
        "loo": None if not loo else {
            "frames": len(frame_rows),
            "agreement": _share(tot_agree, tot_ind),
            "independent_coverage": _share(tot_ind, tot_votes),
            "agreement_distribution": distribution([r["agreement"] for r in frame_rows]),
            "coverage_distribution": distribution([r["independent_coverage"] for r in frame_rows]),
            "per_frame": frame_rows},
        "votes": {
            "voted_points": int(voted.sum()),
            "multi_view_points": int(multi.sum()),
            "multi_view_share": _share(int((multi & labelled).sum()), n_lab),
            "multi_view_share_of_points": _share(int(multi.sum()), n),
            "views_histogram": np.bincount(np.minimum(views[labelled], 10), minlength=11)
                                 .astype(int).tolist(),
        },
        "contested": {
            "rule": {"min_votes": sp.min_votes, "second_share": sp.second_share},
            "points": int(contested.sum()),
            "share": _share(int((contested & labelled).sum()), n_lab),
            "share_of_multi_view": _share(int((contested & multi).sum()), int(multi.sum())),
            "dissent_points": int(dissent.sum()),
            "dissent_share": _share(int((dissent & labelled).sum()), n_lab),
            "overridden_points": int(overridden.sum()),
            "overridden_share": _share(int((overridden & labelled).sum()), n_lab),
        },
        "confidence": calib,
        "classes": classes,
        "seconds": {"total": round(time.perf_counter() - t0, 3), "loo": round(t_loo, 3)},
    }


def _loo_rows(w: Workspace, ws: Path, scene: Scene, frames: list[int], cls: ClassColumns,
              params: LiftParams | None) -> tuple[list[dict], np.ndarray, np.ndarray, np.ndarray]:
    """Each annotated frame's votes against its leave-one-out labels: the per-frame rows and,
    per class column, the votes, those with an independent label and those that agree."""
    C = cls.C
    cls_votes = np.zeros(C, np.int64)
    cls_ind = np.zeros(C, np.int64)
    cls_agree = np.zeros(C, np.int64)
    names = {c.id: c.name for c in scene.taxonomy.classes}
    frame_rows = []
    for f in frames:
        pids, cols = _frame_votes(w, f)
        if not len(pids):
            continue
        ll = loo_labels(ws, scene, f, params=params)
        pos = np.minimum(np.searchsorted(ll.point_ids, pids), len(ll.point_ids) - 1)
        found = ll.point_ids[pos] == pids
        ind = np.where(found, ll.labels[pos], 0)
        by_votes = found & ll.voted[pos]
        has = (ind > 0) & (ind != INVALID)
        agree = has & (ind == cls.ids[cols])
        cls_votes += np.bincount(cols, minlength=C)
        cls_ind += np.bincount(cols[has], minlength=C)
        cls_agree += np.bincount(cols[agree], minlength=C)
        nh = int(has.sum())
        fr = scene.frames[f]
        frame_rows.append({
            "frame": f, "name": fr.name, "votes": int(len(pids)), "independent": nh,
            "independent_votes": int((has & by_votes).sum()),
            "agree": int(agree.sum()),
            "agreement": _share(int(agree.sum()), nh),
            "independent_coverage": _share(nh, len(pids)),
            "disagreements": _disagreements(cls.ids[cols[has & ~agree]], ind[has & ~agree],
                                            names)})
    return frame_rows, cls_votes, cls_ind, cls_agree


def _disagreements(painted: np.ndarray, independent: np.ndarray, names: dict, top: int = 3
                   ) -> list[dict]:
    """The most frequent (painted class, independent label) pairs of a frame's disagreeing
    votes: ``[{"painted", "independent", "votes"}]`` by class name, most votes first -- a
    painter who swaps grass and vegetation shows as grass -> vegetation on every frame."""
    if not len(painted):
        return []
    key = painted.astype(np.int64) * 256 + independent.astype(np.int64)
    u, n = np.unique(key, return_counts=True)
    order = np.lexsort((u, -n))[:top]
    return [{"painted": names.get(int(u[i] // 256), str(int(u[i] // 256))),
             "independent": names.get(int(u[i] % 256), str(int(u[i] % 256))),
             "votes": int(n[i])} for i in order]


def _calibration(lab: np.ndarray, conf: np.ndarray, origin: np.ndarray, labelled: np.ndarray,
                 valid: np.ndarray, truth: np.ndarray | None, n: int, bins: int
                 ) -> tuple[dict, np.ndarray | None, np.ndarray | None]:
    """The report's ``confidence`` section (histograms per origin, the calibration table, the
    reliability against ``truth`` when given), and per point whether the label is right and
    whether it has truth (None without truth)."""
    n_lab = int(labelled.sum())
    has_t = None
    conf_l = conf[labelled]
    org_l = origin[labelled]
    by_origin = {}
    for code, name in ORIGIN_NAMES.items():
        sel = org_l == code
        if not sel.any():
            continue
        c = conf_l[sel]
        hb = np.minimum((np.clip(c, 0, 1) * bins).astype(np.int64), bins - 1)
        by_origin[name] = {"points": int(sel.sum()), "mean_confidence": round(float(c.mean()), 6),
                           "histogram": np.bincount(hb, minlength=bins).astype(int).tolist()}
    table = default_table()
    calib: dict = {
        "mean_confidence": round(float(conf_l.mean()), 6) if n_lab else None,
        "bins": bins, "by_origin": by_origin,
        "table": None if table is None else {
            "path": TABLE_PATH.name, "version": table.meta.get("version"),
            "fitted_on": len(table.meta.get("fitted_on") or []),
            "presets": sorted({str(x.get("preset")) for x in table.meta.get("fitted_on") or []})},
        "truth": None,
    }
    truth_correct = None
    if truth is not None:
        t = np.asarray(truth)
        if t.shape != (n,):
            raise WorkspaceError(f"truth: expected ({n},) raw class ids (one per point), got "
                                 f"shape {t.shape}")
        has_t = labelled & (t > 0) & (t != INVALID) & valid[t]
        truth_correct = np.zeros(n, bool)
        truth_correct[has_t] = lab[has_t] == t[has_t]
        rel = reliability(conf[has_t], truth_correct[has_t], bins)
        ev = (t > 0) & (t != INVALID) & valid[t]
        calib["truth"] = {
            "points": int(has_t.sum()), "ece": round(rel["ece"], 6),
            "accuracy": None if rel["accuracy"] is None else round(rel["accuracy"], 6),
            "mean_confidence": (None if rel["mean_confidence"] is None
                                else round(rel["mean_confidence"], 6)),
            "coverage": _share(int(has_t.sum()), int(ev.sum())),
            "reliability": [{k: (round(v, 6) if isinstance(v, float) else v) for k, v in b.items()}
                            for b in rel["bins"]],
            "by_origin": {name: {"points": int(s.sum()),
                                 "ece": round(reliability(conf[has_t & s], truth_correct[has_t & s],
                                                          bins)["ece"], 6),
                                 "accuracy": round(float(truth_correct[has_t & s].mean()), 6)}
                          for code, name in ORIGIN_NAMES.items()
                          if (s := origin == code)[has_t].any()}}
    return calib, truth_correct, has_t


def _per_class(tax, cls: ClassColumns, lab: np.ndarray, conf: np.ndarray, labelled: np.ndarray,  # noqa: ANN001
               multi: np.ndarray, contested: np.ndarray, truth_correct: np.ndarray | None,
               has_t: np.ndarray | None, cls_votes: np.ndarray, cls_ind: np.ndarray,
               cls_agree: np.ndarray, n_lab: int) -> dict:
    """The report's ``classes``: per class id, points, share, confidence, multi-view and
    contested shares, votes, LOO agreement (and accuracy against truth when given)."""
    C = cls.C
    lab_col = cls.col_of[lab]  # -1 for 0 / 255
    ok = labelled & (lab_col >= 0)
    lc = lab_col[ok].astype(np.int64)
    per_n = np.bincount(lc, minlength=C)
    per_conf = np.bincount(lc, weights=conf[ok].astype(np.float64), minlength=C)
    per_multi = np.bincount(lc, weights=multi[ok].astype(np.float64), minlength=C)
    per_cont = np.bincount(lc, weights=contested[ok].astype(np.float64), minlength=C)
    per_ok = (np.bincount(lc, weights=truth_correct[ok].astype(np.float64), minlength=C)
              if truth_correct is not None else None)
    per_t = (np.bincount(lc, weights=has_t[ok].astype(np.float64), minlength=C)
             if truth_correct is not None else None)
    classes = {}
    for c in range(C):
        cid = int(cls.ids[c])
        if not per_n[c] and not cls_votes[c]:
            continue
        row = {"id": cid, "name": tax[cid].name, "points": int(per_n[c]),
               "share": _share(int(per_n[c]), n_lab),
               "mean_confidence": round(float(per_conf[c] / per_n[c]), 6) if per_n[c] else None,
               "multi_view": _share(float(per_multi[c]), int(per_n[c])),
               "contested": _share(float(per_cont[c]), int(per_n[c])),
               "votes": int(cls_votes[c]),
               "loo_agreement": _share(int(cls_agree[c]), int(cls_ind[c])),
               "independent_coverage": _share(int(cls_ind[c]), int(cls_votes[c]))}
        if per_ok is not None:
            row["accuracy"] = _share(float(per_ok[c]), float(per_t[c]))
        classes[str(cid)] = row
    return classes


def summary_text(q: dict) -> str:
    """A readable summary of a quality report (``occufly report`` without ``--json``)."""
    def pc(v) -> str:  # noqa: ANN001
        return "-" if v is None else f"{100 * v:.1f} %"

    lines = [f"labelled points     {q['labelled_points']:,} of {q['points']:,} ({pc(q['labelled_share'])})",
             f"annotated frames    {q['annotated_frames']}"]
    pol = q.get("policy") or {}
    lines.append(f"version policy      {', '.join(pol['include']) if pol.get('include') else pol.get('note', '-')}")
    lo = q.get("loo")
    if lo:
        d = lo["agreement_distribution"]
        qs = d.get("quantiles") or {}
        lines.append(f"LOO agreement       {pc(lo['agreement'])} over {lo['frames']} frames"
                     + (f" (min {pc(qs.get('p0'))}, p10 {pc(qs.get('p10'))}, median "
                        f"{pc(qs.get('p50'))}, max {pc(qs.get('p100'))})" if qs else ""))
        lines.append(f"independent coverage {pc(lo['independent_coverage'])}")
        worst = sorted((r for r in lo["per_frame"] if r["agreement"] is not None),
                       key=lambda r: r["agreement"])[:3]
        if worst:
            lines.append("  lowest frames     " + ", ".join(
                f"{r['name']} {pc(r['agreement'])}" for r in worst))
            for r in worst:  # what each paints differently from the others (issue 37)
                dis = r.get("disagreements") or []
                if dis:
                    lines.append(f"    {r['name']}: " + "; ".join(
                        f"{d['painted']} where the others say {d['independent']} "
                        f"({d['votes']:,} votes)" for d in dis[:2]))
    v, c, cf = q["votes"], q["contested"], q["confidence"]
    lines.append(f">= 2 views          {pc(v['multi_view_share'])} of the labelled points")
    lines.append(f"contested           {pc(c['share'])} of the labelled points "
                 f"({pc(c['share_of_multi_view'])} of those with >= 2 views); overridden "
                 f"{pc(c['overridden_share'])}")
    lines.append(f"mean confidence     {pc(cf['mean_confidence'])}")
    if cf.get("truth"):
        t = cf["truth"]
        lines.append(f"calibration (truth) ECE {t['ece']:.4f}, accuracy {pc(t['accuracy'])} on "
                     f"{t['points']:,} points")
    else:
        lines.append("calibration         no point truth here (pass --truth): ECE not measured")
    lines.append("per class           points   conf    >=2 views  contested  LOO agr.")
    for row in q["classes"].values():
        lines.append(f"  {row['name'][:16]:<16} {row['points']:>9,}  {pc(row['mean_confidence']):>7}  "
                     f"{pc(row['multi_view']):>8}  {pc(row['contested']):>8}  {pc(row['loo_agreement']):>8}")
    return "\n".join(lines)
