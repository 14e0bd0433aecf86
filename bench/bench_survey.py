"""The benchmark's scale, end to end: every stage a user runs, on three scene sizes.

For each size (default ``bench``, ``survey-half``, ``survey``) the stages run as subprocesses
of the ``occufly`` CLI, exactly as a user types them::

    synth     occufly synth SRC --preset P                       (generation, not a user stage)
    import    occufly import SRC -w WS                           (full visibility: union)
    select    occufly select WS                                  (stratified, 25 m cells)
    lift      occufly lift WS --masks M --no-fill                (votes of every selected mask;
                                                                  M = the truth masks of the selected
                                                                  frames + every full-size frame)
    fill      occufly lift WS --masks M                          (kNN fill + kNN denoise only:
                                                                  every mask is already lifted)
    voxelize  occufly voxelize WS
    export    occufly export WS OUT --workers 2                  (local process pool)
    export_dask occufly export WS OUT2 --dask tcp://...          (Dask LocalCluster, 2 workers)
    review    bench/_survey_stages.py review WS SRC              (quality report, suspects list,
                                                                  LOO agreement of one frame, a
                                                                  1 M point correction + undo)
    gated_export bench/_survey_stages.py gated WS SRC K          (export gated to accepted frames:
                                                                  relift of 4/5 of the masks,
                                                                  voxelize, export every K-th frame)

Per stage: wall time, CPU time (user + sys of the CLI and the children it waited for, read
with ``wait4``), peak RSS (``ru_maxrss``: the largest single process) and the peak RSS summed
over the process tree (sampled every 0.2 s; for the Dask stage the cluster's worker processes
too), disk written (growth of the stage's output folders and ``ru_oublock``). Cost growth: a
log-log fit of wall time against the stage's natural size (points, frames or mask pixels) over
the sizes measured, with the slope; the budgets of issue 16 are checked and reported.

On the largest size with full-size (20 MP) frames, the 20 MP path is timed in-process on one
5472 x 3648 frame: mask PNG decode + votes updated, the prefill render of the lifted labels,
the 2D agreement of the frame, and the export of the frame on one core.

Results are written to ``--out`` (JSON, atomically) after every stage, so a long run that is
stopped keeps what it measured; ``--resume`` skips the stages already in that file. The last
line printed is the one JSON object.

    python bench/bench_survey.py --root /tmp/occufly-survey --out /tmp/occufly-survey/results.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "occufly.cli"]

# issue 16's budgets on 2 cores / 24 GB
BUDGET = {"peak_rss_gb": 16.0, "import_s": 30 * 60, "fill_s": 5 * 60, "voxelize_s": 10 * 60,
          "slope_linear": 1.15, "frame_path_s": 1.0,
          # issue 38's review budgets (CPU seconds of one request's work on one core)
          "loo_one_frame_s": 1.0, "suspects_s": 1.0, "quality_report_s": 2.0,
          "correction_1m_s": 2.0}
STAGES = "synth,import,select,lift,fill,voxelize,export,export_dask,frame_path,review,gated_export"
STAGE_SCRIPT = [sys.executable, str(REPO / "bench" / "_survey_stages.py")]
# a stage whose wall or CPU time moved by more than this against --compare is flagged
MOVED = 0.15
# the stages whose cost should grow linearly with their size driver
LINEAR = ("import", "lift", "fill", "voxelize", "export", "export_dask")


# ---- measuring one subprocess ------------------------------------------------------------------
def _tree_rss(pid: int, extra: list[int]) -> tuple[int, float]:
    """(summed RSS bytes, summed CPU seconds) of ``pid``'s process tree plus ``extra`` pids."""
    import psutil

    procs = []
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.Error:
        pass
    for e in extra:
        try:
            p = psutil.Process(e)
            procs += [p, *p.children(recursive=True)]
        except psutil.Error:
            pass
    rss, cpu = 0, 0.0
    seen = set()
    for p in procs:
        if p.pid in seen:
            continue
        seen.add(p.pid)
        try:
            rss += p.memory_info().rss
            t = p.cpu_times()
            # the children already reaped count in their parent's children_* (a pool's
            # workers are children of its forkserver, which wait4 on the CLI does not see)
            cpu += t.user + t.system + t.children_user + t.children_system
        except psutil.Error:
            pass
    return rss, cpu


