"""Calibrated label confidence: raw evidence scores, their fitted probability maps, reliability.

A lifted label's confidence is meant as the probability that the label is right. It is made
in two steps (issue 23, ``docs/confidence.md``):

Raw score (per origin, from the evidence the fill has; :func:`raw_scores`)
    direct (the vote, or the robust decision, kept through the denoise)
        ``0.5 * (vote margin + denoise share)`` -- the margin ``(top - second) / votes`` of the
        views (a posterior margin after the robust decision) and the share of the point's
        k = 200 neighbourhood that has its class.
    filled (no vote; the IDW kNN vote of the voted points within ``fill_radius``)
        ``fill share * denoise share * (1 - d / 2R)``: the IDW share of the winning class
        among the voted neighbours (their agreement), the share of its k = 200 neighbourhood
        that has the class, and the closeness of the nearest voted neighbour (``d`` its
        distance, ``R`` the fill radius: 1 next to a vote, 0.5 at the radius, 0 beyond it, so
        the opt-in far fill gets the lowest score). It falls with distance and with
        disagreement. (``fill share * (1 - d / R)`` alone separated right from wrong filled
        labels less well: on the tiny scene, degraded masks, right/wrong mean confidence
        0.822 / 0.781 against 0.818 / 0.733 with this score.)
    denoised (the denoise relabelled the vote or fill label)
        the denoise share of the new class.
Probability (per origin; :class:`CalibrationTable`)
    A non-decreasing map from raw score to the share of correct labels, fitted by isotonic
    regression (pool adjacent violators, :func:`fit_isotonic`) on synthetic scenes whose
    truth says which labels are right, and applied by linear interpolation between the
    pooled blocks' centres (so it is non-decreasing: a filled label's confidence never rises
    with distance or with disagreement). The fitted table ships as
    ``occufly/lifting/confidence_calibration.json`` with the scenes, seeds and mask kinds it
    was fitted on; ``bench/bench_calibration.py --fit`` regenerates it (never on the scenes
    it reports on).

Reliability (:func:`reliability`)
    Equal-width confidence bins, each with its count, mean confidence and accuracy, and the
    expected calibration error ``ECE = sum_b n_b / N * |accuracy_b - mean_conf_b|``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from occufly.fsutil import atomic_write_text
from occufly.lifting.result import ORIGIN_DENOISED, ORIGIN_DIRECT, ORIGIN_FILLED

TABLE_PATH = Path(__file__).with_name("confidence_calibration.json")
TABLE_VERSION = 1
#: the origins that carry a fitted map (names as in ``ORIGIN_NAMES``)
CALIBRATED_ORIGINS = {ORIGIN_DIRECT: "direct", ORIGIN_FILLED: "filled", ORIGIN_DENOISED: "denoised"}


# ---- reliability --------------------------------------------------------------------------
def reliability(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> dict:
    """Reliability diagram and expected calibration error of ``confidence`` against ``correct``.

    confidence: (N,) float in [0, 1] (clipped; NaN counts as 0); correct: (N,) bool, whether
    each label is right. bins: number of equal-width bins over [0, 1] (the last one closed).
    Returns ``{"ece", "n", "mean_confidence", "accuracy", "bins": [{lo, hi, count, mean_conf,
    accuracy}, ...]}`` -- every bin is listed, an empty one with count 0 and None means;
    ECE is the count-weighted mean of ``|accuracy - mean_conf|`` (0.0 for no points).
    """
    conf = np.clip(np.nan_to_num(np.asarray(confidence, np.float64).reshape(-1), nan=0.0), 0.0, 1.0)
    ok = np.asarray(correct).reshape(-1)
    if ok.shape != conf.shape:
        raise ValueError(f"confidence {conf.shape} and correct {ok.shape} must have the same length")
    bins = int(bins)
    if bins < 1:
        raise ValueError(f"bins must be >= 1, got {bins}")
    ok = ok.astype(bool)
    n = len(conf)
    b = np.minimum((conf * bins).astype(np.int64), bins - 1)
    count = np.bincount(b, minlength=bins)
    csum = np.bincount(b, weights=conf, minlength=bins)
    asum = np.bincount(b, weights=ok.astype(np.float64), minlength=bins)
    out_bins = []
    ece = 0.0
    for i in range(bins):
        c = int(count[i])
        mc = float(csum[i] / c) if c else None
        ac = float(asum[i] / c) if c else None
        if c:
            ece += c / n * abs(ac - mc)
        out_bins.append({"lo": i / bins, "hi": (i + 1) / bins, "count": c,
                         "mean_conf": mc, "accuracy": ac})
    return {"ece": float(ece), "n": int(n),
            "mean_confidence": float(conf.mean()) if n else None,
            "accuracy": float(ok.mean()) if n else None, "bins": out_bins}


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> float:
    """ECE of :func:`reliability` alone."""
    return reliability(confidence, correct, bins)["ece"]


# ---- fitting ------------------------------------------------------------------------------
def fit_isotonic(score: np.ndarray, correct: np.ndarray, *, max_knots: int = 64,
                 min_block: int = 50) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Non-decreasing map raw score -> P(correct) by pool-adjacent-violators.

    score: (N,) float raw scores; correct: (N,) bool. Equal scores are pooled first, then the
    sorted scores are grouped into at most ``max_knots`` quantile groups of at least
    ``min_block`` points (a small table, a stable fit), then PAV pools violating neighbours.
    Returns (x (K,) float64 block centres = mean score, y (K,) float64 block accuracy,
    non-decreasing; n (K,) int64 block sizes).
    """
    s = np.asarray(score, np.float64).reshape(-1)
    ok = np.asarray(correct, bool).reshape(-1)
    if s.shape != ok.shape:
        raise ValueError(f"score {s.shape} and correct {ok.shape} must have the same length")
    if not len(s):
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    order = np.argsort(s, kind="stable")
    s, ok = s[order], ok[order].astype(np.float64)
    n = len(s)
    groups = max(1, min(int(max_knots), n // max(1, int(min_block))))
    # quantile groups, never splitting equal scores
    cut = np.unique(np.searchsorted(s, s[np.linspace(0, n, groups + 1).astype(np.int64)[1:-1]],
                                    side="left"))
    cut = cut[(cut > 0) & (cut < n)]
    edges = np.r_[0, cut, n]
    sums_s = np.add.reduceat(s, edges[:-1])
    sums_y = np.add.reduceat(ok, edges[:-1])
    cnt = np.diff(edges).astype(np.float64)
    # PAV over the groups
    bx, by, bn = [], [], []
    for xs, ys, c in zip(sums_s, sums_y, cnt, strict=True):
        bx.append(xs)
        by.append(ys)
        bn.append(c)
        while len(by) > 1 and by[-2] / bn[-2] > by[-1] / bn[-1]:
            xs2, ys2, c2 = bx.pop(), by.pop(), bn.pop()
            bx[-1] += xs2
            by[-1] += ys2
            bn[-1] += c2
    bx, by, bn = np.array(bx), np.array(by), np.array(bn)
    return bx / bn, by / bn, bn.astype(np.int64)


# ---- the table ----------------------------------------------------------------------------
@dataclass
class CalibrationTable:
    """Per-origin maps raw score -> probability (``maps[name] = (x, y)``), and what they were
    fitted on (``meta``: scenes, seeds, mask kinds, counts)."""

    maps: dict[str, tuple[np.ndarray, np.ndarray]]
    meta: dict = field(default_factory=dict)

    def probability(self, origin: np.ndarray, raw: np.ndarray) -> np.ndarray:
        """(N,) float32 calibrated confidence of labels with ``origin`` (N,) uint8 codes and raw
        scores ``raw`` (N,) float; origins without a map (none, corrected) keep ``raw``."""
        origin = np.asarray(origin)
        raw = np.asarray(raw, np.float32)
        out = raw.astype(np.float32, copy=True)
        for code, name in CALIBRATED_ORIGINS.items():
            if name not in self.maps:
                continue
            sel = origin == code
            if sel.any():
                x, y = self.maps[name]
                out[sel] = np.interp(raw[sel], x, y).astype(np.float32)
        return np.clip(out, 0.0, 1.0)

    def to_json(self) -> dict:
        return {"version": TABLE_VERSION, **self.meta,
                "maps": {k: {"x": [round(float(a), 6) for a in x],
                             "y": [round(float(b), 6) for b in y]}
                         for k, (x, y) in self.maps.items()}}

    @classmethod
    def from_json(cls, d: dict, *, name: str = "<calibration>") -> CalibrationTable:
        if d.get("version") != TABLE_VERSION or not isinstance(d.get("maps"), dict):
            raise ValueError(f"{name}: expected a version-{TABLE_VERSION} calibration table "
                             "with 'maps'")
        maps = {}
        for k, v in d["maps"].items():
            x, y = np.asarray(v["x"], np.float64), np.asarray(v["y"], np.float64)
            if x.shape != y.shape or not len(x) or np.any(np.diff(x) < 0) or np.any(np.diff(y) < -1e-9):
                raise ValueError(f"{name}: map {k!r} must have equal-length non-decreasing x and y")
            maps[k] = (x, y)
        meta = {k: v for k, v in d.items() if k not in ("version", "maps")}
        return cls(maps, meta)

    def save(self, path: str | Path = TABLE_PATH) -> None:
        atomic_write_text(Path(path), json.dumps(self.to_json(), indent=1) + "\n")


@lru_cache(maxsize=4)
def _load(path: str) -> CalibrationTable | None:
    p = Path(path)
    if not p.is_file():
        return None
    return CalibrationTable.from_json(json.loads(p.read_text()), name=str(p))


def default_table() -> CalibrationTable | None:
    """The shipped table (``confidence_calibration.json`` beside this module), or None when
    it is missing (then confidence is the raw score)."""
    return _load(str(TABLE_PATH))


def fit_table(raw: np.ndarray, origin: np.ndarray, correct: np.ndarray, *, meta: dict | None = None,
              max_knots: int = 64, min_block: int = 200) -> CalibrationTable:
    """Fit one isotonic map per calibrated origin. raw, origin, correct: (N,) arrays pooled
    over the fitting scenes (only labelled points with truth). Returns the table."""
    raw = np.asarray(raw, np.float64)
    origin = np.asarray(origin)
    correct = np.asarray(correct, bool)
    maps, counts = {}, {}
    for code, name in CALIBRATED_ORIGINS.items():
        sel = origin == code
        if not sel.any():
            continue
        x, y, _ = fit_isotonic(raw[sel], correct[sel], max_knots=max_knots, min_block=min_block)
        maps[name] = (x, y)
        counts[name] = {"points": int(sel.sum()), "accuracy": float(correct[sel].mean())}
    return CalibrationTable(maps, {**(meta or {}), "fitted_points": counts})


# ---- raw scores ---------------------------------------------------------------------------
def raw_scores(origin: np.ndarray, *, denoise_share: np.ndarray, vote_margin: np.ndarray | None,
               fill_share: np.ndarray, fill_distance: np.ndarray, fill_radius: float) -> np.ndarray:
    """(N,) float32 raw evidence score per point (see the module docstring).

    origin: (N,) uint8 codes; denoise_share: (N,) float share of the point's denoise
    neighbourhood with its final class (the vote margin for confirmed points the denoise
    overrode); vote_margin: (N,) float or None; fill_share: (N,) IDW share of the filled
    class among the voted neighbours; fill_distance: (N,) metres to the nearest voted point
    used by the fill (inf where none); fill_radius: metres.
    """
    origin = np.asarray(origin)
    a = np.clip(np.asarray(denoise_share, np.float32), 0.0, 1.0)
    out = np.zeros(len(origin), np.float32)
    d = origin == ORIGIN_DIRECT
    m = np.ones(len(origin), np.float32) if vote_margin is None else np.asarray(vote_margin, np.float32)
    out[d] = 0.5 * (a[d] + np.clip(m[d], 0.0, 1.0))
    f = origin == ORIGIN_FILLED
    r = np.asarray(fill_distance, np.float64)[f] / max(float(fill_radius), 1e-9)
    close = np.where(r <= 1.0, 1.0 - 0.5 * np.nan_to_num(r, nan=1.0), 0.0)  # 1 -> 0.5, 0 beyond
    out[f] = (np.clip(np.asarray(fill_share, np.float32)[f], 0.0, 1.0) * a[f]
              * np.clip(close, 0.0, 1.0)).astype(np.float32)
    dn = origin == ORIGIN_DENOISED
    out[dn] = a[dn]
    return out
