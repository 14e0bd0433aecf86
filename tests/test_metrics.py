"""SSC and depth metrics: identity gives 1, perturbed copies match slow Python references."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from occufly.cli import main
from occufly.errors import InputFormatError
from occufly.export import export_dataset
from occufly.metrics import SSCAccumulator, depth_metrics, evaluate_depth_dirs, evaluate_ssc_dirs
from occufly.taxonomy import default_taxonomy
from tests.export_fixtures import SPEC, make_workspace


@pytest.fixture(scope="module")
def gt_export(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("met")
    ws = make_workspace(root, n_frames=3)
    out = root / "gt"
    export_dataset(ws, out, spec=SPEC, workers=1)
    return out


def label_files(root: Path) -> list[Path]:
    return sorted(root.glob("OccuFly_Dataset/*/*/ground_truth/*/*.label"))


def perturb(gt: Path, pred: Path, seed: int = 0) -> None:
    shutil.copytree(gt, pred)
    rng = np.random.default_rng(seed)
    ids = np.array([0, 6, 8, 16, 13, 77])  # 77 is not a class of the taxonomy
    for p in label_files(pred):
        lab = np.fromfile(p, np.uint8)
        flip = rng.random(lab.size) < 0.05
        lab[flip] = rng.choice(ids, int(flip.sum()))
        lab.tofile(p)
    for p in sorted(pred.glob("OccuFly_Dataset/*/*/depth_maps/*.npy")):
        d = np.load(p)
        d = d * rng.uniform(0.8, 1.25, d.shape).astype(np.float32)
        d[rng.random(d.size) < 0.05] = 0.0  # missing predictions
        np.save(p, d)


def slow_ssc(pred_root: Path, gt_root: Path) -> dict:
    """Reference: plain Python loops over voxels, following FORMATS.md section 5."""
    classes = [int(c) for c in default_taxonomy().ids]
    tp = dict.fromkeys(classes, 0)
    fp = dict.fromkeys(classes, 0)
    fn = dict.fromkeys(classes, 0)
    ctp = cfp = cfn = 0
    for g in label_files(gt_root):
        rel = g.relative_to(gt_root)
        gl = np.fromfile(g, np.uint8).tolist()
        pl = np.fromfile(pred_root / rel, np.uint8).tolist()
        inv = np.unpackbits(np.fromfile(g.with_suffix(".invalid"), np.uint8))[: len(gl)].tolist()
        for gv, pv, iv in zip(gl, pl, inv, strict=True):
            if gv == 255 or iv:
                continue
            if gv != 0 and pv != 0:
                ctp += 1
            elif gv == 0 and pv != 0:
                cfp += 1
            elif gv != 0 and pv == 0:
                cfn += 1
            if gv == pv:
                if gv != 0:
                    tp[gv] += 1
            else:
                if pv in tp:
                    fp[pv] += 1
                if gv in tp:
                    fn[gv] += 1
    ious = {c: (tp[c] / (tp[c] + fp[c] + fn[c]) if tp[c] + fp[c] + fn[c] else None) for c in classes}
    present = [v for v in ious.values() if v is not None]
    return {"iou": ctp / (ctp + cfp + cfn), "precision": ctp / (ctp + cfp), "recall": ctp / (ctp + cfn),
            "miou": sum(present) / len(present), "per_class": ious}


def test_ssc_identity_is_one(gt_export):
    res = evaluate_ssc_dirs(gt_export, gt_export)
    o = res["overall"]
    assert o["completion"] == {"iou": 1.0, "precision": 1.0, "recall": 1.0}
    assert o["miou"] == 1.0 and o["classes_evaluated"] == 2  # grass and building are seen
    assert o["per_class_iou"]["road"] is None  # absent from both: n/a, not in the mean
    assert set(res["per_altitude"]) == {"30", "50"}


def test_ssc_perturbed_matches_slow_reference(gt_export, tmp_path):
    pred = tmp_path / "pred"
    perturb(gt_export, pred)
    res = evaluate_ssc_dirs(pred, gt_export)["overall"]
    ref = slow_ssc(pred, gt_export)
    assert res["completion"]["iou"] == pytest.approx(ref["iou"], abs=1e-12)
    assert res["completion"]["precision"] == pytest.approx(ref["precision"], abs=1e-12)
    assert res["completion"]["recall"] == pytest.approx(ref["recall"], abs=1e-12)
    assert res["miou"] == pytest.approx(ref["miou"], abs=1e-12)
    names = {c.id: c.name for c in default_taxonomy().classes}
    for cid, v in ref["per_class"].items():
        got = res["per_class_iou"][names[cid]]
        assert (got is None) == (v is None) and (v is None or got == pytest.approx(v, abs=1e-12))
    assert 0.3 < res["miou"] < 0.999


def test_accumulator_ignores_255_and_invalid():
    acc = SSCAccumulator(np.array([6, 16], np.uint8))
    gt = np.array([6, 6, 16, 255, 0, 16], np.uint8)
    pred = np.array([6, 16, 16, 6, 16, 0], np.uint8)
    inv = np.array([0, 0, 0, 0, 0, 1], bool)
    acc.add(pred, gt, inv)
    r = acc.result()
    # grass: TP 1, FN 1 -> 1/2; building: TP 1, FP 2 (from grass and empty) -> 1/3
    assert r["per_class_iou"] == {"6": 0.5, "16": pytest.approx(1 / 3)}
    assert r["completion"]["iou"] == pytest.approx(3 / 4)


def slow_depth(pred: np.ndarray, gt: np.ndarray) -> dict:
    d1 = d2 = d3 = 0
    s_abs = s_sq = s_ae = s_d = s_d2 = 0.0
    n = 0
    for p, g in zip(pred.ravel().tolist(), gt.ravel().tolist(), strict=True):
        if not g > 0:
            continue
        p = max(p, 1e-3)
        n += 1
        r = max(g / p, p / g)
        d1 += r < 1.25
        d2 += r < 1.25**2
        d3 += r < 1.25**3
        s_abs += abs(p - g) / g
        s_sq += (p - g) ** 2
        s_ae += abs(p - g)
        d = math.log(p) - math.log(g)
        s_d += d
        s_d2 += d * d
    return {"d1": d1 / n, "d2": d2 / n, "d3": d3 / n, "abs_rel": s_abs / n, "rmse": math.sqrt(s_sq / n),
            "mae": s_ae / n, "silog": math.sqrt(s_d2 / n - 0.5 * (s_d / n) ** 2)}


def test_depth_identity_and_perturbed(gt_export, tmp_path):
    res = evaluate_depth_dirs(gt_export, gt_export)["overall"]
    assert res["d1"] == 1.0 and res["abs_rel"] == 0.0 and res["rmse"] == 0.0 and res["silog"] == 0.0
    pred = tmp_path / "pred"
    perturb(gt_export, pred, seed=5)
    res = evaluate_depth_dirs(pred, gt_export)
    refs = []
    for g in sorted(gt_export.glob("OccuFly_Dataset/*/*/depth_maps/*.npy")):
        refs.append(slow_depth(np.load(pred / g.relative_to(gt_export)), np.load(g)))
    for k in ("d1", "d2", "d3", "abs_rel", "rmse", "mae", "silog"):
        assert res["overall"][k] == pytest.approx(np.mean([r[k] for r in refs]), rel=1e-9), k
    assert 0.5 < res["overall"]["d1"] < 1.0


def test_depth_metrics_none_without_gt():
    assert depth_metrics(np.ones(4), np.zeros(4)) is None


def test_cli_tables_and_json(gt_export, tmp_path, capsys):
    pred = tmp_path / "pred"
    perturb(gt_export, pred)
    assert main(["eval-ssc", str(pred), str(gt_export), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["overall"]["miou"] == evaluate_ssc_dirs(pred, gt_export)["overall"]["miou"]
    assert main(["eval-ssc", str(pred), str(gt_export)]) == 0
    table = capsys.readouterr().out
    assert "mIoU" in table and "building" in table and "50 m" in table
    assert main(["eval-depth", str(pred), str(gt_export)]) == 0
    assert "AbsRel" in capsys.readouterr().out
    missing = tmp_path / "missing"
    shutil.copytree(gt_export, missing)
    label_files(missing)[0].unlink()
    with pytest.raises(InputFormatError, match="prediction for frame .* is missing"):
        evaluate_ssc_dirs(missing, gt_export)
    assert main(["eval-ssc", str(missing), str(gt_export)]) == 2