def du(paths: list[Path]) -> int:
    """Bytes on disk under ``paths`` (files only; missing paths count 0)."""
    total = 0
    for p in paths:
        if p.is_file():
            total += p.stat().st_size
        elif p.is_dir():
            for dirpath, _, files in os.walk(p):
                for f in files:
                    try:
                        total += os.lstat(os.path.join(dirpath, f)).st_size
                    except OSError:
                        pass
    return total


def run_stage(name: str, argv: list[str], *, outputs: list[Path], log_dir: Path,
              watch_pids: list[int] | None = None) -> dict:
    """Run one CLI command; returns its figures (and its --json output as ``result``)."""
    before = du(outputs)
    watch_pids = watch_pids or []
    cpu_extra0 = _tree_rss(0, watch_pids)[1] if watch_pids else 0.0
    out_path, err_path = log_dir / f"{name}.stdout", log_dir / f"{name}.stderr"
    t0 = time.perf_counter()
    with open(out_path, "wb") as fo, open(err_path, "wb") as fe:
        proc = subprocess.Popen(argv, stdout=fo, stderr=fe, cwd=REPO,
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
        peak = {"tree": 0, "extra_cpu": 0.0, "tree_cpu": 0.0}
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                rss, tcpu = _tree_rss(proc.pid, [])
                peak["tree"] = max(peak["tree"], rss)
                peak["tree_cpu"] = max(peak["tree_cpu"], tcpu)
                if watch_pids:
                    peak["tree"] = max(peak["tree"], rss + _tree_rss(0, watch_pids)[0])
                if watch_pids:
                    peak["extra_cpu"] = _tree_rss(0, watch_pids)[1] - cpu_extra0
                stop.wait(0.2)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        _, status, ru = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        stop.set()
        th.join()
    wall = time.perf_counter() - t0
    fig = {
        "command": " ".join(str(a) for a in argv[2:]),
        "exit": proc.returncode,
        "wall_s": round(wall, 2),
        # user + sys of the CLI and every descendant: wait4's figure, or the sampled process
        # tree's when larger (pool workers under a forkserver are not reaped by the CLI)
        "cpu_s": round(max(ru.ru_utime + ru.ru_stime, peak["tree_cpu"]), 2),
        "cpu_wait4_s": round(ru.ru_utime + ru.ru_stime, 2),
        "peak_rss_mb": round(ru.ru_maxrss / 1024, 1),
        "peak_rss_tree_mb": round(peak["tree"] / 2**20, 1),
        "disk_written_mb": round((du(outputs) - before) / 2**20, 1),
        "blocks_written_mb": round(ru.ru_oublock * 512 / 2**20, 1),
    }
    if watch_pids:
        fig["cluster_cpu_s"] = round(peak["extra_cpu"], 2)
    text = out_path.read_text(errors="replace").strip()
    if proc.returncode != 0:
        err = err_path.read_text(errors="replace").strip().splitlines()
        fig["error"] = " | ".join(err[-3:]) if err else text[-300:]
    else:
        try:
            fig["result"] = json.loads(text.splitlines()[-1]) if text else None
        except json.JSONDecodeError:
            fig["result"] = None
    return fig


# ---- results file --------------------------------------------------------------------------------
class Results:
    def __init__(self, path: Path, resume: bool) -> None:
        self.path = path
        self.data: dict = {}
        if resume and path.is_file():
            self.data = json.loads(path.read_text())
        self.data.setdefault("benchmark", "survey")
        self.data.setdefault("machine", {"cpus": os.cpu_count(),
                                         "mem_gb": round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)})
        self.data.setdefault("budget", BUDGET)
        self.data.setdefault("sizes", {})

    def size(self, name: str) -> dict:
        return self.data["sizes"].setdefault(name, {"stages": {}})

    def save(self) -> None:
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1))
        os.replace(tmp, self.path)


