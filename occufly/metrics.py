"""SSC and depth metrics exactly as FORMATS.md section 5 defines them.

SSC. One confusion matrix over all evaluated frames (:class:`occufly.confusion.Confusion`,
the module every label metric shares, with its documented absent-class rule), ignoring
voxels whose ground truth is 255 or whose ground-truth invalid bit is set. Per-class IoU = TP / (TP + FP + FN); mIoU = mean over the semantic
classes (empty excluded). **A class absent from both prediction and ground truth (TP + FP +
FN = 0) is reported as n/a (None) and left out of the mIoU.** Completion IoU / precision /
recall on occupied (label != 0) vs empty. A predicted raw id that is not in the taxonomy is
counted as a wrong class (its own "other" column), never silently as empty.

Depth. Over pixels with ground truth > 0 and below ``max_depth``: delta_k = share with
max(gt/pred, pred/gt) < 1.25**k; AbsRel = mean(|pred - gt| / gt); RMSE; MAE;
SILog = sqrt(mean(d**2) - 0.5 * mean(d)**2) with d = ln pred - ln gt. Per image, then
averaged over images. Predictions <= 0 at valid pixels are clamped to ``min_pred`` (1e-3 m)
so ratios and logs stay finite (they count as large errors). Images with no valid pixel are
skipped (and counted).

SSC and depth are computed overall and per altitude; :func:`evaluate_ssc_dirs` /
:func:`evaluate_depth_dirs` read predictions from the same layout as the ground truth.

Points. :func:`evaluate_points` scores per-point labels (the lifting's output) against truth
labels with the same confusion matrix.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml

from occufly.confusion import Confusion
from occufly.datasets.reader import open_dataset, read_label_file
from occufly.errors import InputFormatError
from occufly.taxonomy import INVALID, Taxonomy


# ---- SSC -------------------------------------------------------------------------------------
class SSCAccumulator:
    """SSC confusion matrix (:class:`occufly.confusion.Confusion`): compact columns 0 = empty,
    1..C = taxonomy classes in table order, C + 1 = any other (unknown) predicted id."""

    def __init__(self, class_ids) -> None:
        self._conf = Confusion(class_ids)
        self.class_ids = self._conf.class_ids

    @property
    def n(self) -> int:
        return self._conf.n

    @property
    def cm(self) -> np.ndarray:
        return self._conf.matrix

    @property
    def confusion(self) -> Confusion:
        return self._conf

    def add(self, pred: np.ndarray, gt: np.ndarray, invalid: np.ndarray | None = None) -> None:
        """pred, gt: (...) uint8 raw ids of the same shape; invalid: same shape bool or None."""
        pred = np.asarray(pred).reshape(-1)
        gt = np.asarray(gt).reshape(-1)
        if pred.shape != gt.shape:
            raise InputFormatError(f"prediction has {pred.size} voxels, ground truth {gt.size}")
        keep = gt != INVALID
        if invalid is not None:
            inv = np.asarray(invalid, dtype=bool).reshape(-1)
            if inv.shape != gt.shape:
                raise InputFormatError(f"invalid mask has {inv.size} voxels, ground truth {gt.size}")
            keep &= ~inv
        self._conf.add(gt, pred, keep)

    def merge(self, other: SSCAccumulator) -> None:
        self._conf.merge(other._conf)

    def result(self, taxonomy: Taxonomy | None = None) -> dict:
        names = {c.id: c.name for c in taxonomy.classes} if taxonomy else {}
        conf = self._conf
        return {
            "voxels": conf.total(),
            "completion": conf.completion(),
            "miou": conf.miou(),
            "classes_evaluated": conf.classes_evaluated(),
            "per_class_iou": conf.per_class_iou([names.get(int(c), str(int(c))) for c in self.class_ids]),
        }


# ---- points ----------------------------------------------------------------------------------
def evaluate_points(labels: np.ndarray, truth: np.ndarray, taxonomy: Taxonomy,
                    origin: np.ndarray | None = None) -> dict:
    """Per-point accuracy and per-class IoU of ``labels`` against ``truth`` (both (N,) uint8).

    Points whose truth is 0 or 255 (or not a taxonomy class) are not evaluated; an unlabelled
    prediction (0, 255 or an unknown id) counts as wrong. ``per_class`` lists the classes
    present in the truth or the prediction; the mIoU follows the absent-class rule of
    :mod:`occufly.confusion` (a class predicted but absent from the truth enters it with IoU 0).
    With ``origin`` (the lifting's per-point origin codes) the accuracy is also split by origin.
    """
    labels = np.asarray(labels)
    truth = np.asarray(truth)
    if labels.shape != truth.shape:
        raise ValueError(f"labels {labels.shape} and truth {truth.shape} differ in shape")
    conf = Confusion(taxonomy.ids)
    t_col = conf.lut[truth]
    valid = (t_col > 0) & (t_col <= conf.C)
    conf.add(truth, labels, valid)
    n_valid = int(valid.sum())
    gt_n, pred_n, tp, iou = conf.truth_counts(), conf.pred_counts(), conf.tp(), conf.class_iou()
    per_class = {}
    for i, c in enumerate(taxonomy.classes):
        if gt_n[i] == 0 and pred_n[i] == 0:
            continue
        per_class[c.name] = {"id": c.id, "truth_points": int(gt_n[i]), "predicted_points": int(pred_n[i]),
                             "iou": float(iou[i])}
    m = conf.matrix
    out = {
        "points": int(len(labels)),
        "evaluated": n_valid,
        "accuracy": float(tp.sum() / n_valid) if n_valid else None,
        "unlabelled": int(m[1 : conf.C + 1, 0].sum() + m[1 : conf.C + 1, conf.C + 1].sum()),
        "miou": conf.miou(),
        "per_class": per_class,
    }
    if origin is not None:
        from occufly.lifting import ORIGIN_NAMES

        origin = np.asarray(origin)
        by = {}
        for o, name in ORIGIN_NAMES.items():
            sel = valid & (origin == o)
            if sel.any():
                by[name] = {"points": int(sel.sum()),
                            "accuracy": float((labels[sel] == truth[sel]).mean())}
        out["by_origin"] = by
    return out


# ---- depth -------------------------------------------------------------------------------------
DEPTH_KEYS = ("d1", "d2", "d3", "abs_rel", "rmse", "mae", "silog")


def depth_metrics(pred: np.ndarray, gt: np.ndarray, *, max_depth: float = 1000.0,
                  min_pred: float = 1e-3) -> dict | None:
    """Metrics of one image. pred, gt: same-size float arrays in metres. None if no valid pixel."""
    pred = np.asarray(pred, dtype=np.float64).reshape(-1)
    gt = np.asarray(gt, dtype=np.float64).reshape(-1)
    if pred.shape != gt.shape:
        raise InputFormatError(f"depth prediction has {pred.size} pixels, ground truth {gt.size}")
    m = (gt > 0) & (gt < max_depth) & np.isfinite(gt)
    if not m.any():
        return None
    g = gt[m]
    p = np.where(np.isfinite(pred[m]), pred[m], min_pred)
    p = np.maximum(p, min_pred)
    ratio = np.maximum(g / p, p / g)
    d = np.log(p) - np.log(g)
    return {
        "d1": float(np.mean(ratio < 1.25)),
        "d2": float(np.mean(ratio < 1.25**2)),
        "d3": float(np.mean(ratio < 1.25**3)),
        "abs_rel": float(np.mean(np.abs(p - g) / g)),
        "rmse": float(np.sqrt(np.mean((p - g) ** 2))),
        "mae": float(np.mean(np.abs(p - g))),
        "silog": float(np.sqrt(max(np.mean(d**2) - 0.5 * np.mean(d) ** 2, 0.0))),
        "pixels": int(m.sum()),
    }


def average_depth(per_image: list[dict]) -> dict:
    out: dict = {"images": len(per_image)}
    for k in DEPTH_KEYS:
        out[k] = float(np.mean([r[k] for r in per_image])) if per_image else None
    return out


# ---- reading exports -------------------------------------------------------------------------
PRED_LAYOUTS = ("occufly", "sscbench", "flat")


def prediction_layout(root: Path) -> str:
    """``occufly`` (OccuFly_Dataset/.../<frame>.label), ``sscbench`` (data_2d_raw/<seq>/voxels/
    <frame>.label or preprocess/labels/<seq>/<frame>_1_1.npy) or ``flat`` (<seq>/<frame>.label
    or <seq>/<frame>_1_1.npy directly under the root)."""
    root = Path(root)
    if not root.is_dir():
        raise InputFormatError(f"{root}: prediction folder not found")
    if (root / "OccuFly_Dataset").is_dir():
        return "occufly"
    if (root / "data_2d_raw").is_dir() or (root / "preprocess").is_dir():
        return "sscbench"
    return "flat"


def _inverse_lut(pred_root: Path, gt_root: Path, taxonomy: Taxonomy) -> np.ndarray:
    """(256,) int16 training id -> raw id (-1 where the map has no entry), from the
    prediction's occufly.yaml, else the ground truth's, else the taxonomy."""
    inv = None
    for y in (pred_root / "occufly.yaml", gt_root / "occufly.yaml"):
        if y.is_file():
            try:
                doc = yaml.safe_load(y.read_text())
                inv = {int(k): int(v) for k, v in doc["learning_map_inv"].items()}
            except (ValueError, KeyError, TypeError, yaml.YAMLError):
                raise InputFormatError(f"{y}: no readable learning_map_inv") from None
            break
    if inv is None:
        inv = {v: k for k, v in taxonomy.learning_map().items()}
    lut = np.full(256, -1, np.int16)
    for t, r in inv.items():
        if not (0 <= t <= 255 and 0 <= r <= 255):
            raise InputFormatError(f"learning_map_inv entry {t}: {r} is outside 0..255")
        lut[t] = r
    lut[255] = 255
    return lut


def _read_prediction(pred_root: Path, layout: str, scene: str, alt: int, fid: str, seq: str,
                     n: int, shape: tuple[int, ...], inv_lut: np.ndarray) -> np.ndarray:
    """Raw-id prediction of one frame; training-id ``_1_1.npy`` files are mapped back."""
    if layout == "occufly":
        cands = [(pred_root / "OccuFly_Dataset" / scene / str(alt) / "ground_truth" / fid / f"{fid}.label", "u1")]
    elif layout == "sscbench":
        cands = [(pred_root / "data_2d_raw" / seq / "voxels" / f"{fid}.label", "<u2"),
                 (pred_root / "preprocess" / "labels" / seq / f"{fid}_1_1.npy", "npy")]
    else:
        cands = [(pred_root / seq / f"{fid}_1_1.npy", "npy"), (pred_root / seq / f"{fid}.label", "auto")]
    for path, kind in cands:
        if not path.is_file():
            continue
        if kind == "npy":
            try:  # header first (memory-mapped): a wrong size fails before anything is read
                t = np.load(path, allow_pickle=False, mmap_mode="r")
            except ValueError as e:
                raise InputFormatError(f"{path}: not a numpy label grid ({e})") from None
            if t.size != n or not np.issubdtype(t.dtype, np.integer):
                raise InputFormatError(f"{path}: {t.size} {t.dtype} values, expected {n} integer "
                                       f"training ids for grid {shape}")
            t = np.asarray(t).reshape(-1)
            if t.min(initial=0) < 0 or t.max(initial=0) > 255 or np.any(inv_lut[t.astype(np.int64)] < 0):
                bad = t[(t < 0) | (t > 255)]
                bad = bad if bad.size else t[inv_lut[np.clip(t, 0, 255).astype(np.int64)] < 0]
                raise InputFormatError(f"{path}: training id {int(bad[0])} is not in learning_map_inv")
            return inv_lut[t.astype(np.int64)].astype(np.uint8)
        if kind == "auto":
            size = path.stat().st_size
            kind = "u1" if size == n else "<u2"
        return read_label_file(path, n, shape, dtype=kind).reshape(-1)
    raise InputFormatError(f"{cands[0][0]}: prediction for frame {scene}/{alt}/{fid} is missing "
                           f"({layout} layout{'; looked for ' + ', '.join(str(c[0]) for c in cands[1:]) if len(cands) > 1 else ''})")


def evaluate_ssc_dirs(pred_root: Path, gt_root: Path) -> dict:
    """Evaluate every frame of the ground-truth export (OccuFly or SSCBench layout) against
    the same frames of the predictions, in any of :data:`PRED_LAYOUTS` (raw-id ``.label``
    files, or ``_1_1.npy`` training ids mapped back through the YAML's ``learning_map_inv``).
    Returns overall, per-altitude and per-scene results."""
    pred_root, gt_root = Path(pred_root), Path(gt_root)
    gt = open_dataset(gt_root)
    if not gt.frames:
        raise InputFormatError(f"{gt_root}: no ground-truth frames found")
    tax = gt.taxonomy
    layout = prediction_layout(pred_root)
    inv_lut = _inverse_lut(pred_root, gt_root, tax)
    shape = gt.grid_shape
    n = int(np.prod(shape))
    overall = SSCAccumulator(tax.ids)
    per_alt: dict[int, SSCAccumulator] = {}
    per_scene: dict[str, SSCAccumulator] = {}
    frames_per_alt: dict[int, int] = {}
    for key in gt.frames:
        label, invalid = gt.read_labels(key)
        pred = _read_prediction(pred_root, layout, key.scene, key.altitude, key.frame_id,
                                key.sequence, n, shape, inv_lut)
        acc = per_alt.setdefault(key.altitude, SSCAccumulator(tax.ids))
        acc.add(pred, label, invalid)
        frames_per_alt[key.altitude] = frames_per_alt.get(key.altitude, 0) + 1
        sc = per_scene.setdefault(key.scene, SSCAccumulator(tax.ids))
        sc.add(pred, label, invalid)
    for acc in per_alt.values():
        overall.merge(acc)
    out_alt = {}
    for a in sorted(per_alt):
        out_alt[str(a)] = per_alt[a].result(tax)
        out_alt[str(a)]["frames"] = frames_per_alt[a]
    return {
        "frames": len(gt.frames),
        "gt_layout": gt.layout,
        "pred_layout": layout,
        "overall": overall.result(tax),
        "per_altitude": out_alt,
        "per_scene": {s: per_scene[s].result(tax) for s in sorted(per_scene)},
        "note": "classes absent from both prediction and ground truth are n/a and excluded from mIoU",
    }


def _depth_path(root: Path, layout: str, scene: str, alt: int, fid: str, seq: str) -> Path:
    if layout == "occufly":
        return root / "OccuFly_Dataset" / scene / str(alt) / "depth_maps" / f"{fid}.npy"
    if layout == "sscbench":
        return root / "depth" / seq / f"{fid}.npy"
    return root / seq / f"{fid}.npy"


def evaluate_depth_dirs(pred_root: Path, gt_root: Path, *, max_depth: float = 1000.0) -> dict:
    """Depth metrics of the predicted 1/4-resolution depth maps against the ground-truth
    export's (OccuFly layout ``depth_maps/<frame>.npy``, SSCBench layout ``depth/<seq>/<frame>.npy``;
    predictions in either, or ``<seq>/<frame>.npy`` under PRED), per image then averaged;
    overall and per altitude. Maps are compared by value count (flattened or 2-D)."""
    pred_root, gt_root = Path(pred_root), Path(gt_root)
    gt = open_dataset(gt_root)
    layout = prediction_layout(pred_root)
    per_alt: dict[int, list[dict]] = {}
    skipped = found = 0
    for key in gt.frames:
        gp = _depth_path(gt_root, gt.layout, key.scene, key.altitude, key.frame_id, key.sequence)
        if not gp.is_file():
            continue
        found += 1
        pp = _depth_path(pred_root, layout, key.scene, key.altitude, key.frame_id, key.sequence)
        if not pp.is_file():
            raise InputFormatError(f"{pp}: predicted depth map is missing")
        try:
            g = np.load(gp, allow_pickle=False)
            pm = np.load(pp, allow_pickle=False, mmap_mode="r")
        except ValueError as e:
            raise InputFormatError(f"{pp}: not a numpy depth map ({e})") from None
        if pm.size != g.size:
            raise InputFormatError(f"{pp}: {pm.size} pixels, expected {g.size}")
        r = depth_metrics(np.asarray(pm), g, max_depth=max_depth)
        if r is None:
            skipped += 1
            continue
        per_alt.setdefault(key.altitude, []).append(r)
    if not found:
        raise InputFormatError(f"{gt_root}: no ground-truth depth maps found")
    all_images = [r for rs in per_alt.values() for r in rs]
    return {
        "images": len(all_images), "skipped_no_gt": skipped, "max_depth": max_depth,
        "gt_layout": gt.layout, "pred_layout": layout,
        "overall": average_depth(all_images),
        "per_altitude": {str(a): average_depth(per_alt[a]) for a in sorted(per_alt)},
    }


# ---- tables -------------------------------------------------------------------------------------
def _fmt(v: float | None, pct: bool = True) -> str:
    if v is None:
        return "n/a"
    return f"{100 * v:.2f}" if pct else f"{v:.3f}"


def ssc_table(result: dict) -> str:
    """A table like the benchmark paper's: rows = overall and per altitude; columns =
    completion IoU, mIoU and per-class IoU (in %)."""
    rows = [("all", result["overall"])] + [(f"{a} m", r) for a, r in result["per_altitude"].items()]
    # classes that are n/a overall (absent from prediction and ground truth) are not shown
    classes = [k for k, v in result["overall"]["per_class_iou"].items() if v is not None]
    head = ["split", "IoU", "Prec", "Rec", "mIoU"] + classes
    lines = [head]
    for name, r in rows:
        c = r["completion"]
        lines.append([name, _fmt(c["iou"]), _fmt(c["precision"]), _fmt(c["recall"]), _fmt(r["miou"])]
                     + [_fmt(r["per_class_iou"].get(k)) for k in classes])
    widths = [max(len(str(row[i])) for row in lines) for i in range(len(head))]
    out = ["  ".join(str(v).rjust(w) for v, w in zip(row, widths, strict=True)) for row in lines]
    out.append(result.get("note", ""))
    return "\n".join(out)


TABLE_FORMATS = ("text", "markdown", "latex", "json")


def _ssc_rows(result: dict) -> tuple[list[list[str]], list[list[str]]]:
    """(per-altitude rows, per-class rows) with a header row each, values in %."""
    rows = [("all", result["overall"], result.get("frames"))] + [
        (f"{a} m", r, r.get("frames")) for a, r in result["per_altitude"].items()]
    alt = [["split", "frames", "IoU", "Prec.", "Rec.", "mIoU"]]
    for name, r, nf in rows:
        c = r["completion"]
        alt.append([name, "" if nf is None else str(nf), _fmt(c["iou"]), _fmt(c["precision"]),
                    _fmt(c["recall"]), _fmt(r["miou"])])
    classes = [k for k, v in result["overall"]["per_class_iou"].items() if v is not None]
    cls = [["class"] + [name for name, _, _ in rows]]
    for k in classes:
        cls.append([k] + [_fmt(r["per_class_iou"].get(k)) for _, r, _ in rows])
    cls.append(["mIoU"] + [_fmt(r["miou"]) for _, r, _ in rows])
    return alt, cls


def _markdown(rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(rows[0]) + " |", "|" + "|".join([":---"] + ["---:"] * (len(rows[0]) - 1)) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    return "\n".join(out)


def _latex(rows: list[list[str]], caption: str) -> str:
    def esc(v: str) -> str:
        return v.replace("\\", r"\textbackslash{}").replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")

    cols = "l" + "r" * (len(rows[0]) - 1)
    out = [r"\begin{table}[t]", r"\centering", rf"\caption{{{esc(caption)}}}", rf"\begin{{tabular}}{{{cols}}}",
           r"\toprule", " & ".join(esc(v) for v in rows[0]) + r" \\", r"\midrule"]
    out += [" & ".join(esc(v) for v in r) + r" \\" for r in rows[1:]]
    out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out)


def ssc_report(result: dict, fmt: str = "text") -> str:
    """The paper's two tables -- per altitude (completion IoU / precision / recall, mIoU) and
    per class (IoU per altitude), in %, -- as ``text``, ``markdown``, ``latex`` or ``json``.
    Classes n/a overall (absent from prediction and ground truth) are not shown."""
    if fmt == "json":
        return json.dumps(result, indent=1)
    if fmt == "text":
        return ssc_table(result)
    alt, cls = _ssc_rows(result)
    note = result.get("note", "")
    if fmt == "markdown":
        return (f"**SSC per altitude** (%)\n\n{_markdown(alt)}\n\n**SSC per class** (IoU %)\n\n"
                f"{_markdown(cls)}\n\n{note}\n")
    if fmt == "latex":
        return (_latex(alt, "Semantic scene completion per altitude (%)") + "\n\n"
                + _latex(cls, "Per-class IoU (%) per altitude; " + note) + "\n")
    raise ValueError(f"unknown table format {fmt!r}; expected one of {', '.join(TABLE_FORMATS)}")


def depth_table(result: dict) -> str:
    rows = [("all", result["overall"])] + [(f"{a} m", r) for a, r in result["per_altitude"].items()]
    head = ["split", "images", "d1", "d2", "d3", "AbsRel", "RMSE", "MAE", "SILog"]
    lines = [head]
    for name, r in rows:
        lines.append([name, str(r["images"])] + [_fmt(r[k], pct=False) for k in DEPTH_KEYS])
    widths = [max(len(row[i]) for row in lines) for i in range(len(head))]
    return "\n".join("  ".join(v.rjust(w) for v, w in zip(row, widths, strict=True)) for row in lines)
