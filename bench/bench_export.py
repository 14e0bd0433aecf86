"""Benchmark: whole export of the synthetic ``bench`` scene with 2 workers, against writing
the same bytes with no computation, in the same run.

1. ``export_dataset`` (OccuFly layout, default 192x128x128 @ 0.5 m, local pool of 2
   processes) into a fresh folder: wall time T_export.
2. Baseline: every file the export produced (same paths under a fresh folder, same bytes)
   written by 2 processes with the same atomic write (temp file, fsync, rename) and the same
   per-frame done markers: wall time T_write.

Prints one JSON object with both times, the ratio T_export / T_write (target <= 3), bytes,
frames and the per-frame compute split reported by the export.

    .venv/bin/python bench/bench_export.py [--root /tmp/occufly_bench] [--preset bench]
        [--frames N] [--workers 2]

``--growth small,bench`` instead measures how the export's cost grows with the scene, the way
bench/bench_survey.py does (its ``run_stage``: wall, and CPU of the whole process tree):
``occufly export ROOT/ws_<size> OUT --workers 2 --frames <every --stride-th frame>`` on each
size's workspace (which must hold ``grid/scene_grid.npz``: import, select, lift, voxelize it
first), for the code at ``--baseline`` (``git archive``) and for the working tree, alternating,
best CPU of ``--rounds``; prints the CPU per frame and the log-log slopes of CPU against frames
exported and against image pixels exported, before and after.

    .venv/bin/python bench/bench_export.py --root R --growth small,bench --baseline 7fa56f7
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _scene import ensure_scene  # noqa: E402


def warm_import(name: str) -> bool:
    import importlib

    importlib.import_module(name)
    return True


def write_chunk(items: list[tuple[str, bytes]]) -> int:
    from occufly.fsutil import atomic_write_bytes, fsync_dir

    dirs = set()
    for path, data in items:
        atomic_write_bytes(path, data)
        dirs.add(str(Path(path).parent))
    for d in dirs:
        fsync_dir(Path(d))
    return sum(len(b) for _, b in items)


GROWTH_RUN = ("import sys; sys.path.insert(0, sys.argv.pop(1)); from occufly.cli import main; "
              "sys.exit(main(sys.argv[1:]))")


def growth(root: Path, sizes: list[str], baseline: str, rounds: int, stride: int, workers: int) -> dict:
    import math
    import subprocess

    from bench_survey import run_stage  # the survey's figures: CPU of the whole process tree

    from occufly.scene import Scene

    repo = Path(__file__).resolve().parents[1]
    trees = {"now": repo}
    if baseline:
        code = root / f"code_{baseline}"
        shutil.rmtree(code, ignore_errors=True)
        code.mkdir(parents=True)
        arch = subprocess.run(["git", "-C", str(repo), "archive", baseline, "occufly"], capture_output=True,
                              check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(code)], input=arch, check=True)
        trees = {"baseline": code, **trees}
    logs = root / "logs_growth"
    logs.mkdir(parents=True, exist_ok=True)
    res: dict = {"bench": "export-growth", "sizes": {}, "baseline": baseline, "rounds": rounds,
                 "stride": stride, "workers": workers}
    for size in sizes:
        ws = root / f"ws_{size}"
        if not (ws / "grid" / "scene_grid.npz").is_file():
            raise SystemExit(f"{ws}: no grid/scene_grid.npz (import, select, lift and voxelize it first)")
        scene = Scene.load(ws)
        idx = list(range(0, len(scene.frames), stride))
        px = sum(scene.frames[i].camera.width * scene.frames[i].camera.height for i in idx)
        S = res["sizes"][size] = {"frames": len(scene.frames), "points": scene.n_points,
                                  "frames_exported": len(idx), "pixels_exported": px}
        for _ in range(rounds):
            for name, tree in trees.items():
                out = root / f"growth_{size}_{name}"
                shutil.rmtree(out, ignore_errors=True)
                fig = run_stage(f"{size}_{name}", [sys.executable, "-c", GROWTH_RUN, str(tree), "export", str(ws),
                                                   str(out), "--workers", str(workers), "--frames",
                                                   ",".join(map(str, idx)), "--json"],
                                outputs=[out], log_dir=logs)
                if fig["exit"] != 0:
                    raise SystemExit(f"{size} {name}: {fig.get('error')}")
                S.setdefault(name, {"cpu_s": [], "wall_s": []})
                S[name]["cpu_s"].append(fig["cpu_s"])
                S[name]["wall_s"].append(fig["wall_s"])
                shutil.rmtree(out, ignore_errors=True)
    a, b = res["sizes"][sizes[0]], res["sizes"][sizes[-1]]
    for name in trees if len(sizes) > 1 else ():
        ca, cb = min(a[name]["cpu_s"]), min(b[name]["cpu_s"])
        for driver in ("frames", "pixels"):
            na, nb = a[f"{driver}_exported"], b[f"{driver}_exported"]
            if na != nb:
                res[f"slope_cpu_{driver}_{name}"] = round(math.log(cb / ca) / math.log(nb / na), 3)
        for S in (a, b):
            S[name]["cpu_per_frame_s"] = round(min(S[name]["cpu_s"]) / S["frames_exported"], 4)
    res["linear_budget"] = 1.15
    res["loadavg_1m"] = round(os.getloadavg()[0], 2)
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--root", type=Path, default=Path("/tmp/occufly_bench"))
    ap.add_argument("--preset", default="bench")
    ap.add_argument("--frames", type=int, help="export only the first N frames (default all)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--growth", help="comma-separated sizes (e.g. small,bench): the growth mode above")
    ap.add_argument("--baseline", default="", help="--growth: git revision to compare against")
    ap.add_argument("--rounds", type=int, default=2, help="--growth: runs per size and code version")
    ap.add_argument("--stride", type=int, default=8, help="--growth: export every k-th frame")
    args = ap.parse_args()
    if args.growth:
        print(json.dumps(growth(args.root.absolute(), args.growth.split(","), args.baseline, args.rounds,
                                args.stride, args.workers), indent=1))
        return
    out, ws = ensure_scene(args.root, args.preset)

    from occufly.export import export_dataset
    from occufly.grid import SceneGrid
    from occufly.parallel import LocalExecutor
    from occufly.scene import Scene

    grid = SceneGrid.load(out / "truth" / "scene_grid.npz")
    n = len(Scene.load(ws).frames)
    frames = list(range(min(n, args.frames))) if args.frames else None
    exp = args.root / f"export_{args.preset}"
    base = args.root / f"baseline_{args.preset}"
    shutil.rmtree(exp, ignore_errors=True)
    shutil.rmtree(base, ignore_errors=True)

    with LocalExecutor(args.workers) as ex:
        # start the worker processes and import the library outside the timing (a fixed
        # cost per worker, not per frame); loading the scene and grid stays inside it
        ex.map(warm_import, ["occufly.export.dataset"] * (2 * args.workers))
        t0 = time.perf_counter()
        res = export_dataset(ws, exp, grid=grid, frames=frames, executor=ex)
        t_export = time.perf_counter() - t0

    # the same bytes written with no computation; read into memory in batches of
    # <= 400 MB outside the timing, each batch split over the workers and timed
    files = [p for p in sorted(exp.rglob("*")) if p.is_file()]
    batches, cur, size = [], [], 0
    for p in files:
        cur.append(p)
        size += p.stat().st_size
        if size > 400e6:
            batches.append(cur)
            cur, size = [], 0
    if cur:
        batches.append(cur)
    t_write, written = 0.0, 0
    with ProcessPoolExecutor(args.workers) as pool:
        list(pool.map(abs, [0, 1]))
        for batch in batches:
            payload = [(str(base / p.relative_to(exp)), p.read_bytes()) for p in batch]
            chunks = [payload[i::args.workers] for i in range(args.workers)]
            t0 = time.perf_counter()
            written += sum(pool.map(write_chunk, chunks))
            t_write += time.perf_counter() - t0
            del payload, chunks

    r = res["results"]
    print(json.dumps({
        "bench": "export", "preset": args.preset, "workers": args.workers,
        "frames": res["frames"], "bytes_export": res["bytes"], "bytes_baseline": written,
        "files": len(files),
        "export_s": round(t_export, 2), "write_only_s": round(t_write, 2),
        "ratio_export_vs_write": round(t_export / t_write, 2), "target_ratio": 3.0,
        "per_frame_s_median": round(float(np.median([x["seconds"] for x in r])), 3) if r else None,
        "per_frame_cpu_s_median": round(float(np.median([x["cpu_seconds"] for x in r])), 3) if r else None,
        "per_frame_sample_s_median": round(float(np.median([x["seconds_sample"] for x in r])), 3) if r else None,
        "cpu_count": os.cpu_count(), "loadavg_1m": round(os.getloadavg()[0], 2),
    }))
    shutil.rmtree(base, ignore_errors=True)


if __name__ == "__main__":
    main()
