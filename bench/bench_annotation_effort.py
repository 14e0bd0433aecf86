"""Annotation effort: how much painting the 3D prefill saves (issue 17).

A simulated annotator works through the selected frames of a synthetic scene in the order the
app hands them out (``POST /scenes/{sid}/next`` follows ``app.scenes.service.handout_order``:
each next frame the one seeing the most points no earlier frame sees), with the synthetic
truth mask as what the person wants. For each frame it counts

(a) ``empty``: the labelled pixels to paint when starting from an empty mask (every pixel of
    the truth that carries a class);
(b) ``prefill``: the labelled pixels whose class differs from the prefill, i.e. the lifted
    labels of every frame submitted so far (kNN fill + denoise, as the app's live lifting)
    rendered into this frame as "Prefill from 3D" shows them (``render_prefill``: holes
    between splats closed); split into ``uncovered`` (the prefill has no label) and ``wrong``
    (another class). ``holes_open`` repeats (b) with the plain rendering (the prefill before
    issue 17's hole closing), from the same labels;
(c) ``clicks``: the clicks a scripted "fill this region" policy needs to reach >= 98 % pixel
    agreement with the truth, from empty and from the prefill: each click fills one connected
    truth region (one class) with its class, regions with the most wrong pixels first. This is
    the ideal region tool (its superpixels are the truth's regions), so the counts are a lower
    bound for any real smart tool (GrabCut, scissors, superpixels need more).

``--compare-index-order`` also runs the frames by index (the app's order before issue 17),
``--compare-grow-order`` an order that grows from the painted area; the lifted labels after
each step are cached in ``--cache``/labels (keyed by the frames so far and the lifting code).
The baseline (a) is measured in the same run on the same frames. Prints ONE JSON object with
per-frame curves and totals, and writes a PNG plot (``--plot``). Targets: from the 6th frame
on the prefill leaves <= 10 % of the pixels to change (median), and the total painted area
falls >= 3x versus painting from scratch.

    .venv/bin/python bench/bench_annotation_effort.py --preset small --compare-index-order
    nice .venv/bin/python bench/bench_annotation_effort.py --preset small --preset bench
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _scene import ensure_seeded_scene  # noqa: E402

from app.scenes.service import handout_order  # noqa: E402
from occufly.io.masks import read_mask  # noqa: E402
from occufly.lifting import VoteStore  # noqa: E402
from occufly.render import prefill_for_mask, render_for_mask  # noqa: E402
from occufly.scene import Scene  # noqa: E402
from occufly.selection import select_frames  # noqa: E402

TARGET_AGREEMENT = 0.98


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


def dump_frame(out: Path, n: int, stem: str, truth: np.ndarray, prefill: np.ndarray,
               labelled: np.ndarray, tax) -> None:
    """truth | prefill | diff (black: right; white: no prefill; red: wrong class) side by side."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    lut = np.zeros((256, 3), np.uint8)
    for c in tax.classes:
        lut[c.id] = c.rgb
    diff = np.zeros(truth.shape + (3,), np.uint8)
    diff[labelled & (prefill == 0)] = (255, 255, 255)
    diff[labelled & (prefill > 0) & (prefill != truth)] = (255, 0, 0)
    img = np.concatenate([lut[truth], lut[prefill], diff], axis=1)
    Image.fromarray(img).save(out / f"{n:03d}_{stem}.png")


def _lifting_key(preset: str, seed: int, prefix: list[int]) -> str:
    """Cache key of the lifted labels after submitting ``prefix``: the scene, the frames in
    order and the lifting code (a change in occufly/lifting invalidates the cache)."""
    h = hashlib.sha256(f"{preset}/{seed}/{prefix}".encode())
    for f in sorted((ROOT / "occufly" / "lifting").glob("*.py")):
        h.update(f.read_bytes())
    return h.hexdigest()[:24]