def _summary_result(stage: str, r: dict | None) -> dict:
    """The few fields of a stage's --json output worth keeping (the rest is in the logs)."""
    if not isinstance(r, dict):
        return {}
    keep = {
        "synth": ("frames", "points", "depth_samples", "mean_views_per_point", "full_size_frames",
                  "image_size", "full_image_size", "timings"),
        "import": ("frames", "points", "visibility_source", "visibility_computed"),
        "select": ("selected", "candidates", "ratio", "coverage"),
        "lift": ("masks", "updated", "annotated_frames", "directly_labelled"),
        "fill": ("labels",),
        "voxelize": ("shape", "grid_shape", "occupied", "timings_s", "voxel"),
        "export": ("frames", "written", "bytes", "seconds", "sample_seconds_mean", "skipped_done"),
    }.get(stage.replace("_dask", ""), ())
    out = {k: r[k] for k in keep if k in r}
    if stage in ("review", "gated_export"):  # bench/_survey_stages.py: figures only
        return dict(r)
    if stage == "import" and isinstance(r.get("visibility"), dict):
        v = r["visibility"]
        out["correspondences"] = v.get("correspondences")
        out["views_per_point_mean"] = v.get("views_per_point_mean")
    if stage == "fill" and isinstance(out.get("labels"), dict):
        lab = out.pop("labels")
        out["labels"] = {k: lab[k] for k in ("labelled", "direct", "filled", "timings", "seconds")
                         if k in lab}
    return out


# ---- the pipeline on one size ---------------------------------------------------------------------
def _tree_digest(root: Path, skip_names: tuple[str, ...] = ()) -> dict[str, str]:
    import hashlib

    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and p.name not in skip_names:
            out[str(p.relative_to(root))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def _manifest_free(d: dict[str, str]) -> dict[str, str]:
    """Export trees without their run-specific bookkeeping (manifests hold timings and paths)."""
    return {k: v for k, v in d.items() if not (k.endswith("manifest.json") or "/.state/" in f"/{k}"
                                               or k.startswith(".state") or k.endswith(".log"))}


def run_size(preset: str, root: Path, res: Results, *, stages: list[str], dask: bool,
             keep_exports: bool, export_stride: int, import_workers: int = 1) -> None:
    src, ws = root / f"synth_{preset}", root / f"ws_{preset}"
    masks = root / f"masks_{preset}"
    logs = root / "logs" / preset
    logs.mkdir(parents=True, exist_ok=True)
    S = res.size(preset)
    st = S["stages"]

    def do(name: str, argv: list[str], outputs: list[Path], **kw) -> dict | None:
        if name not in stages:
            return None
        if name in st and st[name].get("exit") == 0:
            return st[name]
        print(f"[{preset}] {name}: {' '.join(map(str, argv[2:]))}", file=sys.stderr, flush=True)
        fig = run_stage(name, argv, outputs=outputs, log_dir=logs, **kw)
        full = fig.pop("result", None)
        fig["result"] = _summary_result(name, full)
        st[name] = fig
        res.save()
        print(f"[{preset}] {name}: exit {fig['exit']} wall {fig['wall_s']} s, peak "
              f"{fig['peak_rss_mb']} MB", file=sys.stderr, flush=True)
        if fig["exit"] != 0:
            raise RuntimeError(f"{preset} {name} failed: {fig.get('error')}")
        return full if full is not None else fig

    if not (src / "truth" / "meta.json").is_file() or "synth" in st and st["synth"].get("exit") != 0:
        do("synth", [*CLI, "synth", str(src), "--preset", preset, "--force", "--json"], [src])
    meta = json.loads((src / "truth" / "meta.json").read_text())
    S["scene"] = {"frames": meta["n_frames"], "points": meta["n_points"],
                  "image_size": meta["image_size"],
                  "full_size_frames": len(meta.get("full_size_frames", [])),
                  "source_mb": round(du([src]) / 2**20, 1)}
    S["generation_timings_s"] = meta.get("timings")
    res.save()
    do("import", [*CLI, "import", str(src), "-w", str(ws), "--force", "--workers",
                  str(import_workers), "--json"], [ws])
    sel = do("select", [*CLI, "select", str(ws), "--json"], [ws / "selection.json"])
    if "lift" in stages:
        chosen = json.loads((ws / "selection.json").read_text())
        names = list(chosen["frame_names"]) + list(meta.get("full_size_frames", []))
        if masks.exists():
            shutil.rmtree(masks)
        masks.mkdir(parents=True)
        px = 0
        cams = {d["name"]: d.get("camera_id", 1) for d in meta["frames_detail"]}
        full = meta.get("camera_full_size") or meta["camera"]
        for n in dict.fromkeys(names):
            stem = Path(n).stem
            os.symlink(src / "truth" / "masks" / f"{stem}.png", masks / f"{stem}.png")
            cam = full if cams.get(n, 1) == 2 else meta["camera"]
            px += cam["width"] * cam["height"]
        S["lifted_frames"] = len(dict.fromkeys(names))
        S["lifted_full_size_frames"] = sum(1 for n in dict.fromkeys(names) if cams.get(n, 1) == 2)
        S["lifted_mask_pixels"] = px
        res.save()
    del sel
    do("lift", [*CLI, "lift", str(ws), "--masks", str(masks), "--no-fill", "--json"], [ws])
    do("fill", [*CLI, "lift", str(ws), "--masks", str(masks), "--json"], [ws])
    do("voxelize", [*CLI, "voxelize", str(ws), "--json"], [ws])
    out_local, out_dask = root / f"export_{preset}", root / f"export_dask_{preset}"
    n_frames = meta["n_frames"]
    exported = list(range(0, n_frames, export_stride))
    S["exported_frames"] = len(exported)
    S["export_stride"] = export_stride
    sel_frames = ["--frames", ",".join(map(str, exported))] if export_stride > 1 else []
    if "export" in stages and not ("export" in st and st["export"].get("exit") == 0):
        shutil.rmtree(out_local, ignore_errors=True)
    do("export", [*CLI, "export", str(ws), str(out_local), "--workers", "2", *sel_frames, "--json"],
       [out_local])
    if dask and "export_dask" in stages and not ("export_dask" in st and st["export_dask"].get("exit") == 0):
        from dask.distributed import LocalCluster

        shutil.rmtree(out_dask, ignore_errors=True)
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, scheduler_port=0,
                          dashboard_address=":0", memory_limit="8GiB") as cluster:
            pids = [int(p) for p in _cluster_pids(cluster)]
            do("export_dask", [*CLI, "export", str(ws), str(out_dask), "--dask", cluster.scheduler_address,
                               *sel_frames, "--json"], [out_dask], watch_pids=pids)
        if out_local.is_dir() and out_dask.is_dir():
            a, b = _manifest_free(_tree_digest(out_local)), _manifest_free(_tree_digest(out_dask))
            diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            S["export_local_vs_dask"] = {"files": len(a), "differing": len(diff), "examples": diff[:5]}
            res.save()
    if not keep_exports:
        for p in (out_local, out_dask):
            shutil.rmtree(p, ignore_errors=True)
    do("review", [*STAGE_SCRIPT, "review", str(ws), str(src)], [ws])
    do("gated_export", [*STAGE_SCRIPT, "gated", str(ws), str(src), str(export_stride)], [])


