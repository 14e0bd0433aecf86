"""The COPC octree: every point in exactly one node, inside its node's cube, every node's
parent present; the file copc-lib writes from it is read back by laspy's COPC reader."""

from __future__ import annotations

import laspy
import numpy as np

from occufly.io import copc


def _cloud(n, seed=0):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 400, (n, 2))
    z = np.sin(xy[:, 0] / 40) * 3 + (rng.random(n) < 0.3) * 12
    return np.column_stack([xy + [500000.0, 4000000.0], z + 100.0])


def test_octree_covers_every_point_once_inside_its_node(monkeypatch):
    monkeypatch.setattr(copc, "MAX_NODE_POINTS", 2000)  # force several levels on a small cloud
    xyz = _cloud(60_000)
    lo, hi = xyz.min(0), xyz.max(0)
    c, h = (lo + hi) / 2, (hi - lo).max() / 2 * 1.0001
    nodes = copc._octree(xyz, c, h)
    keys = {k for k, _ in nodes}
    assert max(k[0] for k in keys) >= 2
    every = np.concatenate([i for _, i in nodes])
    assert len(every) == len(xyz) and len(np.unique(every)) == len(xyz)
    for (d, x, y, z), idx in nodes:
        size = 2 * h / (1 << d)
        lo_n = c - h + np.array([x, y, z]) * size
        p = xyz[idx]
        assert ((p >= lo_n - 1e-6) & (p <= lo_n + size + 1e-6)).all()
        if d:
            assert (d - 1, x // 2, y // 2, z // 2) in keys  # hierarchy has no holes
        # a node thins its cube: at most one point per cell of its GRID^3 grid, unless a leaf
        cell = np.floor((p - lo_n) / size * copc.GRID).astype(int)
        if len(idx) > copc.MAX_NODE_POINTS:
            assert len(np.unique(cell, axis=0)) == len(idx)


def test_copc_written_and_read_back_by_level(tmp_path, monkeypatch):
    monkeypatch.setattr(copc, "MAX_NODE_POINTS", 5000)
    xyz = _cloud(40_000, seed=1)
    hdr = laspy.LasHeader(point_format=7, version="1.4")
    hdr.add_extra_dims([laspy.ExtraBytesParams("class_id", "u1")])
    hdr.offsets, hdr.scales = np.floor(xyz.min(0)), np.array([0.001] * 3)
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.class_id = (np.arange(len(xyz)) % 200).astype(np.uint8)
    info = copc.write_copc(tmp_path / "c.copc.laz", las)
    assert info["points"] == len(xyz) and info["depth"] >= 1
    with laspy.CopcReader.open(tmp_path / "c.copc.laz") as rd:
        full = rd.query()
        root = rd.query(level=0)
    assert len(full) == len(xyz) and 0 < len(root) < len(xyz)
    got = np.column_stack([full.X, full.Y, full.Z, np.asarray(full.class_id)])
    want = np.column_stack([las.X, las.Y, las.Z, np.asarray(las.class_id)])
    assert np.array_equal(got[np.lexsort(got.T)], want[np.lexsort(want.T)])