def lifted_sequence(ws: Path, scene: Scene, syn: Path, order: list[int], preset: str,
                    args: argparse.Namespace):
    """Yield (k, frame index, truth mask, lifted labels before this frame or None) while a
    simulated annotator submits the truth mask of each frame of ``order`` (live lifting: the
    votes, then kNN fill + denoise as the app's lifting service). The labels after each step
    are cached under ``args.cache / "labels"`` so that reruns skip the lifting."""
    tax = scene.taxonomy
    cdir = args.cache / "labels"
    cdir.mkdir(parents=True, exist_ok=True)
    st = None
    labels = None
    for k, fi in enumerate(order):
        fr = scene.frames[fi]
        truth = read_mask(syn / "truth" / "masks" / f"{fr.stem}.png", fr, tax)
        yield k, fi, truth, labels
        path = cdir / f"{_lifting_key(preset, args.seed, order[:k + 1])}.npy"
        if path.is_file() and not args.no_label_cache:
            labels = np.load(path)
            continue
        if st is None:  # replay the submits so far into a fresh vote state
            shutil.rmtree(ws / "lifting", ignore_errors=True)
            st = VoteStore.open(ws, scene)
            for j, fj in enumerate(order[:k]):
                frj = scene.frames[fj]
                st.set_mask(fj, read_mask(syn / "truth" / "masks" / f"{frj.stem}.png", frj, tax),
                            version=f"sim{j}")
        # the annotator submits the corrected mask (= the truth); live lifting updates
        st.set_mask(fi, truth, version=f"sim{k}")
        labels = np.asarray(st.fill_and_denoise().labels)
        np.save(path, labels)
    if st is not None and hasattr(st, "close"):
        st.close()


def run_order(name: str, order: list[int], ws: Path, scene: Scene, syn: Path, preset: str,
              args: argparse.Namespace) -> dict:
    """Per-frame effort for one hand-out order: the prefill as the app renders it (holes
    closed, render_prefill) and, from the same labels, the plain rendering (holes open)."""
    tax = scene.taxonomy
    valid = tax.valid_lut()
    frames = []
    for k, fi, truth, labels in lifted_sequence(ws, scene, syn, order, preset, args):
        fr = scene.frames[fi]
        labelled = valid[truth]
        n = int(labelled.sum())
        if labels is None:
            prefill = plain = np.zeros_like(truth)
            filled = np.zeros(truth.shape, bool)
        else:
            prefill, _, filled = prefill_for_mask(scene, labels, fi, truth.shape)
            plain, _ = render_for_mask(scene, labels, fi, truth.shape)
            prefill = np.asarray(prefill, dtype=truth.dtype)
            plain = np.asarray(plain, dtype=truth.dtype)
        change = int((labelled & (prefill != truth)).sum())
        change_open = int((labelled & (plain != truth)).sum())
        uncovered = int((labelled & (prefill == 0)).sum())
        if args.dump:
            dump_frame(args.dump / preset / name, k + 1, fr.stem, truth, prefill, labelled, tax)
        regions = truth_regions(truth, labelled)
        frames.append({
            "n": k + 1, "frame": fr.stem, "index": fi, "labelled_px": n,
            "empty_px": n, "prefill_px": change, "prefill_px_holes_open": change_open,
            "prefill_share": change / n if n else None,
            "prefill_share_holes_open": change_open / n if n else None,
            # of the pixels to change: where the prefill has no label vs a wrong one
            "uncovered_share": uncovered / n if n else None,
            "wrong_share": (change - uncovered) / n if n else None,
            "holes_filled_share": float(filled.mean()),
            "clicks_empty": region_clicks(np.zeros_like(truth), truth, labelled, regions),
            "clicks_prefill": region_clicks(prefill, truth, labelled, regions),
        })
        # partial results after every frame, in case a long run (bench) is stopped early
        (args.cache / f"partial_{preset}_{args.seed}_{name}.json").write_text(
            json.dumps(summarize(name, order, frames)))
    return summarize(name, order, frames)


