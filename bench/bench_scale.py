"""Benchmark: kNN fill + denoise and densify + voxelize at survey scale (issue 16), with their
cost growth, on clouds built from a real one.

A source cloud (a workspace's ``points/xyz.npy`` or any (N, 3) float32 ``.npy``) and its
per-point truth labels (e.g. the synthetic scene's ``truth/point_labels.npy``) are cut to
each requested size: a size below the source's is a square crop around the centre (same
density, smaller area), a larger one tiles the cloud side by side (copies shifted by its
extent + 1 m). Votes are fabricated for ``--voted`` (default 30 %) of the points -- the
points inside discs of 60 m (an annotated frame's footprint at 50 m) placed over the cloud
-- with 3 % of them flipped to a random present class (annotation noise), a vote margin and
a top count like two agreeing views (1.0 / 2) or one (1.0 / 1), and ties (margin 0) on 1 %.

Each (size, stage) runs in its own fresh Python process, so its peak RSS (``ru_maxrss``) is
that stage's alone (inputs loaded from ``.npy`` files the preparation wrote):

    fill      occufly.lifting.fill_and_denoise on (xyz, direct, margin, top)
    voxelize  occufly.densify.densify on (xyz, the fill's labels), default options, no
              free-space views (the free-space check scales with voxels x frames: it is
              measured by ``bench_survey.py`` on the real survey)

Per stage: wall, CPU (user + sys) and peak RSS; the log-log slope of wall and CPU time
against the number of points over the sizes; and, with ``--check-identical``, whether the
fill's labels / confidence / origin equal those of a single-threaded run on the smallest
size (threads must not change a byte).

    .venv/bin/python bench/bench_scale.py --xyz WS/points/xyz.npy \
        --labels SRC/truth/point_labels.npy --sizes 4e6,15e6,31e6 --root /tmp/h5/scale

Prints one JSON object (also written to ROOT/results.json after every stage).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

STAGE_CODE = r'''
import json, resource, sys, time
import numpy as np
stage, d = sys.argv[1], sys.argv[2]
extra = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {}
from occufly.taxonomy import default_taxonomy
tax = default_taxonomy()
xyz = np.load(d + "/xyz.npy", mmap_mode="r")
t0, c0 = time.perf_counter(), time.process_time()
out = {}
if stage == "fill":
    from occufly.lifting.knn import LiftParams, fill_and_denoise
    direct = np.load(d + "/direct.npy"); margin = np.load(d + "/margin.npy"); top = np.load(d + "/top.npy")
    tag = extra.pop("tag", "")
    res = fill_and_denoise(xyz, direct, tax, vote_margin=margin, vote_top=top,
                           params=LiftParams(**extra))
    np.save(d + f"/labels{tag}.npy", res.labels)
    np.save(d + f"/confidence{tag}.npy", res.confidence)
    np.save(d + f"/origin{tag}.npy", res.origin)
    out["stats"] = {k: v for k, v in res.stats.items() if isinstance(v, (int, float, str))}
elif stage == "voxelize":
    from occufly.densify.pipeline import DensifyOptions, densify
    labels = np.load(d + "/labels.npy")
    res = densify(xyz, labels, tax, options=DensifyOptions())
    out["timings_s"] = res.report["timings_s"]
    out["grid_shape"] = res.report["grid_shape"]
    out["occupied_voxels"] = res.report["occupied_voxels"]
    res.grid.save(d + "/grid.npz")
ru = resource.getrusage(resource.RUSAGE_SELF)
out.update(wall_s=round(time.perf_counter() - t0, 2), cpu_s=round(time.process_time() - c0, 2),
           peak_rss_gb=round(ru.ru_maxrss / 1024**2, 3))
print(json.dumps(out))
'''


def prepare(src_xyz: np.ndarray, src_labels: np.ndarray, n: int, out: Path, voted: float,
            seed: int = 0) -> dict:
    """Write xyz / direct / margin / top for a cloud of about ``n`` points into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    if (out / "meta.json").is_file():
        return json.loads((out / "meta.json").read_text())
    rng = np.random.default_rng(seed)
    N = len(src_xyz)
    lo, hi = src_xyz.min(axis=0), src_xyz.max(axis=0)
    if n <= N:
        # square crop around the centre holding n points (same density)
        c = (lo + hi) / 2
        r = np.abs(src_xyz[:, :2] - c[:2]).max(axis=1)
        keep = np.argsort(r, kind="stable")[:n]
        keep.sort()
        xyz, lab = np.ascontiguousarray(src_xyz[keep]), src_labels[keep]
        tiles = 1
    else:
        t = int(np.ceil(np.sqrt(n / N)))
        step = (hi - lo)[:2] + 1.0
        parts, labs = [], []
        for i in range(t):
            for j in range(t):
                if sum(len(p) for p in parts) >= n:
                    break
                p = src_xyz.copy()
                p[:, 0] += np.float32(i * step[0])
                p[:, 1] += np.float32(j * step[1])
                parts.append(p)
                labs.append(src_labels)
        xyz = np.concatenate(parts)[:n]
        lab = np.concatenate(labs)[:n]
        tiles = len(parts)
        del parts
    m = len(xyz)
    # voted points: inside 60 m discs until `voted` of the points are covered
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    voted_mask = np.zeros(m, bool)
    cell = 20.0  # coverage test on a coarse raster, discs placed at random
    ij = np.floor((xyz[:, :2] - lo[:2]) / cell).astype(np.int64)
    nx, ny = ij.max(axis=0) + 1
    cid = ij[:, 0] * ny + ij[:, 1]
    cnt = np.bincount(cid, minlength=nx * ny)
    covered = np.zeros(nx * ny, bool)
    cx, cy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    while cnt[covered].sum() < voted * m:
        ctr = rng.uniform(lo[:2], hi[:2])
        d2 = ((cx + 0.5) * cell + lo[0] - ctr[0]) ** 2 + ((cy + 0.5) * cell + lo[1] - ctr[1]) ** 2
        covered |= (d2 <= 30.0 ** 2).reshape(-1)
    voted_mask = covered[cid]
    direct = np.where(voted_mask, lab, 0).astype(np.uint8)
    direct[lab == 255] = 0
    present = np.unique(direct[direct > 0])
    flip = voted_mask & (rng.random(m) < 0.03)
    direct[flip] = rng.choice(present, int(flip.sum()))
    two = rng.random(m) < 0.6
    top = np.where(direct > 0, np.where(two, 2, 1), 0).astype(np.uint16)
    margin = np.where(direct > 0, 1.0, 0.0).astype(np.float32)
    tie = (direct > 0) & (rng.random(m) < 0.01)
    margin[tie] = 0.0
    top[tie] = 1
    np.save(out / "xyz.npy", xyz)
    np.save(out / "direct.npy", direct)
    np.save(out / "margin.npy", margin)
    np.save(out / "top.npy", top)
    meta = {"points": int(m), "tiles": tiles, "voted_points": int((direct > 0).sum()),
            "extent_m": (hi - lo).round(1).tolist()}
    (out / "meta.json").write_text(json.dumps(meta))
    return meta


