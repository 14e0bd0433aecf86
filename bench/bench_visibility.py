"""Benchmark: visibility at import (time, peak RSS, views per point, storage) and the frame
selection it enables (|J|/N and rho), for the modes union (default), vis and depth, all
measured in the same run on the same reconstruction.

    flock /tmp/occufly-heavy.lock nice .venv/bin/python bench/bench_visibility.py SRC [--out DIR]
        [--modes union,vis,depth] [--keep]

SRC is a reconstruction (e.g. ``occufly synth SRC --preset bench --seed 0``). Each import runs
in its own process, so its peak RSS (``VmHWM`` of /proc/self/status) is its own. Prints one JSON object; the
baseline is ``vis`` (the visibility a COLMAP ``fused.ply.vis`` alone gives, the old default).
Exits 1 when the default (union) selection misses the issue's bars (greedy/cover rho >= 0.99
with <= 6 % of the frames, stratified <= 10 %).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

_CHILD = r"""
import json, sys, time
from occufly.io.importer import import_scene
t = time.perf_counter()
s = import_scene(sys.argv[1], sys.argv[2], visibility=sys.argv[3], overwrite=True)
dt = time.perf_counter() - t
# VmHWM, not ru_maxrss: ru_maxrss survives exec, so a child would report its parent's peak
hwm = [int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM")][0]
print(json.dumps({"seconds": dt, "peak_rss_gb": hwm / 2**20,
                  "visibility": s.summary()["visibility"],
                  "stats": {k: v for k, v in s.meta["visibility_stats"].items() if k != "warnings"}}))
"""


def _dir_bytes(p: Path) -> int:
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


def _selection(ws: Path) -> dict:
    from occufly.scene import Scene
    from occufly.selection import select_frames

    scene = Scene.load(ws)
    out = {}
    for mode in ("stratified", "greedy", "cover"):
        t = time.perf_counter()
        r = select_frames(scene, mode=mode, target_coverage=0.99)
        out[mode] = {"frames": len(r.frames), "candidates": r.n_candidates,
                     "ratio": round(r.ratio, 4), "coverage": round(r.coverage, 4),
                     "cell": r.cell, "seconds": round(time.perf_counter() - t, 2)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", type=Path)
    ap.add_argument("--out", type=Path, help="folder for the workspaces (default: a temp dir)")
    ap.add_argument("--modes", default="union,vis,depth")
    ap.add_argument("--keep", action="store_true", help="keep the workspaces")
    a = ap.parse_args(argv)
    out_root = a.out or Path(tempfile.mkdtemp(prefix="bench-vis-"))
    out_root.mkdir(parents=True, exist_ok=True)
    res: dict = {"source": str(a.source), "modes": {}}
    for mode in a.modes.split(","):
        ws = out_root / f"ws-{mode}"
        p = subprocess.run([sys.executable, "-c", _CHILD, str(a.source), str(ws), mode],
                           capture_output=True, text=True, cwd=ROOT)
        if p.returncode != 0:
            print(p.stderr, file=sys.stderr)
            return 2
        r = json.loads(p.stdout.strip().splitlines()[-1])
        r["seconds"] = round(r["seconds"], 2)
        r["peak_rss_gb"] = round(r["peak_rss_gb"], 2)
        r["visibility_bytes_on_disk"] = _dir_bytes(ws / "visibility")
        r["selection"] = _selection(ws)
        res["modes"][mode] = r
        print(json.dumps({mode: r}), file=sys.stderr, flush=True)  # progress, one line per mode
        if not a.keep:
            shutil.rmtree(ws, ignore_errors=True)
    m = res["modes"]
    if "union" in m and "vis" in m:
        u, v = m["union"], m["vis"]
        res["union_vs_vis"] = {
            "views_per_point": round(u["visibility"]["views_per_point"]["mean"]
                                     / max(v["visibility"]["views_per_point"]["mean"], 1e-9), 2),
            "greedy_frames": [u["selection"]["greedy"]["frames"], v["selection"]["greedy"]["frames"]],
            "stratified_coverage": [u["selection"]["stratified"]["coverage"],
                                    v["selection"]["stratified"]["coverage"]],
        }
    ok = True
    if "union" in m:
        s = m["union"]["selection"]
        bars = {
            "greedy_rho_0.99_within_6pct": s["greedy"]["coverage"] >= 0.99 and s["greedy"]["ratio"] <= 0.06,
            "cover_rho_0.99_within_6pct": s["cover"]["coverage"] >= 0.99 and s["cover"]["ratio"] <= 0.06,
            "stratified_within_10pct": s["stratified"]["ratio"] <= 0.10,
        }
        res["bars"] = bars
        ok = all(bars.values())
    print(json.dumps(res, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
