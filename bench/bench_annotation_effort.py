"""Annotation effort: how much painting the 3D prefill saves (issue 17).

A simulated annotator works through the selected frames of a synthetic scene in the order the
app hands them out (``POST /scenes/{sid}/next``: selected frames by index), with the synthetic
truth mask as what the person wants. For each frame it counts

(a) ``empty``: the labelled pixels to paint when starting from an empty mask (every pixel of
    the truth that carries a class);
(b) ``prefill``: the labelled pixels whose class differs from the prefill, i.e. the lifted
    labels of every frame submitted so far (kNN fill + denoise, as the app's live lifting)
    rendered into this frame -- what "Prefill from 3D" shows;
(c) ``clicks``: the clicks a scripted "fill this region" policy needs to reach >= 98 % pixel
    agreement with the truth, from empty and from the prefill: each click fills one connected
    truth region (one class) with its class, regions with the most wrong pixels first. This is
    the ideal region tool (its superpixels are the truth's regions), so the counts are a lower
    bound for any real smart tool (GrabCut, scissors, superpixels need more).

The baseline (a) is measured in the same run on the same frames. Prints ONE JSON object with
per-frame curves and totals, and writes a PNG plot (``--plot``). Targets: from the 6th frame
on the prefill leaves <= 10 % of the pixels to change (median), and the total painted area
falls >= 3x versus painting from scratch.

    .venv/bin/python bench/bench_annotation_effort.py --preset small
    flock /tmp/occufly-heavy.lock nice .venv/bin/python bench/bench_annotation_effort.py --preset small --preset bench
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from occufly.io.masks import read_mask  # noqa: E402
from occufly.lifting import LiftState  # noqa: E402
from occufly.render import render_for_mask  # noqa: E402
from occufly.scene import Scene  # noqa: E402
from occufly.selection import select_frames  # noqa: E402

TARGET_AGREEMENT = 0.98


def ensure_scene(cache: Path, preset: str, seed: int) -> tuple[Path, Path]:
    syn = cache / f"synth_{preset}_{seed}"
    ws = cache / f"ws_{preset}_{seed}"
    py = sys.executable
    if not (syn / "truth" / "point_labels.npy").is_file():
        subprocess.run([py, "-m", "occufly.cli", "synth", str(syn), "--preset", preset,
                        "--seed", str(seed), "--force"], check=True, cwd=ROOT,
                       stdout=subprocess.DEVNULL)
    if not (ws / "scene.json").is_file():
        subprocess.run([py, "-m", "occufly.cli", "import", str(syn), "--workspace", str(ws),
                        "--force"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return syn, ws


def truth_regions(truth: np.ndarray, labelled: np.ndarray) -> tuple[np.ndarray, int]:
    """Connected (4-neighbour) regions of one truth class each: (region id per pixel, count);
    0 = not labelled. These are the ideal "superpixels" of the region-fill policy."""
    from scipy import ndimage

    reg = np.zeros(truth.shape, np.int32)
    k = 0
    for c in np.unique(truth[labelled]):
        lab, n = ndimage.label(labelled & (truth == c))
        reg[lab > 0] = lab[lab > 0] + k
        k += n
    return reg, k


def region_clicks(start: np.ndarray, truth: np.ndarray, labelled: np.ndarray,
                  regions: tuple[np.ndarray, int], target: float = TARGET_AGREEMENT) -> int:
    """Clicks of the ideal region-fill policy from ``start`` to >= ``target`` agreement on the
    labelled pixels: a click fills one truth region with its class (fixing every wrong pixel
    in it); regions with the most wrong pixels first."""
    n = int(labelled.sum())
    if n == 0:
        return 0
    wrong = labelled & (start != truth)
    need = int(wrong.sum()) - int(np.floor((1.0 - target) * n))
    if need <= 0:
        return 0
    reg, k = regions
    per = np.bincount(reg[wrong], minlength=k + 1)[1:]
    s = np.sort(per[per > 0])[::-1]
    return int(np.searchsorted(np.cumsum(s), need) + 1)


def run_preset(preset: str, args: argparse.Namespace) -> dict:
    t0 = time.perf_counter()
    syn, ws = ensure_scene(args.cache, preset, args.seed)
    scene = Scene.load(ws)
    tax = scene.taxonomy
    valid = tax.valid_lut() if hasattr(tax, "valid_lut") else None
    # the demo's / app's selection (greedy, best cell of 23-28 m, 99 %), handed out by index
    sel = select_frames(scene, mode="greedy", cell="auto", target_coverage=0.99)
    order = sorted(int(i) for i in sel.frames)
    shutil.rmtree(ws / "lifting", ignore_errors=True)
    st = LiftState.open(ws, scene)
    apply = getattr(st, "apply_frame", None) or st.set_mask
    labels = None
    frames = []
    for k, fi in enumerate(order):
        fr = scene.frames[fi]
        truth = read_mask(syn / "truth" / "masks" / f"{fr.stem}.png", fr, tax)
        labelled = valid[truth] if valid is not None else (truth > 0) & (truth < 255)
        n = int(labelled.sum())
        if labels is None:
            prefill = np.zeros_like(truth)
        else:
            prefill, _ = render_for_mask(scene, np.asarray(labels), fi, truth.shape)
            prefill = np.asarray(prefill, dtype=truth.dtype)
        change = int((labelled & (prefill != truth)).sum())
        covered = int((labelled & (prefill > 0)).sum())
        regions = truth_regions(truth, labelled)
        frames.append({
            "n": k + 1, "frame": fr.stem, "labelled_px": n,
            "empty_px": n, "prefill_px": change,
            "prefill_share": change / n if n else None,
            "prefill_covered": covered / n if n else None,
            "clicks_empty": region_clicks(np.zeros_like(truth), truth, labelled, regions),
            "clicks_prefill": region_clicks(prefill, truth, labelled, regions),
        })
        # the annotator submits the corrected mask (= the truth); live lifting updates
        apply(fi, truth, version=f"sim{k}")
        labels = st.fill_and_denoise().labels
    st.close() if hasattr(st, "close") else None
    from6 = [f["prefill_share"] for f in frames[5:] if f["prefill_share"] is not None]
    tot_empty = sum(f["empty_px"] for f in frames)
    tot_prefill = sum(f["prefill_px"] for f in frames)
    ce = sum(f["clicks_empty"] for f in frames)
    cp = sum(f["clicks_prefill"] for f in frames)
    med = float(np.median(from6)) if from6 else None
    return {
        "preset": preset, "seed": args.seed, "points": scene.n_points,
        "frames_in_scene": len(scene.frames), "selected": len(order), "cell": sel.cell,
        "frames": frames,
        "totals": {
            "painted_px_from_empty": tot_empty, "painted_px_from_prefill": tot_prefill,
            "reduction_x": tot_empty / tot_prefill if tot_prefill else None,
            "median_prefill_share_from_6th": med,
            "clicks_from_empty": ce, "clicks_from_prefill": cp,
            "clicks_reduction_x": ce / cp if cp else None,
        },
        "targets": {
            "median_from_6th_le_10pct": med is not None and med <= 0.10,
            "painted_area_reduction_ge_3x": tot_prefill > 0 and tot_empty / tot_prefill >= 3.0,
        },
        "seconds": round(time.perf_counter() - t0, 1),
    }


def plot(results: list[dict], path: Path) -> None:
    """Per-frame share of pixels to change (from empty = 100 %, from the prefill) per preset."""
    from PIL import Image, ImageDraw

    W, H, ml, mr, mt, mb = 760, 360, 60, 150, 20, 44
    im = Image.new("RGB", (W, H), "white")
    d = ImageDraw.Draw(im)
    n_max = max(len(r["frames"]) for r in results)
    X = lambda n: ml + (n - 1) / max(n_max - 1, 1) * (W - ml - mr)  # noqa: E731
    Y = lambda v: mt + (1.0 - v) * (H - mt - mb)  # noqa: E731
    for v in (0, 0.1, 0.25, 0.5, 0.75, 1.0):
        d.line([(ml, Y(v)), (W - mr, Y(v))], fill=(225, 225, 225) if v != 0.1 else (250, 170, 170))
        d.text((8, Y(v) - 6), f"{int(v * 100):3d} %", fill="black")
    for n in range(1, n_max + 1, max(1, n_max // 10)):
        d.text((X(n) - 4, H - mb + 6), str(n), fill="black")
    d.text((ml + 120, H - 18), "frame in the order the app hands them out", fill="black")
    d.line([(X(1), Y(1.0)), (X(n_max), Y(1.0))], fill=(120, 120, 120), width=2)
    colours = [(10, 102, 194), (217, 48, 37), (46, 125, 50)]
    y_leg = mt + 10
    d.text((W - mr + 10, y_leg), "from empty", fill=(120, 120, 120))
    for r, c in zip(results, colours, strict=False):
        pts = [(X(f["n"]), Y(f["prefill_share"] or 0.0)) for f in r["frames"]]
        d.line(pts, fill=c, width=2)
        for p in pts:
            d.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=c)
        y_leg += 18
        t = r["totals"]
        d.text((W - mr + 10, y_leg), f"{r['preset']}: {t['reduction_x']:.1f}x less", fill=c)
    d.text((ml, 4), "share of labelled pixels to change: from the 3D prefill vs from empty",
           fill="black")
    path.parent.mkdir(parents=True, exist_ok=True)
    im.save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", action="append", help="tiny|small|bench (repeatable; default small and bench)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-bench-effort"))
    ap.add_argument("--plot", type=Path, default=ROOT / "docs" / "annotation_effort.png")
    ap.add_argument("--per-frame", action="store_true", help="keep every per-frame row in the JSON")
    args = ap.parse_args()
    args.cache.mkdir(parents=True, exist_ok=True)
    results = [run_preset(p, args) for p in (args.preset or ["small", "bench"])]
    if args.plot:
        plot(results, args.plot)
    out = {"bench": "annotation-effort", "target_agreement": TARGET_AGREEMENT,
           "plot": str(args.plot) if args.plot else None, "presets": {}}
    for r in results:
        curve = {k: [f[k] for f in r["frames"]] for k in
                 ("prefill_share", "clicks_empty", "clicks_prefill")}
        curve["prefill_share"] = [round(v, 4) if v is not None else None for v in curve["prefill_share"]]
        entry = {k: v for k, v in r.items() if k != "frames"}
        entry["curves"] = curve
        if args.per_frame:
            entry["frames"] = r["frames"]
        out["presets"][r["preset"]] = entry
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
