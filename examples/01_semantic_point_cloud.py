"""01 - Semantic point cloud: one viser node per class, colour modes, stratified LOD.

Builds a demo workspace (procedural, UTM-sized origin) and shows it with the same scene
builder the app uses, on a local viser server bound to 127.0.0.1 (open the printed URL).

    .venv/bin/python examples/01_semantic_point_cloud.py [--points 500000] [--max-points 200000]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import viser

from app.viewer import scene_builder as sb
from app.viewer.demo_scene import make_demo_workspace


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=500_000)
    ap.add_argument("--max-points", type=int, default=200_000)
    ap.add_argument("--seconds", type=float, default=0, help="exit after N s (0 = run until Ctrl-C)")
    args = ap.parse_args()
    ws = Path(tempfile.mkdtemp()) / "demo"
    make_demo_workspace(ws, args.points)
    data = sb.ViewerData.load(ws)
    idx = sb.stratified_subsample(data.labels, data.scene.n_points, args.max_points)

    server = viser.ViserServer(host="127.0.0.1", port=0)
    server.scene.set_up_direction("+z")
    mode = server.gui.add_dropdown("Colour", list(sb.COLOUR_MODES), initial_value="semantic")
    size = sb.default_point_size(data, len(idx))

    def draw() -> None:
        nodes = sb.build_point_nodes(data, mode=mode.value, subsample=idx)
        sb.send_point_nodes(server.scene, nodes, point_size=size)
        for nd in nodes:
            print(f"{nd.name:28s} {len(nd.point_ids):8,d} points")

    mode.on_update(lambda _: draw())
    draw()
    print(f"open http://127.0.0.1:{server.get_port()}/")
    t0 = time.time()
    while not args.seconds or time.time() - t0 < args.seconds:
        time.sleep(0.2)
    server.stop()


if __name__ == "__main__":
    main()