def _cluster_pids(cluster) -> list[int]:
    """PIDs of a LocalCluster's worker (nanny) processes."""
    pids = []
    for w in cluster.workers.values():
        proc = getattr(w, "process", None)
        pid = getattr(getattr(proc, "process", None), "pid", None) or getattr(proc, "pid", None)
        if pid:
            pids.append(pid)
    return pids


# ---- the 20 MP path ---------------------------------------------------------------------------------
FRAME_PATH = r'''
import json, sys, time, tempfile, shutil
from pathlib import Path
import numpy as np
ws, src = Path(sys.argv[1]), Path(sys.argv[2])
from occufly.scene import Scene
from occufly.io.masks import read_mask
from occufly.lifting import VoteStore, load_labels
from occufly.render import render_for_mask, render_labels, agreement
out = {}
def timed(key, fn):
    t0, c0 = time.perf_counter(), time.process_time()
    r = fn()
    out[key + "_s"] = round(time.perf_counter() - t0, 3)
    out[key + "_cpu_s"] = round(time.process_time() - c0, 3)
    return r
meta = json.loads((src / "truth" / "meta.json").read_text())
full = meta["full_size_frames"]
scene = Scene.load(ws)
state = VoteStore.open(ws, scene)
included = state.included_versions()
lifted = [n for n in full if scene.frame_index(n) in included]
name = lifted[0] if lifted else full[0]
fi = scene.frame_index(name)
fr = scene.frames[fi]
out.update(frame=name, size=[fr.camera.width, fr.camera.height], lifted=bool(lifted))
mp = src / "truth" / "masks" / (Path(name).stem + ".png")
data = mp.read_bytes()
# an annotator's save: the PNG decoded and checked, then this frame's votes replaced
mask = timed("mask_decode", lambda: read_mask(data, fr, scene.taxonomy, name=str(mp)))
edited = mask.copy(); edited[1000:1400, 2000:2400] = 1
r = timed("votes_update", lambda: state.set_mask(fi, edited, version="bench-edit", name="edit"))
out["mask_save_to_votes_s"] = round(out["mask_decode_s"] + out["votes_update_s"], 3)
out["mask_save_to_votes_cpu_s"] = round(out["mask_decode_cpu_s"] + out["votes_update_cpu_s"], 3)
out["points_changed"] = int(r.get("points_changed", -1)) if isinstance(r, dict) else None
state.set_mask(fi, mask, version="bench-orig", name=str(mp))
labels = np.asarray(load_labels(ws).labels)
render_labels(scene, labels, (fi + 1) % len(scene.frames), scale=0.05)  # warm the per-scene caches
cls, depth = timed("prefill_render", lambda: render_for_mask(scene, labels, fi, mask.shape))
out["prefill_covered"] = round(float((cls > 0).mean()), 4)
for ds in (2, 4):
    c2, _ = timed(f"prefill_render_downscale{ds}", lambda ds=ds: render_labels(scene, labels, fi, scale=1.0 / ds))
    out[f"prefill_downscale{ds}_covered"] = round(float((c2 > 0).mean()), 4)
ag = timed("agreement", lambda: agreement(mask, cls, scene.taxonomy))
out["agreement"] = round(float(ag["agreement"]), 4)
from occufly.export.dataset import export_dataset
tmp = Path(tempfile.mkdtemp(prefix="frame_export_", dir=str(ws.parent)))
try:
    s = timed("export_one_frame_total", lambda: export_dataset(ws, tmp / "out", frames=[fi], workers=1))
    rs = s.get("results") or [r for sc in s.get("scenes", []) for r in sc.get("results", [])]
    if rs:
        out["export_frame_task_s"] = rs[0].get("seconds")
        out["export_frame_task_cpu_s"] = rs[0].get("cpu_seconds")
except Exception as e:  # e.g. no scene grid yet: the other figures still count
    out["export_error"] = f"{type(e).__name__}: {e}"
finally:
    shutil.rmtree(tmp, ignore_errors=True)
print(json.dumps(out))
'''