def summarize(name: str, order: list[int], frames: list[dict]) -> dict:
    def med6(key):
        v = [f[key] for f in frames[5:] if f[key] is not None]
        return float(np.median(v)) if v else None

    tot_empty = sum(f["empty_px"] for f in frames)
    tot_prefill = sum(f["prefill_px"] for f in frames)
    tot_open = sum(f["prefill_px_holes_open"] for f in frames)
    ce = sum(f["clicks_empty"] for f in frames)
    cp = sum(f["clicks_prefill"] for f in frames)
    med = med6("prefill_share")
    return {
        "order": name, "frames_in_order": order, "frames": frames,
        "totals": {
            "painted_px_from_empty": tot_empty, "painted_px_from_prefill": tot_prefill,
            "reduction_x": tot_empty / tot_prefill if tot_prefill else None,
            "median_prefill_share_from_6th": med,
            "median_uncovered_share_from_6th": med6("uncovered_share"),
            "median_wrong_share_from_6th": med6("wrong_share"),
            "holes_open": {"painted_px_from_prefill": tot_open,
                           "reduction_x": tot_empty / tot_open if tot_open else None,
                           "median_prefill_share_from_6th": med6("prefill_share_holes_open")},
            "clicks_from_empty": ce, "clicks_from_prefill": cp,
            "clicks_reduction_x": ce / cp if cp else None,
        },
        "targets": {
            "median_from_6th_le_10pct": med is not None and med <= 0.10,
            "painted_area_reduction_ge_3x": tot_prefill > 0 and tot_empty / tot_prefill >= 3.0,
        },
    }


def grow_order(scene: Scene, frames: list[int]) -> list[int]:
    """An order that grows from the painted area: first the frame sharing the most points with
    the other frames, then each time the one whose points the frames before see the largest
    share of (ties: more points, lower index). For comparison with the app's order."""
    vis = scene.visibility
    ids = {f: np.unique(vis.frame_ids(f)) for f in frames}
    cnt = np.zeros(scene.n_points, np.int32)
    for f in frames:
        cnt[ids[f]] += 1
    left = list(frames)
    first = max(left, key=lambda f: (int(cnt[ids[f]].sum()) - len(ids[f]), -f))
    seq = [first]
    left.remove(first)
    seen = np.zeros(scene.n_points, bool)
    seen[ids[first]] = True
    while left:
        f = max(left, key=lambda g: (float(seen[ids[g]].mean()), len(ids[g]), -g))
        seq.append(f)
        left.remove(f)
        seen[ids[f]] = True
    return seq


def run_preset(preset: str, args: argparse.Namespace) -> dict:
    t0, c0 = time.perf_counter(), time.process_time()
    syn, ws = ensure_seeded_scene(args.cache, preset, args.seed)
    scene = Scene.load(ws)
    # the demo's / app's selection (greedy, best cell of 23-28 m, 99 %), handed out in the
    # app's order (app.scenes.service.handout_order, what POST /scenes/{sid}/next follows)
    cached = args.cache / f"selection_{preset}_{args.seed}.json"
    if cached.is_file():  # the selection of a bench scene peaks at ~6 GB: once, under the lock
        sel = json.loads(cached.read_text())
    else:
        r = select_frames(scene, mode="greedy", cell="auto", target_coverage=0.99)
        sel = {"frames": sorted(int(i) for i in r.frames), "cell": r.cell}
        cached.write_text(json.dumps(sel, default=lambda o: o.item() if hasattr(o, "item") else str(o)))
    if args.select_only:
        return {"preset": preset, "selected": len(sel["frames"]), "cell": sel["cell"]}
    chosen = sel["frames"]
    orders = {"app": handout_order(scene, chosen)}
    if args.compare_index_order:  # the app's order before issue 17: by frame index
        orders["index"] = chosen
    if args.compare_grow_order:  # each next frame the one most covered by the frames before
        orders["grow"] = grow_order(scene, chosen)
    runs = {}
    for name, o in orders.items():
        runs[name] = run_order(name, o, ws, scene, syn, preset, args)
    out = {"preset": preset, "seed": args.seed, "points": scene.n_points,
           "frames_in_scene": len(scene.frames), "selected": len(chosen), "cell": sel["cell"],
           **runs["app"]}
    out["other_orders"] = {k: v for k, v in runs.items() if k != "app"}
    out["seconds"] = round(time.perf_counter() - t0, 1)
    out["cpu_seconds"] = round(time.process_time() - c0, 1)
    return out


