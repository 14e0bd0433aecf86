"""A model trains on the export: a CPU smoke run of MonoScene's own model (random init, a small
2D backbone instead of the downloaded EfficientNet-B7) and of a pure-PyTorch baseline, on an
SSCBench-layout export with ``--split-by altitude``; evaluated on the test split with the
project's SSC metrics (occufly.metrics.SSCAccumulator) and MonoScene's own (SSCMetrics).
Prints one JSON object and writes the loss-curve PNG (docs/ssc-porting.md, "A model trains on
the export").

    python bench/bench_ssc_train.py EXPORT --monoscene DIR [--steps 300] [--plot PNG] > JSON

Run outside CI (it fetches nothing; DIR is a checkout of astra-vision/MonoScene f52bbb1; its
Python deps: pytorch-lightning, matplotlib for the plot). What runs of MonoScene is its own
code: ``MonoScene`` (FLoSP lifting, the 3D UNet with the context-prior layer, the CE /
sem-scal / geo-scal / relation / frustum-proportion losses), ``collate_fn``, ``SSCMetrics``,
``configure_optimizers`` (AdamW); the data come from occufly.datasets.compat.monoscene
(the documented port). Replaced, and said so in the JSON: the 2D network ``UNet2D.build``
(downloads EfficientNet-B7 weights through torch.hub: here a 4-level CNN with the same
output dict ``1_1 .. 1_16`` of ``feature`` channels), ``Tensor.cuda`` (its forward moves the
projections with ``.cuda()``: the identity on this CPU-only machine) and ``LightningModule.log``
(no Trainer: the logged loss terms are recorded for the curve).

The baseline is a small 2D encoder (3 conv layers to 1/4 resolution) whose features each voxel
gathers at its pixel of the export's own projection (the adapter's ``projected_pix_1``,
``fov_mask_1``) with its depth, then two 3D convolutions: trained with the same optimizer,
steps and class-weighted cross-entropy.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))


def small_unet2d(feature: int):
    """The stand-in for MonoScene's UNet2D (EfficientNet-B7, pretrained weights from the net):
    the same output, a dict of ``feature``-channel maps at 1/1, 1/2, 1/4, 1/8, 1/16."""
    from torch import nn

    def block(i, o, s):
        return nn.Sequential(nn.Conv2d(i, o, 3, s, 1, bias=False), nn.BatchNorm2d(o), nn.ReLU(inplace=True))

    class Small(nn.Module):
        def __init__(self):
            super().__init__()
            ch = [16, 24, 32, 48, 64]
            self.down = nn.ModuleList([block(3, ch[0], 1), block(ch[0], ch[1], 2), block(ch[1], ch[2], 2),
                                       block(ch[2], ch[3], 2), block(ch[3], ch[4], 2)])
            self.out = nn.ModuleList([nn.Conv2d(c, feature, 1) for c in ch])

        def forward(self, x):
            feats, out = x, {}
            for i, (d, o) in enumerate(zip(self.down, self.out, strict=True)):
                feats = d(feats)
                out[f"1_{2 ** i}"] = o(feats)
            return out

    return Small()


class Baseline:
    """The pure-PyTorch reference: 2D encoder -> lift by the export's projection -> 3D head."""

    def __init__(self, n_classes: int, grid_shape, feat: int = 24):
        import torch
        from torch import nn

        self.grid_shape = tuple(grid_shape)
        self.enc = nn.Sequential(
            nn.Conv2d(3, 16, 3, 2, 1), nn.BatchNorm2d(16), nn.ReLU(inplace=True),
            nn.Conv2d(16, feat, 3, 2, 1), nn.BatchNorm2d(feat), nn.ReLU(inplace=True),
            nn.Conv2d(feat, feat, 3, 1, 1), nn.BatchNorm2d(feat), nn.ReLU(inplace=True))
        self.head = nn.Sequential(
            nn.Conv3d(feat + 2, 32, 3, 1, 1), nn.BatchNorm3d(32), nn.ReLU(inplace=True),
            nn.Conv3d(32, 32, 3, 1, 1), nn.BatchNorm3d(32), nn.ReLU(inplace=True),
            nn.Conv3d(32, n_classes, 1))
        self.net = nn.ModuleDict({"enc": self.enc, "head": self.head})
        self.torch = torch

    def __call__(self, batch):
        torch = self.torch
        f = self.enc(batch["img"])  # (B, C, h, w) at 1/4
        B, C, h, w = f.shape
        out = []
        for b in range(B):
            pix = batch["projected_pix_1"][b] // 4
            fov = batch["fov_mask_1"][b]
            z = batch["pix_z_1"][b].float()
            u = pix[:, 0].clamp(0, w - 1)
            v = pix[:, 1].clamp(0, h - 1)
            g = f[b][:, v, u] * fov.float()  # (C, N)
            extra = torch.stack([fov.float(), z / 100.0])  # in-view flag, depth of the voxel
            out.append(torch.cat([g, extra]).reshape(C + 2, *self.grid_shape))
        return self.head(torch.stack(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("export", type=Path)
    ap.add_argument("--monoscene", type=Path, required=True)
    ap.add_argument("--commit", default="f52bbb1")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--feature", type=int, default=8)
    ap.add_argument("--frustum-size", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--plot", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-budget", type=float, default=0,
                    help="stop training after this many wall seconds (0: none); the JSON says how many steps ran")
    ap.add_argument("--test-every", type=int, default=1, help="evaluate every n-th test frame")
    a = ap.parse_args()

    import torch

    json_out = sys.stdout
    sys.stdout = sys.stderr  # MonoScene prints (CRP3D, test_epoch_end): keep stdout for the JSON
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    np.random.seed(a.seed)
    import pytorch_lightning  # noqa: F401 - probes torchvision (find_spec) before the stub exists
    from bench_ssc_loaders import stub_torchvision

    stubs = stub_torchvision()
    sys.path.insert(0, str(a.monoscene))
    torch.Tensor.cuda = lambda self, *args, **kw: self  # their forward: projected_pix.cuda()
    unet2d = importlib.import_module("monoscene.models.unet2d")
    unet2d.UNet2D.build = classmethod(lambda cls, out_feature, use_decoder=True: small_unet2d(out_feature))
    from monoscene.data.semantic_kitti.collate import collate_fn
    from monoscene.models.monoscene import MonoScene

    from occufly.datasets.compat.common import load_geometry
    from occufly.datasets.compat.monoscene import KittiDataset, training_constants
    from occufly.metrics import SSCAccumulator

    export = a.export.absolute()
    geom = load_geometry(export)
    consts = training_constants(export)
    man = json.loads(next((export / "manifests").glob("*.json")).read_text())
    raw_of = {c["name"]: int(c["id"]) for c in man["taxonomy"]["classes"]}
    lut = np.array([0] + [raw_of[n] for n in geom.class_names[1:]], np.uint8)  # train id -> raw id

    t0 = time.perf_counter()
    data = {s: KittiDataset(s, export, export / "preprocess", frustum_size=a.frustum_size)
            for s in ("train", "test")}
    cache = {s: [ds[i] for i in range(len(ds))] for s, ds in data.items()}  # fliplr 0: no flip
    load_s = time.perf_counter() - t0

    def batches(split, shuffle, rng):
        items = cache[split]
        order = rng.permutation(len(items)) if shuffle else np.arange(0, len(items), a.test_every)
        for i in order:
            b = collate_fn([items[i]])  # MonoScene's own collate (it drops pix_z: the baseline's)
            b["pix_z_1"] = [torch.from_numpy(items[i]["pix_z_1"])]
            yield b

    cw = consts["class_weights"]
    model = MonoScene(dataset="kitti", frustum_size=a.frustum_size, project_scale=2,
                      n_relations=4, fp_loss=True, feature=a.feature, full_scene_size=consts["full_scene_size"],
                      project_res=["1", "2", "4", "8"], n_classes=consts["n_classes"],
                      class_names=consts["class_names"], context_prior=True, relation_loss=True,
                      CE_ssc_loss=True, sem_scal_loss=True, geo_scal_loss=True, lr=a.lr,
                      weight_decay=1e-4, class_weights=cw)
    logged: dict = {}
    model.log = lambda name, value, **kw: logged.__setitem__(name, float(value))
    [opt], _ = model.configure_optimizers()
    base = Baseline(consts["n_classes"], geom.grid_shape)
    bopt = torch.optim.AdamW(base.net.parameters(), lr=a.lr, weight_decay=1e-4)
    ce = torch.nn.CrossEntropyLoss(weight=cw.float(), ignore_index=255)

    curves = {"monoscene": [], "monoscene_ssc_ce": [], "baseline": []}
    rng = np.random.default_rng(a.seed)
    wall = {"monoscene": 0.0, "baseline": 0.0}
    step = 0
    model.train()
    base.net.train()
    t_train = time.perf_counter()
    stopped = False
    while step < a.steps and not stopped:
        for batch in batches("train", True, rng):
            if step >= a.steps:
                break
            if a.time_budget and time.perf_counter() - t_train > a.time_budget:
                stopped = True
                break
            t = time.perf_counter()
            opt.zero_grad()
            loss = model.step(batch, "train", model.train_metrics)
            loss.backward()
            opt.step()
            wall["monoscene"] += time.perf_counter() - t
            curves["monoscene"].append(float(loss.detach()))
            curves["monoscene_ssc_ce"].append(logged.get("train/loss_ssc", float("nan")))
            t = time.perf_counter()
            bopt.zero_grad()
            bl = ce(base(batch), batch["target"].long())
            bl.backward()
            bopt.step()
            wall["baseline"] += time.perf_counter() - t
            curves["baseline"].append(float(bl.detach()))
            step += 1
            if step % 25 == 0:
                print(f"step {step}: monoscene {np.mean(curves['monoscene'][-25:]):.3f} "
                      f"(ssc ce {np.mean(curves['monoscene_ssc_ce'][-25:]):.3f}) "
                      f"baseline {np.mean(curves['baseline'][-25:]):.3f}", file=sys.stderr, flush=True)

    # evaluation on the test split: the project's metric and MonoScene's SSCMetrics
    model.eval()
    base.net.eval()
    seen: dict = {}
    fwd = model.forward

    def forward_and_keep(b):  # step() runs the forward; keep its output for our metric
        seen["out"] = fwd(b)
        return seen["out"]

    model.forward = forward_and_keep
    classes = [int(c["id"]) for c in man["taxonomy"]["classes"]]
    ours = {"monoscene": SSCAccumulator(classes), "baseline": SSCAccumulator(classes)}
    from monoscene.loss.sscMetrics import SSCMetrics

    theirs = {"monoscene": model.test_metrics, "baseline": SSCMetrics(consts["n_classes"])}
    theirs["monoscene"].reset()
    with torch.no_grad():
        for batch in batches("test", False, rng):
            model.step(batch, "test", model.test_metrics)  # their own test step adds to SSCMetrics
            pm = seen["out"]["ssc_logit"].argmax(1).numpy()  # the same forward's prediction
            pb = base(batch).argmax(1).numpy()
            gt = batch["target"].numpy()
            theirs["baseline"].add_batch(pb, gt)
            for k, p in (("monoscene", pm), ("baseline", pb)):
                ours[k].add(lut[p], np.where(gt == 255, 255, lut[np.minimum(gt, len(lut) - 1)]).astype(np.uint8))

    def smooth(x, k=25):
        x = np.asarray(x, float)
        return [float(np.mean(x[max(0, i - k + 1):i + 1])) for i in range(len(x))]

    res = {"export": str(export), "grid_shape": list(geom.grid_shape), "voxel_size": geom.voxel_size,
           "frames": {s: len(v) for s, v in cache.items()}, "test_every": a.test_every,
           "steps": step, "steps_asked": a.steps, "stopped_by_time_budget": stopped, "batch_size": 1,
           "train_wall_total_s": round(time.perf_counter() - t_train, 1),
           "lr": a.lr, "threads": a.threads, "codebase": {"name": "MonoScene", "commit": a.commit},
           "monoscene_config": {"feature": a.feature, "frustum_size": a.frustum_size, "project_scale": 2,
                                "project_res": ["1", "2", "4", "8"], "context_prior": True,
                                "relation_loss": True, "fp_loss": True, "init": "random"},
           "replaced": ["monoscene.models.unet2d.UNet2D.build: EfficientNet-B7 from torch.hub (weights "
                        "download) -> 5-level CNN, same output dict of `feature` channels",
                        "torch.Tensor.cuda -> identity (CPU only)",
                        "LightningModule.log -> recorded (no Trainer)"] + stubs,
           "params": {"monoscene": sum(p.numel() for p in model.parameters()),
                      "baseline": sum(p.numel() for p in base.net.parameters())},
           "data_load_s": round(load_s, 1), "train_wall_s": {k: round(v, 1) for k, v in wall.items()},
           "loss": {k: {"first_25": round(float(np.mean(v[:25])), 4), "last_25": round(float(np.mean(v[-25:])), 4)}
                    for k, v in curves.items()},
           "test": {}}
    for k in ours:
        r = ours[k].result()
        st = theirs[k].get_stats()
        res["test"][k] = {
            "occufly_metrics": {"completion_iou": round(r["completion"]["iou"], 4),
                                "miou": None if r["miou"] is None else round(r["miou"], 4),
                                "classes_evaluated": r["classes_evaluated"]},
            "monoscene_sscmetrics": {"completion_iou": round(float(st["iou"]), 4),
                                     "miou": round(float(st["iou_ssc_mean"]), 4),
                                     "precision": round(float(st["precision"]), 4),
                                     "recall": round(float(st["recall"]), 4)},
            "per_class_iou": {"occufly": {n: (None if v is None else round(v, 4))
                                          for n, v in r["per_class_iou"].items()},
                              "monoscene": {n: round(float(v), 4) for n, v in
                                            zip(geom.class_names[1:], st["iou_ssc"][1:], strict=False)}},
        }
    res["curves_smoothed_25"] = {k: [round(x, 4) for x in smooth(v)[::5]] for k, v in curves.items()}
    if a.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7, 4))
        for k, lab in (("monoscene", "MonoScene total loss (own losses)"),
                       ("monoscene_ssc_ce", "MonoScene SSC CE term"), ("baseline", "baseline weighted CE")):
            ax.plot(curves[k], alpha=0.2)
            ax.plot(smooth(curves[k]), label=lab, color=ax.lines[-1].get_color())
        ax.set_xlabel("step (batch 1)")
        ax.set_ylabel("loss")
        ax.set_title(f"CPU training on the export ({geom.grid_shape[0]}x{geom.grid_shape[1]}x"
                     f"{geom.grid_shape[2]} at {geom.voxel_size} m, {len(cache['train'])} train frames)")
        ax.legend()
        fig.tight_layout()
        a.plot.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(a.plot, dpi=90)
        res["plot"] = os.path.relpath(a.plot, REPO) if a.plot.is_relative_to(REPO) else str(a.plot)
    print(json.dumps(res, indent=1), file=json_out)


if __name__ == "__main__":
    main()
