"""Photogrammetry importers on one synthetic truth: ``synth --format all`` then import each.

Per format (ODM, Metashape, Pix4D) against the COLMAP import of the same scene (the baseline,
measured in the same run): camera-centre difference, reprojection difference of the cloud's
points (max and p99 over every frame that sees them), and the import time as a ratio to the
COLMAP import. All imports use the same visibility rule (depth test against depth rendered
from the cloud) so the times compare like for like; the COLMAP default import (its
fused.ply.vis united with the MVS depth maps) is timed as well.

Usage: python bench/bench_formats.py [--preset small] [--seed 0] [--root DIR]
Prints one JSON object.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from occufly.camera import pose_in_world, transform  # noqa: E402
from occufly.io.importer import import_scene  # noqa: E402
from occufly.synthetic.formats import FORMATS, generate_formats  # noqa: E402


def _world_poses(scene) -> list[np.ndarray]:
    return [pose_in_world(f.T_cam_world, scene.origin) for f in scene.frames]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--root", type=Path)
    args = ap.parse_args()
    root = args.root or Path(tempfile.mkdtemp(prefix="bench-formats-"))
    synth = root / f"formats_{args.preset}"
    t0 = time.perf_counter()
    if not (synth / "pix4d" / "truth" / "meta.json").is_file():
        generate_formats(synth, FORMATS, preset=args.preset, seed=args.seed, overwrite=True)
    t_synth = time.perf_counter() - t0
    empty = root / "no-depth-maps"
    empty.mkdir(exist_ok=True)
    sources = {
        "colmap": (synth / "colmap", {"visibility": "depth", "depth_maps": empty}),
        "odm": (synth / "odm", {}),
        "metashape": (synth / "metashape" / "cameras.xml",
                      {"cloud": synth / "metashape" / "dense_cloud.laz"}),
        "pix4d": (synth / "pix4d", {}),
    }
    scenes, seconds = {}, {}
    # the COLMAP baseline is imported first and again last (machine drift, warm caches): its
    # time is the faster of the two
    for fmt in ("colmap", "odm", "metashape", "pix4d", "colmap"):
        src, kw = sources[fmt]
        t = time.perf_counter()
        scenes[fmt] = import_scene(src, root / f"ws_{fmt}", overwrite=True, **kw)
        dt = time.perf_counter() - t
        seconds[fmt] = min(dt, seconds.get(fmt, dt))
        seconds.setdefault(f"{fmt}_runs", []).append(round(dt, 3)) if fmt == "colmap" else None
    t = time.perf_counter()
    import_scene(synth / "colmap", root / "ws_colmap_default", overwrite=True)
    seconds["colmap_default"] = time.perf_counter() - t

    ref = scenes["colmap"]
    T_ref = _world_poses(ref)
    pts = ref.xyz_world()
    results = {}
    for fmt in ("odm", "metashape", "pix4d"):
        sc = scenes[fmt]
        T = _world_poses(sc)
        dc = [float(np.linalg.norm(-a[:3, :3].T @ a[:3, 3] + b[:3, :3].T @ b[:3, 3]))
              for a, b in zip(T, T_ref, strict=True)]
        diffs = []
        for fa, fb, a, b in zip(sc.frames, ref.frames, T, T_ref, strict=True):
            ua, _ = fa.camera.project(transform(a, pts))
            ub, zb = fb.camera.project(transform(b, pts))
            ok = (zb > 0) & fb.camera.in_image(ub)
            diffs.append(np.linalg.norm(ua[ok] - ub[ok], axis=1))
        d = np.concatenate(diffs)
        results[fmt] = {
            "camera_model": sc.frames[0].camera.model,
            "crs": sc.meta.get("crs"),
            "centre_diff_max_m": max(dc),
            "reprojection_diff_px": {"max": float(d.max()), "p99": float(np.percentile(d, 99)),
                                     "mean": float(d.mean()), "observations": int(len(d))},
            "same_cloud": bool(np.array_equal(np.asarray(sc.xyz), np.asarray(ref.xyz))),
            "correspondences": int(sc.visibility.offsets[-1]),
            "import_s": round(seconds[fmt], 3),
            "import_time_ratio_to_colmap": round(seconds[fmt] / seconds["colmap"], 3),
        }
    print(json.dumps({
        "bench": "formats", "preset": args.preset, "seed": args.seed,
        "frames": len(ref.frames), "points": ref.n_points,
        "synth_all_formats_s": round(t_synth, 3),
        "baseline": {"colmap_import_s": round(seconds["colmap"], 3),
                     "colmap_import_runs_s": seconds["colmap_runs"],
                     "colmap_default_import_s": round(seconds["colmap_default"], 3),
                     "correspondences": int(ref.visibility.offsets[-1])},
        "formats": results,
    }, indent=1))


if __name__ == "__main__":
    main()