def frame_path(preset: str, root: Path, res: Results) -> None:
    src, ws = root / f"synth_{preset}", root / f"ws_{preset}"
    logs = root / "logs" / preset
    fig = run_stage("frame_path", [sys.executable, "-c", FRAME_PATH, str(ws), str(src)],
                    outputs=[], log_dir=logs)
    r = fig.pop("result", None) or {}
    fig.pop("command", None)
    res.size(preset)["frame_path_20mp"] = {**r, "process": fig}
    res.save()


# ---- growth --------------------------------------------------------------------------------------
def _driver(stage: str, S: dict) -> tuple[str, float | None]:
    sc = S.get("scene", {})
    st = S["stages"]
    if stage == "import":
        # the import's work is one projection + depth test per candidate correspondence:
        # points x views per point (31 on small, 60 on bench), not points alone
        corr = (st.get("import", {}).get("result") or {}).get("correspondences")
        if corr:
            return "correspondences", corr
    if stage in ("import", "fill", "voxelize", "synth"):
        return "points", sc.get("points")
    if stage == "select":
        return "frames", sc.get("frames")
    if stage == "lift":
        return "mask_pixels", S.get("lifted_mask_pixels")
    if stage in ("export", "export_dask"):
        return "frames_exported", S.get("exported_frames")
    del st
    return "points", sc.get("points")


def _stage_cpu(f: dict) -> float:
    """CPU seconds of a stage: its process tree plus, for the Dask stage, the cluster's
    workers (the CLI is only the client there)."""
    return float(f.get("cpu_s") or 0.0) + float(f.get("cluster_cpu_s") or 0.0)


def growth(res: Results) -> dict:
    sizes = res.data["sizes"]
    out = {}
    stages = sorted({s for S in sizes.values() for s in S["stages"]})
    for stage in stages:
        xs, ys, cs, names = [], [], [], []
        for name, S in sizes.items():
            f = S["stages"].get(stage)
            kind, x = _driver(stage, S)
            if f and f.get("exit") == 0 and x and f["wall_s"] > 0:
                xs.append(float(x))
                ys.append(float(f["wall_s"]))
                cs.append(max(_stage_cpu(f), 1e-3))
                names.append(name)
        if len(xs) < 2 or len(set(xs)) < 2:
            continue
        lx, ly = np.log(xs), np.log(ys)
        slope, icpt = np.polyfit(lx, ly, 1)
        cslope = float(np.polyfit(lx, np.log(cs), 1)[0])
        rss = [sizes[n]["stages"][stage]["peak_rss_tree_mb"] for n in names]
        mslope = float(np.polyfit(lx, np.log(np.maximum(rss, 1.0)), 1)[0])
        # judged on CPU time: on a shared machine wall time also grows with the others' load
        out[stage] = {"driver": kind, "sizes": names, "x": xs, "wall_s": ys, "cpu_s": cs,
                      "slope_wall": round(float(slope), 3), "slope_cpu": round(cslope, 3),
                      "slope_peak_rss": round(mslope, 3),
                      "linear_expected": stage in LINEAR,
                      "within_budget": (bool(cslope <= BUDGET["slope_linear"]) if stage in LINEAR else None)}
    return out


