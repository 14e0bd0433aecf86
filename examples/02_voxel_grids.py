"""02 - Voxel grids as instanced boxes: the scene grid and one frame's camera grid.

The camera grid is sampled from the scene grid with ``occufly.sampling.sample_frame``
(FORMATS.md section 2 layout, here 96x64x64 at 1 m); valid occupied voxels are drawn per
class, occluded ones grey and translucent, a sparse sample of invalid voxels dark.

    .venv/bin/python examples/02_voxel_grids.py [--frame 4]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import viser

from app.viewer import scene_builder as sb
from app.viewer.demo_scene import make_demo_workspace
from app.viewer.scene_view import load_camera_grid
from occufly.sampling import FrameGridSpec


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frame", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=0)
    args = ap.parse_args()
    ws = Path(tempfile.mkdtemp()) / "demo"
    make_demo_workspace(ws, 200_000, voxel_size=1.0)
    data = sb.ViewerData.load(ws)
    server = viser.ViserServer(host="127.0.0.1", port=0)
    server.scene.set_up_direction("+z")
    nodes = sb.scene_grid_nodes(data.grid, data.scene.origin, data.taxonomy)
    cg = load_camera_grid(data, args.frame, FrameGridSpec(shape=(96, 64, 64), voxel_size=1.0))
    nodes += sb.camera_grid_nodes(*cg, taxonomy=data.taxonomy)
    sb.send_voxel_nodes(server.scene, nodes)
    sb.send_frustum_nodes(server.scene, sb.frustum_nodes(data.scene), scale=5.0)
    for nd in nodes:
        print(f"{nd.name:32s} {len(nd.centers):8,d} boxes")
    print(f"open http://127.0.0.1:{server.get_port()}/")
    t0 = time.time()
    while not args.seconds or time.time() - t0 < args.seconds:
        time.sleep(0.2)
    server.stop()


if __name__ == "__main__":
    main()
