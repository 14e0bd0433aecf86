"""04 - A training loop over an export: DataLoader, two trivial baselines, ``occufly eval-ssc``.

Iterates a ``torch.utils.data.DataLoader`` over an export (either layout) with
:class:`occufly.datasets.torch.OccuFlyDataset`, "predicts" with two baselines that need no
training and scores them with ``occufly eval-ssc`` (Markdown tables per altitude and class):

- ``empty``: every voxel empty -- completion IoU 0, the floor any model must beat;
- ``upsample_1_8``: the ground truth's own ``1_8`` grid copied back up to full resolution
  (nearest, 8x per axis) -- what a perfect 1/8-resolution model would score, i.e. the
  ceiling the coarse grid imposes.

Predictions are written as ``<pred>/<sequence>/<frame>_1_1.npy`` training ids (the way
MonoScene-style code dumps them); ``eval-ssc`` maps them back through ``occufly.yaml``.
Without an EXPORT argument a ``tiny`` synthetic scene is generated, imported and exported
(SSCBench layout, its exact truth grid as the scene grid) into a temporary folder first.

    .venv/bin/python examples/04_train_loop.py [EXPORT] [--split train] [--batch-size 2]

Needs the optional extra ``occufly[torch]`` (``scripts/setup.sh --test`` installs it).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader

from occufly.cli import main as occufly
from occufly.datasets.torch import OccuFlyDataset, collate


def build_demo_export(work: Path) -> Path:
    """synth (tiny) -> import -> export (SSCBench layout) with the synthetic truth grid."""
    from occufly.export import export_dataset
    from occufly.grid import SceneGrid

    synth, ws, out = work / "synth", work / "ws", work / "export"
    for argv in (["synth", str(synth), "--preset", "tiny"],
                 ["import", str(synth), "--workspace", str(ws)]):
        print("occufly", " ".join(argv))
        with contextlib.redirect_stdout(io.StringIO()):  # their summaries are long
            rc = occufly(argv)
        if rc != 0:
            raise SystemExit(f"occufly {' '.join(argv)} failed")
    truth = SceneGrid.load(synth / "truth" / "scene_grid.npz")
    res = export_dataset(ws, out, layout="sscbench", grid=truth, frames=list(range(0, 36, 3)), workers=2)
    print(f"exported {res['written']} frames (SSCBench layout) in {res['seconds']:.1f} s -> {out}")
    return out


def upsample(t: torch.Tensor, f: int) -> torch.Tensor:
    return t.repeat_interleave(f, dim=-3).repeat_interleave(f, dim=-2).repeat_interleave(f, dim=-1)


def run(export: Path, split: str | None, batch_size: int, work: Path) -> None:
    ds = OccuFlyDataset(export, split=split, scales=("1_1", "1_8"))
    if len(ds) == 0:
        raise SystemExit(f"{export}: no frames in split {split!r}")
    loader = DataLoader(ds, batch_size=batch_size, collate_fn=collate, num_workers=0)
    preds = {"empty": work / "pred_empty", "upsample_1_8": work / "pred_upsample_1_8"}
    t0, n = time.perf_counter(), 0
    for batch in loader:  # the loop a model's training / evaluation step would sit in
        target = batch["target_1_1"]                      # (B, X, Y, Z) int64, 255 = ignore
        coarse = batch["target_1_8"]                      # (B, X/8, Y/8, Z/8)
        guesses = {"empty": torch.zeros_like(target),
                   "upsample_1_8": torch.where(upsample(coarse, 8) == 255, 0, upsample(coarse, 8))}
        for name, pred in guesses.items():
            for b in range(target.shape[0]):
                d = preds[name] / batch["sequence"][b]
                d.mkdir(parents=True, exist_ok=True)
                np.save(d / f"{batch['frame_id'][b]}_1_1.npy", pred[b].numpy().astype(np.uint8))
        n += target.shape[0]
    print(f"{n} frames through the DataLoader in {time.perf_counter() - t0:.1f} s "
          f"(image {tuple(batch['img'].shape[1:])}, target {tuple(target.shape[1:])})\n")
    for name, pred in preds.items():
        print(f"## baseline: {name}\n")
        occufly(["eval-ssc", str(pred), str(export), "--format", "markdown"])


def cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("export", type=Path, nargs="?", help="export root (default: build a tiny demo)")
    ap.add_argument("--split", choices=("train", "val", "test"), help="only this split's frames")
    ap.add_argument("--batch-size", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="occufly-train-") as tmp:
        work = Path(tmp)
        export = args.export or build_demo_export(work)
        run(export, args.split, args.batch_size, work)


if __name__ == "__main__":
    cli()