def budgets(res: Results) -> dict:
    """Issue 16's budgets, checked on the largest size measured."""
    sizes = res.data["sizes"]
    if not sizes:
        return {}
    big = max(sizes, key=lambda n: sizes[n].get("scene", {}).get("points", 0))
    st = sizes[big]["stages"]
    out: dict = {"size": big}
    peaks = {k: max(v["peak_rss_mb"], v["peak_rss_tree_mb"]) for k, v in st.items() if "peak_rss_mb" in v}
    if peaks:
        worst = max(peaks, key=peaks.get)
        out["peak_rss_gb"] = {"stage": worst, "value": round(peaks[worst] / 1024, 2),
                              "ok": peaks[worst] / 1024 <= BUDGET["peak_rss_gb"]}
    for stage, key in (("import", "import_s"), ("fill", "fill_s"), ("voxelize", "voxelize_s")):
        if stage in st:
            ok = st[stage].get("exit") == 0 and st[stage]["wall_s"] <= BUDGET[key]
            out[key] = {"value": st[stage]["wall_s"], "budget": BUDGET[key], "ok": bool(ok)}
    fp = sizes[big].get("frame_path_20mp")
    if fp:
        # judged on CPU seconds (one core): wall time on the shared machine includes waiting
        out["frame_path_20mp"] = {k: {"wall_s": fp.get(k + "_s"), "cpu_s": fp[k + "_cpu_s"],
                                      "ok": fp[k + "_cpu_s"] <= BUDGET["frame_path_s"]}
                                  for k in ("mask_save_to_votes", "prefill_render", "agreement",
                                            "export_one_frame_total") if k + "_cpu_s" in fp}
    rv = (st.get("review") or {}).get("result") or {}
    for k in ("loo_one_frame", "suspects", "quality_report", "correction_1m"):
        if k + "_cpu_s" in rv:
            out[k] = {"wall_s": rv.get(k + "_s"), "cpu_s": rv[k + "_cpu_s"],
                      "budget_s": BUDGET[k + "_s"], "ok": rv[k + "_cpu_s"] <= BUDGET[k + "_s"]}
    return out


def compare(res: Results, earlier: dict) -> dict:
    """Per size and stage, this run against an earlier results file: wall and CPU ratios, and
    the stages that moved by more than ``MOVED`` (to be explained in the closing note)."""
    out: dict = {"moved_threshold": MOVED, "sizes": {}}
    for name, S in res.data["sizes"].items():
        E = (earlier.get("sizes") or {}).get(name)
        if not E:
            continue
        rows = {}
        for stage, f in S["stages"].items():
            e = E["stages"].get(stage)
            if not e or f.get("exit") != 0 or e.get("exit") != 0:
                continue
            r = {"wall_s": [e["wall_s"], f["wall_s"]], "cpu_s": [_stage_cpu(e), _stage_cpu(f)],
                 "peak_mb": [max(e["peak_rss_mb"], e["peak_rss_tree_mb"]),
                             max(f["peak_rss_mb"], f["peak_rss_tree_mb"])]}
            for k in ("wall_s", "cpu_s", "peak_mb"):
                a, b = r[k]
                r[k.replace("_s", "").replace("_mb", "") + "_ratio"] = round(b / a, 3) if a else None
            r["moved"] = any(v is not None and abs(v - 1) > MOVED
                             for v in (r["wall_ratio"], r["cpu_ratio"], r["peak_ratio"]))
            rows[stage] = r
        out["sizes"][name] = rows
    return out


def _count(n: int) -> str:
    return f"{n / 1e6:.1f} M" if n >= 1e6 else f"{n / 1e3:.0f} k"