def run_stage(stage: str, d: Path, extra: dict | None = None) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    t0 = time.perf_counter()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-c", STAGE_CODE, stage, str(d), json.dumps(extra or {})],
                       capture_output=True, text=True, env=env, cwd=str(REPO))
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        return {"exit": p.returncode, "error": p.stderr.strip().splitlines()[-3:]}
    out = json.loads(p.stdout.strip().splitlines()[-1])
    out["process_wall_s"] = round(time.perf_counter() - t0, 2)
    out["process_cpu_s"] = round((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), 2)
    out["exit"] = 0
    return out


def slope(ns: list[float], ts: list[float]) -> float | None:
    ok = [(n, t) for n, t in zip(ns, ts, strict=True) if n and t and t > 0]
    if len(ok) < 2:
        return None
    x = np.log([n for n, _ in ok])
    y = np.log([t for _, t in ok])
    return round(float(np.polyfit(x, y, 1)[0]), 3)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--xyz", type=Path, required=True)
    ap.add_argument("--labels", type=Path, required=True)
    ap.add_argument("--sizes", default="4e6,15e6,31e6")
    ap.add_argument("--voted", type=float, default=0.3)
    ap.add_argument("--stages", default="fill,voxelize")
    ap.add_argument("--root", type=Path, default=Path("/tmp/occufly-bench-scale"))
    ap.add_argument("--check-identical", action="store_true",
                    help="also run the fill single-threaded (workers=1) on the smallest size "
                    "and compare the outputs byte for byte")
    args = ap.parse_args(argv)
    src_xyz = np.load(args.xyz, mmap_mode="r")
    src_lab = np.load(args.labels, mmap_mode="r")
    if src_lab.shape != (len(src_xyz),):
        raise SystemExit(f"{args.labels}: shape {src_lab.shape} does not match {args.xyz} ({len(src_xyz)} points)")
    src_xyz = np.asarray(src_xyz, np.float32)
    src_lab = np.asarray(src_lab, np.uint8)
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    res: dict = {"source": str(args.xyz), "source_points": int(len(src_xyz)), "sizes": {}}
    args.root.mkdir(parents=True, exist_ok=True)

    def save() -> None:
        (args.root / "results.json").write_text(json.dumps(res, indent=1))

    dirs = {}
    for n in sizes:
        d = args.root / f"n{n}"
        dirs[n] = d
        res["sizes"][str(n)] = {"input": prepare(src_xyz, src_lab, n, d, args.voted)}
        save()
    del src_xyz, src_lab
    for n in sizes:
        for st in args.stages.split(","):
            r = run_stage(st, dirs[n])
            res["sizes"][str(n)][st] = r
            save()
            print(f"{n} {st}: {r.get('wall_s')} s wall, {r.get('cpu_s')} s CPU, "
                  f"{r.get('peak_rss_gb')} GB", file=sys.stderr, flush=True)
    if args.check_identical and "fill" in args.stages:
        n = sizes[0]
        r = run_stage("fill", dirs[n], {"workers": 1, "tag": "_whole"})
        same = {k: (dirs[n] / f"{k}.npy").read_bytes() == (dirs[n] / f"{k}_whole.npy").read_bytes()
                for k in ("labels", "confidence", "origin")}
        res["identical_single_thread"] = {"points": n, "single_thread": r, "same": same}
        save()
    res["slopes"] = {}
    pts = [res["sizes"][str(n)]["input"]["points"] for n in sizes]
    for st in args.stages.split(","):
        rs = [res["sizes"][str(n)].get(st, {}) for n in sizes]
        res["slopes"][st] = {"wall": slope(pts, [r.get("wall_s") for r in rs]),
                             "cpu": slope(pts, [r.get("cpu_s") for r in rs]),
                             "peak_rss": slope(pts, [r.get("peak_rss_gb") for r in rs])}
    save()
    print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
