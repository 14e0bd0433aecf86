"""Depth vs grid per altitude, and what a finer scene grid loses with nearest-centre sampling
(docs/ssc-porting.md, "Depth vs grid at 30 m"); prints one JSON object.

    python bench/bench_ssc_sampling.py WS EXPORT --ref GRID_05 --fine GRID_025 \
        [--frames 20,100,180] [--shell] > docs/bench/ssc_sampling.json

WS: the workspace; EXPORT: its SSCBench-layout export (for the depth maps, depth_full/);
GRID_05: a scene grid at the frame grid's voxel size (the synthetic truth grid of `small`);
GRID_025: the same world at half that voxel size (occufly.synthetic.truth.truth_grid with
voxel 0.25). Per frame and variant: the depth-consistency share (first occupied voxel along
each pixel's ray vs the depth map, within 1 m), occupied voxels, and the occupancy IoU of the
frame grid against the one sampled from GRID_05. ``--shell`` keeps only the surface voxels of
both grids (what a grid voxelized from surface points holds).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from occufly.datasets.compat.common import depth_consistency  # noqa: E402
from occufly.export.sscbench import kitti_K  # noqa: E402
from occufly.grid import SceneGrid  # noqa: E402
from occufly.sampling import FrameGridSpec, sample_frame, surface_mask  # noqa: E402
from occufly.scene import Scene  # noqa: E402


def shell(g: SceneGrid) -> SceneGrid:
    occ = (g.labels != 0) & (g.labels != 255)
    keep = surface_mask(occ) | (g.labels == 255)
    return SceneGrid(np.where(keep, g.labels, 0).astype(np.uint8), g.origin, g.voxel_size)


def render_table(filled: dict, shell_run: dict) -> str:
    """The Markdown table docs/ssc-porting.md carries (checked against the JSON by a test)."""
    rows = ["| frame | scene grid | depth consistency | occupied voxels | IoU vs reference |",
            "|---|---|---|---|---|"]
    for run, kind in ((filled, "filled"), (shell_run, "surface only")):
        for frame, res in run["frames"].items():
            for name, r in res.items():
                iou = f"{r['iou_vs_ref']:.3f}" if "iou_vs_ref" in r else "reference"
                rows.append(f"| {frame} | {kind}: {name} | {r['share']:.3f} | {r['occupied_voxels']} | {iou} |")
    return "\n".join(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("workspace", type=Path)
    ap.add_argument("export", type=Path)
    ap.add_argument("--ref", type=Path, required=True)
    ap.add_argument("--fine", type=Path, required=True)
    ap.add_argument("--frames", default="20,100,180")
    ap.add_argument("--shell", action="store_true")
    a = ap.parse_args()
    sc = Scene.load(a.workspace)
    ref, fine = SceneGrid.load(a.ref), SceneGrid.load(a.fine)
    if a.shell:
        ref, fine = shell(ref), shell(fine)
    spec = FrameGridSpec()
    X, Y, _ = spec.shape
    origin = np.array([-X / 2 * spec.voxel_size, -Y / 2 * spec.voxel_size, 0.0])
    manifest = json.loads(next((a.export / "manifests").glob("*.json")).read_text())
    sid = manifest["scene_id"]
    variants = {"ref grid": (ref, True), "fine grid, nearest centre (before)": (fine, False),
                "fine grid, sub-voxel (after)": (fine, True)}
    out = {"ref_voxel": ref.voxel_size, "fine_voxel": fine.voxel_size, "shell": a.shell,
           "frame_voxel": spec.voxel_size, "frames": {}}
    for f in (int(x) for x in a.frames.split(",")):
        fr = sc.frames[f]
        alt = manifest["frames"][f"{f:06d}"]["altitude"]
        depth = np.load(a.export / "depth_full" / f"{sid}_{alt}" / f"{f:06d}.npy")
        K = kitti_K(fr.camera)
        res: dict = {}
        ref_occ = ref_valid = None
        for name, (g, sub) in variants.items():
            gt = sample_frame(g, fr.camera, fr.T_cam_world, sc.origin, spec, subvoxel=sub)
            occ = (gt.labels != 0) & ~gt.invalid
            r = depth_consistency(gt.label_with_invalid(), depth, K, (fr.camera.width, fr.camera.height),
                                  origin, spec.voxel_size, step=2)
            row = {"share": round(r["share"], 3), "median_abs_err_m": round(r["median_abs_err"], 3),
                   "occupied_voxels": int(occ.sum())}
            if ref_occ is None:
                ref_occ, ref_valid = occ, ~gt.invalid
            else:
                both = ref_valid & ~gt.invalid
                row["iou_vs_ref"] = round(float((occ & ref_occ & both).sum() / max(1, ((occ | ref_occ) & both).sum())), 3)
            res[name] = row
        out["frames"][f"{alt} m ({f:06d})"] = res
        print(json.dumps({alt: res}), file=sys.stderr, flush=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