def markdown_table(data: dict) -> str:
    """README's "How big, how long" table from a results file: per size and stage, wall time,
    CPU time (user + sys of the process tree) and peak memory (the larger of the biggest
    process and the sampled process-tree sum)."""
    order = ["synth", "import", "select", "lift", "fill", "voxelize", "export", "export_dask",
             "review", "gated_export"]
    sizes = [n for n in data.get("sizes", {}) if data["sizes"][n].get("scene")]
    sizes.sort(key=lambda n: data["sizes"][n]["scene"].get("points", 0))
    rows = ["| stage | " + " | ".join(
        f"{n} ({data['sizes'][n]['scene']['frames']} frames, {_count(data['sizes'][n]['scene']['points'])} "
        "points)" for n in sizes) + " |",
        "|---|" + "---|" * len(sizes)]

    def fmt_s(x: float) -> str:
        return f"{x:.0f} s" if x < 120 else f"{x / 60:.1f} min"

    for st in order:
        cells = []
        for n in sizes:
            S = data["sizes"][n]
            f = S["stages"].get(st)
            if f is None or f.get("exit") != 0:
                cells.append("not run" if f is None else "failed")
                continue
            mem = max(f["peak_rss_mb"], f["peak_rss_tree_mb"]) / 1024
            note = ""
            if st.startswith("export") and S.get("export_stride", 1) > 1:
                note = f" ({S['exported_frames']} frames)"
            cells.append(f"{fmt_s(f['wall_s'])} ({fmt_s(_stage_cpu(f))} CPU), {mem:.1f} GB{note}")
        if any(c != "not run" for c in cells):
            rows.append(f"| {st} | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--root", type=Path, default=Path("/tmp/occufly-bench-survey"))
    ap.add_argument("--out", type=Path, help="results JSON, rewritten after every stage "
                    "(default ROOT/results.json)")
    ap.add_argument("--sizes", default="bench,survey-half,survey",
                    help="comma-separated presets, smallest first")
    ap.add_argument("--stages", default=STAGES)
    ap.add_argument("--compare", type=Path, metavar="EARLIER",
                    help="an earlier results file: per stage wall / CPU / peak ratios, stages "
                    f"that moved more than {MOVED:.0%}% flagged (under 'comparison')")
    ap.add_argument("--resume", action="store_true", help="keep the stages already in --out")
    ap.add_argument("--no-dask", action="store_true")
    ap.add_argument("--keep-exports", action="store_true")
    ap.add_argument("--export-stride", type=int, default=8,
                    help="export every k-th frame (per-frame export is independent work: its cost "
                    "per frame is what scales; 1 = every frame)")
    ap.add_argument("--import-workers", type=int, default=1,
                    help="occufly import --workers (visibility frames in parallel; same output)")
    ap.add_argument("--table", type=Path, metavar="RESULTS",
                    help="print the README table of an earlier results file and exit")
    args = ap.parse_args(argv)
    if args.table:
        print(markdown_table(json.loads(args.table.read_text())))
        return 0
    args.root.mkdir(parents=True, exist_ok=True)
    res = Results(args.out or args.root / "results.json", args.resume)
    stages = args.stages.split(",")
    sizes = [s for s in args.sizes.split(",") if s]
    from occufly.synthetic.presets import get_preset

    for s in sizes:  # unknown preset: a clear error before anything runs
        if not (args.root / f"synth_{s}" / "truth" / "meta.json").is_file():
            get_preset(s)
    failures = []
    for s in sizes:
        try:
            run_size(s, args.root, res, stages=stages, dask=not args.no_dask, keep_exports=args.keep_exports,
                     export_stride=max(1, args.export_stride), import_workers=args.import_workers)
            meta = json.loads((args.root / f"synth_{s}" / "truth" / "meta.json").read_text())
            done = res.size(s).get("frame_path_20mp", {}).get("process", {}).get("exit") == 0
            if "frame_path" in stages and meta.get("full_size_frames") and not done:
                frame_path(s, args.root, res)
        except Exception as e:  # keep measuring the other sizes; the failure is in the JSON
            res.size(s)["failed"] = f"{type(e).__name__}: {e}"
            failures.append(s)
            res.save()
        res.data["growth"] = growth(res)
        res.data["budgets"] = budgets(res)
        if args.compare:
            res.data["comparison"] = {"earlier": str(args.compare),
                                      **compare(res, json.loads(args.compare.read_text()))}
        res.save()
    print(json.dumps(res.data, separators=(",", ":")))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