def plot(results: list[dict], path: Path) -> None:
    """Per-frame share of pixels to change (from empty = 100 %, from the prefill) per preset."""
    from PIL import Image, ImageDraw

    W, H, ml, mr, mt, mb = 820, 400, 60, 190, 34, 44
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
    d.text((ml + 120, H - 18), "n-th frame handed out (each curve in its own order)", fill="black")
    d.line([(X(1), Y(1.0)), (X(n_max), Y(1.0))], fill=(120, 120, 120), width=2)
    colours = [(10, 102, 194), (217, 48, 37), (46, 125, 50)]
    y_leg = mt + 10
    d.text((W - mr + 10, y_leg), "from empty", fill=(120, 120, 120))
    for r, c in zip(results, colours, strict=False):
        for name, run in r["other_orders"].items():  # the previous order, thin and light
            light = tuple(int(v + (255 - v) * 0.55) for v in c)
            pts = [(X(f["n"]), Y(f["prefill_share"] or 0.0)) for f in run["frames"]]
            d.line(pts, fill=light, width=1)
            y_leg += 18
            t = run["totals"]
            d.text((W - mr + 10, y_leg), f"{r['preset']}, {name} order:", fill=light)
            y_leg += 13
            d.text((W - mr + 18, y_leg), f"{t['reduction_x']:.1f}x, med {100 * t['median_prefill_share_from_6th']:.1f} %",
                   fill=light)
        pts = [(X(f["n"]), Y(f["prefill_share"] or 0.0)) for f in r["frames"]]
        d.line(pts, fill=c, width=2)
        for p in pts:
            d.ellipse([p[0] - 2, p[1] - 2, p[0] + 2, p[1] + 2], fill=c)
        y_leg += 18
        t = r["totals"]
        d.text((W - mr + 10, y_leg), f"{r['preset']}, app order:", fill=c)
        y_leg += 13
        d.text((W - mr + 18, y_leg), f"{t['reduction_x']:.1f}x, med {100 * t['median_prefill_share_from_6th']:.1f} %",
               fill=c)
    d.text((ml, 4), "share of labelled pixels to change: from the 3D prefill (holes closed) vs from empty",
           fill="black")
    path.parent.mkdir(parents=True, exist_ok=True)
    im.save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", action="append", help="tiny|small|bench (repeatable; default small and bench)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/occufly-bench-effort"))
    ap.add_argument("--plot", type=Path, default=ROOT / "docs" / "annotation_effort.png")
    ap.add_argument("--compare-index-order", action="store_true",
                    help="also run the frames in index order (the app's order before issue 17)")
    ap.add_argument("--compare-grow-order", action="store_true",
                    help="also run an order that grows from the painted area (grow_order)")
    ap.add_argument("--select-only", action="store_true",
                    help="only compute and cache the selection (run it under the heavy lock)")
    ap.add_argument("--no-label-cache", action="store_true", help="lift again even if cached")
    ap.add_argument("--dump", type=Path, help="write truth | prefill | diff PNGs per frame here")
    ap.add_argument("--per-frame", action="store_true", help="keep every per-frame row in the JSON")
    ap.add_argument("--replot", type=Path, nargs="+",
                    help="only draw --plot from earlier outputs of this bench (run with --per-frame)")
    args = ap.parse_args()
    if args.replot:
        results = []
        for f in args.replot:
            for r in json.loads(f.read_text())["presets"].values():
                r["other_orders"] = {k: v for k, v in r.get("other_orders", {}).items() if "frames" in v}
                results.append(r)
        plot(results, args.plot)
        print(json.dumps({"plot": str(args.plot), "presets": [r["preset"] for r in results]}))
        return
    args.cache.mkdir(parents=True, exist_ok=True)
    results = [run_preset(p, args) for p in (args.preset or ["small", "bench"])]
    if args.select_only:
        print(json.dumps(results))
        return
    if args.plot:
        plot(results, args.plot)
    out = {"bench": "annotation-effort", "target_agreement": TARGET_AGREEMENT,
           "plot": str(args.plot) if args.plot else None, "presets": {}}
    def entry_of(r: dict) -> dict:
        curve = {k: [f[k] for f in r["frames"]] for k in
                 ("prefill_share", "prefill_share_holes_open", "clicks_empty", "clicks_prefill")}
        for k in ("prefill_share", "prefill_share_holes_open"):
            curve[k] = [round(v, 4) if v is not None else None for v in curve[k]]
        e = {k: v for k, v in r.items() if k not in ("frames", "other_orders")}
        e["curves"] = curve
        if args.per_frame:
            e["frames"] = r["frames"]
        return e

    for r in results:
        entry = entry_of(r)
        entry["other_orders"] = {k: entry_of(v) for k, v in r["other_orders"].items()}
        out["presets"][r["preset"]] = entry
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
